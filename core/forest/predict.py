"""Forest inference: walk every tree at every pixel with depth, average the leaf posteriors.

The forest reads a model input (`inputs.ModelInput`: probe values, per-pixel offset scale,
floor gate); a plain depth frame is read as its legacy input, as a model whose header names
no input expects.

One numba kernel body, compiled once per number k of features per node, parallel over rows.
Within a row the trees are walked level by level for all pixels at once: a pixel's walk is a
chain of dependent loads, and many independent walks side by side let the CPU overlap them
(the level loop compiles to scalar code; LLVM does not vectorise it). Each step prefetches
the record the pixel goes to, which the next level reads a whole row of pixels later.
The kernel reads a packed copy of the split nodes (`InferenceTable`): one 64-byte,
cache-line-aligned record per split for k = 2 (offsets, weights, threshold, both children,
which v probes are far), no records for leaves, a uint16 probe image; a pixel that has
arrived at a leaf reads a stand-in record and keeps its state, and a row's tree is done when
every pixel has arrived. The probe image has a background border as wide as the frame's
probes reach (`probe_pad`, at most MAX_PAD), so a probe needs no clamping to the image; a
far v probe (`features.FAR_OFFSET`, an absolute feature's) reads the background by a select
instead of landing anywhere. A frame whose probes reach farther than MAX_PAD is walked by a
variant of the same kernel that clamps each probe to the image (one body; `_kernel`).
Results are bit-identical to a plain walk (`apply`, `tests/reference.py`).

With an early exit (`predict_proba(..., early_exit=)`, on in the Segmenter), a pixel whose
first EARLY_TREES trees (or more) already agree stops: before each further tree, the pixels
whose best class averages at least the early-exit posterior leave the row's walk, and their
posterior is the average of the trees they walked (`_keep_unsure`).

Only pixels with depth that the floor gate lets through are walked (a row's pixels to walk
are gathered first, from the grid's plan: `_grid_plan`, or `_settle` on an adaptive grid,
where a pixel that the coarser grid around it settles is upsampled instead of walked). Pixels without depth get an all-zero posterior row (not a
distribution), which the argmax (`crf.segment_argmax`) turns into NO_DEPTH; floor-gated
pixels get background with probability 1. A node sends a pixel left when its response <
threshold (see `features`).
"""

from __future__ import annotations

import functools
import math
import weakref
from dataclasses import dataclass

import numba
import numpy as np
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic

from topseg.core.camera import TopViewMount
from topseg.core.crf.argmax import (
    Summary,
    segment_argmax,
    summarise_no_depth,
    summarise_pixel,
    summarise_values,
)
from topseg.core.forest.features import FAR_OFFSET, response_at
from topseg.core.forest.inputs import ModelInput, as_input, check_input
from topseg.core.forest.tree import Forest
from topseg.core.labels import BACKGROUND

_i32 = np.int32
_f32 = np.float32


#: bytes of a cache line: the table starts on one, so no record spans more lines than it fills
_CACHE_LINE = 64


#: what a grid pixel gets (`_grid_plan`, `_settle`): walked through the trees, background
#: (the floor gate), zeros (no value), or nothing (its posterior is already written)
WALK, FLOOR, NO_VALUE, DONE = 0, 1, 2, 3

#: the adaptive grid (`predict_proba(..., adaptive=)`): a grid pixel between the points of
#: the grid twice as coarse is settled (not walked) when all of the points around it have
#: the same argmax with at least this posterior ...
SETTLE_CONFIDENCE = 0.5
#: ... and probe values within this many mm of its own (2 UPSAMPLE_SIGMA_MM: the upsampling
#: weighs a point farther than that by less than exp(-4)); it takes their upsampled posterior
SETTLE_REACH_MM = 80

#: the widest background border (px) the probe image gets (`_padded`): a frame whose probes
#: all land within it (`probe_pad`) is walked with no probe clamped to the image, ~17 % faster
#: than clamping each (docs/performance.md); one whose probes reach farther (a surface within
#: ~30 cm of a full-resolution camera) is walked with clamped probes, with the same results.
#: 256 px makes a 640x480 frame's probe image 2.3 MB at most.
MAX_PAD = 256

#: early exit (`predict_proba(..., early_exit=)`): a walked pixel may stop walking trees once
#: it has walked this many (`SegmenterConfig.early_exit` says at what confidence)
EARLY_TREES = 2


def _record_words(k: int) -> int:
    """The 32-bit words of one split record for k features per node (`InferenceTable`):
    its 6k + 3 words rounded up to 8 (32 bytes, two records to a cache line) or to whole
    cache lines (16 words: 64 bytes for k = 1 and k = 2, the bundled model's)."""
    used = 6 * k + 3
    return 8 if used <= 8 else 16 * -(-used // 16)


@dataclass(frozen=True)
class InferenceTable:
    """A forest's splits packed for the kernel, one cache-aligned record per split node.

    `words` (n_splits + 1, R) int32 rows, R = `_record_words(k)`, read as float32 through
    `fields` (the same memory): [u_row, u_col, v_row, v_col] * k, weights * k, threshold
    (float32), then the left and right child (int32), then k flags (int32 1 where the
    feature's v is far, `features.is_far`: it reads the background, and its offsets are
    stored as 0 so that it lands on the pixel itself), zero padding. Leaves have no record:
    a walk's state is a split's row, or `n_splits` + the leaf's posterior row once it has
    arrived. Row `n_splits` is a stand-in every arrived pixel reads (zero offsets, +inf
    threshold) so that the level loop needs no branch; its children are never taken.
    `roots` (T,) are the trees' root states. `reach` is the largest offset component a
    probe is moved by (pixel*mm, far v offsets left out): `probe_pad` reads it."""

    words: np.ndarray
    fields: np.ndarray
    roots: np.ndarray
    k: int
    reach: float

    @property
    def n_splits(self) -> int:
        """Split records, the first arrived state."""
        return self.words.shape[0] - 1


def _aligned_zeros(rows: int, cols: int) -> np.ndarray:
    """(rows, cols) int32 zeros whose first byte starts a cache line."""
    n = rows * cols
    raw = np.zeros(n + _CACHE_LINE // 4, np.int32)
    skip = (-raw.ctypes.data % _CACHE_LINE) // 4
    return raw[skip : skip + n].reshape(rows, cols)


_TABLES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def inference_table(forest: Forest) -> InferenceTable:
    """The packed table of `forest`, built once per forest and cached."""
    table = _TABLES.get(forest)
    if table is None:
        k = forest.features_per_node
        split = np.flatnonzero(forest.left >= 0)
        s = split.size
        # state of every node: its split row, or s + its posterior row for a leaf
        state = np.where(forest.left >= 0, -1, s + forest.leaf).astype(np.int64)
        state[split] = np.arange(s)
        words = _aligned_zeros(s + 1, _record_words(k))
        fields = words.view(np.float32)
        offsets = forest.offsets[split].copy()  # (s, k, 4)
        far = (np.abs(offsets[:, :, 2]) >= FAR_OFFSET) | (np.abs(offsets[:, :, 3]) >= FAR_OFFSET)
        offsets[:, :, 2:][far] = 0.0
        fields[:s, : 4 * k] = offsets.reshape(s, 4 * k)
        fields[:s, 4 * k : 5 * k] = forest.weights[split]
        fields[:s, 5 * k] = forest.threshold[split]
        fields[s, 5 * k] = np.inf
        left = forest.left[split]
        words[:s, 5 * k + 1] = state[left]
        words[:s, 5 * k + 2] = state[left + 1]
        words[:s, 5 * k + 3 : 6 * k + 3] = far
        words.flags.writeable = False
        fields.flags.writeable = False
        roots = state[forest.roots].astype(np.int32)
        reach = float(np.abs(offsets).max()) if s else 0.0
        table = InferenceTable(words, fields, roots, k, reach)
        _TABLES[forest] = table
    return table


@intrinsic
def _prefetch(typingctx, table, i):
    """Ask the CPU to start fetching element i of the 1-D `table` (and the rest of its cache
    line) into the first-level cache (`llvm.prefetch`: a hint, which neither blocks nor
    faults)."""

    def codegen(context, builder, signature, args):
        table_type, i_type = signature.args
        array = context.make_array(table_type)(context, builder, args[0])
        index = context.cast(builder, args[1], i_type, types.intp)
        ptr = cgutils.get_item_pointer(context, builder, table_type, array, [index])
        byte_ptr = ir.IntType(8).as_pointer()
        int32 = ir.IntType(32)
        fn = cgutils.get_or_insert_function(
            builder.module,
            ir.FunctionType(ir.VoidType(), [byte_ptr] + [int32] * 3),
            "llvm.prefetch.p0i8",
        )
        read, keep_close, data = ir.Constant(int32, 0), ir.Constant(int32, 3), ir.Constant(int32, 1)
        builder.call(fn, [builder.bitcast(ptr, byte_ptr), read, keep_close, data])
        return context.get_dummy_value()

    return types.void(table, i), codegen


@numba.njit(cache=True, inline="always")
def _probe(padded, base, r, c, inv_d, dr, dc, h, w, wp, clamp):
    """`features.probe` at pixel (r, c), whose place in the padded probe image (`_padded`,
    rows `wp` wide) is `base`: no-depth pixels hold the background, the border what a
    probe off the image reads. With
    `clamp` (a compile-time constant) the probe is clamped to the 1-pixel border, which
    replaces the bounds tests; without, the border is wide enough for every probe. The
    place is never negative: read as unsigned, it needs no wraparound test."""
    pr = _i32(np.floor(dr * inv_d + _f32(0.5)))
    pc = _i32(np.floor(dc * inv_d + _f32(0.5)))
    if clamp:
        pr = min(max(pr, _i32(-1) - r), h - r)
        pc = min(max(pc, _i32(-1) - c), w - c)
    return _i32(padded[np.uint32(base + pr * wp + pc)])


def probe_pad(reach: float, scale: np.ndarray) -> float:
    """The border (px) a probe image needs so that no probe of a pixel with offset scale at
    most max(`scale`) lands beyond it, for offset components up to `reach` (pixel*mm,
    `InferenceTable.reach`); float32 rounding included. inf when that is not finite."""
    top = float(scale.max()) if scale.size else 0.0
    need = reach * top * (1.0 + 1e-6)
    return math.ceil(need) + 2.0 if math.isfinite(need) else math.inf


@numba.njit(cache=True)
def _padded(depth, background, pad, nearest):
    """The probe image as uint16 (half the cache footprint of int32; background <= 16000
    fits), flattened with a border `pad` pixels wide; no-depth pixels hold background, the
    border the nearest edge pixel's value when `nearest` (`Forest.nearest_off_image`), else
    background."""
    h, w = depth.shape
    wp = w + 2 * pad
    out = np.empty((h + 2 * pad) * wp, np.uint16)
    if not nearest or h == 0:  # else the rows above and below are copied from the edge's
        out[: pad * wp] = background  # one write per element, a select per pixel: 0.37 -> 0.23 ms
        out[(h + pad) * wp :] = background
    for r in range(h):
        base = (r + pad) * wp
        for c in range(w):
            z = np.int32(depth[r, c])
            out[base + pad + c] = z if (z != 0 and z <= background) else background
        if nearest:
            out[base : base + pad] = out[base + pad]
            out[base + pad + w : base + wp] = out[base + pad + w - 1]
        else:
            out[base : base + pad] = background
            out[base + pad + w : base + wp] = background
    if nearest and h > 0:
        for r in range(pad):
            out[r * wp : (r + 1) * wp] = out[pad * wp : (pad + 1) * wp]
            last = (h + pad - 1) * wp
            out[(h + pad + r) * wp : (h + pad + r + 1) * wp] = out[last : last + wp]
    return out


@numba.njit(cache=True, inline="always")
def _step(padded, base, r, c, inv_d, fields, words, at, k, h, w, wp, background, clamp):
    """One step of a walk from the split record that starts at word `at` of the flat
    table (`InferenceTable`, `fields` and `words` its two readings): its left child's state
    if the response < threshold, else its right child's.

    The response sums k weighted probe differences in float32, in feature order (as
    training does); a far v probe reads `background` (a select on its flag)."""
    resp = np.float32(0.0)
    for q in range(k):
        b = at + 4 * q
        u = _probe(padded, base, r, c, inv_d, fields[b], fields[b + 1], h, w, wp, clamp)
        v = _probe(padded, base, r, c, inv_d, fields[b + 2], fields[b + 3], h, w, wp, clamp)
        v = background if words[at + 5 * k + 3 + q] != 0 else v
        resp += fields[at + 4 * k + q] * np.float32(u - v)
    return words[at + 5 * k + 1 + _i32(resp >= fields[at + 5 * k])]


@numba.njit(cache=True, inline="always")
def _row_pixels(plan, scale, i, r, stride):
    """The grid pixels of grid row i (pixel row r) to walk (`WALK` in the plan): their
    columns and offset scales, and how many there are."""
    n_cols = plan.shape[1]
    cols = np.empty(n_cols, np.int32)
    inv = np.empty(n_cols, np.float32)
    m = 0
    for j in range(n_cols):
        if plan[i, j] == WALK:
            c = j * stride
            cols[m] = c
            inv[m] = scale[r, c]
            m += 1
    return cols[:m], inv[:m]


@numba.njit(cache=True, inline="always")
def _accumulate(acc, cur, pix, m, n_splits, posteriors):
    """Add each of the m arrived pixels' leaf posterior (state `n_splits` + its row) to its
    sum (row `pix[a]` of `acc`)."""
    for a in range(m):
        row = cur[a] - n_splits
        j = pix[a]
        for q in range(posteriors.shape[1]):
            acc[j, q] += posteriors[row, q]


@numba.njit(cache=True, inline="always")
def _write_row(out, plan, i, r, stride, acc, trees, walked, amax, pmax, psecond):
    """Grid row i's pixels as its plan says: the average of the trees each walked one went
    through, background for the floor, zeros without a value, nothing for those already
    written; and the summary (`crf.argmax.Summary`) of each one written. `walked`, unless
    empty, gets the number of trees of each walked pixel."""
    j_walked = 0
    for j in range(plan.shape[1]):
        c = j * stride
        step = plan[i, j]
        if step == WALK:
            scale = np.float32(1.0) / np.float32(trees[j_walked])
            for q in range(acc.shape[1]):
                out[r, c, q] = acc[j_walked, q] * scale
            if walked.size:
                walked[r, c] = trees[j_walked]
            j_walked += 1
            summarise_pixel(out, r, c, amax, pmax, psecond)
        elif step == FLOOR or step == NO_VALUE:
            _write_fixed(out, r, c, step == FLOOR)
            if step == FLOOR:
                summarise_pixel(out, r, c, amax, pmax, psecond)
            else:
                summarise_no_depth(r, c, amax, pmax, psecond)


@numba.njit(cache=True, inline="always")
def _keep_unsure(acc, trees, t, confidence, pix, cols, inv, m):
    """Early exit after t trees: of the m pixels still walking (`pix` their rows of `acc`,
    the sums of their first t posteriors), those whose best class averages at least
    `confidence` stop (`trees` = t); the rest are moved to the front of `pix`, `cols` and
    `inv`. Returns how many walk on."""
    bar = confidence * np.float32(t)
    kept = 0
    for a in range(m):
        j = pix[a]
        best = acc[j, 0]
        for q in range(1, acc.shape[1]):
            best = max(best, acc[j, q])
        if best >= bar:
            trees[j] = t
        else:
            pix[kept] = j
            cols[kept] = cols[a]
            inv[kept] = inv[a]
            kept += 1
    return kept


@numba.njit(cache=True, inline="always")
def _interleaved(j, n):
    """The j-th of n grid rows in the order the walk takes them: the even rows, then the odd
    ones. numba hands each of two threads one half of a parallel loop, and a person fills a
    band of rows, so halves of the frame hold unequal work (up to 3:1 on the bench frames);
    even and odd rows hold nearly equal work (the walk 2-7 % faster, docs/performance.md)."""
    half = (n + 1) // 2
    return 2 * j if j < half else 2 * (j - half) + 1


@functools.cache
def _kernel(k: int, clamp: bool):
    """The prediction kernel for forests of k features per node, compiled once per (k,
    clamp): probes clamped to the image, or a probe image bordered wide enough for all.

    k and clamp are constants of the kernel (closure variables, which numba freezes at
    compile time), so `_step`'s feature loop is unrolled, the record's fields sit at
    constant offsets of a record of constant size (the table is read flat) and the clamping
    is compiled in or out.
    """
    size = _record_words(k)

    @numba.njit(cache=True, parallel=True)
    def predict(
        padded,
        pad,
        background,
        scale,
        plan,
        fields,
        words,
        posteriors,
        roots,
        stride,
        early_trees,
        confidence,
        out,
        amax,
        pmax,
        psecond,
        walked,
    ):
        """Posteriors of the grid pixels that `plan` walks or fixes. Within a row the trees
        are walked one level at a time for all pixels to walk, until all have arrived at a
        leaf; an arrived pixel reads the stand-in record and keeps its state (a select, not
        a branch). From tree `early_trees` on, before each tree, the pixels whose average so
        far reaches `confidence` stop (`_keep_unsure`)."""
        h, w = _i32(scale.shape[0]), _i32(scale.shape[1])
        wp = w + _i32(2) * pad
        n_splits = _i32(words.shape[0] - 1)
        flat_fields, flat_words = fields.reshape(fields.size), words.reshape(words.size)
        n_trees = roots.shape[0]
        for j in numba.prange(plan.shape[0]):
            i = _interleaved(j, plan.shape[0])
            r = _i32(i * stride)
            row_base = (r + pad) * wp + pad  # pixel (r, 0) in the padded probe image
            cols, inv = _row_pixels(plan, scale, i, r, stride)
            m = cols.shape[0]
            cur = np.empty(m, np.int32)
            pix = np.arange(m).astype(np.int32)  # the acc row of each pixel still walking
            trees = np.full(m, n_trees, np.int32)
            acc = np.zeros((m, posteriors.shape[1]), np.float32)
            for t in range(n_trees):
                if t >= early_trees:
                    m = _keep_unsure(acc, trees, t, confidence, pix, cols, inv, m)
                for a in range(m):
                    cur[a] = roots[t]
                walking = _i32(m) if roots[t] < n_splits else _i32(0)
                while walking > 0:
                    walking = 0
                    fetched = _i32(-1)
                    for a in range(m):
                        n = cur[a]
                        rec = min(n, n_splits)
                        c = cols[a]
                        nxt = _step(
                            padded,
                            row_base + c,
                            r,
                            c,
                            inv[a],
                            flat_fields,
                            flat_words,
                            np.uint32(rec * size),
                            k,
                            h,
                            w,
                            wp,
                            background,
                            clamp,
                        )
                        nxt = nxt if n < n_splits else n
                        walking += _i32(nxt < n_splits)
                        cur[a] = nxt
                        # the record the next level reads; not when the pixel before went there
                        # too (at stride 1 such repeats made prefetching cost more than it saved)
                        if nxt != fetched:
                            _prefetch(flat_words, np.uint32(min(nxt, n_splits) * size))
                            fetched = nxt
                _accumulate(acc, cur, pix, m, n_splits, posteriors)
            _write_row(out, plan, i, r, stride, acc, trees, walked, amax, pmax, psecond)

    return predict


#: the floor distance (mm) between walked pixels that `grid_stride` aims for: 4 px for the
#: Kinect v1 at 3.5 m, where strides 1-4 were measured (docs/performance.md)
GRID_SPACING_MM = 25.0
#: the coarsest grid `grid_stride` picks, px
MAX_STRIDE = 8


def grid_stride(mount: TopViewMount) -> int:
    """The stride whose grid spaces walked pixels about GRID_SPACING_MM apart on the floor
    straight below `mount` (a pixel there spans height / fx mm), between 1 and MAX_STRIDE."""
    return int(min(MAX_STRIDE, max(1, round(GRID_SPACING_MM / mount.floor_pixel_mm()))))


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


@numba.njit(cache=True, inline="always")
def _corner_weights(values, table, r0, r1, wr0, wr1, c, stride, last_c, v):
    """The grid columns c0 <= c <= c1 around column c and the four corners' weights (see
    `_upsample`) for an in-between pixel of probe value v > 0, with their sum."""
    c0 = c - c % stride
    c1 = min(c0 + stride, last_c)
    wc0 = np.float32(stride - (c - c0))
    wc1 = np.float32(stride - (c1 - c)) if c1 != c0 else np.float32(0.0)
    w00 = _range_weight(values, r0, c0, v, wr0 * wc0, table)
    w01 = _range_weight(values, r0, c1, v, wr0 * wc1, table)
    w10 = _range_weight(values, r1, c0, v, wr1 * wc0, table)
    w11 = _range_weight(values, r1, c1, v, wr1 * wc1, table)
    return c0, c1, w00, w01, w10, w11, w00 + w01 + w10 + w11


@numba.njit(cache=True, inline="always")
def _blend(values, out, r0, r1, c0, c1, w00, w01, w10, w11, total, v, buf):
    """The upsampled posterior of an in-between pixel of probe value v from its corners and
    their weights (`_corner_weights`) into `buf`: the weighted mean, or where every weight
    underflows the corner closest in value, or zeros where no corner has a value."""
    if total > np.float32(1e-30):
        inv = np.float32(1.0) / total
        w00, w01, w10, w11 = w00 * inv, w01 * inv, w10 * inv, w11 * inv
        for q in range(buf.shape[0]):
            buf[q] = (
                w00 * out[r0, c0, q]
                + w01 * out[r0, c1, q]
                + w10 * out[r1, c0, q]
                + w11 * out[r1, c1, q]
            )
        return
    best_r, best_c, best = -1, -1, np.int32(1 << 30)
    for gr in (r0, r1):
        for gc in (c0, c1):
            if values[gr, gc] > 0:
                d = abs(np.int32(values[gr, gc]) - v)
                if d < best:
                    best_r, best_c, best = gr, gc, d
    for q in range(buf.shape[0]):
        buf[q] = out[best_r, best_c, q] if best_r >= 0 else np.float32(0.0)


@numba.njit(cache=True, inline="always")
def _between(values, table, out, r0, r1, wr0, wr1, c, stride, last_c, v, buf):
    """The upsampled posterior (see `_upsample`) of the in-between pixel of probe value
    v > 0 in column c of a row between grid rows r0 and r1 (weights wr0, wr1) into `buf`."""
    c0, c1, w00, w01, w10, w11, total = _corner_weights(
        values, table, r0, r1, wr0, wr1, c, stride, last_c, v
    )
    _blend(values, out, r0, r1, c0, c1, w00, w01, w10, w11, total, v, buf)


@numba.njit(cache=True, inline="always")
def _summarise_agreed(r, c, r0, r1, c0, c1, w00, w01, w10, w11, total, amax, pmax, psecond):
    """Summarise the in-between pixel (r, c) from its corners' summaries alone, given their
    weights (`_corner_weights`), when every corner that weighs has the same argmax: its top
    posterior is then exactly the upsampled one (`_blend`'s sums in the same order), and the
    weighed sum of the corners' second posteriors bounds every other class's upsampled
    posterior from above, so it stands for the second. Returns False, writing nothing, when
    the corners disagree, none weighs, or the bound does not stay below the top."""
    if not total > np.float32(1e-30):
        return False
    label = np.int32(-1)
    for gr, gc, wt in ((r0, c0, w00), (r0, c1, w01), (r1, c0, w10), (r1, c1, w11)):
        if wt > 0:
            if label < 0:
                label = np.int32(amax[gr, gc])
            elif amax[gr, gc] != label:
                return False
    inv = np.float32(1.0) / total
    w00, w01, w10, w11 = w00 * inv, w01 * inv, w10 * inv, w11 * inv
    top = w00 * pmax[r0, c0] + w01 * pmax[r0, c1] + w10 * pmax[r1, c0] + w11 * pmax[r1, c1]
    second = (
        w00 * psecond[r0, c0]
        + w01 * psecond[r0, c1]
        + w10 * psecond[r1, c0]
        + w11 * psecond[r1, c1]
    )
    if not second < top:
        return False
    amax[r, c] = label
    pmax[r, c] = top
    psecond[r, c] = second
    return True


@numba.njit(cache=True, inline="always")
def _last_on_grid(n, stride):
    """The last of n rows (or columns) on the stride grid."""
    return (n - 1) - (n - 1) % stride


@numba.njit(cache=True, inline="always")
def _grid_rows(r, stride, last_r):
    """The grid rows r0 <= r <= r1 around row r and their bilinear weights."""
    r0 = r - r % stride
    r1 = min(r0 + stride, last_r)
    wr0 = np.float32(stride - (r - r0))
    wr1 = np.float32(stride - (r1 - r)) if r1 != r0 else np.float32(0.0)
    return r0, r1, wr0, wr1


@numba.njit(cache=True, inline="always")
def _write_fixed(out, r, c, has_value):
    """A pixel the forest does not decide: background for the floor, zeros without a value."""
    for q in range(out.shape[2]):
        out[r, c, q] = np.float32(0.0)
    if has_value:
        out[r, c, BACKGROUND] = np.float32(1.0)


@numba.njit(cache=True, parallel=True)
def _upsample(values, floor, stride, table, out, amax, pmax, psecond, write):
    """Posteriors between the grid points of a strided walk (joint bilateral upsampling,
    Kopf et al. 2007): each pixel with a value averages the posteriors of the up to four
    grid pixels around it, weighted bilinearly and by `table[|dv|]` (`height_weights`:
    exp(-(dv / sigma)^2) of the probe value difference), so an edge in height is an edge
    in the posteriors. Where every neighbour's weight underflows, the neighbour closest in
    value wins; where none of them has a value, zeros (no posterior, as without depth).
    Pixels without a value get zeros, floor pixels background; grid pixels keep their
    walked posteriors. Every in-between pixel gets its summary (`crf.argmax.Summary`); its
    posterior is stored only when `write` (else `_fill` stores it where it is needed).
    Without `write`, a pixel whose weighing corners share their argmax is summarised from
    their summaries (`_summarise_agreed`: its second posterior is then an upper bound) and
    its posteriors are not blended: 1.8 -> 1.2-1.5 ms a bench frame."""
    h, w = values.shape
    last_r, last_c = _last_on_grid(h, stride), _last_on_grid(w, stride)
    for r in numba.prange(h):
        buf = np.empty(out.shape[2], np.float32)
        r0, r1, wr0, wr1 = _grid_rows(r, stride, last_r)
        for c in range(w):
            if r == r0 and c % stride == 0:
                continue
            v = np.int32(values[r, c])
            if v == 0 or floor[r, c]:
                if write:
                    _write_fixed(out, r, c, v != 0)
                if v != 0:
                    amax[r, c] = BACKGROUND
                    pmax[r, c] = np.float32(1.0)
                    psecond[r, c] = np.float32(0.0)
                else:
                    summarise_no_depth(r, c, amax, pmax, psecond)
                continue
            c0, c1, w00, w01, w10, w11, total = _corner_weights(
                values, table, r0, r1, wr0, wr1, c, stride, last_c, v
            )
            if not write and _summarise_agreed(
                r, c, r0, r1, c0, c1, w00, w01, w10, w11, total, amax, pmax, psecond
            ):
                continue
            _blend(values, out, r0, r1, c0, c1, w00, w01, w10, w11, total, v, buf)
            summarise_values(buf, r, c, amax, pmax, psecond)
            if write:
                for q in range(buf.shape[0]):
                    out[r, c, q] = buf[q]


@numba.njit(cache=True, parallel=True)
def _fill(values, floor, stride, table, out, mask):
    """Store the posteriors `_upsample(..., write=False)` left out, at the pixels of `mask`."""
    h, w = values.shape
    last_r, last_c = _last_on_grid(h, stride), _last_on_grid(w, stride)
    for r in numba.prange(h):
        buf = np.empty(out.shape[2], np.float32)
        r0, r1, wr0, wr1 = _grid_rows(r, stride, last_r)
        for c in range(w):
            if not mask[r, c] or (r == r0 and c % stride == 0):
                continue
            v = np.int32(values[r, c])
            if v == 0 or floor[r, c]:
                _write_fixed(out, r, c, v != 0)
                continue
            _between(values, table, out, r0, r1, wr0, wr1, c, stride, last_c, v, buf)
            for q in range(buf.shape[0]):
                out[r, c, q] = buf[q]


@numba.njit(cache=True)
def _grid_plan(values, floor, stride):
    """(rows, cols) uint8 plan of the stride grid: WALK where a pixel has a value and is not
    floor, FLOOR, or NO_VALUE."""
    n_rows = (values.shape[0] + stride - 1) // stride
    n_cols = (values.shape[1] + stride - 1) // stride
    plan = np.empty((n_rows, n_cols), np.uint8)
    for i in range(n_rows):
        for j in range(n_cols):
            v = values[i * stride, j * stride]
            plan[i, j] = NO_VALUE if v == 0 else (FLOOR if floor[i * stride, j * stride] else WALK)
    return plan


@numba.njit(cache=True, inline="always")
def _settled(values, amax, pmax, r0, r1, c0, c1, v, confidence, reach):
    """Whether the coarse grid pixels (r0 | r1, c0 | c1) around a pixel of probe value v all
    have a value within `reach` of v and the same argmax with posterior >= `confidence`."""
    label = amax[r0, c0]
    for gr in (r0, r1):
        for gc in (c0, c1):
            g = np.int32(values[gr, gc])
            if g == 0 or abs(g - v) >= reach:
                return False
            if amax[gr, gc] != label or pmax[gr, gc] < confidence:
                return False
    return True


@numba.njit(cache=True, parallel=True)
def _settle(values, floor, stride, table, confidence, reach, out, amax, pmax, psecond):
    """The plan of the stride grid once the grid twice as coarse is walked and summarised:
    its pixels are DONE; a pixel between them whose coarse neighbours settle it (`_settled`)
    takes their upsampled posterior (`_between` on the coarse grid) and summary, and is
    DONE; the others are planned as by `_grid_plan`."""
    coarse = 2 * stride
    h, w = values.shape
    last_r, last_c = _last_on_grid(h, coarse), _last_on_grid(w, coarse)
    n_rows = (h + stride - 1) // stride
    n_cols = (w + stride - 1) // stride
    plan = np.empty((n_rows, n_cols), np.uint8)
    for i in numba.prange(n_rows):
        buf = np.empty(out.shape[2], np.float32)
        r = i * stride
        r0, r1, wr0, wr1 = _grid_rows(r, coarse, last_r)
        for j in range(n_cols):
            c = j * stride
            v = np.int32(values[r, c])
            if r == r0 and c % coarse == 0:
                plan[i, j] = DONE
            elif v == 0:
                plan[i, j] = NO_VALUE
            elif floor[r, c]:
                plan[i, j] = FLOOR
            else:
                c0 = c - c % coarse
                c1 = min(c0 + coarse, last_c)
                if _settled(values, amax, pmax, r0, r1, c0, c1, v, confidence, reach):
                    _between(values, table, out, r0, r1, wr0, wr1, c, coarse, last_c, v, buf)
                    for q in range(buf.shape[0]):
                        out[r, c, q] = buf[q]
                    summarise_values(buf, r, c, amax, pmax, psecond)
                    plan[i, j] = DONE
                else:
                    plan[i, j] = WALK
    return plan


@numba.njit(cache=True, parallel=True)
def _apply(
    values, probes, scale, floor, offsets, weights, threshold, left, roots, background, nearest, out
):
    for r in numba.prange(values.shape[0]):
        for c in range(values.shape[1]):
            walk = values[r, c] > 0 and not floor[r, c]
            for t in range(roots.shape[0]):
                node = roots[t]
                if walk:
                    inv_d = scale[r, c]
                    while left[node] >= 0:
                        resp = response_at(
                            probes, r, c, inv_d, offsets[node], weights[node], background, nearest
                        )
                        node = left[node] + (0 if resp < threshold[node] else 1)
                out[t, r, c] = node if walk else -1


def predict_proba(
    forest: Forest,
    frame: np.ndarray | ModelInput,
    out: np.ndarray | None = None,
    stride: int = 1,
    summary: Summary | None = None,
    lazy: bool = False,
    adaptive: int = 0,
    walked: np.ndarray | None = None,
    early_exit: float | None = None,
    max_pad: int = MAX_PAD,
) -> np.ndarray:
    """(H, W, NUM_CLASSES) float32 class posteriors averaged over the trees.

    `frame` is a model input (`inputs.model_input`) or a depth frame, read as its legacy
    input (what a depth model expects). Rows of pixels without depth are all
    zero, floor-gated pixels are background. `out` may be a preallocated C-contiguous
    (H, W, NUM_CLASSES) float32 array to fill (a worker reuses one per frame).
    `stride` > 1 walks the trees only at every stride-th pixel of every stride-th row and
    fills the pixels between by edge-aware upsampling (`_upsample`): stride**2 times fewer
    walks; the posteriors at the grid pixels are exact.
    `adaptive` > 0 (with stride > 1) walks the grid stride * 2**adaptive first, then each
    finer grid down to `stride` only at the pixels that the coarser one around them does not
    settle (`_settle`: the same argmax with posterior >= SETTLE_CONFIDENCE, probe values
    within SETTLE_REACH_MM); a settled pixel takes their upsampled posterior.
    `early_exit` (None: every pixel walks every tree) lets a walked pixel stop once the
    average of its first EARLY_TREES or more trees gives one class at least this posterior;
    its posterior is the average of the trees it walked (`_keep_unsure`).
    `walked`, an (H, W) uint8 array when given, gets the number of trees walked at each
    pixel walked (other pixels keep their value).
    `summary` (`crf.argmax.Summary` of (H, W) buffers), when given, is filled with every
    pixel's argmax and top two posteriors as the posteriors are written: what the CRF reads,
    without another pass over them (`crf.segment_crf(..., summary=)`).
    `max_pad` bounds the probe image's border (px, `MAX_PAD`): a frame whose probes reach
    farther (`probe_pad`) is walked with each probe clamped to the image instead, with the
    same results (0: always).
    `lazy` (with stride > 1 and a summary) stores the posteriors of grid pixels only, and
    `fill_posteriors` stores the rest where a reader needs them (the realtime CRF reads its
    band only), sparing the write of the whole (H, W, C) array. Every pixel's argmax and top
    posterior are still exact; the second posterior of an in-between pixel whose grid
    corners agree is an upper bound of it (`_summarise_agreed`), which can only keep the
    realtime CRF from settling a pixel it could have left out of its band.
    """
    inp = check_input(as_input(frame), "forest inference")
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    if adaptive < 0:
        raise ValueError(f"adaptive must be >= 0 levels, got {adaptive}")
    if walked is not None and (
        walked.shape != inp.shape or walked.dtype != np.uint8 or not walked.flags.c_contiguous
    ):
        raise ValueError(f"walked must be a C-contiguous uint8 array of shape {inp.shape}")
    if early_exit is not None and not 0.0 < early_exit <= 1.0:
        raise ValueError(f"early_exit must be in (0, 1] (or None), got {early_exit}")
    if max_pad < 0:
        raise ValueError(f"max_pad must be >= 0 px, got {max_pad}")
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
    background = np.int32(forest.background_mm)
    pad = probe_pad(table.reach, inp.scale)
    clamp = pad > max_pad
    pad = np.int32(1 if clamp else pad)
    walk = _kernel(table.k, clamp)
    padded = _padded(inp.probe_values, background, pad, forest.nearest_off_image)
    tables = (table.fields, table.words, forest.posteriors, table.roots)
    early = (
        (np.int32(forest.n_trees), np.float32(1.0))
        if early_exit is None
        else (np.int32(EARLY_TREES), np.float32(early_exit))
    )
    counts = np.empty((0, 0), np.uint8) if walked is None else walked
    s = stride << (adaptive if stride > 1 else 0)
    plan = _grid_plan(inp.values, inp.floor, s)
    while True:
        walk(padded, pad, background, inp.scale, plan, *tables, s, *early, out, *summary, counts)
        if s == stride:
            break
        s //= 2
        plan = _settle(
            inp.values,
            inp.floor,
            s,
            height_weights(),
            np.float32(SETTLE_CONFIDENCE),
            np.int32(SETTLE_REACH_MM),
            out,
            *summary,
        )
    if stride > 1:
        _upsample(inp.values, inp.floor, stride, height_weights(), out, *summary, not lazy)
    return out


def fill_posteriors(
    frame: ModelInput, out: np.ndarray, stride: int, mask: np.ndarray | None = None
) -> np.ndarray:
    """Store the posteriors `predict_proba(frame, out, stride, lazy=True)` left out, at the
    pixels of (H, W) bool `mask` (all pixels when None); the values are those an eager call
    writes. Returns `out`."""
    inp = check_input(frame, "forest inference")
    if stride > 1:
        mask = np.ones(inp.shape, np.bool_) if mask is None else np.asarray(mask, np.bool_)
        if mask.shape != inp.shape:
            raise ValueError(f"mask is {mask.shape}, the frame {inp.shape}")
        _fill(inp.values, inp.floor, stride, height_weights(), out, mask)
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
        inp.probe_values,
        inp.scale,
        inp.floor,
        forest.offsets,
        forest.weights,
        forest.threshold,
        forest.left,
        forest.roots,
        np.int32(forest.background_mm),
        forest.nearest_off_image,
        out,
    )
    return out


def predict_labels(
    forest: Forest, frame: np.ndarray | ModelInput, stride: int = 1, adaptive: int = 0
) -> np.ndarray:
    """(H, W) uint8 most probable label per pixel; NO_DEPTH where depth == 0 (through the
    one argmax, `crf.segment_argmax`, that the CRF's mode `none` is). `stride` and
    `adaptive` as for `predict_proba`."""
    inp = as_input(frame)
    proba = predict_proba(forest, inp, stride=stride, adaptive=adaptive)
    return segment_argmax(proba, inp.values > 0)
