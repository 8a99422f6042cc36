"""Error types that reach the operator as one clear line."""


class TopsegError(Exception):
    """A problem the operator can fix: a bad path, option, file or config.

    The CLI prints it as `topseg <command>: error: <message>` and exits with status 2;
    services refuse to start with it.
    """


class ConfigError(TopsegError, ValueError):
    """Bad configuration: an unknown or mistyped key, or a value out of range, named with
    the file or section it came from. Also a ValueError, so callers that guard a
    config's construction with `except ValueError` still catch it."""
