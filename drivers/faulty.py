"""A test aid: `faulty:OPTIONS@INNER` wraps any source and makes it fail the way sensors do.

INNER is any other source spec (`replay:rec.mcap`, `synthetic`, ...). OPTIONS is a
comma-separated list of `key=N` settings; each counts frames or opens of this process:

- `fail_opens=N`: the first N opens fail (a sensor not plugged in yet);
- `fail_after=N`: after N frames of an open the sensor drops out (`SourceUnavailable`);
- `stall_after=N`: after N frames of an open it goes silent, and after the live-sensor
  frame timeout (`--frame-timeout`) it is reported stalled, as a real sensor's reader does;
- `faults=K`: only the first K opens drop out or stall; later opens run clean (default:
  every open).

E.g. `topseg driver --source 'faulty:fail_opens=2,fail_after=20,faults=1@replay:rec.mcap' --loop`.
The driver's `Reconnecting` loop handles these like any sensor fault: close, back off,
reopen. Used by the reliability tests (tests/test_reliability_live.py); not for production.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator

from topseg.drivers.base import Source, SourceError, SourceFrame, SourceOptions, SourceUnavailable
from topseg.drivers.spec import open_source, parse_spec

_KEYS = ("fail_opens", "fail_after", "stall_after", "faults")
USAGE = "faulty:KEY=N[,KEY=N...]@INNER-SPEC with KEY one of " + ", ".join(_KEYS)

#: opens so far in this process, per faulty spec (the driver reopens a fresh Source each time)
_opens: dict[str, int] = {}


def parse_options(text: str) -> dict[str, int]:
    """'fail_after=5,faults=1' -> {'fail_after': 5, 'faults': 1}; SourceError otherwise."""
    out: dict[str, int] = {}
    for token in filter(None, (t.strip() for t in text.split(","))):
        key, sep, value = token.partition("=")
        if not sep or key not in _KEYS:
            raise SourceError(f"faulty: bad option {token!r}; use {USAGE}")
        try:
            out[key] = int(value)
        except ValueError:
            raise SourceError(f"faulty: {key} must be an integer, got {value!r}") from None
        if out[key] < 0:
            raise SourceError(f"faulty: {key} must be >= 0, got {value!r}")
    return out


class FaultySource(Source):
    """Frames of the inner source until the injected fault of this open."""

    def __init__(self, inner: Source, settings: dict[str, int], open_no: int, options) -> None:
        self.inner = inner
        self.settings = settings
        self.timeout_s = options.frame_timeout_s
        faults = settings.get("faults")
        self.faulty = faults is None or open_no <= settings.get("fail_opens", 0) + faults
        self.description = f"faulty({inner.description})"
        self.intrinsics = inner.intrinsics
        self.nominal_fps = inner.nominal_fps
        self.finite = inner.finite
        self._closed = threading.Event()

    def frames(self) -> Iterator[SourceFrame]:
        """The inner frames, then the drop-out or stall the settings ask for on a faulty open."""
        fail = self.settings.get("fail_after") if self.faulty else None
        stall = self.settings.get("stall_after") if self.faulty else None
        count = 0
        for frame in self.inner.frames():
            if fail is not None and count >= fail:
                raise SourceUnavailable(f"faulty: sensor dropped out after {count} frames")
            if stall is not None and count >= stall:
                self._closed.wait(self.timeout_s)
                raise SourceUnavailable(f"faulty: no frame for {self.timeout_s:.1f} s (stalled)")
            self.intrinsics = self.inner.intrinsics
            yield frame
            count += 1

    def close(self) -> None:
        """Cut a pending stall short and close the inner source."""
        self._closed.set()
        self.inner.close()


def open(arg: str | None, options: SourceOptions) -> Source:
    """`faulty:OPTIONS@INNER` -> a FaultySource around INNER (or SourceUnavailable at open)."""
    text, sep, inner_spec = (arg or "").partition("@")
    if not sep or not inner_spec:
        raise SourceError(f"faulty needs an inner source: {USAGE}")
    settings = parse_options(text)
    inner = parse_spec(inner_spec)
    if inner.kind == "faulty":
        raise SourceError("faulty: the inner source cannot be faulty too")
    key = arg or ""
    _opens[key] = _opens.get(key, 0) + 1
    if _opens[key] <= settings.get("fail_opens", 0):
        raise SourceUnavailable(f"faulty: sensor not found (open {_opens[key]})")
    return FaultySource(open_source(inner, options), settings, _opens[key], options)
