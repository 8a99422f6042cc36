"""Islands: blobs of a class that cannot be that thing take their surroundings' label.

Seen from above, a whole adult head covers 200-300 cm2 (breadth ~15.5 cm, length ~19.5 cm).
The forest and the CRF leave small blobs of `head` on shoulders, upper arms and hands, where
a shoulder or a raised arm reaches nearly a head's height. Each such blob counts as a
detected head downstream (a people counter, a safety zone keyed on heads), and on rendered
time-of-flight frames they were most of the head blobs found (`docs/results.md`).

Furniture is large from above too: a chair's seat is ~40 x 40 cm, storage and tables more.
The forest leaves small blobs of furniture on legs, arms and the edges of other furniture;
on people they count as "furniture on a person". A potted plant is smaller (its pot, 14 cm
across or more, covers ~150 cm2), and its leaves break into blobs of their own, so plants
have a smaller minimum of their own: it takes the specks of plant that a noisy camera leaves
on table tops.

`relabel_islands` measures every 4-connected blob of a class that has a minimum area in
square metres on the surface it lies on, each pixel covering (z / fx) x (z / fy), and
relabels a blob smaller than its class's minimum to the label most common across its
border: for each pair of 4-neighbours with one pixel in the blob and the other outside it
(neither of the blob's class nor no-depth), the outside pixel's label counts once; ties go
to the lower id. A blob with no such neighbour keeps its label.

Some head blobs on an arm or a hand are as large as a small head (50-150 cm2), but they lie
beside the person's own head. Such a satellite, a head blob under a maximum area whose
centre lies within a radius (`SATELLITE_RADIUS_CM`, 40 cm) of a larger head blob's
centre, takes its border's label the same way: two people's heads are not that close.

A blob within a few pixels of the image's edge (`ISLAND_EDGE_PX`, 2) may be cut
by it: a person walking in or out of view shows part of the head. Such a head blob is held
to a share of the minimum (`EDGE_HEAD_SHARE`, 0.4: 20 cm2 of the default 50).
On the walker stand-ins every head missed before lay at the edge, and there the rule had
relabelled most of them (`docs/results.md`).

Every blob is judged on the labels as they came in (a blob relabelled does not change
another's size, centre or votes), so the result does not depend on the order blobs are met.
The work is proportional to the pixels of the classes measured, after one pass over the
labels.
"""

from __future__ import annotations

import numba
import numpy as np

from topseg.core import labels as L
from topseg.core.camera import Intrinsics

#: Two people's heads are a shoulder's breadth apart (~40 cm between centres): a smaller head
#: blob closer than this to a larger one is not a second head (`segmenter_config.SATELLITE_HEAD_CM2`).
SATELLITE_RADIUS_CM = 40.0
#: head blobs within this many pixels of the image's edge are held to a smaller minimum
#: (`islands`): the border cuts the head of a person walking in or out of view, and the part
#: in view can be smaller than `SegmenterConfig.min_head_cm2` (2 px: time-of-flight and stereo cameras often
#: leave the outermost pixel without depth)
ISLAND_EDGE_PX = 2
#: the share of `min_head_cm2` a head blob at the image's edge must reach: of 0, 0.2 and 0.4
#: on the walker stand-ins, 0.4 kept the lower of head precision and recall highest on most
#: sets, and the most head precision on the mounts table (docs/results.md)
EDGE_HEAD_SHARE = 0.4

#: the classes `min_furniture_cm2` applies to (`relabel_islands`)
FURNITURE_ISLANDS = (L.CHAIR, L.STORAGE, L.TABLE)
#: the classes the `small_furniture` counter counts: those and plants (`min_plant_cm2`)
FURNITURE_COUNTED = (L.CHAIR, L.PLANT, L.STORAGE, L.TABLE)

#: the largest head blobs that may claim satellites: more people than this under one
#: camera is not a robot cell, and it bounds the work on a frame of many small blobs
MAX_HEAD_ANCHORS = 64


@numba.njit(cache=True)
def _measure_blobs(labels, depth, measured, no_depth, fx, fy, cx, cy, edge_px):
    """Every 4-connected blob of a class c with `measured[c]`, in `labels` as given: its
    class, sum of depth^2 (mm^2; over fx * fy, its area), centre (mean x, y in mm on the
    camera's axes), most common border label (-1: none), whether a pixel of it lies within
    `edge_px` pixels of the image's edge, and its pixels as runs along rows.

    Returns (n, blob_class, blob_z2, blob_x, blob_y, blob_border, blob_edge, blob_runs,
    run_v, run_l, run_r): blob b's runs are run_*[blob_runs[b] : blob_runs[b + 1]], run j
    covering row run_v[j], columns run_l[j]..run_r[j].

    A scanline fill per blob: a popped seed grows into the run of unvisited pixels of its
    class along its row; the rows above and below the run give the border's votes and the
    seeds of the next runs (one per stretch of the class). Memory is read along rows, and a
    large table costs a few operations per pixel. Border votes: for each pair of
    4-neighbours with one pixel in the blob and the other outside it (neither of the blob's
    class nor no-depth), the outside pixel's label counts once; ties go to the lower id."""
    h, w = labels.shape
    num_classes = measured.shape[0]
    seen = np.zeros((h, w), np.uint8)
    stack_v = np.empty(2 * h * w + 1, np.int32)  # a pixel is pushed at most from above and
    stack_u = np.empty(2 * h * w + 1, np.int32)  # from below
    run_v = np.empty(h * w, np.int32)
    run_l = np.empty(h * w, np.int32)
    run_r = np.empty(h * w, np.int32)
    cap = h * w + 1
    blob_class = np.empty(cap, np.uint8)
    blob_z2 = np.empty(cap, np.float64)
    blob_x = np.empty(cap, np.float64)
    blob_y = np.empty(cap, np.float64)
    blob_border = np.empty(cap, np.int32)
    blob_edge = np.empty(cap, np.bool_)
    blob_runs = np.empty(cap + 1, np.int32)
    votes = np.zeros(num_classes, np.int64)
    n, runs = 0, 0
    for v0 in range(h):
        for u0 in range(w):
            c = labels[v0, u0]
            if c >= num_classes or not measured[c] or seen[v0, u0]:
                continue
            stack_v[0], stack_u[0] = v0, u0
            top = 1
            blob_runs[n] = runs
            sum_z2, sum_x, sum_y, count = 0.0, 0.0, 0.0, 0
            at_edge = False
            votes[:] = 0
            while top > 0:
                top -= 1
                v, u = stack_v[top], stack_u[top]
                if seen[v, u]:
                    continue
                left, right = u, u
                while left > 0 and labels[v, left - 1] == c and not seen[v, left - 1]:
                    left -= 1
                while right < w - 1 and labels[v, right + 1] == c and not seen[v, right + 1]:
                    right += 1
                for x in range(left, right + 1):
                    seen[v, x] = 1
                    z = float(depth[v, x])
                    sum_z2 += z * z
                    sum_x += (x - cx) * z
                    sum_y += (v - cy) * z
                count += right - left + 1
                if v < edge_px or v >= h - edge_px or left < edge_px or right >= w - edge_px:
                    at_edge = True
                run_v[runs], run_l[runs], run_r[runs] = v, left, right
                runs += 1
                for x in (left - 1, right + 1):  # the run's ends: blob or border
                    if 0 <= x < w:
                        other = labels[v, x]
                        if other != c and other != no_depth and other < num_classes:
                            votes[other] += 1
                for vv in (v - 1, v + 1):
                    if vv < 0 or vv >= h:
                        continue
                    open_stretch = False
                    for x in range(left, right + 1):
                        other = labels[vv, x]
                        if other == c:
                            if not seen[vv, x]:
                                if not open_stretch:
                                    stack_v[top], stack_u[top] = vv, x
                                    top += 1
                                    open_stretch = True
                            else:
                                open_stretch = False
                        else:
                            open_stretch = False
                            if other != no_depth and other < num_classes:
                                votes[other] += 1
            best = 0
            for x in range(1, num_classes):
                if votes[x] > votes[best]:
                    best = x
            blob_class[n] = c
            blob_z2[n] = sum_z2
            blob_x[n] = sum_x / (fx * count)
            blob_y[n] = sum_y / (fy * count)
            blob_border[n] = best if votes[best] > 0 else -1
            blob_edge[n] = at_edge
            n += 1
    blob_runs[n] = runs
    return (
        n, blob_class, blob_z2, blob_x, blob_y, blob_border, blob_edge, blob_runs, run_v,
        run_l, run_r,
    )  # fmt: skip


@numba.njit(cache=True)
def _paint(out, label, first, last, run_v, run_l, run_r):
    """Runs first..last-1 of `_measure_blobs` set to `label` in `out`."""
    for j in range(first, last):
        for x in range(run_l[j], run_r[j] + 1):
            out[run_v[j], x] = label


@numba.njit(cache=True)
def _relabel_islands(
    labels,
    depth,
    min_sum_z2,
    edge_share,
    edge_px,
    satellite_sum_z2,
    radius_mm,
    max_anchors,
    head,
    no_depth,
    focal,
    out,
    relabelled,
):
    """Write to `out` (a copy of `labels`), every blob judged on `labels`:
    - a blob of class c whose sum of depth^2 (mm^2) is under `min_sum_z2[c]` (the area
      threshold times fx * fy; 0 = off) relabelled to its border's most common label, and
      counted per class in `relabelled`; a blob within `edge_px` of the image's edge is held
      to `edge_share[c]` of that threshold;
    - a head blob (class `head`) kept by that rule, under `satellite_sum_z2`, whose centre
      lies within `radius_mm` of a larger head blob's centre (one of the `max_anchors`
      largest) relabelled the same way; returns how many.
    `focal` is (fx, fy, cx, cy). A blob with no border label keeps its own."""
    measured = min_sum_z2 > 0.0
    if satellite_sum_z2 > 0.0:
        measured[head] = True
    n, cls, z2, bx, by, border, at_edge, blob_runs, run_v, run_l, run_r = _measure_blobs(
        labels, depth, measured, no_depth, focal[0], focal[1], focal[2], focal[3], edge_px
    )
    heads = np.empty(n, np.int64)
    n_heads = 0
    for b in range(n):
        c = cls[b]
        if z2[b] < (min_sum_z2[c] * edge_share[c] if at_edge[b] else min_sum_z2[c]):
            if border[b] >= 0:
                _paint(out, border[b], blob_runs[b], blob_runs[b + 1], run_v, run_l, run_r)
                relabelled[c] += 1
        elif c == head:
            heads[n_heads] = b
            n_heads += 1
    if satellite_sum_z2 <= 0.0 or n_heads < 2:
        return 0
    heads = heads[:n_heads]
    heads = heads[np.argsort(-z2[heads])]  # largest first
    r2 = radius_mm * radius_mm
    satellites = 0
    for i in range(1, n_heads):
        b = heads[i]
        if z2[b] >= satellite_sum_z2 or border[b] < 0:
            continue
        for j in range(min(i, max_anchors)):
            a = heads[j]
            if z2[a] > z2[b] and (bx[a] - bx[b]) ** 2 + (by[a] - by[b]) ** 2 < r2:
                _paint(out, border[b], blob_runs[b], blob_runs[b + 1], run_v, run_l, run_r)
                satellites += 1
                break
    return satellites


def relabel_islands(
    labels: np.ndarray,
    depth: np.ndarray,
    k: Intrinsics,
    min_area_cm2,
    satellite_head_cm2: float = 0.0,
    radius_cm: float = 0.0,
    edge_px: int = 0,
    edge_share=None,
) -> tuple[np.ndarray, int]:
    """Relabel, in place, the islands of (H, W) uint8 `labels` to their border's most common
    label, every blob judged on the labels as given (`depth` in mm, `k` the frame's
    intrinsics; areas on the surface):
    - small blobs: of each class c, smaller than `min_area_cm2[c]` (a sequence of
      NUM_CLASSES areas, 0 = keep every blob of that class);
    - satellite heads: head blobs not small, smaller than `satellite_head_cm2`, whose centre
      lies within `radius_cm` of a larger head blob's centre (centres across the camera's
      axes; the `MAX_HEAD_ANCHORS` largest blobs claim satellites); 0 for either: none.
    A blob with a pixel within `edge_px` pixels of the image's edge is held to `edge_share[c]`
    (NUM_CLASSES shares, None: all 1) of its class's minimum: the border may cut it, and the
    part in view can be smaller than the whole.
    Returns (small blobs relabelled per class, int64 NUM_CLASSES; satellite heads)."""
    if labels.shape != np.shape(depth):
        raise ValueError(f"labels {labels.shape} and depth {np.shape(depth)} differ in shape")
    areas = np.asarray(min_area_cm2, np.float64)
    if areas.shape != (L.NUM_CLASSES,):
        raise ValueError(f"min_area_cm2 needs {L.NUM_CLASSES} areas, got shape {areas.shape}")
    for name, value in (("satellite_head_cm2", satellite_head_cm2), ("radius_cm", radius_cm)):
        if not (np.isfinite(value) and value >= 0):
            raise ValueError(f"{name} must be >= 0, got {value}")
    if edge_px < 0:
        raise ValueError(f"edge_px must be >= 0, got {edge_px}")
    shares = np.ones(L.NUM_CLASSES) if edge_share is None else np.asarray(edge_share, np.float64)
    if shares.shape != (L.NUM_CLASSES,) or not ((shares >= 0) & (shares <= 1)).all():
        raise ValueError(f"edge_share needs {L.NUM_CLASSES} shares in [0, 1], got {edge_share}")
    relabelled = np.zeros(L.NUM_CLASSES, np.int64)
    if not (areas > 0).any() and not satellite_head_cm2 > 0:
        return relabelled, 0
    to_sum_z2 = 100.0 * k.fx * k.fy  # cm2 -> the sum of depth^2 (mm^2) that covers it
    min_sum_z2 = np.where(areas > 0, areas * to_sum_z2, 0.0)
    focal = np.array([k.fx, k.fy, k.cx, k.cy], np.float64)
    before = labels.copy()
    satellites = _relabel_islands(
        before,
        depth,
        min_sum_z2,
        shares,
        int(edge_px),
        float(satellite_head_cm2) * to_sum_z2,
        10.0 * float(radius_cm),
        MAX_HEAD_ANCHORS,
        L.HEAD,
        L.NO_DEPTH,
        focal,
        labels,
        relabelled,
    )
    return relabelled, int(satellites)


def island_areas(min_head_cm2: float, min_furniture_cm2: float, min_plant_cm2: float) -> np.ndarray:
    """The per-class minimum areas (cm2, NUM_CLASSES) of `relabel_islands` for a head
    minimum, a furniture minimum (`FURNITURE_ISLANDS`) and a plant minimum; 0 elsewhere."""
    areas = np.zeros(L.NUM_CLASSES, np.float64)
    areas[L.HEAD] = min_head_cm2
    areas[list(FURNITURE_ISLANDS)] = min_furniture_cm2
    areas[L.PLANT] = min_plant_cm2
    return areas


def edge_shares(head_share: float) -> np.ndarray:
    """The per-class `edge_share` of `relabel_islands`: `head_share` for heads, 1 elsewhere
    (furniture at the edge is held to its whole minimum; a smaller one is not measured)."""
    shares = np.ones(L.NUM_CLASSES, np.float64)
    shares[L.HEAD] = head_share
    return shares
