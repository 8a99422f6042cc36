"""Undo a stereo camera's edge fattening before the forest reads depth.

A stereo camera matches windows of pixels between its two imagers; where a window straddles
a depth edge, the nearer surface's texture wins and its depth bleeds over the farther one by
a pixel or two (`core.synth.noise.StereoNoise`: a pixel whose nearest surface nearer by more
than `jump_m` lies r px away takes that depth with probability `fatten`^r). From above, every
head, shoulder and arm of a person seen by such a camera is a ring of pixels wider than it
is, and that ring is what the forest labels: on the mounts table the D435 at 4.5 m kept head
precision 0.62 with fattening and 0.80 without.

topseg thins such edges by the width the camera's noise model expects (the sum of
`fatten`^r over r, rounded: 1 px for the D435 and OAK-D models): a pixel with at least
`MIN_FARTHER` neighbours within that Chebyshev radius that are farther by more than `jump_m`
takes the farthest such neighbour's depth. One such neighbour is not enough: the last pixel
of a true outline has three outside it, each left unfattened 30 % of the time. A pixel
without depth, and its neighbours without depth, are left alone.
Time-of-flight and structured-light frames are not changed, nor are a stereo camera's whose
mount says its edges are not fattened (`TopViewMount.edge_thinning` False: a camera whose own
filters already cleaned them; thinning clean edges costs accuracy). Measured in docs/explanation/noise.md
("Thinning a stereo camera's fattened edges").
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING

import numba
import numpy as np

from topseg.core.errors import TopsegError
from topseg.core.sensors import ACTIVE_STEREO, get_sensor

if TYPE_CHECKING:
    from topseg.core.camera import TopViewMount

#: neighbours farther by more than the jump that a pixel needs to be thinned
MIN_FARTHER = 2


def thinning_of(mount: TopViewMount) -> tuple[int, float]:
    """(radius px, jump mm) of the thinning frames from `mount` get: the width its stereo
    sensor's noise model fattens edges by (scaled by the frame's focal length over the
    sensor's, so a decimated frame is thinned by its own pixels) and the depth step that
    counts as an edge; (0, 0.0) for a sensor that does not fatten edges and for a mount whose
    `edge_thinning` is off."""
    if not mount.edge_thinning:
        return 0, 0.0
    return _thinning(mount.sensor, float(mount.intrinsics.fx))


@functools.lru_cache(maxsize=64)
def _thinning(sensor_name: str, fx: float) -> tuple[int, float]:
    """`thinning_of` for a sensor and a focal length (a frame is one lookup, not a parse of
    the sensor's noise spec)."""
    try:
        sensor = get_sensor(sensor_name)
    except TopsegError:  # an unknown sensor name: nothing to undo that we know of
        return 0, 0.0
    if sensor.family != ACTIVE_STEREO:
        return 0, 0.0
    noise = sensor.noise()
    expected_px = sum(noise.fatten**r for r in range(1, noise.fatten_px + 1))
    radius = round(expected_px * fx / sensor.intrinsics.fx)
    return radius, 1000.0 * noise.jump_m


def _turned_off(mount: TopViewMount) -> bool:
    """Whether `mount`'s sensor fattens edges but its `edge_thinning` is off."""
    return not mount.edge_thinning and _thinning(mount.sensor, float(mount.intrinsics.fx))[0] > 0


def thinning_text(mount: TopViewMount) -> str:
    """', edges thinned 1 px (stereo fattening)' for a mount whose frames are thinned,
    ', edges not thinned (edge_thinning off)' for a stereo one whose mount turned it off, ''
    otherwise: what logs and printed mounts add."""
    radius, _ = thinning_of(mount)
    if radius > 0:
        return f", edges thinned {radius} px (stereo fattening)"
    return ", edges not thinned (edge_thinning off)" if _turned_off(mount) else ""


def thinning_line(mount: TopViewMount) -> str:
    """The calibration summary's line: whether and how frames from `mount` are thinned."""
    radius, jump_mm = thinning_of(mount)
    if radius > 0:
        return f"thinning   on: {radius} px at depth steps > {jump_mm:.0f} mm (stereo fattening)"
    if _turned_off(mount):
        return "thinning   off: the mount says its edges are not fattened (edge_thinning false)"
    return "thinning   off: the sensor does not fatten edges"


def unfatten(depth: np.ndarray, mount: TopViewMount) -> np.ndarray:
    """`depth` (uint16 mm) with its fattened edges thinned as the module says when `mount`'s
    sensor fattens them, else `depth` itself (not copied)."""
    radius, jump_mm = thinning_of(mount)
    if radius <= 0:
        return depth
    return thin_edges(depth, radius, jump_mm)


def thin_edges(
    depth: np.ndarray, radius: int, jump_mm: float, min_farther: int = MIN_FARTHER
) -> np.ndarray:
    """The thinning itself: a new uint16 frame in which every pixel with depth that has at
    least `min_farther` neighbours within Chebyshev distance `radius` farther by more than
    `jump_mm` takes the depth of the farthest of them; every other pixel keeps its own."""
    depth = np.ascontiguousarray(depth, np.uint16)
    if depth.ndim != 2:
        raise ValueError(f"depth must be 2-D, got shape {depth.shape}")
    if radius < 0 or min_farther < 1:
        raise ValueError(f"radius must be >= 0 and min_farther >= 1, got {radius}, {min_farther}")
    out = np.empty_like(depth)
    _thin(depth, int(radius), np.float64(jump_mm), int(min_farther), out)
    return out


@numba.njit(cache=True, parallel=True)
def _thin(depth, radius, jump, min_farther, out):
    """out[r, c] = the largest depth n within Chebyshev `radius` of (r, c) with
    n - depth[r, c] > jump, when depth[r, c] > 0 and at least `min_farther` neighbours are
    such; else depth[r, c].

    Most pixels have no such neighbour: the largest depth within `radius` (a separable max
    filter, rows then columns) rules them out first, and only the rest count their
    neighbours (1.2 ms wall a 640x480 D435 frame against 4.6 ms counting everywhere,
    docs/performance.md)."""
    h, w = depth.shape
    row_max = np.empty((h, w), np.uint16)
    for r in numba.prange(h):
        row = depth[r]
        m = row_max[r]
        m[:] = row
        for k in range(1, radius + 1):
            for c in range(w - k):
                m[c] = max(m[c], row[c + k])
            for c in range(k, w):
                m[c] = max(m[c], row[c - k])
    for r in numba.prange(h):
        r0 = max(0, r - radius)
        r1 = min(h, r + radius + 1)
        near_max = row_max[r0].copy()
        for rr in range(r0 + 1, r1):
            other = row_max[rr]
            for c in range(w):
                near_max[c] = max(near_max[c], other[c])
        for c in range(w):
            d = np.int64(depth[r, c])
            out[r, c] = depth[r, c]
            if d == 0 or np.int64(near_max[c]) - d <= jump:
                continue
            best = d
            count = 0
            for rr in range(r0, r1):
                for cc in range(max(0, c - radius), min(w, c + radius + 1)):
                    n = np.int64(depth[rr, cc])
                    if n - d > jump:
                        count += 1
                        if n > best:
                            best = n
            if count >= min_farther:
                out[r, c] = best
