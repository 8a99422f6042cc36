"""The Segmenter's working resolution: decimation, its optics, the policy, and the labels
brought back to the frame's resolution (against `tests/reference.py`)."""

from __future__ import annotations

import numpy as np
import pytest
from reference import upsample_labels_reference

from topseg.core import labels as L
from topseg.core.camera import KINECT_V1, PAPER_MOUNT, Intrinsics, TopViewMount
from topseg.core.resolution import (
    auto_downsample,
    decimate,
    decimated_intrinsics,
    decimated_mount,
    upsample_labels,
)
from topseg.core.sensors import get_sensor


def random_frame(rng, h, w, factor):
    """A depth frame of patches at a few depths with holes, its decimation, and labels of
    the decimation with some NO_DEPTH on pixels that have depth too."""
    depth = rng.choice(np.array([0, 900, 1500, 1510, 3000], np.uint16), size=(h, w))
    depth = depth + rng.integers(0, 30, size=(h, w)).astype(np.uint16) * (depth > 0)
    small = decimate(depth, factor)
    labels = rng.integers(0, L.NUM_CLASSES, size=small.shape).astype(np.uint8)
    labels[small == 0] = L.NO_DEPTH
    labels[rng.random(small.shape) < 0.05] = L.NO_DEPTH
    return depth, small, labels


@pytest.mark.parametrize(("h", "w", "factor"), [(30, 40, 2), (31, 41, 2), (29, 37, 3), (8, 9, 4)])
def test_upsampled_labels_equal_the_numpy_reference(h, w, factor):
    rng = np.random.default_rng(h * w + factor)
    for _ in range(10):
        depth, small, labels = random_frame(rng, h, w, factor)
        got = upsample_labels(depth, labels, small, factor)
        np.testing.assert_array_equal(got, upsample_labels_reference(depth, labels, small, factor))
        grid = got[::factor, ::factor]  # a pixel of the grid keeps its own label
        has = labels != L.NO_DEPTH
        np.testing.assert_array_equal(grid[has], labels[has])
        assert np.all((got == L.NO_DEPTH) == (depth == 0))


def test_a_label_edge_follows_the_depth_edge():
    # a 10-px-wide table (900 mm away) on the floor (3000 mm); the edge falls between grid
    # columns, so the columns off the grid take the label of the side their depth is on
    depth = np.full((6, 20), 3000, np.uint16)
    depth[:, 5:15] = 900
    small = decimate(depth, 2)
    labels = np.where(small == 900, L.TABLE, L.BACKGROUND).astype(np.uint8)
    got = upsample_labels(depth, labels, small, 2)
    np.testing.assert_array_equal(got, np.where(depth == 900, L.TABLE, L.BACKGROUND))
    # a pixel with depth whose candidates have no label is background
    labels[:] = L.NO_DEPTH
    assert np.all(upsample_labels(depth, labels, small, 2) == L.BACKGROUND)


def test_upsample_refuses_a_decimation_of_another_size():
    depth = np.full((10, 12), 1000, np.uint16)
    with pytest.raises(ValueError, match="decimated by 2 is 6x5"):
        upsample_labels(depth, np.zeros((4, 6), np.uint8), np.zeros((4, 6), np.uint16), 2)
    with pytest.raises(ValueError, match="uint16"):
        decimate(depth.astype(np.float32), 2)


def test_decimated_optics_see_the_same_points_at_the_same_heights():
    k = Intrinsics(640, 480, 570.3, 571.0, 318.2, 242.7)
    small = decimated_intrinsics(k, 2)
    assert (small.width, small.height) == (320, 240) and small.fx == k.fx / 2
    assert decimated_intrinsics(KINECT_V1.scaled_to(41, 31), 2).shape == (16, 21)
    # a tilted mount: the decimated frame's heights are those of the same pixels at full size
    mount = TopViewMount(k, 3300.0, 4.0, -3.0)
    rng = np.random.default_rng(0)
    depth = rng.integers(1500, 3600, size=k.shape).astype(np.uint16)
    full = mount.height_map_mm(depth)
    half = decimated_mount(mount, 2).height_map_mm(decimate(depth, 2))
    np.testing.assert_allclose(half, full[::2, ::2], atol=1e-2)


def test_auto_keeps_a_labelled_pixel_within_a_fifth_of_a_hand():
    """Half where a labelled pixel then spans at most 14.4 mm of the floor, never coarser
    (a third measured worse)."""
    assert auto_downsample(PAPER_MOUNT) == 2  # Kinect v1 at 3.5 m: 6.1 mm a pixel
    assert auto_downsample(TopViewMount(KINECT_V1, 4500.0)) == 1  # 7.9 mm
    assert auto_downsample(TopViewMount(KINECT_V1, 2500.0)) == 2  # 4.4 mm: a third would fit
    d435 = get_sensor("realsense_d435").intrinsics
    assert auto_downsample(TopViewMount(d435, 2500.0)) == 2  # 6.5 mm
    assert auto_downsample(TopViewMount(d435, 3500.0)) == 1  # 9.1 mm
    hd = Intrinsics(1280, 720, 640.0, 640.0, 639.5, 359.5)  # a D435 at 1280x720
    assert auto_downsample(TopViewMount(hd, 3000.0)) == 2  # 4.7 mm
    assert auto_downsample(TopViewMount(hd.scaled_to(2560, 1440), 2000.0)) == 2
    assert auto_downsample(TopViewMount(KINECT_V1.scaled_to(160, 120), 3500.0)) == 1
