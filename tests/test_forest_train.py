"""Forest training: every numba kernel (criterion, splitter, builder) against a plain
numpy/Python reference, then whole trees, bit for bit against saved trees
(tests/data/small_trees.npz)."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from reference import (
    SplitMix,
    best_split_reference,
    gains_reference,
    responses_reference,
)

from topseg.core import labels
from topseg.core.forest import criterion, splitter
from topseg.core.forest import train as ft
from topseg.core.forest.features import FeatureConfig
from topseg.core.forest.predict import predict_proba
from topseg.core.forest.tree import Forest


def test_splitmix_stream_matches_reference():
    key, node = 0xDEADBEEF12345678, 77
    state = splitter._node_state(key, node)
    ref = SplitMix(key, node)
    got = [int(splitter._next_u64(state)) for _ in range(20)]
    assert got == [ref.next() for _ in range(20)]
    vals = [splitter._uniform(state) for _ in range(1000)]
    assert vals == [ref.uniform() for _ in range(1000)]
    assert 0.0 <= min(vals) and max(vals) < 1.0


def test_unit_vector_is_uniform_direction():
    state = splitter._node_state(5, 0)
    out = np.empty(2)
    angles = []
    for _ in range(4000):
        splitter._unit_vector(state, 2, out)
        assert abs(np.hypot(*out) - 1) < 1e-12
        angles.append(np.arctan2(out[1], out[0]))
    hist, _ = np.histogram(angles, bins=8, range=(-np.pi, np.pi))
    assert hist.min() > 0.8 * 500 and hist.max() < 1.2 * 500


@pytest.mark.parametrize("seed", range(3))
def test_responses_match_reference(seed):
    rng = np.random.default_rng(seed)
    fm = rng.integers(-9000, 9000, size=(50, 300)).astype(np.int16)
    ids = rng.choice(300, 120, replace=False)
    feats = rng.integers(0, 50, size=3)
    weights = rng.normal(size=3).astype(np.float32)
    out = np.empty(120, np.float32)
    splitter._responses(fm, ids, feats, weights, out)
    np.testing.assert_array_equal(out, responses_reference(fm, ids, feats, weights))


@pytest.mark.parametrize("seed", range(5))
def test_histogram_gains_match_brute_force(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(5, 400))
    n_cls = labels.NUM_CLASSES
    y = rng.integers(0, rng.integers(2, n_cls + 1), size=n)
    resp = np.round(rng.normal(size=n) * 50).astype(np.float32)  # ties on purpose
    thr = np.sort(resp[rng.integers(0, n, size=min(40, n))])
    hist = np.full((thr.size + 1, n_cls), -1, np.int64)
    criterion._bin_histogram(resp, y, thr, hist)
    assert hist.sum() == n
    # bin b = number of thresholds <= response
    bins = np.searchsorted(thr, resp, side="right")
    np.testing.assert_array_equal(hist.sum(axis=1), np.bincount(bins, minlength=thr.size + 1))
    gains = np.empty(thr.size)
    criterion._gains_from_histogram(hist, criterion.xlogx_table(n + 1), gains)
    np.testing.assert_allclose(gains, gains_reference(resp, y, thr, n_cls), atol=1e-12)


def test_bins_at_the_edges():
    thr = np.array([5, 5, 7], np.float32)
    resp = np.array([4, 5, 6, 7, 8], np.float32)
    hist = np.empty((4, 11), np.int64)
    criterion._bin_histogram(resp, np.zeros(5, np.int64), thr, hist)
    assert hist[:, 0].tolist() == [1, 0, 2, 2]  # searchsorted right: 0, 2, 2, 3, 3
    one = np.empty((2, 11), np.int64)
    criterion._bin_histogram(resp, np.zeros(5, np.int64), np.array([6], np.float32), one)
    assert one[:, 0].tolist() == [2, 3]


def test_gain_is_parent_entropy_for_a_perfect_split():
    resp = np.array([1, 2, 3, 10, 11, 12], np.float32)
    y = np.array([0, 0, 0, 5, 5, 5])
    thr = np.array([10], np.float32)
    hist = np.empty((2, 11), np.int64)
    criterion._bin_histogram(resp, y, thr, hist)
    gains = np.empty(1)
    criterion._gains_from_histogram(hist, criterion.xlogx_table(7), gains)
    assert gains[0] == pytest.approx(1.0)


@pytest.mark.parametrize(
    ("linear", "k", "n", "cap"), [(True, 2, 150, 1000), (False, 1, 150, 1000), (True, 3, 400, 90)]
)
def test_best_split_matches_reference(linear, k, n, cap):
    rng = np.random.default_rng(n + k)
    fm = rng.integers(-3000, 3000, size=(8, 500)).astype(np.int16)
    y = rng.integers(0, 4, size=500)
    # make feature 7 informative so the best split is not a coin flip
    fm[7] = (y * 1000 + rng.integers(-400, 400, size=500)).astype(np.int16)
    ids = np.sort(rng.choice(500, n, replace=False))
    key, node_id = 1234567, 9
    state = splitter._node_state(key, node_id)
    xlogx = criterion.xlogx_table(max(n, cap) + 1)
    gain, feats, weights, thr = splitter._best_split(
        fm, y, ids, state, labels.NUM_CLASSES, 25, 30, k, linear, cap, xlogx
    )
    r_gain, r_feats, r_weights, r_thr = best_split_reference(
        fm, y, ids, key, node_id, 25, 30, k, linear, cap
    )
    assert gain == pytest.approx(r_gain, abs=1e-9)
    np.testing.assert_array_equal(feats, r_feats)
    np.testing.assert_array_equal(weights, r_weights)
    assert thr == r_thr
    assert gain > 0.3  # the informative feature was among the 25 candidates


def test_partition_is_stable_and_matches_reference():
    rng = np.random.default_rng(0)
    fm = rng.integers(-100, 100, size=(10, 200)).astype(np.int16)
    ids = rng.permutation(200)[:150].astype(np.int64)
    feats = np.array([2, 5])
    w = np.array([0.6, -0.8], np.float32)
    resp = responses_reference(fm, ids, feats, w)
    want = np.concatenate([ids[resp < 3.5], ids[~(resp < 3.5)]])
    got = ids.copy()
    n_left = splitter._partition(fm, got, feats, w, np.float32(3.5))
    assert n_left == int((resp < 3.5).sum())
    np.testing.assert_array_equal(got, want)


def test_balanced_counts_share_evenly():
    counts = np.array([5000, 10, 0, 300, 2000, 0, 0, 0, 0, 0, 0])
    take = ft.balanced_counts(counts, 1000)
    assert take.sum() == 1000
    assert take[1] == 10 and take[2] == 0  # small classes give all they have
    assert abs(int(take[0]) - int(take[4])) <= 1 and take[3] == 300
    assert ft.balanced_counts(np.array([3, 4, 0]), 100).tolist() == [3, 4, 0]


def test_sample_pixels_is_balanced_and_valid():
    rng = np.random.default_rng(0)
    lab = np.zeros((40, 50), np.uint8)
    lab[:10] = labels.TABLE
    lab[10:12] = labels.HEAD
    depth = np.full(lab.shape, 3000, np.uint16)
    depth[30:, :] = 0
    lab[30:, :] = labels.NO_DEPTH
    rows, cols, ys = ft.sample_pixels(depth, lab, 300, rng)
    assert np.all(depth[rows, cols] > 0)
    np.testing.assert_array_equal(lab[rows, cols], ys)
    assert len(set(zip(rows.tolist(), cols.tolist(), strict=True))) == 300  # no repeats
    assert np.bincount(ys, minlength=11)[[0, 1, 10]].tolist() == [100, 100, 100]
    lab[0, 0] = 42
    with pytest.raises(ft.TopsegError, match="unknown label"):
        ft.sample_pixels(depth, lab, 300, rng)


def small_frames(seed=0, n=6, shape=(30, 40)):
    """Random blocky scenes: a few rectangles of a few classes at a few heights."""
    rng = np.random.default_rng(seed)
    depth = np.full((n, *shape), 3500, np.uint16)
    lab = np.zeros((n, *shape), np.uint8)
    for i in range(n):
        for _ in range(4):
            r, c = rng.integers(0, shape[0] - 6), rng.integers(0, shape[1] - 6)
            cls = int(rng.choice([labels.TABLE, labels.HEAD, labels.PLANT]))
            height = {labels.TABLE: 800, labels.HEAD: 1700, labels.PLANT: 300}[cls]
            depth[i, r : r + 6, c : c + 8] = 3500 - height
            lab[i, r : r + 6, c : c + 8] = cls
    depth = (depth + rng.normal(0, 10, depth.shape)).astype(np.uint16)
    depth[:, 0, :5] = 0
    lab[:, 0, :5] = labels.NO_DEPTH
    return depth, lab


SMALL = ft.TrainConfig(
    n_trees=2,
    max_depth=8,
    frames_per_tree=5,
    pixels_per_frame=200,
    n_candidates=20,
    n_thresholds=20,
    min_samples_split=6,
    features=FeatureConfig(n_features=40, patch_px=16, reference_depth_mm=2500),
)


def test_tree_is_deterministic_and_seed_dependent():
    depth, lab = small_frames()
    a = ft.train_tree(depth, lab, SMALL, seed=3)
    b = ft.train_tree(depth, lab, SMALL, seed=3)
    c = ft.train_tree(depth, lab, SMALL, seed=4)
    for name, arr in a.arrays().items():
        np.testing.assert_array_equal(arr, b.arrays()[name])
    assert a.n_nodes != c.n_nodes or not np.array_equal(a.threshold, c.threshold)


def test_zarr_frames_train_the_same_tree(tmp_path):
    zarr = pytest.importorskip("zarr")
    depth, lab = small_frames()
    store = zarr.open_group(tmp_path / "ds.zarr", mode="w")
    zd = store.create_array(
        "depth", shape=depth.shape, chunks=(1, *depth.shape[1:]), dtype=np.uint16
    )
    zl = store.create_array("labels", shape=lab.shape, chunks=(1, *lab.shape[1:]), dtype=np.uint8)
    zd[:] = depth
    zl[:] = lab
    a = ft.train_tree(zd, zl, SMALL, seed=8)
    b = ft.train_tree(depth, lab, SMALL, seed=8)
    for name, arr in a.arrays().items():
        np.testing.assert_array_equal(arr, b.arrays()[name])


def test_forest_trees_use_derived_seeds():
    depth, lab = small_frames()
    forest = ft.train_forest(depth, lab, SMALL, seed=11)
    assert forest.n_trees == SMALL.n_trees
    for t in range(forest.n_trees):
        alone = ft.train_tree(depth, lab, SMALL, seed=ft.tree_seed(11, t))
        for name, arr in alone.arrays().items():
            np.testing.assert_array_equal(arr, forest.tree(t).arrays()[name])


def test_a_tree_knows_the_papers_classes_and_any_higher_id_it_trained_on():
    depth, lab = small_frames()
    assert ft.train_tree(depth, lab, SMALL, seed=3).n_classes == labels.PAPER_NUM_CLASSES
    for new, n_classes in ((labels.ROBOT, 12), (labels.OBJECT, 13)):
        relabelled = np.where(lab == labels.PLANT, new, lab).astype(np.uint8)
        tree = ft.train_tree(depth, relabelled, SMALL, seed=3)
        assert tree.n_classes == n_classes
        assert tree.posteriors[:, new].max() > 0.5
        assert tree.posteriors[:, labels.PLANT].max() == 0


def test_a_forest_of_trees_that_know_different_classes_knows_them_all():
    depth, lab = small_frames()
    robots = np.where(lab == labels.PLANT, labels.OBJECT, lab).astype(np.uint8)
    paper, wide = ft.train_tree(depth, lab, SMALL, seed=3), ft.train_tree(depth, robots, SMALL, 4)
    forest = Forest.from_trees([paper, wide])
    assert forest.n_classes == labels.NUM_CLASSES
    assert forest.tree(0).posteriors.shape == (paper.n_leaves, labels.NUM_CLASSES)
    np.testing.assert_array_equal(forest.tree(0).posteriors[:, : paper.n_classes], paper.posteriors)
    got = predict_proba(forest, depth[0])
    alone = [predict_proba(Forest.from_trees([t]), depth[0]) for t in (paper, wide)]
    padded = np.pad(alone[0], ((0, 0), (0, 0), (0, 2)))
    np.testing.assert_allclose(got, (padded + alone[1]) / 2, atol=1e-6)


@pytest.mark.parametrize("split", ["linear", "axis"])
def test_leaves_hold_the_distribution_of_their_training_samples(split):
    """Inference routes each training pixel to the leaf training put it in."""
    depth, lab = small_frames(seed=1)
    config = ft.TrainConfig(**{**SMALL.to_dict(), "split": split, "features": SMALL.features})
    tree = ft.train_tree(depth, lab, config, seed=5)
    assert tree.depth <= config.max_depth
    assert tree.offsets.shape[1] == config.features_per_node
    where, y = ft.training_sample_pixels(depth, lab, config, seed=5)
    forest = Forest.from_trees([tree])
    leaf_of = np.empty(len(y), np.int64)
    for f in np.unique(where[:, 0]):
        sel = where[:, 0] == f
        proba = predict_proba(forest, depth[f])
        rows, cols = where[sel, 1], where[sel, 2]
        # identify the leaf by its posterior row (leaf rows are distinct here w.h.p.)
        post = proba[rows, cols]
        match = (post[:, None, :] == tree.posteriors[None, :, :]).all(axis=2)
        assert np.all(match.sum(axis=1) >= 1)
        leaf_of[sel] = match.argmax(axis=1)
    for leaf_row in np.unique(leaf_of):
        counts = np.bincount(y[leaf_of == leaf_row], minlength=tree.n_classes)
        np.testing.assert_allclose(
            tree.posteriors[leaf_row], counts / counts.sum(), rtol=1e-6, atol=1e-7
        )


def test_stopping_rules():
    depth, lab = small_frames(seed=2)
    stump = ft.train_tree(
        depth,
        lab,
        ft.TrainConfig(**{**SMALL.to_dict(), "max_depth": 0, "features": SMALL.features}),
        seed=0,
    )
    assert stump.n_nodes == 1 and stump.n_leaves == 1
    big_min = ft.TrainConfig(
        **{**SMALL.to_dict(), "min_samples_split": 10**6, "features": SMALL.features}
    )
    assert ft.train_tree(depth, lab, big_min, seed=0).n_nodes == 1
    high_gain = ft.TrainConfig(**{**SMALL.to_dict(), "min_gain": 10.0, "features": SMALL.features})
    assert ft.train_tree(depth, lab, high_gain, seed=0).n_nodes == 1
    # a single-class dataset is pure at the root
    one = np.where(lab == labels.NO_DEPTH, lab, labels.TABLE).astype(np.uint8)
    assert ft.train_tree(depth, one, SMALL, seed=0).n_nodes == 1


def test_bad_frames_are_refused():
    depth, lab = small_frames()
    with pytest.raises(ft.TopsegError, match="uint16"):
        ft.train_tree(depth.astype(np.int32), lab, SMALL, seed=0)
    with pytest.raises(ft.TopsegError, match="shape"):
        ft.train_tree(depth, lab[:, :-1], SMALL, seed=0)
    with pytest.raises(ft.TopsegError, match="no labelled pixels"):
        ft.train_tree(np.zeros_like(depth), lab, SMALL, seed=0)


def test_config_round_trip_and_validation():
    c = ft.TrainConfig(split="axis", max_depth=7, features=FeatureConfig(n_features=75))
    assert ft.TrainConfig.from_dict(c.to_dict()) == c
    assert ft.TrainConfig().to_dict()["features"]["n_features"] == 300
    with pytest.raises(ValueError, match="split"):
        ft.TrainConfig(split="oblique")


FIXTURE = Path(__file__).parent / "data" / "small_trees.npz"


@pytest.mark.parametrize(("split", "seed"), [("linear", 3), ("axis", 5)])
def test_trees_match_those_trained_before_the_split_into_criterion_splitter_builder(split, seed):
    """tests/data/small_trees.npz holds trees trained on `small_frames()` with SMALL by a
    single-module trainer (no criterion/splitter/builder kernels): the kernels give the same
    bits, with probes off the image reading the background as that trainer's did."""
    depth, lab = small_frames()
    then = dataclasses.replace(SMALL.features, off_image="background")
    config = ft.TrainConfig(**{**SMALL.to_dict(), "split": split, "features": then})
    tree = ft.train_tree(depth, lab, config, seed=seed)
    with np.load(FIXTURE) as saved:
        names = sorted(k.removeprefix(f"{split}_") for k in saved.files if k.startswith(split))
        assert names == sorted(tree.arrays())
        for name, arr in tree.arrays().items():
            np.testing.assert_array_equal(arr, saved[f"{split}_{name}"], err_msg=name)
            assert arr.dtype == saved[f"{split}_{name}"].dtype, name


def test_a_tree_reads_probes_off_the_image_as_its_features_say():
    """The builder passes `FeatureConfig.off_image` to the tree, so inference reads probes off
    the image as training did; the default is the nearest edge pixel."""
    depth, lab = small_frames()
    assert ft.train_tree(depth, lab, SMALL, seed=0).nearest_off_image is True
    then = dataclasses.replace(SMALL.features, off_image="background")
    config = ft.TrainConfig(**{**SMALL.to_dict(), "features": then})
    assert ft.train_tree(depth, lab, config, seed=0).nearest_off_image is False
