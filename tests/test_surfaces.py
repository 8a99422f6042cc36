"""One surface, one thing: robot and object pixels on one continuous surface take its
majority class (`core.surfaces`, the `surfaces` stage)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from reference import vote_surfaces_reference
from segmenter_rules import vote_as_the_segmenter

from topseg.core import labels as L
from topseg.core.errors import TopsegError
from topseg.core.segmenter import Segmenter, SegmenterConfig
from topseg.core.segmenter_config import GridConfig, PostConfig
from topseg.core.surfaces import (
    MIN_STEP_MM,
    STEP_BIN_MM,
    STEP_SIGMAS,
    surface_step_mm,
    vote_surfaces,
    voting_table,
)
from topseg.core.synth.cell_scenes import CellConfig
from topseg.core.synth.density import DensityConfig
from topseg.core.synth.synthesis import SynthesisConfig, Synthesizer
from topseg.services.batch.experiment.mounts import cell_mount

VOTING = voting_table(L.NUM_CLASSES)


def random_frame(rng, shape=(37, 53)):
    """Labels over every class and a depth of a few flat steps with noise and holes, so that
    surfaces both join and part."""
    h, w = shape
    labels = rng.choice([L.ROBOT, L.OBJECT, L.ROBOT, L.OBJECT, L.BODY, L.TABLE, 0], size=shape)
    base = rng.choice([1500, 1530, 1600, 2400], size=(h // 6 + 1, w // 6 + 1))
    depth = np.kron(base, np.ones((6, 6)))[:h, :w] + rng.integers(-15, 16, size=shape)
    depth[rng.random(shape) < 0.05] = 0
    return labels.astype(np.uint8), depth


@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_the_vote_matches_its_numpy_reference_on_random_frames(dtype):
    rng = np.random.default_rng(11)
    for sensor in ("kinect_v1", "realsense_d435"):
        step = surface_step_mm(sensor)
        for _ in range(25):
            labels, depth = random_frame(rng)
            depth = depth.astype(dtype)
            want, n, surfaces = vote_surfaces_reference(labels, depth, step, VOTING, STEP_BIN_MM)
            got = labels.copy()
            assert vote_surfaces(got, depth, step, VOTING) == (n, surfaces)
            np.testing.assert_array_equal(got, want)


def test_a_link_of_two_labels_becomes_one_and_a_box_beside_it_at_another_height_stays():
    labels = np.full((20, 30), L.BACKGROUND, np.uint8)
    depth = np.full((20, 30), 3000, np.uint16)
    labels[2:18, 2:14] = L.ROBOT
    labels[2:8, 2:14] = L.OBJECT  # a third of the link read as object
    depth[2:18, 2:14] = 1800
    labels[2:18, 14:28] = L.OBJECT  # a box touching it, 30 cm lower
    depth[2:18, 14:28] = 2100
    labels[10:12, 20:22] = L.ROBOT  # a few robot pixels on the box
    step = surface_step_mm("kinect_v1")
    n, surfaces = vote_surfaces(labels, depth, step, VOTING)
    assert (labels[2:18, 2:14] == L.ROBOT).all() and (labels[2:18, 14:28] == L.OBJECT).all()
    assert (n, surfaces) == (6 * 12 + 4, 2)
    assert (labels[0] == L.BACKGROUND).all()


def test_body_parts_furniture_and_pixels_without_depth_never_change_or_join():
    labels = np.full((10, 30), L.ROBOT, np.uint8)
    labels[:, 10] = L.BODY  # a person's arm across the surface splits it
    labels[:, 20] = L.TABLE
    labels[:, 25] = L.OBJECT
    depth = np.full((10, 30), 2000, np.uint16)
    depth[:, 5] = 0
    labels[:, 0:5] = L.OBJECT  # left of the hole: object, its own surface
    before = labels.copy()
    vote_surfaces(labels, depth, surface_step_mm("kinect_v1"), VOTING)
    assert (labels[:, 0:5] == L.OBJECT).all()  # the hole parts it from the robot
    assert (labels[:, 10] == L.BODY).all() and (labels[:, 20] == L.TABLE).all()
    assert (labels[:, 25] == L.ROBOT).all()  # one column of object on the robot's surface
    assert (labels[:, 5] == before[:, 5]).all()


def test_the_step_grows_with_the_sensors_noise_and_never_falls_below_its_floor():
    for sensor in ("kinect_v1", "kinect_v2", "oak_d", "realsense_d435"):
        step = surface_step_mm(sensor)
        assert step.min() == pytest.approx(MIN_STEP_MM) and not step.flags.writeable
        assert np.all(np.diff(step) >= 0)
    # a stereo camera at 4 m is noisier than a Kinect v2: its surfaces join across more
    at = 4000 // STEP_BIN_MM
    assert surface_step_mm("realsense_d435")[at] > surface_step_mm("kinect_v2")[at]
    assert STEP_SIGMAS > 0


def test_bad_input_is_refused_and_a_model_without_both_classes_votes_on_nothing():
    step = surface_step_mm("kinect_v1")
    with pytest.raises(ValueError, match="differ in shape"):
        vote_surfaces(np.zeros((4, 4), np.uint8), np.zeros((4, 5)), step, VOTING)
    with pytest.raises(ValueError, match="uint8"):
        vote_surfaces(np.zeros((4, 4), np.int32), np.zeros((4, 4)), step, VOTING)
    ten_classes = voting_table(L.PAPER_NUM_CLASSES)
    assert not ten_classes.any()
    labels = np.full((4, 4), L.ROBOT, np.uint8)
    labels[0] = L.OBJECT
    assert vote_surfaces(labels, np.full((4, 4), 2000), step, ten_classes) == (0, 0)
    assert (labels[0] == L.OBJECT).all()


def test_the_setting_is_validated():
    with pytest.raises(TopsegError, match="surface_vote must be on or off"):
        PostConfig(surface_vote="maybe")


@pytest.mark.slow
def test_the_stage_votes_after_the_person_check_on_a_rendered_cell_and_off_turns_it_off():
    """The bundled model on a clean rendered robot cell, at the frame's resolution and
    without island rules: the labels with the vote are the labels without it, voted."""
    mount = cell_mount("kinect_v1", 2.5, 0.0)
    config = SynthesisConfig(mode="cell", noise="none", seed=3, camera=mount,
                             density=DensityConfig(cell=CellConfig(paper_share=0.0)))  # fmt: skip
    post = PostConfig(min_head_cm2=0.0, min_furniture_cm2=0.0, min_plant_cm2=0.0,
                      satellite_head_cm2=0.0)  # fmt: skip
    base = SegmenterConfig(check_camera=False, grid=GridConfig(downsample=1), post=post)
    on = Segmenter.from_file(None, base, crf="realtime")
    off = Segmenter.from_file(
        None,
        dataclasses.replace(base, post=dataclasses.replace(post, surface_vote="off")),
        crf="realtime",
    )
    voted = 0
    with Synthesizer(config) as synth:
        for i in range(3):
            frame = synth.render(frame_seed=i)
            got = on.label(frame.depth, mount=frame.mount)
            want = off.label(frame.depth, mount=frame.mount).labels.copy()
            n, _ = vote_as_the_segmenter(want, frame.depth, frame.mount, on.n_classes)
            np.testing.assert_array_equal(got.labels, want)
            assert got.counts["surface_votes_px"] == n
            voted += n
    assert voted > 0  # the frames had surfaces to vote on
