"""Numba alpha-expansion: each move against brute force, the whole run against the optimum
and against gco, and the grid helper against a plain loop."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from topseg.core.crf.expansion import (
    alpha_expansion,
    energy,
    expansion_move,
    expansion_run,
    grid_neighbours,
)


def grid_problem(rng, h, w, k, unary_max=2000, weight_max=1500):
    """A random integer Potts problem on an h x w grid: (unary, nbr, nw)."""
    unary = rng.integers(0, unary_max, (h * w, k)).astype(np.int64)
    wh = rng.integers(0, weight_max, (h, w - 1)).astype(np.int64)
    wv = rng.integers(0, weight_max, (h - 1, w)).astype(np.int64)
    nbr, nw = grid_neighbours(h, w, wh, wv, np.arange(h * w).reshape(h, w))
    return unary, nbr, nw


def edges_of(nbr, nw):
    p, s = np.nonzero(nbr >= 0)
    q = nbr[p, s]
    once = p < q
    return p[once], q[once], nw[p, s][once]


def energies(labelings, unary, nbr, nw):
    """Energy of every row of `labelings` (M, N) in plain numpy."""
    a, b, w = edges_of(nbr, nw)
    data = unary[np.arange(unary.shape[0]), labelings].sum(axis=1)
    return data + ((labelings[:, a] != labelings[:, b]) * w).sum(axis=1)


def all_labelings(n, k):
    return np.array(list(itertools.product(range(k), repeat=n)), np.int64)


def apply_move(alpha, x, unary, nbr, nw):
    n = unary.shape[0]
    ux = unary[np.arange(n), x].copy()
    wsum = np.where(nbr >= 0, nw, 0).sum(axis=1)
    scratch = [np.empty(n, np.int64) for _ in range(3)]
    gain = expansion_move(alpha, x, ux, np.ascontiguousarray(unary.T), nbr, nw, wsum, *scratch)
    assert np.array_equal(ux, unary[np.arange(n), x])  # kept in step with x
    return gain


def test_energy_matches_numpy():
    rng = np.random.default_rng(0)
    unary, nbr, nw = grid_problem(rng, 5, 7, 4)
    xs = rng.integers(0, 4, (20, 35))
    expected = energies(xs, unary, nbr, nw)
    assert [energy(x, unary, nbr, nw) for x in xs] == list(expected)


def test_grid_neighbours_matches_a_loop():
    rng = np.random.default_rng(1)
    h, w = 4, 6
    wh = rng.integers(1, 9, (h, w - 1))
    wv = rng.integers(1, 9, (h - 1, w))
    index = np.full((h, w), -1)
    sites = rng.random((h, w)) < 0.7
    index[sites] = np.arange(sites.sum())
    nbr, nw = grid_neighbours(h, w, wh, wv, index)
    for i, j in zip(*np.nonzero(sites), strict=True):
        p = index[i, j]
        for s, (di, dj) in enumerate(((0, -1), (0, 1), (-1, 0), (1, 0))):
            ii, jj = i + di, j + dj
            inside = 0 <= ii < h and 0 <= jj < w and index[ii, jj] >= 0
            assert nbr[p, s] == (index[ii, jj] if inside else -1)
            if inside:
                weight = wh[i, min(j, jj)] if di == 0 else wv[min(i, ii), j]
                assert nw[p, s] == weight
            else:
                assert nw[p, s] == 0


@pytest.mark.parametrize("seed", range(3))
def test_each_move_is_the_best_expansion_move(seed):
    """Enumerate every keep/take-alpha choice; the pruned min cut must find the best."""
    rng = np.random.default_rng(seed)
    for trial in range(60):
        h, w, k = 2, int(rng.integers(2, 5)), int(rng.integers(2, 5))
        # strong and weak smoothing both, so pruning sometimes removes everything
        unary, nbr, nw = grid_problem(rng, h, w, k, weight_max=int(rng.choice([300, 3000])))
        x = rng.integers(0, k, h * w).astype(np.int64)
        alpha = int(rng.integers(0, k))
        free = np.nonzero(x != alpha)[0]
        candidates = np.repeat(x[None], 2**free.size, axis=0)
        for row, take in enumerate(itertools.product((False, True), repeat=free.size)):
            candidates[row, free[np.array(take, bool)]] = alpha
        best = energies(candidates, unary, nbr, nw).min()
        before = energy(x, unary, nbr, nw)
        gain = apply_move(alpha, x, unary, nbr, nw)
        after = energy(x, unary, nbr, nw)
        assert after == min(best, before), (seed, trial)
        assert gain == before - after  # the reported gain is the energy's decrease


@pytest.mark.parametrize("seed", range(3))
def test_alpha_expansion_against_the_optimum(seed):
    """Never above the start; within the Potts bound E_data(x*) + 2 E_smooth(x*)."""
    rng = np.random.default_rng(100 + seed)
    hits = 0
    for _ in range(25):
        h, w, k = 2, 4, 3
        unary, nbr, nw = grid_problem(rng, h, w, k)
        labelings = all_labelings(h * w, k)
        e_all = energies(labelings, unary, nbr, nw)
        opt = labelings[np.argmin(e_all)]
        x0 = np.argmin(unary, axis=1)
        x = alpha_expansion(unary, nbr, nw, x0)
        e = energy(x, unary, nbr, nw)
        e_data_opt = unary[np.arange(h * w), opt].sum()
        assert e <= energy(x0, unary, nbr, nw)
        assert e_all.min() <= e <= e_data_opt + 2 * (e_all.min() - e_data_opt)
        hits += e == e_all.min()
        for alpha in range(k):  # converged: no move helps
            assert apply_move(alpha, x.copy(), unary, nbr, nw) == 0
    assert hits >= 20  # on these easy problems expansion nearly always finds the optimum


def test_run_reports_its_energy_decrease():
    rng = np.random.default_rng(8)
    for _ in range(10):
        unary, nbr, nw = grid_problem(rng, 6, 7, 4)
        x0 = rng.integers(0, 4, 42)
        x, gain = expansion_run(unary, nbr, nw, x0)
        assert gain == energy(x0, unary, nbr, nw) - energy(x, unary, nbr, nw) > 0


def test_two_labels_reach_the_global_optimum():
    """With two labels one expansion move is the whole binary problem: exact."""
    rng = np.random.default_rng(5)
    for _ in range(30):
        unary, nbr, nw = grid_problem(rng, 3, 4, 2)
        e_all = energies(all_labelings(12, 2), unary, nbr, nw)
        x0 = rng.integers(0, 2, 12)
        assert energy(alpha_expansion(unary, nbr, nw, x0), unary, nbr, nw) == e_all.min()


def test_cycles_limit_and_strong_unaries():
    rng = np.random.default_rng(9)
    unary, nbr, nw = grid_problem(rng, 6, 6, 4, unary_max=100, weight_max=10)
    x0 = np.argmin(unary, axis=1)
    # weights far below unary gaps: nothing to smooth, argmax is optimal
    strong = unary * 1000
    assert np.array_equal(alpha_expansion(strong, nbr, nw, x0), x0)
    one = alpha_expansion(unary, nbr, nw * 50, x0, 1)
    full = alpha_expansion(unary, nbr, nw * 50, x0)
    assert energy(full, unary, nbr, nw * 50) <= energy(one, unary, nbr, nw * 50)
    assert energy(one, unary, nbr, nw * 50) <= energy(x0, unary, nbr, nw * 50)


def test_gco_and_numba_results_are_fixed_points_of_each_other():
    """gco's converged labeling admits no improving move under the numba move solver,
    and both land within a few percent of each other on a forest-like grid."""
    from gco.pygco import GCO

    rng = np.random.default_rng(11)
    h, w, k = 30, 40, 5
    truth = np.zeros((h, w), np.int64)
    truth[5:20, 8:25] = 1
    truth[12:28, 20:35] = 2
    truth[2:9, 28:38] = 3
    proba = np.full((h, w, k), 0.05)
    proba[np.arange(h)[:, None], np.arange(w)[None, :], truth] = 0.3
    proba += rng.random((h, w, k)) * 0.5
    proba /= proba.sum(axis=2, keepdims=True)
    unary = np.rint(-np.log(proba).reshape(-1, k) * 1000).astype(np.int64)
    wh = np.full((h, w - 1), 1000, np.int64)
    wv = np.full((h - 1, w), 1000, np.int64)
    nbr, nw = grid_neighbours(h, w, wh, wv, np.arange(h * w).reshape(h, w))

    a, b, ew = edges_of(nbr, nw)
    gc = GCO()
    gc.create_general_graph(h * w, k, energy_is_float=False)
    gc.set_data_cost(unary.astype(np.int32))
    gc.set_all_neighbors(a, b, ew.astype(np.int32))
    gc.set_smooth_cost((1 - np.eye(k)).astype(np.int32))
    gc.expansion(-1)
    x_gco = gc.get_labels().astype(np.int64)
    gc.destroy_graph()

    for alpha in range(k):
        assert apply_move(alpha, x_gco.copy(), unary, nbr, nw) == 0
    x0 = np.argmin(unary, axis=1)
    x = alpha_expansion(unary, nbr, nw, x0)
    e_gco, e_numba = energy(x_gco, unary, nbr, nw), energy(x, unary, nbr, nw)
    assert abs(e_numba - e_gco) <= 0.02 * e_gco
    assert e_numba < energy(x0, unary, nbr, nw)
