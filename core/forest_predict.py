"""Forest inference: walk every tree at every pixel with depth, average the leaf posteriors.

One numba kernel, parallel over rows. Pixels without depth (0) are skipped: their
posterior row is all zeros (not a distribution), and `labels_from_proba` gives them
NO_DEPTH. A node sends a pixel left when its response < threshold (see `features`).
"""

from __future__ import annotations

import numba
import numpy as np

from topseg.core import labels
from topseg.core.features import inverse_depth, response_at
from topseg.core.tree import Forest


@numba.njit(cache=True, parallel=True)
def _predict_proba(
    depth, offsets, weights, threshold, left, leaf, posteriors, roots, background, out
):
    n_trees = roots.shape[0]
    n_classes = posteriors.shape[1]
    scale = np.float32(1.0) / np.float32(n_trees)
    for r in numba.prange(depth.shape[0]):
        for c in range(depth.shape[1]):
            d = depth[r, c]
            if d == 0:
                for k in range(n_classes):
                    out[r, c, k] = 0.0
                continue
            inv_d = inverse_depth(d)
            for k in range(n_classes):
                out[r, c, k] = 0.0
            for t in range(n_trees):
                node = roots[t]
                while left[node] >= 0:
                    resp = response_at(depth, r, c, inv_d, offsets[node], weights[node], background)
                    node = left[node] + (0 if resp < threshold[node] else 1)
                row = leaf[node]
                for k in range(n_classes):
                    out[r, c, k] += posteriors[row, k]
            for k in range(n_classes):
                out[r, c, k] *= scale


def _check_depth(depth: np.ndarray) -> np.ndarray:
    depth = np.asarray(depth)
    if depth.ndim != 2 or depth.dtype != np.uint16:
        raise ValueError(
            f"depth must be a (H, W) uint16 frame in mm, got {depth.dtype} {depth.shape}"
        )
    return np.ascontiguousarray(depth)


def predict_proba(forest: Forest, depth: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """(H, W, NUM_CLASSES) float32 class posteriors averaged over the trees.

    Rows of pixels without depth are all zero. `out` may be a preallocated C-contiguous
    (H, W, NUM_CLASSES) float32 array to fill (a worker reuses one per frame).
    """
    depth = _check_depth(depth)
    shape = (*depth.shape, forest.posteriors.shape[1])
    if out is None:
        out = np.empty(shape, np.float32)
    elif out.shape != shape or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ValueError(f"out must be a C-contiguous float32 array of shape {shape}")
    _predict_proba(
        depth,
        forest.offsets,
        forest.weights,
        forest.threshold,
        forest.left,
        forest.leaf,
        forest.posteriors,
        forest.roots,
        np.int32(forest.background_mm),
        out,
    )
    return out


def labels_from_proba(proba: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """(H, W) uint8 argmax labels; NO_DEPTH (255) where depth == 0."""
    out = np.argmax(proba, axis=-1).astype(np.uint8)
    out[np.asarray(depth) == 0] = labels.NO_DEPTH
    return out


def predict_labels(forest: Forest, depth: np.ndarray) -> np.ndarray:
    """(H, W) uint8 most probable label per pixel; NO_DEPTH where depth == 0."""
    return labels_from_proba(predict_proba(forest, depth), depth)
