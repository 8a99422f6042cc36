"""`topseg calibrate robot` as a user runs it: a recording or live Zenoh in, the fitted base
out (printed, or written into the cell file with its comments kept), and its refusals."""

import re
import subprocess
import sys
import time
import tomllib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from netutil import free_port

from tests.safety_scenes import render
from topseg.core.errors import TopsegError
from topseg.core.formats import joint_states, recording, wire
from topseg.core.safety.cell import load_cell
from topseg.core.safety.robot import CellRobot
from topseg.core.safety.robot_calibration import BasePose
from topseg.services.live.calibrate_robot import with_base
from topseg.services.runtime.zenoh_session import open_session

MS = 1_000_000
T0 = 1_800_000_000_000_000_000
TRUE_XYZ, TRUE_YAW = (0.4, 0.1, 0.0), 20.0

CELL_TOML = """# the test cell
cell = "{cell}"

[robot]  # the arm
name = "arm"
urdf = "panda"
base_xyz_m = [0.46, 0.047, 0.0]  # taped
base_yaw_deg = 25.0  # by eye
stopping_time_s = 0.4

[[camera]]
name = "cam0"
x_m = 0.2
"""


def calibrate(*args, timeout=300):
    return subprocess.run(
        [sys.executable, "-m", "topseg.services.cli", "calibrate", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def error_lines(r) -> list[str]:
    return [ln for ln in r.stderr.splitlines() if ln.startswith("topseg calibrate: error")]


def cell_file(folder: Path, cell: str = "robotcal") -> Path:
    path = folder / "cell.toml"
    path.write_text(CELL_TOML.format(cell=cell))
    return path


def scenes(cell_path: Path, n: int):
    """`n` (depth frame, joints) of the robot at its true base, each at its own pose."""
    cell = load_cell(cell_path)
    spec = replace(cell.robot, base_xyz_m=TRUE_XYZ, base_yaw_deg=TRUE_YAW)
    truth = CellRobot(spec, cell_path.parent)
    rng = np.random.default_rng(5)
    lo, hi = np.maximum(truth.model.lower, -1.5), np.minimum(truth.model.upper, 1.5)
    out = []
    for i in range(n):
        joints = dict(zip(truth.joint_names, rng.uniform(lo, hi), strict=True))
        depth, _ = render(cell.cameras[0], truth, joints, seq=i, stamp_ns=T0 + i * 33 * MS)
        out.append((depth, joints))
    return out


def joint_message(joints: dict, stamp_ns: int) -> bytes:
    state = joint_states.JointState(stamp_ns, tuple(joints), tuple(map(float, joints.values())))
    return joint_states.encode_joint_state(state)


def write_recording(path: Path, cell_path: Path, n: int, joint_offset_ns: int = 0, joints=True):
    """A msgpack recording of the camera's depth and the robot's joints (each state just
    before its frame, and one 10 ms after it)."""
    cell = load_cell(cell_path)
    with recording.RecordingWriter(path) as writer:
        for depth, pose in scenes(cell_path, n):
            key = joint_states.joints_key(cell.cell, "arm")
            if joints:
                writer.write(key, joint_message(pose, depth.stamp_ns + joint_offset_ns - 3 * MS))
            writer.write(wire.depth_key(cell.cell, "cam0"), wire.encode_depth(depth))
            if joints:
                writer.write(key, joint_message(pose, depth.stamp_ns + joint_offset_ns + 10 * MS))
    return path


def pose_of(cell_path: Path) -> BasePose:
    robot = load_cell(cell_path).robot
    return BasePose(robot.base_xyz_m, robot.base_yaw_deg)


def assert_near_truth(pose: BasePose):
    x, y, z = pose.xyz_m
    assert np.hypot(x - TRUE_XYZ[0], y - TRUE_XYZ[1]) < 0.01 and abs(z - TRUE_XYZ[2]) < 0.01
    assert abs(pose.yaw_deg - TRUE_YAW) < 1.0


def printed_pose(stdout: str) -> BasePose:
    xyz = re.search(r"^base_xyz_m = \[(.*)\]$", stdout, re.M)
    yaw = re.search(r"^base_yaw_deg = (\S+)$", stdout, re.M)
    assert xyz and yaw, stdout
    return BasePose(tuple(float(v) for v in xyz[1].split(",")), float(yaw[1]))


@pytest.mark.slow
def test_a_recording_gives_the_base_and_write_keeps_the_comments(tmp_path):
    cell_path = cell_file(tmp_path)
    rec = write_recording(tmp_path / "rec.mcap", cell_path, 3)
    r = calibrate("robot", "--cell", cell_path, "--source", f"replay:{rec}", "--frames", 3)
    assert r.returncode == 0, r.stderr
    assert "residual   median" in r.stdout and "change     x" in r.stdout
    assert_near_truth(printed_pose(r.stdout))
    assert cell_path.read_text() == CELL_TOML.format(cell="robotcal")  # not written

    r = calibrate(
        "robot", "--cell", cell_path, "--source", f"replay:{rec}", "--frames", 3, "--write"
    )
    assert r.returncode == 0, r.stderr
    text = cell_path.read_text()
    assert_near_truth(pose_of(cell_path))
    for kept in ("# the test cell", "[robot]  # the arm", "# taped", "# by eye",
                 "stopping_time_s = 0.4", "[[camera]]"):  # fmt: skip
        assert kept in text
    assert "0.46," not in text


@pytest.mark.slow
def test_stale_or_missing_joint_states_are_refused_in_one_line(tmp_path):
    cell_path = cell_file(tmp_path)
    stale = write_recording(tmp_path / "stale.mcap", cell_path, 2, joint_offset_ns=40 * MS)
    r = calibrate("robot", "--cell", cell_path, "--source", f"replay:{stale}", "--frames", 2)
    assert r.returncode == 2 and len(error_lines(r)) == 1, r.stderr
    assert "joint states are stale" in error_lines(r)[0]
    none = write_recording(tmp_path / "none.mcap", cell_path, 2, joints=False)
    r = calibrate("robot", "--cell", cell_path, "--source", f"replay:{none}", "--frames", 2)
    assert r.returncode == 2 and "no joint states on topseg/robotcal/robot/arm/joints" in r.stderr
    assert cell_path.read_text() == CELL_TOML.format(cell="robotcal")


@pytest.mark.slow
def test_flags_of_the_other_mode_are_refused(tmp_path):
    cell_path = cell_file(tmp_path)
    r = calibrate("robot", "--cell", cell_path, "--source", "zenoh", "--out", tmp_path / "m.json")
    assert r.returncode == 2 and "--out is not a flag of `topseg calibrate robot`" in r.stderr
    r = calibrate("--source", "synthetic", "--cell", cell_path)
    assert r.returncode == 2 and "--cell goes with `topseg calibrate robot`" in r.stderr
    r = calibrate("robot", "--source", "zenoh")
    assert r.returncode == 2 and "needs --cell" in r.stderr
    r = calibrate("robot", "--cell", cell_path, "--source", "freenect")
    assert r.returncode == 2 and "zenoh (live) or replay:FILE.mcap" in r.stderr


def test_live_frames_and_joint_states_on_zenoh(tmp_path):
    port = free_port()
    cell_path = cell_file(tmp_path, cell="robotlive")
    frames = scenes(cell_path, 3)
    proc = subprocess.Popen(
        [sys.executable, "-m", "topseg.services.cli", "calibrate", "robot", "--cell",
         str(cell_path), "--source", "zenoh", "--frames", "3", "--timeout", "120",
         "--zenoh-port", str(port)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    session = open_session(port=port)
    try:
        depth_pub = session.declare_publisher(wire.depth_key("robotlive", "cam0"))
        joints_pub = session.declare_publisher(joint_states.joints_key("robotlive", "arm"))
        deadline = time.monotonic() + 120
        while proc.poll() is None and time.monotonic() < deadline:
            for depth, pose in frames:  # again and again until the command has its pairs
                now = time.time_ns()
                joints_pub.put(joint_message(pose, now - 2 * MS))
                depth_pub.put(wire.encode_depth(replace(depth, stamp_ns=now)))
                joints_pub.put(joint_message(pose, now + 25 * MS))  # only after it settles
                time.sleep(0.05)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        session.close()
    assert proc.returncode == 0, err
    assert_near_truth(printed_pose(out))


def test_with_base_edits_only_the_robot_tables_base_lines():
    pose = BasePose((1.0, 2.0, 0.5), -90.0)
    text = "cell = 'c'\n[robot]\nname = 'a'  # keep\n[separation]\nbase_yaw_deg = 1\n"
    edited = with_base(text, pose)
    table = tomllib.loads(edited)
    assert table["robot"]["base_xyz_m"] == [1.0, 2.0, 0.5]
    assert table["robot"]["base_yaw_deg"] == -90.0
    assert table["separation"]["base_yaw_deg"] == 1  # another table's line left alone
    assert "name = 'a'  # keep" in edited
    with pytest.raises(TopsegError, match="no \\[robot\\] table line"):
        with_base("cell = 'c'\nrobot = { name = 'a', urdf = 'panda' }\n", pose)
