"""Islands: blobs of a class too small to be that thing take their surroundings' label.

Seen from above, a whole adult head covers 200-300 cm2 (breadth ~15.5 cm, length ~19.5 cm).
The forest and the CRF leave small blobs of `head` on shoulders, upper arms and hands, where
a shoulder or a raised arm reaches nearly a head's height. Each such blob counts as a
detected head downstream (a people counter, a safety zone keyed on heads), and on rendered
time-of-flight frames they were most of the head blobs found (`docs/results.md`).

Furniture is large from above too: a chair's seat is ~40 x 40 cm, storage and tables more.
The forest leaves small blobs of furniture on legs, arms and the edges of other furniture;
on people they count as "furniture on a person". Plants are left alone: their leaves break
into small blobs of their own.

`relabel_small_blobs` measures every 4-connected blob of a class that has a minimum area in
square metres on the surface it lies on, each pixel covering (z / fx) x (z / fy), and
relabels a blob smaller than its class's minimum to the label most common across its
border: for each pair of 4-neighbours with one pixel in the blob and the other outside it
(neither of the blob's class nor no-depth), the outside pixel's label counts once; ties go
to the lower id. A blob with no such neighbour keeps its label. Every blob is judged on the
labels as they came in (a blob relabelled does not change another's size or votes), so the
result does not depend on the order blobs are met. The work is proportional to the pixels
of the classes with a minimum, after one pass over the labels.
"""

from __future__ import annotations

import numba
import numpy as np

from topseg.core import labels as L

#: the classes `min_furniture_cm2` applies to (`relabel_small_blobs`)
FURNITURE_ISLANDS = (L.CHAIR, L.STORAGE, L.TABLE)


@numba.njit(cache=True)
def _relabel_small_blobs(labels, depth, min_sum_z2, no_depth, out, relabelled):
    """Write to `out` (a copy of `labels`) the blobs of each class c whose sum of depth^2
    (mm^2) is below `min_sum_z2[c]` (the area threshold times fx * fy; 0 = off) relabelled
    to their border's most common label in `labels`; count them per class in `relabelled`.

    A scanline fill per blob: a popped seed grows into the run of unvisited pixels of its
    class along its row; the rows above and below the run give the border's votes and the
    seeds of the next runs (one per stretch of the class). Memory is read along rows, and a
    large table costs a few operations per pixel."""
    h, w = labels.shape
    num_classes = min_sum_z2.shape[0]
    seen = np.zeros((h, w), np.uint8)
    stack_v = np.empty(2 * h * w + 1, np.int32)  # a pixel is pushed at most from above and
    stack_u = np.empty(2 * h * w + 1, np.int32)  # from below
    run_v = np.empty(h * w, np.int32)
    run_l = np.empty(h * w, np.int32)
    run_r = np.empty(h * w, np.int32)
    votes = np.zeros(num_classes, np.int64)
    for v0 in range(h):
        for u0 in range(w):
            c = labels[v0, u0]
            if c >= num_classes or min_sum_z2[c] <= 0.0 or seen[v0, u0]:
                continue
            stack_v[0], stack_u[0] = v0, u0
            top, runs = 1, 0
            sum_z2 = 0.0
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
            if sum_z2 >= min_sum_z2[c]:
                continue
            best = 0
            for x in range(1, num_classes):
                if votes[x] > votes[best]:
                    best = x
            if votes[best] == 0:
                continue
            for j in range(runs):
                for x in range(run_l[j], run_r[j] + 1):
                    out[run_v[j], x] = best
            relabelled[c] += 1


def relabel_small_blobs(
    labels: np.ndarray, depth: np.ndarray, fx: float, fy: float, min_area_cm2
) -> np.ndarray:
    """Relabel, in place, the blobs of each class c in (H, W) uint8 `labels` smaller than
    `min_area_cm2[c]` on the surface (`depth` in mm, focal lengths `fx`, `fy` in px; a
    sequence of NUM_CLASSES areas, 0 = keep every blob of that class) to their border's most
    common label. Returns how many blobs of each class were relabelled (int64, NUM_CLASSES)."""
    if labels.shape != np.shape(depth):
        raise ValueError(f"labels {labels.shape} and depth {np.shape(depth)} differ in shape")
    areas = np.asarray(min_area_cm2, np.float64)
    if areas.shape != (L.NUM_CLASSES,):
        raise ValueError(f"min_area_cm2 needs {L.NUM_CLASSES} areas, got shape {areas.shape}")
    relabelled = np.zeros(L.NUM_CLASSES, np.int64)
    if not (areas > 0).any():
        return relabelled
    min_sum_z2 = np.where(areas > 0, areas * 100.0 * float(fx) * float(fy), 0.0)  # cm2 -> mm2
    before = labels.copy()
    _relabel_small_blobs(before, depth, min_sum_z2, L.NO_DEPTH, labels, relabelled)
    return relabelled


def island_areas(min_head_cm2: float, min_furniture_cm2: float) -> np.ndarray:
    """The per-class minimum areas (cm2, NUM_CLASSES) of `relabel_small_blobs` for a head
    minimum and a furniture minimum (`FURNITURE_ISLANDS`); 0 elsewhere."""
    areas = np.zeros(L.NUM_CLASSES, np.float64)
    areas[L.HEAD] = min_head_cm2
    areas[list(FURNITURE_ISLANDS)] = min_furniture_cm2
    return areas
