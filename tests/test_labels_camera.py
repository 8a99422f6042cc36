import numpy as np
import pytest

from topseg.core import labels
from topseg.core.camera import (
    KINECT_V1,
    PAPER_MOUNT,
    Intrinsics,
    TopViewMount,
    backproject,
    project,
)


def test_label_table_matches_design():
    assert labels.NAMES == (
        "background",
        "head",
        "body",
        "upper-arm",
        "lower-arm",
        "hand",
        "legs",
        "chair",
        "plant",
        "storage",
        "table",
        "robot",
        "object",
    )
    assert labels.NUM_CLASSES == 13
    assert labels.SCORED_IDS == tuple(range(1, 13))
    assert labels.PAPER_NUM_CLASSES == 11
    assert labels.PAPER_SCORED_IDS == tuple(range(1, 11))
    assert labels.OPEN_WORLD_IDS == (labels.ROBOT, labels.OBJECT) == (11, 12)
    assert labels.FURNITURE_IDS == (7, 8, 9, 10)
    assert labels.NO_DEPTH == 255
    assert labels.by_name("table").id == 10
    with pytest.raises(KeyError, match="known"):
        labels.by_name("sofa")


def test_colours_are_distinct_and_colorize_uses_them():
    colours = {lab.color for lab in labels.LABELS}
    assert len(colours) == labels.NUM_CLASSES
    lut = labels.palette()
    assert tuple(lut[labels.ROBOT]) != tuple(lut[200])  # not the colour of an unknown id
    assert labels.NO_DEPTH_LABEL.color not in colours
    img = np.array([[0, 1], [10, 255]], np.uint8)
    rgb = labels.colorize(img)
    assert rgb.shape == (2, 2, 3)
    assert tuple(rgb[1, 0]) == labels.LABELS[10].color
    assert tuple(rgb[1, 1]) == labels.NO_DEPTH_LABEL.color


def test_kinect_defaults():
    k = KINECT_V1
    assert (k.width, k.height, k.fx, k.fy, k.cx, k.cy) == (640, 480, 570.3, 570.3, 319.5, 239.5)
    assert Intrinsics.from_dict(k.to_dict()) == k
    with pytest.raises(ValueError):
        Intrinsics(width=0)


def test_backproject_then_project_returns_pixels():
    rng = np.random.default_rng(0)
    depth = rng.integers(500, 4000, size=KINECT_V1.shape).astype(np.uint16)
    depth[0, 0] = 0
    pts = backproject(depth, KINECT_V1)
    assert np.isnan(pts[0, 0]).all()
    uv = project(pts[1:, 1:], KINECT_V1)
    v, u = np.indices(KINECT_V1.shape)
    np.testing.assert_allclose(uv[..., 0], u[1:, 1:], atol=1e-3)
    np.testing.assert_allclose(uv[..., 1], v[1:, 1:], atol=1e-3)
    with pytest.raises(ValueError, match="does not match"):
        backproject(depth[:10], KINECT_V1)


def test_top_view_mount():
    m = PAPER_MOUNT
    assert m.height_mm == 3500.0
    w, h = m.floor_extent_m()
    assert w == pytest.approx(640 * 3.5 / 570.3)
    assert h == pytest.approx(480 * 3.5 / 570.3)
    p = np.array([[0.3, -0.7, 0.9]])
    np.testing.assert_allclose(m.camera_to_world(m.world_to_camera(p)), p)
    assert m.depth_of_height(0.75) == pytest.approx(2750.0)
    assert TopViewMount.from_dict(m.to_dict()) == m


def test_scaled_intrinsics_keep_field_of_view():
    k2 = KINECT_V1.scaled_to(320, 240)
    np.testing.assert_allclose(k2.field_of_view_deg(), KINECT_V1.field_of_view_deg(), rtol=1e-6)


def test_backproject_pixels_is_backproject_at_those_pixels():
    from topseg.core.camera import backproject, backproject_pixels

    rng = np.random.default_rng(3)
    k = Intrinsics(width=64, height=48, fx=50.0, fy=51.0, cx=31.5, cy=23.5)
    depth = rng.integers(0, 5000, k.shape).astype(np.uint16)
    depth[rng.random(k.shape) < 0.2] = 0
    rows, cols = rng.integers(0, 48, 100), rng.integers(0, 64, 100)
    np.testing.assert_array_equal(
        backproject_pixels(depth, rows, cols, k), backproject(depth, k)[rows, cols]
    )
