"""The forest's input: heights and metric offsets from any mount, the floor gate, the legacy
path, and a model trained at one mount labelling scenes seen from another."""

from dataclasses import replace

import numpy as np
import pytest
from reference import edge_gaps_reference, model_input_float32_reference, model_input_reference

from topseg.core import labels
from topseg.core.camera import KINECT_V1, Intrinsics, TopViewMount, metres_to_mm
from topseg.core.denoise import denoise
from topseg.core.fattening import unfatten
from topseg.core.forest import FeatureConfig, TrainConfig, train_forest
from topseg.core.forest.inputs import (
    FLOOR_SIGMAS,
    MIN_FLOOR_MARGIN_MM,
    floor_margin_mm,
    header_fields,
    legacy_input,
    model_input,
    trained_for,
)
from topseg.core.segmenter import Segmenter
from topseg.core.sensors import depth_sigma_mm
from topseg.core.synth import procedural
from topseg.core.synth.noise import GaussianNoise

FEATURES = FeatureConfig()
SMALL_K1 = KINECT_V1.scaled_to(320, 240)
WIDE = Intrinsics(256, 212, 182.5, 182.5, 127.5, 105.5)  # a Kinect v2 at half resolution


def floor_box():
    """The floor as a primitive (1 mm thick), so that tilted cameras see it right."""
    return procedural.Box(0.0, 0.0, 40.0, 40.0, 0.0, 0.001, labels.BACKGROUND)


def render(prims, mount, rng=None, sigma_mm=0.0):
    depth_m, lab = procedural.render([*prims, floor_box()], mount)
    depth = metres_to_mm(depth_m)
    if sigma_mm > 0:
        depth = GaussianNoise(sigma_mm).apply(depth, rng)
    lab[depth == 0] = labels.NO_DEPTH
    return depth, lab


TABLE = procedural.Box(0.1, -0.1, 0.8, 0.6, 0.3, 0.8, labels.TABLE)


@pytest.mark.parametrize(
    "a, b",
    [
        (TopViewMount(SMALL_K1, 3000.0), TopViewMount(WIDE, 4200.0, sensor="kinect_v2")),
        (TopViewMount(SMALL_K1, 2600.0), TopViewMount(SMALL_K1, 3800.0, 6.0, -4.0)),
    ],
)
def test_the_same_scene_gives_the_same_values_at_two_mounts(a, b):
    values = {}
    for name, mount in (("a", a), ("b", b)):
        depth, lab = render([TABLE], mount)
        inp = model_input(depth, mount, FEATURES)
        top = lab == labels.TABLE
        assert top.sum() > 50
        values[name] = inp.values[top]
        # the table top is 800 mm high: C - 800, whatever the camera
        assert np.abs(values[name].astype(int) - (FEATURES.canonical_height_mm - 800)).max() <= 2
        floor = lab == labels.BACKGROUND
        assert inp.floor[floor].all() and not inp.floor[top].any()
        assert np.abs(inp.values[floor].astype(int) - FEATURES.canonical_height_mm).max() <= 2
    assert abs(float(np.median(values["a"])) - float(np.median(values["b"]))) <= 1


def test_scale_follows_the_focal_length():
    for k in (SMALL_K1, WIDE, KINECT_V1):
        mount = TopViewMount(k, 3000.0)
        depth = np.full(k.shape, 2500, np.uint16)
        depth[0, :5] = 0
        inp = model_input(depth, mount, FEATURES)
        want = np.float32(k.fx / FEATURES.reference_focal_px) / np.float32(2500)
        assert np.all(inp.scale[depth > 0] == want) and np.all(inp.scale[depth == 0] == 0)
        assert np.all(inp.values[depth == 0] == 0)
    # an offset spans the same metric distance: pixels moved at 2.5 m, fx 570.3 vs 182.5
    u = 10 * 2500.0 * FEATURES.reference_focal_px / FEATURES.reference_focal_px
    assert round(u * FEATURES.reference_focal_px / FEATURES.reference_focal_px / 2500) == 10
    assert round(u * (WIDE.fx / FEATURES.reference_focal_px) / 2500) == 3


def test_model_input_matches_first_principles():
    rng = np.random.default_rng(3)
    mount = TopViewMount(SMALL_K1, 3400.0, -7.0, 5.0, sensor="realsense_d435")
    depth = rng.integers(1200, 4200, size=SMALL_K1.shape).astype(np.uint16)
    depth[rng.random(SMALL_K1.shape) < 0.05] = 0
    inp = model_input(depth, mount, FEATURES)
    # a stereo camera: thinned (test_fattening) and, at range, smoothed (test_denoise) first
    depth = denoise(unfatten(depth, mount), mount)
    values, scale, floor, h = model_input_reference(
        depth, mount, FEATURES, lambda d: floor_margin_mm(d, mount.sensor)
    )
    assert np.abs(inp.values.astype(int) - values.astype(int)).max() <= 1
    np.testing.assert_allclose(inp.scale, scale, rtol=1e-6)
    margin = floor_margin_mm(depth, mount.sensor)
    clear = np.abs(np.nan_to_num(h, nan=1e9) - margin) > 1.0
    np.testing.assert_array_equal(inp.floor[clear], floor[clear])
    assert inp.floor.any() and (~inp.floor & (depth > 0)).any()
    assert 0 < inp.floor_share() < 1


@pytest.mark.parametrize("seed", range(4))
def test_model_input_kernel_is_bit_identical_to_numpy(seed):
    rng = np.random.default_rng(seed)
    k = SMALL_K1 if seed % 2 else WIDE
    mount = TopViewMount(k, rng.uniform(2200, 4500), *rng.uniform(-10, 10, 2), sensor="oak_d")
    depth = rng.integers(0, 9000, size=k.shape).astype(np.uint16)
    depth[rng.random(k.shape) < 0.1] = 0
    inp = model_input(depth, mount, FEATURES)
    kept = model_input(depth, mount, replace(FEATURES, edge_gaps="background"))
    # thinned (test_fattening) and smoothed where the camera is noisy (test_denoise) first
    depth = denoise(unfatten(depth, mount), mount)
    values, scale, floor = model_input_float32_reference(
        depth, mount, FEATURES, lambda d: floor_margin_mm(d, mount.sensor)
    )
    np.testing.assert_array_equal(inp.values, values)
    np.testing.assert_array_equal(inp.scale, scale)
    np.testing.assert_array_equal(inp.floor, floor)
    assert inp.values.dtype == np.uint16 and inp.scale.dtype == np.float32
    probes, filled = edge_gaps_reference(values)  # FEATURES fill the edge's gaps
    assert filled > 0 and inp.probes is not None
    np.testing.assert_array_equal(inp.probe_values, probes)
    assert kept.probes is None and np.array_equal(kept.values, inp.values)


def test_floor_gate_is_noise_aware():
    z = np.array([1000, 2400, 3500, 4500], np.float32)
    kinect = floor_margin_mm(z, "kinect_v1")
    assert kinect[0] == MIN_FLOOR_MARGIN_MM and np.all(np.diff(kinect) >= 0)
    assert kinect[-1] > MIN_FLOOR_MARGIN_MM  # a few sigma of 25 mm at 4.5 m
    stereo = floor_margin_mm(z, "oak_d")
    assert np.all(stereo >= kinect)  # stereo is noisier at range
    # a camera measured quieter than its model: the margin shrinks with it, to the minimum
    half = floor_margin_mm(z, "oak_d", 0.5)
    expected = np.clip(0.5 * FLOOR_SIGMAS * depth_sigma_mm(z, "oak_d"), MIN_FLOOR_MARGIN_MM, 150)
    np.testing.assert_allclose(half, expected, rtol=1e-6)
    assert np.all(half <= stereo) and half[-1] < stereo[-1]
    # a 100 mm step above the floor is not gated at 3 m, the floor with 15 mm noise mostly is
    mount = TopViewMount(SMALL_K1, 3000.0)
    rng = np.random.default_rng(0)
    low = procedural.Box(0.0, 0.0, 1.0, 1.0, 0.0, 0.1, labels.TABLE)
    depth, lab = render([low], mount, rng, 15.0)
    inp = model_input(depth, mount, FEATURES)
    assert inp.floor[lab == labels.BACKGROUND].mean() > 0.97
    assert inp.floor[lab == labels.TABLE].mean() < 0.01


def test_the_floor_gate_follows_the_mounts_measured_noise_scale():
    # 60 mm shoes 4.5 m below a Kinect v1: within its modelled 3 sigma (~75 mm), so gated;
    # measured three times quieter (a time-of-flight camera), the gate is 40 mm: kept
    mount = TopViewMount(SMALL_K1, 4500.0)
    shoes = procedural.Box(0.0, 0.0, 1.0, 1.0, 0.0, 0.06, labels.LEGS)
    depth, lab = render([shoes], mount)
    on = lab == labels.LEGS
    assert model_input(depth, mount, FEATURES).floor[on].mean() > 0.99
    quiet = replace(mount, noise_scale=0.33)
    assert model_input(depth, quiet, FEATURES).floor[on].mean() < 0.01
    _, _, floor = model_input_float32_reference(
        depth, quiet, FEATURES, lambda d: floor_margin_mm(d, "kinect_v1", 0.33)
    )
    np.testing.assert_array_equal(model_input(depth, quiet, FEATURES).floor, floor)


def test_legacy_input_is_depth():
    depth = np.random.default_rng(1).integers(0, 5000, (20, 30)).astype(np.uint16)
    inp = legacy_input(depth)
    assert inp.values is depth or np.array_equal(inp.values, depth)
    has = depth > 0
    np.testing.assert_array_equal(inp.scale[has], np.float32(1) / depth[has].astype(np.float32))
    assert not inp.floor.any() and inp.floor_share() == 0


def test_wrong_size_is_refused():
    mount = TopViewMount(SMALL_K1, 3000.0)
    with pytest.raises(ValueError, match="320x240"):
        model_input(np.zeros((10, 10), np.uint16), mount, FEATURES)


def test_trained_for_and_outside_it():
    mounts = [
        TopViewMount(SMALL_K1, 2500.0),
        TopViewMount(WIDE, 4400.0, 8.0, 0.0, "kinect_v2"),
    ]
    tf = trained_for(mounts)
    assert tf["height_mm"] == [2500.0, 4400.0] and tf["tilt_deg"] == pytest.approx(8.0)
    assert tf["sensors"] == ["kinect_v1", "kinect_v2"]
    assert tf["resolutions"] == [[256, 212], [320, 240]]
    from topseg.core.forest import Forest, random_tree

    forest = Forest.from_trees([random_tree(np.random.default_rng(0), 2, 2, 1e5)])
    seg = Segmenter(forest, header_fields(FEATURES, tf))
    assert seg.reads_height and seg.trained_for == tf
    assert seg.outside_trained_for(TopViewMount(SMALL_K1, 3300.0, 3.0)) is None
    assert "5.20 m" in seg.outside_trained_for(TopViewMount(SMALL_K1, 5200.0))
    assert "tilt" in seg.outside_trained_for(TopViewMount(SMALL_K1, 3000.0, 15.0))
    assert "oak_d" in seg.outside_trained_for(TopViewMount(SMALL_K1, 3000.0, sensor="oak_d"))


# --- the point of it all: one model, any ceiling, any focal length --------------------------

TRAIN_MOUNT = TopViewMount(SMALL_K1, 3000.0)
OTHER_MOUNTS = [
    TopViewMount(WIDE, 4200.0, sensor="kinect_v2"),  # higher, half the focal length
    TopViewMount(SMALL_K1, 2500.0, 5.0, -3.0),  # lower, tilted
]


def scenes(rng, n, mounts):
    """`n` scenes placed in view of every mount (the smallest view), rendered at each."""
    out = {i: ([], []) for i in range(len(mounts))}
    for _ in range(n):
        prims = procedural.random_scene(rng, TopViewMount(SMALL_K1, 2400.0))
        for i, m in enumerate(mounts):
            d, lab = render(prims, m, rng, 12.0)
            out[i][0].append(d)
            out[i][1].append(lab)
    return out


def accuracy(forest, depth, truth, mount, features):
    ok = total = 0
    seg = Segmenter(forest, header_fields(features), crf="none")
    for d, t in zip(depth, truth, strict=True):
        pred = seg.label(d, mount=mount).labels
        m = t != labels.NO_DEPTH
        ok += int((pred[m] == t[m]).sum())
        total += int(m.sum())
    return ok / total


def test_a_model_trained_at_one_mount_labels_others_alike():
    rng = np.random.default_rng(14)
    features = FeatureConfig(n_features=120, absolute_fraction=0.2)
    config = TrainConfig(
        n_trees=2,
        max_depth=12,
        frames_per_tree=24,
        pixels_per_frame=800,
        n_candidates=30,
        n_thresholds=30,
        features=features,
    )
    train = scenes(rng, 24, [TRAIN_MOUNT])[0]
    forest = train_forest(
        np.stack(train[0]), np.stack(train[1]), config, seed=0, mounts=[TRAIN_MOUNT] * 24
    )
    mounts = [TRAIN_MOUNT, *OTHER_MOUNTS]
    test = scenes(rng, 5, mounts)
    acc = [accuracy(forest, *test[i], m, features) for i, m in enumerate(mounts)]
    assert acc[0] >= 0.9
    for a in acc[1:]:
        assert a >= acc[0] - 0.05, acc
