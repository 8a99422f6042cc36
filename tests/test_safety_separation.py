"""The separation of people from the robot (core/safety/separation.py): human pixels as
cell-frame points with their blobs, and the numba nearest-capsule kernel against its numpy
reference (tests/reference.py)."""

from __future__ import annotations

import numpy as np
import pytest
from reference import capsule_distances_reference, label4_reference

from topseg.core import labels
from topseg.core.camera import KINECT_V1, TopViewMount, depth_to_range
from topseg.core.safety.cell import CameraPlacement
from topseg.core.safety.separation import (
    Capsules,
    HumanPoints,
    human_points,
    label4,
    nearest,
    point_distances,
)
from topseg.core.synth.geometry import BOX, SPHERE
from topseg.core.synth.render import Primitives, raycast


def Placement(x_m: float = 0.0, y_m: float = 0.0, yaw_deg: float = 0.0) -> CameraPlacement:
    """The cell file's camera placement, by position."""
    return CameraPlacement(x_m=x_m, y_m=y_m, yaw_deg=yaw_deg)


def _random_capsules(rng, m):
    a = rng.uniform(-1, 1, (m, 3))
    b = a + rng.uniform(-0.4, 0.4, (m, 3))
    b[: m // 4] = a[: m // 4]  # some spheres
    return Capsules(a, b, rng.uniform(0.0, 0.2, m), tuple(f"link{i}" for i in range(m)))


def _points(cell_points, part=None, blob=None) -> HumanPoints:
    n = len(cell_points)
    return HumanPoints(
        points_m=np.asarray(cell_points, np.float64),
        part=np.full(n, labels.HAND, np.uint8) if part is None else np.asarray(part, np.uint8),
        rows=np.zeros(n, np.int32),
        cols=np.arange(n, dtype=np.int32),
        blob=np.zeros(n, np.int32) if blob is None else np.asarray(blob, np.int32),
        blob_count=1 if blob is None else int(np.max(blob)) + 1,
        shape=(1, max(n, 1)),
    )


@pytest.mark.parametrize("seed", range(5))
def test_kernel_matches_the_numpy_reference(seed):
    rng = np.random.default_rng(seed)
    caps = _random_capsules(rng, int(rng.integers(1, 40)))
    points = rng.uniform(-1.5, 1.5, (2000, 3))
    distance, index = point_distances(points, caps)
    ref_distance, ref_index = capsule_distances_reference(points, caps.a, caps.b, caps.radius)
    np.testing.assert_allclose(distance, ref_distance, rtol=0, atol=1e-12)
    # the index may differ only where two capsules are equally near
    differs = index != ref_index
    assert differs.sum() <= 2
    assert (distance >= 0).all() and (distance == 0).any()


def test_points_inside_a_capsule_are_at_zero_and_outside_at_their_gap():
    caps = Capsules(np.array([[0.0, 0, 1]]), np.array([[1.0, 0, 1]]), np.array([0.1]), ("l",))
    pts = np.array([[0.5, 0, 1], [0.5, 0.05, 1.0], [0.5, 0.5, 1], [-0.3, 0, 1], [1.0, 0, 1.25]])
    distance, _ = point_distances(pts, caps)
    np.testing.assert_allclose(distance, [0, 0, 0.4, 0.2, 0.15], atol=1e-12)


def test_nearest_names_the_pair_and_every_blob():
    caps = Capsules(
        np.array([[0.0, 0, 1], [2.0, 0, 1]]), np.array([[0.0, 0, 1.5], [2.0, 0, 1]]),
        np.array([0.1, 0.2]), ("link2", "link5"),
    )  # fmt: skip
    pts = [[0.5, 0, 1.2], [0.0, 0.4, 1.4], [2.0, 0.7, 1.0], [2.0, -0.6, 1.0], [2.0, 3.0, 1.0]]
    near = nearest(
        _points(pts, part=[labels.HEAD, labels.HAND, labels.BODY, labels.LEGS, labels.HAND],
                blob=[0, 0, 1, 1, 1]),
        caps,
    )  # fmt: skip
    assert near.distance_m == pytest.approx(0.3)
    assert (near.part, near.link) == (labels.HAND, "link2")
    np.testing.assert_allclose(near.point_m, [0.0, 0.4, 1.4])
    np.testing.assert_allclose(near.link_point_m, [0.0, 0.1, 1.4], atol=1e-12)
    assert [(p.blob, p.part, p.link, p.pixel_count) for p in near.per_person] == [
        (0, labels.HAND, "link2", 2), (1, labels.LEGS, "link5", 3),
    ]  # fmt: skip
    assert [p.distance_m for p in near.per_person] == pytest.approx([0.3, 0.4])


@pytest.mark.parametrize("seed", range(3))
def test_the_link_point_is_on_the_capsule_at_the_distance(seed):
    rng = np.random.default_rng(seed)
    caps = _random_capsules(rng, 12)
    pts = rng.uniform(-3, 3, (50, 3))
    near = nearest(_points(pts), caps)
    assert np.linalg.norm(near.point_m - near.link_point_m) == pytest.approx(near.distance_m)
    d_surface, _ = point_distances(near.link_point_m[None], caps)
    assert d_surface[0] == pytest.approx(0.0, abs=1e-9)


def test_nothing_to_measure_is_none():
    caps = _random_capsules(np.random.default_rng(0), 3)
    assert nearest(_points(np.zeros((0, 3))), caps) is None
    empty = Capsules(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), ())
    assert nearest(_points([[0.0, 0, 0]]), empty) is None


@pytest.mark.parametrize("seed", range(4))
def test_blobs_match_scipys_components(seed):
    rng = np.random.default_rng(seed)
    mask = rng.random((60, 80)) < [0.3, 0.5, 0.6, 0.05][seed]
    ids, count = label4(mask)
    ref_ids, ref_count = label4_reference(mask)
    assert count == ref_count
    np.testing.assert_array_equal(ids, ref_ids)


# --- human points from a rendered frame -----------------------------------------------------

K = KINECT_V1.scaled_to(160, 120)


def _scene_frame(mount, placement, hand_cell, head_cell):
    """A hand (sphere) and a head (box) placed in the cell, rendered by the camera."""
    centres = placement.to_camera_world(np.array([hand_cell, head_cell]))
    prims = Primitives(
        np.array([SPHERE, BOX], np.int32),
        np.array([[0.08, 0, 0], [0.1, 0.1, 0.1]]),
        centres,
        np.repeat(np.eye(3)[None], 2, 0),
        np.array([labels.HAND, labels.HEAD], np.uint8),
    )
    floor = Primitives(
        np.array([BOX], np.int32), np.array([[20.0, 20.0, 0.01]]), np.array([[0.0, 0, -0.01]]),
        np.eye(3)[None], np.array([labels.BACKGROUND], np.uint8),
    )  # fmt: skip
    return raycast(Primitives.concat([prims, floor]), mount)


@pytest.mark.parametrize(
    "mount, placement",
    [
        (TopViewMount(K, 3000.0), Placement()),
        (TopViewMount(K, 3200.0, pitch_deg=8.0, roll_deg=-5.0), Placement(1.5, -0.7, 35.0)),
    ],
)
def test_human_points_land_where_the_parts_are_in_the_cell(mount, placement):
    hand, head = placement.to_cell(np.array([[0.4, -0.2, 1.1], [-0.3, 0.25, 1.6]]))
    depth, lab = _scene_frame(mount, placement, hand, head)
    pts = human_points(depth, lab, mount, placement)
    assert pts.blob_count == 2 and set(np.unique(pts.part)) == {labels.HAND, labels.HEAD}
    hand_pts = pts.points_m[pts.part == labels.HAND]
    # every visible hand point is on the sphere's upper surface (depth is rounded to mm)
    np.testing.assert_allclose(np.linalg.norm(hand_pts - hand, axis=1), 0.08, atol=0.004)
    head_pts = pts.points_m[pts.part == labels.HEAD]
    # the box stands square to the camera's world frame
    in_box = placement.to_camera_world(head_pts) - placement.to_camera_world(head)
    assert np.all(np.abs(in_box) <= 0.1 + 0.004)
    assert len(np.unique(pts.blob[pts.part == labels.HAND])) == 1
    np.testing.assert_array_equal(lab[pts.rows, pts.cols], pts.part)
    assert pts.pixel_index.max() < K.width * K.height


def test_a_radial_camera_gives_the_same_points():
    mount = TopViewMount(K, 3000.0, pitch_deg=5.0)
    radial = TopViewMount(K, 3000.0, pitch_deg=5.0, radial=True)
    depth, lab = _scene_frame(mount, Placement(), (0.6, 0.4, 1.0), (-0.5, 0.2, 1.5))
    plain = human_points(depth, lab, mount, Placement())
    ranged = human_points(depth_to_range(depth, K), lab, radial, Placement())
    np.testing.assert_allclose(ranged.points_m, plain.points_m, atol=0.002)


def test_pixels_without_depth_and_other_labels_are_left_out():
    depth = np.full(K.shape, 2000, np.uint16)
    lab = np.zeros(K.shape, np.uint8)
    lab[10:20, 10:20] = labels.BODY
    lab[10:20, 30:40] = labels.ROBOT
    depth[10:20, 15:20] = 0
    pts = human_points(depth, lab, TopViewMount(K, 3000.0), Placement())
    assert len(pts) == 50 and pts.blob_count == 1
    assert (pts.cols < 15).all()


def test_frames_of_the_wrong_size_are_refused():
    with pytest.raises(ValueError, match="camera's"):
        human_points(
            np.zeros((10, 10), np.uint16), np.zeros((10, 10), np.uint8),
            TopViewMount(K, 3000.0), Placement(),
        )  # fmt: skip
