"""The worker's mount bookkeeping (services/live/worker_mount.py) with a stand-in estimator and clock:
what waits for the first estimate, when re-checks happen, what counts as a move."""

import logging
from dataclasses import dataclass

import numpy as np
import pytest

from topseg.core.calibration import CalibrationError
from topseg.core.camera import KINECT_V1, TopViewMount
from topseg.core.formats.wire import DepthFrame
from topseg.core.sensors import nearest_sensor
from topseg.services.live.worker_mount import MountWatch, MountWatchConfig

K = KINECT_V1.scaled_to(16, 12)


@dataclass
class Estimate:
    mount: TopViewMount
    inlier_share: float = 0.8
    residual_mm: float = 5.0


class Floor:
    """A stand-in estimator: the floor is wherever the test says; `fail` raises once."""

    def __init__(self, height_mm=3000.0):
        self.height_mm, self.fail, self.calls, self.radial = height_mm, None, [], False

    def __call__(self, depths, k, sensor):
        self.calls.append(len(depths))
        if self.fail:
            why, self.fail = self.fail, None
            raise CalibrationError(why)
        return Estimate(TopViewMount(k, self.height_mm, sensor=sensor, radial=self.radial))


def frame(seq, mount=None):
    return DepthFrame(np.full(K.shape, 2000, np.uint16), K, seq, 0, "cam0", mount)


def test_first_frames_wait_for_the_estimate_then_are_all_released(caplog):
    floor = Floor()
    watch = MountWatch("c/cam0", MountWatchConfig(first_frames=3, recheck_s=30), floor)
    with caplog.at_level(logging.INFO, "topseg.worker"):
        assert watch.take(frame(0), now=0.0) == []
        assert watch.take(frame(1), now=0.1) == []
        released = watch.take(frame(2), now=0.2)
    assert [f.seq for f in released] == [0, 1, 2] and floor.calls == [3]
    assert watch.mount.height_mm == 3000.0 and watch.source == "estimated"
    assert watch.mount.sensor == nearest_sensor(K.width, K.height, K.fx).name == "kinect_v1"
    assert "camera c/cam0: estimated mount from 3 frames: height 3.00 m" in caplog.text
    assert [f.seq for f in watch.take(frame(3), now=0.3)] == [3]  # no waiting any more
    assert watch.stats() == {
        "height_mm": 3000.0, "pitch_deg": 0.0, "roll_deg": 0.0, "sensor": "kinect_v1",
        "source": "estimated", "moved": 0,
    }  # fmt: skip


def test_a_slow_camera_waits_at_most_first_wait_s():
    watch = MountWatch("c/cam0", MountWatchConfig(first_frames=10, first_wait_s=1.0), Floor())
    assert watch.take(frame(0), now=5.0) == [] and not watch.due(5.5)
    assert watch.seconds_to_due(5.5) == pytest.approx(0.5)
    assert watch.due(6.0) and [f.seq for f in watch.flush(6.0)] == [0]
    assert watch.seconds_to_due(6.0) is None


def test_a_failed_estimate_labels_without_a_mount_and_retries(caplog):
    floor = Floor()
    floor.fail = "no plane covers enough of the view"
    cfg = MountWatchConfig(first_frames=1, recheck_s=30, retry_s=5)
    watch = MountWatch("c/cam0", cfg, floor)
    with caplog.at_level(logging.WARNING, "topseg.worker"):
        assert [f.seq for f in watch.take(frame(0), now=0.0)] == [0]
    assert watch.mount is None and "no plane covers" in caplog.text
    assert [f.seq for f in watch.take(frame(1), now=1.0)] == [1]  # labelled, not held
    assert watch.mount is None and floor.calls == [1]  # not retried at once
    assert [f.seq for f in watch.take(frame(2), now=5.5)] == [2]  # retried on the newest
    assert watch.mount is not None and floor.calls == [1, 3]  # the newest three frames


def test_a_bumped_camera_is_reported_counted_and_the_new_estimate_used(caplog):
    floor = Floor(3310.0)
    watch = MountWatch("cell/cam0", MountWatchConfig(first_frames=1, recheck_s=30), floor)
    watch.take(frame(0), now=0.0)
    floor.height_mm = 3330.0  # within the threshold: not a move
    watch.take(frame(1), now=31.0)
    assert watch.moved == 0 and watch.mount.height_mm == 3310.0
    floor.height_mm = 3120.0
    with caplog.at_level(logging.WARNING, "topseg.worker"):
        watch.take(frame(2), now=62.0)
    assert "camera cell/cam0 moved: height 3.31 -> 3.12 m" in caplog.text
    assert watch.moved == 1 and watch.mount.height_mm == 3120.0
    assert watch.stats()["moved"] == 1


def test_the_frames_mount_is_used_checked_and_overridden_when_the_floor_disagrees(caplog):
    carried = TopViewMount(K, 2800.0, 1.0, 0.0)
    floor = Floor(2800.0)
    watch = MountWatch("c/cam0", MountWatchConfig(recheck_s=10), floor)
    assert [f.seq for f in watch.take(frame(0, carried), now=0.0)] == [0]
    assert (watch.mount, watch.source) == (carried, "frame") and floor.calls == []
    floor.height_mm = 2500.0  # the camera slipped since its calibration
    with caplog.at_level(logging.WARNING, "topseg.worker"):
        watch.take(frame(1, carried), now=11.0)
    assert "moved: height 2.80 -> 2.50 m" in caplog.text and "calibrate it again" in caplog.text
    assert watch.source == "estimated" and watch.mount.height_mm == 2500.0
    watch.take(frame(2, carried), now=12.0)  # the same stale mount on the frames: still overridden
    assert watch.source == "estimated"
    recalibrated = TopViewMount(K, 2500.0, 0.0, 0.0)
    watch.take(frame(3, recalibrated), now=13.0)  # a new mount file: used again
    assert (watch.mount, watch.source) == (recalibrated, "frame")


def test_an_estimate_that_replaces_the_frames_mount_keeps_its_edge_thinning():
    """The floor shows where the camera hangs, not how it filters its edges: a camera whose
    mount turned thinning off keeps it off after a move."""
    carried = TopViewMount(K, 2800.0, sensor="realsense_d435", edge_thinning=False)
    floor = Floor(2800.0)
    watch = MountWatch("c/d435", MountWatchConfig(recheck_s=10), floor)
    watch.take(frame(0, carried), now=0.0)
    floor.height_mm = 2500.0
    watch.take(frame(1, carried), now=11.0)
    assert watch.moved == 1 and watch.mount.height_mm == 2500.0
    assert watch.mount.edge_thinning is False


def test_a_mount_that_reads_range_as_depth_is_replaced_not_counted_as_a_move(caplog):
    carried = TopViewMount(K, 2800.0)  # a hand-written mount: depth
    floor = Floor(2800.0)
    floor.radial = True  # but the camera sends range: the re-check's fit finds it out
    watch = MountWatch("c/tof", MountWatchConfig(recheck_s=10), floor)
    watch.take(frame(0, carried), now=0.0)
    assert not watch.mount.radial
    with caplog.at_level(logging.WARNING, "topseg.worker"):
        watch.take(frame(1, carried), now=11.0)
    assert "camera c/tof sends range along each ray, but the frames' mount says" in caplog.text
    assert "calibrate it again" in caplog.text
    assert watch.mount.radial and watch.source == "estimated" and watch.moved == 0


def test_no_recheck_when_switched_off():
    floor = Floor()
    watch = MountWatch("c/cam0", MountWatchConfig(first_frames=1, recheck_s=0), floor)
    for i in range(5):
        watch.take(frame(i), now=100.0 * i)
    assert floor.calls == [1]


def test_guess_sensor_by_size_and_focal_length():
    from topseg.core.sensors import SENSORS

    for s in SENSORS:
        k = s.intrinsics
        assert nearest_sensor(k.width, k.height, k.fx).name == s.name


def test_a_radial_camera_is_estimated_with_the_real_fit_and_logged(caplog):
    """A camera that sends range along each ray: the worker's estimate (the real one) says
    so, and the frames are then labelled through a mount that reads them as depth."""
    from topseg.core.camera import depth_to_range

    k = KINECT_V1.scaled_to(160, 120)
    truth = TopViewMount(k, 3100.0, 2.0, -1.0)
    v, u = np.indices(k.shape)
    rays = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones(k.shape)], axis=-1)
    floor = np.rint(-truth.height_mm / (rays @ truth.up_normal_camera())).astype(np.uint16)
    ranges = depth_to_range(floor, k)
    watch = MountWatch("c/tof", MountWatchConfig(first_frames=2, recheck_s=30))
    with caplog.at_level(logging.INFO, "topseg.worker"):
        watch.take(DepthFrame(ranges, k, 0, 0, "tof"), now=0.0)
        released = watch.take(DepthFrame(ranges, k, 1, 0, "tof"), now=0.1)
    assert [f.seq for f in released] == [0, 1]
    assert watch.mount.radial and abs(watch.mount.height_mm - 3100.0) < 5
    assert "radial distance read as depth" in caplog.text
