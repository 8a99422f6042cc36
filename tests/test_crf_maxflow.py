"""The numba Boykov-Kolmogorov min cut against scipy's max-flow and brute force."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import maximum_flow

from topseg.core.crf.maxflow import build_csr, mincut


def random_graph(rng, n, density=2.0, cap=20):
    m = int(rng.integers(0, int(density * n) + 1))
    u = rng.integers(0, n, m)
    v = rng.integers(0, n, m)
    keep = u != v
    u, v = u[keep], v[keep]

    def sparse(size):  # capacities, a fifth of them zero
        return rng.integers(0, cap, size) * (rng.random(size) < 0.8)

    cap_s = rng.integers(0, 2 * cap, n) * (rng.random(n) < 0.5)
    cap_t = rng.integers(0, 2 * cap, n) * (rng.random(n) < 0.5)
    return [np.asarray(a, np.int64) for a in (u, v, sparse(u.size), sparse(u.size), cap_s, cap_t)]


def scipy_maxflow(n, u, v, cuv, cvu, cap_s, cap_t):
    s, t = n, n + 1
    rows = np.concatenate([u, v, np.full(n, s), np.arange(n)])
    cols = np.concatenate([v, u, np.arange(n), np.full(n, t)])
    data = np.concatenate([cuv, cvu, cap_s, cap_t]).astype(np.int32)
    graph = csr_matrix((data, (rows, cols)), shape=(n + 2, n + 2))
    graph.sum_duplicates()
    return int(maximum_flow(graph, s, t).flow_value)


def cut_value(u, v, cuv, cvu, cap_s, cap_t, in_source):
    """What the partition `in_source` cuts, counted edge by edge."""
    return int(
        cap_s[~in_source].sum()
        + cap_t[in_source].sum()
        + cuv[in_source[u] & ~in_source[v]].sum()
        + cvu[in_source[v] & ~in_source[u]].sum()
    )


def test_csr_lists_every_arc_once_from_its_tail():
    rng = np.random.default_rng(0)
    n = 30
    u, v = rng.integers(0, n, 80), rng.integers(0, n, 80)
    first, adj, head = build_csr(n, u, v)
    assert first[-1] == 2 * u.size
    assert sorted(adj) == list(range(2 * u.size))
    for i in range(n):
        for a in adj[first[i] : first[i + 1]]:
            assert head[a ^ 1] == i  # the sister arc points back at the tail


@pytest.mark.parametrize("seed", range(4))
def test_min_cut_equals_scipy_max_flow_on_random_graphs(seed):
    rng = np.random.default_rng(seed)
    for _ in range(150):
        n = int(rng.integers(1, 60))
        g = random_graph(rng, n, density=rng.uniform(0.5, 4.0))
        value, in_source = mincut(n, *g)
        expected = scipy_maxflow(n, *g)
        assert value == expected
        assert cut_value(*g, in_source) == expected  # the partition really is a min cut


def test_min_cut_equals_brute_force_on_tiny_graphs():
    rng = np.random.default_rng(42)
    for _ in range(200):
        n = int(rng.integers(1, 9))
        g = random_graph(rng, n, density=3.0)
        best = min(
            cut_value(*g, np.array(side, bool))
            for side in itertools.product((False, True), repeat=n)
        )
        value, in_source = mincut(n, *g)
        assert value == best == cut_value(*g, in_source)


def test_grid_graph_like_an_expansion_move():
    """A 4-connected grid with large terminal weights, the shape the CRF produces."""
    rng = np.random.default_rng(7)
    h, w = 60, 80
    idx = np.arange(h * w).reshape(h, w)
    u = np.concatenate([idx[:, :-1].ravel(), idx[:-1, :].ravel()])
    v = np.concatenate([idx[:, 1:].ravel(), idx[1:, :].ravel()])
    c = np.full(u.size, 1000, np.int64)
    cap_s = rng.integers(0, 14000, h * w)
    cap_t = rng.integers(0, 14000, h * w)
    value, in_source = mincut(h * w, u, v, c, c, cap_s, cap_t)
    assert value == scipy_maxflow(h * w, u, v, c, c, cap_s, cap_t)
    assert cut_value(u, v, c, c, cap_s, cap_t, in_source) == value


def test_empty_and_edgeless_graphs():
    none = np.zeros(0, np.int64)
    assert mincut(0, none, none, none, none, none, none)[0] == 0
    cap_s = np.array([3, 0, 5], np.int64)
    cap_t = np.array([1, 4, 5], np.int64)
    value, in_source = mincut(3, none, none, none, none, cap_s, cap_t)
    assert value == 1 + 0 + 5
    assert not in_source[1]
