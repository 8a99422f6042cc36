"""The resolution the Segmenter works at, and its labels brought back to the frame's.

A 640x480 Kinect v1 3.5 m above the floor sees 6 mm of floor in a pixel: four pixels across
a finger, twelve across a hand. The forest already walks only a grid of pixels ~25 mm apart
(`forest.predict.grid_stride`), but the posteriors' upsampling, the CRF's band and the island
rules pay for every pixel of the frame. So where a pixel spans little of the floor the
Segmenter labels every `factor`-th pixel of every `factor`-th row (`decimate`: the
pixels themselves, no mixing of depths, so no new flying pixels), seen through the same
optics at that resolution (`decimated_mount`), and `upsample_labels` gives each pixel of the
frame the label of the nearest in depth of the up to four labelled pixels around it: a label
edge follows the depth edge between them.

`auto_downsample(mount)` is the policy (`SegmenterConfig.downsample` = None): half
resolution where a labelled pixel then spans at most `MAX_WORKING_PX_MM` of the floor
straight below, the frame's own elsewhere. Measured in docs/performance.md (a third, which
the same bound gives a Kinect v1 below 2.74 m, scored lower: `AUTO_MAX_DOWNSAMPLE`,
docs/results.md).
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numba
import numpy as np

from topseg.core.camera import Intrinsics, check_depth
from topseg.core.labels import BACKGROUND, NO_DEPTH

if TYPE_CHECKING:
    from topseg.core.camera import TopViewMount

#: the most floor (mm, straight below the camera) a pixel the Segmenter labels may span by
#: default, a fifth of a hand's width: `auto_downsample` halves the resolution where that
#: keeps it. Half resolution for a Kinect v1 (fx 570) up to 4.1 m, for a Kinect v2 or a D435
#: at 640x480 up to 2.6 m, an OAK-D up to 3.2 m and any camera of 1280 px across.
MAX_WORKING_PX_MM = 14.4
#: the coarsest factor `auto_downsample` picks. The bound above alone would label a Kinect v1
#: below 2.74 m at a third: on the 60-frame random-mount held-out set (9 such frames) that
#: scored avg F1 0.6864 against 0.6900 at half (docs/results.md)
AUTO_MAX_DOWNSAMPLE = 2
#: the largest factor `SegmenterConfig.downsample` takes
MAX_DOWNSAMPLE = 4


def auto_downsample(mount: TopViewMount) -> int:
    """The factor the Segmenter works at on frames from `mount` by default: the largest (up
    to AUTO_MAX_DOWNSAMPLE, half) at which a labelled pixel spans at most MAX_WORKING_PX_MM
    of the floor straight below; 1 where a pixel of the frame spans more than half of that."""
    factor = MAX_WORKING_PX_MM // mount.floor_pixel_mm()
    return int(max(1, min(AUTO_MAX_DOWNSAMPLE, factor)))


def decimated_intrinsics(k: Intrinsics, factor: int) -> Intrinsics:
    """The optics of every `factor`-th pixel of every `factor`-th row of a frame from `k`
    (pixel (i, j) of the result is pixel (factor i, factor j) of the frame)."""
    return Intrinsics(
        -(-k.width // factor),
        -(-k.height // factor),
        k.fx / factor,
        k.fy / factor,
        k.cx / factor,
        k.cy / factor,
    )


def decimated_mount(mount: TopViewMount, factor: int) -> TopViewMount:
    """`mount` with the intrinsics of its frames decimated by `factor` (`decimate`)."""
    return replace(mount, intrinsics=decimated_intrinsics(mount.intrinsics, factor))


def decimate(depth: np.ndarray, factor: int) -> np.ndarray:
    """Every `factor`-th pixel of every `factor`-th row of a uint16 depth frame (C-contiguous
    copy; the depths themselves, never averaged)."""
    depth = check_depth(depth, "decimate")
    return np.ascontiguousarray(depth[::factor, ::factor])


#: `_blocks`' mark of a block whose candidates do not share one label (labels are 0-10, 255)
_MIXED = np.uint8(254)


@numba.njit(cache=True, inline="always")
def _nearest_label(d, small_labels, small_depth, i0, i1, j0, j1):
    """The label for a pixel of depth d among its candidates (i0, j0), (i0, j1), (i1, j0),
    (i1, j1): of those with a label, the first nearest in depth (the first wins a tie, so a
    pixel of the grid keeps its own label); BACKGROUND when none has one."""
    best = np.int32(1 << 30)
    label = np.uint8(BACKGROUND)
    for k in range(4):
        i = i0 if k < 2 else i1
        j = j0 if k % 2 == 0 else j1
        s = np.int32(small_depth[i, j])
        lab = small_labels[i, j]
        if s != 0 and lab != NO_DEPTH:
            gap = abs(s - d)
            if gap < best:
                best = gap
                label = lab
    return label


@numba.njit(cache=True, parallel=True)
def _blocks(small_labels, small_depth):
    """(h, w) uint8: the label every pixel of the block at decimated (i, j) takes when its
    candidates (i, j), (i, j + 1), (i + 1, j) and (i + 1, j + 1) share it and (i, j) has
    depth (`_nearest_label` would pick it for each), else _MIXED."""
    sh, sw = small_labels.shape
    out = np.empty((sh, sw), np.uint8)
    for i in numba.prange(sh):
        i1 = min(i + 1, sh - 1)
        for j in range(sw):
            j1 = min(j + 1, sw - 1)
            a = small_labels[i, j]
            same = (
                (a != NO_DEPTH)
                & (small_depth[i, j] != 0)
                & (small_labels[i, j1] == a)
                & (small_labels[i1, j] == a)
                & (small_labels[i1, j1] == a)
            )
            out[i, j] = a if same else _MIXED
    return out


@numba.njit(cache=True, parallel=True)
def _upsample_labels(depth, small_labels, small_depth, factor, out):
    """`upsample_labels`' kernel: a pixel of a block whose candidates share one label
    (`_blocks`) takes it without comparing depths; the others choose (`_nearest_label`)."""
    h, w = depth.shape
    sh, sw = small_labels.shape
    blocks = _blocks(small_labels, small_depth)
    block_of = np.empty(w, np.int64)  # the decimated column of each column, and its offset
    offset = np.empty(w, np.int64)
    for c in range(w):
        block_of[c] = c // factor
        offset[c] = c % factor
    for r in numba.prange(h):
        i0 = r // factor
        i1 = min(i0 + (1 if r % factor else 0), sh - 1)
        for c in range(w):
            d = np.int32(depth[r, c])
            j0 = block_of[c]
            b = blocks[i0, j0]
            if d == 0:
                out[r, c] = NO_DEPTH
            elif b != _MIXED:
                out[r, c] = b
            else:
                j1 = min(j0 + (1 if offset[c] else 0), sw - 1)
                out[r, c] = _nearest_label(d, small_labels, small_depth, i0, i1, j0, j1)


def upsample_labels(
    depth: np.ndarray,
    small_labels: np.ndarray,
    small_depth: np.ndarray,
    factor: int,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """(H, W) uint8 labels of the full frame `depth` from the labels of its decimation
    (`small_depth` = `decimate(depth, factor)`, labelled `small_labels`).

    Each pixel with depth takes the label of the one, among the up to four decimated pixels
    around it (those on the rows and columns of the decimated grid on either side), nearest
    to it in depth that has a label; a pixel of the grid keeps its own. Pixels without depth
    are NO_DEPTH; a pixel with depth whose candidates have none is BACKGROUND."""
    depth = check_depth(depth, "upsample_labels")
    small_depth = check_depth(small_depth, "upsample_labels")
    want = (-(-depth.shape[0] // factor), -(-depth.shape[1] // factor))
    if small_depth.shape != want or np.shape(small_labels) != want:
        raise ValueError(
            f"a {depth.shape[1]}x{depth.shape[0]} frame decimated by {factor} is "
            f"{want[1]}x{want[0]}; got depth {small_depth.shape[::-1]} and labels "
            f"{np.shape(small_labels)[::-1]}"
        )
    small_labels = np.ascontiguousarray(small_labels, np.uint8)
    if out is None:
        out = np.empty(depth.shape, np.uint8)
    _upsample_labels(depth, small_labels, small_depth, np.int64(factor), out)
    return out
