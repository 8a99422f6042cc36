"""The one interface every depth source implements, and reconnecting with backoff.

A `Source` is opened by `topseg.drivers.open_source(spec, options)` (the constructor opens
it), yields `SourceFrame`s from `frames()` and is closed by `close()` or a `with` block::

    with open_source("replay:recordings/demo.mcap", SourceOptions(loop=True)) as src:
        for depth, truth, companions in src.frames():   # DepthFrame, LabelFrame or None
            ...

Frames carry host time (`stamp_ns`, ns since the epoch, taken when the frame reached
topseg) and a per-source `seq` from 0; `truth` is the ground-truth label image when the
source knows it (synthetic scenes, recordings that carry a truth channel).

A source must never block for ever: live sensors read under `options.frame_timeout_s` and
raise `SourceUnavailable` when a sensor is missing, drops or stalls. `Reconnecting` turns
that into close, wait (exponential backoff with jitter), reopen.

A driver module (replay, freenect, openni2, oak, synthetic) exposes
`open(arg: str | None, options: SourceOptions) -> Source`; `spec.py` dispatches to it.
"""

from __future__ import annotations

import abc
import logging
import random
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import NamedTuple

from topseg.core.camera import Intrinsics, TopViewMount
from topseg.core.errors import TopsegError
from topseg.core.formats.wire import DepthFrame, LabelFrame

log = logging.getLogger(__name__)


class SourceError(TopsegError):
    """A depth source cannot be used: bad spec, unreadable file, unusable device."""


class SourceUnavailable(SourceError):
    """A sensor is missing, dropped out or stalled; worth retrying later."""


@dataclass(frozen=True)
class SourceOptions:
    """What a driver may be asked besides its spec.

    loop: start a finite source (a replay) again at its end.
    realtime: pace a replay at its recorded rate; False = as fast as it is consumed.
    fps: frame rate: pacing for replays without timing, a cap for live sensors.
    frame_timeout_s: a live sensor silent this long has stalled.
    open_timeout_s: how long opening a sensor may take.
    """

    loop: bool = False
    realtime: bool = True
    fps: float | None = None
    frame_timeout_s: float = 2.0
    open_timeout_s: float = 15.0

    def __post_init__(self) -> None:
        if self.fps is not None and not 0 < self.fps <= 1000:
            raise SourceError(f"fps must be in (0, 1000], got {self.fps}")
        if self.frame_timeout_s <= 0 or self.open_timeout_s <= 0:
            raise SourceError("timeouts must be positive")


class SourceFrame(NamedTuple):
    """One frame from a source: the depth image and, when the source knows it, the truth
    labels; a replay adds the recording's companion messages of that frame (joint states,
    safety truth: `replay.Companion`) to publish with it."""

    depth: DepthFrame
    truth: LabelFrame | None = None
    companions: tuple = ()


class Source(abc.ABC):
    """An open depth source. Subclasses set the attributes and implement `frames()`."""

    #: the spec or a human description (logs, the `info` queryable)
    description: str = ""
    #: camera of the frames; None until the first frame where a source cannot know earlier
    intrinsics: Intrinsics | None = None
    #: where the camera hangs, when the source knows it (a recording's frames carry it)
    mount: TopViewMount | None = None
    #: the rate frames come at, when known
    nominal_fps: float | None = None
    #: True when frames() ends on its own (a replay without --loop)
    finite: bool = False

    @abc.abstractmethod
    def frames(self) -> Iterator[SourceFrame]:
        """Frames until the source ends (finite) or fails (SourceUnavailable)."""

    def close(self) -> None:  # noqa: B027 - sources without resources need nothing
        """Release the device or file; safe to call twice."""

    def info(self) -> dict:
        """JSON-able description for the driver's `info` queryable."""
        k = self.intrinsics
        return {
            "source": self.description,
            "intrinsics": None if k is None else k.to_dict(),
            "mount": None if self.mount is None else self.mount.to_dict(),
            "fps": self.nominal_fps,
            "finite": self.finite,
        }

    def __enter__(self) -> Source:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ---------------------------------------------------------------------------- timing


@dataclass
class Backoff:
    """Exponential backoff with jitter: initial, x factor each failure, capped; reset on success."""

    initial_s: float = 0.5
    maximum_s: float = 10.0
    factor: float = 2.0
    jitter: float = 0.1
    failures: int = 0

    def next_delay(self, rng: random.Random | None = None) -> float:
        """Seconds to wait after this failure: initial_s * factor**failures, capped, +/- jitter."""
        base = min(self.maximum_s, self.initial_s * self.factor**self.failures)
        self.failures += 1
        spread = (rng or random).uniform(-self.jitter, self.jitter)
        return max(0.0, base * (1.0 + spread))

    def reset(self) -> None:
        """Forget past failures (a frame arrived), so the next one waits `initial_s` again."""
        self.failures = 0


class Pacer:
    """Sleep so that media time advances with the wall clock (replay at recorded rate).

    `wait(t)` returns when `t` seconds of media time have passed since the first call (or
    the last `restart()`); a consumer slower than the media loses the backlog, it never
    gets a burst: lagging more than `max_lag_s` moves the schedule forward.
    """

    def __init__(self, realtime: bool = True, max_lag_s: float = 0.25) -> None:
        self.realtime = realtime
        self.max_lag_s = max_lag_s
        self._origin: float | None = None  # wall time of media time 0

    def restart(self) -> None:
        """Make the next `wait` media time 0 again (a replay looping back to its start)."""
        self._origin = None

    def wait(self, media_s: float, stop: threading.Event | None = None) -> None:
        """Block until `media_s` s of media time are due or `stop` is set; no-op if not realtime."""
        if not self.realtime:
            return
        now = time.monotonic()
        if self._origin is None:
            self._origin = now - media_s
        due = self._origin + media_s
        if due > now:
            if stop is not None:
                stop.wait(due - now)
            else:
                time.sleep(due - now)
        elif now - due > self.max_lag_s:
            self._origin = now - media_s


class Throttle:
    """Let at most `fps` frames a second through (None = all)."""

    def __init__(self, fps: float | None) -> None:
        self.period = None if fps is None else 1.0 / fps
        self._next = 0.0

    def admit(self, now: float | None = None) -> bool:
        """True when a frame arriving at `now` (monotonic s) fits the rate; False means drop it."""
        if self.period is None:
            return True
        now = time.monotonic() if now is None else now
        if now + 0.1 * self.period < self._next:
            return False
        self._next += self.period
        if self._next <= now:  # late by more than a period: start a new schedule
            self._next = now + self.period
        return True


# ---------------------------------------------------------------------------- reconnecting


class Reconnecting:
    """Frames from a source reopened with backoff whenever it is unavailable.

    `open_fn` opens a fresh source; `SourceUnavailable` (at open or while reading), or a
    live source whose frames simply end, closes it, waits `backoff` and opens again. Other
    errors (bad spec, unreadable file) propagate. Stops when `stop` is set or a finite
    source ends.
    """

    def __init__(
        self,
        open_fn: Callable[[], Source],
        *,
        name: str = "source",
        backoff: Backoff | None = None,
        stop: threading.Event | None = None,
        on_open: Callable[[Source], None] | None = None,
    ) -> None:
        self.open_fn = open_fn
        self.name = name
        self.backoff = backoff or Backoff()
        self.stop = stop or threading.Event()
        self.on_open = on_open
        self.opens = 0
        self.failures = 0
        self.last_error: str | None = None
        self.source: Source | None = None

    def _fail(self, exc: Exception) -> None:
        self.failures += 1
        self.last_error = str(exc)
        delay = self.backoff.next_delay()
        log.warning("%s: %s; trying again in %.1f s", self.name, exc, delay)
        self.stop.wait(delay)

    def frames(self) -> Iterator[SourceFrame]:
        """Frames across reopens until `stop` is set or a finite source ends (retries hidden)."""
        while not self.stop.is_set():
            try:
                source = self.open_fn()
            except SourceUnavailable as exc:
                self._fail(exc)
                continue
            self.opens += 1
            if self.opens > 1:
                log.info("%s: open again (%s)", self.name, source.description)
            self.source = source
            try:
                if self.on_open is not None:
                    self.on_open(source)
                for frame in source.frames():
                    self.backoff.reset()
                    yield frame
                    if self.stop.is_set():
                        return
                if source.finite:
                    return
                raise SourceUnavailable(f"{source.description} stopped sending frames")
            except SourceUnavailable as exc:
                source.close()
                self._fail(exc)
            finally:
                source.close()
                self.source = None
