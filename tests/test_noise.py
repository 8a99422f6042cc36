"""Noise models: specs, the Gaussian's statistics, and the Kinect v1 model's kernels against
their numpy reference and each effect against its parameters."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import reference

from topseg.core import labels
from topseg.core.camera import PAPER_MOUNT, Intrinsics, TopViewMount
from topseg.core.errors import TopsegError
from topseg.core.synth import noise, render
from topseg.core.synth.geometry import BOX


def _docs_module(name: str):
    """A module of docs/ (analysis tools beside the figures they make, not in the package)."""
    path = Path(__file__).resolve().parents[1] / "docs" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


depth_stats = _docs_module("depth_stats")

SMALL = TopViewMount(Intrinsics(160, 120, 142.6, 142.6, 79.5, 59.5), 3500.0)


def _boxes(rng, mount=SMALL, n=6) -> np.ndarray:
    """A floor with `n` random boxes, ray-cast to uint16 mm, with a hole of no depth."""
    kind = np.full(n + 1, BOX, np.int32)
    size = np.vstack(
        [
            [10.0, 10.0, 0.05],
            np.column_stack([rng.uniform(0.1, 0.5, (n, 2)), rng.uniform(0.2, 0.8, n)]),
        ]
    )
    center = np.vstack(
        [
            [0, 0, -0.05],
            np.column_stack([rng.uniform(-1.5, 1.5, n), rng.uniform(-1.0, 1.0, n), size[1:, 2]]),
        ]
    )
    rot = np.repeat(np.eye(3)[None], n + 1, axis=0)
    depth, _ = render.raycast(
        render.Primitives(kind, size, center, rot, np.arange(n + 1, dtype=np.uint8)), mount
    )
    depth[:5, :7] = 0
    return depth


def test_specs_parse_and_print_back():
    assert isinstance(noise.parse_noise("none"), noise.NoNoise)
    g = noise.parse_noise("gaussian:15")
    assert isinstance(g, noise.GaussianNoise) and g.sigma_mm == 15 and g.spec == "gaussian:15"
    k = noise.parse_noise("kinect")
    assert k == noise.KinectNoise() and k.spec == "kinect"
    k2 = noise.parse_noise("kinect:edge_dropout=0.5,subpixel=4")
    assert k2.edge_dropout == 0.5 and k2.subpixel == 4
    for m in (g, k, k2, noise.NoNoise()):
        assert noise.parse_noise(m.spec) == m
    for bad, msg in (
        ("gaussian", "gaussian:<sigma_mm>"),
        ("gaussian:-3", ">= 0"),
        ("salt", "unknown noise"),
        ("kinect:wobble=1", "unknown kinect parameter"),
        ("kinect:flying=2", "probability"),
        ("kinect:flying=x", "needs a number"),
    ):
        with pytest.raises(TopsegError, match=msg):
            noise.parse_noise(bad)
    with pytest.raises(ValueError, match="uint16"):
        g.apply(np.zeros((4, 4), np.float32), np.random.default_rng(0))


def test_gaussian_noise_has_its_sigma_and_keeps_zeros():
    depth = np.full((300, 300), 3000, np.uint16)
    depth[:, :20] = 0
    for sigma in (5.0, 15.0, 100.0):
        out = noise.GaussianNoise(sigma).apply(depth, np.random.default_rng(1))
        assert np.all(out[:, :20] == 0) and np.all(out[:, 20:] > 0)
        err = out[:, 20:].astype(float) - 3000
        n = err.size
        assert abs(err.mean()) < 4 * sigma / np.sqrt(n) + 0.5
        assert err.std() == pytest.approx(np.sqrt(sigma**2 + 1 / 12), rel=0.02)  # + rounding to mm
    assert np.array_equal(noise.GaussianNoise(0).apply(depth, np.random.default_rng(2)), depth)
    a = noise.GaussianNoise(15).apply(depth, np.random.default_rng(3))
    b = noise.GaussianNoise(15).apply(depth, np.random.default_rng(3))
    assert np.array_equal(a, b)
    near = np.full((50, 50), 2, np.uint16)  # a measured pixel never turns into "no depth"
    assert noise.GaussianNoise(100).apply(near, np.random.default_rng(4)).min() >= 1


def test_hash_generator_matches_its_numpy_twin_and_is_uniform():
    seed = 123456789
    idx = np.arange(200_000)
    ref = reference.hash_uniform_np(seed, idx)
    assert ref.min() >= 0 and ref.max() < 1
    assert ref.mean() == pytest.approx(0.5, abs=0.005) and ref.var() == pytest.approx(
        1 / 12, rel=0.02
    )
    assert abs(np.corrcoef(ref[:-1], ref[1:])[0, 1]) < 0.01
    for i in (0, 1, 17, 199_999):
        assert noise._hash_uniform(np.uint64(seed), i) == ref[i]


@pytest.mark.parametrize(
    "params",
    [
        {},
        {"flying": 1.0, "edge_dropout": 0.0, "shadow_dropout": 0.0, "speckle": 0.0},
        {"edge_dropout": 1.0, "shadow_dropout": 0.3, "edge_band_px": 3, "noise_cell_px": 1},
        {"speckle": 0.2, "disparity_sigma_px": 0.3, "subpixel": 4},
    ],
)
def test_kinect_kernels_match_the_numpy_reference(params):
    model = noise.KinectNoise(**params)
    rng = np.random.default_rng(5)
    for _ in range(3):
        depth = _boxes(rng)
        field, seed = model.draws(depth.shape, np.random.default_rng(int(rng.integers(1 << 30))))
        ref = reference.kinect_reference(model, depth, field, seed)
        out = np.empty_like(depth)
        noise._kinect_kernel(
            depth, *model.flags(depth), field, float(model.noise_cell_px), np.uint64(seed), model.fb, float(model.subpixel),
            model.disparity_sigma_px, model.edge_band_px, model.shadow_dropout, model.edge_dropout, model.flying,
            model.speckle,
            model.min_range_m, model.max_range_m, out,
        )  # fmt: skip
        assert np.array_equal(out, ref)
        assert np.all(out[depth == 0] == 0)


def test_kinect_on_a_plane_has_its_steps_and_its_sigma():
    model = noise.KinectNoise(speckle=0.0)
    for z in (2.0, 3.0, 3.5):
        # a gentle ramp (0.3 mm a pixel, no jumps) so the true depth samples every phase
        # between two levels, as real surfaces do
        depth = (z * 1000 + 0.3 * (np.arange(640) - 320))[None, :].repeat(480, 0).astype(np.uint16)
        out = model.apply(depth, np.random.default_rng(int(z * 10)))
        assert np.all(out > 0)  # no edges, no shadows, no speckle: nothing drops
        # every value is a disparity level fb / (k / subpixel), in mm
        levels = np.unique(out)
        k = np.rint(model.fb * model.subpixel / (levels / 1000.0))
        assert np.all(np.abs(np.floor(model.fb / (k / model.subpixel) * 1000 + 0.5) - levels) == 0)
        steps = np.diff(levels)
        assert np.median(steps) == pytest.approx(model.depth_step_mm(z), rel=0.1)
        err = out.astype(float) - depth
        assert err.std() == pytest.approx(model.sigma_mm(z), rel=0.15)
        assert abs(err.mean()) < 0.25 * model.depth_step_mm(z)
    # past the range limit nothing is measured
    far = np.full((20, 20), 9000, np.uint16)
    assert np.all(model.apply(far, np.random.default_rng(0)) == 0)


def test_speckle_drops_its_fraction():
    model = noise.KinectNoise(speckle=0.02)
    out = model.apply(np.full((400, 400), 3000, np.uint16), np.random.default_rng(9))
    p = (out == 0).mean()
    assert p == pytest.approx(0.02, abs=4 * np.sqrt(0.02 * 0.98 / out.size))


def _table_scene():
    mount = PAPER_MOUNT
    top = 0.8
    box = render.Primitives(
        np.array([BOX, BOX], np.int32), np.array([[10, 10, 0.05], [0.4, 0.3, top / 2]]),
        np.array([[0, 0, -0.05], [0.3, 0.1, top / 2]]), np.repeat(np.eye(3)[None], 2, 0), np.array([0, labels.TABLE], np.uint8),
    )  # fmt: skip
    depth, lab = render.raycast(box, mount)
    return depth, lab, top


def test_shadows_fall_left_of_near_objects_as_wide_as_the_disparity_jump():
    depth, lab, top = _table_scene()
    model = noise.KinectNoise()
    flags, _ = model.flags(depth)
    shadow = (flags & noise.SHADOW) != 0
    rows = np.nonzero((lab == labels.TABLE).any(1))[0]
    rows = rows[5:-5]
    expected = model.fb * (1 / (3.5 - top) - 1 / 3.5)  # pixels between the two projector columns
    for v in rows[::10]:
        cols = np.nonzero(lab[v] == labels.TABLE)[0]
        left = cols.min()
        width = 0
        while shadow[v, left - 1 - width]:
            width += 1
        assert abs(width - expected) <= 1.5
        assert not shadow[v, cols.max() + 1 : cols.max() + 20].any()  # nothing on the right
    quiet = noise.KinectNoise(edge_dropout=0.0, shadow_dropout=0.0, flying=0.0, speckle=0.0)
    out = quiet.apply(depth, np.random.default_rng(0))
    assert np.array_equal(out == 0, shadow)


def test_bands_beside_shadows_and_jumps_drop_their_fractions():
    depth, _, _ = _table_scene()
    p_shadow, p_edge = 0.7, 0.2
    model = noise.KinectNoise(shadow_dropout=p_shadow, edge_dropout=p_edge, flying=0.0, speckle=0.0)
    flags, near_h = model.flags(depth)
    bits = np.zeros(depth.shape, np.uint8)
    b = model.edge_band_px
    for dv in range(-b, b + 1):
        bits |= np.roll(near_h, dv, axis=0)
    lit = (flags & noise.SHADOW) == 0
    by_shadow = lit & ((bits & noise.NEAR_SHADOW) != 0)
    by_jump = lit & ~by_shadow & ((bits & noise.NEAR_JUMP) != 0)
    assert by_shadow.sum() > 100 and by_jump.sum() > 100
    out = model.apply(depth, np.random.default_rng(1))
    for band, p in ((by_shadow, p_shadow), (by_jump, p_edge)):
        dropped = (out == 0)[band].mean()
        assert dropped == pytest.approx(p, abs=4 * np.sqrt(p * (1 - p) / band.sum()))
    assert not (out == 0)[lit & (bits == 0)].any()
    # real frames' no-depth bands are a few pixels wider than the projector's shadow (docs/explanation/noise.md)
    model = noise.KinectNoise()
    runs = depth_stats.gap_runs(model.apply(depth, np.random.default_rng(2)))
    far_left = runs[:, 3] == 1
    assert far_left.mean() > 0.8  # shadows: the far side is on the left
    shadow = model.fb * (1000 / runs[far_left, 1] - 1000 / runs[far_left, 2])
    assert np.median(runs[far_left, 0] - shadow) > 1.0


def test_flying_pixels_lie_between_the_two_sides():
    depth, lab, _ = _table_scene()
    model = noise.KinectNoise(
        edge_dropout=0.0, shadow_dropout=0.0, flying=1.0, speckle=0.0, disparity_sigma_px=0.0
    )
    flags, _ = model.flags(depth)
    out = model.apply(depth, np.random.default_rng(2)).astype(float)
    jump = ((flags & noise.JUMP) != 0) & ((flags & noise.SHADOW) == 0)
    top, floor = depth[lab == labels.TABLE].min(), depth.max()
    inner = out[jump]
    step = model.depth_step_mm(floor / 1000)
    assert np.all(
        (inner > top + 0.1 * (floor - top) - step) & (inner < floor - 0.1 * (floor - top) + step)
    )
    calm = ~jump & (depth > 0) & ((flags & noise.SHADOW) == 0)
    assert np.all(np.abs(out[calm] - depth[calm]) <= model.depth_step_mm(floor / 1000))


def test_depth_statistics_measure_what_they_say():
    edges = np.array([1000, 2000, 3000])
    img = np.zeros((64, 64), np.uint16)
    img[:32] = (1000 + 10 * (np.arange(64) % 50))[None, :]  # levels 10 mm apart in 1..2 m
    img[32:] = (2000 + 25 * (np.arange(64) % 30))[None, :]  # 25 mm apart in 2..3 m
    np.testing.assert_allclose(depth_stats.level_spacing(img, edges), [10, 25])

    rng = np.random.default_rng(0)
    plane = 2500 + 0.5 * np.arange(256)[None, :] + rng.normal(0, 6.0, (256, 256))
    rough = depth_stats.roughness(np.rint(plane).astype(np.uint16), edges)
    assert np.isnan(rough[0]) and rough[1] == pytest.approx(6.0, rel=0.1)

    row = np.array([[3000, 3000, 0, 0, 0, 2000, 2000, 0, 2010, 2000]], np.uint16)
    runs = depth_stats.gap_runs(row)
    np.testing.assert_array_equal(runs, [[3, 2000, 3000, 1]])  # the small 10 mm gap is no jump
    fb = 43.5
    s = depth_stats.shadow_summary(np.repeat(row, 10, 0), fb)
    assert s["runs"] == 10 and s["far_on_left"] == 1.0
    assert s["left_extra_px"] == pytest.approx(3 - fb * (1 / 2.0 - 1 / 3.0))

    step = np.array([[2000, 2000, 2500, 3000, 3000, 2000, 2000, 0, 3000, 3000]], np.uint16)
    e = depth_stats.edge_summary(step)
    # three 5-px windows span a jump: middles 2500 (flying), 3000 (outside 2000..2500), 0 (missing)
    assert e["jumps"] == 3 and e["missing"] == pytest.approx(1 / 3) and e["flying"] == 0.5


# --- time of flight and active stereo ----------------------------------------------------------

QUIET_TOF = dict(
    sigma_c0_mm=0.0, sigma_c1_mm=0.0, sigma_c2_mm=0.0, flying=0.0, multipath_mm=0.0,
    dark_dropout=0.0, speckle=0.0, border_px=0, corner_sigma=1.0,
)  # fmt: skip
QUIET_STEREO = dict(disparity_sigma_px=0.0, fatten=0.0, speckle=0.0, border_px=0)


def _plane(z_mm: float, shape=(240, 320)) -> np.ndarray:
    """A gentle ramp around `z_mm` (0.3 mm a column): a flat floor sampling every phase."""
    h, w = shape
    return (z_mm + 0.3 * (np.arange(w) - w / 2))[None, :].repeat(h, 0).astype(np.uint16)


def _random_labels(rng, shape) -> np.ndarray:
    """Label ids with head blobs, for the dark-surface mask."""
    lab = np.zeros(shape, np.uint8)
    for _ in range(4):
        v, u = rng.integers(0, shape[0]), rng.integers(0, shape[1])
        lab[max(0, v - 8) : v + 8, max(0, u - 10) : u + 10] = labels.HEAD
    return lab


def test_tof_and_stereo_specs_parse_print_back_and_refuse_in_one_line():
    t = noise.parse_noise("tof")
    assert t == noise.ToFNoise() and t.spec == "tof"
    t2 = noise.parse_noise("tof:flying_px=2,edge_invalid=0.9, multipath_mm=35")
    assert t2.flying_px == 2 and isinstance(t2.flying_px, int) and t2.edge_invalid == 0.9
    s = noise.parse_noise("stereo")
    assert s == noise.StereoNoise() and s.spec == "stereo"
    s2 = noise.parse_noise("Stereo:baseline_m=0.075,focal_px=441.25,subpixel_bits=3")
    assert s2.fb == pytest.approx(0.075 * 441.25) and s2.subpixel == 8
    for m in (t, t2, s, s2):
        assert noise.parse_noise(m.spec) == m
        assert noise.parse_noise(m.spec).to_dict() == m.to_dict()
    for bad, msg in (
        ("tof:wobble=1", "unknown tof parameter 'wobble'"),
        ("tof:flying=1.5", "probability"),
        ("tof:flying_px=x", "needs a number"),
        ("tof:flying_px=0", "flying_px"),
        ("tof:concave_min=0.1,concave_full=0.05", "concave_min"),
        ("tof:sigma_c0_mm=-5", "sigma"),
        ("stereo:baseline_m=0", "baseline_m > 0"),
        ("stereo:fatten=2", "probability"),
        ("stereo:speckle", "unknown stereo parameter"),
        ("stereo:max_range_m=70", "65.535"),
        ("sonar", "tof or stereo"),
    ):
        with pytest.raises(TopsegError, match=msg) as err:
            noise.parse_noise(bad)
        assert "\n" not in str(err.value)


@pytest.mark.parametrize(
    "params",
    [
        {},
        {"flying": 1.0, "flying_px": 2, "edge_invalid": 0.3, "dark_dropout": 0.6, "speckle": 0.1},
        {"multipath_mm": 50.0, "multipath_px": 2, "concave_min": 0.0, "corner_sigma": 5.0},
        {"fov_radius": 0.8, "border_px": 3, "dark_cell_px": 1, "sigma_c0_mm": 17.0},
        {"fov_cut": 1.0, "fov_cut_min": 0.3, "fov_radius": 0.9},
    ],
)
def test_tof_kernel_matches_the_numpy_reference(params):
    model = noise.ToFNoise(**params)
    rng = np.random.default_rng(11)
    for _ in range(3):
        depth = _boxes(rng)
        dark = model.dark_mask(_random_labels(rng, depth.shape), depth.shape)
        draws = model.draws(depth.shape, np.random.default_rng(int(rng.integers(1 << 30))))
        ref = reference.tof_reference(model, depth, dark, *draws)
        out = model.run(depth, dark, *draws)
        assert np.array_equal(out, ref)
        assert np.all(out[depth == 0] == 0)


@pytest.mark.parametrize(
    "params",
    [
        {},
        {"fatten": 1.0, "fatten_px": 3, "speckle": 0.1, "border_px": 2},
        {"subpixel_bits": 0, "disparity_sigma_px": 0.5, "noise_cell_px": 1, "fatten_px": 0},
        {"focal_px": 142.6, "baseline_m": 0.3, "speckle_cell_px": 1, "min_range_m": 3.0},
    ],
)
def test_stereo_kernel_matches_the_numpy_reference(params):
    model = noise.StereoNoise(**params)
    rng = np.random.default_rng(12)
    for _ in range(3):
        depth = _boxes(rng)
        draws = model.draws(depth.shape, np.random.default_rng(int(rng.integers(1 << 30))))
        ref = reference.stereo_reference(model, depth, *draws)
        out = model.run(depth, *draws)
        assert np.array_equal(out, ref)
        assert np.all(out[depth == 0] == 0)


def test_concavity_matches_the_numpy_reference():
    rng = np.random.default_rng(13)
    depth = _boxes(rng)
    ref = reference.concavity_reference(depth, 4, 100.0)
    out = np.array(
        [[noise._concavity(depth, v, u, 4, 100.0) for u in range(depth.shape[1])]
         for v in range(depth.shape[0])]
    )  # fmt: skip
    assert np.array_equal(out, ref)


@pytest.mark.parametrize("spec", ["tof", "stereo", "tof:edge_invalid=0.8,flying_px=2"])
def test_new_models_are_deterministic_given_the_generator(spec):
    model = noise.parse_noise(spec)
    rng = np.random.default_rng(3)
    depth = _boxes(rng)
    lab = _random_labels(rng, depth.shape)
    a = model.apply(depth, np.random.default_rng(7), labels=lab)
    b = model.apply(depth, np.random.default_rng(7), labels=lab)
    c = model.apply(depth, np.random.default_rng(8), labels=lab)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    with pytest.raises(ValueError, match="labels"):
        model.apply(depth, np.random.default_rng(7), labels=lab[:-1])


def test_tof_sigma_follows_range_on_a_flat_floor_and_grows_to_the_corners():
    model = noise.ToFNoise(speckle=0.0, corner_sigma=1.0, multipath_mm=0.0)
    for z in (1.0, 2.4, 3.5, 4.5):
        depth = _plane(z * 1000)
        out = model.apply(depth, np.random.default_rng(int(z * 10)))
        inner = out[1:-1, 1:-1] > 0
        assert inner.all()  # only the 1 px border drops
        err = (out.astype(float) - depth)[1:-1, 1:-1]
        # rounding to whole mm adds 1/12 mm^2
        assert err.std() == pytest.approx(np.hypot(model.sigma_mm(z), 12**-0.5), rel=0.05)
        assert abs(err.mean()) < 0.1
    # Fankhauser et al. 2015 at 2.4 / 3.5 / 4.5 m (docs/research/sensor-noise-sources.md)
    np.testing.assert_allclose(
        model.sigma_mm(np.array([2.4, 3.5, 4.5])), [2.03, 3.43, 5.33], atol=0.01
    )
    corners = noise.ToFNoise(speckle=0.0, corner_sigma=3.0, multipath_mm=0.0, sigma_c0_mm=10.0)
    depth = _plane(2000)
    err = corners.apply(depth, np.random.default_rng(1)).astype(float) - depth
    centre = err[100:140, 140:180].std()
    corner = np.concatenate([err[1:12, 1:12].ravel(), err[-12:-1, -12:-1].ravel()]).std()
    assert corner / centre == pytest.approx(2.9, rel=0.15)  # 1 + 2 r^2, r^2 ~ 0.95 there
    assert not np.any(model.apply(np.full((20, 20), 7000, np.uint16), np.random.default_rng(0)))


def test_tof_flying_pixels_lie_only_on_depth_edges_between_the_two_sides():
    depth, _, _ = _table_scene()
    model = noise.ToFNoise(**{**QUIET_TOF, "flying": 1.0, "flying_px": 2})
    out = model.apply(depth, np.random.default_rng(4)).astype(np.int64)
    # the band: a window of radius 2 spans more than jump_m
    d = depth.astype(np.int64)
    lo, hi = d.copy(), d.copy()
    for dv in range(-2, 3):
        for du in range(-2, 3):
            n = np.roll(np.roll(d, dv, 0), du, 1)
            lo, hi = np.minimum(lo, n), np.maximum(hi, n)
    band = hi - lo > 100
    changed = out != d
    assert changed.sum() > 200 and not changed[~band].any()
    mixed = out[band]
    assert np.all(
        (mixed >= lo[band] + 0.2 * (hi - lo)[band] - 1)
        & (mixed <= hi[band] - 0.2 * (hi - lo)[band] + 1)
    )
    # the Azure depth engine drops them instead
    azure = noise.ToFNoise(**{**QUIET_TOF, "edge_invalid": 1.0})
    gone = azure.apply(depth, np.random.default_rng(4)) == 0
    assert gone.sum() > 100 and not gone[~band].any()


def test_tof_dark_dropout_is_patchy_and_only_where_the_labels_say():
    rng = np.random.default_rng(5)
    depth = np.full((240, 320), 2500, np.uint16)
    lab = np.zeros(depth.shape, np.uint8)
    lab[40:200, 60:260] = labels.HEAD
    model = noise.ToFNoise(**{**QUIET_TOF, "dark_dropout": 0.3})
    out = model.apply(depth, rng, labels=lab)
    holes = out == 0
    assert not holes[lab != labels.HEAD].any()
    assert holes[lab == labels.HEAD].mean() == pytest.approx(0.3, abs=0.05)
    from scipy import ndimage

    _, n = ndimage.label(holes)
    assert holes.sum() / n > 4  # blobs, not single pixels
    assert not np.any(model.apply(depth, rng) == 0)  # no labels: no dark surfaces known
    noisy = noise.ToFNoise(**{**QUIET_TOF, "sigma_c0_mm": 2.0, "dark_sigma": 4.0})
    err = noisy.apply(depth, rng, labels=lab).astype(float) - depth
    assert err[lab == labels.HEAD].std() / err[lab != labels.HEAD].std() == pytest.approx(
        4, rel=0.1
    )


def test_tof_valid_circle_is_drawn_per_frame_in_a_share_of_frames():
    depth = np.full((120, 160), 2500, np.uint16)
    model = noise.ToFNoise(**{**QUIET_TOF, "fov_cut": 0.25, "fov_cut_min": 0.5})
    rng = np.random.default_rng(6)
    radii = np.array([model.draws(depth.shape, rng)[-1] for _ in range(800)])
    cut = radii < 1.0
    assert cut.mean() == pytest.approx(0.25, abs=0.05)
    assert radii[cut].min() >= 0.5 and radii[cut].max() < 1.0
    assert np.mean(radii[cut] < 0.75) == pytest.approx(0.5, abs=0.1)  # uniform in [0.5, 1)
    assert np.all(noise.ToFNoise(**QUIET_TOF).apply(depth, rng) > 0)  # 1: nothing cut
    always = noise.ToFNoise(**{**QUIET_TOF, "fov_cut": 1.0, "fov_cut_min": 0.6, "fov_radius": 0.6})
    out = always.apply(depth, rng)
    v, u = np.indices(depth.shape)
    r = np.hypot(u - 79.5, v - 59.5) / np.hypot(80, 60)
    assert np.all(out[r > 0.6] == 0) and np.all(out[r < 0.59] > 0)  # a circle in pixels
    with pytest.raises(TopsegError, match="fov_cut_min"):
        noise.ToFNoise(fov_cut=0.5, fov_cut_min=0.0)
    assert noise.parse_noise("tof:fov_cut=0.3").fov_cut == 0.3


def _wall_scene():
    """A floor and a 2.5 m wall right of the camera: its face meets the floor in a concave
    corner that the camera sees from above."""
    mount = TopViewMount(Intrinsics(160, 120, 142.6, 142.6, 79.5, 59.5), 3500.0)
    prims = render.Primitives(
        np.array([BOX, BOX], np.int32), np.array([[10, 10, 0.05], [0.5, 3.0, 1.25]]),
        np.array([[0, 0, -0.05], [2.0, 0.0, 1.25]]), np.repeat(np.eye(3)[None], 2, 0),
        np.array([0, 1], np.uint8),
    )  # fmt: skip
    return render.raycast(prims, mount)


def test_tof_multipath_biases_depth_only_near_concave_corners():
    depth, lab = _wall_scene()
    face = (lab == 1) & (depth > 1100)  # the wall's inner face (its top is at 1000 mm)
    assert face.sum() > 100
    model = noise.ToFNoise(**{**QUIET_TOF, "multipath_mm": 30.0, "multipath_px": 4})
    out = model.apply(depth, np.random.default_rng(0)).astype(np.int64)
    bias = out - depth
    assert bias.min() >= 0 and bias.max() == 30
    # where the floor meets the wall: the first face column of each row
    corner_col = np.array(
        [np.nonzero(face[v])[0].min() if face[v].any() else -1 for v in range(120)]
    )
    rows = np.nonzero(corner_col > 0)[0][5:-5]
    for v in rows:
        c = corner_col[v]
        assert bias[v, c - 1 : c + 1].max() >= 20  # strong at the corner line
        assert not bias[v, : c - 5].any()  # nothing on the open floor
        assert not bias[v, c + 5 :].any()  # nor on the wall's face higher up, nor its top
    assert bias[(lab == 0) & (depth > 0)].sum() > 0  # the floor side of the corner gets some too


def test_stereo_sigma_and_steps_follow_range_on_a_flat_floor():
    model = noise.StereoNoise(speckle=0.0)
    for z in (1.0, 2.4, 3.5, 4.5):
        depth = _plane(z * 1000, (480, 640))
        out = model.apply(depth, np.random.default_rng(int(z * 10)))
        band = int(np.ceil(model.invalid_band_px(z))) + 2
        err = (out.astype(float) - depth)[:, band:]
        assert np.all(out[:, band:] > 0)
        assert err.std() == pytest.approx(model.sigma_mm(z), rel=0.15)
        assert abs(err.mean()) < 0.1 * model.sigma_mm(z)
    # Intel's RMS = z^2 subpixel / (f B) at 640x480 (docs/research): 24 / 51 / 84 mm
    np.testing.assert_allclose(model.sigma_mm(np.array([2.4, 3.5, 4.5])), [24, 51, 85], rtol=0.02)
    # every value is a disparity level fb / (k / 2^bits) in mm
    coarse = noise.StereoNoise(subpixel_bits=2, speckle=0.0)
    out = coarse.apply(_plane(3000), np.random.default_rng(0))
    levels = np.unique(out[out > 0])
    k = np.rint(coarse.fb * coarse.subpixel / (levels / 1000.0))
    assert np.all(np.floor(coarse.fb / (k / coarse.subpixel) * 1000 + 0.5) == levels)


@pytest.mark.parametrize("sensor", ["realsense_d435", "oak_d"])
def test_stereo_invalid_band_at_the_left_edge_is_f_b_over_z_wide(sensor):
    from topseg.core.sensors import get_sensor

    s = get_sensor(sensor)
    model = noise.parse_noise(s.noise_spec)
    quiet = noise.StereoNoise(**{**model.to_dict(), **QUIET_STEREO})
    for z in (0.8, 2.4, 3.5, 4.5):
        depth = np.full((40, 640), int(z * 1000), np.uint16)
        out = quiet.apply(depth, np.random.default_rng(0))
        widths = (out == 0).sum(1)
        expected = s.baseline_m * s.intrinsics.fx / z
        assert np.all(np.abs(widths - expected) <= 1), (z, widths[0], expected)
        assert np.all(out[:, widths.max() :] > 0)


def test_stereo_fattens_the_foreground_and_leaves_the_occluded_side_empty():
    depth, lab, top = _table_scene()
    table = lab == labels.TABLE
    fat = noise.StereoNoise(focal_px=570.3, **{**QUIET_STEREO, "fatten": 1.0, "fatten_px": 2})
    out = fat.apply(depth, np.random.default_rng(0)).astype(np.int64)
    near = out < 3500 - top * 1000 + 100
    from scipy import ndimage

    grown = ndimage.binary_dilation(table, np.ones((5, 5), bool))
    # the foreground reaches exactly 2 px beyond the table, never further
    assert np.array_equal(near & (out > 0), grown & (out > 0))
    thin = noise.StereoNoise(focal_px=570.3, **QUIET_STEREO)
    out0 = thin.apply(depth, np.random.default_rng(0))
    assert np.array_equal((out0 > 0) & (out0 < 3000), table)
    # the second imager cannot see a band left of the table: f B (1/z_top - 1/z_floor) px
    rows = np.nonzero(table.any(1))[0][5:-5]
    expected = thin.fb * (1 / (3.5 - top) - 1 / 3.5)
    for v in rows[::10]:
        left = np.nonzero(table[v])[0].min()
        width = 0
        while out0[v, left - 1 - width] == 0:
            width += 1
        assert abs(width - expected) <= 1.5
        assert np.all(out0[v, np.nonzero(table[v])[0].max() + 1 :] > 0)


def test_stereo_speckle_holes_cover_their_share_in_blobs():
    model = noise.StereoNoise(disparity_sigma_px=0.0, speckle=0.05)
    depth = np.full((480, 640), 2000, np.uint16)
    out = model.apply(depth, np.random.default_rng(2))
    holes = (out == 0)[:, 20:]
    assert holes.mean() == pytest.approx(0.05, abs=0.015)
    from scipy import ndimage

    _, n = ndimage.label(holes)
    assert holes.sum() / n > 4
