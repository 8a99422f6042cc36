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
   (`topseg.core.crf.expansion`: numba, exactly pruned moves, warm-started from the
   argmax), and keeps the argmax unless the result has a lower energy, so the frame's
   energy never rises above the forest's own labeling.

Kernels are serial on purpose: on the 2-core target the worker runs forest inference
beside the CRF, and OpenMP threads waiting for a busy core cost more than they gain
(`topseg bench crf` measured 60 ms with 2 threads vs 15 ms with 1 on a loaded machine).
`topseg bench crf` reports the time and the energy ratio to `exact`.
"""

from __future__ import annotations

from collections.abc import Callable

import numba
import numpy as np

from topseg.core.crf.argmax import Summary, argmax_confidence
from topseg.core.crf.energy import ENERGY_SCALE, CRFConfig, edge_weights
from topseg.core.crf.expansion import expansion_run

#: Extra nats a settled pixel's argmax must win by: covers the solver's integer rounding.
SETTLED_MARGIN = 0.01


@numba.njit(cache=True)
def settled(i, j, pmax, psecond, keep, eps):
    """True if no expansion move from the argmax can change pixel (i, j).

    `keep` = exp(-(4 * smoothness + SETTLED_MARGIN)): the argmax beats every other label
    by more than the weight any pixel's edges can have, so every move prunes the pixel
    whatever its neighbours do (see `topseg.core.crf.expansion`), and leaving it out of
    the band changes nothing. (Bounding the weights by 4 * smoothness rather than
    summing the pixel's own keeps this to one comparison; it only ever settles fewer.)
    """
    return max(psecond[i, j], eps) <= max(pmax[i, j], eps) * keep


@numba.njit(cache=True)
def free_mask(amax, pmax, psecond, valid, confidence, ring, smoothness, eps):
    """The band: pixels with depth that are neither sure (top posterior >= `confidence`
    and all 4 neighbours agree) nor settled, grown by `ring` steps into unsettled pixels."""
    h, w = amax.shape
    keep = np.float32(np.exp(-(4.0 * smoothness + SETTLED_MARGIN)))
    eps = np.float32(eps)
    free = np.zeros((h, w), np.bool_)
    for i in range(h):
        for j in range(w):
            if not valid[i, j]:
                continue
            a = amax[i, j]
            sure = pmax[i, j] >= confidence
            if sure and i > 0 and valid[i - 1, j] and amax[i - 1, j] != a:
                sure = False
            if sure and i + 1 < h and valid[i + 1, j] and amax[i + 1, j] != a:
                sure = False
            if sure and j > 0 and valid[i, j - 1] and amax[i, j - 1] != a:
                sure = False
            if sure and j + 1 < w and valid[i, j + 1] and amax[i, j + 1] != a:
                sure = False
            free[i, j] = not sure and not settled(i, j, pmax, psecond, keep, eps)
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
                ) and not settled(i, j, pmax, psecond, keep, eps):
                    grown[i, j] = True
        free = grown
    return free


@numba.njit(cache=True)
def number_band(free):
    """Row-major ids of the free pixels: (index (H, W) int32, -1 off the band; count)."""
    h, w = free.shape
    index = np.full((h, w), -1, np.int32)
    n = 0
    for i in range(h):
        for j in range(w):
            if free[i, j]:
                index[i, j] = n
                n += 1
    return index, n


@numba.njit(cache=True)
def band_problem(proba, amax, index, n, wh, wv, eps, scale):
    """The band's own CRF in gco-style integers (x `scale`, rounded).

    Returns the band pixels' flat ids, (N, C) unaries with the edges to fixed neighbours
    folded in (w [l != their argmax] is a constant per label), a neighbour table (N, 4)
    (left, right, up, down; -1 = none) with its weights, and each pixel's argmax.
    """
    h, w = amax.shape
    c = proba.shape[2]
    cap = np.int32(np.rint(-np.log(eps) * scale))
    pix = np.empty(n, np.int64)
    init = np.empty(n, np.int32)
    unary = np.empty((n, c), np.int32)
    nbr = np.full((n, 4), -1, np.int32)
    nw = np.zeros((n, 4), np.int32)
    for i in range(h):
        for j in range(w):
            r = index[i, j]
            if r < 0:
                continue
            pix[r] = i * w + j
            init[r] = amax[i, j]
            for k in range(c):
                pk = proba[i, j, k]
                unary[r, k] = cap if pk <= eps else np.int32(np.rint(-np.log(pk) * scale))
            for s in range(4):
                if s == 0:
                    ii, jj, wt = i, j - 1, wh[i, j - 1] if j > 0 else 0.0
                elif s == 1:
                    ii, jj, wt = i, j + 1, wh[i, j] if j + 1 < w else 0.0
                elif s == 2:
                    ii, jj, wt = i - 1, j, wv[i - 1, j] if i > 0 else 0.0
                else:
                    ii, jj, wt = i + 1, j, wv[i, j] if i + 1 < h else 0.0
                iw = np.int32(np.rint(wt * scale))
                if iw <= 0:
                    continue
                q = index[ii, jj]
                if q >= 0:
                    nbr[r, s] = q
                    nw[r, s] = iw
                else:
                    fixed = amax[ii, jj]
                    for k in range(c):
                        if k != fixed:
                            unary[r, k] += iw
    return pix, unary, nbr, nw, init


@numba.njit(cache=True)
def float_gain(proba, before, after, pix, wh, wv, eps):
    """E(before) - E(after) in float, for labelings that differ only at band pixels `pix`."""
    h, w = before.shape
    gain = 0.0
    for r in range(pix.shape[0]):
        p = pix[r]
        i, j = p // w, p % w
        old, new = before[i, j], after[i, j]
        if old == new:
            continue
        gain += np.log(max(np.float64(proba[i, j, new]), eps))
        gain -= np.log(max(np.float64(proba[i, j, old]), eps))
        for s in range(4):
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
            q_old, q_new = before[ii, jj], after[ii, jj]
            if q_old != q_new and ii * w + jj < p:
                continue  # both ends changed: counted from the other end
            gain += wt * (np.float64(old != q_old) - np.float64(new != q_new))
    return gain


@numba.njit(cache=True)
def _solve_band(unary, nbr, nw, init, cycles):
    """Expansion on the band: (labels as uint8, integer energy decrease, pixels changed)."""
    x, gain = expansion_run(unary, nbr, nw, init, cycles)
    out = np.empty(x.shape[0], np.uint8)
    changed = 0
    for r in range(x.shape[0]):
        out[r] = x[r]
        changed += x[r] != init[r]
    return out, gain, changed


def band_mask(proba: np.ndarray, depth: np.ndarray, config: CRFConfig) -> np.ndarray:
    """(H, W) bool: the pixels `segment_realtime` hands to the solver (for benches, viewers)."""
    proba = np.ascontiguousarray(proba, dtype=np.float32)
    valid = np.asarray(depth) > 0
    amax, pmax, psecond = argmax_confidence(proba, valid)
    return free_mask(
        amax, pmax, psecond, valid, config.confidence, config.ring, config.smoothness, config.eps
    )


def segment_realtime(
    proba: np.ndarray,
    depth: np.ndarray,
    config: CRFConfig,
    summary: Summary | None = None,
    fill: Callable[[np.ndarray], object] | None = None,
) -> np.ndarray:
    """(H, W) uint8 labels: argmax where fixed, alpha-expansion on the band (see module doc).

    `summary` is `proba`'s argmax and top two posteriors when the caller has them (the
    forest fills them as it writes `proba`); its arrays are read, never returned. `fill`,
    when given, is called with the (H, W) bool band before `proba` is read there: `proba`
    need hold posteriors only where `fill` stores them (`forest.fill_posteriors` of a lazy
    `predict_proba`); it needs a summary."""
    if fill is not None and summary is None:
        raise ValueError("segment_realtime: fill needs the summary of the posteriors")
    proba = np.ascontiguousarray(proba, dtype=np.float32)
    valid = np.asarray(depth) > 0
    if summary is None:
        amax, pmax, psecond = argmax_confidence(proba, valid)
    else:  # the caller's buffers: the labels returned must be a copy
        amax, pmax, psecond = summary.amax.copy(), summary.pmax, summary.psecond
    if config.smoothness == 0:
        return amax
    wh, wv = edge_weights(depth, config)
    free = free_mask(
        amax, pmax, psecond, valid, config.confidence, config.ring, config.smoothness, config.eps
    )
    index, n = number_band(free)
    if n == 0:
        return amax
    if fill is not None:
        fill(free)
    eps = np.float32(config.eps)
    pix, unary, nbr, nw, init = band_problem(proba, amax, index, n, wh, wv, eps, ENERGY_SCALE)
    cycles = config.cycles if config.cycles > 0 else 1_000_000
    sol, gain, changed = _solve_band(unary, nbr, nw, init, cycles)
    if changed == 0:
        return amax
    out = amax.copy()
    out.ravel()[pix] = sol
    # Keep the promise in float: never above the argmax's energy. The integer gain is
    # exact for the rounded problem; it can differ from the float gain by less than
    # 10 rounding units per changed pixel (its two unaries of <= 5 rounded parts each,
    # and its 4 edges), so only a small integer gain needs the float check.
    if gain > 10 * changed:
        return out
    if float_gain(proba, amax, out, pix, wh, wv, float(config.eps)) > 0:
        return out
    return amax
