"""The real-time CRF's numba kernels against plain numpy / scipy references."""

from __future__ import annotations

import numpy as np
import pytest
from reference import band_problem_reference, reference_free, reference_settled
from scipy import ndimage

from topseg.core import labels as L
from topseg.core.crf import CRFConfig, edge_weights, potts_energy
from topseg.core.crf.expansion import alpha_expansion, energy
from topseg.core.crf.realtime import (
    BAND_PARTS,
    PARALLEL_BAND_PIXELS,
    _band_problem_parallel,
    _band_problem_serial,
    argmax_confidence,
    band_mask,
    band_parts,
    band_problem,
    float_gain,
    free_mask,
    number_band,
    segment_realtime,
    solve_band,
)
from topseg.services.batch.bench.crf_standin import forest_like_posteriors, synthetic_scene

C = L.PAPER_NUM_CLASSES  # a paper model's posteriors, as the stand-in forest's
CROSS = ndimage.generate_binary_structure(2, 1)


def random_frame(rng, h=40, w=50):
    proba = rng.dirichlet(np.full(C, 0.2), size=(h, w)).astype(np.float32)
    depth = rng.integers(1000, 3500, (h, w)).astype(np.uint16)
    depth[rng.random((h, w)) < 0.05] = 0
    return proba, depth


def test_argmax_confidence_matches_numpy():
    rng = np.random.default_rng(0)
    proba, depth = random_frame(rng)
    valid = depth > 0
    proba[0, :5] = 0.1  # ties: the first maximum, as numpy's argmax
    amax, pmax, psecond = argmax_confidence(proba, valid)
    assert np.array_equal(amax[valid], proba.argmax(axis=2)[valid])
    assert (amax[~valid] == L.NO_DEPTH).all()
    ordered = np.sort(proba, axis=2)
    assert np.array_equal(pmax[valid], ordered[..., -1][valid])
    assert np.array_equal(psecond[valid], ordered[..., -2][valid])


@pytest.mark.parametrize("ring", [0, 1, 3])
def test_free_mask_matches_numpy(ring):
    rng = np.random.default_rng(ring)
    proba, depth = random_frame(rng)
    proba[10:30, 10:40] = 0.0  # a confident, agreeing block the mask must leave fixed
    proba[10:30, 10:40, 3] = 1.0
    proba[5:8, 5:45] = 0.001  # a strip so sure of label 6 that it is settled
    proba[5:8, 5:45, 6] = 0.99
    valid = depth > 0
    amax, pmax, psecond = argmax_confidence(proba, valid)
    for smoothness in (0.5, 2.0):
        cfg = CRFConfig(smoothness=smoothness)
        settled = reference_settled(proba, valid, smoothness, cfg.eps)
        assert settled[6, 20:30].all() == (smoothness == 0.5)
        for confidence in (0.3, 0.6, 0.9):
            free = free_mask(amax, pmax, psecond, valid, confidence, ring, smoothness, cfg.eps)
            expected = reference_free(amax, pmax, valid, confidence, ring, settled)
            assert np.array_equal(free, expected)
            assert not free[20, 25]


def test_free_mask_reads_confidence_as_float32_like_numpy():
    """A top posterior equal to the confidence rounded to float32 reaches it (0.7 rounds
    down in float32): the kernel decides as the numpy reference does, at the boundary too."""
    h, w = 3, 9
    amax = np.zeros((h, w), np.uint8)
    valid = np.ones((h, w), bool)
    psecond = np.full((h, w), 0.2, np.float32)
    for confidence in (0.3, 0.6, 0.7):
        c = np.float32(confidence)
        below, above = np.nextafter(c, np.float32(0)), np.nextafter(c, np.float32(1))
        pmax = np.tile(np.array([below, c, above], np.float32), (h, 3))
        settled = np.zeros((h, w), bool)
        free = free_mask(amax, pmax, psecond, valid, confidence, 0, 1.0, 1e-6)
        assert np.array_equal(free, reference_free(amax, pmax, valid, confidence, 0, settled))
        assert np.array_equal(free[1], np.tile([True, False, False], 3))


def test_settled_pixels_never_move_in_a_full_expansion():
    """Leaving settled pixels out is exact: expansion over every pixel never moves them."""
    rng = np.random.default_rng(9)
    proba = rng.dirichlet(np.full(C, 0.05), size=(30, 40)).astype(np.float32)
    depth = np.full((30, 40), 2000, np.uint16)
    cfg = CRFConfig(smoothness=0.6)
    valid = depth > 0
    amax, _, _ = argmax_confidence(proba, valid)
    wh, wv = edge_weights(depth, cfg)
    settled = reference_settled(proba, valid, cfg.smoothness, cfg.eps)
    assert 0.1 < settled.mean() < 0.9
    index, n = number_band(valid)  # every pixel in the problem
    pix, unary, nbr, nw, init = band_problem(
        proba, amax, index, n, wh, wv, np.float32(cfg.eps), 1000.0
    )
    x = alpha_expansion(unary, nbr, nw, init)
    assert (x != init).any()
    assert np.array_equal(x[settled.ravel()[pix]], init[settled.ravel()[pix]])


def test_band_ids_are_row_major():
    rng = np.random.default_rng(1)
    free = rng.random((60, 70)) < 0.45
    index, n = number_band(free)
    assert n == free.sum()
    assert np.array_equal(index[free], np.arange(n))
    assert (index[~free] == -1).all()


def band_of(rng, cfg, shape=(40, 50)):
    proba, depth = random_frame(rng, *shape)
    valid = depth > 0
    amax, pmax, psecond = argmax_confidence(proba, valid)
    wh, wv = edge_weights(depth, cfg)
    free = free_mask(amax, pmax, psecond, valid, cfg.confidence, cfg.ring, cfg.smoothness, cfg.eps)
    index, n = number_band(free)
    return proba, depth, amax, wh, wv, index, n


def test_band_problem_keeps_the_frame_energy_up_to_a_constant():
    """Band energy of any band labeling + a constant == the frame's Potts energy."""
    rng = np.random.default_rng(2)
    cfg = CRFConfig(smoothness=0.8, depth_sigma_mm=500.0, confidence=0.5, ring=1)
    proba, depth, amax, wh, wv, index, n = band_of(rng, cfg)
    scale = 1e5  # fine rounding, so the constant shows
    pix, unary, nbr, nw, init = band_problem(
        proba, amax, index, n, wh, wv, np.float32(cfg.eps), scale
    )
    assert np.array_equal(init, amax.ravel()[pix])
    assert np.array_equal(pix, np.flatnonzero(index.ravel() >= 0))
    offsets = []
    for _ in range(6):
        x = rng.integers(0, C, n)
        frame = amax.copy()
        frame.ravel()[pix] = x
        band = energy(x, unary.astype(np.int64), nbr.astype(np.int64), nw.astype(np.int64))
        offsets.append(potts_energy(frame, proba, depth, cfg) - band / scale)
    assert np.ptp(offsets) < 1e-2


@pytest.mark.parametrize("shape", [(40, 50), (90, 120)])
def test_band_problem_matches_the_reference_on_both_paths(shape):
    """A small band is built serially, one of PARALLEL_BAND_PIXELS or more on numba's threads
    (row by row): both give the numpy reference's problem."""
    rng = np.random.default_rng(11)
    cfg = CRFConfig(smoothness=0.9, depth_sigma_mm=300.0, confidence=0.8, ring=2)
    proba, _, amax, wh, wv, index, n = band_of(rng, cfg, shape)
    assert (n >= PARALLEL_BAND_PIXELS) == (shape == (90, 120))
    eps, scale = np.float32(cfg.eps), 1000.0
    got = band_problem(proba, amax, index, n, wh, wv, eps, scale)
    want = band_problem_reference(proba, amax, index, wh, wv, eps, scale)
    names = ("pix", "nbr", "nw", "init")
    for name, a, b in zip(names, got[:1] + got[2:], want[:1] + want[2:], strict=True):
        assert np.array_equal(a, b), name
    diff = np.abs(got[1].astype(np.int64) - want[1])
    assert diff.max() <= 1 and (diff > 0).mean() < 1e-3  # last-place log differences only
    serial = _band_problem_serial(proba, amax, index, n, wh, wv, eps, scale)
    parallel = _band_problem_parallel(proba, amax, index, n, wh, wv, eps, scale)
    assert all(np.array_equal(a, b) for a, b in zip(serial, parallel, strict=True))


def test_float_gain_is_the_energy_difference():
    rng = np.random.default_rng(5)
    cfg = CRFConfig(smoothness=1.3, confidence=0.6, ring=1)
    proba, depth, amax, wh, wv, index, _ = band_of(rng, cfg)
    pix = np.flatnonzero(index.ravel() >= 0)
    before = potts_energy(amax, proba, depth, cfg)
    for fraction in (0.0, 0.1, 0.5, 1.0):
        after = amax.copy()
        change = pix[rng.random(pix.size) < fraction]
        after.ravel()[change] = rng.integers(0, C, change.size)
        gain = float_gain(proba, amax, after, pix, wh, wv, cfg.eps)
        assert gain == pytest.approx(before - potts_energy(after, proba, depth, cfg), abs=1e-3)


def test_fixed_pixels_keep_the_argmax_and_holes_stay_holes():
    rng = np.random.default_rng(3)
    depth, truth = synthetic_scene(rng, (120, 160))
    proba = forest_like_posteriors(truth, rng)
    cfg = CRFConfig(confidence=0.6, ring=1)
    valid = depth > 0
    amax, _, _ = argmax_confidence(proba, valid)
    free = band_mask(proba, depth, cfg)
    out = segment_realtime(proba, depth, cfg)
    assert np.array_equal(out[~free], amax[~free])
    assert (out[~valid] == L.NO_DEPTH).all()
    assert (out[free] != amax[free]).any()  # the band did get smoothed
    assert potts_energy(out, proba, depth, cfg) < potts_energy(amax, proba, depth, cfg)


def test_smoothness_zero_is_the_argmax():
    rng = np.random.default_rng(4)
    proba, depth = random_frame(rng)
    amax, _, _ = argmax_confidence(proba, depth > 0)
    assert np.array_equal(segment_realtime(proba, depth, CRFConfig(smoothness=0.0)), amax)


@pytest.mark.parametrize("mode", ["none", "realtime"])
def test_a_given_summary_gives_the_same_labels_and_is_never_returned(mode):
    from topseg.core.crf import Summary, argmax_confidence, segment_crf

    rng = np.random.default_rng(31)
    for _ in range(4):
        proba, depth = random_frame(rng)
        cfg = CRFConfig(mode=mode)
        summary = Summary(*argmax_confidence(proba, depth > 0))
        kept = [a.copy() for a in summary]
        got = segment_crf(proba, depth, cfg, summary)
        np.testing.assert_array_equal(got, segment_crf(proba, depth, cfg))
        assert not np.shares_memory(got, summary.amax)  # the caller reuses its buffers
        for a, b in zip(summary, kept, strict=True):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("seed", range(3))
def test_an_upper_bound_of_the_second_posterior_grows_the_band_not_the_labels(seed):
    """A lazy forest grid stores a bound of the second posterior where its corners agree
    (`argmax.Summary`): fewer pixels are settled, the band grows, the labels stay."""
    from topseg.core.crf import Summary

    rng = np.random.default_rng(40 + seed)
    depth, truth = synthetic_scene(rng, (120, 160))
    proba = forest_like_posteriors(truth, rng)
    for cols, label in ((slice(10, 40), 2), (slice(40, 70), 3)):  # two sure blocks, whose
        proba[10:40, cols] = 0.001  # common edge is settled, not sure
        proba[10:40, cols, label] = 0.99
    valid = depth > 0
    cfg = CRFConfig(confidence=0.5)
    exact = Summary(*argmax_confidence(proba, valid))
    bounded = exact.psecond + rng.random(exact.psecond.shape, np.float32) * (
        exact.pmax - exact.psecond
    )
    loose = Summary(exact.amax.copy(), exact.pmax, np.maximum(bounded, exact.psecond))
    args = (valid, cfg.confidence, cfg.ring, cfg.smoothness, cfg.eps)
    exact_band = free_mask(*exact, *args)
    loose_band = free_mask(*loose, *args)
    assert np.all(loose_band >= exact_band) and loose_band.sum() > exact_band.sum()
    want = segment_realtime(proba, depth, cfg, exact)
    np.testing.assert_array_equal(segment_realtime(proba, depth, cfg, loose), want)


def large_band(seed, shape=(240, 320)):
    """A band problem of a forest-like scene, big enough to be split (`solve_band`)."""
    rng = np.random.default_rng(seed)
    depth, truth = synthetic_scene(rng, shape)
    proba = forest_like_posteriors(truth, rng)
    cfg = CRFConfig(confidence=0.5, ring=0)  # a band of several components
    valid = depth > 0
    amax, pmax, psecond = argmax_confidence(proba, valid)
    wh, wv = edge_weights(depth, cfg)
    free = free_mask(amax, pmax, psecond, valid, cfg.confidence, cfg.ring, cfg.smoothness, cfg.eps)
    index, n = number_band(free)
    return free, band_problem(proba, amax, index, n, wh, wv, np.float32(cfg.eps), 1000.0)


@pytest.mark.parametrize("seed", range(3))
def test_band_parts_keep_components_whole_and_balance_them(seed):
    free, (pix, _, nbr, _, _) = large_band(seed)
    parts = band_parts(nbr, 2)
    # scipy's components of the band's graph (edges of weight 0 are not in it: none here)
    comp, n_comp = ndimage.label(free, CROSS)
    comp = comp.ravel()[pix]
    assert n_comp > 2
    for c in range(1, n_comp + 1):
        assert np.unique(parts[comp == c]).size == 1
    sizes = np.bincount(comp)[1:]
    load = np.bincount(parts, minlength=2)
    # greedy largest-first: the parts differ by at most the largest component
    assert abs(load[0] - load[1]) <= sizes.max()


@pytest.mark.parametrize("cycles", [1, 3])
def test_a_split_band_is_solved_component_by_component(cycles):
    """Each part's labels are those of expansion on its own components, solved alone;
    one thread or two, the same."""
    import numba

    _, (_, unary, nbr, nw, init) = large_band(7)
    assert init.size >= PARALLEL_BAND_PIXELS
    labels, gain, changed = solve_band(unary, nbr, nw, init, cycles)
    parts = band_parts(nbr, BAND_PARTS)
    want = np.empty_like(init)
    for k in range(BAND_PARTS):
        ids = np.flatnonzero(parts == k)
        local = np.full(init.size, -1)
        local[ids] = np.arange(ids.size)
        sub_nbr = np.where(nbr[ids] >= 0, local[nbr[ids]], -1).astype(nbr.dtype)
        want[ids] = alpha_expansion(unary[ids], sub_nbr, nw[ids], init[ids], cycles)
    np.testing.assert_array_equal(labels, want)
    assert changed == np.count_nonzero(want != init) > 0
    args = (unary.astype(np.int64), nbr.astype(np.int64), nw.astype(np.int64))
    assert gain == energy(init.astype(np.int64), *args) - energy(want.astype(np.int64), *args)
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        one = solve_band(unary, nbr, nw, init, cycles)
    finally:
        numba.set_num_threads(threads)
    np.testing.assert_array_equal(one[0], labels)
