"""Decision trees and forests as flat arrays (the layout of scikit-learn's `tree`).

Node i of a tree is described by row i of each array:

- `offsets[i]`  (k, 4) float32: the k feature offset pairs (u_row, u_col, v_row, v_col) it
  combines, pixel*mm (see `features`); k = 1 for axis-aligned splits;
- `weights[i]`  (k,) float32: the response's weights (a unit vector; 1 for axis-aligned);
- `threshold[i]` float32: a pixel goes left when its response < threshold, else right;
- `left[i]`     int32: index of the left child; the right child is `left[i] + 1`; -1 marks
  a leaf. Children always come after their parent (`left[i] > i`), which makes every walk
  from the root finite;
- `leaf[i]`     int32: for a leaf, its row in `posteriors` (n_leaves, n_classes) float32,
  the class distribution of the training samples that reached it; -1 for split nodes.
  A model knows `n_classes` classes: ids 0..n_classes-1 of the label table, 2 to
  NUM_CLASSES of them (a model trained on the paper's classes knows PAPER_NUM_CLASSES).

A `Forest` is the concatenation of T trees with child and leaf indices shifted, plus
`roots` (T,) int32, so inference over all trees is one numba call.

Both also carry `background_mm`, the value no-depth probes read during training
(`FeatureConfig.background_mm`), and `nearest_off_image`, whether a probe off the image read
the nearest edge pixel instead of `background_mm` (`FeatureConfig.off_image`), which
inference must use too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from topseg.core.labels import NUM_CLASSES, PAPER_NUM_CLASSES

#: array name -> dtype, for every node/leaf array of a tree or forest
ARRAY_DTYPES: dict[str, np.dtype] = {
    "offsets": np.dtype(np.float32),
    "weights": np.dtype(np.float32),
    "threshold": np.dtype(np.float32),
    "left": np.dtype(np.int32),
    "leaf": np.dtype(np.int32),
    "posteriors": np.dtype(np.float32),
}


def validate_arrays(arrays: dict[str, np.ndarray], roots: np.ndarray) -> None:
    """Check dtypes, shapes and every index of a flat forest; ValueError says what is wrong.

    Guarantees that inference cannot index out of bounds or loop: each root is a node,
    children come after their parent and exist, each leaf has a posterior row.
    """
    for name, dtype in ARRAY_DTYPES.items():
        if name not in arrays:
            raise ValueError(f"missing array {name!r}")
        if arrays[name].dtype != dtype:
            raise ValueError(f"array {name!r} has dtype {arrays[name].dtype}, expected {dtype}")
    offsets, weights = arrays["offsets"], arrays["weights"]
    threshold, left, leaf = arrays["threshold"], arrays["left"], arrays["leaf"]
    posteriors = arrays["posteriors"]
    n = threshold.shape[0]
    if offsets.ndim != 3 or offsets.shape[0] != n or offsets.shape[2] != 4 or offsets.shape[1] < 1:
        raise ValueError(f"offsets must be ({n}, k, 4), got {offsets.shape}")
    k = offsets.shape[1]
    for name, arr, shape in (
        ("weights", weights, (n, k)),
        ("threshold", threshold, (n,)),
        ("left", left, (n,)),
        ("leaf", leaf, (n,)),
    ):
        if arr.shape != shape:
            raise ValueError(f"array {name!r} must have shape {shape}, got {arr.shape}")
    if posteriors.ndim != 2 or not 2 <= posteriors.shape[1] <= NUM_CLASSES:
        raise ValueError(
            f"posteriors must be (n_leaves, n_classes) with 2 <= n_classes <= {NUM_CLASSES}, "
            f"got {posteriors.shape}"
        )
    if n == 0:
        raise ValueError("a forest needs at least one node")
    if roots.dtype != np.int32 or roots.ndim != 1 or roots.size == 0:
        raise ValueError(
            f"roots must be a non-empty 1-D int32 array, got {roots.dtype} {roots.shape}"
        )
    if roots.min() < 0 or roots.max() >= n:
        raise ValueError(f"a root index is outside the {n} nodes")
    for name, arr in (("offsets", offsets), ("weights", weights), ("threshold", threshold)):
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"array {name!r} holds non-finite values")
    is_leaf = left == -1
    split = ~is_leaf
    ids = np.arange(n)
    if np.any(left[split] <= ids[split]) or np.any(left[split] + 1 >= n):
        raise ValueError("a child index is out of bounds or does not come after its parent")
    if np.any(leaf[split] != -1):
        raise ValueError("a split node also names a leaf posterior")
    n_leaves = posteriors.shape[0]
    if np.any(leaf[is_leaf] < 0) or np.any(leaf[is_leaf] >= n_leaves):
        raise ValueError(f"a leaf index is outside the {n_leaves} posterior rows")
    if not np.all(np.isfinite(posteriors)) or np.any(posteriors < 0) or np.any(posteriors > 1):
        raise ValueError("posteriors must be class probabilities in [0, 1]")
    if np.any(posteriors.sum(axis=1, dtype=np.float64) <= 0):
        raise ValueError("a leaf's posterior row is all zeros (it would vote for no class)")


@dataclass(frozen=True, eq=False)
class Tree:
    """One trained tree as flat arrays (see the module docstring); node 0 is the root."""

    offsets: np.ndarray
    weights: np.ndarray
    threshold: np.ndarray
    left: np.ndarray
    leaf: np.ndarray
    posteriors: np.ndarray
    background_mm: int = 10000
    nearest_off_image: bool = False

    def __post_init__(self) -> None:
        validate_arrays(self.arrays(), np.zeros(1, np.int32))

    def arrays(self) -> dict[str, np.ndarray]:
        """The tree's arrays by name, as the model file stores them."""
        return {name: getattr(self, name) for name in ARRAY_DTYPES}

    @property
    def n_nodes(self) -> int:
        """Number of nodes, leaves included."""
        return int(self.threshold.shape[0])

    @property
    def n_leaves(self) -> int:
        """Number of leaves (rows of `posteriors`)."""
        return int(self.posteriors.shape[0])

    @property
    def n_classes(self) -> int:
        """Number of classes the tree knows (columns of `posteriors`, ids 0..n_classes-1)."""
        return int(self.posteriors.shape[1])

    @property
    def depth(self) -> int:
        """Length of the longest root-to-leaf path (0 for a lone leaf)."""
        return int(node_depths(self.left, np.zeros(1, np.int32)).max())


@dataclass(frozen=True, eq=False)
class Forest:
    """T trees concatenated: the node arrays of a `Tree` plus `roots` (T,) int32."""

    offsets: np.ndarray
    weights: np.ndarray
    threshold: np.ndarray
    left: np.ndarray
    leaf: np.ndarray
    posteriors: np.ndarray
    roots: np.ndarray
    background_mm: int = 10000
    nearest_off_image: bool = False

    def __post_init__(self) -> None:
        validate_arrays(self.arrays(), self.roots)

    def arrays(self) -> dict[str, np.ndarray]:
        """Every array, `roots` included, by name (what the model file stores)."""
        out = {name: getattr(self, name) for name in ARRAY_DTYPES}
        out["roots"] = self.roots
        return out

    @classmethod
    def from_trees(cls, trees: list[Tree]) -> Forest:
        """Concatenate trees; they must share k (the number of features per node).

        The forest knows the most classes any tree knows: a tree that saw fewer (its bag
        held no pixel of a later class) gets zero posterior columns for them."""
        if not trees:
            raise ValueError("a forest needs at least one tree")
        ks = {t.offsets.shape[1] for t in trees}
        if len(ks) != 1:
            raise ValueError(f"trees mix features per node: {sorted(ks)}")
        backgrounds = {t.background_mm for t in trees}
        if len(backgrounds) != 1:
            raise ValueError(f"trees mix background constants: {sorted(backgrounds)}")
        if len({t.nearest_off_image for t in trees}) != 1:
            raise ValueError("trees mix what a probe off the image reads")
        node_base = np.cumsum([0] + [t.n_nodes for t in trees])
        leaf_base = np.cumsum([0] + [t.n_leaves for t in trees])
        n_classes = max(t.n_classes for t in trees)
        parts: dict[str, list[np.ndarray]] = {name: [] for name in ARRAY_DTYPES}
        for t, nb, lb in zip(trees, node_base, leaf_base, strict=False):
            for name in ("offsets", "weights", "threshold"):
                parts[name].append(getattr(t, name))
            parts["posteriors"].append(_widen(t.posteriors, n_classes))
            parts["left"].append(np.where(t.left >= 0, t.left + nb, -1).astype(np.int32))
            parts["leaf"].append(np.where(t.leaf >= 0, t.leaf + lb, -1).astype(np.int32))
        arrays = {name: np.concatenate(p) for name, p in parts.items()}
        return cls(
            **arrays,
            roots=node_base[:-1].astype(np.int32),
            background_mm=trees[0].background_mm,
            nearest_off_image=trees[0].nearest_off_image,
        )

    def tree(self, t: int) -> Tree:
        """Tree t back as its own arrays (indices rebased to 0)."""
        lo = int(self.roots[t])
        hi = int(self.roots[t + 1]) if t + 1 < self.n_trees else self.n_nodes
        left, leaf = self.left[lo:hi], self.leaf[lo:hi]
        leaves = leaf[leaf >= 0]
        l0 = int(leaves.min())
        l1 = int(leaves.max()) + 1
        return Tree(
            self.offsets[lo:hi],
            self.weights[lo:hi],
            self.threshold[lo:hi],
            np.where(left >= 0, left - lo, -1).astype(np.int32),
            np.where(leaf >= 0, leaf - l0, -1).astype(np.int32),
            self.posteriors[l0:l1],
            self.background_mm,
            self.nearest_off_image,
        )

    @property
    def n_trees(self) -> int:
        """Number of trees."""
        return int(self.roots.shape[0])

    @property
    def n_nodes(self) -> int:
        """Number of nodes over all trees."""
        return int(self.threshold.shape[0])

    @property
    def features_per_node(self) -> int:
        """k: pool features one node combines (1: axis-aligned)."""
        return int(self.offsets.shape[1])

    @property
    def n_classes(self) -> int:
        """Number of classes the forest knows (columns of `posteriors`, ids 0..n_classes-1)."""
        return int(self.posteriors.shape[1])

    @property
    def depth(self) -> int:
        """The deepest leaf's depth (the root is depth 0)."""
        return int(node_depths(self.left, self.roots).max())


def _widen(posteriors: np.ndarray, n_classes: int) -> np.ndarray:
    """`posteriors` with zero columns appended up to `n_classes`."""
    missing = n_classes - posteriors.shape[1]
    return np.pad(posteriors, ((0, 0), (0, missing))) if missing else posteriors


def node_depths(left: np.ndarray, roots: np.ndarray) -> np.ndarray:
    """Depth of every node reachable from `roots` (root = 0), level by level."""
    depth = np.zeros(left.shape[0], np.int64)
    frontier, level = np.asarray(roots, np.int64), 0
    while frontier.size:
        depth[frontier] = level
        children = left[frontier]
        children = children[children >= 0].astype(np.int64)
        frontier, level = np.concatenate([children, children + 1]), level + 1
    return depth


def random_tree(
    rng: np.random.Generator,
    depth: int,
    features_per_node: int,
    max_offset: float,
    threshold_scale: float = 300.0,
    n_classes: int = PAPER_NUM_CLASSES,
) -> Tree:
    """A full binary tree of `depth` with random splits and random leaf posteriors over
    `n_classes` classes.

    Stands in for a trained tree where only the shape matters: kernel tests and the
    inference benchmark (every pixel walks all `depth` levels, the worst case).
    Nodes are in breadth-first order; thresholds are Gaussian with `threshold_scale` mm.
    """
    n_split = 2**depth - 1
    n = 2 ** (depth + 1) - 1
    k = features_per_node
    offsets = rng.uniform(-max_offset, max_offset, size=(n, k, 4)).astype(np.float32)
    w = rng.normal(size=(n, k))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    threshold = (rng.normal(size=n) * threshold_scale).astype(np.float32)
    ids = np.arange(n)
    left = np.where(ids < n_split, 2 * ids + 1, -1).astype(np.int32)
    leaf = np.where(ids < n_split, -1, ids - n_split).astype(np.int32)
    posteriors = rng.dirichlet(np.full(n_classes, 0.3), size=n - n_split).astype(np.float32)
    return Tree(offsets, w.astype(np.float32), threshold, left, leaf, posteriors)
