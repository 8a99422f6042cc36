"""The driver interface: spec parsing, backoff, throttling, pacing and reconnecting."""

import random
import threading
import time

import numpy as np
import pytest

from topseg.core.camera import KINECT_V1
from topseg.core.formats.wire import DepthFrame
from topseg.drivers import (
    Reconnecting,
    Source,
    SourceError,
    SourceFrame,
    SourceOptions,
    SourceUnavailable,
    open_source,
    parse_spec,
)
from topseg.drivers.base import Backoff, Pacer, Throttle


def test_parse_spec():
    assert (parse_spec("replay:/x/y.mcap").kind, parse_spec("replay:/x/y.mcap").arg) == (
        "replay",
        "/x/y.mcap",
    )
    assert parse_spec("freenect").arg is None
    assert parse_spec("FREENECT:1").kind == "freenect"
    assert str(parse_spec("oak:14442C10")) == "oak:14442C10"
    assert parse_spec("replay:c:/windows/odd:name").arg == "c:/windows/odd:name"
    for bad, match in [
        ("", "empty"),
        ("kinect2", "unknown"),
        ("replay", "path"),
        ("oak:", "after"),
    ]:
        with pytest.raises(SourceError, match=match):
            parse_spec(bad)


def test_bad_args_are_source_errors_not_retries(tmp_path):
    with pytest.raises(SourceError, match="index"):
        open_source("freenect:abc")
    with pytest.raises(SourceError, match="does not exist"):
        open_source(f"replay:{tmp_path}/none.mcap")
    with pytest.raises(SourceError):
        SourceOptions(fps=0)


def test_backoff_grows_caps_and_resets():
    b = Backoff(initial_s=0.5, maximum_s=4.0, factor=2.0, jitter=0.1)
    rng = random.Random(0)
    delays = [b.next_delay(rng) for _ in range(6)]
    for d, base in zip(delays, [0.5, 1, 2, 4, 4, 4], strict=True):
        assert base * 0.9 <= d <= base * 1.1
    b.reset()
    assert b.next_delay(rng) <= 0.55


def test_throttle_keeps_the_rate_not_the_burst():
    th = Throttle(10.0)
    arrivals = np.arange(0, 2.0, 1 / 30)  # a 30 fps sensor for 2 s
    admitted = [t for t in arrivals if th.admit(t)]
    assert len(admitted) in (20, 21)
    assert np.diff(admitted).min() > 0.09
    assert th.admit(100.0) and not th.admit(100.01)  # after a gap: one frame, not a burst
    assert all(Throttle(None).admit(t) for t in arrivals)


def test_pacer_follows_media_time():
    pacer = Pacer(realtime=True)
    t0 = time.monotonic()
    for i in range(5):
        pacer.wait(i * 0.04)
    elapsed = time.monotonic() - t0
    assert elapsed >= 0.15  # never faster than the media (4 gaps of 40 ms)
    free = Pacer(realtime=False)
    t0 = time.monotonic()
    for i in range(5):
        free.wait(i * 10.0)
    assert time.monotonic() - t0 < 1.0


class FlakySource(Source):
    """Delivers `n` frames then drops out (or ends, when finite): an interface double."""

    opened = 0
    closed = 0

    def __init__(self, n: int, finite: bool = False, fail_open: int = 0):
        FlakySource.opened += 1
        if FlakySource.opened <= fail_open:
            raise SourceUnavailable("not plugged in yet")
        self.n, self.finite = n, finite
        self.description = "flaky"
        self.intrinsics = KINECT_V1.scaled_to(4, 3)

    def frames(self):
        for i in range(self.n):
            yield SourceFrame(DepthFrame(np.full((3, 4), i, np.uint16), self.intrinsics, i))
        if not self.finite:
            raise SourceUnavailable("cable pulled")

    def close(self):
        FlakySource.closed += 1


@pytest.fixture
def flaky():
    FlakySource.opened = FlakySource.closed = 0
    return FlakySource


def test_reconnecting_reopens_after_failures(flaky, caplog):
    r = Reconnecting(
        lambda: flaky(3, fail_open=2), name="cam", backoff=Backoff(initial_s=0.01, maximum_s=0.02)
    )
    got = []
    for frame in r.frames():
        got.append(int(frame.depth.depth[0, 0]))
        if len(got) == 8:
            break
    assert got == [0, 1, 2, 0, 1, 2, 0, 1]
    assert flaky.opened == 2 + 3 and r.opens == 3
    assert r.failures == 2 + 2
    assert flaky.closed >= 3  # every opened source was closed, the last one by break
    assert "cable pulled" in caplog.text and "not plugged in yet" in caplog.text


def test_reconnecting_ends_with_a_finite_source_and_on_stop(flaky):
    r = Reconnecting(lambda: flaky(4, finite=True), backoff=Backoff(initial_s=0.01))
    assert len(list(r.frames())) == 4 and flaky.opened == 1
    stop = threading.Event()
    r = Reconnecting(lambda: flaky(0), backoff=Backoff(initial_s=30.0), stop=stop)
    threading.Timer(0.2, stop.set).start()
    t0 = time.monotonic()
    assert list(r.frames()) == []
    assert time.monotonic() - t0 < 5.0  # the 30 s backoff wait is cut short by stop


def test_reconnecting_passes_config_errors_through(flaky):
    def bad():
        raise SourceError("replay: nope.mcap does not exist")

    with pytest.raises(SourceError, match="does not exist"):
        list(Reconnecting(bad).frames())
