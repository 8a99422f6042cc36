"""Kinect v1 through libfreenect, for real, on Debian's fakenect library playing a dump topseg wrote."""

import os
from pathlib import Path

import numpy as np
import pytest

from topseg.drivers import Reconnecting, SourceOptions, SourceUnavailable, open_source
from topseg.drivers import fakenect_dump as fd
from topseg.drivers.base import Backoff
from topseg.drivers.freenect import FAKENECT_LIBRARY_DIR


def scene(rng):
    depth = (3500 + rng.normal(0, 15, (480, 640))).astype(np.uint16)
    depth[100:250, 200:420] = 2750  # a table
    depth[300:340, 50:90] = 1800  # a head
    depth[rng.random((480, 640)) < 0.02] = 0  # no-depth speckle
    return depth


# ----------------------------------------------------------------------------- conversion


def test_raw_to_mm_matches_libfreenect_zero_plane_model():
    t = fd.RAW_TO_MM
    # hand-evaluated freenect_raw_to_mm with the default zero plane (mm truncated)
    assert [int(t[r]) for r in (0, 600, 800, 1000, 1050)] == [317, 705, 1193, 3864, 8767]
    valid = np.flatnonzero(t)
    assert valid[0] == 0 and np.all(np.diff(valid) == 1)  # one contiguous valid range
    assert np.all(np.diff(t[valid].astype(int)) >= 0)  # depth rises with disparity
    assert t[fd.NO_DISPARITY] == 0 and t[valid[-1]] <= fd.MAX_MM


def test_mm_round_trip_within_quantisation():
    mm = np.arange(0, 12001, dtype=np.uint16)
    raw = fd.mm_to_raw(mm)
    back = fd.raw_to_mm(raw).astype(int)
    inside = (mm >= fd.MIN_MM) & (mm <= fd.MAX_VALID_MM)
    assert np.all(raw[~inside] == fd.NO_DISPARITY) and np.all(back[~inside] == 0)
    err = np.abs(back - mm)[inside]
    assert np.all(err <= fd.quantisation_step_mm(mm)[inside] // 2 + 1)
    # the step at 3.5 m is the Kinect's ~3.5 cm
    assert 25 <= fd.quantisation_step_mm(np.array([3500], np.uint16))[0] <= 45
    # every representable depth survives exactly
    exact = fd.RAW_TO_MM[fd.RAW_TO_MM > 0]
    np.testing.assert_array_equal(fd.raw_to_mm(fd.mm_to_raw(exact)), exact)


def test_dump_layout(tmp_path):
    rng = np.random.default_rng(0)
    frames = [scene(rng) for _ in range(2)]
    names = fd.write_dump(tmp_path, frames, fps=10.0)
    index = (tmp_path / "INDEX.txt").read_text().splitlines()
    assert index[:2] == names and index[2].startswith("a-")
    blob = (tmp_path / names[1]).read_bytes()
    assert blob.startswith(b"P5 640 480 65535\n") and len(blob) == 17 + 640 * 480 * 2
    raw = np.frombuffer(blob, "<u2", offset=17).reshape(480, 640)
    assert raw.max() <= 2047 and np.all((raw == 2047) == (frames[1] == 0))
    host = [float(n.split("-")[1]) for n in names]
    assert host[1] - host[0] == pytest.approx(0.1)
    back = list(fd.read_dump(tmp_path))
    np.testing.assert_array_equal(back[1].raw, raw)
    with pytest.raises(Exception, match="already"):
        fd.write_dump(tmp_path, frames)


# ----------------------------------------------------------------------------- the driver


@pytest.fixture
def fakenect(tmp_path, monkeypatch):
    """A dump of topseg frames, served by libfreenect's fakenect to the driver's reader."""
    assert Path(FAKENECT_LIBRARY_DIR, "libfreenect.so.0.5").exists(), "apt install libfreenect-bin"
    rng = np.random.default_rng(1)
    frames = [scene(rng) for _ in range(4)]
    fd.write_dump(tmp_path / "dump", frames)
    monkeypatch.setenv("LD_LIBRARY_PATH", FAKENECT_LIBRARY_DIR)
    monkeypatch.setenv("FAKENECT_PATH", str(tmp_path / "dump"))
    return frames


def check_frame(got, original):
    back = got.depth.depth.astype(int)
    assert got.depth.depth.shape == (480, 640)
    np.testing.assert_array_equal(back == 0, original == 0)
    assert np.all(np.abs(back - original) <= fd.quantisation_step_mm(original) // 2 + 1)


def test_freenect_reads_the_dump_then_reports_the_stall(fakenect):
    options = SourceOptions(frame_timeout_s=1.0)
    with open_source("freenect:0", options) as src:
        assert src.intrinsics.shape == (480, 640) and src.description == "freenect:0"
        it = src.frames()
        got = [next(it) for _ in fakenect]
        for g, original in zip(got, fakenect, strict=True):
            check_frame(g, original)
        assert [g.depth.seq for g in got] == [0, 1, 2, 3]
        # fakenect 0.5.3 blocks or dies after the last frame: the reader says so, in time
        with pytest.raises(SourceUnavailable):
            next(it)


def test_freenect_reconnects_after_the_sensor_drops(fakenect, caplog):
    options = SourceOptions(frame_timeout_s=1.0)
    r = Reconnecting(lambda: open_source("freenect", options), backoff=Backoff(initial_s=0.05))
    got = []
    for frame in r.frames():
        got.append(frame)
        if len(got) == 2 * len(fakenect):
            break
    assert r.opens == 2 and r.failures == 1
    for g, original in zip(got, fakenect + fakenect, strict=True):
        check_frame(g, original)
    assert "trying again" in caplog.text


def test_no_kinect_is_unavailable(monkeypatch):
    monkeypatch.delenv("LD_LIBRARY_PATH", raising=False)
    monkeypatch.delenv("FAKENECT_PATH", raising=False)
    assert "fakenect" not in os.environ.get("LD_LIBRARY_PATH", "")
    with pytest.raises(SourceUnavailable, match="no Kinect"):
        open_source("freenect:0", SourceOptions(open_timeout_s=10.0))
