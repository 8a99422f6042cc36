"""The person check: is each blob of body-part labels a person, or part of something else?

The forest labels pixels one at a time, so the top of a robot link, a drum or a cabinet can
come out as `body` or `head`. Seen as a whole, such a blob is unlike a person: its size, its
height profile, what surrounds it and the forest's posteriors over all of it differ. After the
CRF, every 8-connected blob of body-part labels is described by `FEATURES` (`blob_features`)
and scored by a small boosted tree ensemble the model file carries (`PersonCheck`, fitted by
`topseg person-check` on the model's own labels of rendered cells); a blob scoring under the
check's threshold is not a person, and its pixels take their most probable class that is
neither a body part nor background (`relabel_blobs`): something stands there.

Everything here is pure: numpy, and the numba kernels of `person_check_kernels`, on the
working resolution's arrays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from topseg.core import labels as L
from topseg.core import person_check_kernels as K
from topseg.core.camera import Intrinsics
from topseg.core.errors import TopsegError

#: the ring around a blob that its neighbours are read from: pixels within this many pixels
RING_PX = 3
#: a ring pixel this high above the floor (mm) or more is "tall" (a blob on top of something)
TALL_MM = 300.0
#: a blob pixel within this much (mm) of the blob's highest is on its top
TOP_MM = 50.0
#: a body part covering at least this share of a blob counts as present in it
PART_PRESENT = 0.05
#: `extent_ratio` divides by at least this (m): a blob a pixel or two wide has no shape
MIN_EXTENT_M = 0.01
#: posterior columns every feature row has (a model with fewer classes pads with zeros)
POSTERIOR_COLUMNS = L.NUM_CLASSES
#: `head_rel_h` of a blob without a head (mm)
NO_HEAD_MM = -2000.0

_PARTS = tuple(L.HUMAN_IDS)
#: label -> its body part's index in _PARTS (-1: not a body part)
_PART_OF = np.full(256, -1, np.int64)
_PART_OF[list(_PARTS)] = np.arange(len(_PARTS))
#: label -> whether a rejected blob's pixel may take it: neither a body part nor background
REPLACEMENT = np.ones(L.NUM_CLASSES, bool)
REPLACEMENT[[L.BACKGROUND, *_PARTS]] = False
#: label -> whether it is a body part
IS_PART = _PART_OF >= 0
#: label -> what it is to the ring and component sums (`person_check_kernels`)
_KINDS = np.full(256, K.OTHER, np.int64)
_KINDS[L.ROBOT], _KINDS[L.OBJECT], _KINDS[L.BACKGROUND] = K.ROBOT, K.OBJECT, K.BACKGROUND
_KINDS[list(L.FURNITURE_IDS)] = K.FURNITURE
#: what each feature row holds, in order; a model file's check names them and must match
FEATURES: tuple[str, ...] = (
    "log_area_cm2",
    "height_max_mm",
    "height_mean_mm",
    "height_std_mm",
    "height_min_mm",
    "height_range_mm",
    "top_share",
    *(f"part_{L.NAMES[c].replace('-', '_')}" for c in _PARTS),
    "parts_present",
    *(f"posterior_{i}" for i in range(POSTERIOR_COLUMNS)),
    "posterior_body_parts",
    "posterior_furniture",
    "log_head_cm2",
    "head_below_top_mm",
    "extent_major_m",
    "extent_minor_m",
    "extent_ratio",
    "ring_robot",
    "ring_object",
    "ring_furniture",
    "ring_background",
    "ring_no_depth",
    "ring_height_mean_mm",
    "ring_above_top_mm",
    "ring_tall",
    "component_log_ratio",
    "component_robot",
    "component_object",
    "component_furniture",
    "camera_height_mm",
    "pixel_mm",
)


@dataclass(frozen=True)
class Blobs:
    """The body-part blobs of one frame: `image` (h, w) int32 blob numbers (0: none, blob
    k is `image == k + 1`), `features` (n, len(FEATURES)) float64, `area_cm2` (n,)."""

    image: np.ndarray
    features: np.ndarray
    area_cm2: np.ndarray

    @property
    def count(self) -> int:
        """How many blobs."""
        return len(self.area_cm2)


def blob_features(
    labels: np.ndarray,
    depth_mm: np.ndarray,
    heights_mm: np.ndarray,
    proba: np.ndarray,
    intrinsics,
    camera_height_mm: float,
    parts: np.ndarray | None = None,
) -> Blobs:
    """Every body-part blob of `labels` and its `FEATURES` row.

    labels      (h, w) uint8 class ids after the CRF
    depth_mm    (h, w) depth (0: none); heights_mm (h, w) height above the floor (NaN: none)
    proba       (h, w, C) forest posteriors, stored at least at every body-part pixel
    intrinsics  the optics at this resolution (fx, fy, cx, cy)
    parts       `IS_PART[labels]`, when the caller has it already
    """
    image, n = K.label8(IS_PART[labels] if parts is None else parts)
    if n == 0:
        return Blobs(image, np.zeros((0, len(FEATURES))), np.zeros(0))
    k = intrinsics
    heights = np.asarray(heights_mm, np.float32)
    s = K.blob_sums(image, n, labels, _PART_OF, depth_mm, heights, proba, POSTERIOR_COLUMNS,
                    k.fx, k.fy, k.cx, k.cy)  # fmt: skip
    h_max = np.where(np.isfinite(s[:, K.H_MAX]), s[:, K.H_MAX], 0.0)
    h_min = np.where(np.isfinite(s[:, K.H_MIN]), s[:, K.H_MIN], 0.0)
    K.blob_top(image, depth_mm, heights, h_max, TOP_MM, k.fx, k.fy, s)
    area = s[:, K.AREA]
    safe = np.maximum(area, 1e-9)
    h_mean = s[:, K.AREA_H] / safe
    h_std = np.sqrt(np.maximum(s[:, K.AREA_HH] / safe - h_mean**2, 0.0))
    parts = s[:, K.PART : K.PART + len(_PARTS)] / safe[:, None]
    posterior = s[:, K.POSTERIOR :] / np.maximum(s[:, K.PIXELS], 1.0)[:, None]
    head_area = s[:, K.PART]
    head_h = s[:, K.HEAD_AREA_H] / np.maximum(head_area, 1e-9)
    head_below = np.where(head_area > 0, head_h - h_max, NO_HEAD_MM)
    major, minor = _extents(s, safe)
    features = np.column_stack([
        np.log1p(area), h_max, h_mean, h_std, h_min, h_max - h_min, s[:, K.TOP] / safe,
        parts, (parts > PART_PRESENT).sum(axis=1),
        posterior, posterior[:, list(_PARTS)].sum(axis=1),
        posterior[:, list(L.FURNITURE_IDS)].sum(axis=1),
        np.log1p(head_area), head_below,
        major, minor, major / np.maximum(minor, MIN_EXTENT_M),
        _ring_features(image, n, labels, depth_mm, heights, h_max),
        _component_features(image, n, labels, depth_mm, k, area),
        np.full(n, camera_height_mm), np.full(n, camera_height_mm / k.fx),
    ])  # fmt: skip
    return Blobs(image, np.nan_to_num(features, nan=0.0, posinf=1e30, neginf=-1e30), area)


def _extents(s: np.ndarray, safe_area: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each blob's spread on the floor (m): the square roots of its points' covariance's
    eigenvalues (area-weighted), major first."""
    mx, my = s[:, K.MX] / safe_area, s[:, K.MY] / safe_area
    sxx = s[:, K.MXX] / safe_area - mx * mx
    syy = s[:, K.MYY] / safe_area - my * my
    sxy = s[:, K.MXY] / safe_area - mx * my
    half_trace = (sxx + syy) / 2
    root = np.sqrt(np.maximum(((sxx - syy) / 2) ** 2 + sxy * sxy, 0.0))
    return np.sqrt(np.maximum(half_trace + root, 0.0)), np.sqrt(np.maximum(half_trace - root, 0.0))


def _ring_features(image, n, labels, depth_mm, heights, h_max) -> np.ndarray:
    """What lies within RING_PX pixels around each blob: shares of robot, object, furniture,
    background and no depth, its mean height, how far its highest point is above the blob's,
    and the share of it that is tall."""
    r = K.ring_sums(image, n, labels, _KINDS, depth_mm, heights, RING_PX, TALL_MM)
    total = np.maximum(r[:, K.R_PIXELS], 1.0)
    valid = r[:, K.R_VALID]
    safe_valid = np.maximum(valid, 1.0)
    return np.column_stack([
        r[:, K.R_ROBOT] / total,
        r[:, K.R_OBJECT] / total,
        r[:, K.R_FURNITURE] / total,
        r[:, K.R_BACKGROUND] / total,
        r[:, K.R_NO_DEPTH] / total,
        r[:, K.R_H] / safe_valid,
        np.where(valid > 0, r[:, K.R_H_MAX] - h_max, 0.0),
        r[:, K.R_TALL] / safe_valid,
    ])  # fmt: skip


def _component_features(image, n, labels, depth_mm, k, blob_area) -> np.ndarray:
    """The blob's place in the connected foreground it belongs to (everything labelled and
    not background): log of that component's area over the blob's, and the shares of it
    labelled robot, object and furniture."""
    foreground = (depth_mm > 0) & (labels != L.BACKGROUND) & (labels != L.NO_DEPTH)
    comp, m = K.label8(foreground)
    sums, which = K.component_sums(comp, m, image, n, labels, _KINDS, depth_mm, k.fx, k.fy)
    comp_area = np.maximum(sums[:, K.C_AREA], 1e-9)
    ratio = np.log(comp_area[which] / np.maximum(blob_area, 1e-9))
    ratio[which == 0] = 0.0
    shares = [sums[which, col] / comp_area[which] for col in (K.C_ROBOT, K.C_OBJECT, K.C_FURNITURE)]
    return np.column_stack([ratio, *shares])


#: the deepest tree a `TreeEnsemble` scores (laid out complete: 2**depth leaves a tree)
MAX_TREE_DEPTH = 12


def complete_trees(feature, threshold, left, right, value, roots):
    """Linked trees (`TreeEnsemble`'s node arrays) as complete binary trees of the deepest
    one's depth D: ((T, 2**D - 1) int32 features, float64 thresholds; (T, 2**D) float64 leaf
    values), node k's children at 2k + 1 (x <= threshold) and 2k + 2. A leaf above depth D
    gives its value to every complete leaf below its place, so any way down the padding
    (feature 0, threshold 0) ends on it: each row reaches the same leaf value as by the links.
    TopsegError when a node has two parents or a tree is deeper than `MAX_TREE_DEPTH`."""
    n = feature.size
    inner = feature >= 0
    children = np.concatenate([roots, left[inner], right[inner]])
    if np.unique(children).size != children.size:
        raise TopsegError("the check's trees share nodes: each node must have one parent")
    tree = np.full(n, -1, np.int64)
    place = np.zeros(n, np.int64)  # the node's index in its complete tree
    level = np.zeros(n, np.int64)
    tree[roots] = np.arange(roots.size)
    for k in range(n):  # children come after their parent (`from_dict` checks it)
        if inner[k] and tree[k] >= 0:
            for child, side in ((left[k], 1), (right[k], 2)):
                tree[child], place[child] = tree[k], 2 * place[k] + side
                level[child] = level[k] + 1
    walked = tree >= 0
    depth = int(level[walked].max())
    if depth > MAX_TREE_DEPTH:
        raise TopsegError(
            f"the check's trees are {depth} deep: at most {MAX_TREE_DEPTH} are scored"
        )
    first = 2**depth - 1
    c_feature = np.zeros((roots.size, first), np.int32)
    c_threshold = np.zeros((roots.size, first), np.float64)
    c_value = np.zeros((roots.size, 2**depth), np.float64)
    nodes = np.flatnonzero(walked & inner)
    c_feature[tree[nodes], place[nodes]] = feature[nodes]
    c_threshold[tree[nodes], place[nodes]] = threshold[nodes]
    for k in np.flatnonzero(walked & ~inner):
        below = 2 ** (depth - level[k])  # complete leaves under this leaf's place
        start = (place[k] + 1) * below - 1 - first
        c_value[tree[k], start : start + below] = value[k]
    return c_feature, c_threshold, c_value


def deepened(complete: tuple, depth: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Complete trees (`complete_trees`) laid out `depth` deep, at least their own: the new
    levels are padding (feature 0, threshold 0) and each leaf's value goes to the leaves
    below its place, so every row reaches the same value."""
    feature, threshold, value = complete
    own = int(np.log2(value.shape[1]))
    if depth <= own:
        return feature, threshold, value
    pad = 2**depth - 1 - feature.shape[1]
    return (
        np.pad(feature, ((0, 0), (0, pad))),
        np.pad(threshold, ((0, 0), (0, pad))),
        np.repeat(value, 2 ** (depth - own), axis=1),
    )


@dataclass(frozen=True)
class TreeEnsemble:
    """Boosted regression trees in flat arrays: score = offset + rate * sum of each tree's
    leaf value. A node with `feature` -1 is a leaf; otherwise rows with feature <= threshold
    (compared in float32, as scikit-learn fits them) go to `left`, the rest to `right`, both
    after their parent (so a walk always ends)."""

    feature: np.ndarray  # int32
    threshold: np.ndarray  # float64
    left: np.ndarray  # int32, absolute node index
    right: np.ndarray  # int32
    value: np.ndarray  # float64
    roots: np.ndarray  # int32, the first node of each tree
    offset: float
    rate: float
    depth: int
    #: the same trees laid out complete for scoring (`complete_trees`)
    complete: tuple[np.ndarray, np.ndarray, np.ndarray] = field(
        init=False, repr=False, compare=False
    )

    def __post_init__(self) -> None:
        object.__setattr__(self, "complete", complete_trees(
            self.feature, self.threshold, self.left, self.right, self.value, self.roots
        ))  # fmt: skip

    def score(self, x: np.ndarray) -> np.ndarray:
        """(n,) scores of the (n, F) feature rows `x`."""
        x = np.ascontiguousarray(np.asarray(x, np.float32), np.float64)
        one = np.zeros(len(self.roots), np.int64)
        return self.offset + self.rate * K.grouped_tree_sums(x, *self.complete, one, 1)[:, 0]

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON lists and numbers (what a model header holds)."""
        return {
            "feature": self.feature.tolist(),
            "threshold": self.threshold.tolist(),
            "left": self.left.tolist(),
            "right": self.right.tolist(),
            "value": self.value.tolist(),
            "roots": self.roots.tolist(),
            "offset": self.offset,
            "rate": self.rate,
            "depth": self.depth,
        }

    @classmethod
    def from_dict(cls, d: Any, n_features: int) -> TreeEnsemble:
        """The ensemble `to_dict` wrote; TopsegError when it is malformed or reads a feature
        or a node out of bounds."""
        if not isinstance(d, dict):
            raise TopsegError("the person check's trees are not a table")
        try:
            feature = np.asarray(d["feature"], np.int32)
            threshold = np.asarray(d["threshold"], np.float64)
            left = np.asarray(d["left"], np.int32)
            right = np.asarray(d["right"], np.int32)
            value = np.asarray(d["value"], np.float64)
            roots = np.asarray(d["roots"], np.int32)
            offset, rate, depth = float(d["offset"]), float(d["rate"]), int(d["depth"])
        except (KeyError, TypeError, ValueError, OverflowError) as exc:
            raise TopsegError(f"the person check's trees are malformed ({exc})") from None
        n = feature.size
        arrays = (feature, threshold, left, right, value, roots)
        if (
            n == 0
            or any(a.ndim != 1 for a in arrays)
            or not all(a.size == n for a in (threshold, left, right, value))
        ):
            raise TopsegError("the person check's tree arrays differ in length")
        inner = feature >= 0
        if (
            roots.size == 0
            or feature.max() >= n_features
            or feature.min() < -1
            or roots.min() < 0
            or roots.max() >= n
            or (inner & ((left < 0) | (left >= n) | (right < 0) | (right >= n))).any()
            or (inner & ((left <= np.arange(n)) | (right <= np.arange(n)))).any()
            or not 0 <= depth <= 64
            or not all(map(math.isfinite, (offset, rate)))
            or not np.isfinite(value).all()
        ):
            raise TopsegError("the person check's trees read a feature or a node out of bounds")
        return cls(feature, threshold, left, right, value, roots, offset, rate, depth)


@dataclass(frozen=True)
class GroupedTrees:
    """Several `TreeEnsemble`s scored in one pass (`person_check_kernels.grouped_tree_sums`):
    their trees stacked, each laid out as deep as the deepest."""

    feature: np.ndarray
    threshold: np.ndarray
    value: np.ndarray
    group: np.ndarray  # the ensemble of each tree
    offsets: np.ndarray
    rates: np.ndarray

    @classmethod
    def of(cls, ensembles: tuple[TreeEnsemble, ...]) -> GroupedTrees:
        """The ensembles' trees, stacked in order."""
        depth = max(int(np.log2(e.complete[2].shape[1])) for e in ensembles)
        laid = [deepened(e.complete, depth) for e in ensembles]
        return cls(
            np.concatenate([f for f, _, _ in laid]),
            np.concatenate([t for _, t, _ in laid]),
            np.concatenate([v for _, _, v in laid]),
            np.concatenate([np.full(len(f), i, np.int64) for i, (f, _, _) in enumerate(laid)]),
            np.array([e.offset for e in ensembles]),
            np.array([e.rate for e in ensembles]),
        )

    def scores(self, x: np.ndarray) -> np.ndarray:
        """(n, ensembles) each ensemble's scores of the (n, F) feature rows `x`, equal to
        its own `TreeEnsemble.score`."""
        x = np.ascontiguousarray(np.asarray(x, np.float32), np.float64)
        sums = K.grouped_tree_sums(
            x, self.feature, self.threshold, self.value, self.group, len(self.offsets)
        )
        return self.offsets + self.rates * sums


@dataclass(frozen=True)
class PersonCheck:
    """A fitted check: blobs whose `TreeEnsemble` score is below `threshold` (a logit) are
    not people. `validation` holds what the fit measured on its held-out frames."""

    trees: TreeEnsemble
    threshold: float
    validation: dict

    #: the model header's key
    HEADER_KEY = "person_check"

    def people(self, blobs: Blobs) -> np.ndarray:
        """(n,) bool: which of `blobs` are people."""
        return self.trees.score(blobs.features) >= self.threshold

    def to_header(self) -> dict[str, Any]:
        """The header entry (`HEADER_KEY`): features named, trees, threshold, validation."""
        return {
            "features": list(FEATURES),
            "threshold": self.threshold,
            "trees": self.trees.to_dict(),
            "validation": self.validation,
        }

    @classmethod
    def from_header(cls, header: dict[str, Any]) -> PersonCheck | None:
        """The check a model header carries (None: none). TopsegError when it is malformed or
        reads features this topseg does not compute."""
        entry = header.get(cls.HEADER_KEY)
        if entry is None:
            return None
        if not isinstance(entry, dict):
            raise TopsegError("the model's person check is not a table")
        if entry.get("features") != list(FEATURES):
            raise TopsegError(
                "the model's person check reads other blob features than this topseg "
                "computes (refit it: `topseg person-check`)"
            )
        return cls(*check_entry(entry, "person check", len(FEATURES)))


def finite_threshold(value: Any, what: str) -> float:
    """`value` as a finite float; TopsegError otherwise, naming `what` (e.g. "person check
    threshold")."""
    try:
        threshold = float(value)
    except (TypeError, ValueError):
        raise TopsegError(f"the model's {what} is missing or not a number") from None
    if not math.isfinite(threshold):
        raise TopsegError(f"the model's {what} is not finite")
    return threshold


def check_entry(entry: dict, what: str, n_features: int) -> tuple[TreeEnsemble, float, dict]:
    """The trees, threshold and validation of a check's model header entry (`what` names the
    check in errors); TopsegError when the threshold is missing or not finite, or the trees
    are malformed."""
    threshold = finite_threshold(entry.get("threshold"), f"{what} threshold")
    trees = TreeEnsemble.from_dict(entry.get("trees"), n_features)
    validation = entry.get("validation", {})
    return trees, threshold, validation if isinstance(validation, dict) else {}


def relabel_blobs(
    labels: np.ndarray, blobs: Blobs, people: np.ndarray, proba: np.ndarray
) -> tuple[int, int]:
    """Give every pixel of a blob that is not a person (`people` False) its most probable
    class that is neither a body part nor background (it stands above the floor: the floor
    gate passed it), in place; (blobs, pixels) relabelled."""
    rejected = np.flatnonzero(~people)
    if rejected.size == 0:
        return 0, 0
    is_rejected = np.zeros(blobs.count + 1, bool)
    is_rejected[rejected + 1] = True
    pixels = K.relabel_rejected(labels, blobs.image, is_rejected, proba, REPLACEMENT)
    return int(rejected.size), int(pixels)


def warm_up_check(depth: np.ndarray, check: PersonCheck) -> None:
    """Compile (or load from numba's cache) the check's kernels on a small frame of `depth`'s
    shape with a body-part blob, writable and read-only (as frames off the wire are)."""
    labels = np.full(depth.shape, L.OBJECT, np.uint8)
    labels[: depth.shape[0] // 2, : depth.shape[1] // 2] = L.BODY
    proba = np.full((*depth.shape, L.NUM_CLASSES), 1.0 / L.NUM_CLASSES, np.float32)
    heights = np.full(depth.shape, 1000.0, np.float32)
    read_only = np.full(depth.shape, 2000, np.uint16)
    read_only.flags.writeable = False
    rows, cols = depth.shape
    k = Intrinsics(cols, rows, 500.0, 500.0, cols / 2, rows / 2)
    for frame in (np.full(depth.shape, 2000, np.uint16), read_only):
        blobs = blob_features(labels, frame, heights, proba, k, 3000.0)
        relabel_blobs(labels.copy(), blobs, np.zeros(blobs.count, bool), proba)
        check.people(blobs)


__all__ = [
    "FEATURES",
    "IS_PART",
    "MAX_TREE_DEPTH",
    "REPLACEMENT",
    "Blobs",
    "GroupedTrees",
    "PersonCheck",
    "TreeEnsemble",
    "blob_features",
    "check_entry",
    "complete_trees",
    "deepened",
    "finite_threshold",
    "relabel_blobs",
    "warm_up_check",
]
