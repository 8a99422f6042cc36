"""Procedural top-view scenes: the analytic render is exact, frames are well formed."""

import numpy as np
import pytest

from topseg.core import labels
from topseg.core.camera import KINECT_V1, PAPER_MOUNT, Intrinsics, TopViewMount
from topseg.core.synth import procedural

SMALL = TopViewMount(KINECT_V1.scaled_to(160, 120), PAPER_MOUNT.height_mm)


def world_points(depth_m, mount):
    """(H, W, 3) world points of a float depth image in metres."""
    k = mount.intrinsics
    v, u = np.indices(k.shape, dtype=np.float64)
    cam = np.stack([(u - k.cx) / k.fx * depth_m, (v - k.cy) / k.fy * depth_m, depth_m], axis=-1)
    return mount.camera_to_world(cam)


def surface_distance(prim, p):
    """Distance (m) from points p (..., 3) to the surface of a primitive."""
    x, y, z = p[..., 0] - prim.x, p[..., 1] - prim.y, p[..., 2]
    if isinstance(prim, procedural.Box):
        c, s = np.cos(prim.yaw), np.sin(prim.yaw)
        lx, ly = c * x + s * y, -s * x + c * y
        out = np.maximum.reduce(
            [
                np.abs(lx) - prim.sx / 2,
                np.abs(ly) - prim.sy / 2,
                np.abs(z - prim.height / 2) - prim.height / 2,
            ]
        )
        return np.abs(out)
    if isinstance(prim, procedural.Cylinder):
        rad = np.hypot(x, y)
        half = (prim.z1 - prim.z0) / 2
        return np.abs(np.maximum(rad - prim.radius, np.abs(z - (prim.z0 + half)) - half))
    return np.abs(np.sqrt(x**2 + y**2 + (z - prim.z) ** 2) - prim.radius)


@pytest.mark.parametrize("seed", range(4))
def test_every_pixel_lies_on_the_surface_it_is_labelled_with(seed):
    rng = np.random.default_rng(seed)
    mount = SMALL
    prims = procedural.random_scene(rng, mount, n_objects=6)
    depth_m, lab = procedural.render(prims, mount)
    p = world_points(depth_m, mount)
    floor = lab == labels.BACKGROUND
    np.testing.assert_allclose(p[floor][:, 2], 0.0, atol=1e-9)
    covered = np.zeros(lab.shape, bool)
    for prim in prims:
        on = surface_distance(prim, p) < 1e-7
        covered |= on & (lab == prim.label)
    assert covered[~floor].all()
    # and every object pixel is nearer than the floor
    assert np.all(depth_m[~floor] < mount.height_mm / 1000.0)


def test_closed_form_depths_on_the_optical_axis():
    k = Intrinsics(width=64, height=48, fx=60.0, fy=60.0, cx=32.0, cy=24.0)
    mount = TopViewMount(k, 3500.0)
    axis = (24, 32)
    box = procedural.Box(0.0, 0.0, 0.5, 0.4, 0.3, 0.75, labels.TABLE)
    sph = procedural.Sphere(0.0, 0.0, 1.6, 0.12, labels.HEAD)
    cyl = procedural.Cylinder(0.0, 0.0, 0.2, 0.0, 1.4, labels.BODY)
    assert procedural.hit_depth_m(box, mount)[axis] == pytest.approx(3.5 - 0.75, abs=1e-12)
    assert procedural.hit_depth_m(sph, mount)[axis] == pytest.approx(3.5 - 1.72, abs=1e-12)
    assert procedural.hit_depth_m(cyl, mount)[axis] == pytest.approx(3.5 - 1.4, abs=1e-12)
    depth_m, lab = procedural.render([cyl, sph], mount)
    assert lab[axis] == labels.HEAD and depth_m[axis] == pytest.approx(1.78)
    # a box far off to the side shows its wall: some pixels are deeper than its top
    side = procedural.Box(1.2, 0.0, 0.3, 0.3, 0.0, 1.5, labels.STORAGE)
    t = procedural.hit_depth_m(side, mount)
    seen = np.isfinite(t)
    assert seen.any() and t[seen].max() > 3.5 - 1.5 + 0.1


def test_procedural_frame_is_well_formed_and_seeded():
    d1, l1 = procedural.procedural_frame(np.random.default_rng(3), SMALL)
    d2, l2 = procedural.procedural_frame(np.random.default_rng(3), SMALL)
    np.testing.assert_array_equal(d1, d2)
    np.testing.assert_array_equal(l1, l2)
    assert d1.shape == l1.shape == SMALL.intrinsics.shape
    assert d1.dtype == np.uint16 and l1.dtype == np.uint8
    kinds = {lab for ids in procedural.KINDS.values() for lab in ids} | {labels.BACKGROUND}
    assert set(np.unique(l1).tolist()) <= kinds
    assert labels.HEAD in l1 and labels.BODY in l1  # every scene has a person


def test_noise_and_missing_pixels():
    rng = np.random.default_rng(0)
    depth, lab = procedural.procedural_frame(
        rng, PAPER_MOUNT, noise_sigma_mm=15.0, missing_fraction=0.05
    )
    floor = (lab == labels.BACKGROUND) & (depth > 0)
    err = depth[floor].astype(float) - PAPER_MOUNT.height_mm
    assert abs(err.mean()) < 1.0 and 13.5 < err.std() < 16.5
    missing = depth == 0
    assert 0.04 < missing.mean() < 0.06
    np.testing.assert_array_equal(missing, lab == labels.NO_DEPTH)
    clean, _ = procedural.procedural_frame(rng, SMALL, noise_sigma_mm=0.0)
    assert np.all(clean > 0)
    with pytest.raises(ValueError, match="missing_fraction"):
        procedural.procedural_frame(rng, SMALL, missing_fraction=1.0)
    with pytest.raises(ValueError, match="unknown shape kind"):
        procedural.random_object(rng, "sofa")
