"""Real-time Potts CRF: the same energy as `exact`, minimised on the uncertain band only.

In a top view most pixels are floor or the inside of a large surface, where the forest is
confident and every neighbour agrees; smoothing does not change them in practice. So:

1. every pixel with depth whose top posterior reaches `config.confidence` and whose 4
   neighbours with depth share its argmax is *fixed* to that argmax;
2. the rest (the *band*: boundaries and noisy blobs) is grown by `config.ring` steps and
   split into 4-connected components, each an independent problem;
3. each edge from a band pixel to a fixed neighbour q is folded into the band pixel's
   unaries as the exact constant w_pq [l != x_q];
4. each component runs `config.cycles` rounds of alpha-expansion
   (`topseg.core.crf_expansion`: numba, exactly pruned moves, warm-started from the
   argmax), and keeps the argmax unless the result has a lower energy, so the frame's
   energy never rises above the forest's own labeling.

Kernels are serial on purpose: on the 2-core target the worker runs forest inference
beside the CRF, and OpenMP threads waiting for a busy core cost more than they gain
(`topseg bench crf` measured 60 ms with 2 threads vs 15 ms with 1 on a loaded machine).
`topseg bench crf` reports the time and the energy ratio to `exact`.
"""

from __future__ import annotations

import numba
import numpy as np

from topseg.core import labels as L
from topseg.core.crf import ENERGY_SCALE, CRFConfig, edge_weights
from topseg.core.crf_expansion import alpha_expansion, energy


@numba.njit(cache=True)
def argmax_confidence(proba, valid):
    """Per-pixel argmax (uint8, NO_DEPTH where invalid) and top posterior (float32)."""
    h, w, c = proba.shape
    amax = np.empty((h, w), np.uint8)
    pmax = np.zeros((h, w), np.float32)
    for i in range(h):
        for j in range(w):
            if not valid[i, j]:
                amax[i, j] = L.NO_DEPTH
                continue
            best = 0
            bp = proba[i, j, 0]
            for k in range(1, c):
                if proba[i, j, k] > bp:
                    bp = proba[i, j, k]
                    best = k
            amax[i, j] = best
            pmax[i, j] = bp
    return amax, pmax


@numba.njit(cache=True)
def free_mask(amax, pmax, valid, confidence, ring):
    """Pixels left to the solver: not (confident and agreeing with all 4 neighbours), + ring."""
    h, w = amax.shape
    free = np.zeros((h, w), np.bool_)
    for i in range(h):
        for j in range(w):
            if not valid[i, j]:
                continue
            a = amax[i, j]
            ok = pmax[i, j] >= confidence
            if ok and i > 0 and valid[i - 1, j] and amax[i - 1, j] != a:
                ok = False
            if ok and i + 1 < h and valid[i + 1, j] and amax[i + 1, j] != a:
                ok = False
            if ok and j > 0 and valid[i, j - 1] and amax[i, j - 1] != a:
                ok = False
            if ok and j + 1 < w and valid[i, j + 1] and amax[i, j + 1] != a:
                ok = False
            free[i, j] = not ok
    for _ in range(ring):
        grown = free.copy()
        for i in range(h):
            for j in range(w):
                if free[i, j] or not valid[i, j]:
                    continue
                if (
                    (i > 0 and free[i - 1, j])
                    or (i + 1 < h and free[i + 1, j])
                    or (j > 0 and free[i, j - 1])
                    or (j + 1 < w and free[i, j + 1])
                ):
                    grown[i, j] = True
        free = grown
    return free


@numba.njit(cache=True)
def number_components(free):
    """Number free pixels component by component (4-connected, breadth first).

    Returns (index (H, W), -1 off the band; starts: component c owns ids
    starts[c]:starts[c + 1]), so each component is a contiguous, independent problem.
    """
    h, w = free.shape
    index = np.full((h, w), -1, np.int64)
    queue = np.empty(h * w, np.int64)
    starts = [0]
    n = 0
    for i0 in range(h):
        for j0 in range(w):
            if not free[i0, j0] or index[i0, j0] >= 0:
                continue
            index[i0, j0] = n
            queue[n] = i0 * w + j0
            head = n
            n += 1
            while head < n:
                i, j = divmod(queue[head], w)
                head += 1
                for ii, jj in ((i, j - 1), (i, j + 1), (i - 1, j), (i + 1, j)):
                    if 0 <= ii < h and 0 <= jj < w and free[ii, jj] and index[ii, jj] < 0:
                        index[ii, jj] = n
                        queue[n] = ii * w + jj
                        n += 1
            starts.append(n)
    return index, np.array(starts, np.int64)


@numba.njit(cache=True)
def band_problem(proba, amax, index, n, wh, wv, eps):
    """The band's own CRF: its pixel ids, (N, C) float unaries with the edges to fixed
    neighbours folded in, a local neighbour table (N, 4) with weights, and the argmax."""
    h, w = amax.shape
    c = proba.shape[2]
    pix = np.empty(n, np.int64)
    init = np.empty(n, np.int64)
    unary = np.empty((n, c), np.float32)
    nbr = np.full((n, 4), -1, np.int64)
    nw = np.zeros((n, 4), np.float32)
    for i in range(h):
        for j in range(w):
            r = index[i, j]
            if r < 0:
                continue
            pix[r] = i * w + j
            init[r] = amax[i, j]
            for k in range(c):
                unary[r, k] = -np.log(max(proba[i, j, k], eps))
            for s in range(4):  # left, right, up, down
                if s == 0:
                    ii, jj, wt = i, j - 1, wh[i, j - 1] if j > 0 else 0.0
                elif s == 1:
                    ii, jj, wt = i, j + 1, wh[i, j] if j + 1 < w else 0.0
                elif s == 2:
                    ii, jj, wt = i - 1, j, wv[i - 1, j] if i > 0 else 0.0
                else:
                    ii, jj, wt = i + 1, j, wv[i, j] if i + 1 < h else 0.0
                if wt <= 0:
                    continue
                q = index[ii, jj]
                if q >= 0:
                    nbr[r, s] = q
                    nw[r, s] = wt
                else:  # fixed neighbour: w [l != its argmax] is a constant per label
                    fixed = amax[ii, jj]
                    for k in range(c):
                        if k != fixed:
                            unary[r, k] += wt
    return pix, unary, nbr, nw, init


@numba.njit(cache=True)
def expand_components(unary, nbr, nw, init, starts, cycles):
    """Alpha-expansion on each band component on its own; float (N, C) unaries and (N, 4)
    weights. A component keeps its argmax unless the result has a lower float energy."""
    iu = np.empty(unary.shape, np.int64)
    iw = np.empty(nw.shape, np.int64)
    for r in range(unary.shape[0]):
        for k in range(unary.shape[1]):
            iu[r, k] = round(unary[r, k] * ENERGY_SCALE)
        for s in range(nw.shape[1]):
            iw[r, s] = round(nw[r, s] * ENERGY_SCALE)
    x = init.copy()
    for c in range(starts.shape[0] - 1):
        a, b = starts[c], starts[c + 1]
        local = nbr[a:b].copy()
        for r in range(b - a):
            for s in range(local.shape[1]):
                if local[r, s] >= 0:
                    local[r, s] -= a
        sol = alpha_expansion(iu[a:b], local, iw[a:b], init[a:b], cycles)
        if energy(sol, unary[a:b], local, nw[a:b]) < energy(init[a:b], unary[a:b], local, nw[a:b]):
            x[a:b] = sol
    return x


def segment_realtime(proba: np.ndarray, depth: np.ndarray, config: CRFConfig) -> np.ndarray:
    """(H, W) uint8 labels: argmax where fixed, alpha-expansion on the band (see module doc)."""
    proba = np.ascontiguousarray(proba, dtype=np.float32)
    valid = np.asarray(depth) > 0
    amax, pmax = argmax_confidence(proba, valid)
    if config.smoothness == 0:
        return amax
    wh, wv = edge_weights(depth, config)
    free = free_mask(amax, pmax, valid, np.float32(config.confidence), config.ring)
    index, starts = number_components(free)
    n = int(starts[-1])
    if n == 0:
        return amax
    pix, unary, nbr, nw, init = band_problem(proba, amax, index, n, wh, wv, np.float32(config.eps))
    cycles = config.cycles if config.cycles > 0 else 1_000_000
    sol = expand_components(unary, nbr, nw, init, starts, cycles)
    out = amax.copy()
    out.ravel()[pix] = sol
    return out
