"""OpenNI2 for real, on its built-in Dummy device (libOpenNI2 runs in the driver's child)."""

import itertools
import math

import pytest

from topseg.drivers import SourceOptions, SourceUnavailable, open_source
from topseg.drivers.openni2 import intrinsics_from_fov


def test_dummy_device_streams_depth():
    with open_source("openni2:Dummy", SourceOptions(frame_timeout_s=2.0)) as src:
        assert src.description == "openni2:Dummy"
        assert src.intrinsics.shape == (240, 320)
        assert src.nominal_fps == 30.0
        it = src.frames()
        got = [next(it) for _ in range(4)]
    seqs = [g.depth.seq for g in got]
    stamps = [g.depth.stamp_ns for g in got]
    assert seqs == [0, 1, 2, 3] and stamps == sorted(stamps)
    for g in got:
        d = g.depth.depth
        assert d.dtype.name == "uint16" and d.shape == (240, 320)
        assert d.max() > 0  # the Dummy device serves a test pattern in mm


def test_fps_cap_drops_frames():
    with open_source("openni2:Dummy", SourceOptions(fps=10.0)) as src:
        it = src.frames()
        got = [next(it) for _ in range(3)]
    gaps = [(b.depth.stamp_ns - a.depth.stamp_ns) / 1e9 for a, b in itertools.pairwise(got)]
    assert min(gaps) > 0.08  # 10 fps out of a 30 fps device


def test_missing_device_is_unavailable():
    with pytest.raises(SourceUnavailable, match="NoSuchDevice"):
        open_source("openni2:NoSuchDevice")


def test_intrinsics_from_field_of_view():
    k = intrinsics_from_fov(640, 480, math.radians(58.5), math.radians(45.6))
    assert k.fx == pytest.approx(320 / math.tan(math.radians(29.25)))
    assert k.field_of_view_deg() == pytest.approx((58.5, 45.6))
    assert intrinsics_from_fov(320, 240, None, None).fx == pytest.approx(570.3 / 2)
