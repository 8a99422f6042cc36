"""The builder: grows a tree level by level from the splitter's choices and makes its leaves.

All nodes of a level are split in parallel (`_grow_level`); a node's samples are a slice of
one index array that the splitter partitions in place, so the children of a level are
contiguous slices again. Stopping rules: a node becomes a leaf at `max_depth`, with fewer than
`min_samples_split` samples, when it is pure, or when its best split gains no more than
`min_gain` bits (or sends every sample one way). Leaves store the normalised class histogram
of all samples that reach them; node ids are assigned level by level, children in pairs.
"""

from __future__ import annotations

from collections.abc import Callable

import numba
import numpy as np

from topseg.core import labels as label_table
from topseg.core.forest.criterion import xlogx_table
from topseg.core.forest.splitter import _best_split, _node_state, _partition
from topseg.core.forest.train_config import TrainConfig
from topseg.core.forest.tree import Tree


@numba.njit(cache=True, parallel=True)
def _grow_level(
    fm,
    y,
    idx,
    starts,
    ends,
    node_ids,
    key,
    may_split,
    n_classes,
    n_candidates,
    n_thresholds,
    k,
    linear,
    cap,
    min_samples,
    min_gain,
    xlogx,
):
    """Split every node of one level (in parallel); `idx[start:end]` are a node's samples.

    Returns per node: mid (start of the right child's samples, -1 for a leaf), the chosen
    feats (m, k), weights (m, k), thresholds (m,), gains (m,) and class counts (m, C).
    """
    m = starts.shape[0]
    mid = np.full(m, -1, np.int64)
    feats = np.zeros((m, k), np.int64)
    weights = np.zeros((m, k), np.float32)
    thresholds = np.zeros(m, np.float32)
    gains = np.zeros(m, np.float64)
    counts = np.zeros((m, n_classes), np.int64)
    for i in numba.prange(m):
        ids = idx[starts[i] : ends[i]]
        for s in range(ids.shape[0]):
            counts[i, y[ids[s]]] += 1
        n_present = 0
        for c in range(n_classes):
            if counts[i, c] > 0:
                n_present += 1
        if not may_split or ids.shape[0] < min_samples or n_present < 2:
            continue
        state = _node_state(key, node_ids[i])
        gain, f, w, t = _best_split(
            fm, y, ids, state, n_classes, n_candidates, n_thresholds, k, linear, cap, xlogx
        )
        if gain > min_gain:
            n_left = _partition(fm, ids, f, w, t)
            if 0 < n_left < ids.shape[0]:
                mid[i] = starts[i] + n_left
                feats[i] = f
                weights[i] = w
                thresholds[i] = t
                gains[i] = gain
    return mid, feats, weights, thresholds, gains, counts


def grow_tree(
    fm: np.ndarray,
    y: np.ndarray,
    offsets: np.ndarray,
    config: TrainConfig,
    key: int,
    progress: Callable[[int, int], None] | None = None,
) -> Tree:
    """Grow one tree on a feature matrix (int16, feature-major) and its labels `y`.

    `offsets` are the pool's probe offsets (a node stores its features' offsets); `key`
    seeds every node's stream; `progress(level, nodes)` is called after each level.
    """
    n_classes = max(label_table.PAPER_NUM_CLASSES, int(y.max(initial=0)) + 1)
    k = config.features_per_node
    idx = np.arange(y.shape[0], dtype=np.int64)
    y = y.astype(np.int64)
    xlogx = xlogx_table(min(config.max_split_samples, y.shape[0]) + 1)
    starts, ends = np.array([0]), np.array([y.shape[0]])
    levels = []
    next_id = 0
    for level in range(config.max_depth + 1):
        node_ids = np.arange(next_id, next_id + starts.size)
        next_id += starts.size
        mid, feats, weights, thresholds, _gains, counts = _grow_level(
            fm,
            y,
            idx,
            starts,
            ends,
            node_ids,
            np.uint64(key),
            level < config.max_depth,
            n_classes,
            config.n_candidates,
            config.n_thresholds,
            k,
            config.split == "linear",
            config.max_split_samples,
            config.min_samples_split,
            config.min_gain,
            xlogx,
        )
        split = mid >= 0
        left = np.full(starts.size, -1, np.int64)
        left[split] = next_id + 2 * np.arange(split.sum())
        levels.append((left, feats, weights, thresholds, counts))
        if progress is not None:
            progress(level, int(starts.size))
        if not split.any():
            break
        starts, ends = (
            np.stack([starts[split], mid[split]], axis=1).ravel(),
            np.stack([mid[split], ends[split]], axis=1).ravel(),
        )
    left = np.concatenate([lv[0] for lv in levels]).astype(np.int32)
    feats = np.concatenate([lv[1] for lv in levels])
    weights = np.concatenate([lv[2] for lv in levels])
    threshold = np.concatenate([lv[3] for lv in levels])
    counts = np.concatenate([lv[4] for lv in levels])
    is_leaf = left < 0
    leaf = np.full(left.size, -1, np.int32)
    leaf[is_leaf] = np.arange(is_leaf.sum(), dtype=np.int32)
    hist = counts[is_leaf].astype(np.float64)
    posteriors = (hist / hist.sum(axis=1, keepdims=True)).astype(np.float32)
    node_offsets = offsets[feats].astype(np.float32)
    node_offsets[is_leaf] = 0.0
    weights[is_leaf] = 0.0
    return Tree(
        node_offsets,
        weights.astype(np.float32),
        threshold.astype(np.float32),
        left,
        leaf,
        posteriors,
        config.features.background_mm,
        config.features.nearest_off_image,
    )
