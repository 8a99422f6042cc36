"""Forest inference: the numba kernels against a plain numpy traversal on random forests."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from reference import (
    adaptive_reference,
    apply_reference,
    bounded_second_reference,
    predict_reference,
    trees_walked_reference,
    upsample_reference,
)
from segmenter_rules import relabel_as_the_segmenter

from topseg.core import labels
from topseg.core.crf.argmax import Summary, argmax_confidence
from topseg.core.forest import (
    Forest,
    fill_posteriors,
    predict_labels,
    predict_proba,
    random_tree,
)
from topseg.core.forest import predict as predict_module
from topseg.core.forest.edge_gaps import fill_edge_gaps
from topseg.core.forest.features import FAR_OFFSET, OFF_IMAGE
from topseg.core.forest.inputs import ModelInput, as_input
from topseg.core.forest.predict import (
    MAX_PAD,
    SETTLE_REACH_MM,
    UPSAMPLE_SIGMA_MM,
    _padded,
    _upsample,
    apply,
    height_weights,
    inference_table,
    probe_pad,
)
from topseg.core.forest.tree import Tree, node_depths

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"


def random_forest(seed, k, depths=(3, 6, 5), scale=300.0, nearest=False):
    """A random forest whose probes off the image read background, or the nearest edge pixel."""
    rng = np.random.default_rng(seed)
    forest = Forest.from_trees([random_tree(rng, d, k, 40 * 2500.0, scale) for d in depths])
    return dataclasses.replace(forest, nearest_off_image=nearest)


def random_depth(seed, shape=(29, 41)):
    rng = np.random.default_rng(seed)
    depth = rng.integers(1500, 4000, size=shape).astype(np.uint16)
    depth[rng.random(shape) < 0.1] = 0
    depth[rng.random(shape) < 0.02] = 12000  # beyond the background constant
    return depth


@pytest.mark.parametrize("nearest", [False, True])  # off the image: background, the edge
@pytest.mark.parametrize("max_pad", [MAX_PAD, 0])  # a wide border, or probes clamped
@pytest.mark.parametrize("k", [1, 2, 3])
@pytest.mark.parametrize("seed", range(3))
def test_predict_matches_reference(k, seed, max_pad, nearest):
    forest = random_forest(seed, k, nearest=nearest)
    depth = random_depth(seed + 10)
    got = predict_proba(forest, depth, max_pad=max_pad)
    np.testing.assert_array_equal(got, predict_reference(forest, depth))


@pytest.mark.parametrize("nearest", [False, True])
@pytest.mark.parametrize("k", [1, 2])
def test_apply_matches_reference(k, nearest):
    forest = random_forest(20 + k, k, nearest=nearest)
    depth = random_depth(30 + k)
    leaves = apply(forest, depth)
    assert leaves.shape == (forest.n_trees, *depth.shape)
    np.testing.assert_array_equal(leaves[:, depth > 0], apply_reference(forest, depth))
    assert np.all(leaves[:, depth == 0] == -1)
    assert np.all(forest.left[leaves[:, depth > 0]] == -1)


def test_trees_of_unequal_depth_and_a_lone_leaf():
    rng = np.random.default_rng(4)
    trees = [random_tree(rng, 0, 2, 1e5), random_tree(rng, 7, 2, 1e5), random_tree(rng, 1, 2, 1e5)]
    forest = Forest.from_trees(trees)
    assert forest.depth == 7 and node_depths(forest.left, forest.roots)[forest.roots].max() == 0
    depth = random_depth(5, (17, 64))
    np.testing.assert_array_equal(predict_proba(forest, depth), predict_reference(forest, depth))


def test_posterior_is_the_mean_of_leaf_distributions():
    forest = random_forest(7, 2)
    depth = random_depth(8)
    proba = predict_proba(forest, depth)
    has = depth > 0
    np.testing.assert_allclose(proba[has].sum(axis=1), 1.0, rtol=1e-5)
    assert np.all(proba[~has] == 0)
    # one tree alone gives exactly its leaves' rows
    single = Forest.from_trees([forest.tree(1)])
    p1 = predict_proba(single, depth)[has]
    assert (p1[:, None, :] == single.posteriors[None]).all(axis=2).any(axis=1).all()


@pytest.mark.parametrize("shape", [(31, 45), (32, 44)])
def test_stride_walks_a_grid_and_upsamples_by_height(shape):
    forest = random_forest(9, 2)
    depth = random_depth(10, shape)
    full = predict_proba(forest, depth)
    inp = as_input(depth)
    for s in (2, 3, 4):
        fast = predict_proba(forest, depth, stride=s)
        np.testing.assert_array_equal(fast[::s, ::s], full[::s, ::s])
        want = upsample_reference(full, inp.values, inp.floor, s, UPSAMPLE_SIGMA_MM)
        np.testing.assert_allclose(fast, want, rtol=2e-5, atol=1e-6)
        assert np.all(fast[depth == 0] == 0)
        informed = want.sum(axis=2) > 0  # some grid neighbour has depth
        assert informed[depth > 0].mean() > 0.9
        np.testing.assert_allclose(fast[informed].sum(axis=1), 1.0, rtol=1e-5)


@pytest.mark.parametrize("stride", [1, 2, 3])
def test_the_summary_filled_with_the_posteriors_is_their_argmax_confidence(stride):
    forest = random_forest(70 + stride, 2)
    inp = random_input(80 + stride, (31, 45))
    summary = Summary(*(np.full_like(a, 7) for a in Summary.empty(inp.shape)))  # stale buffers
    proba = predict_proba(forest, inp, stride=stride, summary=summary)
    for got, want in zip(summary, argmax_confidence(proba, inp.values > 0), strict=True):
        np.testing.assert_array_equal(got, want)
    with pytest.raises(ValueError, match="summary"):
        predict_proba(forest, inp, summary=Summary.empty((3, 3)))


def assert_lazy_summary(lazy, eager, inp, stride) -> float:
    """A lazy grid's summary against the eager one's: the same argmax and top posterior
    everywhere; the second posterior is the eager one, or at in-between pixels whose corners
    agree the bound `bounded_second_reference` gives, never below the eager one. Returns the
    share of pixels with a value that hold a bound."""
    np.testing.assert_array_equal(lazy.amax, eager.amax)
    np.testing.assert_array_equal(lazy.pmax, eager.pmax)
    assert np.all(lazy.psecond >= eager.psecond)
    bound = bounded_second_reference(eager, inp.values, inp.floor, stride, UPSAMPLE_SIGMA_MM)
    exact = np.isnan(bound)
    np.testing.assert_array_equal(lazy.psecond[exact], eager.psecond[exact])
    np.testing.assert_allclose(lazy.psecond[~exact], bound[~exact], rtol=1e-5, atol=1e-7)
    return float((~exact).sum() / (inp.values > 0).sum())


@pytest.mark.parametrize("stride", [2, 3, 4])
def test_lazy_posteriors_keep_the_summary_and_fill_to_the_eager_values(stride):
    forest = random_forest(90 + stride, 2)
    inp = random_input(95 + stride, (31, 45))
    eager_summary = Summary.empty(inp.shape)
    eager = predict_proba(forest, inp, stride=stride, summary=eager_summary)
    lazy_summary = Summary.empty(inp.shape)
    lazy = predict_proba(
        forest,
        inp,
        out=np.full_like(eager, np.nan),
        stride=stride,
        summary=lazy_summary,
        lazy=True,
    )
    assert_lazy_summary(lazy_summary, eager_summary, inp, stride)
    np.testing.assert_array_equal(lazy[::stride, ::stride], eager[::stride, ::stride])
    assert np.isnan(lazy).any()  # the in-between pixels were left out
    mask = np.random.default_rng(stride).random(inp.shape) < 0.3
    fill_posteriors(inp, lazy, stride, mask)
    np.testing.assert_array_equal(lazy[mask], eager[mask])
    fill_posteriors(inp, lazy, stride)
    np.testing.assert_array_equal(lazy, eager)
    with pytest.raises(ValueError, match="mask"):
        fill_posteriors(inp, lazy, stride, np.ones((3, 3), bool))


def test_upsampling_keeps_a_height_edge():
    """A step in height between grid columns: pixels take the posterior of their own side."""
    values = np.full((9, 9), 2000, np.uint16)
    values[:, 5:] = 3000  # grid columns 0, 4 | 8: the edge falls between columns 4 and 8
    floor = np.zeros(values.shape, bool)
    proba = np.zeros((9, 9, labels.NUM_CLASSES), np.float32)
    proba[:, :5, 1] = 1.0
    proba[:, 5:, 7] = 1.0
    grid = np.zeros_like(proba)
    grid[::4, ::4] = proba[::4, ::4]
    _upsample(values, floor, 4, height_weights(), grid, *Summary.empty(values.shape), True)
    np.testing.assert_array_equal(grid.argmax(axis=2), proba.argmax(axis=2))


def test_labels_and_no_depth():
    forest = random_forest(11, 2)
    depth = random_depth(12)
    proba = predict_proba(forest, depth)
    lab = predict_labels(forest, depth)
    assert lab.dtype == np.uint8
    assert np.all(lab[depth == 0] == labels.NO_DEPTH)
    has = depth > 0
    np.testing.assert_array_equal(lab[has], proba[has].argmax(axis=1))


def test_reused_output_and_bad_input():
    forest = random_forest(13, 2)
    depth = random_depth(14)
    out = np.full((*depth.shape, forest.n_classes), 7.0, np.float32)
    assert predict_proba(forest, depth, out=out) is out
    np.testing.assert_array_equal(out, predict_reference(forest, depth))
    with pytest.raises(ValueError, match="uint16"):
        predict_proba(forest, depth.astype(np.float32))
    with pytest.raises(ValueError, match="out must be"):
        predict_proba(forest, depth, out=np.empty((3, 3, 11), np.float32))
    with pytest.raises(ValueError, match="stride"):
        predict_proba(forest, depth, stride=0)


def random_input(seed, shape=(29, 41)):
    """A model input with random values, scales and floor gate, whose probes read its edge's
    no-depth regions filled (`FeatureConfig.edge_gaps`)."""
    rng = np.random.default_rng(seed)
    depth = random_depth(seed, shape)
    values = np.where(depth > 0, rng.integers(1, 9999, size=shape), 0).astype(np.uint16)
    scale = np.where(depth > 0, rng.uniform(1 / 4000, 1 / 1500, size=shape), 0).astype(np.float32)
    floor = (depth > 0) & (rng.random(shape) < 0.3)
    probes, filled = fill_edge_gaps(values)
    assert filled > 0  # the kernels are checked reading an image other than the values
    return ModelInput(values, scale, floor, probes)


@pytest.mark.parametrize("nearest", [False, True])
@pytest.mark.parametrize("max_pad", [MAX_PAD, 0])
@pytest.mark.parametrize("k", [1, 2, 3])
def test_predict_on_a_model_input_matches_reference(k, max_pad, nearest):
    forest = random_forest(40 + k, k, nearest=nearest)
    inp = random_input(50 + k)
    got = predict_proba(forest, inp, max_pad=max_pad)
    np.testing.assert_array_equal(got, predict_reference(forest, inp))
    floor = inp.floor
    assert np.all(got[floor, labels.BACKGROUND] == 1) and np.all(got[floor].sum(axis=1) == 1)
    leaves = apply(forest, inp)
    walked = (inp.values > 0) & ~floor
    np.testing.assert_array_equal(leaves[:, walked], apply_reference(forest, inp))
    assert np.all(leaves[:, ~walked] == -1)
    lab = predict_labels(forest, inp)
    assert np.all(lab[floor] == labels.BACKGROUND) and np.all(lab[inp.values == 0] == 255)


def test_stride_on_a_model_input_keeps_the_floor_gate():
    forest = random_forest(60, 2)
    inp = random_input(61, (31, 45))
    full = predict_proba(forest, inp)
    fast = predict_proba(forest, inp, stride=2)
    np.testing.assert_array_equal(fast[::2, ::2], full[::2, ::2])
    assert np.all(fast[inp.floor, labels.BACKGROUND] == 1)
    assert np.all(fast[inp.values == 0] == 0)


def test_legacy_path_is_bit_identical_to_before():
    """A raw-depth model on demo.mcap frames gives exactly what the code before height inputs
    gave: tests/data/legacy_model.npz and legacy_posteriors.npz were both made by that code
    (06e0f6e): the model trained on demo frames, its posteriors and realtime-CRF labels."""
    from topseg.core.forest.inputs import legacy_input
    from topseg.core.segmenter import Segmenter

    fx = np.load(DATA / "legacy_posteriors.npz", allow_pickle=False)
    seg = Segmenter.from_file(DATA / "legacy_model.npz", crf="realtime")
    assert not seg.reads_height
    r0, r1, c0, c1 = fx["crop"]
    for depth, proba, lab in zip(fx["depth"], fx["proba_crop"], fx["labels"], strict=True):
        np.testing.assert_array_equal(predict_proba(seg.forest, depth)[r0:r1, c0:c1], proba)
        inp = legacy_input(depth)
        np.testing.assert_array_equal(predict_proba(seg.forest, inp)[r0:r1, c0:c1], proba)
        result = seg.label(depth)
        # the labels of that code, then the blobs too small to be heads or furniture and the
        # satellite heads (added since)
        want = lab.copy()
        relabel_as_the_segmenter(want, depth, seg.camera)
        np.testing.assert_array_equal(result.labels, want)
        assert result.floor_share == 0.0


def ragged_tree(rng, depth, k, off_image_share=0.3):
    """A random tree with leaves at every level up to `depth` (the pixels of a row arrive at
    different levels, as in a trained tree), breadth-first; `off_image_share` of the split
    features probe v off every image (`features.OFF_IMAGE`), as absolute features do."""
    full = random_tree(rng, depth, k, 40 * 2500.0)
    nodes, levels, splits = [0], [0], []
    for i in range(2 ** (depth + 1)):
        if i == len(nodes):
            break
        split = levels[i] < depth and (i == 0 or rng.random() < 0.75)
        splits.append(split)
        if split:
            nodes += [2 * nodes[i] + 1, 2 * nodes[i] + 2]
            levels += [levels[i] + 1] * 2
    ids, split = np.array(nodes), np.array(splits)
    left = np.full(ids.size, -1, np.int32)
    left[split] = 1 + 2 * np.arange(split.sum())  # each split appended its two children
    leaf = np.full(ids.size, -1, np.int32)
    leaf[~split] = np.arange((~split).sum())
    offsets = full.offsets[ids].copy()
    offsets[..., 2:][split[:, None] & (rng.random((ids.size, k)) < off_image_share)] = OFF_IMAGE
    posteriors = rng.dirichlet(np.full(labels.NUM_CLASSES, 0.3), size=(~split).sum())
    return Tree(
        offsets, full.weights[ids], full.threshold[ids], left, leaf, posteriors.astype(np.float32)
    )


@pytest.mark.parametrize("nearest", [False, True])
@pytest.mark.parametrize("k", [1, 2, 3])
def test_ragged_trees_with_off_image_probes_match_reference(k, nearest):
    rng = np.random.default_rng(100 + k)
    forest = Forest.from_trees([ragged_tree(rng, d, k) for d in (9, 4, 12)])
    forest = dataclasses.replace(forest, nearest_off_image=nearest)
    depths = node_depths(forest.left, forest.roots)[forest.left < 0]
    assert depths.min() < depths.max() - 3  # leaves at many levels
    assert np.any(forest.offsets == OFF_IMAGE)
    for inp in (random_input(110 + k, (33, 47)), as_input(random_depth(120 + k, (33, 47)))):
        np.testing.assert_array_equal(predict_proba(forest, inp), predict_reference(forest, inp))
        fast = predict_proba(forest, inp, stride=3)
        np.testing.assert_array_equal(fast[::3, ::3], predict_reference(forest, inp)[::3, ::3])


@pytest.mark.parametrize("k", [1, 2, 3])
def test_the_inference_table_holds_each_split_once_in_aligned_records(k):
    rng = np.random.default_rng(130 + k)
    forest = Forest.from_trees([ragged_tree(rng, 6, k), random_tree(rng, 0, k, 1e5)])
    table = inference_table(forest)
    assert inference_table(forest) is table  # packed once per forest
    split = np.flatnonzero(forest.left >= 0)
    s = table.n_splits
    assert s == split.size
    record = table.words.strides[0]
    assert table.words.ctypes.data % 64 == 0 and (record == 32 or record % 64 == 0)
    assert record >= 4 * (6 * k + 3)
    f, w = table.fields, table.words
    # a far v (an absolute feature's) is a flag with zero offsets, the rest as in the forest
    offsets = forest.offsets[split]
    far = np.abs(offsets[:, :, 2]) >= FAR_OFFSET
    assert np.any(far) and np.any(~far)
    np.testing.assert_array_equal(w[:s, 5 * k + 3 : 6 * k + 3], far)
    offsets[:, :, 2:][far] = 0
    np.testing.assert_array_equal(f[:s, : 4 * k], offsets.reshape(s, 4 * k))
    assert table.reach == np.abs(offsets).max() < FAR_OFFSET
    np.testing.assert_array_equal(f[:s, 4 * k : 5 * k], forest.weights[split])
    np.testing.assert_array_equal(f[:s, 5 * k], forest.threshold[split])
    assert f[s, 5 * k] == np.inf and np.all(f[s, : 5 * k] == 0)  # the arrived stand-in
    # each state names one node: a split's row, or n_splits + a leaf's posterior row
    node_of_state = np.empty(s + forest.posteriors.shape[0], np.int64)
    node_of_state[:s] = split
    leaves = np.flatnonzero(forest.left < 0)
    node_of_state[s + forest.leaf[leaves]] = leaves
    np.testing.assert_array_equal(node_of_state[w[:s, 5 * k + 1]], forest.left[split])
    np.testing.assert_array_equal(node_of_state[w[:s, 5 * k + 2]], forest.left[split] + 1)
    np.testing.assert_array_equal(node_of_state[table.roots], forest.roots)
    assert table.roots[1] == s + forest.leaf[forest.roots[1]]  # the lone leaf: arrived


def blocky_input(seed, shape=(61, 81)):
    """A model input of four flat blocks at random heights beside a floor band, with a few
    noisy pixels and holes: regions where a coarse grid settles the finer one (probes of
    `short_forest` stay inside a block), and edges where it does not."""
    rng = np.random.default_rng(seed)
    h, w = shape
    values = np.full(shape, 3400, np.uint16)  # the floor band: the last fifth of the columns
    for rows in (slice(0, h // 2), slice(h // 2, h)):
        for cols in (slice(0, 2 * w // 5), slice(2 * w // 5, 4 * w // 5)):
            values[rows, cols] = rng.integers(2000, 3200)
    noisy = rng.random(shape) < 0.004
    values[noisy] = rng.integers(1500, 3500, size=noisy.sum())
    values[rng.random(shape) < 0.004] = 0
    floor = (values == 3400) & (rng.random(shape) < 0.8)
    scale = np.float32(1) / np.maximum(values, 1).astype(np.float32)
    return ModelInput(values, scale, floor)


def short_forest(seed):
    """Three random trees whose probes reach at most ~5 px at these depths."""
    rng = np.random.default_rng(seed)
    return Forest.from_trees([random_tree(rng, d, 2, 4 * 2500.0, 150.0) for d in (4, 6, 5)])


@pytest.mark.parametrize("early", [False, True])
@pytest.mark.parametrize(("stride", "levels"), [(2, 1), (3, 1), (2, 2), (4, 1), (1, 2)])
def test_adaptive_grid_matches_reference(stride, levels, early, monkeypatch):
    # three random trees rarely agree on more than a fifth of the posterior
    monkeypatch.setattr(predict_module, "SETTLE_CONFIDENCE", 0.15)
    forest = short_forest(300 + stride)
    inp = blocky_input(310 + stride + levels)
    early_exit = median_confidence(forest, inp) if early else None
    walked = np.zeros(inp.shape, np.uint8)
    got = predict_proba(
        forest, inp, stride=stride, adaptive=levels, walked=walked, early_exit=early_exit
    )
    want, want_walked = adaptive_reference(
        forest,
        inp,
        stride,
        levels if stride > 1 else 0,
        0.15,
        SETTLE_REACH_MM,
        UPSAMPLE_SIGMA_MM,
        early_exit,
    )
    np.testing.assert_array_equal(walked, want_walked)
    np.testing.assert_allclose(got, want, rtol=2e-5, atol=1e-6)
    if early:  # some walked grid pixels stopped after two trees, some walked all three
        assert {2, 3} <= set(np.unique(walked))
    if stride > 1:  # both branches ran: some grid pixels settled, some walked
        grid = np.zeros(inp.shape, bool)
        grid[::stride, ::stride] = True
        walkable = grid & (inp.values > 0) & ~inp.floor
        assert 0.1 < np.count_nonzero(walked) / walkable.sum() < 0.9
        plain = np.zeros(inp.shape, np.uint8)
        predict_proba(forest, inp, stride=stride, walked=plain)
        np.testing.assert_array_equal(plain > 0, walkable)
    else:  # every pixel is walked at stride 1: there is no grid to adapt
        np.testing.assert_array_equal(got, predict_proba(forest, inp, early_exit=early_exit))


@pytest.mark.parametrize("levels", [1, 2])
def test_adaptive_grid_summary_and_lazy_fill_are_the_eager_ones(levels, monkeypatch):
    monkeypatch.setattr(predict_module, "SETTLE_CONFIDENCE", 0.15)
    forest = short_forest(330 + levels)
    inp = blocky_input(340 + levels)
    eager_summary = Summary.empty(inp.shape)
    eager = predict_proba(forest, inp, stride=2, summary=eager_summary, adaptive=levels)
    for got, want in zip(eager_summary, argmax_confidence(eager, inp.values > 0), strict=True):
        np.testing.assert_array_equal(got, want)
    lazy_summary = Summary.empty(inp.shape)
    lazy = predict_proba(
        forest,
        inp,
        out=np.full_like(eager, np.nan),
        stride=2,
        summary=lazy_summary,
        lazy=True,
        adaptive=levels,
    )
    assert assert_lazy_summary(lazy_summary, eager_summary, inp, 2) > 0.2
    fill_posteriors(inp, lazy, 2)
    np.testing.assert_array_equal(lazy, eager)


def median_confidence(forest, frame, trees=2):
    """An early-exit confidence that stops about half the walked pixels after `trees` trees:
    of the averages the pixels reach there, the one closest to halving them (they tie often)."""
    leaves = apply_reference(forest, frame)[:trees]
    best = (sum(forest.posteriors[forest.leaf[node]] for node in leaves) / trees).max(axis=1)
    candidates = np.unique(best)
    stopped = np.array([np.mean(best >= c) for c in candidates])
    return float(candidates[np.argmin(np.abs(stopped - 0.5))])


@pytest.mark.parametrize("k", [1, 2])
@pytest.mark.parametrize("seed", range(3))
def test_early_exit_matches_reference(k, seed):
    """A pixel whose first two (or three) trees agree stops; its posterior is the average of
    the trees it walked, bit for bit as numpy's, and `walked` counts them."""
    forest = random_forest(60 + seed, k, depths=(3, 6, 5, 4))
    inp = random_input(70 + seed)
    for early_exit in (median_confidence(forest, inp), 1.0):
        walked = np.zeros(inp.shape, np.uint8)
        got = predict_proba(forest, inp, walked=walked, early_exit=early_exit)
        np.testing.assert_array_equal(got, predict_reference(forest, inp, early_exit))
        trees = trees_walked_reference(forest, inp, early_exit)
        np.testing.assert_array_equal(walked, trees)
        if early_exit < 1.0:  # both kinds of pixel: stopped after two trees, walked on
            assert np.count_nonzero(trees == 2) > 0.2 * np.count_nonzero(trees)
            assert np.count_nonzero(trees > 2) > 0.2 * np.count_nonzero(trees)
    walked = np.zeros(inp.shape, np.uint8)
    np.testing.assert_array_equal(
        predict_proba(forest, inp, walked=walked), predict_reference(forest, inp)
    )
    np.testing.assert_array_equal(walked, trees_walked_reference(forest, inp))
    assert set(np.unique(walked)) == {0, 4}


def test_adaptive_grid_refuses_bad_arguments():
    forest = random_forest(350, 2)
    inp = blocky_input(351)
    with pytest.raises(ValueError, match="adaptive"):
        predict_proba(forest, inp, stride=2, adaptive=-1)
    with pytest.raises(ValueError, match="walked"):
        predict_proba(forest, inp, stride=2, walked=np.zeros((3, 3), np.uint8))
    with pytest.raises(ValueError, match="walked"):
        predict_proba(forest, inp, stride=2, walked=np.zeros(inp.shape, bool))
    for bad in (0.0, -0.1, 1.5):
        with pytest.raises(ValueError, match="early_exit"):
            predict_proba(forest, inp, stride=2, early_exit=bad)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_realtime_crf_labels_a_lazy_grid_as_it_labels_the_eager_one(seed, monkeypatch):
    """A lazy adaptive grid (bounded second posteriors, posteriors filled where the band
    reads them) gives the realtime CRF's labels of the eager one (the bound itself against
    a larger band: `test_crf_realtime.py`)."""
    from functools import partial

    from topseg.core.crf import CRFConfig, segment_crf

    monkeypatch.setattr(predict_module, "SETTLE_CONFIDENCE", 0.15)
    forest = short_forest(360 + seed)
    inp = blocky_input(370 + seed)
    config = CRFConfig(mode="realtime", confidence=0.3)
    eager_summary = Summary.empty(inp.shape)
    eager = predict_proba(forest, inp, stride=2, summary=eager_summary, adaptive=1)
    want = segment_crf(eager, inp.values, config, eager_summary)
    lazy_summary = Summary.empty(inp.shape)
    lazy = np.full_like(eager, np.nan)
    predict_proba(forest, inp, lazy, stride=2, summary=lazy_summary, lazy=True, adaptive=1)
    fill = partial(fill_posteriors, inp, lazy, 2)
    got = segment_crf(lazy, inp.values, config, lazy_summary, fill)
    assert np.any(lazy_summary.psecond != eager_summary.psecond)  # some seconds are bounds
    assert np.any(want != eager_summary.amax)  # the CRF did change some labels
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("nearest", [False, True])
@pytest.mark.parametrize("pad", [1, 3, 40])
@pytest.mark.parametrize("shape", [(1, 1), (7, 5), (31, 45)])
def test_the_padded_probe_image_is_the_values_with_a_background_or_edge_border(shape, pad, nearest):
    rng = np.random.default_rng(shape[0])
    values = rng.integers(0, 12000, size=shape).astype(np.uint16)
    values[rng.random(shape) < 0.2] = 0
    background = 10000
    inside = np.where((values != 0) & (values <= background), values, background)
    if nearest:
        want = np.pad(inside, pad, mode="edge").astype(np.uint16).ravel()
    else:
        want = np.pad(inside, pad, constant_values=background).astype(np.uint16).ravel()
    got = _padded(values, np.int32(background), np.int32(pad), nearest)
    assert got.dtype == np.uint16
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("seed", range(3))
def test_the_probe_pad_bounds_every_rounded_probe(seed):
    """No probe of an offset within the reach, at a scale within the frame's, moves farther
    than the pad less one (float32 rounding as the kernel does it)."""
    rng = np.random.default_rng(seed)
    reach = float(rng.uniform(1e3, 1e5))
    scale = rng.uniform(0, 1 / float(rng.uniform(200, 5000)), (40, 50)).astype(np.float32)
    pad = probe_pad(reach, scale)
    top = scale.max()
    offsets = np.concatenate([[reach, -reach], rng.uniform(-reach, reach, 10000)])
    inv = np.concatenate([[top], rng.choice(scale.ravel(), 9)]).astype(np.float32)
    moved = np.floor(offsets.astype(np.float32)[:, None] * inv + np.float32(0.5))
    assert np.abs(moved).max() <= pad - 1
    assert probe_pad(reach, np.zeros((0, 0), np.float32)) == 2
    assert probe_pad(np.inf, scale) == np.inf


@pytest.mark.parametrize("nearest", [False, True])
@pytest.mark.parametrize("k", [1, 2])
def test_a_frame_whose_probes_reach_past_the_border_is_walked_with_clamped_probes(k, nearest):
    """Pixels a few cm from the camera move probes farther than MAX_PAD: the kernel then
    clamps them, with the reference's results; so does a forest whose offsets reach far."""
    forest = random_forest(60 + k, k, nearest=nearest)
    inp = random_input(70 + k)
    scale = inp.scale.copy()
    scale[3:6, 4:9] = np.where(scale[3:6, 4:9] > 0, np.float32(1 / 20.0), 0)  # 2 cm away
    near = dataclasses.replace(inp, scale=scale)  # its probes too
    assert probe_pad(inference_table(forest).reach, near.scale) > MAX_PAD
    np.testing.assert_array_equal(predict_proba(forest, near), predict_reference(forest, near))
    fast = predict_proba(forest, near, stride=2, early_exit=0.6)
    clamped = predict_proba(forest, near, stride=2, early_exit=0.6, max_pad=0)
    np.testing.assert_array_equal(fast, clamped)


def test_a_far_v_offset_reads_the_background_at_any_scale():
    """An absolute feature's v reads the background even where its offset times a tiny
    scale would land inside the frame (`features.FAR_OFFSET`): in training's features, the
    plain walk and the fast kernel alike."""
    from reference import extract_reference

    from topseg.core.forest.features import extract_features

    rng = np.random.default_rng(5)
    forest = Forest.from_trees([ragged_tree(rng, d, 2) for d in (8, 10)])
    assert np.any(forest.offsets == OFF_IMAGE)
    inp = random_input(80, (25, 30))
    tiny = np.where(inp.scale > 0, np.float32(1e-8), 0).astype(np.float32)  # 1e9 -> 10 px
    frame = ModelInput(inp.values, tiny, inp.floor)
    want = predict_reference(forest, frame)
    for max_pad in (MAX_PAD, 0):
        np.testing.assert_array_equal(predict_proba(forest, frame, max_pad=max_pad), want)
    rows, cols = np.nonzero(frame.values)
    offsets = np.array([[3e4, -2e4, OFF_IMAGE, OFF_IMAGE]], np.float32)
    got = extract_features(frame, rows, cols, offsets, 10000)
    assert np.all(got[:, 0] == frame.values[rows, cols].astype(np.int32) - 10000)
    np.testing.assert_array_equal(got, extract_reference(frame, rows, cols, offsets, 10000))


def test_the_walk_takes_every_grid_row_once_even_rows_first():
    from topseg.core.forest.predict import _interleaved

    for n in range(1, 12):
        order = [_interleaved(j, n) for j in range(n)]
        assert sorted(order) == list(range(n))
        assert order[: (n + 1) // 2] == list(range(0, n, 2))
