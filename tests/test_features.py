"""Depth-difference features: numba kernels against plain numpy references."""

import numpy as np
import pytest
from reference import extract_reference, response_reference

from topseg.core.forest import features
from topseg.core.forest.features import FeatureConfig


def random_depth(rng, shape=(37, 53), zero_fraction=0.1, hi=12000):
    depth = rng.integers(400, hi, size=shape).astype(np.uint16)
    depth[rng.random(shape) < zero_fraction] = 0
    return depth


@pytest.mark.parametrize("nearest", [False, True])
@pytest.mark.parametrize("seed", range(4))
def test_extract_features_matches_reference(seed, nearest):
    rng = np.random.default_rng(seed)
    config = FeatureConfig(n_features=40, patch_px=int(rng.integers(4, 80)))
    depth = random_depth(rng, hi=int(rng.choice([5000, 12000])))
    offsets = features.sample_offsets(config, rng)
    rows, cols = np.nonzero(depth)
    pick = rng.choice(rows.size, 200, replace=False)
    r, c, bg = rows[pick], cols[pick], config.background_mm
    got = features.extract_features(depth, r, c, offsets, bg, nearest=nearest)
    want = extract_reference(depth, r, c, offsets, bg, nearest)
    assert got.dtype == np.int16
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("nearest", [False, True])
@pytest.mark.parametrize("k", [1, 2, 3])
def test_node_response_matches_reference(k, nearest):
    rng = np.random.default_rng(k)
    config = FeatureConfig(patch_px=48)
    depth = random_depth(rng)
    offsets = features.sample_offsets(FeatureConfig(n_features=k, patch_px=48), rng)
    weights = features.random_unit_vectors(rng, 1, k)[0]
    bg = config.background_mm
    got = features.node_response_image(depth, offsets, weights, bg, nearest)
    want = response_reference(depth, offsets, weights, bg, nearest)
    np.testing.assert_array_equal(np.isnan(got), depth == 0)
    np.testing.assert_array_equal(got, want)


def test_probes_off_image_or_on_no_depth_read_background():
    depth = np.full((10, 10), 2000, np.uint16)
    depth[5, 7] = 0
    bg = 10000
    # u points off the image, v lands on the pixel itself: f = bg - d(s)
    off = np.array([[-40 * 2000, 0, 0, 0]], np.float32)
    assert features.extract_features(depth, [5], [5], off, bg)[0, 0] == bg - 2000
    # u lands on the no-depth pixel two columns right
    off = np.array([[0, 2 * 2000, 0, 0]], np.float32)
    assert features.extract_features(depth, [5], [5], off, bg)[0, 0] == bg - 2000
    # depths beyond the background constant are clamped to it
    depth[5, 6] = 15000
    off = np.array([[0, 1 * 2000, 0, 0]], np.float32)
    assert features.extract_features(depth, [5], [5], off, bg)[0, 0] == bg - 2000


def test_probes_off_image_read_the_nearest_edge_pixel_when_asked():
    """`off_image` "nearest": a surface cut by the image's edge reads as going on beyond it;
    a no-depth edge pixel still reads background, and so does a far v offset."""
    depth = np.full((10, 10), 3000, np.uint16)
    depth[:, 0] = 2000  # the left column: a person cut by the image's edge
    depth[0, 5] = 0
    bg = 10000
    left = np.array([[0, -40 * 2000, 0, 0]], np.float32)  # u far left of (5, 5), v on it
    assert features.extract_features(depth, [5], [5], left, bg, nearest=True)[0, 0] == -1000
    assert features.extract_features(depth, [5], [5], left, bg)[0, 0] == bg - 3000
    up = np.array([[-40 * 2000, 0, 0, 0]], np.float32)  # lands on the no-depth (0, 5)
    assert features.extract_features(depth, [5], [5], up, bg, nearest=True)[0, 0] == bg - 3000
    far = np.array([[0, 0, features.OFF_IMAGE, 0]], np.float32)
    assert features.extract_features(depth, [5], [5], far, bg, nearest=True)[0, 0] == 3000 - bg


def test_offsets_are_depth_invariant():
    """The same metric step seen at two depths gives the same feature."""
    bg = 10000
    off = np.array([[0, 10 * 1000, 0, -10 * 1000]], np.float32)  # 10 px at 1 m, either side
    near = np.full((1, 60), 1000, np.uint16)
    near[0, 40:] = 900  # a 100 mm step 10 px right of pixel 30
    far = np.full((1, 60), 2000, np.uint16)
    far[0, 35:] = 1900  # the same step, half as many pixels away at twice the depth
    f_near = features.extract_features(near, [0], [30], off, bg)[0, 0]
    f_far = features.extract_features(far, [0], [30], off, bg)[0, 0]
    assert f_near == f_far == -100


def test_sample_offsets_stay_in_patch():
    config = FeatureConfig(n_features=500, patch_px=64, reference_depth_mm=2500)
    off = features.sample_offsets(config, np.random.default_rng(0))
    assert off.shape == (500, 4) and off.dtype == np.float32
    px = off / config.reference_depth_mm
    assert np.abs(px).max() <= 32
    assert np.abs(px).max() > 30  # the whole patch is used


def test_absolute_features_compare_with_the_background():
    config = FeatureConfig(n_features=400, absolute_fraction=0.25)
    off = features.sample_offsets(config, np.random.default_rng(1))
    absolute = off[:, 2] == features.OFF_IMAGE
    assert 0.18 < absolute.mean() < 0.32 and np.all(off[absolute, 3] == features.OFF_IMAGE)
    depth = np.random.default_rng(2).integers(500, 4000, (30, 40)).astype(np.uint16)
    rows, cols = np.nonzero(depth > 0)
    f = features.extract_features(depth, rows, cols, off[absolute], config.background_mm)
    u = extract_reference(depth, rows, cols, off[absolute] * [1, 1, 0, 0], config.background_mm)
    # f = p(s + u/d) - background = (p(s + u/d) - d(s)) - (background - d(s))
    np.testing.assert_array_equal(
        f.astype(int), u.astype(int) + depth[rows, cols][:, None].astype(int) - config.background_mm
    )


def test_random_unit_vectors_are_unit():
    w = features.random_unit_vectors(np.random.default_rng(0), 100, 3)
    np.testing.assert_allclose(np.linalg.norm(w, axis=1), 1.0, rtol=1e-6)


def test_bad_input_is_refused():
    depth = np.full((5, 5), 1000, np.uint16)
    off = np.zeros((3, 4), np.float32)
    with pytest.raises(ValueError, match="uint16"):
        features.extract_features(depth.astype(np.float32), [0], [0], off, 10000)
    with pytest.raises(ValueError, match="outside"):
        features.extract_features(depth, [5], [0], off, 10000)
    depth[0, 0] = 0
    with pytest.raises(ValueError, match="depth"):
        features.extract_features(depth, [0], [0], off, 10000)
    with pytest.raises(ValueError, match="background_mm"):
        FeatureConfig(background_mm=40000)


def test_config_round_trip():
    c = FeatureConfig(n_features=75, patch_px=32)
    assert FeatureConfig.from_dict(c.to_dict()) == c
    assert c.off_image == "nearest" and c.nearest_off_image
    b = FeatureConfig(off_image="background")
    assert FeatureConfig.from_dict(b.to_dict()) == b and not b.nearest_off_image
    with pytest.raises(ValueError, match="off_image"):
        FeatureConfig(off_image="mirror")
    assert FeatureConfig().edge_gaps == "nearest"
    assert FeatureConfig.from_dict(FeatureConfig(edge_gaps="background").to_dict()).edge_gaps == (
        "background"
    )
    with pytest.raises(ValueError, match="edge_gaps"):
        FeatureConfig(edge_gaps="zero")


def test_old_feature_configs_load_with_the_new_defaults():
    old = {k: v for k, v in FeatureConfig().to_dict().items()}
    del old["canonical_height_mm"], old["reference_focal_px"]
    c = FeatureConfig.from_dict(old)
    assert c.reference_focal_px == 570.3 and 0 < c.canonical_height_mm < c.background_mm
    with pytest.raises(ValueError, match="canonical_height_mm"):
        FeatureConfig(canonical_height_mm=20000)


@pytest.mark.parametrize("seed", range(3))
def test_features_of_a_model_input_match_reference(seed):
    """Probe values and per-pixel scales of a height model's input, not depth."""
    from topseg.core.forest.edge_gaps import fill_edge_gaps
    from topseg.core.forest.inputs import ModelInput

    rng = np.random.default_rng(seed + 7)
    depth = random_depth(rng)
    values = np.where(depth > 0, rng.integers(1, 9999, depth.shape), 0).astype(np.uint16)
    scale = np.where(depth > 0, rng.uniform(1e-4, 1e-3, depth.shape), 0).astype(np.float32)
    probes, filled = fill_edge_gaps(values)  # probes read the edge's gaps filled
    assert filled > 0
    inp = ModelInput(values, scale, np.zeros(depth.shape, bool), probes)
    offsets = features.sample_offsets(FeatureConfig(n_features=30), rng)
    rows, cols = np.nonzero(values)
    for nearest in (False, True):
        got = features.extract_features(inp, rows, cols, offsets, 10000, nearest=nearest)
        want = extract_reference(inp, rows, cols, offsets, 10000, nearest)
        np.testing.assert_array_equal(got, want)
        w = features.random_unit_vectors(rng, 1, 2)[0]
        got = features.node_response_image(inp, offsets[:2], w, 10000, nearest)
        np.testing.assert_array_equal(got, response_reference(inp, offsets[:2], w, 10000, nearest))
