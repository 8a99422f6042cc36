"""Shotton depth-difference features and the two feature response functions.

A feature is a pair of offsets (u, v), each (row, col) in pixel*millimetres. At a pixel s
with depth d(s) (mm) it reads

    f(s) = p(s + u / d(s)) - p(s + v / d(s))

where p(q) is the depth at probe q, the probe position is rounded to the nearest pixel
(floor(x + 0.5)), and a probe outside the image or on a no-depth pixel reads the large
constant `background_mm` (so does any depth above it: probes are clamped to it, which keeps
every response inside int16). Dividing by d(s) makes the feature depth invariant: the
offsets span the same metric distance at any depth, and `patch_px` pixels at
`reference_depth_mm`.

Response functions (Criminisi & Shotton's decision-forest framework):
- axis-aligned: one feature against a threshold;
- linear: a random unit vector w over k features of the pool, sum_j w_j f_j(s), against a
  threshold.
Both are "sum_j w_j f_j(s)" with k = 1, w = 1 for axis-aligned, so one kernel serves both.
Responses are float32 and accumulated in float32 in the same order at training (from the
int16 feature matrix) and at inference (from probes), so both sides see identical values.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numba
import numpy as np

from topseg.core.camera import check_depth


@dataclass(frozen=True)
class FeatureConfig:
    """The feature pool drawn per tree.

    n_features: PC, the pool size (paper: 300).
    patch_px: side of the square patch the offsets stay within at the reference depth
        (paper: 64, so |u|, |v| <= 32 px per axis).
    reference_depth_mm: depth at which `patch_px` is measured; ~2500 mm is the height of a
        person's shoulders and table tops in a 3.5 m top view.
    background_mm: what a probe off the image or on no depth reads; larger than any depth.
    absolute_fraction: share of the pool whose v offset points off every image, so that
        f(s) = p(s + u/d(s)) - background_mm: the probe's depth against a fixed value, i.e.
        its height above the floor for a fixed top-view mount. Not in the paper (0 keeps
        its pure depth differences, which cannot tell a table's flat interior from the
        floor); 0.2 lifts procedural-scene pixel accuracy from ~0.86 to ~0.97
        (tests/test_forest_learn.py). It gives up depth invariance for those features.
    """

    n_features: int = 300
    patch_px: int = 64
    reference_depth_mm: float = 2500.0
    background_mm: int = 10000
    absolute_fraction: float = 0.0

    def __post_init__(self) -> None:
        if self.n_features < 1:
            raise ValueError(f"n_features must be >= 1, got {self.n_features}")
        if self.patch_px < 2:
            raise ValueError(f"patch_px must be >= 2, got {self.patch_px}")
        if self.reference_depth_mm <= 0:
            raise ValueError(f"reference_depth_mm must be > 0, got {self.reference_depth_mm}")
        if not 0.0 <= self.absolute_fraction <= 1.0:
            raise ValueError(f"absolute_fraction must be in [0, 1], got {self.absolute_fraction}")
        if not 0 < self.background_mm <= 16000:
            # clamped probes differ by at most background_mm, which must fit in int16
            raise ValueError(f"background_mm must be in (0, 16000], got {self.background_mm}")

    @property
    def max_offset(self) -> float:
        """Largest |offset| component, pixel*mm."""
        return self.patch_px / 2 * self.reference_depth_mm

    def to_dict(self) -> dict:
        """The config as a plain dict (`from_dict` reads it back)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict, source: str = "feature config") -> FeatureConfig:
        """The config in `d` (`to_dict`'s form); a key missing takes its default, an unknown or
        mistyped one is a ConfigError naming it."""
        from topseg.core.config import from_dict

        return from_dict(cls, d, source)


#: a v offset no image reaches: the probe reads `background_mm`, so f = p(s + u/d) - background
OFF_IMAGE = 1.0e9


def sample_offsets(config: FeatureConfig, rng: np.random.Generator) -> np.ndarray:
    """Draw a feature pool: (PC, 4) float32 rows (u_row, u_col, v_row, v_col), pixel*mm.

    Each component is uniform in [-max_offset, max_offset], so both probes fall in the
    `patch_px` square around the pixel at the reference depth; for `absolute_fraction` of
    the rows v is `OFF_IMAGE` instead (see `FeatureConfig`).
    """
    m = config.max_offset
    off = rng.uniform(-m, m, size=(config.n_features, 4))
    absolute = rng.random(config.n_features) < config.absolute_fraction
    off[absolute, 2:] = OFF_IMAGE
    return off.astype(np.float32)


@numba.njit(cache=True, inline="always")
def probe(depth, r, c, inv_d, dr, dc, background):
    """Depth read at the probe (r, c) + round((dr, dc) * inv_d), or `background`.

    All arithmetic is float32 (`inv_d` = float32(1) / float32(d(s))), identical in every
    kernel and in the numpy references.
    """
    pr = r + np.int64(np.floor(dr * inv_d + np.float32(0.5)))
    pc = c + np.int64(np.floor(dc * inv_d + np.float32(0.5)))
    if pr < 0 or pc < 0 or pr >= depth.shape[0] or pc >= depth.shape[1]:
        return background
    z = np.int32(depth[pr, pc])
    if z == 0 or z > background:
        return background
    return z


@numba.njit(cache=True, inline="always")
def inverse_depth(d):
    """float32(1) / float32(d): the scale every probe of a pixel uses."""
    return np.float32(1.0) / np.float32(d)


@numba.njit(cache=True, inline="always")
def pair_feature(depth, r, c, inv_d, offset, background):
    """f(s) for one offset row (u_row, u_col, v_row, v_col) at pixel (r, c)."""
    return probe(depth, r, c, inv_d, offset[0], offset[1], background) - probe(
        depth, r, c, inv_d, offset[2], offset[3], background
    )


@numba.njit(cache=True, inline="always")
def response_at(depth, r, c, inv_d, offsets, weights, background):
    """sum_j w_j f_j(s) in float32: the response of one node at pixel (r, c).

    `offsets` is (k, 4), `weights` (k,); `inv_d` = `inverse_depth(d(s))`.
    """
    acc = np.float32(0.0)
    for j in range(offsets.shape[0]):
        acc += weights[j] * np.float32(pair_feature(depth, r, c, inv_d, offsets[j], background))
    return acc


@numba.njit(cache=True, parallel=True)
def _extract(depth, rows, cols, offsets, background, out):
    for i in numba.prange(rows.shape[0]):
        r, c = rows[i], cols[i]
        inv_d = inverse_depth(depth[r, c])
        for f in range(offsets.shape[0]):
            out[i, f] = pair_feature(depth, r, c, inv_d, offsets[f], background)


def extract_features(
    depth: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    offsets: np.ndarray,
    background_mm: int,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """The (n, PC) int16 feature matrix of pixels (rows[i], cols[i]) of one frame.

    Every pixel must have depth (> 0); training samples only such pixels. `out`, if given,
    is an (n, PC) int16 array (e.g. a slice of a larger matrix) filled in place.
    """
    depth = check_depth(depth, "features")
    rows = np.asarray(rows, np.int64)
    cols = np.asarray(cols, np.int64)
    offsets = np.ascontiguousarray(offsets, np.float32)
    if rows.shape != cols.shape or rows.ndim != 1:
        raise ValueError(f"rows and cols must be equal 1-D arrays, got {rows.shape} {cols.shape}")
    if rows.size and (
        rows.min() < 0
        or cols.min() < 0
        or rows.max() >= depth.shape[0]
        or cols.max() >= depth.shape[1]
    ):
        raise ValueError("sample pixels outside the frame")
    if rows.size and np.any(depth[rows, cols] == 0):
        raise ValueError("sample pixels must have depth (> 0)")
    if out is None:
        out = np.empty((rows.size, offsets.shape[0]), np.int16)
    elif out.shape != (rows.size, offsets.shape[0]) or out.dtype != np.int16:
        raise ValueError(f"out must be int16 {(rows.size, offsets.shape[0])}, got {out.shape}")
    _extract(depth, rows, cols, offsets, np.int32(background_mm), out)
    return out


@numba.njit(cache=True, parallel=True)
def _node_response_image(depth, offsets, weights, background, out):
    for r in numba.prange(depth.shape[0]):
        for c in range(depth.shape[1]):
            d = depth[r, c]
            if d == 0:
                out[r, c] = np.nan
            else:
                inv_d = inverse_depth(d)
                out[r, c] = response_at(depth, r, c, inv_d, offsets, weights, background)


def node_response_image(
    depth: np.ndarray, offsets: np.ndarray, weights: np.ndarray, background_mm: int
) -> np.ndarray:
    """(H, W) float32 response of one node (k offsets, k weights) at every pixel; NaN: no depth.

    For inspecting a split and for tests; inference walks the trees without it.
    """
    depth = check_depth(depth, "features")
    offsets = np.ascontiguousarray(np.atleast_2d(offsets), np.float32)
    weights = np.ascontiguousarray(np.atleast_1d(weights), np.float32)
    if offsets.shape != (weights.shape[0], 4):
        raise ValueError(f"offsets must be (k, 4) for k weights, got {offsets.shape}")
    out = np.empty(depth.shape, np.float32)
    _node_response_image(depth, offsets, weights, np.int32(background_mm), out)
    return out


def random_unit_vectors(rng: np.random.Generator, n: int, k: int) -> np.ndarray:
    """(n, k) float32 unit vectors, uniform on the sphere (normalised Gaussians)."""
    w = rng.normal(size=(n, k))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    return w.astype(np.float32)
