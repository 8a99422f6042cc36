"""The labelled 3-D point cloud of a frame: one conversion for every viewer sink.

Rerun and Foxglove show the same points: every `stride`-th pixel of every `stride`-th row
that has depth, back-projected through the camera's intrinsics, in the floor frame when the
camera's mount is known (x, y on the floor, z up, origin below the camera centre:
`TopViewMount`'s world frame) and in the camera's optical frame (x right, y down, z forward)
when it is not. Colours come from the label table (`core/labels.py`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from topseg.core import labels
from topseg.core.camera import Intrinsics, TopViewMount, axis_depth, backproject_pixels


@dataclass(frozen=True)
class LabelledCloud:
    """(N, 3) float32 points in metres, their (N,) uint8 label ids and the frame they are in."""

    xyz: np.ndarray
    ids: np.ndarray
    in_floor_frame: bool

    def rgba(self) -> np.ndarray:
        """(N, 4) uint8 colours of the points' labels, opaque."""
        rgba = np.full((len(self.ids), 4), 255, np.uint8)
        rgba[:, :3] = labels.colorize(self.ids)
        return rgba


def labelled_cloud(
    depth_mm: np.ndarray,
    label_img: np.ndarray,
    k: Intrinsics,
    mount: TopViewMount | None,
    stride: int,
) -> LabelledCloud:
    """The pixels with depth of a (depth, labels) pair, subsampled by `stride`, as points.

    In the floor frame when `mount` is given (a `radial` camera's range read as depth first),
    else in the camera's optical frame.
    """
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    if label_img.shape != depth_mm.shape:
        raise ValueError(f"labels {label_img.shape} and depth {depth_mm.shape} differ in shape")
    rows, cols = np.nonzero(np.asarray(depth_mm)[::stride, ::stride] > 0)
    rows, cols = rows * stride, cols * stride
    xyz = backproject_pixels(axis_depth(np.asarray(depth_mm), mount), rows, cols, k)
    if mount is not None:
        xyz = mount.camera_to_world(xyz)
    ids = np.asarray(label_img[rows, cols], np.uint8)
    return LabelledCloud(xyz.astype(np.float32), ids, mount is not None)
