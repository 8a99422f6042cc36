"""Edge-preserving smoothing of noisy depth before the forest reads it.

A stereo camera's depth error grows with z^2: 1 sigma is 51 mm for a RealSense D435 at
3.5 m and 85 mm at 4.5 m, as thick as an arm. Their makers ship an edge-preserving spatial
filter for this (librealsense's `spatial_filter`, a recursive domain-transform filter after
Gastal & Oliveira 2011; Luxonis' `SpatialFilter`); topseg applies the same kind of filter to
frames from a camera whose noise at the floor is at least `MIN_SIGMA_MM`:

- each pass runs along every row left to right, then right to left, then along every column
  top down and bottom up; a pixel takes `ALPHA` of its own depth and 1 - `ALPHA` of its
  already smoothed neighbour, when both have depth and differ by less than `SIGMAS` sigma of
  the sensor's noise at the pixel's depth (`sensors.depth_sigma_mm`, times the mount's
  measured `noise_scale`). A larger difference is an edge: the smoothing stops there, so a
  person's outline and a table's edge stay where they are;
- pixels without depth stay without depth (the Segmenter fills small holes inside one
  surface before, `core/holes.py`; the smoothing does not);
- `ITERATIONS` passes; a frame being labelled whose noise at the floor is `HEAVY_SIGMA_MM`
  or more (a D435 from ~4.25 m up) gets `HEAVY_ITERATIONS`. Training keeps
  `ITERATIONS` for every frame: a forest trained on the noisier input and shown the cleaner
  one labels those frames better than one trained and shown the same (`docs/explanation/noise.md`).

Quieter cameras (a Kinect v1 below ~4.3 m, time-of-flight) are left as they are: their noise
is below the depth steps the filter could remove. Measured in `docs/explanation/noise.md`.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING

import numba
import numpy as np

from topseg.core.sensors import depth_sigma_mm

if TYPE_CHECKING:
    from topseg.core.camera import TopViewMount

#: smallest 1-sigma depth noise (mm) at the floor for which a frame is smoothed
MIN_SIGMA_MM = 20.0
#: an edge: neighbours that differ by this many sigma of the sensor's noise or more
SIGMAS = 2.0
#: the share of its own depth a smoothed pixel keeps
ALPHA = 0.25
#: passes of the four directions
ITERATIONS = 2
#: smallest 1-sigma depth noise (mm) at the floor for which a frame being labelled gets
#: HEAVY_ITERATIONS passes: a D435 from ~4.25 m up; an OAK-D only when noisier than its
#: model (65 mm at 4.5 m, where a third pass did not pay: docs/explanation/noise.md)
HEAVY_SIGMA_MM = 75.0
#: passes of the four directions for such a frame (training keeps ITERATIONS)
HEAVY_ITERATIONS = 3
#: pixels per thread in a column pass
_COLUMN_CHUNK = 64


def needs_denoise(mount: TopViewMount) -> bool:
    """Whether frames from `mount` are smoothed: `floor_sigma_mm(mount)` >= MIN_SIGMA_MM."""
    return floor_sigma_mm(mount) >= MIN_SIGMA_MM


def floor_sigma_mm(mount: TopViewMount) -> float:
    """1 sigma of the mount's depth noise (mm) at the floor straight below the camera: its
    sensor's model at the camera's height, times the mount's `noise_scale`."""
    sigma = depth_sigma_mm(np.float32(mount.height_mm), mount.sensor)
    return float(sigma) * float(mount.noise_scale)


def smoothing_text(mount: TopViewMount) -> str:
    """', depth smoothed (noise 85 mm at the floor)' for a mount whose frames are smoothed,
    '' otherwise: what logs and printed mounts add."""
    if not needs_denoise(mount):
        return ""
    return f", depth smoothed (noise {floor_sigma_mm(mount):.0f} mm at the floor)"


@functools.lru_cache(maxsize=16)
def edge_table(sensor: str, noise_scale: float) -> np.ndarray:
    """The edge threshold (mm, float32) at every uint16 depth: SIGMAS sigma of the sensor's
    noise times `noise_scale`; 0 at depth 0 (no pixel without depth is smoothed)."""
    sigma = depth_sigma_mm(np.arange(65536, dtype=np.float32), sensor)
    table = (np.float32(SIGMAS * noise_scale) * sigma).astype(np.float32)
    table[0] = 0.0
    table.flags.writeable = False
    return table


def passes(mount: TopViewMount, for_training: bool = False) -> int:
    """How many passes `denoise` makes over frames from `mount` (0: not smoothed):
    HEAVY_ITERATIONS for a frame being labelled with `floor_sigma_mm(mount)` >=
    HEAVY_SIGMA_MM, else ITERATIONS for a noisy camera's (`needs_denoise`)."""
    if not needs_denoise(mount):
        return 0
    heavy = not for_training and floor_sigma_mm(mount) >= HEAVY_SIGMA_MM
    return HEAVY_ITERATIONS if heavy else ITERATIONS


def denoise(depth: np.ndarray, mount: TopViewMount, for_training: bool = False) -> np.ndarray:
    """`depth` (uint16 mm) smoothed as the module says with `passes(mount, for_training)`
    passes, or `depth` itself (not copied) when that is 0."""
    n = passes(mount, for_training)
    if n == 0:
        return depth
    return smooth_depth(depth, edge_table(mount.sensor, float(mount.noise_scale)), iterations=n)


def smooth_depth(
    depth: np.ndarray, edge_mm: np.ndarray, alpha: float = ALPHA, iterations: int = ITERATIONS
) -> np.ndarray:
    """The filter itself: `depth` (uint16, C-contiguous) smoothed with `edge_mm` (float32,
    indexed by each pixel's own raw depth) as the edge threshold; a new uint16 frame,
    rounded to the nearest mm, zero where `depth` is zero."""
    depth = np.ascontiguousarray(depth, np.uint16)
    edge_mm = np.ascontiguousarray(edge_mm, np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth must be 2-D, got shape {depth.shape}")
    if edge_mm.shape != (65536,):  # the kernels index it by any uint16 depth, unchecked
        raise ValueError(f"edge_mm must have 65536 entries, got shape {edge_mm.shape}")
    if depth.size == 0:
        return depth.copy()
    x = depth.astype(np.float32)
    a = np.float32(alpha)
    b = np.float32(1.0) - a
    for _ in range(iterations):
        _rows(x, depth, edge_mm, a, b)
        _columns(x, depth, edge_mm, a, b)
    out = np.empty_like(depth)
    _round(x, depth, out)
    return out


@numba.njit(cache=True, inline="always")
def _blend(x, depth, edge, r, c, prev, a, b):
    """x[r, c] after one step from its neighbour's smoothed depth `prev` (0: no depth)."""
    v = x[r, c]
    if prev > 0 and v > 0 and abs(v - prev) < edge[depth[r, c]]:
        v = a * v + b * prev
        x[r, c] = v
    return v


@numba.njit(cache=True, parallel=True)
def _rows(x, depth, edge, a, b):
    """One left-to-right and one right-to-left pass over every row (rows in parallel)."""
    h, w = x.shape
    for r in numba.prange(h):
        prev = x[r, 0]
        for c in range(1, w):
            prev = _blend(x, depth, edge, r, c, prev, a, b)
        prev = x[r, w - 1]
        for c in range(w - 2, -1, -1):
            prev = _blend(x, depth, edge, r, c, prev, a, b)


@numba.njit(cache=True, parallel=True)
def _columns(x, depth, edge, a, b):
    """One top-down and one bottom-up pass over every column: a thread takes a band of
    _COLUMN_CHUNK columns and walks it row by row, so it reads memory in rows; a row's steps
    are independent, and a select in place of `_blend`'s branch makes this pass ~20 %
    faster."""
    h, w = x.shape
    chunks = (w + _COLUMN_CHUNK - 1) // _COLUMN_CHUNK
    for k in numba.prange(chunks):
        c0 = k * _COLUMN_CHUNK
        c1 = min(c0 + _COLUMN_CHUNK, w)
        for r in range(1, h):
            for c in range(c0, c1):
                _select(x, depth, edge, r, c, x[r - 1, c], a, b)
        for r in range(h - 2, -1, -1):
            for c in range(c0, c1):
                _select(x, depth, edge, r, c, x[r + 1, c], a, b)


@numba.njit(cache=True, inline="always")
def _select(x, depth, edge, r, c, prev, a, b):
    """`_blend` without a branch (its result not returned)."""
    v = x[r, c]
    ok = (prev > 0) & (v > 0) & (abs(v - prev) < edge[depth[r, c]])
    x[r, c] = a * v + b * prev if ok else v


@numba.njit(cache=True, parallel=True)
def _round(x, depth, out):
    """out = x rounded half up to uint16 (at least 1 mm), 0 where depth is 0."""
    h, w = x.shape
    for r in numba.prange(h):
        for c in range(w):
            if depth[r, c] == 0:
                out[r, c] = 0
            else:
                out[r, c] = np.uint16(min(max(np.floor(x[r, c] + np.float32(0.5)), 1.0), 65535.0))
