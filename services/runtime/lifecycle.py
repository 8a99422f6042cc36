"""The start-up and shut-down every long-running topseg service shares.

    svc = ServiceLifecycle("worker", args)     # a bad Zenoh config fails here (exit 2)
    ...load what the service needs...
    with svc:                                  # signals handled, Zenoh session open
        sub = svc.declare(svc.session.declare_subscriber(key, handler))
        svc.ready("serving ...", status=status_line)   # READY=1 once the handlers exist
        svc.wait()                             # until a signal; or a loop calling svc.beat()
    # STOPPING=1, signals restored, clean-ups in reverse order, session closed

SIGTERM and SIGINT set `svc.stop` (a threading.Event) and log "<SIGNAL>: stopping". The
Python handler itself takes no lock (an Event.set() in a handler can deadlock the main
thread inside that Event's own wait): the C-level handler writes the signal number to a
pipe (`signal.set_wakeup_fd`) and a small thread reads it, sets `stop` and calls the
`on_stop` wakers, so a main loop blocked on its own Condition wakes at once. Inside
`with svc.interruptible():` a signal also raises `ServiceStopped` to cut a blocking call
short (a sensor read); the `with svc:` block swallows it.

Once a service is ready, what it loaded is frozen out of the garbage collector
(`gc.freeze()`, after one last collection): a warmed worker holds ~120 000 tracked objects
(numba, Zenoh, the model's header), and a full collection of them would stop it for 68-84 ms
(the viewer 42-54, the driver 30-35) in the middle of a run, two or three frames at 30 fps
(docs/explanation/speed.md). That collection runs in `ready`, before the first frame, and
later full collections scan only what came after it. (Freezing does not change the demo
path's or `bench pipeline`'s figures measurably: in runs of 10-20 s that collection comes
once, near the end.)

A session that has been alone (no Zenoh peer or router) for `ISOLATION_WARN_S`, since it
opened or since its last peer went, though it should not be (it connects to a rendezvous
port it does not hold and that something holds, or to configured endpoints), is warned
about once (`zenoh_session.isolation_problem`: another program or a frozen process on the
port leaves services "ready" and never meeting), and the recovery logged. When nothing
holds the rendezvous port any more (the other services, its holder among them, stopped),
that is no fault: it is said once, at INFO.

On the way out every clean-up runs, last registered first, even when one fails; then the
session closes; then the original handlers come back. More stopping signals meanwhile (an
impatient operator, `docker stop` after systemd's stop) are logged and the clean-up goes on,
so tokens are undeclared and the exit status stays the service's; only once the shut-down
has taken `FORCE_AFTER_S` does a signal have its usual effect (Ctrl-C raises
KeyboardInterrupt, SIGTERM ends the process), for a clean-up that hangs. A service that a
signal stopped leaves SIGTERM and SIGINT ignored, not restored: the process is on its way
out, and one more signal would only turn its exit status 0 into 143 or a traceback. An error of the service body wins over errors of its
clean-ups.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

from topseg.services.runtime import systemd_notify, zenoh_session

#: The signals that ask a service to stop.
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)
#: Longest wait between two heartbeats (shorter when systemd's watchdog asks for it).
TICK_S = 0.5
#: A stopping signal during a shut-down that has taken this long forces it (s); before, the
#: signal is logged and the clean-up goes on.
FORCE_AFTER_S = 5.0
#: A session that met nobody this long after opening or after its last peer went (and
#: should have) is warned about (s).
ISOLATION_WARN_S = 5.0
#: How often the session's peers are looked at (s).
ISOLATION_CHECK_S = 1.0


class ServiceStopped(BaseException):
    """Raised by the signal handler inside `interruptible()`; a BaseException, so that the
    `except Exception` of a source or a library does not swallow it."""


def freeze_loaded_objects() -> int:
    """Collect once, then move every object still tracked into the collector's permanent
    generation (`gc.freeze`), so full collections stop rescanning what a service loaded at
    start-up; returns how many are frozen in all."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


@contextlib.contextmanager
def stop_between_steps() -> Iterator[threading.Event]:
    """Within: the first SIGINT or SIGTERM sets the returned Event instead of raising
    KeyboardInterrupt wherever the main thread is (inside numba's compiled code that ended in
    a `SystemError`, exit 1); a batch loop checks it between steps and says what it wrote.
    A second one raises KeyboardInterrupt (the operator insists)."""
    stop = threading.Event()

    def handler(signum: int, frame: Any) -> None:
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()

    old = {s: signal.signal(s, handler) for s in STOP_SIGNALS}
    try:
        yield stop
    finally:
        for s, h in old.items():
            signal.signal(s, h)


class ServiceLifecycle:
    """One service's signals, Zenoh session, systemd notifications and clean-ups.

    `name` names the logger (`topseg.<name>`); the Zenoh config comes from `args`
    (`--zenoh-config`, `--zenoh-port`) unless `config` (a zenoh.Config) is given, and is
    checked here, before anything else starts. `open_error` starts the one-line error
    when Zenoh cannot open; `signal_note` ends the log line of a stopping signal;
    `status` is the STATUS= line the heartbeat refreshes (see `ready`).
    """

    def __init__(
        self,
        name: str,
        args: Any = None,
        *,
        config: Any = None,
        open_error: str = "cannot open a Zenoh session",
        signal_note: str = "stopping",
        status: Callable[[], str] | None = None,
        notifier: systemd_notify.Notifier | None = None,
    ) -> None:
        self.name = name
        self.log = logging.getLogger(f"topseg.{name}")
        self.config = config if config is not None else zenoh_session.config_from_args(args)
        self.rendezvous = None  # the default config's port, when it is in use
        if config is None and not getattr(args, "zenoh_config", None):
            self.rendezvous = zenoh_session.rendezvous_port(getattr(args, "zenoh_port", None))
        self.open_error = open_error
        self.signal_note = signal_note
        self.notifier = notifier or systemd_notify.default()
        self.heartbeat = systemd_notify.Heartbeat(status, notifier=self.notifier)
        #: the longest a loop should block between two `beat()`s
        self.tick = min(TICK_S, self.notifier.watchdog_s or TICK_S)
        self.stop = threading.Event()
        self.session: Any = None
        self._cleanups: list[tuple[Callable[..., Any], tuple]] = []
        self._wakers: list[Callable[[], Any]] = []
        self._old_handlers: dict[int, Any] = {}
        self._old_wakeup_fd = -1
        self._pipe: tuple[int, int] | None = None
        self._watcher: threading.Thread | None = None
        self._interruptible = False
        self._shutting_down = False
        self._shutdown_began = 0.0
        self._signalled = False  # a stopping signal came: leave them ignored on the way out
        self._frozen = False  # start-up objects frozen out of the collector (`ready`)

    # -- start and stop -------------------------------------------------------------------

    def __enter__(self) -> ServiceLifecycle:
        self._install_signals()
        try:
            self.session = zenoh_session.open_config(self.config, self.open_error)
        except BaseException:
            self._restore_signals()
            raise
        threading.Thread(
            target=self._watch_isolation, name=f"{self.name}-peers", daemon=True
        ).start()
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        self.stop.set()
        self._interruptible = False
        self._shutdown_began = time.monotonic()
        self._shutting_down = True  # another signal now: logged, the clean-up goes on
        self.notifier.stopping()
        try:
            return self._shut_down(exc_type)
        finally:
            self._restore_signals()

    def _shut_down(self, exc_type) -> bool:
        first: BaseException | None = None
        while self._cleanups:
            fn, args = self._cleanups.pop()
            try:
                fn(*args)
            except Exception as err:  # every clean-up runs; the first error is kept (a forced
                # stop, KeyboardInterrupt, leaves the rest)
                self.log.warning(
                    "clean-up %s failed: %s",
                    getattr(fn, "__qualname__", fn),
                    zenoh_session.error_line(err),  # Zenoh's own errors name Rust sources
                )
                first = first or err
        if self.session is not None:
            try:
                self.session.close()
            except Exception as err:
                self.log.warning(
                    "closing the Zenoh session failed: %s", zenoh_session.error_line(err)
                )
                first = first or err
        if exc_type is not None:
            return issubclass(exc_type, ServiceStopped)  # a body error wins over clean-ups'
        if first is not None:
            raise first
        return False

    # -- what the service registers ---------------------------------------------------------

    def defer(self, fn: Callable[..., Any], *args: Any) -> None:
        """Run `fn(*args)` on the way out (last registered, first run), even after an error."""
        self._cleanups.append((fn, args))

    def declare(self, entity: Any) -> Any:
        """A Zenoh subscriber, queryable or liveliness token, undeclared on the way out."""
        self.defer(entity.undeclare)
        return entity

    def on_stop(self, wake: Callable[[], Any]) -> None:
        """Call `wake()` when a stopping signal comes (from a helper thread, not the handler):
        for a main loop blocked on its own Condition or queue."""
        self._wakers.append(wake)

    @contextlib.contextmanager
    def interruptible(self) -> Iterator[None]:
        """Within: a stopping signal raises ServiceStopped out of the blocking call."""
        if self.stop.is_set():
            raise ServiceStopped
        self._interruptible = True
        try:
            yield
        finally:
            self._interruptible = False

    # -- systemd ------------------------------------------------------------------------------

    def ready(self, text: str | None = None, status: Callable[[], str] | None = None) -> None:
        """READY=1 (once; later calls update STATUS=) with `text`, or `status()` when no text;
        `status` becomes the line the heartbeat refreshes. The first call freezes what the
        service has loaded out of the garbage collector (see the module)."""
        if not self._frozen:
            freeze_loaded_objects()
            self._frozen = True
        if status is not None:
            self.heartbeat.status_fn = status
        if text is None and self.heartbeat.status_fn is not None:
            text = self.heartbeat.status_fn()
        self.notifier.ready(text)

    def beat(self) -> None:
        """From the main loop: the watchdog ping (rate-limited) and STATUS= every few s."""
        self.heartbeat()

    @property
    def stopping(self) -> bool:
        """True once a stopping signal came (or the service is on its way out)."""
        return self.stop.is_set()

    def wait(self, timeout: float | None = None) -> bool:
        """Block until stopped or `timeout` s passed (None: until stopped), pinging the
        watchdog meanwhile; True when stopped."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            self.beat()
            left = self.tick if deadline is None else min(self.tick, deadline - time.monotonic())
            if left <= 0 or self.stop.wait(left):
                return self.stop.is_set()

    def _watch_isolation(self) -> None:
        """Once the session has been alone ISOLATION_WARN_S (since it opened, or since its
        last peer went): warn when it should have met someone (`isolation_problem`), or say
        at INFO that nothing holds the rendezvous port (the others stopped); log when a peer
        comes again."""
        alone_since, said = time.monotonic(), False
        while not self.stop.wait(ISOLATION_CHECK_S):
            try:
                now = time.monotonic()
                if zenoh_session.has_peers(self.session):
                    if said:
                        self.log.info("Zenoh: a peer or router is reached now")
                    alone_since, said = now, False
                    continue
                if said or now - alone_since < ISOLATION_WARN_S:
                    continue
                said = self._say_alone(now - alone_since)
            except Exception as err:  # a closing session: nothing to say
                self.log.debug("checking Zenoh peers failed: %s", err)
                return

    def _say_alone(self, alone_s: float) -> bool:
        """Warn about a session alone that should not be, or note one whose rendezvous port
        nobody holds any more; True when something was said."""
        problem = zenoh_session.isolation_problem(self.session, self.config, self.rendezvous)
        if problem:
            self.log.warning("%s (alone for %.0f s)", problem, alone_s)
            return True
        if self.rendezvous is not None and zenoh_session.rendezvous_free(self.rendezvous):
            self.log.info(
                "Zenoh: no peer for %.0f s and nothing holds the rendezvous port "
                "tcp/127.0.0.1:%d: the other services stopped (or none started yet); the "
                "next one to start takes the port and they meet again",
                alone_s,
                self.rendezvous,
            )
            return True
        return False

    # -- signals ------------------------------------------------------------------------------

    def _on_signal(self, signum: int, frame: Any) -> None:
        # no locks here: the wakeup fd already carries the signal to the watcher thread
        if self._shutting_down:
            if time.monotonic() - self._shutdown_began > FORCE_AFTER_S:  # a clean-up hangs
                self._force(signum, frame)
            return
        if self._interruptible:
            self._interruptible = False
            raise ServiceStopped

    def _force(self, signum: int, frame: Any) -> None:
        """The signal's usual effect, as if topseg had installed no handler."""
        old = self._old_handlers.get(signum, signal.SIG_DFL)
        if callable(old):
            old(signum, frame)  # Python's own SIGINT handler: KeyboardInterrupt
            return
        signal.signal(signum, signal.SIG_DFL if old is None else old)
        os.kill(os.getpid(), signum)

    def _install_signals(self) -> None:
        read_fd, write_fd = os.pipe()
        os.set_blocking(write_fd, False)
        self._pipe = (read_fd, write_fd)
        self._old_wakeup_fd = signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
        self._old_handlers = {s: signal.signal(s, self._on_signal) for s in STOP_SIGNALS}
        self._watcher = threading.Thread(
            target=self._watch, args=(read_fd,), name=f"{self.name}-signals", daemon=True
        )
        self._watcher.start()

    def _watch(self, read_fd: int) -> None:
        while True:
            try:
                data = os.read(read_fd, 64)
            except OSError:
                return
            if not data:  # the write end closed: the service is done
                return
            for signum in data:
                if signum not in self._old_handlers:
                    continue
                if self._shutting_down:
                    self.log.warning(
                        "%s again: still stopping (undeclaring, closing Zenoh)",
                        signal.Signals(signum).name,
                    )
                else:
                    self._signalled = True
                    self._stopped_by(signum)

    def _stopped_by(self, signum: int) -> None:
        self.log.info("%s: %s", signal.Signals(signum).name, self.signal_note)
        self.stop.set()
        for wake in list(self._wakers):
            try:
                wake()
            except Exception as err:
                self.log.warning("waking the main loop failed: %s", err)

    def _restore_signals(self) -> None:
        if self._pipe is None:
            return
        for s, handler in self._old_handlers.items():
            signal.signal(s, signal.SIG_IGN if self._signalled else handler)
        signal.set_wakeup_fd(self._old_wakeup_fd)
        read_fd, write_fd = self._pipe
        self._pipe = None
        os.close(write_fd)  # the watcher reads what is left, then the end of the pipe
        if self._watcher is not None:
            self._watcher.join(5)
        os.close(read_fd)
