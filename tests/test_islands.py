"""Blobs too small to be a head or a piece of furniture, and head blobs beside a larger
head, take their border's label (`core/islands.py`)."""

from __future__ import annotations

import numpy as np
import pytest
from reference import islands_reference

from topseg.core import labels as L
from topseg.core.camera import Intrinsics
from topseg.core.islands import (
    FURNITURE_ISLANDS,
    MAX_HEAD_ANCHORS,
    SATELLITE_RADIUS_CM,
    edge_shares,
    island_areas,
    relabel_islands,
)

K = Intrinsics()  # Kinect v1: fx = fy = 570.3


def relabel_small_heads(labels, depth, k, min_head_cm2):
    """`relabel_islands` for small heads only; how many head blobs it relabelled."""
    small, satellites = relabel_islands(labels, depth, k, island_areas(min_head_cm2, 0.0, 0.0))
    assert satellites == 0
    return int(small[L.HEAD])


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
    for head, furniture, plant in (
        (5.0, 0.0, 0.0),
        (50.0, 0.0, 0.0),
        (400.0, 0.0, 0.0),
        (0.0, 300.0, 0.0),
        (0.0, 0.0, 100.0),
        (50.0, 300.0, 100.0),
    ):
        areas = island_areas(head, furniture, plant)
        if seed % 2:  # any class may have a minimum, not only heads and furniture
            areas = areas + rng.choice([0.0, 20.0, 200.0], size=L.NUM_CLASSES)
        want, n_want, _ = islands_reference(labels, depth, K, areas, L.NO_DEPTH)
        got = labels.copy()
        n_got, satellites = relabel_islands(got, depth, K, areas)
        assert satellites == 0
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(n_got, n_want)
        assert n_got[L.HEAD] > 0 or head in (0.0, 5.0)  # the test exercises relabelling
        assert n_got[list(FURNITURE_ISLANDS)].sum() > 0 or furniture == 0.0
        assert n_got[L.PLANT] > 0 or plant == 0.0
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
    n = relabel_islands(got, depth, K, island_areas(0.0, 300.0, 0.0))[0]
    assert (n[L.CHAIR], n[L.STORAGE], n[L.TABLE]) == (1, 1, 0)  # the table is large
    want = np.full((100, 100), L.TABLE, np.uint8)
    want[10:12, 10:12] = L.CHAIR
    np.testing.assert_array_equal(got, want)
    # the same frame turned half round: the chair is met first
    got = np.rot90(labels, 2).copy()
    relabel_islands(got, depth, K, island_areas(0.0, 300.0, 0.0))
    np.testing.assert_array_equal(got, np.rot90(want, 2))


def test_a_speck_of_plant_on_a_table_is_table_and_a_potted_plant_stays():
    # a table top 0.75 m high under a camera 3.5 m up (2750 mm away): a speck of plant 8 x 8
    # px (~15 cm2) on it, and a potted plant 40 x 40 px at 0.6 m (~410 cm2) beside it
    labels = np.full((120, 160), L.BACKGROUND, np.uint8)
    depth = np.full((120, 160), 3500, np.uint16)
    labels[10:110, 10:110] = L.TABLE
    depth[10:110, 10:110] = 2750
    labels[30:38, 30:38] = L.PLANT
    labels[60:100, 115:155] = L.PLANT
    depth[60:100, 115:155] = 2900
    got = labels.copy()
    n = relabel_islands(got, depth, K, island_areas(0.0, 0.0, 100.0))[0]
    assert n[L.PLANT] == 1 and n.sum() == 1
    want = labels.copy()
    want[30:38, 30:38] = L.TABLE
    np.testing.assert_array_equal(got, want)
    # 0 keeps every blob of plant
    got = labels.copy()
    assert not relabel_islands(got, depth, K, island_areas(0.0, 0.0, 0.0))[0].any()
    np.testing.assert_array_equal(got, labels)


def test_areas_must_be_one_per_class():
    with pytest.raises(ValueError, match="areas"):
        relabel_islands(np.zeros((4, 4), np.uint8), np.zeros((4, 4), np.uint16), K, [1.0])


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
    assert relabel_small_heads(got, depth, K, 50.0) == 2
    assert (got[80:124, 80:124] == L.HEAD).all()
    assert (got[62:72, 130:140] == L.BODY).all()
    assert (got[152:156, 12:15] == L.HAND).all()
    untouched = labels != L.HEAD
    np.testing.assert_array_equal(got[untouched], labels[untouched])


def test_zero_area_keeps_every_head():
    labels, depth = person_from_above()
    got = labels.copy()
    assert relabel_small_heads(got, depth, K, 0.0) == 0
    np.testing.assert_array_equal(got, labels)


@pytest.mark.parametrize("side_px, z_mm", [(44, 1600), (22, 3200), (11, 6400)])
def test_the_area_is_measured_on_the_surface_not_in_pixels(side_px, z_mm):
    """One head, 44 px wide at 1.6 m, 22 px at 3.2 m, 11 px at 6.4 m: 152 cm2 each."""
    labels = np.full((60, 60), L.BODY, np.uint8)
    depth = np.full((60, 60), z_mm + 300, np.uint16)
    labels[5 : 5 + side_px, 5 : 5 + side_px] = L.HEAD
    depth[5 : 5 + side_px, 5 : 5 + side_px] = z_mm
    assert relabel_small_heads(labels.copy(), depth, K, 150.0) == 0
    assert relabel_small_heads(labels.copy(), depth, K, 155.0) == 1


def test_a_head_with_nothing_around_it_keeps_its_label():
    labels = np.full((10, 10), L.NO_DEPTH, np.uint8)
    depth = np.zeros((10, 10), np.uint16)
    labels[4:6, 4:6] = L.HEAD
    depth[4:6, 4:6] = 2000
    assert relabel_small_heads(labels, depth, K, 50.0) == 0
    assert (labels[4:6, 4:6] == L.HEAD).all()


def test_shapes_must_agree():
    with pytest.raises(ValueError, match="differ in shape"):
        relabel_small_heads(np.zeros((4, 4), np.uint8), np.zeros((4, 5), np.uint16), K, 50.0)


def scattered_heads(rng, shape, n_heads):
    """Labels of random body-part blocks with `n_heads` head discs of random sizes and
    places (some overlapping, some touching), depth a head's height under 2.5-4.5 m."""
    h, w = shape
    labels = blocky_labels(rng, shape, 6, 0.0)
    labels[labels == L.HEAD] = L.BODY
    depth = rng.integers(1500, 3500, size=shape).astype(np.uint16)
    v, u = np.indices(shape)
    for _ in range(n_heads):
        cv, cu, r = rng.integers(0, h), rng.integers(0, w), rng.uniform(2.0, 14.0)
        disc = (v - cv) ** 2 + (u - cu) ** 2 <= r * r
        labels[disc] = L.HEAD
        depth[disc] = int(rng.integers(1000, 2500))
    depth[labels == L.NO_DEPTH] = 0
    return labels, depth


@pytest.mark.parametrize("seed", range(8))
def test_satellites_match_the_scipy_reference_on_random_heads(seed):
    rng = np.random.default_rng(100 + seed)
    shape = (int(rng.integers(60, 160)), int(rng.integers(60, 200)))
    labels, depth = scattered_heads(rng, shape, int(rng.integers(3, 30)))
    k = Intrinsics(shape[1], shape[0], 570.3, 570.3, rng.uniform(0, shape[1]), shape[0] / 2)
    total = 0
    for head, furniture, satellite, radius in (
        (0.0, 0.0, 150.0, SATELLITE_RADIUS_CM),
        (50.0, 300.0, 150.0, SATELLITE_RADIUS_CM),
        (20.0, 0.0, 400.0, 60.0),
        (50.0, 0.0, 0.0, SATELLITE_RADIUS_CM),
    ):
        areas = island_areas(head, furniture, 0.0)
        want, n_want, sat_want = islands_reference(
            labels, depth, k, areas, L.NO_DEPTH, satellite, radius, L.HEAD
        )
        got = labels.copy()
        n_got, sat_got = relabel_islands(got, depth, k, areas, satellite, radius)
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(n_got, n_want)
        assert sat_got == sat_want
        assert sat_got == 0 or satellite > 0
        total += sat_got
    assert total > 0  # the test exercises satellites


def person_with_an_arm(arm_offset_px, arm_side_px=26, second_head_px=0):
    """A person 3.3 m under the camera: body at 1.4 m, a whole head (~230 cm2) at 1.6 m, a
    head blob `arm_side_px` wide on the arm `arm_offset_px` right of the head's centre; a
    second person's head `second_head_px` wide 60 cm left of it, if any."""
    depth = np.full((300, 400), 3300, np.uint16)
    labels = np.full((300, 400), L.BACKGROUND, np.uint8)
    labels[100:200, 60:340] = L.BODY
    depth[100:200, 60:340] = 1900
    labels[128:172, 178:222] = L.HEAD  # 44 px at 1.7 m: (44 * 1.7 / 570 m)^2 ~ 172 cm2
    depth[128:172, 178:222] = 1700
    c = 200 + arm_offset_px
    half = arm_side_px // 2
    labels[150 - half : 150 + half, c - half : c + half] = L.HEAD
    depth[150 - half : 150 + half, c - half : c + half] = 2000
    if second_head_px:
        c2, half2 = 200 - 170, second_head_px // 2  # 170 px at 2 m ~ 60 cm
        labels[150 - half2 : 150 + half2, c2 - half2 : c2 + half2] = L.HEAD
        depth[150 - half2 : 150 + half2, c2 - half2 : c2 + half2] = 2000
    return labels, depth


#: the camera of `person_with_an_arm`: its optical axis through the head's centre
K_CELL = Intrinsics(400, 300, 570.3, 570.3, 199.5, 149.5)


def px_cm(px, z_mm):
    """Pixels at depth z (mm) as cm across."""
    return px * z_mm / K.fx / 10.0


def test_a_head_blob_on_the_arm_beside_a_head_takes_the_arms_label():
    labels, depth = person_with_an_arm(80)  # 80 px at 2 m: 28 cm from the head's centre
    assert px_cm(80, 2000) < SATELLITE_RADIUS_CM
    got = labels.copy()
    small, satellites = relabel_islands(
        got, depth, K_CELL, island_areas(50.0, 0.0, 0.0), 150.0, SATELLITE_RADIUS_CM
    )
    assert (small[L.HEAD], satellites) == (0, 1)  # ~83 cm2: not small, but a satellite
    assert (got[128:172, 178:222] == L.HEAD).all()
    assert (got == L.HEAD).sum() == 44 * 44
    np.testing.assert_array_equal(got[labels != L.HEAD], labels[labels != L.HEAD])


def test_a_head_blob_further_off_or_as_large_as_a_head_stays():
    labels, depth = person_with_an_arm(130)  # 46 cm off
    assert px_cm(130, 2000) > SATELLITE_RADIUS_CM
    assert (
        relabel_islands(
            labels.copy(), depth, K_CELL, island_areas(50.0, 0.0, 0.0), 150.0, SATELLITE_RADIUS_CM
        )[1]
        == 0
    )
    labels, depth = person_with_an_arm(80, arm_side_px=32)  # ~126 cm2
    for limit, want in ((100.0, 0), (150.0, 1)):
        got = labels.copy()
        assert (
            relabel_islands(
                got, depth, K_CELL, island_areas(50.0, 0.0, 0.0), limit, SATELLITE_RADIUS_CM
            )[1]
            == want
        )


def test_a_second_persons_head_is_not_a_satellite():
    labels, depth = person_with_an_arm(80, second_head_px=30)  # ~85 cm2, 60 cm off
    got = labels.copy()
    assert (
        relabel_islands(
            got, depth, K_CELL, island_areas(50.0, 0.0, 0.0), 150.0, SATELLITE_RADIUS_CM
        )[1]
        == 1
    )  # the arm
    assert (got[135:165, 15:45] == L.HEAD).all()


def test_off_keeps_every_head_blob():
    labels, depth = person_with_an_arm(80)
    got = labels.copy()
    small, satellites = relabel_islands(
        got, depth, K_CELL, island_areas(0.0, 0.0, 0.0), 0.0, SATELLITE_RADIUS_CM
    )
    assert satellites == 0 and not small.any()
    np.testing.assert_array_equal(got, labels)


def test_only_the_largest_head_blobs_claim_satellites():
    """MAX_HEAD_ANCHORS + 1 heads 1 m apart, each a little smaller than the one before; a
    satellite beside the largest is relabelled, beside the smallest (not an anchor) not."""
    n = MAX_HEAD_ANCHORS + 1
    cols = 9
    rows = -(-n // cols)
    step = 285  # px at 2 m: 1 m
    labels = np.full((rows * step, cols * step), L.BODY, np.uint8)
    depth = np.full(labels.shape, 2000, np.uint16)
    centres = []
    for i in range(n):
        v, u = step // 2 + (i // cols) * step, step // 2 + (i % cols) * step
        half = 30 - i // 4  # ~250 cm2 down to ~70: the last is the smallest
        labels[v - half : v + half, u - 30 : u + 30] = L.HEAD
        centres.append((v, u))
    for v, u in (centres[0], centres[-1]):
        labels[v - 5 : v + 5, u + 60 : u + 70] = L.HEAD  # ~12 cm2, 23 cm off
    _, satellites = relabel_islands(
        labels, depth, K, island_areas(0.0, 0.0, 0.0), 150.0, SATELLITE_RADIUS_CM
    )
    assert satellites == 1
    v, u = centres[0]
    assert (labels[v - 5 : v + 5, u + 60 : u + 70] == L.BODY).all()
    v, u = centres[-1]
    assert (labels[v - 5 : v + 5, u + 60 : u + 70] == L.HEAD).all()


def test_satellite_options_are_checked():
    labels, depth = person_with_an_arm(80)
    for bad in ({"satellite_head_cm2": -1.0}, {"radius_cm": float("nan")}):
        with pytest.raises(ValueError, match="must be >= 0"):
            relabel_islands(labels, depth, K_CELL, island_areas(50.0, 0.0, 0.0), **bad)


@pytest.mark.parametrize("seed", range(6))
def test_small_blobs_at_the_image_edge_are_kept_as_the_reference_keeps_them(seed):
    rng = np.random.default_rng(100 + seed)
    shape = (int(rng.integers(20, 90)), int(rng.integers(20, 120)))
    # blocks of 3 px or more: fewer head blobs than MAX_HEAD_ANCHORS, which the reference
    # does not model
    labels = blocky_labels(rng, shape, int(rng.integers(3, 7)), float(rng.uniform(0.1, 0.4)))
    depth = rng.integers(400, 5000, size=shape).astype(np.uint16)
    depth[labels == L.NO_DEPTH] = 0
    areas = island_areas(50.0, 300.0, 0.0)
    kept_any = False
    anywhere = rng.uniform(0.0, 1.0, L.NUM_CLASSES)
    for edge_px, shares in ((1, edge_shares(0.0)), (2, edge_shares(0.2)), (3, anywhere)):
        want, n_want, sat_want = islands_reference(
            labels, depth, K, areas, L.NO_DEPTH, 150.0, SATELLITE_RADIUS_CM,
            edge_px=edge_px, edge_share=shares,
        )  # fmt: skip
        got = labels.copy()
        n_got, satellites = relabel_islands(
            got, depth, K, areas, 150.0, SATELLITE_RADIUS_CM, edge_px, shares
        )
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(n_got, n_want)
        assert satellites == sat_want
        plain = labels.copy()
        n_plain, _ = relabel_islands(plain, depth, K, areas, 150.0, SATELLITE_RADIUS_CM)
        kept_any |= bool(n_plain[L.HEAD] > n_got[L.HEAD])
    assert kept_any  # the edge kept some small head the plain rule relabelled


def test_a_head_cut_by_the_image_edge_keeps_its_label():
    labels = np.full((60, 80), L.BODY, np.uint8)
    labels[20:27, 0:7] = L.HEAD  # 7x7 px at 3 m: about 14 cm2, under the 50 cm2 minimum
    labels[40:46, 30:36] = L.HEAD  # the same inside the view
    labels[50:52, 78:80] = L.HEAD  # 2x2 px at the edge: about 1 cm2, under 0.2 x 50 cm2
    depth = np.full(labels.shape, 3000, np.uint16)
    got = labels.copy()
    areas = island_areas(50.0, 0.0, 0.0)
    small, _ = relabel_islands(got, depth, K, areas, 0.0, 0.0, 2, edge_shares(0.2))
    assert small[L.HEAD] == 2
    assert (got[20:27, 0:7] == L.HEAD).all() and (got[40:46, 30:36] == L.BODY).all()
    assert (got[50:52, 78:80] == L.BODY).all()
    for bad in ({"edge_px": -1}, {"edge_share": np.full(L.NUM_CLASSES, 1.5)}):
        with pytest.raises(ValueError, match="edge_"):
            relabel_islands(labels.copy(), depth, K, areas, **bad)
