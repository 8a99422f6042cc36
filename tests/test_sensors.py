"""The sensor registry: names, families, intrinsics and noise specs that agree."""

from __future__ import annotations

import numpy as np
import pytest

from topseg.core import sensors
from topseg.core.errors import ConfigError
from topseg.core.synth import noise


def test_the_four_sensors_are_registered_with_their_families_and_resolutions():
    assert sensors.NAMES == ("kinect_v1", "kinect_v2", "oak_d", "realsense_d435")
    expected = {
        "kinect_v1": (sensors.STRUCTURED_LIGHT, (480, 640), 570.3, noise.KinectNoise),
        "kinect_v2": (sensors.TIME_OF_FLIGHT, (424, 512), 365.0, noise.ToFNoise),
        "oak_d": (sensors.ACTIVE_STEREO, (400, 640), 441.25, noise.StereoNoise),
        "realsense_d435": (sensors.ACTIVE_STEREO, (480, 640), 385.0, noise.StereoNoise),
    }
    for s in sensors.SENSORS:
        family, shape, fx, kind = expected[s.name]
        assert sensors.get_sensor(s.name) is s
        assert s.family == family and s.intrinsics.shape == shape
        assert s.intrinsics.fx == fx == s.intrinsics.fy
        model = s.noise()
        assert isinstance(model, kind) and noise.parse_noise(model.spec) == model
        # the noise model measures the range the registry states
        assert (model.min_range_m, model.max_range_m) == (s.min_range_m, s.max_range_m)
        if family == sensors.ACTIVE_STEREO:
            assert model.focal_px == s.intrinsics.fx and model.baseline_m == s.baseline_m
        sigma = s.sigma_mm(np.array([2.4, 3.5, 4.5]))
        assert sigma.shape == (3,) and np.all(np.diff(sigma) > 0)


def test_fields_of_view_match_the_published_ones():
    fov = {s.name: s.intrinsics.field_of_view_deg() for s in sensors.SENSORS}
    assert fov["kinect_v1"] == pytest.approx((58.6, 45.6), abs=1.5)  # 57 x 43 published
    assert fov["kinect_v2"] == pytest.approx((70.6, 60.0), abs=1.0)
    assert fov["oak_d"][0] == pytest.approx(71.9, abs=1.0)


def test_unknown_sensor_is_one_line_naming_the_known_ones():
    with pytest.raises(ConfigError) as err:
        sensors.get_sensor("kinect_v3")
    msg = str(err.value)
    assert "\n" not in msg and "kinect_v3" in msg
    assert all(name in msg for name in sensors.NAMES)
    with pytest.raises(ConfigError, match="unknown sensor"):
        sensors.get_sensor(None)
    with pytest.raises(ConfigError, match="family"):
        sensors.SensorModel("x", "sonar", sensors.KINECT_V1.intrinsics, "none", 0.1, 1.0)


def test_nearest_sensor_by_size_then_field_of_view():
    from topseg.core.sensors import KINECT_V1, KINECT_V2, REALSENSE_D435, nearest_sensor

    assert nearest_sensor(640, 480) is KINECT_V1  # same size, no focal length: the first listed
    assert nearest_sensor(512, 424) is KINECT_V2
    d435 = REALSENSE_D435.intrinsics
    assert nearest_sensor(640, 480, d435.fx) is REALSENSE_D435  # same size: the field of view
    assert nearest_sensor(320, 240, d435.fx / 2) is REALSENSE_D435  # resampled: the field of view


def test_the_sensor_of_frames_that_say_no_optics():
    from topseg.core.errors import ConfigError
    from topseg.core.sensors import KINECT_V1, OAK_D, REALSENSE_D435, sensor_of_frames

    assert sensor_of_frames((480, 640)) is KINECT_V1
    assert sensor_of_frames((400, 640)) is OAK_D
    assert sensor_of_frames((240, 320)) is None  # no supported sensor of that size
    assert sensor_of_frames((480, 640), "realsense_d435") is REALSENSE_D435
    with pytest.raises(ConfigError, match=r"640x480 frames .* the oak_d.s are 640x400"):
        sensor_of_frames((480, 640), "oak_d")
    with pytest.raises(ConfigError, match="unknown sensor"):
        sensor_of_frames((480, 640), "kinect_v9")
