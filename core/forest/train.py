"""Training a decision tree (and a forest, tree by tree) on labelled depth frames.

One tree:

1. **Bagging.** The tree draws min(F, N) of the N frames with replacement
   (`frames_per_tree` = F); a frame drawn twice is sampled twice.
2. **Class-balanced pixel sampling.** From each drawn frame, `pixels_per_frame` pixels with
   depth and a class label, shared out evenly over the classes present (a class with too
   few pixels gives all it has and the rest goes to the others). Leaf posteriors are
   therefore class distributions under a uniform class prior, as in Shotton et al.
   Given the frames' mounts, each frame is cropped to its camera, read as a height model's
   input (`inputs.model_input`) and its floor-gated pixels are not sampled (inference never
   walks them); without mounts the frames are read as depth (a legacy model).
3. **Features once.** The tree draws its own pool of PC offset pairs and extracts the
   (PC, n_samples) int16 feature matrix once (feature-major, so a candidate streams rows) (2 bytes per value: the paper's F = 1600,
   2000 pixels per frame and PC = 300 take 1.9 GB per tree, so two trees train side by
   side in 8 GB).
4. **Randomized node optimisation**, level by level, all nodes of a level in parallel.
   A node with at least `min_samples_split` samples, below `max_depth` and not pure draws
   R candidate responses (axis-aligned: one pool feature; linear: `linear_k` features and
   a random unit vector) and, per candidate, K thresholds among the candidate's responses.
   Responses are computed on at most `max_split_samples` samples of the node (drawn with
   replacement when the node is larger); the information gain (bits) of all K thresholds
   comes from one per-class histogram. The best split is kept if its gain > `min_gain`,
   and all the node's samples are partitioned by it (left: response < threshold).
5. **Leaves** store the normalised class histogram of all samples that reach them.

The work is split as scikit-learn splits it: this module samples and holds the entry points
(`TrainConfig`, `train_tree`, `train_forest`, `tree_seed`); `criterion` scores thresholds,
`splitter` draws and chooses a node's split (with its per-node random stream, so a tree
depends only on its seed) and `builder` grows the tree and makes its leaves.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from topseg.core import labels as label_table
from topseg.core.errors import TopsegError
from topseg.core.forest.builder import grow_tree
from topseg.core.forest.features import extract_features, sample_offsets
from topseg.core.forest.inputs import legacy_input, model_input
from topseg.core.forest.train_config import TrainConfig
from topseg.core.forest.tree import Forest, Tree

log = logging.getLogger(__name__)


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
    depth: np.ndarray,
    label: np.ndarray,
    n: int,
    rng: np.random.Generator,
    exclude: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Class-balanced sample of up to `n` pixels with depth and a class, and not in the
    `exclude` mask (the floor gate): (rows, cols, labels)."""
    lab = label.ravel()
    bad = (lab >= label_table.NUM_CLASSES) & (lab != label_table.NO_DEPTH)
    if bad.any():
        raise TopsegError(f"label frame holds unknown label ids {np.unique(lab[bad]).tolist()}")
    ok = (depth.ravel() > 0) & (lab < label_table.NUM_CLASSES)
    if exclude is not None:
        ok &= ~exclude.ravel()
    valid = np.flatnonzero(ok)
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


def _mount_at(mounts: Any, i: int) -> Any:
    """The mount of frame i: `mounts(i)` for a callable, else `mounts[i]`."""
    return mounts(i) if callable(mounts) else mounts[i]


def frame_input(
    depth: np.ndarray, label: np.ndarray, config: TrainConfig, mount: Any = None
) -> tuple[Any, np.ndarray]:
    """(model input, labels) of one training frame: cropped to its mount's camera and read
    as a height model's input, or read as depth (legacy) without a mount."""
    if mount is None:
        return legacy_input(depth), label
    h, w = mount.intrinsics.shape
    if depth.shape[0] < h or depth.shape[1] < w:
        raise TopsegError(
            f"a {depth.shape[1]}x{depth.shape[0]} frame is smaller than its camera's {w}x{h}"
        )
    depth = np.ascontiguousarray(depth[:h, :w])
    inp = model_input(depth, mount, config.features, for_training=True)
    return inp, np.ascontiguousarray(label[:h, :w])


def gather_samples(
    depth_frames: Any,
    label_frames: Any,
    config: TrainConfig,
    rng: np.random.Generator,
    offsets: np.ndarray,
    mounts: Any = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bag frames, sample pixels, extract features.

    `mounts` (a sequence or a callable of the frame position; None: read the frames as
    depth) gives each frame's mount (see the module). Returns (features (PC, n) int16,
    feature-major; labels (n,) uint8; where (n, 3) int64 rows of (frame, row, col)); `where`
    lets tests and tools replay a tree on its own samples.
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
        mount = None if mounts is None else _mount_at(mounts, int(frame))
        inp, label = frame_input(depth, label, config, mount)
        gate = inp.floor if mount is not None else None
        for _ in range(times):
            rows, cols, ys = sample_pixels(inp.values, label, config.pixels_per_frame, rng, gate)
            end = n + rows.size
            fm[:, n:end] = extract_features(
                inp,
                rows,
                cols,
                offsets,
                config.features.background_mm,
                nearest=config.features.nearest_off_image,
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


def train_tree(
    depth_frames: Any,
    label_frames: Any,
    config: TrainConfig,
    seed: int,
    progress: Callable[[int, int], None] | None = None,
    mounts: Any = None,
) -> Tree:
    """Train one tree on (N, H, W) depth (uint16 mm) and label (uint8) frames.

    The frames may be any array-likes with integer indexing (numpy or zarr arrays); only the
    bagged frames are read, one at a time. With `mounts` (each frame's mount, a sequence or
    a callable of the frame position) the tree reads heights (a height model); without, it
    reads depth. Deterministic for a seed. `progress(level, nodes)` is called after each
    level with the number of nodes on it.
    """
    rng = np.random.default_rng(seed)
    key = int(rng.integers(0, 2**63))
    offsets = sample_offsets(config.features, rng)
    t0 = time.perf_counter()
    fm, y, _ = gather_samples(depth_frames, label_frames, config, rng, offsets, mounts)
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
    mounts: Any = None,
) -> Forest:
    """Train `n_trees` (default `config.n_trees`) trees one after the other.

    Tree t uses `tree_seed(seed, t)`, so a parallel trainer gives identical trees.
    `progress(tree, level, nodes)` is called after each level of each tree. `mounts` as for
    `train_tree` (with them the forest reads heights: save it with
    `inputs.header_fields(config.features, ...)` in its header).
    """
    n = config.n_trees if n_trees is None else n_trees
    trees = []
    for t in range(n):
        cb = None if progress is None else (lambda level, nodes, t=t: progress(t, level, nodes))
        trees.append(train_tree(depth_frames, label_frames, config, tree_seed(seed, t), cb, mounts))
    return Forest.from_trees(trees)


def training_sample_pixels(
    depth_frames: Any, label_frames: Any, config: TrainConfig, seed: int, mounts: Any = None
) -> tuple[np.ndarray, np.ndarray]:
    """The (frame, row, col) rows and labels `train_tree(..., seed)` trains on, in order."""
    rng = np.random.default_rng(seed)
    rng.integers(0, 2**63)
    offsets = sample_offsets(config.features, rng)
    _, y, where = gather_samples(depth_frames, label_frames, config, rng, offsets, mounts)
    return where, y
