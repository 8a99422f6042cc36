"""Forest inference: walk every tree at every pixel with depth, average the leaf posteriors.

The forest reads a model input (`inputs.ModelInput`: probe values, per-pixel offset scale,
floor gate); a plain depth frame is read as its legacy input, as models trained before
heights expect.

One numba kernel body, compiled once per number k of features per node, parallel over rows.
Within a row the trees are walked level by level for all pixels at once (a pixel's walk is a chain of dependent loads; many independent walks side
by side let the CPU overlap them and let LLVM vectorise the step with gathers). For that the
kernel uses a packed copy of the node arrays (`InferenceTable`): one float32 row per node
(offsets, weights, threshold) and a `step` index in which a leaf points to itself with an
infinite threshold, so one more step never moves a pixel that has arrived; a row stops when
a whole level moved nothing.

Only pixels with depth that the floor gate lets through are walked (a row's pixels to walk
are gathered first). Pixels without depth get an all-zero posterior row (not a
distribution), which the argmax (`crf.segment_argmax`) turns into NO_DEPTH; floor-gated
pixels get background with probability 1. A node sends a pixel left when its response <
threshold (see `features`).
"""

from __future__ import annotations

import functools
import weakref
from dataclasses import dataclass

import numba
import numpy as np

from topseg.core.camera import TopViewMount
from topseg.core.crf.argmax import Summary, summarise_no_depth, summarise_pixel
from topseg.core.forest.features import response_at
from topseg.core.forest.inputs import ModelInput, as_input, check_input
from topseg.core.forest.tree import Forest
from topseg.core.labels import BACKGROUND

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
def _row_pixels(values, scale, floor, r, stride, n_cols):
    """The evaluated pixels of row r to walk (a value and not floor): their columns and
    offset scales, and how many there are."""
    cols = np.empty(n_cols, np.int32)
    inv = np.empty(n_cols, np.float32)
    m = 0
    for j in range(n_cols):
        c = j * stride
        if values[r, c] > 0 and not floor[r, c]:
            cols[m] = c
            inv[m] = scale[r, c]
            m += 1
    return cols[:m], inv[:m]


@numba.njit(cache=True, inline="always")
def _accumulate(acc, cur, leaf, posteriors):
    for j in range(cur.shape[0]):
        row = leaf[cur[j]]
        for q in range(posteriors.shape[1]):
            acc[j, q] += posteriors[row, q]


@numba.njit(cache=True, inline="always")
def _write_row(out, values, floor, r, stride, n_cols, cols, acc, n_trees, amax, pmax, psecond):
    """Row r's evaluated pixels: zeros without a value, background for the floor, the tree
    average for the walked ones; and each one's summary (`crf.argmax.Summary`)."""
    scale = np.float32(1.0) / np.float32(n_trees)
    walked = 0
    for j in range(n_cols):
        c = j * stride
        if walked < cols.shape[0] and cols[walked] == c:
            for q in range(acc.shape[1]):
                out[r, c, q] = acc[walked, q] * scale
            walked += 1
            summarise_pixel(out, r, c, amax, pmax, psecond)
            continue
        for q in range(out.shape[2]):
            out[r, c, q] = np.float32(0.0)
        if values[r, c] > 0:  # the floor: background, sure
            out[r, c, BACKGROUND] = np.float32(1.0)
            summarise_pixel(out, r, c, amax, pmax, psecond)
        else:
            summarise_no_depth(r, c, amax, pmax, psecond)


@functools.cache
def _kernel(k: int):
    """The prediction kernel for forests of k features per node, compiled once per k.

    k is a constant of the kernel (a closure variable, which numba freezes at compile time),
    so `_step`'s feature loop is unrolled and LLVM vectorises the level loop with gathers; a
    k passed at run time would leave a branch in that loop, which stops the vectorisation.
    """

    @numba.njit(cache=True, parallel=True)
    def predict(
        values,
        scale,
        floor,
        nodes,
        step,
        leaf,
        posteriors,
        roots,
        background,
        stride,
        out,
        amax,
        pmax,
        psecond,
    ):
        """Posteriors of the evaluated pixels. Within a row the trees are walked one level
        at a time for all pixels to walk; `cur` is local and the level loop plain so that it
        vectorises."""
        h, w = _i32(values.shape[0]), _i32(values.shape[1])
        padded = _padded(values, background)
        n_rows = (values.shape[0] + stride - 1) // stride
        n_cols = (values.shape[1] + stride - 1) // stride
        for i in numba.prange(n_rows):
            r = _i32(i * stride)
            cols, inv = _row_pixels(values, scale, floor, r, stride, n_cols)
            m = cols.shape[0]
            cur = np.empty(m, np.int32)
            acc = np.zeros((m, posteriors.shape[1]), np.float32)
            for t in range(roots.shape[0]):
                for j in range(m):
                    cur[j] = roots[t]
                while True:
                    moving = 0
                    for j in range(m):
                        n = cur[j]
                        nxt = _step(padded, r, cols[j], inv[j], nodes, step, n, k, h, w)
                        moving += _i32(nxt != n)
                        cur[j] = nxt
                    if moving == 0:
                        break
                _accumulate(acc, cur, leaf, posteriors)
            _write_row(
                out,
                values,
                floor,
                r,
                stride,
                n_cols,
                cols,
                acc,
                roots.shape[0],
                amax,
                pmax,
                psecond,
            )

    return predict


#: the floor distance (mm) between walked pixels that `grid_stride` aims for: 4 px for the
#: Kinect v1 at 3.5 m, where strides 1-4 were measured (docs/performance.md)
GRID_SPACING_MM = 25.0
#: the coarsest grid `grid_stride` picks, px
MAX_STRIDE = 8


def grid_stride(mount: TopViewMount) -> int:
    """The stride whose grid spaces walked pixels about GRID_SPACING_MM apart on the floor
    straight below `mount` (a pixel there spans height / fx mm), between 1 and MAX_STRIDE."""
    floor_px_mm = mount.height_mm / mount.intrinsics.fx
    return int(min(MAX_STRIDE, max(1, round(GRID_SPACING_MM / floor_px_mm))))


#: the height scale (mm) of the edge-aware upsampling: a grid neighbour whose probe value
#: differs by this much counts exp(-1) as much as one at the pixel's own height
UPSAMPLE_SIGMA_MM = 40.0
#: probe values differing by this much or more weigh nothing (exp(-(512 / 40)^2) underflows
#: float32 long before)
_WEIGHT_TABLE_SIZE = 512


@functools.cache
def height_weights(sigma_mm: float = UPSAMPLE_SIGMA_MM) -> np.ndarray:
    """(512,) float32 exp(-(d / sigma)^2) for integer probe-value differences d (mm): the
    range weights of `_upsample`, a table lookup instead of four exps a pixel."""
    d = np.arange(_WEIGHT_TABLE_SIZE, dtype=np.float32) / np.float32(sigma_mm)
    table = np.exp(-(d * d)).astype(np.float32)
    table.flags.writeable = False
    return table


@numba.njit(cache=True, inline="always")
def _range_weight(values, gr, gc, v, spatial, table):
    """Grid pixel (gr, gc)'s weight for a pixel of probe value v: 0 without a value."""
    g = values[gr, gc]
    if g == 0:
        return np.float32(0.0)
    d = abs(np.int32(g) - v)
    if d >= table.shape[0]:
        return np.float32(0.0)
    return spatial * table[d]


@numba.njit(cache=True, parallel=True)
def _upsample(values, floor, stride, table, out, amax, pmax, psecond):
    """Posteriors between the grid points of a strided walk (joint bilateral upsampling,
    Kopf et al. 2007): each pixel with a value averages the posteriors of the up to four
    grid pixels around it, weighted bilinearly and by `table[|dv|]` (`height_weights`:
    exp(-(dv / sigma)^2) of the probe value difference), so an edge in height is an edge
    in the posteriors. Where every neighbour's weight underflows, the neighbour closest in
    value wins; where none of them has a value, zeros (no posterior, as without depth).
    Pixels without a value get zeros, floor pixels background; grid pixels keep their
    walked posteriors. Each pixel written gets its summary (`crf.argmax.Summary`)."""
    h, w = values.shape
    n_classes = out.shape[2]
    last_r = (h - 1) - (h - 1) % stride
    last_c = (w - 1) - (w - 1) % stride
    for r in numba.prange(h):
        r0 = r - r % stride
        r1 = min(r0 + stride, last_r)
        wr0 = np.float32(stride - (r - r0))
        wr1 = np.float32(stride - (r1 - r)) if r1 != r0 else np.float32(0.0)
        for c in range(w):
            c0 = c - c % stride
            if r == r0 and c == c0:
                continue
            v = np.int32(values[r, c])
            if v == 0 or floor[r, c]:
                for q in range(n_classes):
                    out[r, c, q] = np.float32(0.0)
                if v != 0:
                    out[r, c, BACKGROUND] = np.float32(1.0)
                    summarise_pixel(out, r, c, amax, pmax, psecond)
                else:
                    summarise_no_depth(r, c, amax, pmax, psecond)
                continue
            c1 = min(c0 + stride, last_c)
            wc0 = np.float32(stride - (c - c0))
            wc1 = np.float32(stride - (c1 - c)) if c1 != c0 else np.float32(0.0)
            w00 = _range_weight(values, r0, c0, v, wr0 * wc0, table)
            w01 = _range_weight(values, r0, c1, v, wr0 * wc1, table)
            w10 = _range_weight(values, r1, c0, v, wr1 * wc0, table)
            w11 = _range_weight(values, r1, c1, v, wr1 * wc1, table)
            total = w00 + w01 + w10 + w11
            if total > np.float32(1e-30):
                inv = np.float32(1.0) / total
                w00, w01, w10, w11 = w00 * inv, w01 * inv, w10 * inv, w11 * inv
                for q in range(n_classes):
                    out[r, c, q] = (
                        w00 * out[r0, c0, q]
                        + w01 * out[r0, c1, q]
                        + w10 * out[r1, c0, q]
                        + w11 * out[r1, c1, q]
                    )
                summarise_pixel(out, r, c, amax, pmax, psecond)
                continue
            best_r, best_c, best = -1, -1, np.int32(1 << 30)
            for gr in (r0, r1):
                for gc in (c0, c1):
                    if values[gr, gc] > 0:
                        d = abs(np.int32(values[gr, gc]) - v)
                        if d < best:
                            best_r, best_c, best = gr, gc, d
            for q in range(n_classes):
                out[r, c, q] = out[best_r, best_c, q] if best_r >= 0 else np.float32(0.0)
            summarise_pixel(out, r, c, amax, pmax, psecond)


@numba.njit(cache=True, parallel=True)
def _apply(values, scale, floor, offsets, weights, threshold, left, roots, background, out):
    for r in numba.prange(values.shape[0]):
        for c in range(values.shape[1]):
            walk = values[r, c] > 0 and not floor[r, c]
            for t in range(roots.shape[0]):
                node = roots[t]
                if walk:
                    inv_d = scale[r, c]
                    while left[node] >= 0:
                        resp = response_at(
                            values, r, c, inv_d, offsets[node], weights[node], background
                        )
                        node = left[node] + (0 if resp < threshold[node] else 1)
                out[t, r, c] = node if walk else -1


def predict_proba(
    forest: Forest,
    frame: np.ndarray | ModelInput,
    out: np.ndarray | None = None,
    stride: int = 1,
    summary: Summary | None = None,
) -> np.ndarray:
    """(H, W, NUM_CLASSES) float32 class posteriors averaged over the trees.

    `frame` is a model input (`inputs.model_input`) or a depth frame, read as its legacy
    input (what models trained before heights expect). Rows of pixels without depth are all
    zero, floor-gated pixels are background. `out` may be a preallocated C-contiguous
    (H, W, NUM_CLASSES) float32 array to fill (a worker reuses one per frame).
    `stride` > 1 walks the trees only at every stride-th pixel of every stride-th row and
    fills the pixels between by edge-aware upsampling (`_upsample`): stride**2 times fewer
    walks; the posteriors at the grid pixels are exact.
    `summary` (`crf.argmax.Summary` of (H, W) buffers), when given, is filled with every
    pixel's argmax and top two posteriors as the posteriors are written: what the CRF reads,
    without another pass over them (`crf.segment_crf(..., summary=)`).
    """
    inp = check_input(as_input(frame), "forest inference")
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    shape = (*inp.shape, forest.posteriors.shape[1])
    if out is None:
        out = np.empty(shape, np.float32)
    elif out.shape != shape or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ValueError(f"out must be a C-contiguous float32 array of shape {shape}")
    if summary is None:
        summary = Summary.empty(inp.shape)
    elif any(a.shape != inp.shape or not a.flags.c_contiguous for a in summary):
        raise ValueError(f"summary arrays must be C-contiguous of shape {inp.shape}")
    table = inference_table(forest)
    _kernel(table.k)(
        inp.values,
        inp.scale,
        inp.floor,
        table.nodes,
        table.step,
        forest.leaf,
        forest.posteriors,
        forest.roots,
        np.int32(forest.background_mm),
        stride,
        out,
        *summary,
    )
    if stride > 1:
        _upsample(inp.values, inp.floor, stride, height_weights(), out, *summary)
    return out


def apply(forest: Forest, frame: np.ndarray | ModelInput) -> np.ndarray:
    """(T, H, W) int32: the leaf node each pixel reaches in each tree; -1 where the forest is
    not walked (no depth, or the floor gate).

    A plain per-pixel walk (not the fast kernel): for inspection, path statistics and tests.
    """
    inp = check_input(as_input(frame), "forest inference")
    out = np.empty((forest.n_trees, *inp.shape), np.int32)
    _apply(
        inp.values,
        inp.scale,
        inp.floor,
        forest.offsets,
        forest.weights,
        forest.threshold,
        forest.left,
        forest.roots,
        np.int32(forest.background_mm),
        out,
    )
    return out


def predict_labels(forest: Forest, frame: np.ndarray | ModelInput, stride: int = 1) -> np.ndarray:
    """(H, W) uint8 most probable label per pixel; NO_DEPTH where depth == 0 (through the
    one argmax, `crf.segment_argmax`, that the CRF's mode `none` is)."""
    from topseg.core.crf.argmax import segment_argmax

    inp = as_input(frame)
    return segment_argmax(predict_proba(forest, inp, stride=stride), inp.values > 0)
