"""core/labelled_cloud: the one conversion of (depth, labels) to points both viewer sinks use."""

from dataclasses import replace

import numpy as np
import pytest

from topseg.core import labels
from topseg.core.camera import KINECT_V1, PAPER_MOUNT, TopViewMount, depth_to_range
from topseg.core.labelled_cloud import labelled_cloud
from topseg.core.synth.procedural import procedural_frame

K = KINECT_V1.scaled_to(160, 120)


def test_camera_frame_points_are_the_backprojection_of_kept_pixels():
    rng = np.random.default_rng(0)
    depth, truth = procedural_frame(
        rng, TopViewMount(K, PAPER_MOUNT.height_mm), missing_fraction=0.1
    )
    cloud = labelled_cloud(depth, truth, K, None, 4)
    assert not cloud.in_floor_frame
    sub = depth[::4, ::4]
    assert len(cloud.xyz) == len(cloud.ids) == int((sub > 0).sum())
    np.testing.assert_array_equal(cloud.ids, truth[::4, ::4][sub > 0])
    v, u = np.nonzero(sub > 0)
    z = sub[sub > 0] / 1000.0
    np.testing.assert_allclose(cloud.xyz[:, 2], z, rtol=1e-6)
    np.testing.assert_allclose(cloud.xyz[:, 0], (4 * u - K.cx) * z / K.fx, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(cloud.xyz[:, 1], (4 * v - K.cy) * z / K.fy, rtol=1e-5, atol=1e-6)
    assert labels.NO_DEPTH not in cloud.ids


def floor_depth_mm(mount: TopViewMount) -> np.ndarray:
    """What a mount's camera reads of a bare floor: depth along each pixel's ray, in mm."""
    k = mount.intrinsics
    v, u = np.indices(k.shape)
    rays = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones(k.shape)], axis=-1)
    return np.rint(-mount.height_mm / (rays @ mount.up_normal_camera())).astype(np.uint16)


def test_floor_frame_puts_the_floor_of_a_tilted_camera_at_z_0_and_objects_above():
    mount = TopViewMount(K, 2600.0, pitch_deg=12.0, roll_deg=-7.0)
    depth = floor_depth_mm(mount)
    ids = np.full(K.shape, labels.BACKGROUND, np.uint8)
    ids[40:80, 60:100] = labels.TABLE  # half way up to the camera: 1.3 m above the floor
    depth[40:80, 60:100] //= 2
    cloud = labelled_cloud(depth, ids, K, mount, 2)
    assert cloud.in_floor_frame and cloud.xyz.dtype == np.float32
    floor = cloud.ids == labels.BACKGROUND
    assert floor.sum() > 100 and (~floor).sum() > 100
    # depth is whole millimetres: the floor comes back within a few mm of z = 0
    np.testing.assert_allclose(cloud.xyz[floor, 2], 0.0, atol=0.003)
    np.testing.assert_allclose(cloud.xyz[~floor, 2], 1.3, atol=0.003)
    # the same points as the camera-frame cloud, moved by the mount
    in_camera = labelled_cloud(depth, ids, K, None, 2)
    np.testing.assert_allclose(mount.world_to_camera(cloud.xyz), in_camera.xyz, atol=1e-5)
    # a radial camera's range frame gives the same points
    radial = replace(mount, radial=True)
    from_range = labelled_cloud(depth_to_range(depth, K), ids, K, radial, 2)
    np.testing.assert_allclose(from_range.xyz, cloud.xyz, atol=0.003)


def test_colours_come_from_the_label_table():
    depth = np.full(K.shape, 2000, np.uint16)
    ids = np.zeros(K.shape, np.uint8)
    ids[:, : K.width // 2] = labels.HEAD
    cloud = labelled_cloud(depth, ids, K, None, 8)
    rgba = cloud.rgba()
    assert rgba.shape == (len(cloud.ids), 4) and rgba.dtype == np.uint8
    head = cloud.ids == labels.HEAD
    assert head.any() and (~head).any()
    np.testing.assert_array_equal(rgba[head, :3], [labels.LABELS[labels.HEAD].color] * head.sum())
    np.testing.assert_array_equal(rgba[~head, :3], [labels.LABELS[0].color] * (~head).sum())
    assert (rgba[:, 3] == 255).all()


def test_mismatched_shapes_and_bad_stride_are_refused():
    depth = np.full(K.shape, 2000, np.uint16)
    with pytest.raises(ValueError, match="differ in shape"):
        labelled_cloud(depth, np.zeros((10, 10), np.uint8), K, None, 1)
    with pytest.raises(ValueError, match="stride"):
        labelled_cloud(depth, np.zeros(K.shape, np.uint8), K, None, 0)
