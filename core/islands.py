"""Head islands: blobs labelled head that are too small to be a head take their surroundings'
label.

Seen from above, a whole adult head covers 200-300 cm2 (breadth ~15.5 cm, length ~19.5 cm).
The forest and the CRF leave small blobs of `head` on shoulders, upper arms and hands, where
a shoulder or a raised arm reaches nearly a head's height. Each such blob counts as a
detected head downstream (a people counter, a safety zone keyed on heads), and on rendered
time-of-flight frames they were most of the head blobs found (`docs/results.md`).

`relabel_small_heads` measures every 4-connected blob of `head` in square metres on the
surface it lies on, each pixel covering (z / fx) x (z / fy), and relabels a blob smaller than
`min_area_cm2` to the label most common across its border: for each pair of 4-neighbours
with one pixel in the blob and the other outside it (neither head nor no-depth), the outside
pixel's label counts once; ties go to the lower id. A blob with no such neighbour keeps
`head`. The work is proportional to the head pixels, after one pass over the labels.
"""

from __future__ import annotations

import numba
import numpy as np

from topseg.core import labels as L


@numba.njit(cache=True)
def _relabel_small_heads(labels, depth, min_sum_z2, head, no_depth, num_classes):
    """Relabel, in place, the 4-connected blobs of `head` whose sum of depth^2 (mm^2) is below
    `min_sum_z2` (the area threshold times fx * fy); the number of blobs relabelled."""
    h, w = labels.shape
    seen = np.zeros((h, w), np.uint8)
    blob = np.empty(h * w, np.int64)
    votes = np.zeros(num_classes, np.int64)
    relabelled = 0
    for v0 in range(h):
        for u0 in range(w):
            if labels[v0, u0] != head or seen[v0, u0]:
                continue
            seen[v0, u0] = 1
            blob[0] = v0 * w + u0
            n, i = 1, 0
            sum_z2 = 0.0
            votes[:] = 0
            while i < n:
                v, u = divmod(blob[i], w)
                i += 1
                z = float(depth[v, u])
                sum_z2 += z * z
                for k in range(4):
                    vv, uu = v, u
                    if k == 0:
                        vv -= 1
                    elif k == 1:
                        vv += 1
                    elif k == 2:
                        uu -= 1
                    else:
                        uu += 1
                    if vv < 0 or vv >= h or uu < 0 or uu >= w:
                        continue
                    other = labels[vv, uu]
                    if other == head:
                        if not seen[vv, uu]:
                            seen[vv, uu] = 1
                            blob[n] = vv * w + uu
                            n += 1
                    elif other != no_depth and other < num_classes:
                        votes[other] += 1
            if sum_z2 >= min_sum_z2:
                continue
            best = 0
            for c in range(1, num_classes):
                if votes[c] > votes[best]:
                    best = c
            if votes[best] == 0:
                continue
            for j in range(n):
                v, u = divmod(blob[j], w)
                labels[v, u] = best
            relabelled += 1
    return relabelled


def relabel_small_heads(
    labels: np.ndarray, depth: np.ndarray, fx: float, fy: float, min_area_cm2: float
) -> int:
    """Relabel, in place, the blobs of `head` in (H, W) uint8 `labels` smaller than
    `min_area_cm2` on the surface (`depth` in mm, focal lengths `fx`, `fy` in px) to their
    border's most common label; returns how many blobs were relabelled. 0 leaves all."""
    if labels.shape != np.shape(depth):
        raise ValueError(f"labels {labels.shape} and depth {np.shape(depth)} differ in shape")
    if not min_area_cm2 > 0:
        return 0
    min_sum_z2 = float(min_area_cm2) * 100.0 * float(fx) * float(fy)  # cm2 -> mm2, x fx fy
    return int(_relabel_small_heads(labels, depth, min_sum_z2, L.HEAD, L.NO_DEPTH, L.NUM_CLASSES))
