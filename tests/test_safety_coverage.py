"""How much of the space around the robot the cameras see."""

import numpy as np
import pytest

from tests.safety_scenes import MOUNT
from topseg.core.camera import TopViewMount
from topseg.core.safety.cell import CameraPlacement, cell_from_dict
from topseg.core.safety.coverage import coverage, disc_points, seen_by
from topseg.core.safety.iso15066 import protective_distance
from topseg.core.sensors import KINECT_V2


def cell(cameras, **robot):
    spec = {"name": "arm", "urdf": "panda", "base_xyz_m": [0.0, 0.0, 0.0], **robot}
    return cell_from_dict({"cell": "c", "robot": spec, "camera": cameras}, "test")


def test_disc_points_fill_the_disc():
    pts = disc_points((1.0, 2.0), 0.5, 0.01)
    assert np.all(np.hypot(pts[:, 0] - 1.0, pts[:, 1] - 2.0) <= 0.5 + 1e-9)
    assert len(pts) == pytest.approx(np.pi * 50**2, rel=0.01)  # the disc's area in cells


def test_seen_by_is_the_image_of_the_camera():
    placement = CameraPlacement(name="cam0", x_m=2.0)
    centre, far, above = [2.0, 0.0, 0.0], [9.0, 0.0, 0.0], [2.0, 0.0, 3.5]
    got = seen_by(np.array([centre, far, above]), placement, MOUNT)
    assert got.tolist() == [True, False, False]
    # the floor the camera sees reaches farther than its view at shoulder height
    w = MOUNT.floor_extent_m()[0] / 2 * 0.9  # 90 % of the half-width, on the floor
    edge = np.array([[2.0 + w, 0.0, 0.0], [2.0 + w, 0.0, 1.5]])
    assert seen_by(edge, placement, MOUNT).tolist() == [True, False]


def test_coverage_of_one_narrow_camera_and_of_it_with_a_second():
    one = cell([{"name": "cam0"}])
    got = coverage(one, 0.85, {"cam0": MOUNT})
    s_p = protective_distance(one.separation, one.robot, 0.1, one.robot.max_speed_mps)
    assert got.s_p_m == pytest.approx(s_p) and got.radius_m == pytest.approx(0.85 + s_p)
    assert 0 < got.seen[1.5] < got.seen[0.0] < 1  # a 3 m Kinect v1 sees less than the disc
    assert got.worst() == got.seen[1.5] and "widen the view" in got.sentence()
    two = cell([{"name": "cam0"}, {"name": "cam1", "x_m": 2.0}])
    both = coverage(two, 0.85, {"cam0": MOUNT, "cam1": MOUNT})
    assert both.seen[0.0] > got.seen[0.0]
    assert coverage(two, 0.85, {"cam0": MOUNT}).seen == got.seen  # cam1's mount not known


def test_a_high_wide_camera_over_a_slow_robot_sees_all_of_it():
    slow = cell([{"name": "cam0"}], max_speed_mps=0.1, stopping_time_s=0.05,
                stopping_distance_m=0.02)  # fmt: skip
    high = TopViewMount(KINECT_V2.intrinsics, height_mm=4500.0)
    got = coverage(slow, 0.3, {"cam0": high})
    assert got.radius_m < 1.2 and got.seen == {0.0: 1.0, 1.5: 1.0}
    assert "widen" not in got.sentence()


def test_no_robot_no_coverage():
    bare = cell_from_dict({"cell": "c", "camera": [{"name": "cam0"}]}, "test")
    assert coverage(bare, 1.0, {"cam0": MOUNT}) is None


def test_a_huge_disc_is_sampled_coarsely_and_an_unbounded_one_is_unseen():
    fast = cell([{"name": "cam0"}], max_speed_mps=200.0)
    got = coverage(fast, 0.85, {"cam0": MOUNT})
    assert got.radius_m > 20 and 0 < got.seen[0.0] < 0.05
    unbounded = coverage(cell([{"name": "cam0"}]), float("inf"), {"cam0": MOUNT})
    assert unbounded.seen == {0.0: 0.0, 1.5: 0.0} and "widen the view" in unbounded.sentence()
