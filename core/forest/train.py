"""Training a decision tree (and a forest, tree by tree) on labelled depth frames.

One tree:

1. **Bagging.** The tree draws min(F, N) of the N frames with replacement
   (`frames_per_tree` = F); a frame drawn twice is sampled twice.
2. **Class-balanced pixel sampling.** From each drawn frame, `pixels_per_frame` pixels with
   depth and a class label, shared out evenly over the classes present (a class with too
   few pixels gives all it has and the rest goes to the others). Leaf posteriors are
   therefore class distributions under a uniform class prior, as in Shotton et al.
3. **Features once.** The tree draws its own pool of PC offset pairs and extracts the
   (PC, n_samples) int16 feature matrix once (feature-major, so a candidate streams rows) (2 bytes per value: the paper's F = 1600,
   2000 pixels per frame and PC = 300 take 1.9 GB per tree, so two trees train side by
   side in 8 GB).
4. **Randomized node optimisation**, level by level, all nodes of a level in parallel.
   A node with at least `min_samples_split` samples, below `max_depth` and not pure draws
   R candidate responses (axis-aligned: one pool feature; linear: `linear_k` features and
   a random unit vector) and, per candidate, K thresholds among the candidate's responses.
   Responses are computed on at most `max_split_samples` samples of the node (drawn with
   replacement when the node is larger); each sample's bin among the sorted thresholds
   goes into a per-class histogram whose cumulative sums give the information gain (bits)
   of all K thresholds at once. The best split is kept if its gain > `min_gain`, and all
   the node's samples are partitioned by it (left: response < threshold).
5. **Leaves** store the normalised class histogram of all samples that reach them.

All randomness of a node comes from a splitmix64 stream seeded by (tree key, node id), so
a tree depends only on its seed, never on thread scheduling. The draws of a node, in
order: the subsample positions (only when the node is larger than `max_split_samples`),
then per candidate its k feature ids, its weights (linear only: k uniforms in [-1, 1]
redrawn until their norm is in (0, 1], then normalised), and its thresholds' positions.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numba
import numpy as np

from topseg.core import labels as label_table
from topseg.core.errors import TopsegError
from topseg.core.forest.features import FeatureConfig, extract_features, sample_offsets
from topseg.core.forest.tree import Forest, Tree

log = logging.getLogger(__name__)

SPLITS = ("linear", "axis")


@dataclass(frozen=True)
class TrainConfig:
    """Forest training parameters; the defaults are the paper's (Sharma et al. 2016, V).

    pixels_per_frame: 2000 keeps the paper's full configuration (F = 1600 frames per tree)
        at 3.2 M samples and 1.9 GB of features per tree, while giving each of the ~5
        classes of a frame a few hundred samples.
    max_split_samples: samples used to choose a split at a node; larger nodes are
        subsampled for the choice (all of their samples are still partitioned). Only the
        top levels of a large tree are affected, and 20 000 samples estimate a gain well.
    min_gain: a split must gain more than this many bits.
    """

    n_trees: int = 5
    max_depth: int = 19
    frames_per_tree: int = 1600
    pixels_per_frame: int = 2000
    n_candidates: int = 100
    n_thresholds: int = 100
    split: str = "linear"
    linear_k: int = 2
    min_samples_split: int = 20
    min_gain: float = 0.0
    max_split_samples: int = 20000
    features: FeatureConfig = field(default_factory=FeatureConfig)

    def __post_init__(self) -> None:
        if self.split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {self.split!r}")
        for name in (
            "n_trees",
            "frames_per_tree",
            "pixels_per_frame",
            "n_candidates",
            "n_thresholds",
            "linear_k",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 0 <= self.max_depth <= 30:
            raise ValueError(f"max_depth must be in [0, 30], got {self.max_depth}")
        if self.min_samples_split < 2:
            raise ValueError(f"min_samples_split must be >= 2, got {self.min_samples_split}")
        if self.max_split_samples < 2:
            raise ValueError(f"max_split_samples must be >= 2, got {self.max_split_samples}")
        if self.min_gain < 0:
            raise ValueError(f"min_gain must be >= 0, got {self.min_gain}")

    @property
    def features_per_node(self) -> int:
        """k: pool features one split combines (1 for axis-aligned splits)."""
        return self.linear_k if self.split == "linear" else 1

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        known = {k: v for k, v in d.items() if k in cls.__dataclass_fields__}
        if "features" in known:
            known["features"] = FeatureConfig.from_dict(known["features"])
        return cls(**known)


# --- random numbers: a splitmix64 stream per node -------------------------------------

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)


@numba.njit(cache=True, inline="always")
def _next_u64(state):
    """Advance the 1-element uint64 `state`; return the next 64 random bits (splitmix64)."""
    state[0] += _GOLDEN
    z = state[0]
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@numba.njit(cache=True, inline="always")
def _uniform(state):
    """A float64 uniform in [0, 1) from the top 53 bits."""
    return np.float64(_next_u64(state) >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@numba.njit(cache=True, inline="always")
def _randint(state, n):
    """An integer uniform in [0, n)."""
    return np.int64(_uniform(state) * n)


@numba.njit(cache=True)
def _node_state(key, node_id):
    """The stream of node `node_id` of the tree with `key`."""
    state = np.empty(1, np.uint64)
    state[0] = np.uint64(key) + np.uint64(node_id) * _GOLDEN
    state[0] = _next_u64(state)
    return state


# --- node optimisation kernels ---------------------------------------------------------


@numba.njit(cache=True)
def _responses(fm, ids, feats, weights, out):
    """out[i] = sum_j weights[j] * fm[feats[j], ids[i]] in float32 (same order as inference).

    `fm` is feature-major (PC, n_samples): a node's ids are ascending, so each feature is
    read as one forward pass over its row.
    """
    out[:] = 0.0
    for j in range(feats.shape[0]):
        row = fm[feats[j]]
        wj = weights[j]
        for i in range(ids.shape[0]):
            out[i] += wj * np.float32(row[ids[i]])


@numba.njit(cache=True)
def _bin_histogram(resp, y, thresholds, hist):
    """Fill hist (K + 1, C): row b counts samples with exactly b sorted thresholds <= response.

    A sample goes left of threshold k (response < t_k) iff its bin is <= k.
    """
    k = thresholds.shape[0]
    hist[:] = 0
    for i in range(resp.shape[0]):
        v = resp[i]
        lo, hi = 0, k  # bisect right
        while lo < hi:
            mid = (lo + hi) >> 1
            if v < thresholds[mid]:
                hi = mid
            else:
                lo = mid + 1
        b = lo
        hist[b, y[i]] += 1


@numba.njit(cache=True)
def _gains_from_histogram(hist, xlogx, gains):
    """Fill gains (K,) with the information gain (bits) of each threshold from hist (K + 1, C).

    With S(counts) = n log2 n - sum_c n_c log2 n_c (= n H), the gain of a split is
    (S(parent) - S(left) - S(right)) / n; `xlogx[i]` = i log2 i. Only classes present in
    the node are visited.
    """
    k = hist.shape[0] - 1
    n_classes = hist.shape[1]
    total = np.zeros(n_classes, np.int64)
    for b in range(k + 1):
        for c in range(n_classes):
            total[c] += hist[b, c]
    present = np.empty(n_classes, np.int64)
    n_present = 0
    n = 0
    s_parent = 0.0
    for c in range(n_classes):
        if total[c] > 0:
            present[n_present] = c
            n_present += 1
            n += total[c]
            s_parent -= xlogx[total[c]]
    s_parent += xlogx[n]
    left = np.zeros(n_classes, np.int64)
    n_left = 0
    for t in range(k):
        s_left = 0.0
        s_right = 0.0
        for q in range(n_present):
            c = present[q]
            left[c] += hist[t, c]
            n_left += hist[t, c]
            s_left -= xlogx[left[c]]
            s_right -= xlogx[total[c] - left[c]]
        s_left += xlogx[n_left]
        s_right += xlogx[n - n_left]
        gains[t] = (s_parent - s_left - s_right) / n


@numba.njit(cache=True)
def _unit_vector(state, k, out):
    """k uniforms in [-1, 1] redrawn until 0 < norm <= 1, normalised: uniform on the sphere."""
    while True:
        sq = 0.0
        for j in range(k):
            v = 2.0 * _uniform(state) - 1.0
            out[j] = v
            sq += v * v
        if 0.0 < sq <= 1.0:
            norm = np.sqrt(sq)
            for j in range(k):
                out[j] = out[j] / norm
            return


@numba.njit(cache=True)
def _best_split(fm, y, ids, state, n_classes, n_candidates, n_thresholds, k, linear, cap, xlogx):
    """Randomized node optimisation for the samples `ids` of one node.

    Returns (gain, feats (k,) int64, weights (k,) float32, threshold float32); gain is -1
    when no candidate was drawn. The draws follow the order in the module docstring.
    """
    n = ids.shape[0]
    if n > cap:
        m = cap
        sub = np.empty(m, ids.dtype)
        for i in range(m):
            sub[i] = ids[_randint(state, n)]
    else:
        m = n
        sub = ids
    ys = np.empty(m, np.int64)
    for i in range(m):
        ys[i] = y[sub[i]]
    n_thr = min(n_thresholds, m)
    resp = np.empty(m, np.float32)
    thr = np.empty(n_thr, np.float32)
    feats = np.empty(k, np.int64)
    w64 = np.empty(k, np.float64)
    weights = np.empty(k, np.float32)
    best_gain = -1.0
    best_feats = np.zeros(k, np.int64)
    best_weights = np.zeros(k, np.float32)
    best_thr = np.float32(0.0)
    hist = np.empty((n_thr + 1, n_classes), np.int64)
    gains = np.empty(n_thr, np.float64)
    n_features = fm.shape[0]
    for _ in range(n_candidates):
        for j in range(k):
            feats[j] = _randint(state, n_features)
        if linear:
            _unit_vector(state, k, w64)
            for j in range(k):
                weights[j] = np.float32(w64[j])
        else:
            weights[:] = 1.0
        _responses(fm, sub, feats, weights, resp)
        for t in range(n_thr):
            thr[t] = resp[_randint(state, m)]
        thr.sort()
        _bin_histogram(resp, ys, thr, hist)
        _gains_from_histogram(hist, xlogx, gains)
        for t in range(n_thr):
            if gains[t] > best_gain:
                best_gain = gains[t]
                best_feats[:] = feats
                best_weights[:] = weights
                best_thr = thr[t]
    return best_gain, best_feats, best_weights, best_thr


@numba.njit(cache=True)
def _partition(fm, ids, feats, weights, threshold):
    """Stable in-place partition of `ids`: response < threshold first; returns the count."""
    n = ids.shape[0]
    resp = np.empty(n, np.float32)
    _responses(fm, ids, feats, weights, resp)
    tmp = np.empty(n, ids.dtype)
    n_left = 0
    for i in range(n):
        if resp[i] < threshold:
            tmp[n_left] = ids[i]
            n_left += 1
    j = n_left
    for i in range(n):
        if not resp[i] < threshold:
            tmp[j] = ids[i]
            j += 1
    ids[:] = tmp
    return n_left


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


# --- sampling ------------------------------------------------------------------------------


def balanced_counts(class_counts: np.ndarray, budget: int) -> np.ndarray:
    """Share `budget` samples evenly over classes with pixels (water-filling).

    A class with fewer pixels than its share gives all of them; the rest is shared again.
    """
    take = np.zeros_like(class_counts)
    present = np.flatnonzero(class_counts)
    remaining = budget
    for i, c in enumerate(present[np.argsort(class_counts[present], kind="stable")]):
        take[c] = min(class_counts[c], remaining // (len(present) - i))
        remaining -= take[c]
    return take


def sample_pixels(
    depth: np.ndarray, label: np.ndarray, n: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Class-balanced sample of up to `n` pixels with depth and a class: (rows, cols, labels)."""
    lab = label.ravel()
    bad = (lab >= label_table.NUM_CLASSES) & (lab != label_table.NO_DEPTH)
    if bad.any():
        raise TopsegError(f"label frame holds unknown label ids {np.unique(lab[bad]).tolist()}")
    valid = np.flatnonzero((depth.ravel() > 0) & (lab < label_table.NUM_CLASSES))
    classes = lab[valid]
    order = np.argsort(classes, kind="stable")
    counts = np.bincount(classes, minlength=label_table.NUM_CLASSES)
    take = balanced_counts(counts, n)
    bounds = np.concatenate([[0], np.cumsum(counts)])
    chosen = []
    for c in np.flatnonzero(take):
        pick = rng.choice(counts[c], size=take[c], replace=False)
        chosen.append(valid[order[bounds[c] + pick]])
    flat = np.concatenate(chosen) if chosen else np.zeros(0, np.int64)
    rows, cols = np.divmod(flat, depth.shape[1])
    return rows, cols, lab[flat]


def _check_frames(depth_frames: Any, label_frames: Any) -> int:
    for name, frames, dtype in (
        ("depth", depth_frames, np.uint16),
        ("labels", label_frames, np.uint8),
    ):
        if len(getattr(frames, "shape", ())) != 3:
            raise TopsegError(
                f"{name} frames must be an (N, H, W) array, got shape {getattr(frames, 'shape', None)}"
            )
        if np.dtype(frames.dtype) != dtype:
            raise TopsegError(f"{name} frames must be {np.dtype(dtype)}, got {frames.dtype}")
    if tuple(depth_frames.shape) != tuple(label_frames.shape):
        raise TopsegError(
            f"depth {tuple(depth_frames.shape)} and label {tuple(label_frames.shape)} frames differ in shape"
        )
    if depth_frames.shape[0] == 0:
        raise TopsegError("no frames to train on")
    return int(depth_frames.shape[0])


def gather_samples(
    depth_frames: Any,
    label_frames: Any,
    config: TrainConfig,
    rng: np.random.Generator,
    offsets: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bag frames, sample pixels, extract features.

    Returns (features (PC, n) int16, feature-major; labels (n,) uint8; where (n, 3) int64
    rows of (frame, row, col)); `where` lets tests and tools replay a tree on its own samples.
    """
    n_frames = _check_frames(depth_frames, label_frames)
    draws = np.sort(rng.integers(0, n_frames, size=min(config.frames_per_tree, n_frames)))
    frames, repeats = np.unique(draws, return_counts=True)
    cap = len(draws) * config.pixels_per_frame
    fm = np.empty((offsets.shape[0], cap), np.int16)
    y = np.empty(cap, np.uint8)
    where = np.empty((cap, 3), np.int64)
    n = 0
    for frame, times in zip(frames, repeats, strict=True):
        depth = np.asarray(depth_frames[int(frame)])
        label = np.asarray(label_frames[int(frame)])
        for _ in range(times):
            rows, cols, ys = sample_pixels(depth, label, config.pixels_per_frame, rng)
            end = n + rows.size
            fm[:, n:end] = extract_features(
                depth, rows, cols, offsets, config.features.background_mm
            ).T
            y[n:end] = ys
            where[n:end] = np.stack([np.full(rows.size, frame), rows, cols], axis=1)
            n = end
    if n == 0:
        raise TopsegError("the bagged frames hold no labelled pixels with depth")
    return fm[:, :n], y[:n], where[:n]  # a view: copying would double the peak memory


# --- trees and forests ---------------------------------------------------------------------


def tree_seed(seed: int, tree_index: int) -> int:
    """The seed of tree `tree_index` of a forest trained with `seed` (any scheduler)."""
    return int(np.random.SeedSequence([seed, tree_index]).generate_state(1, np.uint64)[0])


def _xlogx(n: int) -> np.ndarray:
    i = np.arange(n + 1, dtype=np.float64)
    out = np.zeros(n + 1)
    out[1:] = i[1:] * np.log2(i[1:])
    return out


def grow_tree(
    fm: np.ndarray,
    y: np.ndarray,
    offsets: np.ndarray,
    config: TrainConfig,
    key: int,
    progress: Callable[[int, int], None] | None = None,
) -> Tree:
    """Grow one tree on a feature matrix (see the module docstring, steps 4 and 5)."""
    n_classes = label_table.NUM_CLASSES
    k = config.features_per_node
    idx = np.arange(y.shape[0], dtype=np.int64)
    y = y.astype(np.int64)
    xlogx = _xlogx(min(config.max_split_samples, y.shape[0]) + 1)
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
    )


def train_tree(
    depth_frames: Any,
    label_frames: Any,
    config: TrainConfig,
    seed: int,
    progress: Callable[[int, int], None] | None = None,
) -> Tree:
    """Train one tree on (N, H, W) depth (uint16 mm) and label (uint8) frames.

    The frames may be any array-likes with integer indexing (numpy or zarr arrays); only the
    bagged frames are read, one at a time. Deterministic for a seed. `progress(level, nodes)`
    is called after each level with the number of nodes on it.
    """
    rng = np.random.default_rng(seed)
    key = int(rng.integers(0, 2**63))
    offsets = sample_offsets(config.features, rng)
    t0 = time.perf_counter()
    fm, y, _ = gather_samples(depth_frames, label_frames, config, rng, offsets)
    log.debug(
        "tree seed %d: %d features x %d samples in %.1f s",
        seed,
        *fm.shape,
        time.perf_counter() - t0,
    )
    t0 = time.perf_counter()
    tree = grow_tree(fm, y, offsets, config, key, progress)
    log.debug(
        "tree seed %d: %d nodes, depth %d in %.1f s",
        seed,
        tree.n_nodes,
        tree.depth,
        time.perf_counter() - t0,
    )
    return tree


def train_forest(
    depth_frames: Any,
    label_frames: Any,
    config: TrainConfig,
    seed: int = 0,
    n_trees: int | None = None,
    progress: Callable[[int, int, int], None] | None = None,
) -> Forest:
    """Train `n_trees` (default `config.n_trees`) trees one after the other.

    Tree t uses `tree_seed(seed, t)`, so a parallel trainer gives identical trees.
    `progress(tree, level, nodes)` is called after each level of each tree.
    """
    n = config.n_trees if n_trees is None else n_trees
    trees = []
    for t in range(n):
        cb = None if progress is None else (lambda level, nodes, t=t: progress(t, level, nodes))
        trees.append(train_tree(depth_frames, label_frames, config, tree_seed(seed, t), cb))
    return Forest.from_trees(trees)


def training_sample_pixels(
    depth_frames: Any, label_frames: Any, config: TrainConfig, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """The (frame, row, col) rows and labels `train_tree(..., seed)` trains on, in order."""
    rng = np.random.default_rng(seed)
    rng.integers(0, 2**63)
    offsets = sample_offsets(config.features, rng)
    _, y, where = gather_samples(depth_frames, label_frames, config, rng, offsets)
    return where, y
