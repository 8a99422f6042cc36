"""Blobs too small to be a head or a piece of furniture take their border's label
(`core/islands.py`)."""

from __future__ import annotations

import numpy as np
import pytest
from reference import small_blobs_reference

from topseg.core import labels as L
from topseg.core.islands import FURNITURE_ISLANDS, island_areas, relabel_small_blobs

FX, FY = 570.3, 570.3


def relabel_small_heads(labels, depth, fx, fy, min_head_cm2):
    """`relabel_small_blobs` for heads only; how many head blobs it relabelled."""
    return int(relabel_small_blobs(labels, depth, fx, fy, island_areas(min_head_cm2, 0.0))[L.HEAD])


def blocky_labels(rng, shape, block, head_share):
    """Labels in random blocks (so that blobs of every size touch every class), head in a
    share of them, and no depth scattered."""
    h, w = shape
    coarse = rng.integers(0, L.NUM_CLASSES, size=(h // block + 1, w // block + 1))
    coarse[rng.random(coarse.shape) < head_share] = L.HEAD
    labels = np.kron(coarse, np.ones((block, block), np.int64))[:h, :w].astype(np.uint8)
    flip = rng.random(shape) < 0.05  # ragged edges: single pixels of another class
    labels[flip] = rng.integers(0, L.NUM_CLASSES, size=int(flip.sum()))
    labels[rng.random(shape) < 0.03] = L.NO_DEPTH
    return labels


@pytest.mark.parametrize("seed", range(6))
def test_kernel_matches_the_scipy_reference_on_random_labels(seed):
    rng = np.random.default_rng(seed)
    shape = (int(rng.integers(20, 90)), int(rng.integers(20, 120)))
    labels = blocky_labels(rng, shape, int(rng.integers(1, 7)), float(rng.uniform(0.1, 0.6)))
    depth = rng.integers(400, 5000, size=shape).astype(np.uint16)
    depth[labels == L.NO_DEPTH] = 0
    for head, furniture in ((5.0, 0.0), (50.0, 0.0), (400.0, 0.0), (0.0, 300.0), (50.0, 300.0)):
        areas = island_areas(head, furniture)
        if seed % 2:  # any class may have a minimum, not only heads and furniture
            areas = areas + rng.choice([0.0, 20.0, 200.0], size=L.NUM_CLASSES)
        want, n_want = small_blobs_reference(labels, depth, FX, FY, areas, L.NO_DEPTH)
        got = labels.copy()
        n_got = relabel_small_blobs(got, depth, FX, FY, areas)
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(n_got, n_want)
        assert n_got[L.HEAD] > 0 or head in (0.0, 5.0)  # the test exercises relabelling
        assert n_got[list(FURNITURE_ISLANDS)].sum() > 0 or furniture == 0.0
        off = areas == 0
        assert not n_got[off].any()


def test_blobs_are_judged_on_the_labels_as_given():
    # a small chair blob in a table, a smaller storage blob in the chair's top left corner:
    # the chair's border is mostly table; the storage's is half chair, half table, a tie
    # that goes to chair (the lower id), in the labels as they came. So the chair becomes
    # table and the storage chair, whichever is met first
    labels = np.full((100, 100), L.TABLE, np.uint8)  # ~1900 cm2 at 2.5 m
    labels[10:20, 10:20] = L.CHAIR  # ~19 cm2
    labels[10:12, 10:12] = L.STORAGE  # met before the chair
    depth = np.full((100, 100), 2500, np.uint16)
    got = labels.copy()
    n = relabel_small_blobs(got, depth, FX, FY, island_areas(0.0, 300.0))
    assert (n[L.CHAIR], n[L.STORAGE], n[L.TABLE]) == (1, 1, 0)  # the table is large
    want = np.full((100, 100), L.TABLE, np.uint8)
    want[10:12, 10:12] = L.CHAIR
    np.testing.assert_array_equal(got, want)
    # the same frame turned half round: the chair is met first
    got = np.rot90(labels, 2).copy()
    relabel_small_blobs(got, depth, FX, FY, island_areas(0.0, 300.0))
    np.testing.assert_array_equal(got, np.rot90(want, 2))


def test_areas_must_be_one_per_class():
    with pytest.raises(ValueError, match="areas"):
        relabel_small_blobs(np.zeros((4, 4), np.uint8), np.zeros((4, 4), np.uint16), FX, FY, [1.0])


def person_from_above():
    """A body with a whole head (~250 cm2 at 1.6 m) and a head-like patch on a shoulder
    (~25 cm2), a hand with a head fragment on it, on the floor 3.3 m down."""
    depth = np.full((200, 200), 3300, np.uint16)
    labels = np.full((200, 200), L.BACKGROUND, np.uint8)
    labels[60:140, 50:150] = L.BODY
    depth[60:140, 50:150] = 1900
    labels[80:124, 80:124] = L.HEAD  # 44 x 44 px at 1.6 m: (44 * 1600 / 570)^2 mm2 ~ 153 cm2
    depth[80:124, 80:124] = 1600
    labels[62:72, 130:140] = L.HEAD  # 10 x 10 px on the shoulder at 1.9 m: ~11 cm2
    labels[150:160, 10:30] = L.HAND
    depth[150:160, 10:30] = 2400
    labels[152:156, 12:15] = L.HEAD
    return labels, depth


def test_a_patch_on_a_shoulder_becomes_body_and_the_head_stays():
    labels, depth = person_from_above()
    got = labels.copy()
    assert relabel_small_heads(got, depth, FX, FY, 50.0) == 2
    assert (got[80:124, 80:124] == L.HEAD).all()
    assert (got[62:72, 130:140] == L.BODY).all()
    assert (got[152:156, 12:15] == L.HAND).all()
    untouched = labels != L.HEAD
    np.testing.assert_array_equal(got[untouched], labels[untouched])


def test_zero_area_keeps_every_head():
    labels, depth = person_from_above()
    got = labels.copy()
    assert relabel_small_heads(got, depth, FX, FY, 0.0) == 0
    np.testing.assert_array_equal(got, labels)


@pytest.mark.parametrize("side_px, z_mm", [(44, 1600), (22, 3200), (11, 6400)])
def test_the_area_is_measured_on_the_surface_not_in_pixels(side_px, z_mm):
    """One head, 44 px wide at 1.6 m, 22 px at 3.2 m, 11 px at 6.4 m: 152 cm2 each."""
    labels = np.full((60, 60), L.BODY, np.uint8)
    depth = np.full((60, 60), z_mm + 300, np.uint16)
    labels[5 : 5 + side_px, 5 : 5 + side_px] = L.HEAD
    depth[5 : 5 + side_px, 5 : 5 + side_px] = z_mm
    assert relabel_small_heads(labels.copy(), depth, FX, FY, 150.0) == 0
    assert relabel_small_heads(labels.copy(), depth, FX, FY, 155.0) == 1


def test_a_head_with_nothing_around_it_keeps_its_label():
    labels = np.full((10, 10), L.NO_DEPTH, np.uint8)
    depth = np.zeros((10, 10), np.uint16)
    labels[4:6, 4:6] = L.HEAD
    depth[4:6, 4:6] = 2000
    assert relabel_small_heads(labels, depth, FX, FY, 50.0) == 0
    assert (labels[4:6, 4:6] == L.HEAD).all()


def test_shapes_must_agree():
    with pytest.raises(ValueError, match="differ in shape"):
        relabel_small_heads(np.zeros((4, 4), np.uint8), np.zeros((4, 5), np.uint16), FX, FY, 50.0)
