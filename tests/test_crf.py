"""The Potts CRF: config, energy against a loop reference, both modes against brute force
on tiny grids and against each other on forest-like frames."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from topseg.core import labels as L
from topseg.core.crf import (
    CRFConfig,
    edge_weights,
    potts_energy,
    segment_crf,
    unaries_from_posteriors,
)
from topseg.core.errors import TopsegError
from topseg.services.batch.bench.crf_standin import forest_like_posteriors, synthetic_scene

C = L.PAPER_NUM_CLASSES  # a paper model's posteriors, as the stand-in forest's
EXACT = CRFConfig(mode="exact")
REALTIME = CRFConfig(mode="realtime")
NONE = CRFConfig(mode="none")


def random_posteriors(rng, h, w, concentration=0.3):
    return rng.dirichlet(np.full(C, concentration), size=(h, w)).astype(np.float32)


def random_depth(rng, h, w, holes=0.1):
    depth = rng.integers(1500, 3500, (h, w)).astype(np.uint16)
    depth[rng.random((h, w)) < holes] = 0
    return depth


def loop_energy(labels, proba, depth, cfg):
    """The energy written out pixel by pixel and edge by edge."""
    h, w = labels.shape
    total = 0.0
    for i in range(h):
        for j in range(w):
            if depth[i, j] == 0:
                continue
            total += -np.log(max(float(proba[i, j, labels[i, j]]), cfg.eps))
            for ii, jj in ((i, j + 1), (i + 1, j)):
                if ii < h and jj < w and depth[ii, jj] > 0 and labels[ii, jj] != labels[i, j]:
                    weight = cfg.smoothness
                    if cfg.depth_sigma_mm > 0:
                        dd = float(depth[i, j]) - float(depth[ii, jj])
                        weight *= np.exp(-(dd**2) / (2 * cfg.depth_sigma_mm**2))
                    total += weight
    return total


# --- config ---------------------------------------------------------------------------


def test_config_round_trips_and_validates():
    cfg = CRFConfig(mode="exact", smoothness=2.5, depth_sigma_mm=40.0, ring=2, cycles=0)
    assert CRFConfig.from_dict(cfg.to_dict()) == cfg
    for bad in (
        {"mode": "fast"},
        {"smoothness": -1.0},
        {"depth_sigma_mm": -5.0},
        {"eps": 0.0},
        {"confidence": 1.5},
        {"ring": -1},
        {"cycles": -2},
    ):
        with pytest.raises(TopsegError):
            CRFConfig(**bad)
    with pytest.raises(TopsegError, match="smoothnes"):
        CRFConfig.from_dict({"smoothnes": 1.0})


# --- energy ---------------------------------------------------------------------------


def test_unaries_are_clipped_negative_log():
    proba = np.zeros((2, 3, C), np.float32)
    proba[..., 4] = 0.25
    u = unaries_from_posteriors(proba, eps=1e-3)
    assert u.dtype == np.float32
    assert np.allclose(u[..., 4], -np.log(0.25))
    assert np.allclose(u[..., 0], -np.log(1e-3))


@pytest.mark.parametrize("sigma", [0.0, 30.0, 300.0])
def test_edge_weights_match_numpy(sigma):
    from reference import edge_weights_reference

    rng = np.random.default_rng(int(sigma))
    for shape in [(1, 1), (1, 7), (6, 1), (37, 53)]:
        depth = rng.integers(900, 1100, size=shape).astype(np.uint16)
        depth[rng.random(shape) < 0.2] = 0
        config = CRFConfig(smoothness=1.7, depth_sigma_mm=sigma)
        for got, want in zip(
            edge_weights(depth, config), edge_weights_reference(depth, config), strict=True
        ):
            assert got.dtype == np.float32 and got.shape == want.shape
            if sigma == 0:
                np.testing.assert_array_equal(got, want)
            else:  # numba's expf and numpy's may differ in the last bit
                np.testing.assert_allclose(got, want, rtol=2e-7, atol=1e-30)


def test_edge_weights_vanish_at_holes_and_across_depth_steps():
    depth = np.array([[2000, 2000, 0], [2000, 3000, 3000]], np.uint16)
    wh, wv = edge_weights(depth, CRFConfig(smoothness=2.0))
    assert wh.tolist() == [[2.0, 0.0], [2.0, 2.0]]
    assert wv.tolist() == [[2.0, 2.0, 0.0]]
    wh, wv = edge_weights(depth, CRFConfig(smoothness=2.0, depth_sigma_mm=50.0))
    assert wh[0, 0] == 2.0 and wh[1, 0] < 1e-6 and wh[1, 1] == 2.0
    assert wv[0, 1] < 1e-6


@pytest.mark.parametrize("sigma", [0.0, 300.0])
def test_energy_matches_the_loop_reference(sigma):
    rng = np.random.default_rng(int(sigma))
    cfg = CRFConfig(smoothness=0.7, depth_sigma_mm=sigma)
    for _ in range(5):
        proba, depth = random_posteriors(rng, 6, 7), random_depth(rng, 6, 7)
        labels = rng.integers(0, C, (6, 7)).astype(np.uint8)
        labels[depth == 0] = L.NO_DEPTH
        expected = loop_energy(labels, proba, depth, cfg)
        assert potts_energy(labels, proba, depth, cfg) == pytest.approx(expected, rel=1e-5)
        unary = unaries_from_posteriors(proba, cfg.eps)
        assert potts_energy(labels, unary, depth, cfg, kind="unary") == pytest.approx(
            expected, rel=1e-5
        )


def test_energy_refuses_bad_input():
    rng = np.random.default_rng(0)
    proba, depth = random_posteriors(rng, 4, 4), random_depth(rng, 4, 4, holes=0)
    labels = np.zeros((4, 4), np.uint8)
    labels[1, 1] = L.NO_DEPTH  # a pixel with depth must carry a class
    with pytest.raises(TopsegError, match="class ids"):
        potts_energy(labels, proba, depth, REALTIME)
    with pytest.raises(TopsegError, match="shape"):
        potts_energy(labels[:3], proba, depth, REALTIME)
    too_many = np.zeros((4, 4, L.NUM_CLASSES + 1), np.float32)
    for classes in (proba[..., :1], too_many):
        with pytest.raises(TopsegError, match="posteriors"):
            segment_crf(classes, depth, REALTIME)
    labels[1, 1] = L.ROBOT  # the posteriors' model knows ids 0..10 only
    with pytest.raises(TopsegError, match="class ids below the 11 classes"):
        potts_energy(labels, proba, depth, REALTIME)
    with pytest.raises(TopsegError, match="depth shape"):
        segment_crf(proba, depth[:3], REALTIME)


# --- segmentation on tiny grids, against brute force ----------------------------------


def brute_force(proba, depth, cfg):
    """(optimal energy, its data part) over every labeling of the pixels with depth."""
    valid = depth > 0
    unary = unaries_from_posteriors(proba, cfg.eps)[valid].astype(np.float64)
    wh, wv = edge_weights(depth, cfg)
    index = np.full(depth.shape, -1)
    index[valid] = np.arange(valid.sum())
    a = np.concatenate([index[:, :-1].ravel(), index[:-1, :].ravel()])
    b = np.concatenate([index[:, 1:].ravel(), index[1:, :].ravel()])
    w = np.concatenate([wh.ravel(), wv.ravel()])
    keep = (a >= 0) & (b >= 0)
    a, b, w = a[keep], b[keep], w[keep]
    n = int(valid.sum())
    best, best_data = np.inf, np.inf
    for head in itertools.product(range(C), repeat=n - 3):  # 3 sites enumerated at once
        tail = np.array(list(itertools.product(range(C), repeat=3)))
        x = np.concatenate([np.tile(head, (len(tail), 1)), tail], axis=1).astype(np.intp)
        data = unary[np.arange(n), x].sum(axis=1)
        total = data + ((x[:, a] != x[:, b]) * w).sum(axis=1)
        i = int(np.argmin(total))
        if total[i] < best:
            best, best_data = float(total[i]), float(data[i])
    return best, best_data


CONVERGED = CRFConfig(mode="realtime", confidence=1.0, cycles=0)  # every pixel in the band


@pytest.mark.parametrize("seed", range(3))
def test_tiny_grids_against_brute_force(seed):
    """Optimum <= E <= E_data(opt) + 2 E_smooth(opt) (the Potts bound of alpha-expansion)
    for exact and converged realtime; every mode at or below the argmax."""
    rng = np.random.default_rng(seed)
    for _ in range(2):
        proba = random_posteriors(rng, 2, 3, concentration=0.5)
        depth = random_depth(rng, 2, 3, holes=0)
        depth[0, 0] = 0  # a hole: five sites of eleven labels
        opt, opt_data = brute_force(proba, depth, REALTIME)
        e_argmax = potts_energy(segment_crf(proba, depth, NONE), proba, depth, REALTIME)
        for cfg in (EXACT, CONVERGED, REALTIME):
            labels = segment_crf(proba, depth, cfg)
            assert labels[0, 0] == L.NO_DEPTH
            e = potts_energy(labels, proba, depth, cfg)
            assert opt - 1e-4 <= e <= e_argmax + 1e-9
            if cfg is not REALTIME:
                assert e <= opt_data + 2 * (opt - opt_data) + 1e-4


def test_easy_cases_reach_the_optimum():
    """Two-label problems (expansion is exact there) and an isolated mistake."""
    rng = np.random.default_rng(3)
    for _ in range(3):
        proba = np.full((2, 3, C), 1e-7, np.float32)
        proba[..., 2] = rng.uniform(0.2, 0.8, (2, 3))
        proba[..., 7] = 1.0 - proba[..., 2]
        depth = random_depth(rng, 2, 3, holes=0)
        depth[0, 0] = 0
        opt, _ = brute_force(proba, depth, REALTIME)
        for cfg in (EXACT, CONVERGED):
            e = potts_energy(segment_crf(proba, depth, cfg), proba, depth, cfg)
            assert e == pytest.approx(opt, abs=1e-3)
    proba = np.full((9, 9, C), 0.01, np.float32)
    proba[..., L.TABLE] = 0.9
    proba[4, 4, L.TABLE], proba[4, 4, L.CHAIR] = 0.3, 0.6  # one weak, isolated mistake
    depth = np.full((9, 9), 2750, np.uint16)
    for cfg in (EXACT, REALTIME, CONVERGED):
        assert (segment_crf(proba, depth, cfg) == L.TABLE).all()
    assert segment_crf(proba, depth, NONE)[4, 4] == L.CHAIR


# --- frames ---------------------------------------------------------------------------


def test_modes_keep_shape_dtype_and_holes():
    rng = np.random.default_rng(4)
    depth, truth = synthetic_scene(rng, (120, 160))
    proba = forest_like_posteriors(truth, rng)
    holes = depth == 0
    assert holes.any()
    for cfg in (NONE, EXACT, REALTIME):
        labels = segment_crf(proba, depth, cfg)
        assert labels.shape == depth.shape and labels.dtype == np.uint8
        assert np.array_equal(labels == L.NO_DEPTH, holes)
        # what the posteriors say where there is no depth plays no part
        other = proba.copy()
        other[holes] = random_posteriors(rng, 1, int(holes.sum()))[0]
        assert np.array_equal(segment_crf(other, depth, cfg), labels)


@pytest.mark.parametrize("seed", range(3))
def test_realtime_close_to_exact_on_small_forest_like_frames(seed):
    rng = np.random.default_rng(10 + seed)
    depth, truth = synthetic_scene(rng, (240, 320))
    proba = forest_like_posteriors(truth, rng)
    e_exact = potts_energy(segment_crf(proba, depth, EXACT), proba, depth, EXACT)
    e_rt = potts_energy(segment_crf(proba, depth, REALTIME), proba, depth, REALTIME)
    e_argmax = potts_energy(segment_crf(proba, depth, NONE), proba, depth, NONE)
    assert e_rt <= 1.02 * e_exact
    assert e_exact <= e_argmax and e_rt <= e_argmax
    assert (e_argmax - e_rt) >= 0.8 * (e_argmax - e_exact)  # most of the CRF's gain


def test_realtime_within_2_percent_of_exact_on_a_full_frame():
    """The realtime CRF's energy within 2 % of the exact CRF's, and its labels within 2 % of
    the exact ones, on one 640x480 forest-like frame (exact: ~1.5 s)."""
    rng = np.random.default_rng(2016)
    depth, truth = synthetic_scene(rng)
    proba = forest_like_posteriors(truth, rng)
    exact = segment_crf(proba, depth, EXACT)
    realtime = segment_crf(proba, depth, REALTIME)
    e_exact = potts_energy(exact, proba, depth, EXACT)
    e_rt = potts_energy(realtime, proba, depth, REALTIME)
    e_argmax = potts_energy(segment_crf(proba, depth, NONE), proba, depth, NONE)
    assert e_exact <= e_argmax and e_rt <= e_argmax
    assert e_rt <= 1.02 * e_exact
    valid = depth > 0
    assert (exact == realtime)[valid].mean() > 0.98


def test_degenerate_frames():
    rng = np.random.default_rng(6)
    proba = random_posteriors(rng, 3, 4)
    holes = np.zeros((3, 4), np.uint16)
    one = holes.copy()
    one[1, 2] = 2000
    for cfg in (NONE, EXACT, REALTIME, CONVERGED):
        assert (segment_crf(proba, holes, cfg) == L.NO_DEPTH).all()
        labels = segment_crf(proba, one, cfg)
        assert labels[1, 2] == proba[1, 2].argmax()  # alone: nothing to agree with
        assert (labels[one == 0] == L.NO_DEPTH).all()


def test_stand_in_posteriors_err_like_a_forest():
    """The bench's and tests' stand-in: normalised, mostly right, wrong near boundaries."""
    from topseg.services.batch.bench.crf_standin import boundary_distance

    rng = np.random.default_rng(12)
    depth, truth = synthetic_scene(rng)
    assert ((depth == 0) == (truth == L.NO_DEPTH)).all()
    assert set(np.unique(truth)) >= {L.BACKGROUND, L.HEAD, L.BODY, L.HAND}
    proba = forest_like_posteriors(truth, rng)
    assert np.allclose(proba.sum(axis=2), 1.0, atol=1e-5)
    fg = (truth != L.BACKGROUND) & (truth != L.NO_DEPTH)
    wrong = (proba.argmax(axis=2) != truth) & fg
    assert 0.75 < 1 - wrong[fg].mean() < 0.97
    dist = boundary_distance(truth)
    assert dist[wrong].mean() < 0.5 * dist[fg].mean()
