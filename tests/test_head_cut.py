"""The image's edge moved across a head (`core.synth.head_cut`), alone and in the synthesiser."""

from __future__ import annotations

import numpy as np
import pytest

from topseg.core import labels as L
from topseg.core.errors import TopsegError
from topseg.core.synth.head_cut import KEPT_SHARE, MIN_HEAD_PX, cut_across_head
from topseg.core.synth.synthesis import MountDistribution, SynthesisConfig, Synthesizer


def _frame(rows, cols, h=120, w=160):
    """A floor at 3000 mm with one square head at 1300 mm over rows x cols."""
    depth = np.full((h, w), 3000, np.uint16)
    lab = np.full((h, w), L.BACKGROUND, np.uint8)
    depth[rows, cols] = 1300
    lab[rows, cols] = L.HEAD
    return depth, lab


@pytest.mark.parametrize("seed", range(12))
def test_the_cut_crosses_the_head_from_its_nearer_border(seed):
    rows, cols = slice(20, 40), slice(100, 130)  # nearer the top and the right
    depth, lab = _frame(rows, cols)
    before_depth, before_lab = depth.copy(), lab.copy()
    axis, keep, line = cut_across_head(depth, lab, np.random.default_rng(seed))
    gone = depth == 0
    lo, hi = (20, 40) if axis == 0 else (100, 130)
    assert lo < line < hi  # across the head, never beside it
    idx = np.arange(depth.shape[axis])
    removed = idx < line if keep > 0 else idx >= line
    assert keep == (1 if axis == 0 else -1)  # top rows go, or right columns
    expect = np.broadcast_to(removed[:, None] if axis == 0 else removed[None, :], depth.shape)
    assert np.array_equal(gone, expect)
    assert np.all(lab[gone] == L.NO_DEPTH)
    assert np.array_equal(depth[~gone], before_depth[~gone])
    assert np.array_equal(lab[~gone], before_lab[~gone])
    kept = (lab == L.HEAD).sum() / (before_lab == L.HEAD).sum()
    assert KEPT_SHARE[0] - 0.05 <= kept <= KEPT_SHARE[1] + 0.05


def test_no_head_large_enough_changes_nothing():
    rng = np.random.default_rng(0)
    depth, lab = _frame(slice(0, 0), slice(0, 0))
    assert cut_across_head(depth, lab, rng) is None
    side = int(np.sqrt(MIN_HEAD_PX)) - 1
    depth, lab = _frame(slice(50, 50 + side), slice(50, 50 + side))
    before = depth.copy()
    assert cut_across_head(depth, lab, rng) is None
    assert np.array_equal(depth, before)
    with pytest.raises(ValueError, match="same 2-D shape"):
        cut_across_head(depth, lab[:, :10], rng)


def test_one_of_two_heads_is_cut():
    depth, lab = _frame(slice(20, 40), slice(20, 40))
    depth[70:90, 120:140], lab[70:90, 120:140] = 1300, L.HEAD
    cuts = set()
    for seed in range(20):
        d, cut_lab = depth.copy(), lab.copy()
        cut_across_head(d, cut_lab, np.random.default_rng(seed))
        heads = ((slice(20, 40), slice(20, 40)), (slice(70, 90), slice(120, 140)))
        whole = [bool((cut_lab[r, c] == L.HEAD).all()) for r, c in heads]
        assert whole.count(True) == 1
        cuts.add(whole.index(False))
    assert cuts == {0, 1}  # either head can be the one


def test_the_synthesiser_cuts_a_share_of_the_frames_with_heads():
    """head_cut 1 vs 0 on the same seeds: a frame with a head loses a band reaching its
    border, and nothing else changes; without a head, the frame is the same."""
    frames = {}
    for share in (0.0, 1.0):
        config = SynthesisConfig(noise="kinect", seed=6, mounts=MountDistribution(), head_cut=share)
        with Synthesizer(config, warm=False) as s:
            frames[share] = [s.render(i) for i in range(6)]
    cut = 0
    for whole, part in zip(frames[0.0], frames[1.0], strict=True):
        changed = whole.depth != part.depth
        assert not (part.depth[changed]).any()  # only depth taken away
        if (whole.labels == L.HEAD).sum() < MIN_HEAD_PX:
            assert not changed.any()
            continue
        cut += changed.any()
        if changed.any():  # a band reaching a border
            rows, cols = np.nonzero(changed)
            h, w = changed.shape
            assert rows.min() == 0 or cols.min() == 0 or rows.max() == h - 1 or cols.max() == w - 1
        assert np.array_equal(part.labels[changed], np.full(changed.sum(), L.NO_DEPTH))
    assert cut >= 2
    assert "head_cut" not in SynthesisConfig().to_dict()  # earlier recipes keep their keys
    back = SynthesisConfig.from_dict(SynthesisConfig(head_cut=0.3).to_dict())
    assert back.head_cut == 0.3
    with pytest.raises(TopsegError, match="head_cut"):
        SynthesisConfig(head_cut=1.5)


def test_datasets_with_drawn_mounts_cut_heads_and_the_papers_do_not():
    from topseg.services.datagen.sources import GENERATORS, HEAD_CUT_SHARE, generator_config

    target = GENERATORS["synthesis"]
    drawn = generator_config(target, "modeled", "sensor", None, MountDistribution().to_dict())
    assert drawn["head_cut"] == HEAD_CUT_SHARE > 0
    assert "head_cut" not in generator_config(target, "modeled", "kinect", None)
