"""Forest inference: walk every tree at every pixel with depth, average the leaf posteriors.

One numba kernel body, compiled once per number k of features per node, parallel over rows.
Within a row the trees are walked level by level for all pixels at once (a pixel's walk is a chain of dependent loads; many independent walks side
by side let the CPU overlap them and let LLVM vectorise the step with gathers). For that the
kernel uses a packed copy of the node arrays (`InferenceTable`): one float32 row per node
(offsets, weights, threshold) and a `step` index in which a leaf points to itself with an
infinite threshold, so one more step never moves a pixel that has arrived; a row stops when
a whole level moved nothing.

Pixels without depth (0) are walked too (their probes read the pixel itself) but their
posterior row is set to all zeros (not a distribution); the argmax (`crf.segment_argmax`)
gives them NO_DEPTH. A node sends a pixel left when its response < threshold (see `features`).
"""

from __future__ import annotations

import functools
import weakref
from dataclasses import dataclass

import numba
import numpy as np

from topseg.core.camera import check_depth
from topseg.core.forest.features import inverse_depth, response_at
from topseg.core.forest.tree import Forest

_i32 = np.int32
_f32 = np.float32


@dataclass(frozen=True)
class InferenceTable:
    """Node arrays packed for the kernel: `nodes` (n, 5k + 1) float32 rows of
    [u_row, u_col, v_row, v_col] * k, weights * k, threshold; `step` (n,) int32: the left
    child, or the node itself for a leaf (whose threshold is +inf)."""

    nodes: np.ndarray
    step: np.ndarray
    k: int


_TABLES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def inference_table(forest: Forest) -> InferenceTable:
    """The packed table of `forest`, built once per forest and cached."""
    table = _TABLES.get(forest)
    if table is None:
        n, k = forest.n_nodes, forest.features_per_node
        is_leaf = forest.left < 0
        nodes = np.zeros((n, 5 * k + 1), np.float32)
        nodes[:, : 4 * k] = forest.offsets.reshape(n, 4 * k)
        nodes[:, 4 * k : 5 * k] = forest.weights
        nodes[:, 5 * k] = forest.threshold
        nodes[is_leaf] = 0.0
        nodes[is_leaf, 5 * k] = np.inf
        step = np.where(is_leaf, np.arange(n), forest.left).astype(np.int32)
        table = InferenceTable(nodes, step, k)
        _TABLES[forest] = table
    return table


@numba.njit(cache=True, inline="always")
def _probe(padded, r, c, inv_d, dr, dc, h, w):
    """`features.probe` on a padded copy whose 1-pixel border (and no-depth pixels) hold
    the background: clamping to the border replaces the bounds tests."""
    pr = r + _i32(np.floor(dr * inv_d + _f32(0.5)))
    pc = c + _i32(np.floor(dc * inv_d + _f32(0.5)))
    pr = min(max(pr, _i32(-1)), h) + _i32(1)
    pc = min(max(pc, _i32(-1)), w) + _i32(1)
    return padded[pr * (w + _i32(2)) + pc]


@numba.njit(cache=True)
def _padded(depth, background):
    h, w = depth.shape
    out = np.full((h + 2) * (w + 2), background, np.int32)
    for r in range(h):
        for c in range(w):
            z = np.int32(depth[r, c])
            if z != 0 and z <= background:
                out[(r + 1) * (w + 2) + c + 1] = z
    return out


@numba.njit(cache=True, inline="always")
def _step(padded, r, c, inv_d, nodes, step, n, k, h, w):
    """One step of a walk: the node `n` sends the pixel to step[n] (left) or step[n] + 1.

    The response sums k weighted probe differences in float32, in feature order (as
    training does); a leaf's infinite threshold keeps the pixel where it is."""
    resp = np.float32(0.0)
    for q in range(k):
        b = 4 * q
        f = _probe(padded, r, c, inv_d, nodes[n, b], nodes[n, b + 1], h, w) - _probe(
            padded, r, c, inv_d, nodes[n, b + 2], nodes[n, b + 3], h, w
        )
        resp += nodes[n, 4 * k + q] * np.float32(f)
    return step[n] + _i32(resp >= nodes[n, 5 * k])


@numba.njit(cache=True, inline="always")
def _row_inverse_depth(depth, r, stride, n_cols):
    """inverse_depth of the evaluated pixels of row r; 0 where there is no depth."""
    inv = np.empty(n_cols, np.float32)
    for j in range(n_cols):
        d = depth[r, j * stride]
        inv[j] = np.float32(1.0) / np.float32(d) if d > 0 else np.float32(0.0)
    return inv


@numba.njit(cache=True, inline="always")
def _accumulate(acc, cur, leaf, posteriors):
    for j in range(cur.shape[0]):
        row = leaf[cur[j]]
        for q in range(posteriors.shape[1]):
            acc[j, q] += posteriors[row, q]


@numba.njit(cache=True, inline="always")
def _write_row(out, r, stride, inv, acc, n_trees):
    scale = np.float32(1.0) / np.float32(n_trees)
    for j in range(inv.shape[0]):
        has_depth = inv[j] > 0
        for q in range(acc.shape[1]):
            out[r, j * stride, q] = acc[j, q] * scale if has_depth else np.float32(0.0)


@functools.cache
def _kernel(k: int):
    """The prediction kernel for forests of k features per node, compiled once per k.

    k is a constant of the kernel (a closure variable, which numba freezes at compile time),
    so `_step`'s feature loop is unrolled and LLVM vectorises the level loop with gathers; a
    k passed at run time would leave a branch in that loop, which stops the vectorisation.
    """

    @numba.njit(cache=True, parallel=True)
    def predict(depth, nodes, step, leaf, posteriors, roots, background, stride, out):
        """Posteriors of the evaluated pixels. Within a row the trees are walked one level
        at a time for all pixels; `cur` is local and the level loop plain so that it
        vectorises."""
        h, w = _i32(depth.shape[0]), _i32(depth.shape[1])
        padded = _padded(depth, background)
        n_rows = (depth.shape[0] + stride - 1) // stride
        n_cols = (depth.shape[1] + stride - 1) // stride
        for i in numba.prange(n_rows):
            r = _i32(i * stride)
            inv = _row_inverse_depth(depth, r, stride, n_cols)
            cur = np.empty(n_cols, np.int32)
            acc = np.zeros((n_cols, posteriors.shape[1]), np.float32)
            for t in range(roots.shape[0]):
                for j in range(n_cols):
                    cur[j] = roots[t]
                while True:
                    moving = 0
                    for j in range(n_cols):
                        n = cur[j]
                        nxt = _step(padded, r, _i32(j * stride), inv[j], nodes, step, n, k, h, w)
                        moving += _i32(nxt != n)
                        cur[j] = nxt
                    if moving == 0:
                        break
                _accumulate(acc, cur, leaf, posteriors)
            _write_row(out, r, stride, inv, acc, roots.shape[0])

    return predict


@numba.njit(cache=True, parallel=True)
def _fill_strided(depth, stride, out):
    """Copy each evaluated pixel's posterior to the stride x stride block it stands for;
    pixels without depth get zeros."""
    h, w = depth.shape
    for r in numba.prange(h):
        r0 = r - r % stride
        for c in range(w):
            c0 = c - c % stride
            if depth[r, c] == 0:
                out[r, c, :] = 0.0
            elif r != r0 or c != c0:
                out[r, c, :] = out[r0, c0, :]


@numba.njit(cache=True, parallel=True)
def _apply(depth, offsets, weights, threshold, left, roots, background, out):
    for r in numba.prange(depth.shape[0]):
        for c in range(depth.shape[1]):
            d = depth[r, c]
            for t in range(roots.shape[0]):
                node = roots[t]
                if d > 0:
                    inv_d = inverse_depth(d)
                    while left[node] >= 0:
                        resp = response_at(
                            depth, r, c, inv_d, offsets[node], weights[node], background
                        )
                        node = left[node] + (0 if resp < threshold[node] else 1)
                out[t, r, c] = node if d > 0 else -1


def predict_proba(
    forest: Forest, depth: np.ndarray, out: np.ndarray | None = None, stride: int = 1
) -> np.ndarray:
    """(H, W, NUM_CLASSES) float32 class posteriors averaged over the trees.

    Rows of pixels without depth are all zero. `out` may be a preallocated C-contiguous
    (H, W, NUM_CLASSES) float32 array to fill (a worker reuses one per frame).
    `stride` > 1 walks the trees only at every stride-th pixel of every stride-th row and
    copies the result over each stride x stride block: a faster, blockier approximation
    (the posteriors at the evaluated pixels are exact).
    """
    depth = check_depth(depth, "forest inference")
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    shape = (*depth.shape, forest.posteriors.shape[1])
    if out is None:
        out = np.empty(shape, np.float32)
    elif out.shape != shape or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ValueError(f"out must be a C-contiguous float32 array of shape {shape}")
    table = inference_table(forest)
    _kernel(table.k)(
        depth,
        table.nodes,
        table.step,
        forest.leaf,
        forest.posteriors,
        forest.roots,
        np.int32(forest.background_mm),
        stride,
        out,
    )
    if stride > 1:
        _fill_strided(depth, stride, out)
    return out


def apply(forest: Forest, depth: np.ndarray) -> np.ndarray:
    """(T, H, W) int32: the leaf node each pixel reaches in each tree; -1 without depth.

    A plain per-pixel walk (not the fast kernel): for inspection, path statistics and tests.
    """
    depth = check_depth(depth, "forest inference")
    out = np.empty((forest.n_trees, *depth.shape), np.int32)
    _apply(
        depth,
        forest.offsets,
        forest.weights,
        forest.threshold,
        forest.left,
        forest.roots,
        np.int32(forest.background_mm),
        out,
    )
    return out


def predict_labels(forest: Forest, depth: np.ndarray, stride: int = 1) -> np.ndarray:
    """(H, W) uint8 most probable label per pixel; NO_DEPTH where depth == 0 (through the
    one argmax, `crf.segment_argmax`, that the CRF's mode `none` is)."""
    from topseg.core.crf.argmax import segment_argmax

    depth = np.asarray(depth)
    return segment_argmax(predict_proba(forest, depth, stride=stride), depth > 0)
