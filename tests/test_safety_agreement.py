"""Scoring the safety decisions against a sequence's truth: whether the camera sees the
truth's nearest point, and the error split it gives."""

import numpy as np
import pytest

from tests.safety_scenes import MOUNT
from topseg.core.formats.wire import DepthFrame
from topseg.core.safety.agreement import Compared, nearest_point_seen, score, truth_nearest
from topseg.core.safety.cell import CameraPlacement

PLACEMENT = CameraPlacement(name="cam0", x_m=1.0, y_m=-0.5, yaw_deg=30.0)


def frame_with_a_box() -> DepthFrame:
    """The floor 3 m below the camera, a box top 1 m above the floor over the pixels of
    the cell point (1, -0.5) (under the camera) and around it."""
    depth = np.full(MOUNT.intrinsics.shape, 3000, np.uint16)
    k = MOUNT.intrinsics
    rows, cols = int(k.cy), int(k.cx)
    depth[rows - 10 : rows + 10, cols - 10 : cols + 10] = 2000
    return DepthFrame(depth, k, 0, 1, "cam0", MOUNT)


@pytest.mark.parametrize(
    ("point", "seen"),
    [
        ((1.0, -0.5, 1.0), True),  # on the box top
        ((1.0, -0.5, 0.3), False),  # inside or under the box: hidden by it
        ((1.6, -1.1, 0.0), True),  # on the open floor
        ((1.6, -1.1, 0.04), True),  # just above it, within the tolerance
        ((9.0, 9.0, 1.0), False),  # outside the image
        ((1.0, -0.5, 3.5), False),  # above the camera
    ],
)
def test_nearest_point_seen(point, seen):
    assert nearest_point_seen(point, frame_with_a_box(), PLACEMENT) is seen


def test_a_frame_without_a_mount_sees_nothing():
    depth = frame_with_a_box()
    bare = DepthFrame(depth.depth, depth.intrinsics, 0, 1, "cam0", None)
    assert not nearest_point_seen((1.0, -0.5, 1.0), bare, PLACEMENT)


def test_the_error_is_split_by_whether_the_nearest_point_is_seen():
    def c(err, seen):
        return Compared("stop", "stop", 0.5 + err, 0.5, "hand", "hand", 1, None, seen)

    figures = score([c(0.01, True), c(0.02, True), c(0.30, False), c(0.5, None)])
    assert figures["distance_frames"] == 4
    assert figures["distance_frames_seen"] == 2 and figures["distance_frames_hidden"] == 1
    assert figures["distance_error_p95_seen_m"] == pytest.approx(0.02)  # nearest rank
    assert figures["distance_error_p95_hidden_m"] == pytest.approx(0.30)


def test_the_error_has_its_two_sides_apart():
    def c(measured, truth):
        return Compared("stop", "stop", measured, truth, "hand", "hand", 1, None, True)

    figures = score([c(0.50, 0.40), c(0.30, 0.50), c(0.45, 0.45), c(None, 0.2)])
    assert figures["distance_farther_p99_m"] == pytest.approx(0.10)
    assert figures["distance_nearer_p99_m"] == pytest.approx(0.20)
    assert score([c(0.4, 0.4)])["distance_nearer_p99_m"] == 0.0


def test_truth_nearest_carries_the_persons_point():
    persons = [
        {"distance_m": 0.8, "part": "head", "link": "a", "point_m": [0, 0, 1.7]},
        {"distance_m": 0.3, "part": "hand", "link": "b", "point_m": [1, 2, 1.0]},
        {"distance_m": 0.1, "part": "body", "link": "c", "in_view": False},
    ]
    nearest, in_view = truth_nearest(persons)
    assert in_view == 2 and nearest.link == "b" and nearest.point_m == (1.0, 2.0, 1.0)


def test_a_point_one_camera_cannot_see_is_seen_when_another_does():
    """`truth_point_seen` over a cell's cameras: the point inside the box is hidden from the
    camera over it and seen by one beside it whose floor it lies on."""
    from topseg.core.safety.agreement import TruthNearest, truth_point_seen

    hidden = TruthNearest(0.5, 0, "link1", (1.0, -0.5, 0.3))
    beside = CameraPlacement(name="cam1", x_m=2.0, y_m=-0.5, yaw_deg=0.0)
    floor = DepthFrame(np.full(MOUNT.intrinsics.shape, 3000, np.uint16), MOUNT.intrinsics,
                       0, 1, "cam1", MOUNT)  # fmt: skip
    assert truth_point_seen(hidden, [(frame_with_a_box(), PLACEMENT)]) is False
    assert truth_point_seen(hidden, [(frame_with_a_box(), PLACEMENT), (floor, beside)]) is True
    assert truth_point_seen(None, [(floor, beside)]) is None
