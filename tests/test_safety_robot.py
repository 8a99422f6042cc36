"""The cell's robot (core/safety/robot.py): capsules that contain every link as posed, the
base placement, joint-state checks, link speeds and the silhouette a camera sees."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from reference import grow_mask_reference

from topseg.core import labels
from topseg.core.camera import KINECT_V1, TopViewMount, depth_to_range
from topseg.core.errors import TopsegError
from topseg.core.safety.cell import CameraPlacement, RobotSpec
from topseg.core.safety.robot import CellRobot, ellipse_half_widths, grow_mask
from topseg.core.safety.separation import human_points, nearest, point_distances
from topseg.core.synth.geometry import BOX, CAPSULE, CYLINDER, SPHERE


def Spec(name: str = "arm", **fields) -> RobotSpec:
    """The cell file's robot, named "arm" unless told."""
    return RobotSpec(name=name, **fields)


def Placement(x_m: float = 0.0, y_m: float = 0.0, yaw_deg: float = 0.0) -> CameraPlacement:
    """The cell file's camera placement, by position."""
    return CameraPlacement(x_m=x_m, y_m=y_m, yaw_deg=yaw_deg)


PRIMITIVE_URDF = """<?xml version="1.0"?>
<robot name="prims">
  <link name="base"><collision><geometry><box size="0.3 0.2 0.1"/></geometry></collision></link>
  <link name="upper">
    <collision><origin xyz="0 0 0.25" rpy="0.3 0 0"/>
      <geometry><cylinder radius="0.05" length="0.5"/></geometry></collision>
    <collision><origin xyz="0 0.1 0.5"/><geometry><sphere radius="0.08"/></geometry></collision>
  </link>
  <link name="ball"><visual><geometry><sphere radius="0.06"/></geometry></visual></link>
  <joint name="j1" type="revolute"><parent link="base"/><child link="upper"/>
    <origin xyz="0 0 0.05"/><axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/>
  </joint>
  <joint name="j2" type="prismatic"><parent link="upper"/><child link="ball"/>
    <origin xyz="0 0 0.6"/><axis xyz="1 0 0"/><limit lower="-0.2" upper="0.2" effort="1" velocity="1"/>
  </joint>
</robot>
"""


@pytest.fixture(scope="module")
def primitive_urdf(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("cell")
    (folder / "prims.urdf").write_text(PRIMITIVE_URDF)
    return folder


def _surface_samples(kind, size, centre, rot, rng, n=400) -> np.ndarray:
    """Points on a primitive's surface (a box's corners and faces, a round shape's skin)."""
    if kind == BOX:
        local = rng.uniform(-1, 1, (n, 3))
        axis = rng.integers(0, 3, n)
        local[np.arange(n), axis] = np.sign(local[np.arange(n), axis])
        local = np.concatenate(
            [local, [[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]]
        )
        local = local * size
    else:
        r, h = size[0], (0.0 if kind == SPHERE else size[1])
        direction = rng.normal(size=(n, 3))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        if kind == CYLINDER:
            angle = rng.uniform(0, 2 * np.pi, n)
            local = np.stack([r * np.cos(angle), r * np.sin(angle), rng.uniform(-h, h, n)], 1)
            local[: n // 4, 2] = h * np.sign(local[: n // 4, 2])  # the rims
        else:
            local = r * direction
            if kind == CAPSULE:
                local[:, 2] += np.where(direction[:, 2] > 0, h, -h)
    return local @ rot.T + centre


def _assert_capsules_contain_the_geometry(robot: CellRobot, joints, rng):
    caps = robot.capsules(joints)
    prims, tris = robot.geometry(joints)
    model = robot.model
    checked = 0
    for i, link in enumerate(caps.link):
        lo, hi = model._tri_blocks[i]
        pts = [tris.vertices[lo:hi].reshape(-1, 3)]
        for p in np.flatnonzero(model._prim_link == i):
            pts.append(
                _surface_samples(prims.kind[p], prims.size[p], prims.center[p], prims.rot[p], rng)
            )
        pts = np.concatenate(pts)
        one = type(caps)(caps.a[i : i + 1], caps.b[i : i + 1], caps.radius[i : i + 1], (link,))
        distance, _ = point_distances(pts, one)
        assert distance.max() <= 1e-9, f"{link}: a point {distance.max():.4f} m outside"
        checked += len(pts)
    assert checked > 0


@pytest.mark.parametrize("name", ["panda", "kuka_iiwa", "xarm6", "kuka_kr16", "random:3", "prims"])
@pytest.mark.parametrize("base", [((0.0, 0.0, 0.0), 0.0, False), ((1.2, -0.4, 2.3), 135.0, True)])
def test_capsules_contain_every_vertex_and_primitive(name, base, primitive_urdf):
    urdf = "prims.urdf" if name == "prims" else name
    robot = CellRobot(Spec(urdf=urdf, base_xyz_m=base[0], base_yaw_deg=base[1],
                           upside_down=base[2]), primitive_urdf)  # fmt: skip
    rng = np.random.default_rng(0)
    for _ in range(3):
        _assert_capsules_contain_the_geometry(robot, robot.model.random_joints(rng), rng)


def test_capsules_are_snug(primitive_urdf):
    robot = CellRobot(Spec(urdf="prims.urdf"), primitive_urdf)
    caps = robot.capsules({"j1": 0.0, "j2": 0.0})
    by_link = dict(zip(caps.link, caps.radius, strict=True))
    # a lone sphere is its own capsule
    assert by_link["ball"] == pytest.approx(0.06, abs=1e-6)
    i = caps.link.index("ball")
    np.testing.assert_allclose(caps.a[i], caps.b[i], atol=1e-9)
    np.testing.assert_allclose(caps.a[i], [0, 0, 0.05 + 0.6], atol=1e-9)
    # a 0.3 x 0.2 x 0.1 box along its long side: radius its cross-section's half diagonal
    assert by_link["base"] == pytest.approx(np.hypot(0.1, 0.05), rel=1e-6)


def test_the_base_places_and_turns_the_capsules(primitive_urdf):
    joints = {"j1": 0.4, "j2": 0.1}
    folder = primitive_urdf
    home = CellRobot(Spec(urdf="prims.urdf"), folder).capsules(joints)
    moved = CellRobot(Spec(urdf="prims.urdf", base_xyz_m=(1.0, 2.0, 0.5), base_yaw_deg=90.0),
                      folder).capsules(joints)  # fmt: skip
    turn = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    np.testing.assert_allclose(moved.a, home.a @ turn.T + [1.0, 2.0, 0.5], atol=1e-9)
    np.testing.assert_allclose(moved.radius, home.radius)
    hanging = CellRobot(Spec(urdf="prims.urdf", base_xyz_m=(0, 0, 3.0), upside_down=True),
                        folder).capsules(joints)  # fmt: skip
    flip = np.diag([1.0, -1.0, -1.0])  # turned about x by pi
    np.testing.assert_allclose(hanging.b, home.b @ flip.T + [0, 0, 3.0], atol=1e-9)
    assert hanging.b[:, 2].max() < 3.0 + 1e-9


def test_joint_states_must_name_every_joint_and_no_other(primitive_urdf):
    robot = CellRobot(Spec(name="cellarm", urdf="prims.urdf"), primitive_urdf)
    assert robot.joint_names == ("j1", "j2")
    with pytest.raises(ValueError, match="cellarm: joint state lacks joint 'j2'"):
        robot.capsules({"j1": 0.0})
    with pytest.raises(ValueError, match="no joint 'j3'"):
        robot.capsules({"j1": 0.0, "j2": 0.0, "j3": 1.0})
    with pytest.raises(ValueError, match="'j1' is nan"):
        robot.capsules({"j1": float("nan"), "j2": 0.0})


def test_a_missing_urdf_names_the_file(tmp_path):
    with pytest.raises(TopsegError, match=r"arm\.urdf"):
        CellRobot(Spec(urdf="arm.urdf"), tmp_path)


def test_link_speeds_of_a_turning_joint(primitive_urdf):
    robot = CellRobot(Spec(urdf="prims.urdf"), primitive_urdf)
    a, b = {"j1": 0.0, "j2": 0.2}, {"j1": 0.1, "j2": 0.2}
    # the ball's centre is 0.2 m off the turning axis: its chord over 0.1 rad in 0.05 s
    caps = robot.capsules(a)
    fastest = max(np.hypot(*caps.a[:, :2].T).max(), np.hypot(*caps.b[:, :2].T).max())
    expected = 2 * fastest * np.sin(0.05) / 0.05
    assert robot.link_speeds(a, b, 0.05) == pytest.approx(expected, rel=1e-9)
    assert robot.link_speeds(a, a, 0.05) == 0.0
    slide = robot.link_speeds({"j1": 0.0, "j2": -0.2}, {"j1": 0.0, "j2": 0.2}, 0.5)
    assert slide == pytest.approx(0.8)
    with pytest.raises(ValueError, match="time step"):
        robot.link_speeds(a, b, 0.0)


# --- the silhouette ---------------------------------------------------------------------------

K = KINECT_V1.scaled_to(160, 120)


@pytest.mark.parametrize(
    "mount, placement",
    [
        (TopViewMount(K, 2600.0), Placement()),
        (TopViewMount(K, 2800.0, pitch_deg=7.0, roll_deg=-4.0), Placement(0.6, -0.3, 40.0)),
    ],
)
def test_the_silhouettes_points_lie_in_the_capsules(mount, placement):
    # every pixel of the robot, back-projected like a person's, is on the robot: within the
    # capsules, so the frames of robot, camera and cell agree
    robot = CellRobot(Spec(urdf="panda", base_xyz_m=(0.5, -0.2, 0.3), base_yaw_deg=30.0), ".")
    joints = robot.model.random_joints(np.random.default_rng(1))
    depth, mask = robot.silhouette(joints, mount, placement, 0.0)
    seen = depth > 0
    assert seen.sum() > 100
    np.testing.assert_array_equal(mask, seen)
    as_human = np.where(seen, labels.BODY, labels.BACKGROUND).astype(np.uint8)
    pts = human_points(depth, as_human, mount, placement)
    distance, _ = point_distances(pts.points_m, robot.capsules(joints))
    assert distance.max() <= 0.002  # depth is whole millimetres
    assert nearest(pts, robot.capsules(joints)).distance_m <= 0.002


def test_the_silhouette_of_a_radial_camera_is_range():
    robot = CellRobot(Spec(urdf="panda"), ".")
    joints = dict.fromkeys(robot.joint_names, 0.0)
    plain = TopViewMount(K, 2600.0, pitch_deg=5.0)
    radial = TopViewMount(K, 2600.0, pitch_deg=5.0, radial=True)
    depth, _ = robot.silhouette(joints, plain, Placement(), 0.0)
    ranged, _ = robot.silhouette(joints, radial, Placement(), 0.0)
    np.testing.assert_array_equal(ranged, depth_to_range(depth, K))


def test_the_mask_grows_by_the_margin_at_the_robots_depth():
    robot = CellRobot(Spec(urdf="panda"), ".")
    joints = dict.fromkeys(robot.joint_names, 0.0)
    mount = TopViewMount(K, 2600.0)
    depth, mask = robot.silhouette(joints, mount, Placement(), 0.15)
    seen = depth > 0
    z = depth[seen].min() / 1000.0
    ru, rv = 0.15 * K.fx / z, 0.15 * K.fy / z
    np.testing.assert_array_equal(mask, grow_mask_reference(seen, ru, rv))
    assert mask.sum() > seen.sum() and (mask | ~seen).all()
    with pytest.raises(ValueError, match="margin"):
        robot.silhouette(joints, mount, Placement(), -0.1)


@pytest.mark.parametrize("seed", range(6))
def test_grow_kernel_matches_the_numpy_reference(seed):
    rng = np.random.default_rng(seed)
    mask = rng.random((50, 70)) < [0.002, 0.01, 0.05, 0.0, 0.0, 0.0][seed]
    mask[0, 69] = seed == 3  # a pixel in a corner
    if seed == 4:  # a robot-like blob well inside the image: only its box is grown
        mask[20:26, 30:41] = rng.random((6, 11)) < 0.7
    if seed == 5:  # a blob against the left edge
        mask[5:40, 0:3] = True
    depth = np.where(mask, rng.integers(1500, 3000, mask.shape), 0).astype(np.uint16)
    margin = rng.uniform(0.02, 0.2)
    fx, fy = rng.uniform(50, 120, 2)
    grown = grow_mask(mask, depth, margin, fx, fy)
    if mask.any():
        z = depth[mask].min() / 1000.0
        np.testing.assert_array_equal(
            grown, grow_mask_reference(mask, margin * fx / z, margin * fy / z)
        )
    else:
        assert not grown.any()


def test_ellipse_half_widths():
    np.testing.assert_array_equal(ellipse_half_widths(2.5, 1.5), [1, 2, 1])
    np.testing.assert_array_equal(ellipse_half_widths(3.0, 3.0), [0, 2, 2, 3, 2, 2, 0])
