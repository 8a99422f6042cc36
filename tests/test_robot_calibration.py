"""The robot's base pose fitted to rendered depth frames: recovered from 8 cm and 5 degrees
off, with a person in front of the arm and with sensor noise; the refusals; and the pairing
of depth frames with joint states by stamp."""

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest

from tests.safety_scenes import MOUNT, person, render
from topseg.core.formats.joint_states import JointState
from topseg.core.safety.cell import cell_from_dict
from topseg.core.safety.robot import CellRobot
from topseg.core.safety.robot_calibration import (
    KEEP_FRAMES,
    KEEP_STATES,
    FramePairer,
    RobotCalibrationError,
    RobotView,
    fit_base_pose,
)
from topseg.core.sensors import get_sensor

MS = 1_000_000
T0 = 1_800_000_000_000_000_000
BASE = (0.4, 0.1, 0.3)
YAW = 20.0
#: the cell file's base: 8 cm and 5 degrees from the true one
OFF_XYZ = (0.4 + 0.06, 0.1 - 0.053, 0.3)
OFF_YAW = 25.0


def cell(urdf: str, xyz=BASE, yaw=YAW):
    table = {
        "cell": "c1",
        "robot": {"name": "arm", "urdf": urdf, "base_xyz_m": list(xyz), "base_yaw_deg": yaw},
        "camera": [{"name": "cam0", "x_m": 0.2, "y_m": -0.1, "yaw_deg": 10.0}],
    }
    return cell_from_dict(table, "test cell", Path("."))


def poses(robot: CellRobot, n: int, seed: int) -> list[dict[str, float]]:
    """`n` joint states drawn within the joints' limits (and +-1.5 rad)."""
    rng = np.random.default_rng(seed)
    lo, hi = np.maximum(robot.model.lower, -1.5), np.minimum(robot.model.upper, 1.5)
    return [dict(zip(robot.joint_names, rng.uniform(lo, hi), strict=True)) for _ in range(n)]


def views(urdf, joints, people=(), noise=None, seed=0):
    """Rendered depth of the robot at its true base at each joint state, as RobotViews."""
    c = cell(urdf)
    robot = CellRobot(c.robot, Path("."))
    rng = np.random.default_rng(seed)
    out = []
    for j in joints:
        depth, lab = render(c.cameras[0], robot, j, list(people))
        d = depth.depth if noise is None else noise.apply(depth.depth, rng, lab.labels)
        out.append(RobotView(d, MOUNT, j))
    return out


def start_robot(urdf, xyz=OFF_XYZ, yaw=OFF_YAW) -> CellRobot:
    """The robot as the cell file (off by 8 cm and 5 degrees) places it."""
    return CellRobot(cell(urdf, xyz, yaw).robot, Path("."))


def assert_recovered(fit):
    x, y, z = fit.pose.xyz_m
    assert np.hypot(x - BASE[0], y - BASE[1]) < 0.01, fit.summary()
    assert abs(z - BASE[2]) < 0.01, fit.summary()
    assert abs(fit.pose.yaw_deg - YAW) < 1.0, fit.summary()
    assert fit.within_share > 0.8 and fit.median_mm < 10, fit.summary()


@pytest.mark.parametrize("urdf", ["panda", "random:3"])
def test_the_base_is_recovered_from_8_cm_and_5_degrees_off(urdf):
    robot = start_robot(urdf)
    fit = fit_base_pose(robot, cell(urdf).cameras[0], views(urdf, poses(robot, 5, seed=1)))
    assert_recovered(fit)
    dx, dy, _, dyaw = fit.change()
    assert np.hypot(dx, dy) == pytest.approx(0.08, abs=0.01)
    assert dyaw == pytest.approx(-5.0, abs=1.0)
    assert "change" in fit.summary() and "within 2 cm" in fit.summary()


@pytest.mark.slow
def test_a_person_in_front_of_the_arm_and_sensor_noise_do_not_drag_it():
    robot = start_robot("panda")
    someone = person(0.9, 0.1, hand_at=(0.6, 0.15, 1.0))  # an arm reaching over the robot
    noise = get_sensor("kinect_v1").noise()
    frames = views("panda", poses(robot, 5, seed=2), [someone], noise, seed=4)
    assert_recovered(fit_base_pose(robot, cell("panda").cameras[0], frames))


def test_a_robot_outside_the_view_is_refused():
    robot = start_robot("panda", xyz=(6.0, 6.0, 0.0))
    with pytest.raises(RobotCalibrationError, match="not in view: at the cell file's base"):
        fit_base_pose(robot, cell("panda").cameras[0], views("panda", poses(robot, 2, 1)))


def test_a_robot_that_is_not_where_the_cell_file_puts_it_is_refused():
    robot = start_robot("panda")
    empty = [
        RobotView(render(cell("panda").cameras[0])[0].depth, MOUNT, j) for j in poses(robot, 2, 1)
    ]
    with pytest.raises(RobotCalibrationError, match="not in view: camera 'cam0' sees a surface"):
        fit_base_pose(robot, cell("panda").cameras[0], empty)


def test_joint_states_that_do_not_match_the_frames_are_refused_as_not_converging():
    robot = start_robot("panda", xyz=BASE, yaw=YAW)
    frames = views("panda", poses(robot, 3, seed=1))
    wrong = [replace(v, joints=j) for v, j in zip(frames, poses(robot, 3, seed=9), strict=True)]
    with pytest.raises(RobotCalibrationError, match="the fit did not converge"):
        fit_base_pose(robot, cell("panda").cameras[0], wrong)


# --- pairing ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Frame:
    stamp_ns: int


def state(stamp_ns: int) -> JointState:
    return JointState(stamp_ns, ("j1",), (0.0,))


def test_frames_pair_with_the_nearest_joint_state_within_20_ms():
    pairer = FramePairer(wanted=3)
    for k in range(10):  # joint states every 10 ms, frames every 33 ms between them
        pairer.add_state(state(T0 + k * 10 * MS))
        if k % 3 == 0:
            pairer.add_frame(Frame(T0 + k * 10 * MS + 4 * MS))
    pairer.finish()
    assert [(f.stamp_ns - T0, s.stamp_ns - T0) for f, s in pairer.pairs] == [
        (4 * MS, 0), (34 * MS, 30 * MS), (64 * MS, 60 * MS)
    ]  # fmt: skip
    assert pairer.done


def test_a_joint_state_arriving_after_its_frame_still_pairs():
    pairer = FramePairer(wanted=1)
    pairer.add_state(state(T0))
    pairer.add_frame(Frame(T0 + 15 * MS))
    assert not pairer.pairs  # a nearer state may still come
    pairer.add_state(state(T0 + 16 * MS))
    assert not pairer.pairs
    pairer.add_state(state(T0 + 40 * MS))
    assert [s.stamp_ns for _, s in pairer.pairs] == [T0 + 16 * MS]


def test_stale_and_missing_joint_states_say_so():
    stale = FramePairer(wanted=2)
    stale.add_state(state(T0))
    for k in range(3):
        stale.add_frame(Frame(T0 + (35 + k) * MS))
    stale.finish()
    assert not stale.pairs and stale.unpaired == 3
    why = stale.shortfall("depth key", "joints key")
    assert "stale" in why and "35 ms away" in why
    missing = FramePairer(wanted=2)
    missing.add_frame(Frame(T0))
    missing.finish()
    assert "no joint states on joints key" in missing.shortfall("depth key", "joints key")
    assert "no depth frames on depth key" in FramePairer(2).shortfall("depth key", "joints key")


def test_pairing_memory_is_bounded():
    pairer = FramePairer(wanted=10**6)
    for k in range(3 * KEEP_STATES):
        pairer.add_state(state(T0 + k * MS))
        pairer.add_frame(Frame(T0 - 10**9 + k))  # never near a state
    assert len(pairer.states) == KEEP_STATES and len(pairer.waiting) <= KEEP_FRAMES
    assert not pairer.pairs
