"""`carry_labels`: an earlier frame's labels carried onto a newer depth frame."""

import numpy as np
import pytest

from topseg.core import labels as L
from topseg.core.safety import carry
from topseg.core.safety.carry import UNIDENTIFIED, carry_labels

HUMAN = np.zeros(256, bool)
HUMAN[list(L.HUMAN_IDS)] = True


def frame(shape=(12, 16), depth=3000, label=L.BACKGROUND):
    """Labels, the labels' depth, the new depth and the new heights of a flat floor."""
    lab = np.full(shape, label, np.uint8)
    then = np.full(shape, depth, np.uint16)
    return lab, then, then.copy(), np.zeros(shape)


def test_nothing_changed_keeps_every_label():
    rng = np.random.default_rng(0)
    lab = rng.integers(0, L.NUM_CLASSES, (20, 30)).astype(np.uint8)
    depth = rng.integers(1500, 3000, (20, 30)).astype(np.uint16)
    heights = rng.uniform(0, 2, (20, 30))
    np.testing.assert_array_equal(carry_labels(lab, depth, depth, heights, 50.0), lab)


def test_a_noisy_camera_needs_a_larger_step():
    lab, then, now, heights = frame()
    now[5, 5], heights[5, 5] = 3000 - 100, 1.0
    assert carry_labels(lab, then, now, heights, 50.0, noise_mm=10.0)[5, 5] == UNIDENTIFIED
    assert carry_labels(lab, then, now, heights, 50.0, noise_mm=20.0)[5, 5] == L.BACKGROUND


def test_something_new_above_the_floor_is_a_person_of_unknown_part():
    lab, then, now, heights = frame()
    now[5, 5], heights[5, 5] = 2000, 1.0  # a head-high thing where the floor was
    now[1, 1], heights[1, 1] = 3000 - carry.APPEARED_MM + 1, 1.0  # not near enough
    now[8, 8], heights[8, 8] = 2900, 0.01  # nearer, but the floor's own noise
    then[10, 10], now[10, 10], heights[10, 10] = 0, 2500, 0.5  # depth where there was none
    out = carry_labels(lab, then, now, heights, 50.0)
    assert out[5, 5] == UNIDENTIFIED
    assert out[1, 1] == L.BACKGROUND and out[8, 8] == L.BACKGROUND
    assert out[10, 10] == L.BACKGROUND  # a shadow that flickered says nothing new
    assert (out == UNIDENTIFIED).sum() == 1


def test_something_new_beside_a_body_part_takes_that_part_within_reach():
    lab, then, now, heights = frame((10, 40))
    lab[5, 2:4] = L.HAND
    now[5, 4:40], heights[5, 4:40] = 2000, 1.0  # a hand reaching on, and on
    pixels_per_m = 40.0  # PART_REACH_M * 40 = 6 pixels
    out = carry_labels(lab, then, now, heights, pixels_per_m)
    reach = int(carry.PART_REACH_M * pixels_per_m)
    assert (out[5, 4 : 3 + reach + 1] == L.HAND).all()
    assert (out[5, 3 + reach + 1 :] == UNIDENTIFIED).all()


def test_every_earlier_label_stays_where_nothing_appeared():
    lab, then, now, heights = frame(label=L.OBJECT)
    lab[2:4, 2:4] = L.BODY
    now[2:4, 2:4] = 3500  # the person left: what they stood on is still theirs until labelled
    lab[6:9, 6:9] = L.ROBOT
    then[6:9, 6:9] = now[6:9, 6:9] = 2200
    now[6, 6:9] = 3000  # a link moved off these (or a person read as robot stepped back)
    out = carry_labels(lab, then, now, heights, 50.0)
    assert (out[2:4, 2:4] == L.BODY).all()
    assert (out[6:9, 6:9] == L.ROBOT).all()  # the monitor's stray rule judges them


def test_random_frames_match_a_pixel_by_pixel_reference():
    rng = np.random.default_rng(7)
    for _ in range(20):
        shape = (int(rng.integers(5, 25)), int(rng.integers(5, 25)))
        lab = rng.choice([L.BACKGROUND, L.OBJECT, L.ROBOT, L.HAND, L.BODY, L.LEGS], shape)
        lab = lab.astype(np.uint8)
        then = rng.integers(0, 3000, shape).astype(np.uint16)
        now = rng.integers(0, 3000, shape).astype(np.uint16)
        heights = rng.uniform(-0.1, 2.0, shape)
        pixels_per_m = float(rng.uniform(0, 60))
        noise = rng.uniform(0, 40, shape).astype(np.float32)
        out = carry_labels(lab, then, now, heights, pixels_per_m, noise)
        reach = carry.PART_REACH_M * pixels_per_m
        humans = np.argwhere(HUMAN[lab])
        for (i, j), got in np.ndenumerate(out):
            old, new = int(then[i, j]), int(now[i, j])
            step = max(carry.APPEARED_MM, carry.APPEARED_SIGMAS * np.sqrt(2) * noise[i, j])
            appeared = new > 0 and old > 0 and new < old - step
            appeared &= heights[i, j] > carry.APPEARED_FLOOR_M
            if appeared and not HUMAN[lab[i, j]]:
                near = np.hypot(*(humans - (i, j)).T) if len(humans) else np.array([np.inf])
                if reach >= 1 and near.min() <= reach:
                    # a body part at the least distance (ties may go to any of them)
                    assert HUMAN[got] and got in lab[tuple(humans[near == near.min()].T)]
                else:
                    assert got == UNIDENTIFIED
            else:
                assert got == lab[i, j]


def test_frames_of_other_shapes_are_refused():
    lab, then, now, heights = frame()
    with pytest.raises(ValueError, match="differ"):
        carry_labels(lab, then[:, :-1], now, heights, 50.0)
