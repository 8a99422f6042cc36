"""Robot arms from URDF: every catalogue robot loads and poses within its limits and reach; a
placed robot round-trips through JSON and renders as robot; a URDF the user writes loads, poses
as worked out by hand and renders; bad files are one clear error naming the file."""

from __future__ import annotations

import json
import math
import sys

import numpy as np
import pytest

from topseg.core import labels
from topseg.core.camera import PAPER_MOUNT
from topseg.core.errors import TopsegError
from topseg.core.synth import render, robots
from topseg.core.synth.geometry import BOX, CYLINDER, polygon_area, quat_to_matrix

trimesh = pytest.importorskip("trimesh")
pytest.importorskip("yourdfpy")

FLOOR = render.Primitives(
    np.array([BOX], np.int32),
    np.array([[10.0, 10.0, 0.05]]),
    np.array([[0.0, 0.0, -0.05]]),
    np.eye(3)[None],
    np.array([0], np.uint8),
)


# --- the catalogue --------------------------------------------------------------------------


def test_the_catalogue_holds_arms_of_every_size():
    assert len(robots.ROBOTS) >= 8
    assert {"panda", "kuka_iiwa", "xarm6", "abb_irb140", "kuka_kr16", "kuka_kr210"} <= set(
        robots.ROBOTS
    )
    reach = [robots.robot_model(n).reach_m for n in robots.ROBOTS]
    assert min(reach) < 0.8 and max(reach) > 3.0  # small cobots to a KR 210


@pytest.mark.parametrize("name", robots.ROBOTS)
def test_every_catalogue_robot_loads_and_poses_within_its_limits_and_reach(name):
    model = robots.robot_model(name)
    assert robots.robot_model(name) is model  # cached
    assert model.name == name and len(model.joint_names) == len(set(model.joint_names)) > 0
    assert np.all(model.lower <= model.upper)
    rng = np.random.default_rng(0)
    for trial in range(5):
        joints = model.random_joints(rng)
        assert list(joints) == list(model.joint_names)
        q = np.array(list(joints.values()))
        assert np.all(q >= model.lower) and np.all(q <= model.upper)
        base = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0, 1)])
        mount = ("floor", "pedestal", "table", "gantry", "floor")[trial]
        placed = robots.PlacedRobot(
            7, name, base[0], base[1], rng.uniform(-math.pi, math.pi), mount,
            2.5 if mount == "gantry" else base[2], joints, (0.2, trial % 2),
        )  # fmt: skip
        prims, tris = model.link_geometry(joints, placed.base_pos(), placed.base_quat())
        assert len(prims) + len(tris) > 0
        assert np.all(prims.label == labels.ROBOT) and np.all(tris.label == labels.ROBOT)
        assert np.all(np.isfinite(tris.vertices))
        tool = placed.tool_position()
        assert np.linalg.norm(tool - placed.base_pos()) <= model.reach_m + 1e-9
    # the arm is about its datasheet's size: its reach bounds the posed triangles' spread too
    extent = np.ptp(tris.vertices.reshape(-1, 3), axis=0).max()
    assert 0.1 < extent < 2 * model.reach_m + 1.0


def test_continuous_joints_range_over_one_turn():
    model = robots.robot_model("interbotix_wx250s")  # its gripper joint is continuous
    i = model.joint_names.index("gripper")
    assert (model.lower[i], model.upper[i]) == (-math.pi, math.pi)


def test_a_posed_panda_renders_as_robot_from_the_ceiling():
    placed = robots.PlacedRobot(1, "panda", 0.2, -0.3, 0.4, "floor", 0.0, {})
    prims, tris = placed.geometry()
    depth, lab = render.raycast(render.Primitives.concat([FLOOR, prims]), PAPER_MOUNT, tris)
    robot = lab == labels.ROBOT
    assert robot.sum() > 500
    # the panda's top at its rest pose is ~1.1 m above the floor: 3.5 m - 1.1 m from the camera
    assert 2300 < depth[robot].min() < 2500
    assert np.all(lab[~robot] == 0)


# --- placing a robot ------------------------------------------------------------------------


@pytest.mark.parametrize("mount", robots.MOUNTS)
def test_a_placed_robot_round_trips_through_json_exactly(mount):
    rng = np.random.default_rng(3)
    joints = robots.robot_model("kuka_kr6").random_joints(rng)
    placed = robots.PlacedRobot(
        12, "kuka_kr6", 0.1 + 1e-13, -2.0 / 3.0, 2.0943951023931953, mount,
        2.4 if mount == "gantry" else 0.7, joints, (0.3, 1.0),
    )  # fmt: skip
    back = robots.PlacedRobot.from_dict(json.loads(json.dumps(placed.to_dict())))
    assert back == placed
    assert back.to_dict() == placed.to_dict()
    for a, b in zip(back.geometry(), placed.geometry(), strict=True):
        assert all(
            np.array_equal(x, y) for x, y in zip(vars(a).values(), vars(b).values(), strict=True)
        )


def test_an_unknown_mount_is_refused():
    with pytest.raises(ValueError, match="mount"):
        robots.PlacedRobot(1, "panda", 0.0, 0.0, 0.0, "wall", 0.0, {})


def test_a_pedestal_stands_from_the_floor_to_the_base_and_a_table_adds_nothing():
    joints = {}  # the rest pose: nothing below the base
    square = robots.PlacedRobot(1, "panda", 1.0, 0.5, 0.3, "pedestal", 0.6, joints, (0.25, 0.0))
    round_ = robots.PlacedRobot(1, "panda", 1.0, 0.5, 0.3, "pedestal", 0.6, joints, (0.25, 1.0))
    table = robots.PlacedRobot(1, "panda", 1.0, 0.5, 0.3, "table", 0.6, joints, (0.25, 1.0))
    arm_prims, _ = table.geometry()
    for placed, kind, size in (
        (square, BOX, (0.25, 0.25, 0.3)),
        (round_, CYLINDER, (0.25, 0.3, 0)),
    ):
        prims, _ = placed.geometry()
        assert len(prims) == len(arm_prims) + 1
        assert prims.kind[-1] == kind and prims.label[-1] == labels.ROBOT
        np.testing.assert_allclose(prims.size[-1], size)
        np.testing.assert_allclose(prims.center[-1], (1.0, 0.5, 0.3))
        assert placed.z_range()[0] == pytest.approx(0.0, abs=1e-12)  # the pedestal's foot
        # the footprint holds the pedestal's square or disc and the base
        fp = placed.footprint()
        assert polygon_area(fp) >= (0.25 * 0.25 * math.pi) * 0.99
    assert table.z_range()[0] >= 0.6 - 0.01  # the arm only, from the table's top


def test_a_gantry_robot_hangs_upside_down_under_its_beam():
    model = robots.robot_model("kuka_kr16")
    placed = robots.PlacedRobot(3, "kuka_kr16", -0.5, 0.2, 1.0, "gantry", 2.6, {})
    up = quat_to_matrix(placed.base_quat()) @ (0.0, 0.0, 1.0)
    np.testing.assert_allclose(up, (0.0, 0.0, -1.0), atol=1e-12)  # the robot's z points down
    prims, tris = placed.geometry()
    beam, posts = prims.center[-3], prims.center[-2:]
    assert beam[2] == pytest.approx(2.6 + robots.GANTRY_BEAM / 2)
    lo, hi = placed.z_range()
    assert hi == pytest.approx(2.6 + robots.GANTRY_BEAM)  # the beam's top
    assert lo == pytest.approx(0.0)  # the posts stand on the floor
    assert tris.vertices[:, :, 2].max() <= 2.6 + 1e-9  # the arm hangs below the beam
    # the posts stand beyond the arm's reach on either side of the base
    d = np.linalg.norm(posts[:, :2] - (-0.5, 0.2), axis=1)
    np.testing.assert_allclose(d, model.reach_m + robots.GANTRY_CLEARANCE)
    assert placed.tool_position()[2] < 2.6


def test_the_footprint_is_a_convex_ccw_polygon_under_the_arm():
    rng = np.random.default_rng(5)
    model = robots.robot_model("kuka_kr120")
    placed = robots.PlacedRobot(
        2, "kuka_kr120", 1.5, -1.0, 0.7, "floor", 0.0, model.random_joints(rng)
    )
    fp = placed.footprint()
    x, y = fp[:, 0], fp[:, 1]
    signed = 0.5 * (np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    assert signed > 0  # counter-clockwise
    _, tris = placed.geometry()
    pts = tris.vertices.reshape(-1, 3)[:, :2]
    edges = np.roll(fp, -1, axis=0) - fp
    cross = edges[:, 0] * (pts[:, None, 1] - fp[:, 1]) - edges[:, 1] * (pts[:, None, 0] - fp[:, 0])
    assert np.all(cross >= -1e-9)  # every vertex of the arm lies inside


# --- a URDF the user writes -----------------------------------------------------------------

TWO_LINK = """<?xml version="1.0"?>
<robot name="two_link">
  <link name="base">
    <collision><origin xyz="0 0 0.05"/><geometry><box size="0.2 0.2 0.1"/></geometry></collision>
  </link>
  <link name="upper">
    <collision>
      <origin xyz="0.25 0 0" rpy="0 1.5707963267948966 0"/>
      <geometry><cylinder radius="0.04" length="0.5"/></geometry>
    </collision>
  </link>
  <link name="fore">
    <collision><origin xyz="0.2 0 0"/><geometry><box size="0.4 0.06 0.1"/></geometry></collision>
  </link>
  <link name="flange"/>
  <joint name="shoulder" type="revolute">
    <parent link="base"/><child link="upper"/><origin xyz="0 0 0.1"/><axis xyz="0 0 1"/>
    <limit lower="-1.5" upper="1.5" effort="1" velocity="1"/>
  </joint>
  <joint name="elbow" type="revolute">
    <parent link="upper"/><child link="fore"/><origin xyz="0.5 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-2" upper="2" effort="1" velocity="1"/>
  </joint>
  <joint name="tool" type="fixed">
    <parent link="fore"/><child link="flange"/><origin xyz="0.4 0 0"/>
  </joint>
</robot>
"""


def write(path, text: str) -> str:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return str(path)


def test_a_user_urdf_with_a_box_and_a_cylinder_loads_poses_and_renders(tmp_path):
    model = robots.robot_model(write(tmp_path / "two_link.urdf", TWO_LINK))
    assert model.joint_names == ("shoulder", "elbow")
    assert model.tool_link == "flange"
    assert model.reach_m == pytest.approx(0.1 + 0.5 + 0.4)
    a, b = 0.6, -1.1
    joints = {"shoulder": a, "elbow": b}
    base = np.array([0.3, -0.2, 0.0])
    tool = model.tool_position(joints, base, (0.0, 0.0, 0.0, 1.0))
    reach = np.array([math.cos(a), math.sin(a), 0.0]) * 0.5
    reach += np.array([math.cos(a + b), math.sin(a + b), 0.0]) * 0.4
    by_hand = base + reach + (0.0, 0.0, 0.1)
    np.testing.assert_allclose(tool, by_hand, atol=1e-12)
    prims, tris = model.link_geometry(joints, base, (0.0, 0.0, 0.0, 1.0))
    assert len(tris) == 0 and sorted(prims.kind.tolist()) == [BOX, BOX, CYLINDER]
    depth, lab = render.raycast(render.Primitives.concat([FLOOR, prims]), PAPER_MOUNT, tris)
    robot = lab == labels.ROBOT
    assert robot.sum() > 300
    assert depth[robot].min() == 3500 - 150  # the forearm box's top, 0.15 m above the floor


def test_meshes_resolve_relative_file_and_package_paths_beside_the_urdf(tmp_path):
    box = trimesh.creation.box((0.1, 0.1, 0.1))
    (tmp_path / "my_arm" / "meshes").mkdir(parents=True)
    box.export(tmp_path / "my_arm" / "meshes" / "a.stl")
    box.export(tmp_path / "b.stl")
    text = TWO_LINK.replace(
        '<geometry><box size="0.2 0.2 0.1"/></geometry>',
        '<geometry><mesh filename="package://my_arm/meshes/a.stl"/></geometry>',
    ).replace(
        '<geometry><box size="0.4 0.06 0.1"/></geometry>',
        f'<geometry><mesh filename="file://{tmp_path / "b.stl"}" scale="4 0.6 1"/></geometry>',
    )
    model = robots.robot_model(write(tmp_path / "my_arm" / "urdf" / "arm.urdf", text))
    _, tris = model.link_geometry({}, (0, 0, 0), (0, 0, 0, 1))
    assert len(tris) == 24
    fore = tris.vertices[12:].reshape(-1, 3)
    np.testing.assert_allclose(np.ptp(fore, axis=0), (0.4, 0.06, 0.1), atol=1e-12)  # scaled


def test_a_dense_mesh_is_decimated_to_the_link_budget(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.1)  # 20480 faces
    sphere.export(tmp_path / "ball.stl")
    text = TWO_LINK.replace(
        '<geometry><box size="0.4 0.06 0.1"/></geometry>',
        '<geometry><mesh filename="ball.stl"/></geometry>',
    )
    model = robots.robot_model(write(tmp_path / "ball_arm.urdf", text))
    assert 0 < model.triangle_count <= robots.MAX_LINK_FACES
    _, tris = model.link_geometry({}, (0, 0, 0), (0, 0, 0, 1))
    # the ball sits 0.2 m along the forearm, which starts 0.5 m out and 0.1 m up
    radius = np.linalg.norm(tris.vertices.reshape(-1, 3) - (0.7, 0.0, 0.1), axis=1)
    assert radius.min() > 0.09 and radius.max() < 0.102  # still a ball


BAD = {
    "unparsable": ("<robot name='x'><link name='a'>", "cannot read URDF"),
    "no_joint": (
        "<robot name='x'><link name='a'><collision><geometry><box size='1 1 1'/></geometry>"
        "</collision></link></robot>",
        "no movable joint",
    ),
    "missing_mesh": (
        TWO_LINK.replace('<box size="0.2 0.2 0.1"/>', '<mesh filename="meshes/gone.stl"/>'),
        "meshes/gone.stl",
    ),
    "bad_mesh": (
        TWO_LINK.replace('<box size="0.2 0.2 0.1"/>', '<mesh filename="junk.stl"/>'),
        "junk.stl",
    ),
    "floating": (
        TWO_LINK.replace('name="shoulder" type="revolute"', 'name="shoulder" type="floating"'),
        "floating",
    ),
    "unknown_package": (
        TWO_LINK.replace('<box size="0.2 0.2 0.1"/>', '<mesh filename="package://nowhere/x.stl"/>'),
        "package://nowhere/x.stl",
    ),
}


@pytest.mark.parametrize("case", list(BAD))
def test_a_bad_urdf_is_one_clear_error_naming_the_file(tmp_path, case):
    text, what = BAD[case]
    (tmp_path / "junk.stl").write_bytes(b"solid nonsense\nthis is not an STL\n")
    path = write(tmp_path / f"{case}.urdf", text)
    with pytest.raises(TopsegError) as err:
        robots.robot_model(path)
    message = str(err.value)
    assert path in message and what in message
    assert "\n" not in message


def test_a_missing_file_or_an_unknown_name_is_one_clear_error(tmp_path):
    missing = str(tmp_path / "nowhere.urdf")
    with pytest.raises(TopsegError, match="no such file") as err:
        robots.robot_model(missing)
    assert missing in str(err.value)
    with pytest.raises(TopsegError, match=r"unknown robot 'r2d2'.*panda"):
        robots.robot_model("r2d2")


def test_without_the_train_extra_a_model_is_one_line_naming_it(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "yourdfpy", None)  # as if it were not installed
    with pytest.raises(TopsegError, match=r"yourdfpy is not installed .*topseg\[train\]"):
        robots.robot_model(write(tmp_path / "arm.urdf", TWO_LINK))
