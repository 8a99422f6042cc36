"""Fixtures shared by the service tests."""

import numpy as np
import pytest
from netutil import Services

from topseg.core.camera import KINECT_V1, PAPER_MOUNT, TopViewMount
from topseg.core.formats import dataset as D
from topseg.core.formats import wire
from topseg.core.formats.recording import RecordingWriter
from topseg.core.synth import procedural

#: the camera and rate of `small_recording`
SMALL_K = KINECT_V1.scaled_to(160, 120)
SMALL_FPS = 30


@pytest.fixture(autouse=True)
def _collector_unfrozen():
    """A service run in the test process freezes its objects out of the garbage collector
    when it is ready (`ServiceLifecycle.ready`); give them back after each test, so the
    suite's own cycles stay collectable."""
    import gc

    yield
    gc.unfreeze()


@pytest.fixture(scope="session")
def data(tmp_path_factory):
    """A 12-frame procedural dataset written through the real dataset writer."""
    path = tmp_path_factory.mktemp("train") / "ds.zarr"
    n = 12
    attrs = D.make_attrs(
        seed=5,
        mode="procedural",
        noise="gaussian:10",
        room=None,
        generator={"name": "procedural"},
        frames=n,
    )
    rng = np.random.default_rng(5)
    with D.DatasetWriter.open(path, attrs) as w:
        fw = D.FrameWriter(path)
        for i in range(n):
            depth, labels = procedural.procedural_frame(rng)
            fw.write(i, depth, labels, {"index": i})
        w.mark_complete(range(n))
    return path


@pytest.fixture
def run():
    """Start topseg services as subprocesses (`netutil.Services`); all stopped afterwards."""
    services = Services()
    yield services
    services.close()


@pytest.fixture(scope="session")
def small_recording(tmp_path_factory):
    """One second of 160x120 procedural frames at 30 fps (SMALL_K, SMALL_FPS; replayed
    with --loop)."""
    path = tmp_path_factory.mktemp("small") / "small.mcap"
    rng = np.random.default_rng(7)
    with RecordingWriter(path) as w:
        for i in range(SMALL_FPS):
            depth, _ = procedural.procedural_frame(
                rng, TopViewMount(SMALL_K, PAPER_MOUNT.height_mm)
            )
            t = 10**18 + i * 10**9 // SMALL_FPS
            w.write(wire.depth_key(), wire.encode_depth(wire.DepthFrame(depth, SMALL_K, i, t)), t)
    return path
