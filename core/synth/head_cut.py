"""The image's edge across a person's head, as when someone walks in or out of view.

A person walking under a ceiling camera crosses the edge of its view many times. On a
sequence of one person walking (the issue's judging kind, `scripts/ceiling_proxy.py`), a
quarter to a half of the heads in view touch the image border, and every head the bundled
model missed there was one of them (`docs/results.md`). Training frames hold fewer: the
edge band of the density function (`density.HUMAN_EDGE_M`) lies across the floor's edge,
where the border cuts legs, and a head reaches the border only where the view at head
height ends, about half way out on a 3.3 m ceiling.

`cut_across_head` moves the image's edge onto one head instead: it picks a head in the
frame, an axis (rows or columns) and a line across the head's bounding box, and takes the
depth away between that line and the image border nearer the head (labels NO_DEPTH there),
so that most of the frame stays. The forest cannot tell the
two apart: a probe outside the image and a probe on a pixel without depth both read the
background constant (`forest.features`), so the frame is one from a smaller camera whose
border crosses the head. The sensor's own edge effects (a stereo camera's invalid band)
stay at the original border.
"""

from __future__ import annotations

import numpy as np

from topseg.core import labels as L

#: the share of the head's extent across the cut that stays in view: drawn uniformly from it
KEPT_SHARE = (0.2, 0.8)
#: smallest head (pixels) a cut is put across
MIN_HEAD_PX = 30


def cut_across_head(
    depth: np.ndarray, labels: np.ndarray, rng: np.random.Generator
) -> tuple[int, int, int] | None:
    """Remove, in place, the depth beyond a line across one head of `labels` (truth labels,
    NO_DEPTH written there too). Returns (axis, kept side, line) or None, changing nothing,
    when no head has MIN_HEAD_PX pixels: along `axis` (0 rows, 1 columns) the indices below
    `line` are gone when the kept side is +1, those from `line` on when it is -1.

    The head is drawn among the 4-connected head blobs of MIN_HEAD_PX pixels or more, the
    axis from both, and the kept share of the head's bounding box along it from KEPT_SHARE;
    the border nearer the head's centre moves."""
    from scipy import ndimage

    if depth.shape != labels.shape or depth.ndim != 2:
        raise ValueError(
            f"depth {depth.shape} and labels {labels.shape} must be the same 2-D shape"
        )
    blobs, n = ndimage.label(labels == L.HEAD)
    if n == 0:
        return None
    sizes = np.bincount(blobs.ravel(), minlength=n + 1)[1:]
    heads = np.flatnonzero(sizes >= MIN_HEAD_PX) + 1
    if heads.size == 0:
        return None
    head = int(heads[rng.integers(heads.size)])
    axis = int(rng.integers(2))
    coords = np.nonzero(blobs == head)[axis]
    lo, hi = int(coords.min()), int(coords.max()) + 1
    keep = 1 if lo + hi < depth.shape[axis] else -1  # the head nearer index 0: cut from there
    kept = round(float(rng.uniform(*KEPT_SHARE)) * (hi - lo))  # rows or columns of it kept
    line = hi - kept if keep > 0 else lo + kept
    gone = [slice(None), slice(None)]
    gone[axis] = slice(0, line) if keep > 0 else slice(line, None)
    depth[tuple(gone)] = 0
    labels[tuple(gone)] = L.NO_DEPTH
    return axis, keep, line
