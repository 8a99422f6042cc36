"""The tilted top-view mount: world <-> camera, the floor plane, the height map."""

from __future__ import annotations

import numpy as np
import pytest
import reference

from topseg.core.camera import (
    KINECT_V1,
    PAPER_MOUNT,
    Intrinsics,
    TopViewMount,
    depth_to_range,
    metres_to_mm,
    range_to_depth,
)
from topseg.core.errors import ConfigError

SMALL = Intrinsics(160, 120, 142.6, 142.6, 79.5, 59.5)


def random_mounts(n: int, seed: int = 0) -> list[TopViewMount]:
    """Mounts over the supported range: 2.4-4.5 m, pitch and roll within 10 deg."""
    rng = np.random.default_rng(seed)
    return [
        TopViewMount(
            SMALL,
            float(rng.uniform(2400, 4500)),
            float(rng.uniform(-10, 10)),
            float(rng.uniform(-10, 10)),
        )
        for _ in range(n)
    ]


def floor_depth(mount: TopViewMount, heights_mm: np.ndarray | float = 0.0) -> np.ndarray:
    """Float depth (mm) of horizontal surfaces at `heights_mm` seen through each pixel."""
    k = mount.intrinsics
    v, u = np.indices(k.shape, dtype=np.float64)
    rays = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u)], axis=-1)
    n_dot_r = rays @ mount.up_normal_camera()
    return (np.asarray(heights_mm) - mount.height_mm) / n_dot_r


def test_straight_down_is_the_old_flip():
    m = TopViewMount(KINECT_V1, 3000.0)
    np.testing.assert_array_equal(m.rotation_world_to_camera(), np.diag([1.0, -1.0, -1.0]))
    np.testing.assert_array_equal(m.up_normal_camera(), [0.0, 0.0, -1.0])
    assert m.tilt_deg() == 0.0
    p = np.array([[0.3, -0.2, 0.75]])
    np.testing.assert_allclose(m.world_to_camera(p), [[0.3, 0.2, 2.25]])
    assert m.depth_of_height(0.75) == pytest.approx(2250.0)


def test_paper_mount_is_the_papers_kinect_and_top_view_its_old_name():
    assert PAPER_MOUNT.intrinsics == KINECT_V1
    assert PAPER_MOUNT.height_mm == pytest.approx(3.5 * 1000)
    assert (PAPER_MOUNT.pitch_deg, PAPER_MOUNT.roll_deg) == (0.0, 0.0)


def test_height_has_no_default():
    with pytest.raises(TypeError):
        TopViewMount(KINECT_V1)  # type: ignore[call-arg]


@pytest.mark.parametrize("mount", random_mounts(20))
def test_world_camera_round_trip(mount):
    rng = np.random.default_rng(1)
    p = rng.uniform(-3, 3, (50, 3))
    np.testing.assert_allclose(mount.camera_to_world(mount.world_to_camera(p)), p, atol=1e-12)
    np.testing.assert_allclose(mount.world_to_camera(mount.camera_to_world(p)), p, atol=1e-12)
    r = mount.rotation_world_to_camera()
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)
    # the camera centre maps to the origin, the floor point below it to (0, 0, h)-ish
    np.testing.assert_allclose(mount.world_to_camera(mount.centre_world_m()), 0.0, atol=1e-12)
    below = mount.world_to_camera(np.zeros(3))
    assert np.linalg.norm(below) == pytest.approx(mount.height_mm / 1000.0)
    # the up-normal is world z seen from the camera; tilt is its angle to -optical axis
    np.testing.assert_allclose(mount.up_normal_camera(), r @ [0.0, 0.0, 1.0], atol=1e-12)
    cos = np.cos(np.radians(mount.pitch_deg)) * np.cos(np.radians(mount.roll_deg))
    assert mount.tilt_deg() == pytest.approx(np.degrees(np.arccos(cos)))


@pytest.mark.parametrize("mount", random_mounts(30, seed=2))
def test_from_floor_plane_gives_the_mount_back(mount):
    n = mount.up_normal_camera()
    for scale in (1.0, 3.7, -0.5):  # any length, either orientation
        back = TopViewMount.from_floor_plane(
            scale * n, scale * mount.height_mm, mount.intrinsics, "oak_d"
        )
        assert back.height_mm == pytest.approx(mount.height_mm, abs=1e-9)
        assert back.pitch_deg == pytest.approx(mount.pitch_deg, abs=1e-9)
        assert back.roll_deg == pytest.approx(mount.roll_deg, abs=1e-9)
        assert back.sensor == "oak_d"


def test_a_world_floor_point_is_on_the_plane():
    for mount in random_mounts(10, seed=3):
        p = mount.world_to_camera(np.array([[0.7, -1.1, 0.0], [-0.4, 0.2, 1.2]])) * 1000.0
        heights = mount.height_mm + p @ mount.up_normal_camera()
        np.testing.assert_allclose(heights, [0.0, 1200.0], atol=1e-6)


@pytest.mark.parametrize("mount", random_mounts(10, seed=4))
def test_height_map_of_a_floor_is_zero_and_of_a_box_top_its_height(mount):
    k = mount.intrinsics
    surface = np.zeros(k.shape)
    surface[30:70, 40:110] = 850.0  # a box top 850 mm above the floor
    depth = metres_to_mm(floor_depth(mount, surface) / 1000.0)
    depth[::7, ::5] = 0  # holes
    h = mount.height_map_mm(depth)
    assert h.dtype == np.float32 and h.shape == k.shape
    assert np.isnan(h[depth == 0]).all()
    # depth is rounded to 1 mm, so heights are within about a mm
    floor = (surface == 0) & (depth > 0)
    assert np.abs(h[floor]).max() < 1.0
    assert np.abs(h[(surface > 0) & (depth > 0)] - 850.0).max() < 1.0
    ref = reference.height_map_reference(depth, mount)
    np.testing.assert_allclose(h, ref, atol=0.01, equal_nan=True)


def test_height_map_refuses_another_camera():
    with pytest.raises(ValueError, match="does not match"):
        PAPER_MOUNT.height_map_mm(np.zeros((120, 160), np.uint16))


def test_mount_dict_round_trip_and_old_dicts_load():
    m = TopViewMount(SMALL, 3123.5, 4.25, -7.5, "realsense_d435", 0.42)
    assert TopViewMount.from_dict(m.to_dict()) == m
    old = {"intrinsics": KINECT_V1.to_dict(), "height_mm": 3000}
    back = TopViewMount.from_dict(old)
    assert back == TopViewMount(KINECT_V1, 3000.0)
    assert (back.pitch_deg, back.roll_deg, back.sensor) == (0.0, 0.0, "kinect_v1")
    assert back.noise_scale == 1.0  # not measured: as the sensor model says
    with pytest.raises(ConfigError, match="height_mm"):
        TopViewMount.from_dict({"intrinsics": KINECT_V1.to_dict()})
    with pytest.raises(ConfigError, match="pitch_deg"):
        TopViewMount.from_dict({**old, "pitch_deg": 95.0})
    with pytest.raises(ConfigError, match="height"):
        TopViewMount.from_dict({**old, "height_mm": -1})
    for bad in (0.0, -1.0, float("nan"), 1e9):
        with pytest.raises(ConfigError, match="noise_scale"):
            TopViewMount.from_dict({**old, "noise_scale": bad})


def test_a_radial_cameras_range_is_read_as_depth():
    rng = np.random.default_rng(5)
    depth = rng.integers(500, 6000, SMALL.shape).astype(np.uint16)
    depth[::7, ::5] = 0
    rng_img = depth_to_range(depth, SMALL)
    v, u = np.indices(SMALL.shape)
    ray = np.sqrt(1 + ((u - SMALL.cx) / SMALL.fx) ** 2 + ((v - SMALL.cy) / SMALL.fy) ** 2)
    np.testing.assert_array_equal(rng_img, np.rint(depth * ray).astype(np.uint16))
    assert rng_img[1, 1] > depth[1, 1] and rng_img[60, 80] == depth[60, 80]  # the axis: equal
    back = range_to_depth(rng_img, SMALL)
    assert np.abs(back.astype(int) - depth).max() <= 1 and np.all((back == 0) == (depth == 0))
    radial = TopViewMount(SMALL, 3000.0, 2.0, -1.0, radial=True)
    plain = TopViewMount(SMALL, 3000.0, 2.0, -1.0)
    np.testing.assert_array_equal(radial.z_depth(rng_img), back)
    assert plain.z_depth(depth) is depth
    np.testing.assert_allclose(
        radial.height_map_mm(rng_img), plain.height_map_mm(back), rtol=0, atol=1e-3
    )
    with pytest.raises(ValueError, match="range image is 640x480 but the camera is 160x120"):
        range_to_depth(np.zeros((480, 640), np.uint16), SMALL)


def test_radial_goes_into_the_dict_only_when_true():
    plain = TopViewMount(SMALL, 3000.0)
    radial = TopViewMount(SMALL, 3000.0, radial=True)
    assert "radial" not in plain.to_dict()  # a depth camera's mount reads as before
    assert radial.to_dict()["radial"] is True
    assert TopViewMount.from_dict(radial.to_dict()) == radial
    with pytest.raises(ConfigError, match="radial must be"):
        TopViewMount.from_dict({**plain.to_dict(), "radial": "yes"})
