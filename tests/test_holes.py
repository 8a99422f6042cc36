"""Small holes inside one surface take its depth: the numba kernel against the numpy
reference on random frames, and what is filled and what is not."""

from __future__ import annotations

import numpy as np
import pytest
from reference import fill_holes_reference

from topseg.core import holes
from topseg.core.camera import Intrinsics

K = Intrinsics(160, 120, 142.6, 142.6, 79.5, 59.5)


def _frame_with_holes(rng: np.random.Generator) -> np.ndarray:
    """Boxes on a floor with holes of every size, some on edges, some at the image's edge."""
    depth = np.full(K.shape, 3000 + rng.integers(-20, 20, K.shape), np.uint16)
    for _ in range(6):
        v, u = rng.integers(0, 110), rng.integers(0, 150)
        depth[v : v + rng.integers(5, 40), u : u + rng.integers(5, 40)] = rng.integers(1500, 2900)
    holes_mask = rng.random(K.shape) < rng.choice([0.02, 0.1, 0.4])
    for _ in range(4):
        v, u = rng.integers(0, 115), rng.integers(0, 155)
        holes_mask[v : v + rng.integers(1, 15), u : u + rng.integers(1, 15)] = True
    depth[holes_mask] = 0
    return depth


@pytest.mark.parametrize("seed", range(12))
def test_fill_holes_matches_the_numpy_reference(seed):
    rng = np.random.default_rng(seed)
    depth = _frame_with_holes(rng)
    max_cm2, span = rng.choice([5.0, 30.0, 100.0, 1e4]), rng.choice([0.0, 40.0, 100.0, 5000.0])
    share = rng.choice([0.3, 0.5, holes.SURFACE_SHARE, 1.0])
    got, n = holes.fill_holes(depth, K, max_cm2, span, share)
    want, m = fill_holes_reference(depth, max_cm2 * 100.0 * K.fx * K.fy, span, share)
    assert np.array_equal(got, want) and n == m
    assert np.array_equal(got[depth > 0], depth[depth > 0])  # measured pixels never change


def test_a_hole_in_a_head_is_filled_and_a_shadow_beside_it_is_not():
    depth = np.full(K.shape, 3300, np.uint16)
    depth[40:80, 40:80] = 1600  # a head, 1.7 m below the camera
    head_hole = (slice(55, 60), slice(55, 62))  # dark hair: 35 px of 1.1 cm, 44 cm2
    depth[head_hole] = 0
    depth[40:80, 80:84] = 0  # a shadow between the head and the floor
    depth[100:103, 10:13] = 0  # a hole on the floor: 9 px of 2.3 cm, 48 cm2
    got, n = holes.fill_holes(depth, K)
    assert n == 2
    assert np.all(got[head_hole] == 1600) and np.all(got[100:103, 10:13] == 3300)
    assert np.all(got[40:80, 80:84] == 0)
    smaller, n = holes.fill_holes(depth, K, max_cm2=46.0)  # the head's 44 cm2, not the 48
    assert n == 1 and np.all(smaller[head_hole] == 1600) and np.all(smaller[100:103, 10:13] == 0)


def test_dropout_reaching_a_heads_outline_is_filled_with_the_head():
    """Dark hair's dropout that reaches the head's outline has a few of its border pixels
    on the floor: filled with the head's depth when most of its border is the head (the
    floor's pixels do not pull the fill down); with a share of 1 it stays a hole."""
    depth = np.full(K.shape, 3300, np.uint16)
    depth[40:80, 40:80] = 1600
    depth[42:48, 40:52] = 0  # from inside the head out to its left outline
    depth[42:48, 38:40] = 3300  # the floor beside it
    got, n = holes.fill_holes(depth, K)
    assert n == 1 and np.all(got[42:48, 40:52] == 1600)  # 6 of 30 border pairs are floor
    kept, n = holes.fill_holes(depth, K, surface_share=1.0)
    assert n == 0 and np.all(kept[42:48, 40:52] == 0)
    # the same hole with half of its border on the floor is a shadow: it stays
    depth[42:48, 52:60] = 3300
    assert holes.fill_holes(depth, K)[1] == 0


def test_a_frame_with_no_holes_or_no_depth_at_all():
    flat = np.full(K.shape, 2000, np.uint16)
    assert holes.fill_holes(flat, K)[1] == 0
    empty = np.zeros(K.shape, np.uint16)
    got, n = holes.fill_holes(empty, K)
    assert n == 0 and not got.any()
    assert holes.fill_holes(flat, K, max_cm2=0.0)[1] == 0
    with pytest.raises(ValueError, match="intrinsics"):
        holes.fill_holes(flat[:-1], K)
    with pytest.raises(ValueError, match=">= 0"):
        holes.fill_holes(flat, K, max_cm2=-1.0)
    with pytest.raises(ValueError, match="surface_share"):
        holes.fill_holes(flat, K, surface_share=0.0)
