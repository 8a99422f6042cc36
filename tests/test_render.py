"""The numba ray caster: against its plain-numpy reference on random primitives, and against
geometry worked out by hand (a box and a cylinder of known size and place)."""

from __future__ import annotations

import numpy as np
import pytest
import reference

from topseg.core import labels
from topseg.core.camera import (
    PAPER_MOUNT,
    Intrinsics,
    TopViewMount,
    metres_to_mm,
    metres_to_mm_scalar,
)
from topseg.core.synth import render
from topseg.core.synth.geometry import (
    BOX,
    CAPSULE,
    CYLINDER,
    SPHERE,
    quat_from_axis_angle,
    quat_to_matrix,
)

SMALL = TopViewMount(Intrinsics(160, 120, 142.6, 142.6, 79.5, 59.5), 3500.0)


def random_primitives(rng: np.random.Generator, n: int) -> render.Primitives:
    kind = rng.integers(0, 4, n).astype(np.int32)
    size = np.zeros((n, 3))
    size[:, 0] = rng.uniform(0.03, 0.4, n)
    size[:, 1] = rng.uniform(0.03, 0.5, n)
    size[:, 2] = rng.uniform(0.03, 0.4, n)
    rot = np.array(
        [
            quat_to_matrix(quat_from_axis_angle(rng.normal(size=3), rng.uniform(0, np.pi)))
            for _ in range(n)
        ]
    )
    # some upright (a ray along the axis is the hard case for cylinders)
    rot[: n // 4] = np.eye(3)
    center = np.stack(
        [rng.uniform(-1.8, 1.8, n), rng.uniform(-1.3, 1.3, n), rng.uniform(0.0, 2.2, n)], 1
    )
    lab = rng.integers(1, 11, n).astype(np.uint8)
    floor = render.Primitives(
        np.array([BOX], np.int32),
        np.array([[10.0, 10.0, 0.05]]),
        np.array([[0.0, 0.0, -0.05]]),
        np.eye(3)[None],
        np.array([0], np.uint8),
    )
    return render.Primitives.concat([floor, render.Primitives(kind, size, center, rot, lab)])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_numba_kernel_matches_numpy_reference(seed):
    prims = random_primitives(np.random.default_rng(seed), 40)
    depth, lab = render.raycast_m(prims, SMALL)
    ref_depth, ref_lab = reference.raycast_reference(prims, SMALL)
    assert np.array_equal(lab, ref_lab)
    hit = np.isfinite(ref_depth)
    assert np.array_equal(np.isfinite(depth), hit)
    np.testing.assert_allclose(depth[hit], ref_depth[hit], rtol=0, atol=1e-9)
    assert len(np.unique(lab)) > 5  # the scene really has many labels in view


def test_every_kind_is_hit_where_the_reference_hits_it():
    rng = np.random.default_rng(9)
    for kind in (SPHERE, CAPSULE, BOX, CYLINDER):
        prims = random_primitives(rng, 12)
        prims.kind[1:] = kind
        _depth, lab = render.raycast_m(prims, SMALL)
        _ref_depth, ref_lab = reference.raycast_reference(prims, SMALL)
        assert np.array_equal(lab, ref_lab)
        assert np.mean(lab != labels.BACKGROUND) > 0.02


def _one(kind, size, center, rot=None, label=labels.TABLE) -> render.Primitives:
    rot = np.eye(3) if rot is None else rot
    return render.Primitives(
        np.array([kind], np.int32),
        np.array([size], float),
        np.array([center], float),
        rot[None],
        np.array([label], np.uint8),
    )


def test_a_box_of_known_size_and_place_gives_its_footprint_and_depth():
    mount = PAPER_MOUNT
    k = mount.intrinsics
    x0, x1, y0, y1, top = 0.40, 1.00, 0.25, 0.65, 0.80  # world metres; the box stands on the floor
    box = _one(
        BOX, ((x1 - x0) / 2, (y1 - y0) / 2, top / 2), ((x0 + x1) / 2, (y0 + y1) / 2, top / 2)
    )
    depth, lab = render.raycast(box, mount)
    # by hand: pixel (u, v) sees the box when its ray, at some depth z in [H - top, H], passes
    # inside [x0, x1] x [y0, y1]; the depth is the smallest such z
    H = mount.height_mm / 1000.0
    v, u = np.indices(k.shape, dtype=float)
    a, b = (u - k.cx) / k.fx, -(v - k.cy) / k.fy  # world x = a z, world y = b z
    zlo = np.full(k.shape, H - top)
    zhi = np.full(k.shape, H)
    for slope, lo, hi in ((a, x0, x1), (b, y0, y1)):
        with np.errstate(divide="ignore", invalid="ignore"):
            z1, z2 = lo / slope, hi / slope
        zmin = np.where(
            slope > 0, z1, np.where(slope < 0, z2, np.where((lo <= 0) & (0 <= hi), -np.inf, np.inf))
        )
        zmax = np.where(
            slope > 0, z2, np.where(slope < 0, z1, np.where((lo <= 0) & (0 <= hi), np.inf, -np.inf))
        )
        zlo, zhi = np.maximum(zlo, zmin), np.minimum(zhi, zmax)
    seen = zlo <= zhi
    assert np.array_equal(lab == labels.TABLE, seen)
    np.testing.assert_array_equal(depth[seen], np.rint(zlo[seen] * 1000).astype(np.uint16))
    # its top alone: 2.7 m away, where the pixel grid puts it
    on_top = depth == 2700
    us = np.nonzero(on_top.any(0))[0]
    assert us.min() == int(np.ceil(x0 / (H - top) * k.fx + k.cx)) and us.max() == int(
        np.floor(x1 / (H - top) * k.fx + k.cx)
    )
    assert np.all(lab[~seen] == labels.NO_DEPTH) and np.all(depth[~seen] == 0)  # no floor here


def test_an_upright_cylinder_shows_a_disc_at_its_top():
    mount = PAPER_MOUNT
    k = mount.intrinsics
    cx, cy, r, top = -0.5, 0.3, 0.25, 0.74
    depth, lab = render.raycast(
        _one(CYLINDER, (r, top / 2, 0), (cx, cy, top / 2), label=labels.PLANT), mount
    )
    z = mount.height_mm / 1000.0 - top
    v, u = np.indices(k.shape, dtype=float)
    x, y = (u - k.cx) / k.fx * z, -(v - k.cy) / k.fy * z
    disc = (x - cx) ** 2 + (y - cy) ** 2 < r * r
    assert np.all(depth[disc] == round(z * 1000))
    assert np.all(lab[disc] == labels.PLANT)
    # beyond the rim, away from the image centre, the camera sees the cylinder's wall, deeper
    wall = (lab == labels.PLANT) & ~disc
    assert wall.sum() > 0 and np.all(depth[wall] >= round(z * 1000))
    assert np.mean(depth[wall] > round(z * 1000) + 5) > 0.9


def test_screen_boxes_cull_what_is_behind_or_outside_the_camera():
    mount = PAPER_MOUNT
    prims = render.Primitives.concat(
        [
            _one(SPHERE, (0.1, 0, 0), (0.0, 0.0, 4.0)),  # above the camera
            _one(SPHERE, (0.1, 0, 0), (30.0, 0.0, 0.5)),  # far outside the view
            _one(SPHERE, (0.1, 0, 0), (0.0, 0.0, 1.0)),
        ]
    )
    c, rot = render.to_camera(prims, mount)
    boxes = render.screen_boxes(c, render._half_extents(prims.kind, prims.size, rot), mount)
    assert boxes[0, 0] > boxes[0, 1] and boxes[1, 0] > boxes[1, 1]
    assert boxes[2, 0] <= 320 <= boxes[2, 1] and boxes[2, 2] <= 240 <= boxes[2, 3]
    depth, _lab = render.raycast(prims, mount)
    assert depth[240, 320] == round((3.5 - 1.1) * 1000) or depth[239, 319] == round(
        (3.5 - 1.1) * 1000
    )


def test_metres_to_mm_rounds_half_up_and_marks_misses():
    d = np.array([[np.inf, 1.0004, 1.0006], [0.0, 70.0, 2.5], [np.nan, -np.inf, 65.535]])
    want = [[0, 1000, 1001], [0, 0, 2500], [0, 0, 65535]]
    np.testing.assert_array_equal(metres_to_mm(d), want)
    assert metres_to_mm(d).dtype == np.uint16
    assert [metres_to_mm_scalar(float(x)) for x in d.ravel()] == np.ravel(want).tolist()
    # half a millimetre rounds up (the renderer's rounding), not to even as np.rint does
    assert metres_to_mm(np.array([0.0025, 0.0035])).tolist() == [3, 4]


# --- tilted cameras and other intrinsics ----------------------------------------------------

TILTED = [
    TopViewMount(Intrinsics(128, 106, 91.25, 91.25, 63.5, 52.5), 2400.0, 10.0, -10.0, "kinect_v2"),
    TopViewMount(Intrinsics(160, 100, 110.3, 110.3, 79.5, 49.5), 4500.0, -7.5, 4.0, "oak_d"),
    TopViewMount(Intrinsics(160, 120, 96.25, 96.25, 79.5, 59.5), 3100.0, 3.0, 9.0),
]


@pytest.mark.parametrize("mount", TILTED, ids=["tof-2.4m", "oak-4.5m", "d435-3.1m"])
def test_tilted_cameras_match_both_references(mount):
    prims = random_primitives(np.random.default_rng(5), 30)
    depth, lab = render.raycast_m(prims, mount)
    for ref in (reference.raycast_reference, reference.raycast_world_reference):
        ref_depth, ref_lab = ref(prims, mount)
        hit = np.isfinite(ref_depth)
        assert np.array_equal(np.isfinite(depth), hit)
        np.testing.assert_allclose(depth[hit], ref_depth[hit], rtol=0, atol=1e-9)
        assert np.mean(lab != ref_lab) < 1e-3  # ties at exact edges only
    assert np.isfinite(depth).all()  # the floor fills every pixel, tilted or not


def _floor() -> render.Primitives:
    return _one(BOX, (10.0, 10.0, 0.05), (0.0, 0.0, -0.05), label=labels.BACKGROUND)


@pytest.mark.parametrize(
    "intr",
    [
        Intrinsics(512, 424, 365.0, 365.0, 255.5, 211.5),
        Intrinsics(640, 400, 441.25, 441.25, 319.5, 199.5),
    ],
    ids=["512x424", "640x400"],
)
@pytest.mark.parametrize("pitch,roll", [(10.0, 0.0), (0.0, -10.0), (-10.0, 10.0)])
def test_a_tilted_camera_sees_a_plane_floor_of_height_zero(intr, pitch, roll):
    mount = TopViewMount(intr, 2400.0, pitch, roll)
    depth_m, lab = render.raycast_m(_floor(), mount)
    assert np.isfinite(depth_m).all() and np.all(lab == labels.BACKGROUND)
    # a plane seen by a pinhole: 1 / depth is exactly linear in (u, v)
    v, u = np.indices(intr.shape, dtype=float)
    a = np.column_stack([u.ravel(), v.ravel(), np.ones(u.size)])
    coef, *_ = np.linalg.lstsq(a, 1.0 / depth_m.ravel(), rcond=None)
    assert np.abs(a @ coef - 1.0 / depth_m.ravel()).max() < 1e-9
    # the depth gradient points the way the camera tilts: positive pitch, farther bottom rows
    if pitch:
        assert np.sign(depth_m[-1, :].mean() - depth_m[0, :].mean()) == np.sign(pitch)
    if roll:
        assert np.sign(depth_m[:, 0].mean() - depth_m[:, -1].mean()) == np.sign(roll)
    # heights from the mount of the rendered floor are ~0 (mm rounding only)
    h = mount.height_map_mm(metres_to_mm(depth_m))
    assert np.nanmax(np.abs(h)) < 1.0
    assert np.ptp(depth_m) > 0.3  # tilted: the floor is not at one depth


def test_a_box_top_reads_its_height_through_a_tilted_mount():
    mount = TopViewMount(Intrinsics(160, 120, 96.25, 96.25, 79.5, 59.5), 3000.0, -8.0, 6.0)
    box = _one(BOX, (0.3, 0.25, 0.4), (0.1, -0.2, 0.4))
    prims = render.Primitives.concat([_floor(), box])
    depth, lab = render.raycast(prims, mount)
    h = mount.height_map_mm(depth)
    top = (lab == labels.TABLE) & (np.abs(h - 800.0) < 1.0)
    assert top.sum() > 50  # the box's top, 0.8 m above the floor, seen tilted
    assert np.nanmax(np.abs(h[lab == labels.BACKGROUND])) < 1.0


def test_screen_boxes_give_a_primitive_straddling_the_near_plane_the_whole_image():
    mount = TopViewMount(Intrinsics(160, 120, 96.25, 96.25, 79.5, 59.5), 2400.0, 10.0, 10.0)
    prims = _floor()
    c, rot = render.to_camera(prims, mount)
    ext = render._half_extents(prims.kind, prims.size, rot)
    assert c[0, 2] - ext[0, 2] < render.NEAR_M  # its camera-frame box reaches behind the camera
    assert render.screen_boxes(c, ext, mount)[0].tolist() == [0, 159, 0, 119]
