"""Small holes inside one surface take that surface's depth before a frame is labelled.

A time-of-flight camera loses depth on dark hair: seen from above, the top of a head comes
back with holes in it (`synth.noise.ToFNoise`, `dark_dropout`). The forest reads a probe
that lands in a hole as far away, so a head with holes looks like arms and hands: on
rendered walker frames with hair dropout the bundled model found 0.16-0.25 of the heads as
blobs (`docs/results.md`). Many cameras leave small holes on flat surfaces too (speckle).

`fill_holes` finds every 4-connected region without depth and fills it with the mean depth
of the nearest surface on its border when both hold:
- it lies inside that surface: at least `surface_share` of its border lies within
  `span_mm` of the border's nearest depth. A shadow or a dropped edge lies between a near
  and a far surface (a person and the floor), with each of them on about half of its
  border, so it stays a hole. Dark hair's dropout often reaches the head's outline, where
  a few of its border pixels are the shoulders or the floor: with a share of 1 (the whole
  border within the span) such a hole stays, and on rendered Kinect v2 frames 37 % of the
  head's pixels are still without depth after the fill (docs/results.md);
- it is small: at most `max_cm2` on the surface, its pixels measured at that surface's mean
  depth ((z / fx) x (z / fy) each).
The border counts each pair of 4-neighbours with one pixel in the hole and the other with
depth once. The work is proportional to the pixels without depth.
"""

from __future__ import annotations

import numba
import numpy as np

from topseg.core.camera import Intrinsics, check_depth

#: the largest hole filled, on the surface (cm2): under half the top of a head (200-300 cm2)
MAX_HOLE_CM2 = 100.0
#: the nearest surface on a hole's border: the border pixels within this (mm) of its nearest
#: depth; a depth edge (the noise models' `jump_m`) is larger
MAX_SPAN_MM = 100.0
#: a hole is filled only when at least this share of its border is that surface
SURFACE_SHARE = 0.8


@numba.njit(cache=True, inline="always")
def neighbour(v, u, k):
    """The k-th (0-3) 4-neighbour of pixel (v, u): below, above, right, left (it may lie
    off the image)."""
    return v + (1 if k == 0 else -1 if k == 1 else 0), u + (1 if k == 2 else -1 if k == 3 else 0)


@numba.njit(cache=True)
def _fill_holes(depth, max_sum_z2, span_mm, surface_share, out):
    """Fill `out` (a copy of `depth`) as `fill_holes` says; `max_sum_z2` is the largest
    pixel count times mean surface depth squared (mm^2). Returns the holes filled."""
    h, w = depth.shape
    seen = np.zeros((h, w), np.uint8)
    stack_v = np.empty(h * w, np.int32)
    stack_u = np.empty(h * w, np.int32)
    pix_v = np.empty(h * w, np.int32)
    pix_u = np.empty(h * w, np.int32)
    filled = 0
    for v0 in range(h):
        for u0 in range(w):
            if depth[v0, u0] != 0 or seen[v0, u0]:
                continue
            seen[v0, u0] = 1
            stack_v[0], stack_u[0] = v0, u0
            top, n = 1, 0
            lo, count = 1 << 30, 0
            while top > 0:
                top -= 1
                v, u = stack_v[top], stack_u[top]
                pix_v[n], pix_u[n] = v, u
                n += 1
                for k in range(4):
                    vv, uu = neighbour(v, u, k)
                    if vv < 0 or vv >= h or uu < 0 or uu >= w:
                        continue
                    d = np.int64(depth[vv, uu])
                    if d == 0:
                        if not seen[vv, uu]:
                            seen[vv, uu] = 1
                            stack_v[top], stack_u[top] = vv, uu
                            top += 1
                    else:
                        lo = min(lo, d)
                        count += 1
            if count == 0:
                continue
            # the border once more: the share of it on the nearest surface, and its mean
            total, near = 0.0, 0
            for i in range(n):
                for k in range(4):
                    vv, uu = neighbour(pix_v[i], pix_u[i], k)
                    if vv < 0 or vv >= h or uu < 0 or uu >= w:
                        continue
                    d = np.int64(depth[vv, uu])
                    if d != 0 and d - lo <= span_mm:
                        total += d
                        near += 1
            if near < surface_share * count:
                continue
            z = total / near
            if n * z * z > max_sum_z2:
                continue
            fill = np.uint16(np.floor(z + 0.5))
            for i in range(n):
                out[pix_v[i], pix_u[i]] = fill
            filled += 1
    return filled


def fill_holes(
    depth: np.ndarray,
    k: Intrinsics,
    max_cm2: float = MAX_HOLE_CM2,
    span_mm: float = MAX_SPAN_MM,
    surface_share: float = SURFACE_SHARE,
) -> tuple[np.ndarray, int]:
    """(a copy of uint16 `depth` with its small holes inside one surface filled, how many
    were filled); `k` the frame's intrinsics (areas on the surface). The module says which
    holes; `max_cm2` 0 fills none, `surface_share` 1 asks for the whole border within
    `span_mm`."""
    depth = check_depth(depth, "fill_holes")
    if depth.shape != k.shape:
        raise ValueError(f"depth {depth.shape} is not the intrinsics' {k.shape}")
    if not (np.isfinite(max_cm2) and max_cm2 >= 0 and np.isfinite(span_mm) and span_mm >= 0):
        raise ValueError(f"max_cm2 and span_mm must be >= 0, got {max_cm2}, {span_mm}")
    if not 0.0 < surface_share <= 1.0:
        raise ValueError(f"surface_share must be in (0, 1], got {surface_share}")
    out = depth.copy()
    if max_cm2 == 0:
        return out, 0
    max_sum_z2 = float(max_cm2) * 100.0 * k.fx * k.fy  # cm2 -> pixels x depth^2 (mm^2)
    return out, int(_fill_holes(depth, max_sum_z2, float(span_mm), float(surface_share), out))
