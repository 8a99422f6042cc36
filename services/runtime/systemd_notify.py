"""Tell systemd how a service is doing, without libsystemd: READY=1, WATCHDOG=1, STATUS=...

Messages are datagrams written straight to the AF_UNIX socket named by `$NOTIFY_SOCKET`
(a leading '@' is Linux's abstract namespace). Without that variable every call is a no-op,
so the services call these functions unconditionally. Send errors are logged once and
otherwise ignored: telling systemd must never stop a service.

The watchdog: systemd sets `$WATCHDOG_USEC` (and `$WATCHDOG_PID`, the process meant) when a
unit has `WatchdogSec=`; `watchdog()` sends WATCHDOG=1 at most every half of it, so a
service calls it once per iteration of its main loop and a hung loop is caught.
`Heartbeat` bundles that with a STATUS= line refreshed every few seconds.
"""

from __future__ import annotations

import array
import logging
import os
import select
import socket
import time
from collections.abc import Callable, Mapping

log = logging.getLogger("topseg.systemd")

#: How often a Heartbeat refreshes its STATUS= line.
STATUS_EVERY_S = 5.0


def socket_address(value: str | None) -> str | bytes | None:
    """$NOTIFY_SOCKET as a socket address: a path, b'\\0name' (abstract), or None (unusable)."""
    if not value:
        return None
    if value.startswith("@"):
        return b"\0" + value[1:].encode()
    if value.startswith("/"):
        return value
    return None  # vsock: and relative paths are not for us


def watchdog_interval(environ: Mapping[str, str], pid: int | None = None) -> float | None:
    """Seconds between watchdog pings (half of $WATCHDOG_USEC), or None when not asked for."""
    text = environ.get("WATCHDOG_USEC", "")
    try:
        usec = int(text)
    except ValueError:
        return None
    if usec <= 0:
        return None
    owner = environ.get("WATCHDOG_PID", "")
    if owner and owner != str(os.getpid() if pid is None else pid):
        return None  # the watchdog is meant for another process (our parent, say)
    return usec / 2e6


def format_message(fields: Mapping[str, object]) -> bytes:
    """KEY=value lines; values are one line (a newline would start a new field)."""
    lines = []
    for key, value in fields.items():
        if value is True:
            value = 1
        text = " ".join(str(value).splitlines())
        lines.append(f"{key.upper()}={text}")
    return "\n".join(lines).encode()


class Notifier:
    """The connection to systemd's notify socket, read from the environment once."""

    def __init__(self, environ: Mapping[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        self.address = socket_address(env.get("NOTIFY_SOCKET"))
        self.watchdog_s = watchdog_interval(env) if self.address else None
        self._next_ping = 0.0
        self._sock: socket.socket | None = None
        self._warned = False
        self.is_ready = False

    @property
    def enabled(self) -> bool:
        """True when $NOTIFY_SOCKET names a socket we can write to."""
        return self.address is not None

    def _send(self, data: bytes, fds: list[int] | None = None) -> bool:
        if self.address is None:
            return False
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            if fds:
                ancillary = [(socket.SOL_SOCKET, socket.SCM_RIGHTS, array.array("i", fds))]
                self._sock.sendmsg([data], ancillary, 0, self.address)
            else:
                self._sock.sendto(data, self.address)
            return True
        except OSError as exc:
            if not self._warned:
                log.warning("cannot notify systemd at %r: %s", self.address, exc)
                self._warned = True
            return False

    def notify(self, **fields: object) -> bool:
        """Send KEY=value fields (notify(READY=1, STATUS="...")); True when sent."""
        return self._send(format_message(fields)) if fields else False

    def ready(self, status: str | None = None) -> bool:
        """READY=1 (once; later calls only update STATUS=) and a first watchdog ping."""
        fields: dict[str, object] = {} if self.is_ready else {"READY": 1}
        if status:
            fields["STATUS"] = status
        sent = self.notify(**fields)
        if not self.is_ready:
            self.is_ready = True
            self._next_ping = 0.0
            self.watchdog()
        return sent

    def status(self, text: str) -> bool:
        """STATUS=<text>: the line `systemctl status` shows."""
        return self.notify(STATUS=text)

    def stopping(self, status: str | None = None) -> bool:
        """STOPPING=1 (and STATUS=): the service has begun shutting down."""
        return self.notify(STOPPING=1, **({"STATUS": status} if status else {}))

    def watchdog(self, now: float | None = None) -> bool:
        """WATCHDOG=1 if half the watchdog interval has passed since the last one."""
        if self.watchdog_s is None:
            return False
        now = time.monotonic() if now is None else now
        if now < self._next_ping:
            return False
        self._next_ping = now + self.watchdog_s
        return self.notify(WATCHDOG=1)

    def failed(self, text: str, errno: int | None = None, wait_s: float = 1.0) -> bool:
        """STATUS=<error> (ERRNO= too) before exiting; waits until systemd has read it."""
        fields: dict[str, object] = {"STATUS": text}
        if errno:
            fields["ERRNO"] = errno
        sent = self.notify(**fields)
        if sent:
            self.barrier(wait_s)
        return sent

    def barrier(self, timeout_s: float = 1.0) -> bool:
        """BARRIER=1: return once systemd has processed everything sent before (or timeout).

        systemd closes the pipe end it receives; a process that exits right after its last
        message would otherwise race systemd reading it (and NotifyAccess=main drops
        messages of a process already gone).
        """
        if self.address is None:
            return False
        read_fd, write_fd = os.pipe()
        try:
            if not self._send(b"BARRIER=1", [write_fd]):
                return False
            os.close(write_fd)
            write_fd = -1
            poller = select.poll()
            poller.register(read_fd, 0)  # POLLHUP is always reported
            return bool(poller.poll(int(timeout_s * 1000)))
        finally:
            os.close(read_fd)
            if write_fd >= 0:
                os.close(write_fd)


class Heartbeat:
    """Once per loop iteration: the watchdog ping, and `status_fn()` every few seconds."""

    def __init__(
        self,
        status_fn: Callable[[], str] | None = None,
        every_s: float = STATUS_EVERY_S,
        notifier: Notifier | None = None,
    ) -> None:
        self.notifier = notifier or default()
        self.status_fn = status_fn
        self.every_s = every_s
        self._next_status = time.monotonic() + every_s

    def __call__(self) -> None:
        n = self.notifier
        if not n.enabled:
            return
        now = time.monotonic()
        n.watchdog(now)
        if self.status_fn is not None and now >= self._next_status:
            self._next_status = now + self.every_s
            n.status(self.status_fn())


_default: Notifier | None = None


def default() -> Notifier:
    """The process's notifier (made on first use, from the environment then)."""
    global _default
    if _default is None:
        _default = Notifier()
    return _default


def notify(**fields: object) -> bool:
    """`Notifier.notify` on the process's notifier."""
    return default().notify(**fields)


def ready(status: str | None = None) -> bool:
    """`Notifier.ready` on the process's notifier."""
    return default().ready(status)


def status(text: str) -> bool:
    """`Notifier.status` on the process's notifier."""
    return default().status(text)


def watchdog() -> bool:
    """`Notifier.watchdog` on the process's notifier."""
    return default().watchdog()


def stopping(status: str | None = None) -> bool:
    """`Notifier.stopping` on the process's notifier."""
    return default().stopping(status)


def failed(text: str, errno: int | None = None) -> bool:
    """`Notifier.failed` on the process's notifier (the CLI's last word before exit 2)."""
    return default().failed(text, errno)
