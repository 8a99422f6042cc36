"""The robot's own surface (core/safety/surface.py): point-to-triangle and point-to-primitive
kernels against numpy references, the capsule-bounded search against every shape, and the
separation it gives against the rendered sequences' truth (trimesh on tessellated shapes)."""

from __future__ import annotations

import numpy as np
import pytest
from reference import primitive_distances_reference, triangle_distances_reference

from topseg.core import labels
from topseg.core.safety.cell import RobotSpec
from topseg.core.safety.robot import CellRobot
from topseg.core.safety.separation import HumanPoints, nearest, point_distances
from topseg.core.safety.surface import (
    posed_surface,
    primitive_closest,
    refine,
    surface_layout,
    triangle_closest,
)
from topseg.core.synth import body_distance
from topseg.core.synth.geometry import BOX, CAPSULE, CYLINDER, SPHERE, quat_to_matrix
from topseg.core.synth.render import Primitives, Triangles


def _random_rotation(rng) -> np.ndarray:
    q = rng.normal(size=4)
    return quat_to_matrix(q / np.linalg.norm(q))


@pytest.mark.parametrize("seed", range(4))
def test_triangle_kernel_matches_the_numpy_reference(seed):
    rng = np.random.default_rng(seed)
    tris = rng.uniform(-1, 1, (30, 3, 3))
    tris[0, 2] = tris[0, 0]  # a triangle that is a segment
    tris[1, 1] = tris[1, 2] = tris[1, 0]  # and one that is a point
    tris[2, 2] = 2 * tris[2, 1] - tris[2, 0]  # and three corners on one line
    points = np.concatenate([rng.uniform(-1.5, 1.5, (300, 3)), tris.mean(axis=1)])
    ref = triangle_distances_reference(points, tris)
    got = np.empty_like(ref)
    closest = np.empty((*ref.shape, 3))
    q = np.empty(3)
    for i, p in enumerate(points):
        for t, tri in enumerate(tris):
            got[i, t] = triangle_closest(p[0], p[1], p[2], tri, q)
            closest[i, t] = q
    np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(
        np.linalg.norm(points[:, None] - closest, axis=-1), got, rtol=1e-6, atol=1e-12
    )
    # the closest point is on the triangle: its own distance to it is 0
    for t, tri in enumerate(tris):
        assert triangle_distances_reference(closest[:, t], tri[None]).max() < 1e-9


@pytest.mark.parametrize("kind", [BOX, CYLINDER, SPHERE, CAPSULE])
@pytest.mark.parametrize("seed", range(3))
def test_primitive_kernel_matches_the_numpy_reference(kind, seed):
    rng = np.random.default_rng(seed)
    size = np.array([*rng.uniform(0.05, 0.4, 2), rng.uniform(0.05, 0.4)])
    centre, rot = rng.uniform(-1, 1, 3), _random_rotation(rng)
    points = centre + np.concatenate(
        [rng.uniform(-1, 1, (400, 3)), rng.uniform(-0.025, 0.025, (20, 3))]
    )
    ref = primitive_distances_reference(points, kind, size, centre, rot)
    assert (ref == 0).any() and (ref > 0).any()  # points inside and outside
    q = np.empty(3)
    for p, expect in zip(points, ref, strict=True):
        d = primitive_closest(p[0], p[1], p[2], kind, size, centre, rot, q)
        assert d == pytest.approx(expect, abs=1e-9)
        assert np.linalg.norm(p - q) == pytest.approx(d, abs=1e-12)
        on = primitive_distances_reference(q[None], kind, size, centre, rot)[0]
        assert on < 1e-9  # the closest point is on (or, inside, in) the primitive


def _panda(joints_seed: int = 0):
    robot = CellRobot(RobotSpec(name="arm", urdf="panda", base_xyz_m=(0.3, -0.2, 0.5)), ".")
    rng = np.random.default_rng(joints_seed)
    q = rng.uniform(robot.model.lower, robot.model.upper)
    return robot, dict(zip(robot.joint_names, q, strict=True))


def _brute_force(robot: CellRobot, joints, points):
    """Every point against every triangle and primitive of the posed links: (n,) distance
    and the link name of the nearest shape."""
    prims, tris = robot.model.link_geometry(joints, robot.base_pos, robot.base_quat)
    links, tri_link, prim_link = robot.model.shape_links()
    d = [triangle_distances_reference(points, tris.vertices)] if len(tris.vertices) else []
    owner = [tri_link] if len(tris.vertices) else []
    for i in range(len(prims)):
        one = primitive_distances_reference(
            points, prims.kind[i], prims.size[i], prims.center[i], prims.rot[i]
        )
        d.append(one[:, None])
        owner.append(np.array([prim_link[i]]))
    d, owner = np.concatenate(d, axis=1), np.concatenate(owner)
    best = d.argmin(axis=1)
    return d[np.arange(len(points)), best], [links[k] for k in owner[best]]


@pytest.mark.parametrize("seed", range(3))
def test_refine_finds_every_blobs_nearest_point_as_the_brute_force_does(seed):
    robot, joints = _panda(seed)
    rng = np.random.default_rng(100 + seed)
    points = robot.base_pos + rng.uniform(-0.9, 0.9, (400, 3)) + [0, 0, 0.4]
    blob = rng.integers(0, 5, len(points))
    lower, _ = point_distances(points, robot.capsules(joints))
    got = refine(robot.surface(joints), points, blob, lower)
    ref, ref_link = _brute_force(robot, joints, points)
    assert (lower <= ref + 1e-12).all()  # the capsules bound the robot
    finite = np.isfinite(got.distance_m)
    np.testing.assert_allclose(got.distance_m[finite], ref[finite], atol=1e-9)
    links = robot.surface(joints).links
    assert [links[k] for k in got.link[finite]] == [ref_link[i] for i in np.flatnonzero(finite)]
    for b in range(5):
        mine = blob == b
        assert got.distance_m[mine].min() == pytest.approx(ref[mine].min(), abs=1e-9)
    # a surface point is the robot's own, at the distance
    on, _ = _brute_force(robot, joints, got.surface_point_m[finite])
    assert on.max() < 1e-9
    np.testing.assert_allclose(
        np.linalg.norm(points[finite] - got.surface_point_m[finite], axis=1),
        got.distance_m[finite],
        atol=1e-12,
    )
    # the search skips most points: only the band between capsules and links is measured
    assert finite.sum() < len(points) / 2


def test_the_separation_is_the_truths_not_the_capsules():
    """Against `body_distance` (the rendered sequences' truth: trimesh on the shapes
    tessellated), within its tessellation's tolerance; the capsules alone read nearer."""
    robot, joints = _panda(7)
    rng = np.random.default_rng(7)
    points = robot.base_pos + rng.uniform(-0.8, 0.8, (300, 3)) + [0, 0, 0.4]
    prims, tris = robot.model.link_geometry(joints, robot.base_pos, robot.base_quat)
    links, tri_link, prim_link = robot.model.shape_links()
    truth_surface = body_distance.robot_surface(prims, prim_link, tris, tri_link, links)
    truth, _, _ = body_distance.closest_points(truth_surface, points)
    points, truth = points[truth > 0.1], truth[truth > 0.1]  # a person a hand's width off
    human = HumanPoints(
        points_m=points,
        part=np.full(len(points), labels.HAND, np.uint8),
        rows=np.zeros(len(points), np.int32),
        cols=np.arange(len(points), dtype=np.int32),
        blob=np.zeros(len(points), np.int32),
        blob_count=1,
        shape=(1, len(points)),
    )
    capsules = robot.capsules(joints)
    exact = nearest(human, capsules, robot.surface(joints))
    bounded = nearest(human, capsules)
    assert exact.distance_m == pytest.approx(truth.min(), abs=2e-4)
    assert bounded.distance_m < exact.distance_m - 0.005
    assert np.linalg.norm(exact.point_m - exact.link_point_m) == pytest.approx(exact.distance_m)
    assert exact.per_person[0].distance_m == exact.distance_m
    assert exact.link == exact.per_person[0].link


def test_a_link_with_shapes_needs_a_capsule():
    tri = Triangles(np.zeros((1, 3, 3)), np.zeros(1, np.uint8))
    with pytest.raises(ValueError, match="'b' has shapes and no bounding capsule"):
        surface_layout(Primitives.empty(), np.zeros(0), tri, np.array([1]), ("a", "b"), ("a",))


def test_a_surface_posed_twice_keeps_its_layout():
    robot, joints = _panda(1)
    first, again = robot.surface(joints), robot.surface(dict(joints))
    assert first.links == again.links and np.array_equal(first.triangles, again.triangles)
    moved = {name: value + 0.1 for name, value in joints.items()}
    prims, tris = robot.model.link_geometry(
        robot.check_joints(moved), robot.base_pos, robot.base_quat
    )
    layout = robot._layout
    posed = posed_surface(layout, prims, tris, robot.capsules(moved))
    assert not np.array_equal(posed.triangles, first.triangles)
    np.testing.assert_allclose(posed.triangles, robot.surface(moved).triangles)
