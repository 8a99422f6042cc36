"""The OAK driver's host side, for real, on a host-only depthai pipeline feeding RAW16 frames."""

import datetime
import time

import numpy as np
import pytest

from topseg.core.camera import Intrinsics
from topseg.drivers import SourceError, SourceOptions, SourceUnavailable
from topseg.drivers.oak import OakSource, import_depthai

dai = import_depthai()
K = Intrinsics(64, 40, 50.0, 50.0, 31.5, 19.5)


class Feeder(dai.node.ThreadedHostNode):
    """Sends the given uint16 images as RAW16 ImgFrames, 10 ms apart, then stops sending."""

    def __init__(self):
        super().__init__()
        self.out = self.createOutput()
        self.images = []
        self.frame_type = dai.ImgFrame.Type.RAW16

    def run(self):
        for i, img in enumerate(self.images):
            if not self.isRunning():
                return
            f = dai.ImgFrame()
            f.setType(self.frame_type)
            f.setWidth(img.shape[1])
            f.setHeight(img.shape[0])
            f.setData(np.ascontiguousarray(img).view(np.uint8).reshape(-1))
            f.setSequenceNum(i)
            f.setTimestamp(datetime.timedelta(seconds=time.monotonic()))
            self.out.send(f)
            time.sleep(0.01)


QUICK = SourceOptions(frame_timeout_s=0.5)


def host_source(images, options=QUICK, frame_type=None):
    pipeline = dai.Pipeline(False)
    feeder = pipeline.create(Feeder)
    feeder.images = images
    if frame_type is not None:
        feeder.frame_type = frame_type
    queue = feeder.out.createOutputQueue(maxSize=8, blocking=True)
    return OakSource(pipeline, queue, K, options, "oak:host-test", 30.0)


def test_host_pipeline_frames_arrive_in_mm_then_stall_is_reported():
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 10000, (40, 64), dtype=np.uint16) for _ in range(4)]
    with host_source(images) as src:
        assert src.intrinsics == K
        it = src.frames()
        got = [next(it) for _ in images]
        with pytest.raises(SourceUnavailable, match="no frame"):
            next(it)
    for img, g in zip(images, got, strict=True):
        np.testing.assert_array_equal(g.depth.depth, img)
        assert g.depth.intrinsics == K
    assert [g.depth.seq for g in got] == [0, 1, 2, 3]


def test_wrong_size_or_type_is_refused():
    with (
        host_source([np.zeros((10, 10), np.uint16)]) as src,
        pytest.raises(SourceError, match="10x10"),
    ):
        next(src.frames())
    gray = dai.ImgFrame.Type.GRAY8
    with host_source([np.zeros((40, 64), np.uint16)], frame_type=gray) as src:
        with pytest.raises(SourceError, match="RAW16"):
            next(src.frames())


def test_telemetry_is_off():
    import os

    assert os.environ["DEPTHAI_TELEMETRY"] == "0"
