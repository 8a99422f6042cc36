"""No-depth regions that touch the image's edge read as the surface beside them.

Many cameras return no depth along part of the image's edge: a time-of-flight camera outside
its valid circle (`synth.noise.ToFNoise`, `fov_cut`: 30 % of the Kinect v2 frames the model
is trained on), a stereo camera's invalid band at one side, an undistorted or resampled
frame's empty border. A probe there that read `background_mm` would see the floor drop
away into a pit, so a person beside such a region would look cut off there, the same error
a probe off the image makes when it reads `background_mm` (`FeatureConfig.off_image`).

`fill_edge_gaps` gives the forest's probe image (`inputs.ModelInput.probes`) a value in each
such region: an edge gap is a 4-connected region without depth with a pixel on the image's
border. It is filled from its rim inwards, one ring of pixels at a time: a pixel takes the
smallest value (the highest surface) among its 4-neighbours that have depth or were filled
in an earlier ring. So each pixel reads a surface nearest to it along the gap (city-block
distance), and the fill does not depend on the order pixels are visited in. Holes inside the
image keep no depth; no pixel gains a label: only what probes read changes. Beyond one pass
over the frame (none when its border has depth all round), the work is proportional to the
pixels in edge gaps.
"""

from __future__ import annotations

import numba
import numpy as np

from topseg.core.holes import neighbour

#: states of `_fill_edge_gaps`'s pixels
_HAS_DEPTH, _HOLE, _GAP, _NEXT, _FILLED = 0, 1, 2, 3, 4


@numba.njit(cache=True)
def _fill_edge_gaps(values, out):
    """Fill `out` (a copy of `values`) as `fill_edge_gaps` says; returns the pixels filled."""
    h, w = values.shape
    state = np.empty((h, w), np.uint8)
    for r in range(h):
        for c in range(w):
            state[r, c] = _HAS_DEPTH if values[r, c] != 0 else _HOLE
    # the gaps: a flood over pixels without depth from every border pixel without depth
    stack_r = np.empty(h * w, np.int32)
    stack_c = np.empty(h * w, np.int32)
    top = 0
    for i in range(2 * (h + w)):
        if i < w:
            r, c = 0, i
        elif i < 2 * w:
            r, c = h - 1, i - w
        elif i < 2 * w + h:
            r, c = i - 2 * w, 0
        else:
            r, c = i - 2 * w - h, w - 1
        if 0 <= r < h and 0 <= c < w and state[r, c] == _HOLE:
            state[r, c] = _GAP
            stack_r[top], stack_c[top] = r, c
            top += 1
    ring_r = np.empty(h * w, np.int32)  # the ring being filled, and the next one
    ring_c = np.empty(h * w, np.int32)
    next_r = np.empty(h * w, np.int32)
    next_c = np.empty(h * w, np.int32)
    m = 0  # on the way, the first ring: gap pixels beside a pixel with depth
    while top > 0:
        top -= 1
        r, c = stack_r[top], stack_c[top]
        beside_depth = False
        for k in range(4):
            rr, cc = neighbour(r, c, k)
            if 0 <= rr < h and 0 <= cc < w:
                if state[rr, cc] == _HOLE:
                    state[rr, cc] = _GAP
                    stack_r[top], stack_c[top] = rr, cc
                    top += 1
                elif state[rr, cc] == _HAS_DEPTH:
                    beside_depth = True
        if beside_depth:
            state[r, c] = _NEXT
            ring_r[m], ring_c[m] = r, c
            m += 1
    filled = 0
    while m > 0:
        # each pixel of the ring takes the least value among its settled neighbours ...
        for i in range(m):
            r, c = ring_r[i], ring_c[i]
            best = np.int32(1 << 30)
            for k in range(4):
                rr, cc = neighbour(r, c, k)
                if 0 <= rr < h and 0 <= cc < w:
                    s = state[rr, cc]
                    if s == _HAS_DEPTH or s == _FILLED:
                        best = min(best, np.int32(out[rr, cc]))
            out[r, c] = best
        # ... and only then counts as settled, so the ring's order does not matter
        for i in range(m):
            state[ring_r[i], ring_c[i]] = _FILLED
        filled += m
        # the next ring: gap pixels beside this one
        nxt = 0
        for i in range(m):
            for k in range(4):
                rr, cc = neighbour(ring_r[i], ring_c[i], k)
                if 0 <= rr < h and 0 <= cc < w and state[rr, cc] == _GAP:
                    state[rr, cc] = _NEXT
                    next_r[nxt], next_c[nxt] = rr, cc
                    nxt += 1
        ring_r, next_r = next_r, ring_r
        ring_c, next_c = next_c, ring_c
        m = nxt
    return filled


def fill_edge_gaps(values: np.ndarray) -> tuple[np.ndarray, int]:
    """(probe image, pixels filled) of a model input's (H, W) uint16 `values` (0: no depth):
    every no-depth region that touches the image's border takes, ring by ring from its rim,
    the least value among each pixel's settled 4-neighbours (see the module). `values`
    itself when there is nothing to fill (no copy)."""
    values = np.ascontiguousarray(values, np.uint16)
    if values.ndim != 2:
        raise ValueError(f"values must be (H, W), got shape {values.shape}")
    if values.size == 0 or not _border_has_gap(values):
        return values, 0
    out = values.copy()
    return out, int(_fill_edge_gaps(values, out))


def _border_has_gap(values: np.ndarray) -> bool:
    """Whether any pixel on the image's border has no depth (the common case is none)."""
    return bool(
        not values[0].all()
        or not values[-1].all()
        or not values[:, 0].all()
        or not values[:, -1].all()
    )
