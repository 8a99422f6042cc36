"""The splitter: randomized node optimisation, the split a node keeps and its partition.

A node draws R candidate responses (axis-aligned: one pool feature; linear: k pool features
and a random unit vector) and, per candidate, K thresholds among the candidate's responses
on (at most `cap` of) its samples; `criterion` scores all K at once and the best gain wins.
All randomness of a node comes from a splitmix64 stream seeded by (tree key, node id), so a
tree depends only on its seed, never on thread scheduling. The draws of a node, in order:
the subsample positions (only when the node is larger than `cap`), then per candidate its k
feature ids, its weights (linear only: k uniforms in [-1, 1] redrawn until their norm is in
(0, 1], then normalised), and its thresholds' positions.
"""

from __future__ import annotations

import numba
import numpy as np

from topseg.core.forest.criterion import _bin_histogram, _gains_from_histogram

# --- random numbers: a splitmix64 stream per node -------------------------------------

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)


@numba.njit(cache=True, inline="always")
def _next_u64(state):
    """Advance the 1-element uint64 `state`; return the next 64 random bits (splitmix64)."""
    state[0] += _GOLDEN
    z = state[0]
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@numba.njit(cache=True, inline="always")
def _uniform(state):
    """A float64 uniform in [0, 1) from the top 53 bits."""
    return np.float64(_next_u64(state) >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@numba.njit(cache=True, inline="always")
def _randint(state, n):
    """An integer uniform in [0, n)."""
    return np.int64(_uniform(state) * n)


@numba.njit(cache=True)
def _node_state(key, node_id):
    """The stream of node `node_id` of the tree with `key`."""
    state = np.empty(1, np.uint64)
    state[0] = np.uint64(key) + np.uint64(node_id) * _GOLDEN
    state[0] = _next_u64(state)
    return state


# --- candidates and the partition ------------------------------------------------------


@numba.njit(cache=True)
def _responses(fm, ids, feats, weights, out):
    """out[i] = sum_j weights[j] * fm[feats[j], ids[i]] in float32 (same order as inference).

    `fm` is feature-major (PC, n_samples): a node's ids are ascending, so each feature is
    read as one forward pass over its row.
    """
    out[:] = 0.0
    for j in range(feats.shape[0]):
        row = fm[feats[j]]
        wj = weights[j]
        for i in range(ids.shape[0]):
            out[i] += wj * np.float32(row[ids[i]])


@numba.njit(cache=True)
def _unit_vector(state, k, out):
    """k uniforms in [-1, 1] redrawn until 0 < norm <= 1, normalised: uniform on the sphere."""
    while True:
        sq = 0.0
        for j in range(k):
            v = 2.0 * _uniform(state) - 1.0
            out[j] = v
            sq += v * v
        if 0.0 < sq <= 1.0:
            norm = np.sqrt(sq)
            for j in range(k):
                out[j] = out[j] / norm
            return


@numba.njit(cache=True)
def _best_split(fm, y, ids, state, n_classes, n_candidates, n_thresholds, k, linear, cap, xlogx):
    """Randomized node optimisation for the samples `ids` of one node.

    Returns (gain, feats (k,) int64, weights (k,) float32, threshold float32); gain is -1
    when no candidate was drawn. The draws follow the order in the module docstring.
    """
    n = ids.shape[0]
    if n > cap:
        m = cap
        sub = np.empty(m, ids.dtype)
        for i in range(m):
            sub[i] = ids[_randint(state, n)]
    else:
        m = n
        sub = ids
    ys = np.empty(m, np.int64)
    for i in range(m):
        ys[i] = y[sub[i]]
    n_thr = min(n_thresholds, m)
    resp = np.empty(m, np.float32)
    thr = np.empty(n_thr, np.float32)
    feats = np.empty(k, np.int64)
    w64 = np.empty(k, np.float64)
    weights = np.empty(k, np.float32)
    best_gain = -1.0
    best_feats = np.zeros(k, np.int64)
    best_weights = np.zeros(k, np.float32)
    best_thr = np.float32(0.0)
    hist = np.empty((n_thr + 1, n_classes), np.int64)
    gains = np.empty(n_thr, np.float64)
    n_features = fm.shape[0]
    for _ in range(n_candidates):
        for j in range(k):
            feats[j] = _randint(state, n_features)
        if linear:
            _unit_vector(state, k, w64)
            for j in range(k):
                weights[j] = np.float32(w64[j])
        else:
            weights[:] = 1.0
        _responses(fm, sub, feats, weights, resp)
        for t in range(n_thr):
            thr[t] = resp[_randint(state, m)]
        thr.sort()
        _bin_histogram(resp, ys, thr, hist)
        _gains_from_histogram(hist, xlogx, gains)
        for t in range(n_thr):
            if gains[t] > best_gain:
                best_gain = gains[t]
                best_feats[:] = feats
                best_weights[:] = weights
                best_thr = thr[t]
    return best_gain, best_feats, best_weights, best_thr


@numba.njit(cache=True)
def _partition(fm, ids, feats, weights, threshold):
    """Stable in-place partition of `ids`: response < threshold first; returns the count."""
    n = ids.shape[0]
    resp = np.empty(n, np.float32)
    _responses(fm, ids, feats, weights, resp)
    tmp = np.empty(n, ids.dtype)
    n_left = 0
    for i in range(n):
        if resp[i] < threshold:
            tmp[n_left] = ids[i]
            n_left += 1
    j = n_left
    for i in range(n):
        if not resp[i] < threshold:
            tmp[j] = ids[i]
            j += 1
    ids[:] = tmp
    return n_left
