"""The edge-preserving smoothing of noisy depth (`core.denoise`): the kernels against the
plain reference on random frames, which cameras it runs for, and what it keeps."""

import numpy as np
import pytest
from reference import smooth_depth_reference

from topseg.core.camera import KINECT_V1, TopViewMount
from topseg.core.denoise import (
    ALPHA,
    HEAVY_ITERATIONS,
    HEAVY_SIGMA_MM,
    ITERATIONS,
    MIN_SIGMA_MM,
    SIGMAS,
    denoise,
    edge_table,
    floor_sigma_mm,
    needs_denoise,
    passes,
    smooth_depth,
)
from topseg.core.fattening import unfatten
from topseg.core.forest.features import FeatureConfig
from topseg.core.forest.inputs import model_input
from topseg.core.sensors import depth_sigma_mm, get_sensor


def mount_of(sensor: str, height_mm: float, noise_scale: float = 1.0) -> TopViewMount:
    """A straight-down mount of `sensor` at `height_mm`."""
    k = get_sensor(sensor).intrinsics
    return TopViewMount(k, height_mm, sensor=sensor, noise_scale=noise_scale)


def noisy_frame(rng, shape, holes=0.05):
    """A floor with a raised block and random dropouts, with ~60 mm of noise."""
    h, w = shape
    depth = np.full(shape, 4500.0)
    depth[h // 4 : h // 2, w // 3 : 2 * w // 3] = 3000.0
    depth += rng.normal(0, 60, shape)
    depth = np.clip(np.round(depth), 1, 65535).astype(np.uint16)
    depth[rng.random(shape) < holes] = 0
    return depth


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("shape", [(7, 5), (23, 130), (40, 31)])
@pytest.mark.parametrize("alpha, iterations", [(ALPHA, ITERATIONS), (0.6, 1), (0.1, 3)])
def test_kernels_match_the_reference(seed, shape, alpha, iterations):
    rng = np.random.default_rng(seed)
    depth = noisy_frame(rng, shape)
    edge = edge_table("realsense_d435", float(rng.uniform(0.5, 2.0)))
    got = smooth_depth(depth, edge, alpha, iterations)
    want = smooth_depth_reference(depth, edge, alpha, iterations)
    np.testing.assert_array_equal(got, want)


def test_random_depths_and_thresholds_match_the_reference():
    rng = np.random.default_rng(11)
    depth = rng.integers(0, 6000, (37, 70)).astype(np.uint16)
    edge = rng.uniform(0, 400, 65536).astype(np.float32)
    np.testing.assert_array_equal(
        smooth_depth(depth, edge, 0.3, 2), smooth_depth_reference(depth, edge, 0.3, 2)
    )


def test_it_lowers_the_noise_and_keeps_edges_and_holes():
    rng = np.random.default_rng(3)
    shape = (120, 160)
    depth = noisy_frame(rng, shape)  # the block: rows 30-59, columns 53-105
    out = smooth_depth(depth, edge_table("realsense_d435", 1.0))
    has = depth > 0
    np.testing.assert_array_equal(out > 0, has)  # holes stay holes, no depth is made up
    floor = has.copy()
    floor[26:64, 49:110] = False  # the block and a margin around it
    before = np.std(depth[floor].astype(float) - 4500)
    after = np.std(out[floor].astype(float) - 4500)
    assert after < 0.6 * before
    # the edge stays put: the block keeps its height up to its outline, the floor its own
    block = np.zeros(shape, bool)
    block[30:60, 53:106] = True
    assert np.all(np.abs(out[block & has].astype(int) - 3000) < 300)
    assert np.all(np.abs(out[~block & has].astype(int) - 4500) < 300)


def test_which_cameras_are_smoothed():
    assert needs_denoise(mount_of("realsense_d435", 4500.0))
    assert needs_denoise(mount_of("oak_d", 3500.0))
    assert not needs_denoise(mount_of("kinect_v2", 4500.0))
    assert not needs_denoise(mount_of("kinect_v1", 3500.0))
    # the measured noise scale counts: a Kinect v1 twice as noisy as its model is smoothed
    assert needs_denoise(mount_of("kinect_v1", 3500.0, noise_scale=2.0))
    for sensor, height in (("kinect_v1", 3500.0), ("realsense_d435", 2000.0)):
        sigma = float(depth_sigma_mm(np.float32(height), sensor))
        assert needs_denoise(mount_of(sensor, height)) == (sigma >= MIN_SIGMA_MM)


def test_a_quiet_camera_is_left_as_it_is():
    depth = noisy_frame(np.random.default_rng(0), KINECT_V1.shape)
    mount = TopViewMount(KINECT_V1, 3500.0)
    assert denoise(depth, mount) is depth


def test_edge_table_is_sigmas_times_the_noise():
    table = edge_table("oak_d", 1.5)
    d = np.array([1000, 2500, 4500], np.float32)
    np.testing.assert_allclose(table[d.astype(int)], SIGMAS * 1.5 * depth_sigma_mm(d, "oak_d"))
    assert table[0] == 0.0
    assert not table.flags.writeable


def test_the_noisiest_frames_get_more_passes_when_labelled_not_in_training():
    assert HEAVY_SIGMA_MM > MIN_SIGMA_MM and HEAVY_ITERATIONS > ITERATIONS
    for sensor, height in (
        ("kinect_v1", 3500.0),
        ("kinect_v2", 4500.0),
        ("oak_d", 3500.0),
        ("oak_d", 4500.0),
        ("realsense_d435", 2500.0),
        ("realsense_d435", 4000.0),
        ("realsense_d435", 4500.0),
    ):
        mount = mount_of(sensor, height)
        sigma = floor_sigma_mm(mount)
        want = 0 if sigma < MIN_SIGMA_MM else ITERATIONS
        assert passes(mount, for_training=True) == want
        assert passes(mount) == (HEAVY_ITERATIONS if sigma >= HEAVY_SIGMA_MM else want)
    assert passes(mount_of("realsense_d435", 4500.0)) == HEAVY_ITERATIONS
    assert passes(mount_of("realsense_d435", 2500.0)) == ITERATIONS


@pytest.mark.parametrize("for_training", [False, True])
def test_model_input_reads_the_smoothed_frame(for_training):
    mount = mount_of("realsense_d435", 4500.0)
    k = mount.intrinsics
    depth = noisy_frame(np.random.default_rng(5), k.shape)
    features = FeatureConfig()
    got = model_input(depth, mount, features, for_training)
    # a stereo camera's edges are thinned first (`core.fattening`, tests/test_fattening.py)
    n = ITERATIONS if for_training else HEAVY_ITERATIONS
    smoothed = smooth_depth(unfatten(depth, mount), edge_table(mount.sensor, 1.0), ALPHA, n)
    quiet = TopViewMount(k, 4500.0, sensor="kinect_v2")  # same optics, not smoothed
    want = model_input(smoothed, quiet, features)
    np.testing.assert_array_equal(got.values, want.values)
    np.testing.assert_array_equal(got.scale, want.scale)
    # the other number of passes reads another frame
    other = smooth_depth(unfatten(depth, mount), edge_table(mount.sensor, 1.0), ALPHA, 5 - n)
    assert not np.array_equal(model_input(other, quiet, features).values, got.values)


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match="2-D"):
        smooth_depth(np.zeros((2, 3, 4), np.uint16), edge_table("oak_d", 1.0))
    with pytest.raises(ValueError, match="65536 entries"):
        smooth_depth(np.ones((4, 4), np.uint16), np.zeros(100, np.float32))
    for shape in ((0, 5), (5, 0), (1, 1)):
        depth = np.full(shape, 3000, np.uint16)
        np.testing.assert_array_equal(smooth_depth(depth, edge_table("oak_d", 1.0)), depth)


def test_logs_say_when_frames_are_smoothed():
    from topseg.core.denoise import smoothing_text
    from topseg.services.live.worker_mount import mount_text

    far = mount_of("realsense_d435", 4500.0)
    assert smoothing_text(far) == ", depth smoothed (noise 85 mm at the floor)"
    assert mount_text(far).endswith("depth smoothed (noise 85 mm at the floor)")
    assert smoothing_text(mount_of("kinect_v2", 3000.0)) == ""


def test_the_calibration_summary_says_whether_frames_are_smoothed():
    from topseg.core.calibration import _smoothing_line

    assert _smoothing_line(mount_of("realsense_d435", 4500.0)) == (
        "smoothing  on: noise 85 mm at the floor (>= 20 mm)"
    )
    assert _smoothing_line(mount_of("kinect_v1", 2500.0)) == (
        "smoothing  off: noise 8 mm at the floor (< 20 mm)"
    )
