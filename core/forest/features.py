"""Shotton depth-difference features and the two feature response functions.

A feature is a pair of offsets (u, v), each (row, col) in pixel*millimetres. At a pixel s
it reads

    f(s) = p(s + u * S(s)) - p(s + v * S(s))

where p(q) is the model input's probe value at q and S(s) the pixel's offset scale
(`inputs.ModelInput`: for a height model p is C - height above the floor and
S = (fx / reference_focal_px) / d(s); for a legacy model p is depth and S = 1 / d(s)). The
probe position is rounded to the nearest pixel (floor(x + 0.5)), and a probe on a no-depth
pixel reads the large constant `background_mm` (so does any value above it: probes are
clamped to it, which keeps every response inside int16; so does a v offset of `FAR_OFFSET`
or more, an absolute feature's, wherever it is applied). A probe outside the image reads
the pixel on the image's edge nearest to it (`FeatureConfig.off_image` "nearest": a surface
cut by the image's edge reads as going on beyond it), or `background_mm` ("background",
what a model whose header lacks `off_image` reads): then a person cut by the edge reads as
ending there, and the top of a cut torso looks like a head. Dividing by
d(s) makes the feature depth invariant and the focal-length ratio sensor invariant: the
offsets span the same metric distance at any depth and on any camera, `patch_px` pixels at
`reference_depth_mm` on a camera of the reference focal length.

Response functions (Criminisi & Shotton's decision-forest framework):
- axis-aligned: one feature against a threshold;
- linear: a random unit vector w over k features of the pool, sum_j w_j f_j(s), against a
  threshold.
Both are "sum_j w_j f_j(s)" with k = 1, w = 1 for axis-aligned, so one kernel serves both.
Responses are float32 and accumulated in float32 in the same order at training (from the
int16 feature matrix) and at inference (from probes), so both sides see identical values.
"""

from __future__ import annotations

import numba
import numpy as np

from topseg.core.forest.feature_config import FeatureConfig
from topseg.core.forest.inputs import ModelInput, as_input, check_input

#: a v offset no image reaches: the probe reads `background_mm`, so f = p(s + u/d) - background
OFF_IMAGE = 1.0e9
#: a v offset with a component at least this large (pixel*mm; OFF_IMAGE is one) reads
#: `background_mm` by definition, whatever the pixel's offset scale: off every image, not only
#: off the images seen so far, so that inference may skip computing where it lands
FAR_OFFSET = OFF_IMAGE / 2


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
def probe(values, r, c, inv_d, dr, dc, background, nearest):
    """Value read at the probe (r, c) + round((dr, dc) * inv_d), or `background`.

    `values` is the model input's probe image (`inputs.ModelInput.probe_values`: depth
    for a legacy model) and `inv_d` the pixel's offset scale (`ModelInput.scale[r, c]`). A probe
    outside the image reads the nearest pixel on its edge when `nearest`, else
    `background`. All arithmetic is float32, identical in every kernel and in the numpy
    references.
    """
    pr = r + np.int64(np.floor(dr * inv_d + np.float32(0.5)))
    pc = c + np.int64(np.floor(dc * inv_d + np.float32(0.5)))
    if pr < 0 or pc < 0 or pr >= values.shape[0] or pc >= values.shape[1]:
        if not nearest:
            return background
        pr = min(max(pr, 0), values.shape[0] - 1)
        pc = min(max(pc, 0), values.shape[1] - 1)
    z = np.int32(values[pr, pc])
    if z == 0 or z > background:
        return background
    return z


@numba.njit(cache=True, inline="always")
def is_far(dr, dc):
    """Whether a v offset reads `background_mm` wherever it is applied (`FAR_OFFSET`)."""
    return abs(dr) >= FAR_OFFSET or abs(dc) >= FAR_OFFSET


@numba.njit(cache=True, inline="always")
def pair_feature(values, r, c, inv_d, offset, background, nearest):
    """f(s) for one offset row (u_row, u_col, v_row, v_col) at pixel (r, c); a far v
    (`is_far`) reads `background`."""
    u = probe(values, r, c, inv_d, offset[0], offset[1], background, nearest)
    if is_far(offset[2], offset[3]):
        return u - background
    return u - probe(values, r, c, inv_d, offset[2], offset[3], background, nearest)


@numba.njit(cache=True, inline="always")
def response_at(values, r, c, inv_d, offsets, weights, background, nearest):
    """sum_j w_j f_j(s) in float32: the response of one node at pixel (r, c).

    `offsets` is (k, 4), `weights` (k,); `inv_d` is the pixel's offset scale.
    """
    acc = np.float32(0.0)
    for j in range(offsets.shape[0]):
        f = pair_feature(values, r, c, inv_d, offsets[j], background, nearest)
        acc += weights[j] * np.float32(f)
    return acc


@numba.njit(cache=True, parallel=True)
def _extract(values, scale, rows, cols, offsets, background, nearest, out):
    for i in numba.prange(rows.shape[0]):
        r, c = rows[i], cols[i]
        inv_d = scale[r, c]
        for f in range(offsets.shape[0]):
            out[i, f] = pair_feature(values, r, c, inv_d, offsets[f], background, nearest)


def extract_features(
    frame: np.ndarray | ModelInput,
    rows: np.ndarray,
    cols: np.ndarray,
    offsets: np.ndarray,
    background_mm: int,
    out: np.ndarray | None = None,
    nearest: bool = False,
) -> np.ndarray:
    """The (n, PC) int16 feature matrix of pixels (rows[i], cols[i]) of one frame.

    `frame` is a model input (`inputs.model_input`), or a depth frame read as its legacy
    input (V = depth, scale = 1/depth). Every pixel must have a value (> 0); training
    samples only such pixels. `out`, if given, is an (n, PC) int16 array (e.g. a slice of a
    larger matrix) filled in place. `nearest`: a probe off the image reads the nearest edge
    pixel (`FeatureConfig.nearest_off_image`), else `background_mm`.
    """
    inp = check_input(as_input(frame), "features")
    values = inp.probe_values
    rows = np.asarray(rows, np.int64)
    cols = np.asarray(cols, np.int64)
    offsets = np.ascontiguousarray(offsets, np.float32)
    if rows.shape != cols.shape or rows.ndim != 1:
        raise ValueError(f"rows and cols must be equal 1-D arrays, got {rows.shape} {cols.shape}")
    if rows.size and (
        rows.min() < 0
        or cols.min() < 0
        or rows.max() >= values.shape[0]
        or cols.max() >= values.shape[1]
    ):
        raise ValueError("sample pixels outside the frame")
    if rows.size and np.any(values[rows, cols] == 0):
        raise ValueError("sample pixels must have depth (> 0)")
    if out is None:
        out = np.empty((rows.size, offsets.shape[0]), np.int16)
    elif out.shape != (rows.size, offsets.shape[0]) or out.dtype != np.int16:
        raise ValueError(f"out must be int16 {(rows.size, offsets.shape[0])}, got {out.shape}")
    _extract(values, inp.scale, rows, cols, offsets, np.int32(background_mm), bool(nearest), out)
    return out


@numba.njit(cache=True, parallel=True)
def _node_response_image(values, probes, scale, offsets, weights, background, nearest, out):
    for r in numba.prange(values.shape[0]):
        for c in range(values.shape[1]):
            if values[r, c] == 0:
                out[r, c] = np.nan
            else:
                inv_d = scale[r, c]
                out[r, c] = response_at(probes, r, c, inv_d, offsets, weights, background, nearest)


def node_response_image(
    frame: np.ndarray | ModelInput,
    offsets: np.ndarray,
    weights: np.ndarray,
    background_mm: int,
    nearest: bool = False,
) -> np.ndarray:
    """(H, W) float32 response of one node (k offsets, k weights) at every pixel; NaN: no depth.

    `frame` and `nearest` as for `extract_features`. For inspecting a split and for tests;
    inference walks the trees without it.
    """
    inp = check_input(as_input(frame), "features")
    offsets = np.ascontiguousarray(np.atleast_2d(offsets), np.float32)
    weights = np.ascontiguousarray(np.atleast_1d(weights), np.float32)
    if offsets.shape != (weights.shape[0], 4):
        raise ValueError(f"offsets must be (k, 4) for k weights, got {offsets.shape}")
    out = np.empty(inp.values.shape, np.float32)
    background = np.int32(background_mm)
    _node_response_image(
        inp.values, inp.probe_values, inp.scale, offsets, weights, background, bool(nearest), out
    )
    return out


def random_unit_vectors(rng: np.random.Generator, n: int, k: int) -> np.ndarray:
    """(n, k) float32 unit vectors, uniform on the sphere (normalised Gaussians)."""
    w = rng.normal(size=(n, k))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    return w.astype(np.float32)
