"""Triangles in the ray caster: against the plain-numpy Moller-Trumbore reference on random
triangles (straight down and tilted), and a box as 12 triangles against the box primitive."""

from __future__ import annotations

import numpy as np
import pytest
import reference

from topseg.core import labels
from topseg.core.camera import PAPER_MOUNT, Intrinsics, TopViewMount
from topseg.core.synth import render
from topseg.core.synth.geometry import BOX, quat_from_axis_angle, quat_to_matrix

SMALL = TopViewMount(Intrinsics(160, 120, 142.6, 142.6, 79.5, 59.5), 3500.0)
MOUNTS = [
    SMALL,
    TopViewMount(Intrinsics(128, 106, 91.25, 91.25, 63.5, 52.5), 2400.0, 10.0, -10.0),
    TopViewMount(Intrinsics(160, 100, 110.3, 110.3, 79.5, 49.5), 4500.0, -7.5, 4.0),
]
MOUNT_IDS = ["straight-3.5m", "tilted-2.4m", "tilted-4.5m"]


def floor_and_boxes(rng: np.random.Generator, n: int) -> render.Primitives:
    """A floor and `n` random boxes that triangles can hide behind or stand in front of."""
    size = rng.uniform(0.05, 0.3, (n, 3))
    center = np.stack(
        [rng.uniform(-1.5, 1.5, n), rng.uniform(-1.0, 1.0, n), rng.uniform(0.0, 1.5, n)], 1
    )
    return render.Primitives(
        np.array([BOX] * (n + 1), np.int32),
        np.concatenate([[[10.0, 10.0, 0.05]], size]),
        np.concatenate([[[0.0, 0.0, -0.05]], center]),
        np.repeat(np.eye(3)[None], n + 1, 0),
        np.concatenate([[labels.BACKGROUND], rng.integers(7, 11, n)]).astype(np.uint8),
    )


def random_triangles(rng: np.random.Generator, n: int) -> render.Triangles:
    """`n` triangles of random size and slant over the floor, a few big ones among them."""
    centre = np.stack(
        [rng.uniform(-1.5, 1.5, n), rng.uniform(-1.1, 1.1, n), rng.uniform(0.0, 2.0, n)], 1
    )
    spread = rng.uniform(0.02, 0.4, n)
    spread[: n // 10] = 0.8  # a few big ones, low over the floor
    centre[: n // 10, 2] = 0.2
    vertices = centre[:, None, :] + rng.normal(size=(n, 3, 3)) * spread[:, None, None]
    return render.Triangles(vertices, rng.integers(1, 13, n).astype(np.uint8))


@pytest.mark.parametrize("mount", MOUNTS, ids=MOUNT_IDS)
@pytest.mark.parametrize("seed", [0, 1])
def test_triangles_match_the_moller_trumbore_reference(mount, seed):
    rng = np.random.default_rng(seed)
    prims = floor_and_boxes(rng, 8)
    tris = random_triangles(rng, 60)
    depth, lab = render.raycast_m(prims, mount, tris)
    ref_depth, ref_lab = reference.raycast_triangles_reference(prims, tris, mount)
    hit = np.isfinite(ref_depth)
    assert np.array_equal(np.isfinite(depth), hit)
    np.testing.assert_allclose(depth[hit], ref_depth[hit], rtol=0, atol=1e-9)
    assert np.array_equal(lab, ref_lab)
    # triangles really take part: they take many pixels from the primitives
    _, prims_lab = render.raycast_m(prims, mount)
    assert np.mean(lab != prims_lab) > 0.1 and len(np.unique(lab)) > 6


@pytest.mark.parametrize("mount", MOUNTS, ids=MOUNT_IDS)
def test_long_thin_triangles_match_the_reference(mount):
    """Slivers across many rows and columns: each row tests only its chord of the triangle,
    so a chord cut short would lose pixels the reference keeps."""
    rng = np.random.default_rng(7)
    n = 80
    a = np.stack([rng.uniform(-1.5, 1.5, n), rng.uniform(-1.1, 1.1, n), rng.uniform(0, 1.5, n)], 1)
    b = a + rng.normal(size=(n, 3)) * 1.2
    c = a + (b - a) * rng.uniform(0.2, 0.8, (n, 1)) + rng.normal(size=(n, 3)) * 0.01
    tris = render.Triangles(np.stack([a, b, c], 1), rng.integers(1, 13, n).astype(np.uint8))
    prims = floor_and_boxes(rng, 0)
    depth, lab = render.raycast_m(prims, mount, tris)
    ref_depth, ref_lab = reference.raycast_triangles_reference(prims, tris, mount)
    np.testing.assert_allclose(depth, ref_depth, rtol=0, atol=1e-9)
    assert np.array_equal(lab, ref_lab)
    assert np.mean(lab != labels.BACKGROUND) > 0.01  # the slivers cover many pixels


def test_triangles_that_reach_behind_the_camera_match_the_reference():
    rng = np.random.default_rng(3)
    tris = random_triangles(rng, 20)
    # corners above the camera (3.5 m): straddling the near plane or wholly behind it
    tris.vertices[:5, 0, 2] = 4.0
    tris.vertices[5:8, :, 2] = 3.8
    prims = floor_and_boxes(rng, 0)
    depth, lab = render.raycast_m(prims, SMALL, tris)
    ref_depth, ref_lab = reference.raycast_triangles_reference(prims, tris, SMALL)
    np.testing.assert_allclose(depth, ref_depth, rtol=0, atol=1e-9)
    assert np.array_equal(lab, ref_lab)


def box_triangles(half, center, rot, label) -> render.Triangles:
    """A box as the 12 triangles of its 6 faces, world frame."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    faces = [  # corner indices (x * 4 + y * 2 + z) of each face, as two triangles
        (0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1),
        (2, 3, 7), (2, 7, 6), (0, 2, 6), (0, 6, 4), (1, 5, 7), (1, 7, 3),
    ]  # fmt: skip
    world = (corners * half) @ rot.T + center
    return render.Triangles(world[np.array(faces)], np.full(12, label, np.uint8))


@pytest.mark.parametrize("mount", [PAPER_MOUNT, *MOUNTS[1:]], ids=["paper", *MOUNT_IDS[1:]])
def test_a_box_as_12_triangles_renders_as_the_box_primitive(mount):
    half = np.array([0.31, 0.17, 0.42])
    center = np.array([0.123, -0.211, 0.61])
    rot = quat_to_matrix(quat_from_axis_angle((0.3, -0.5, 1.0), 0.7))
    floor = floor_and_boxes(np.random.default_rng(0), 0)
    as_box = render.Primitives.concat(
        [
            floor,
            render.Primitives(
                np.array([BOX], np.int32), half[None], center[None], rot[None],
                np.array([labels.ROBOT], np.uint8),
            ),
        ]
    )  # fmt: skip
    box_depth, box_lab = render.raycast(as_box, mount)
    tris = box_triangles(half, center, rot, labels.ROBOT)
    tri_depth, tri_lab = render.raycast(floor, mount, tris)
    assert (box_lab == labels.ROBOT).sum() > 100
    assert np.array_equal(tri_lab, box_lab)
    assert np.array_equal(tri_depth, box_depth)


def test_no_triangles_change_nothing_and_concat_keeps_order():
    prims = floor_and_boxes(np.random.default_rng(4), 5)
    plain = render.raycast(prims, SMALL)
    for none in (None, render.Triangles.empty(), render.Triangles.concat([])):
        with_none = render.raycast(prims, SMALL, none)
        assert all(np.array_equal(a, b) for a, b in zip(plain, with_none, strict=True))
    a = random_triangles(np.random.default_rng(5), 3)
    b = random_triangles(np.random.default_rng(6), 2)
    both = render.Triangles.concat([a, render.Triangles.empty(), b])
    assert len(both) == 5 and both.vertices.shape == (5, 3, 3) and both.label.dtype == np.uint8
    assert np.array_equal(both.vertices[3:], b.vertices)
    assert np.array_equal(both.label, np.concatenate([a.label, b.label]))


def test_a_triangle_hides_a_primitive_only_when_nearer():
    floor = floor_and_boxes(np.random.default_rng(0), 0)
    k = SMALL.intrinsics
    # a big flat triangle at 1 m above the floor and the floor under it
    tri = render.Triangles(
        np.array([[[-3.0, -3.0, 1.0], [3.0, -3.0, 1.0], [0.0, 3.0, 1.0]]]), np.array([12], np.uint8)
    )
    depth, lab = render.raycast(floor, SMALL, tri)
    centre = (int(k.cy), int(k.cx))
    assert lab[centre] == 12 and depth[centre] == 2500
    below = render.Triangles(tri.vertices - [0.0, 0.0, 1.5], tri.label)  # under the floor
    depth, lab = render.raycast(floor, SMALL, below)
    assert lab[centre] == labels.BACKGROUND and depth[centre] == 3500
