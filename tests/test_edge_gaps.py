"""No-depth regions at the image's edge read as the surface beside them: the numba kernel
against the numpy reference on random frames, what is filled and what is not, and what the
forest labels there."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from reference import edge_gaps_reference

from topseg.core.camera import KINECT_V1, TopViewMount
from topseg.core.forest import FeatureConfig
from topseg.core.forest.edge_gaps import fill_edge_gaps
from topseg.core.forest.inputs import model_input


def test_fill_edge_gaps_matches_the_numpy_reference():
    rng = np.random.default_rng(0)
    for _ in range(200):
        h, w = rng.integers(1, 40, 2)
        values = rng.integers(1, 9999, (h, w)).astype(np.uint16)
        values[rng.random((h, w)) < rng.uniform(0.05, 0.9)] = 0
        got, n = fill_edge_gaps(values)
        want, m = edge_gaps_reference(values)
        assert np.array_equal(got, want) and n == m
        has = values > 0
        assert np.array_equal(got[has], values[has])  # measured pixels never change


def test_a_ring_outside_the_valid_circle_reads_the_surface_inside_it():
    """A time-of-flight frame's ring: each pixel reads the nearest surface across the rim, the
    higher one (smaller value) at a tie; a hole inside keeps no depth."""
    h, w = 60, 80
    v, u = np.indices((h, w))
    values = np.where(u < 40, 3000, 2000).astype(np.uint16)  # a low left, a high right half
    values[(v - 30) ** 2 + (u - 40) ** 2 > 28**2] = 0
    values[28:32, 18:22] = 0  # a hole inside the circle
    got, n = fill_edge_gaps(values)
    ring = (v - 30) ** 2 + (u - 40) ** 2 > 28**2
    assert n == ring.sum() and np.all(got[ring] > 0)
    assert np.all(got[28:32, 18:22] == 0)
    assert got[30, 0] == 3000 and got[30, -1] == 2000  # across the rim on its own side
    assert set(np.unique(got[ring])) == {2000, 3000}


def test_nothing_to_fill_returns_the_frame_and_no_depth_stays_none():
    full = np.full((5, 7), 1234, np.uint16)
    got, n = fill_edge_gaps(full)
    assert got is full and n == 0
    empty = np.zeros((5, 7), np.uint16)
    got, n = fill_edge_gaps(empty)
    assert n == 0 and not got.any()
    band = full.copy()
    band[:, :2] = 0  # a stereo camera's invalid band on the left
    got, n = fill_edge_gaps(band)
    assert n == 10 and np.all(got == 1234) and not band[:, :2].any()  # the input is kept


def test_the_forest_labels_no_pixel_in_an_edge_gap():
    """Only what probes read changes: the pixels of a gap still have no depth, so no label."""
    from topseg.core import labels
    from topseg.core.segmenter import Segmenter, SegmenterConfig

    k = KINECT_V1.scaled_to(160, 120)
    mount = TopViewMount(k, 3000.0, sensor="kinect_v2")
    depth = np.full(k.shape, 3000, np.uint16)
    depth[40:80, 60:100] = 1400  # a person's shoulders
    depth[:, :12] = 0  # an invalid band
    nearest = model_input(depth, mount, FeatureConfig())
    background = model_input(depth, mount, FeatureConfig(edge_gaps="background"))
    assert np.array_equal(nearest.values, background.values) and background.probes is None
    edge = np.broadcast_to(nearest.values[:, 12:13], (k.height, 12))
    np.testing.assert_array_equal(nearest.probe_values[:, :12], edge)
    seg = Segmenter.from_file(None, SegmenterConfig(check_camera=False), crf="realtime")
    seg.features = replace(seg.features, edge_gaps="nearest")
    got = seg.label(depth, mount=mount).labels
    assert np.all(got[:, :12] == labels.NO_DEPTH) and np.all(got[:, 12:] != labels.NO_DEPTH)
