"""Error types that reach the operator as one clear line."""


class TopsegError(Exception):
    """A problem the operator can fix: a bad path, option, file or config.

    The CLI prints it as `topseg <command>: error: <message>` and exits with status 2;
    services refuse to start with it.
    """
