"""The person check: is each blob of body-part labels a person, or part of something else?

The forest labels pixels one at a time, so the top of a robot link, a drum or a cabinet can
come out as `body` or `head`. Seen as a whole, such a blob is unlike a person: its size, its
height profile, what surrounds it and the forest's posteriors over all of it differ. After the
CRF, every 8-connected blob of body-part labels is described by `FEATURES` (`blob_features`)
and scored by a small boosted tree ensemble the model file carries (`PersonCheck`, fitted by
`topseg person-check` on the model's own labels of rendered cells); a blob scoring under the
check's threshold is not a person, and its pixels take their most probable class that is not
a body part (`relabel_blobs`).

Everything here is pure numpy and scipy.ndimage on the working resolution's arrays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage

from topseg.core import labels as L
from topseg.core.errors import TopsegError

#: how blobs connect: 8-neighbours, as the island rules and the open-world report count them
EIGHT = np.ones((3, 3), bool)
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


def pixel_area_cm2(depth_mm: np.ndarray, fx: float, fy: float) -> np.ndarray:
    """Each pixel's footprint (cm2) on a surface facing the camera at its depth; 0 without
    depth."""
    z_cm = depth_mm.astype(np.float64) / 10.0
    return z_cm * z_cm / (fx * fy)


def blob_features(
    labels: np.ndarray,
    depth_mm: np.ndarray,
    heights_mm: np.ndarray,
    proba: np.ndarray,
    intrinsics,
    camera_height_mm: float,
) -> Blobs:
    """Every body-part blob of `labels` and its `FEATURES` row.

    labels      (h, w) uint8 class ids after the CRF
    depth_mm    (h, w) depth (0: none); heights_mm (h, w) height above the floor (NaN: none)
    proba       (h, w, C) forest posteriors, stored at least at every body-part pixel
    intrinsics  the optics at this resolution (fx, fy, cx, cy)
    """
    human = np.isin(labels, _PARTS)
    image, n = ndimage.label(human, structure=EIGHT)
    if n == 0:
        return Blobs(image, np.zeros((0, len(FEATURES))), np.zeros(0))
    index = np.arange(1, n + 1)
    flat = image.ravel()
    valid = depth_mm > 0
    area = pixel_area_cm2(depth_mm, intrinsics.fx, intrinsics.fy)
    h = np.where(valid, np.nan_to_num(heights_mm, nan=0.0), 0.0).astype(np.float64)

    def per_blob(weights: np.ndarray) -> np.ndarray:
        return np.bincount(flat, weights.ravel(), n + 1)[1:]

    blob_area = per_blob(area)
    safe_area = np.maximum(blob_area, 1e-9)
    pixels = np.maximum(np.bincount(flat, minlength=n + 1)[1:], 1)
    h_max = _extreme(ndimage.maximum, np.where(valid, h, -np.inf), image, index)
    h_min = _extreme(ndimage.minimum, np.where(valid, h, np.inf), image, index)
    h_mean = per_blob(area * h) / safe_area
    h_std = np.sqrt(np.maximum(per_blob(area * h * h) / safe_area - h_mean**2, 0.0))
    top = np.zeros_like(h)
    inside = image > 0
    top[inside] = h[inside] > h_max[image[inside] - 1] - TOP_MM
    top_share = per_blob(area * top) / safe_area
    parts = np.stack([per_blob(area * (labels == c)) / safe_area for c in _PARTS], axis=1)
    posterior = np.zeros((n, POSTERIOR_COLUMNS))
    for c in range(min(proba.shape[-1], POSTERIOR_COLUMNS)):
        posterior[:, c] = per_blob(np.where(inside, proba[..., c], 0.0)) / pixels
    head = labels == L.HEAD
    head_area = per_blob(area * head)
    head_h = per_blob(area * head * h) / np.maximum(head_area, 1e-9)
    head_below = np.where(head_area > 0, head_h - h_max, NO_HEAD_MM)
    major, minor = _extents(depth_mm, area, flat, n, intrinsics)
    ring = _ring_features(labels, valid, h, image, index, h_max)
    component = _component_features(labels, valid, area, image, index, blob_area)
    features = np.column_stack([
        np.log1p(blob_area), h_max, h_mean, h_std, h_min, h_max - h_min, top_share,
        parts, (parts > PART_PRESENT).sum(axis=1),
        posterior, posterior[:, list(_PARTS)].sum(axis=1),
        posterior[:, list(L.FURNITURE_IDS)].sum(axis=1),
        np.log1p(head_area), head_below,
        major, minor, major / np.maximum(minor, MIN_EXTENT_M),
        ring, component,
        np.full(n, camera_height_mm), np.full(n, camera_height_mm / intrinsics.fx),
    ])  # fmt: skip
    return Blobs(image, np.nan_to_num(features, nan=0.0, posinf=1e30, neginf=-1e30), blob_area)


def _extreme(fn, values: np.ndarray, image: np.ndarray, index: np.ndarray) -> np.ndarray:
    """ndimage's per-blob max or min of `values`; 0 for a blob without a finite value."""
    out = np.asarray(fn(values, image, index), np.float64)
    return np.where(np.isfinite(out), out, 0.0)


def _extents(depth_mm, area, flat, n, k) -> tuple[np.ndarray, np.ndarray]:
    """Each blob's spread on the floor (m): the square roots of its points' covariance's
    eigenvalues (area-weighted), major first."""
    rows, cols = np.indices(depth_mm.shape)
    z = depth_mm.astype(np.float64) / 1000.0
    x, y = (cols - k.cx) * z / k.fx, (rows - k.cy) * z / k.fy
    w = np.bincount(flat, area.ravel(), n + 1)[1:]
    w = np.maximum(w, 1e-9)

    def mean(v):
        return np.bincount(flat, (area * v).ravel(), n + 1)[1:] / w

    mx, my = mean(x), mean(y)
    sxx, syy, sxy = mean(x * x) - mx * mx, mean(y * y) - my * my, mean(x * y) - mx * my
    half_trace = (sxx + syy) / 2
    root = np.sqrt(np.maximum(((sxx - syy) / 2) ** 2 + sxy * sxy, 0.0))
    return np.sqrt(np.maximum(half_trace + root, 0.0)), np.sqrt(np.maximum(half_trace - root, 0.0))


def _ring_features(labels, valid, h, image, index, h_max) -> np.ndarray:
    """What lies within RING_PX pixels around each blob: shares of robot, object, furniture,
    background and no depth, its mean height, how far its highest point is above the blob's,
    and the share of it that is tall."""
    n = len(index)
    grown = ndimage.grey_dilation(image, size=(2 * RING_PX + 1, 2 * RING_PX + 1))
    ring = np.where(image == 0, grown, 0)
    flat = ring.ravel()

    def count(mask):
        return np.bincount(flat, mask.ravel().astype(np.float64), n + 1)[1:]

    total = np.maximum(count(ring > 0), 1.0)
    with_depth = count(valid)
    safe_depth = np.maximum(with_depth, 1.0)
    highest = _extreme(ndimage.maximum, np.where(valid, h, -np.inf), ring, index)
    return np.column_stack([
        count(labels == L.ROBOT) / total,
        count(labels == L.OBJECT) / total,
        count(np.isin(labels, L.FURNITURE_IDS)) / total,
        count(labels == L.BACKGROUND) / total,
        count(~valid) / total,
        np.bincount(flat, (h * valid).ravel(), n + 1)[1:] / safe_depth,
        np.where(with_depth > 0, highest - h_max, 0.0),
        count(valid & (h > TALL_MM)) / safe_depth,
    ])  # fmt: skip


def _component_features(labels, valid, area, image, index, blob_area) -> np.ndarray:
    """The blob's place in the connected foreground it belongs to (everything labelled and
    not background): log of that component's area over the blob's, and the shares of it
    labelled robot, object and furniture."""
    foreground = valid & (labels != L.BACKGROUND) & (labels != L.NO_DEPTH)
    comp, m = ndimage.label(foreground, structure=EIGHT)
    flat = comp.ravel()

    def per_comp(weights):
        return np.bincount(flat, weights.ravel(), m + 1)

    comp_area = np.maximum(per_comp(area), 1e-9)
    which = np.asarray(ndimage.maximum(comp, image, index), np.int64)
    shares = [
        per_comp(area * (labels == L.ROBOT)) / comp_area,
        per_comp(area * (labels == L.OBJECT)) / comp_area,
        per_comp(area * np.isin(labels, L.FURNITURE_IDS)) / comp_area,
    ]
    ratio = np.log(comp_area[which] / np.maximum(blob_area, 1e-9))
    ratio[which == 0] = 0.0
    return np.column_stack([ratio, *(s[which] for s in shares)])


@dataclass(frozen=True)
class TreeEnsemble:
    """Boosted regression trees in flat arrays: score = offset + rate * sum of each tree's
    leaf value. A node with `feature` -1 is a leaf; otherwise rows with feature <= threshold
    (compared in float32, as scikit-learn fits them) go to `left`, the rest to `right`."""

    feature: np.ndarray  # int32
    threshold: np.ndarray  # float64
    left: np.ndarray  # int32, absolute node index
    right: np.ndarray  # int32
    value: np.ndarray  # float64
    roots: np.ndarray  # int32, the first node of each tree
    offset: float
    rate: float
    depth: int

    def score(self, x: np.ndarray) -> np.ndarray:
        """(n,) scores of the (n, F) feature rows `x`."""
        x = np.asarray(x, np.float32).astype(np.float64)
        if x.shape[0] == 0:
            return np.zeros(0)
        rows = np.arange(x.shape[0])[:, None]
        node = np.broadcast_to(self.roots, (x.shape[0], len(self.roots))).copy()
        for _ in range(self.depth):
            f = self.feature[node]
            leaf = f < 0
            go_left = x[rows, np.where(leaf, 0, f)] <= self.threshold[node]
            node = np.where(leaf, node, np.where(go_left, self.left[node], self.right[node]))
        return self.offset + self.rate * self.value[node].sum(axis=1)

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
            or not 0 <= depth <= 64
            or not all(map(math.isfinite, (offset, rate)))
            or not np.isfinite(value).all()
        ):
            raise TopsegError("the person check's trees read a feature or a node out of bounds")
        return cls(feature, threshold, left, right, value, roots, offset, rate, depth)


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
        try:
            threshold = float(entry["threshold"])
        except (KeyError, TypeError, ValueError):
            raise TopsegError("the model's person check has no threshold") from None
        if not math.isfinite(threshold):
            raise TopsegError("the model's person check threshold is not finite")
        trees = TreeEnsemble.from_dict(entry.get("trees"), len(FEATURES))
        validation = entry.get("validation", {})
        return cls(trees, threshold, validation if isinstance(validation, dict) else {})


def relabel_blobs(
    labels: np.ndarray, blobs: Blobs, people: np.ndarray, proba: np.ndarray
) -> tuple[int, int]:
    """Give every pixel of a blob that is not a person (`people` False) its most probable
    class that is not a body part, in place; (blobs, pixels) relabelled."""
    rejected = np.flatnonzero(~people)
    if rejected.size == 0:
        return 0, 0
    mask = np.isin(blobs.image, rejected + 1)
    others = np.array([c for c in range(proba.shape[-1]) if c not in _PARTS])
    labels[mask] = others[np.argmax(proba[mask][:, others], axis=1)].astype(labels.dtype)
    return int(rejected.size), int(mask.sum())


__all__ = [
    "FEATURES",
    "Blobs",
    "PersonCheck",
    "TreeEnsemble",
    "blob_features",
    "relabel_blobs",
]
