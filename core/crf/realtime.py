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

The solve of a band of PARALLEL_BAND_PIXELS or more runs on BAND_PARTS threads, each part
a set of whole components (`solve_band`): 4.3 -> 3.2 ms median and 9.2 -> 6.5 ms p99 on the
bundled recording's frames. Such a band's problem (`band_problem`: eleven logs a band
pixel) is built row by row on the threads too: 1.75 -> 1.00 ms median on bench frames. The
other kernels are serial: one pass over the frame each, they measured no faster on two
threads (the threads' wake-up eats the gain).
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
    summing the pixel's own keeps this to one comparison; it only ever settles fewer.) An
    upper bound of the second posterior in its place (`argmax.Summary`) also only settles
    fewer.
    """
    return max(psecond[i, j], eps) <= max(pmax[i, j], eps) * keep


#: `free_mask`'s label for a pixel without depth (and the frame's border): agrees with any
NO_LABEL = np.uint8(255)


@numba.njit(cache=True)
def free_mask(amax, pmax, psecond, valid, confidence, ring, smoothness, eps):
    """The band: pixels with depth that are neither sure (top posterior >= `confidence`,
    rounded to float32, and all 4 neighbours with depth share its argmax) nor settled, grown
    by `ring` steps into unsettled pixels.

    Branch-free passes over padded copies (no bounds tests), which LLVM vectorises: 0.5-0.6
    against 1.7-3.4 ms a 640x480 frame for the same masks (docs/performance.md)."""
    h, w = amax.shape
    keep = np.float32(np.exp(-(4.0 * smoothness + SETTLED_MARGIN)))
    eps = np.float32(eps)
    conf = np.float32(confidence)  # a float32 comparison, as numpy's with a Python float
    code = np.empty((h + 2, w + 2), np.uint8)  # the argmax; NO_LABEL off the frame or depth
    code[0, :] = NO_LABEL
    code[h + 1, :] = NO_LABEL
    for i in range(h):
        code[i + 1, 0] = NO_LABEL
        code[i + 1, w + 1] = NO_LABEL
        for j in range(w):
            code[i + 1, j + 1] = amax[i, j] if valid[i, j] else NO_LABEL
    movable = np.empty((h, w), np.bool_)  # with depth and not settled
    for i in range(h):
        for j in range(w):
            movable[i, j] = valid[i, j] & (not settled(i, j, pmax, psecond, keep, eps))
    free = np.zeros((h + 2, w + 2), np.bool_)  # padded: the border is never free
    for i in range(h):
        for j in range(w):
            a = code[i + 1, j + 1]
            agree = True
            for q in (code[i + 1, j], code[i + 1, j + 2], code[i, j + 1], code[i + 2, j + 1]):
                agree &= (q == NO_LABEL) | (q == a)
            sure = (pmax[i, j] >= conf) & agree
            free[i + 1, j + 1] = movable[i, j] & (not sure)
    for _ in range(ring):
        grown = free.copy()
        for i in range(h):
            for j in range(w):
                near = free[i + 1, j] | free[i + 1, j + 2] | free[i, j + 1] | free[i + 2, j + 1]
                grown[i + 1, j + 1] = free[i + 1, j + 1] | (movable[i, j] & near)
        free = grown
    return free[1:-1, 1:-1].copy()


@numba.njit(cache=True)
def number_band(free):
    """Row-major ids of the free pixels: (index (H, W) int32, -1 off the band; count)."""
    h, w = free.shape
    index = np.empty((h, w), np.int32)
    n = np.int32(0)
    for i in range(h):  # branch-free: 0.36 -> 0.26 ms a 640x480 frame
        for j in range(w):
            f = free[i, j]
            index[i, j] = n if f else np.int32(-1)
            n += np.int32(f)
    return index, np.int64(n)


@numba.njit(cache=True, inline="always")
def _neighbour(i, j, s, wh, wv):
    """Neighbour s (left, right, up, down) of pixel (i, j): its row, column and the weight
    (float64) of the edge to it, 0 off the grid."""
    h, w = wv.shape[0] + 1, wh.shape[1] + 1
    if s == 0:
        return i, j - 1, np.float64(wh[i, j - 1]) if j > 0 else 0.0
    if s == 1:
        return i, j + 1, np.float64(wh[i, j]) if j + 1 < w else 0.0
    if s == 2:
        return i - 1, j, np.float64(wv[i - 1, j]) if i > 0 else 0.0
    return i + 1, j, np.float64(wv[i, j]) if i + 1 < h else 0.0


@numba.njit(cache=True, inline="always")
def _band_row(i, proba, amax, index, wh, wv, eps, cap, scale, pix, unary, nbr, nw, init):
    """`band_problem`'s work for the band pixels of row i (each writes only its own rows)."""
    w = amax.shape[1]
    c = proba.shape[2]
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
            ii, jj, wt = _neighbour(i, j, s, wh, wv)
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


@numba.njit(cache=True, inline="always")
def _band_arrays(n, c):
    """Empty outputs of `band_problem` for n band pixels and c labels."""
    return (
        np.empty(n, np.int64),
        np.empty((n, c), np.int32),
        np.full((n, 4), -1, np.int32),
        np.zeros((n, 4), np.int32),
        np.empty(n, np.int32),
    )


@numba.njit(cache=True)
def _band_problem_serial(proba, amax, index, n, wh, wv, eps, scale):
    """`band_problem` on one thread, for bands under PARALLEL_BAND_PIXELS."""
    cap = np.int32(np.rint(-np.log(eps) * scale))
    pix, unary, nbr, nw, init = _band_arrays(n, proba.shape[2])
    for i in range(amax.shape[0]):
        _band_row(i, proba, amax, index, wh, wv, eps, cap, scale, pix, unary, nbr, nw, init)
    return pix, unary, nbr, nw, init


@numba.njit(cache=True, parallel=True)
def _band_problem_parallel(proba, amax, index, n, wh, wv, eps, scale):
    """`band_problem` with its rows on numba's threads: the serial kernel's numbers."""
    cap = np.int32(np.rint(-np.log(eps) * scale))
    pix, unary, nbr, nw, init = _band_arrays(n, proba.shape[2])
    for i in numba.prange(amax.shape[0]):
        # a prange index may be unsigned: int64 keeps i - 1 an integer in the row's body
        _band_row(
            np.int64(i), proba, amax, index, wh, wv, eps, cap, scale, pix, unary, nbr, nw, init
        )
    return pix, unary, nbr, nw, init


def band_problem(proba, amax, index, n, wh, wv, eps, scale):
    """The band's own CRF in gco-style integers (x `scale`, rounded).

    Returns the band pixels' flat ids, (N, C) unaries with the edges to fixed neighbours
    folded in (w [l != their argmax] is a constant per label), a neighbour table (N, 4)
    (left, right, up, down; -1 = none) with its weights, and each pixel's argmax. A band of
    PARALLEL_BAND_PIXELS or more is built on numba's threads, row by row (the same
    numbers: every pixel's entries depend on it and its neighbours only).
    """
    kernel = _band_problem_parallel if n >= PARALLEL_BAND_PIXELS else _band_problem_serial
    return kernel(proba, amax, index, n, wh, wv, eps, scale)


@numba.njit(cache=True)
def float_gain(proba, before, after, pix, wh, wv, eps):
    """E(before) - E(after) in float, for labelings that differ only at band pixels `pix`."""
    w = before.shape[1]
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
            ii, jj, wt = _neighbour(i, j, s, wh, wv)
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


@numba.njit(cache=True)
def band_parts(nbr, n_parts):
    """(N,) int64: the part (0 .. n_parts - 1) of each band pixel. Connected components of
    the band's graph stay whole; the largest first, each goes to the part with the fewest
    pixels so far, so the parts are independent problems of about equal size."""
    n, d = nbr.shape
    comp = np.full(n, -1, np.int64)
    sizes = np.zeros(n, np.int64)
    stack = np.empty(n, np.int64)
    n_comp = 0
    for p0 in range(n):
        if comp[p0] >= 0:
            continue
        comp[p0] = n_comp
        stack[0] = p0
        top = 1
        while top > 0:
            top -= 1
            p = stack[top]
            sizes[n_comp] += 1
            for s in range(d):
                q = nbr[p, s]
                if q >= 0 and comp[q] < 0:
                    comp[q] = n_comp
                    stack[top] = q
                    top += 1
        n_comp += 1
    load = np.zeros(n_parts, np.int64)
    part_of = np.empty(n_comp, np.int64)
    for c in np.argsort(-sizes[:n_comp], kind="mergesort"):
        k = np.argmin(load)
        part_of[c] = k
        load[k] += sizes[c]
    out = np.empty(n, np.int64)
    for p in range(n):
        out[p] = part_of[comp[p]]
    return out


@numba.njit(cache=True, parallel=True)
def _solve_parts(unary, nbr, nw, init, cycles, part, n_parts):
    """`_solve_band` on each part (`band_parts`) by itself, the parts in parallel. An
    expansion move on a union of unconnected graphs is the move on each, except that the
    union takes a part's move of equal energy when another part gains: parts keep their
    labels at such ties, so the labels are a valid expansion result of the whole band that
    may differ from `_solve_band`'s at ties, never in the guarantees."""
    n, d = nbr.shape
    local = np.empty(n, np.int64)  # each pixel's id within its part
    counts = np.zeros(n_parts, np.int64)
    for p in range(n):
        local[p] = counts[part[p]]
        counts[part[p]] += 1
    out = np.empty(n, np.uint8)
    gains = np.zeros(n_parts, np.int64)
    changes = np.zeros(n_parts, np.int64)
    for k in numba.prange(n_parts):
        m = counts[k]
        ids = np.empty(m, np.int64)
        i = 0
        for p in range(n):
            if part[p] == k:
                ids[i] = p
                i += 1
        sub_unary = np.empty((m, unary.shape[1]), unary.dtype)
        sub_nbr = np.full((m, d), -1, nbr.dtype)
        sub_nw = np.empty((m, d), nw.dtype)
        sub_init = np.empty(m, init.dtype)
        for i in range(m):
            p = ids[i]
            sub_unary[i] = unary[p]
            sub_nw[i] = nw[p]
            sub_init[i] = init[p]
            for s in range(d):
                q = nbr[p, s]
                if q >= 0:
                    sub_nbr[i, s] = local[q]
        x, gain, changed = _solve_band(sub_unary, sub_nbr, sub_nw, sub_init, cycles)
        gains[k] = gain
        changes[k] = changed
        for i in range(m):
            out[ids[i]] = x[i]
    return out, gains.sum(), changes.sum()


#: bands of this many pixels or more are split into BAND_PARTS parts, solved in parallel
PARALLEL_BAND_PIXELS = 2048
#: the parts of a large band: the worker's two cores (the labels must not depend on the
#: threads a machine has, so this is a constant; one thread solves the parts in turn)
BAND_PARTS = 2


def solve_band(unary, nbr, nw, init, cycles):
    """Expansion on the band: (labels as uint8, integer energy decrease, pixels changed).
    A band of PARALLEL_BAND_PIXELS or more is split into BAND_PARTS independent problems
    of whole components (`band_parts`), solved in parallel on numba's threads; a smaller
    one is solved as one part.

    `_solve_parts` is the only way in from Python: with `_solve_band` entered directly as
    well, a numba cache whose two entries were written by different runs (two processes
    compiling at once after an update) linked `_solve_band`'s environment to the copy inside
    `_solve_parts`, and returning its labels failed ("'descr' is NULL")."""
    n = init.shape[0]
    if n < PARALLEL_BAND_PIXELS:
        return _solve_parts(unary, nbr, nw, init, cycles, np.zeros(n, np.int64), 1)
    part = band_parts(nbr, BAND_PARTS)
    return _solve_parts(unary, nbr, nw, init, cycles, part, BAND_PARTS)


def warm_up(n_labels: int) -> None:
    """Compile (or load from numba's cache) both paths of the band's problem and of its
    solve, the parallel ones included: a small warm-up frame's band never reaches
    PARALLEL_BAND_PIXELS, and loading a parallel kernel on the first real frame that does
    cost ~40 ms (frames dropped at a worker's start)."""
    n = PARALLEL_BAND_PIXELS
    proba = np.full((1, n, n_labels), 1.0 / n_labels, np.float32)
    index = np.arange(n, dtype=np.int32).reshape(1, n)
    wh, wv = np.ones((1, n - 1), np.float32), np.ones((0, n), np.float32)
    amax = np.zeros((1, n), np.uint8)
    band_problem(proba, amax, index, n, wh, wv, np.float32(1e-6), ENERGY_SCALE)
    unary = np.zeros((n, n_labels), np.int32)
    unary[:, 0] = 1  # every pixel moves to label 1: the moves run their whole path
    nbr = np.full((n, 4), -1, np.int32)
    nbr[1::2, 0], nbr[0::2, 1] = np.arange(0, n, 2), np.arange(1, n, 2)  # pairs of pixels
    nw = np.where(nbr >= 0, 1, 0).astype(np.int32)
    solve_band(unary, nbr, nw, np.zeros(n, np.int32), 1)


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
    sol, gain, changed = solve_band(unary, nbr, nw, init, cycles)
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
