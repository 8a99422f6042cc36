"""A stereo camera's fattened edges thinned (`core.fattening`): the kernel against the plain
reference on random frames, which cameras it runs for, and what it undoes."""

import numpy as np
import pytest
from reference import thin_edges_reference

from topseg.core.camera import TopViewMount
from topseg.core.fattening import MIN_FARTHER, thin_edges, thinning_of, unfatten
from topseg.core.forest.features import FeatureConfig
from topseg.core.forest.inputs import model_input
from topseg.core.resolution import decimated_mount
from topseg.core.sensors import get_sensor
from topseg.core.synth.noise import StereoNoise


def mount_of(sensor: str, height_mm: float = 3500.0) -> TopViewMount:
    """A straight-down mount of `sensor` at `height_mm`."""
    return TopViewMount(get_sensor(sensor).intrinsics, height_mm, sensor=sensor)


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("radius", [0, 1, 2, 3])
@pytest.mark.parametrize("min_farther", [1, MIN_FARTHER, 4])
def test_kernel_matches_the_reference(seed, radius, min_farther):
    rng = np.random.default_rng(seed)
    shape = tuple(int(n) for n in rng.integers(1, 60, 2))
    depth = rng.integers(0, 5000, shape).astype(np.uint16)
    depth[rng.random(shape) < 0.1] = 0
    jump = float(rng.uniform(0, 800))
    np.testing.assert_array_equal(
        thin_edges(depth, radius, jump, min_farther),
        thin_edges_reference(depth, radius, jump, min_farther),
    )


def test_blocky_frames_match_the_reference():
    # surfaces of constant depth with steps between them, as top views are
    rng = np.random.default_rng(7)
    coarse = rng.choice([0, 1500, 2400, 2450, 3500], size=(12, 16)).astype(np.uint16)
    depth = np.kron(coarse, np.ones((5, 5), np.uint16))
    for radius in (1, 2):
        np.testing.assert_array_equal(
            thin_edges(depth, radius, 100.0),
            thin_edges_reference(depth, radius, 100.0, MIN_FARTHER),
        )


def test_it_undoes_a_one_pixel_fattening():
    floor, head = 3500, 1700
    truth = np.full((40, 40), floor, np.uint16)
    truth[10:30, 12:28] = head
    fattened = truth.copy()
    fattened[9:31, 11:29] = head  # the head bleeds one pixel over the floor all around
    out = thin_edges(fattened, 1, 100.0)
    np.testing.assert_array_equal(out, truth)
    # a step smaller than the jump is a slope, not an edge: left alone
    gentle = np.full((20, 20), 3000, np.uint16)
    gentle[5:15, 5:15] = 2950
    np.testing.assert_array_equal(thin_edges(gentle, 1, 100.0), gentle)


def test_one_farther_neighbour_is_not_enough():
    # a fattened ring with one pixel missing: the true outline's pixel beside the gap has a
    # single farther neighbour and keeps its depth; the ring's pixels have three and go
    floor, head = 3500, 1700
    depth = np.full((20, 20), floor, np.uint16)
    depth[4:16, 4:16] = head  # the fattened ring: rows and columns 4 and 15
    depth[4, 9] = floor  # one ring pixel left unfattened
    out = thin_edges(depth, 1, 100.0)
    assert out[5, 9] == head  # below the gap: (4, 9) is its only farther neighbour
    assert np.all(out[4, 5:15] == floor) and np.all(out[5:15, 4] == floor)


def test_pixels_without_depth_are_left_alone():
    depth = np.full((10, 10), 3000, np.uint16)
    depth[4:6, 4:6] = 0  # a hole in a surface
    depth[0, :] = 1000
    out = thin_edges(depth, 1, 100.0)
    assert np.all(out[4:6, 4:6] == 0)  # no depth is made up
    assert np.all(out[depth > 0] > 0)  # and none is taken away
    assert np.all(out[0] == 3000)  # the near row is thinned onto the surface behind it


def test_which_cameras_are_thinned():
    for name in ("realsense_d435", "oak_d"):
        noise = get_sensor(name).noise()
        assert isinstance(noise, StereoNoise)
        radius, jump = thinning_of(mount_of(name))
        assert radius == round(sum(noise.fatten**r for r in range(1, noise.fatten_px + 1)))
        assert radius >= 1
        assert jump == pytest.approx(1000.0 * noise.jump_m)
    for name in ("kinect_v1", "kinect_v2"):
        mount = mount_of(name)
        assert thinning_of(mount) == (0, 0.0)
        depth = np.full(mount.intrinsics.shape, 3000, np.uint16)
        assert unfatten(depth, mount) is depth


def test_a_mount_can_say_its_edges_are_not_fattened():
    from dataclasses import replace

    from topseg.core.fattening import thinning_line, thinning_text
    from topseg.services.live.worker_mount import mount_text

    clean = replace(mount_of("realsense_d435"), edge_thinning=False)
    assert thinning_of(clean) == (0, 0.0)
    assert thinning_of(decimated_mount(clean, 2)) == (0, 0.0)  # decimation keeps it
    depth = np.full(clean.intrinsics.shape, 3000, np.uint16)
    depth[100:200, 100:200] = 1500
    assert unfatten(depth, clean) is depth
    assert thinning_text(clean) == ", edges not thinned (edge_thinning off)"
    assert "edges not thinned (edge_thinning off)" in mount_text(clean)
    assert thinning_line(clean) == (
        "thinning   off: the mount says its edges are not fattened (edge_thinning false)"
    )
    # a sensor that does not fatten says so whatever its mount says
    tof = replace(mount_of("kinect_v2"), edge_thinning=False)
    assert thinning_text(tof) == ""
    assert thinning_line(tof) == "thinning   off: the sensor does not fatten edges"
    # the mount file's form: sent only when off, and read back
    assert clean.to_dict()["edge_thinning"] is False
    assert "edge_thinning" not in mount_of("realsense_d435").to_dict()
    assert TopViewMount.from_dict(clean.to_dict()) == clean


def test_a_decimated_frame_is_thinned_by_its_own_pixels():
    full = mount_of("realsense_d435")
    assert thinning_of(decimated_mount(full, 4))[0] == 0  # a quarter of a pixel: nothing
    assert thinning_of(decimated_mount(full, 1))[0] == thinning_of(full)[0]


def test_model_input_reads_the_thinned_frame():
    mount = mount_of("realsense_d435", 2500.0)
    k = mount.intrinsics
    depth = np.full(k.shape, 2500, np.uint16)
    depth[100:200, 150:300] = 1200
    depth[99, 150:300] = 1200  # a fattened row; no noise, so smoothing leaves it as it is
    features = FeatureConfig()
    got = model_input(depth, mount, features)
    quiet = TopViewMount(k, 2500.0, sensor="kinect_v2")  # same optics, not thinned
    want = model_input(thin_edges(depth, 1, 100.0, MIN_FARTHER), quiet, features)
    np.testing.assert_array_equal(got.values, want.values)
    assert not np.array_equal(got.values, model_input(depth, quiet, features).values)


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="2-D"):
        thin_edges(np.zeros((2, 3, 4), np.uint16), 1, 100.0)
    with pytest.raises(ValueError, match="radius"):
        thin_edges(np.zeros((3, 3), np.uint16), -1, 100.0)
    with pytest.raises(ValueError, match="min_farther"):
        thin_edges(np.zeros((3, 3), np.uint16), 1, 100.0, 0)
    for shape in ((0, 5), (5, 0)):
        assert thin_edges(np.zeros(shape, np.uint16), 1, 100.0).shape == shape


def test_logs_and_the_calibration_summary_say_when_edges_are_thinned():
    from topseg.core.calibration import MountEstimate
    from topseg.core.fattening import thinning_line, thinning_text
    from topseg.services.live.worker_mount import mount_text

    stereo, tof = mount_of("oak_d"), mount_of("kinect_v2")
    assert thinning_text(stereo) == ", edges thinned 1 px (stereo fattening)"
    assert "edges thinned 1 px (stereo fattening)" in mount_text(stereo)
    assert thinning_text(tof) == "" and "thinned" not in mount_text(tof)
    assert thinning_line(stereo) == (
        "thinning   on: 1 px at depth steps > 100 mm (stereo fattening)"
    )
    assert thinning_line(tof) == "thinning   off: the sensor does not fatten edges"
    estimate = MountEstimate(stereo, 9.0, 0.8, 10, 10, 1.0, 0.1, "2026-11-28T00:00:00Z")
    assert thinning_line(stereo) in estimate.summary().splitlines()
