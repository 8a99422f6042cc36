"""Mount calibration: the floor plane recovered from depth, the refusals, the mount file."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from topseg.core.calibration import (
    CalibrationConfig,
    CalibrationError,
    MountEstimate,
    estimate_mount,
    floor_mask,
    mount_difference,
    noise_scale,
)
from topseg.core.camera import KINECT_V1, NOISE_SCALE_RANGE, Intrinsics, TopViewMount
from topseg.core.errors import ConfigError
from topseg.core.formats.mount_file import read_mount_document, read_mount_file, write_mount_file
from topseg.core.sensors import depth_sigma_mm

K = KINECT_V1.scaled_to(320, 240)


def analytic_frame(
    mount: TopViewMount,
    rng: np.random.Generator,
    cover: float = 0.4,
    tables: tuple = (),
    sigma_mm_per_m2: float = 1.4,
    holes: float = 0.05,
) -> np.ndarray:
    """Depth (uint16 mm) of a flat floor seen from `mount`, with random boxes (0.3-1.9 m
    tall) covering `cover` of the view, `tables` ((rows, cols) slices, height mm) on top,
    Kinect-like noise (sigma = sigma_mm_per_m2 * z^2) and `holes` of the pixels without depth.
    """
    k = mount.intrinsics
    v, u = np.indices(k.shape, dtype=np.float64)
    rays = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u)], axis=-1)
    n_dot_r = rays @ mount.up_normal_camera()
    top = np.zeros(k.shape)
    covered = np.zeros(k.shape, bool)
    while covered.mean() < cover:
        h, w = rng.integers(k.height // 12, k.height // 3, 2)
        r0, c0 = rng.integers(0, k.height - h), rng.integers(0, k.width - w)
        top[r0 : r0 + h, c0 : c0 + w] = rng.uniform(300, 1900)
        covered[r0 : r0 + h, c0 : c0 + w] = True
    for where, height in tables:
        top[where] = height
    z = (top - mount.height_mm) / n_dot_r
    z = z + rng.normal(0.0, 1.0, z.shape) * sigma_mm_per_m2 * (z / 1000.0) ** 2
    depth = np.round(z).astype(np.uint16)
    depth[rng.random(k.shape) < holes] = 0
    return depth


def frames_of(mount, n=3, seed=0, **kw):
    rng = np.random.default_rng(seed)
    return [analytic_frame(mount, rng, **kw) for _ in range(n)]


@pytest.mark.parametrize(
    ("height", "pitch", "roll"),
    [(2400.0, 9.5, -9.5), (3100.0, -4.0, 7.0), (3500.0, 0.0, 0.0), (4500.0, -10.0, 3.0)],
)
def test_the_mount_comes_back_from_a_tilted_floor_with_boxes_on_40_percent(height, pitch, roll):
    truth = TopViewMount(K, height, pitch, roll, "kinect_v1")
    est = estimate_mount(frames_of(truth, cover=0.4), K, "kinect_v1")
    assert isinstance(est, MountEstimate)
    m = est.mount
    assert abs(m.height_mm - height) < 5.0
    assert abs(m.pitch_deg - pitch) < 0.1
    assert abs(m.roll_deg - roll) < 0.1
    assert m.intrinsics == K and m.sensor == "kinect_v1"
    assert 0.45 < est.inlier_share < 0.65  # 60 % floor, less what noise pushes out
    sigma = 1.4 * (height / 1000.0) ** 2
    assert 0.5 * sigma < est.residual_mm < 1.5 * sigma
    assert est.frames_used == est.frames_given == 3
    assert est.height_spread_mm < 10 and est.angle_spread_deg < 0.2
    assert est.made_at.endswith("+00:00")
    dh, da = mount_difference(m, truth)
    assert dh < 5.0 and da < 0.1


def test_the_same_frames_give_the_same_mount():
    truth = TopViewMount(K, 3000.0, 3.0, 2.0)
    frames = frames_of(truth)
    a = estimate_mount(frames, K)
    b = estimate_mount(frames, K)
    assert a.mount == b.mount and a.residual_mm == b.residual_mm


def test_a_big_table_is_not_taken_for_the_floor():
    truth = TopViewMount(K, 3000.0, 4.0, -3.0)
    table = ((slice(20, 220), slice(30, 270)), 750.0)  # 62.5 % of the view, one flat top
    frames = frames_of(truth, cover=0.0, tables=(table,))
    est = estimate_mount(frames, K)
    assert abs(est.mount.height_mm - 3000.0) < 5.0
    assert abs(est.mount.pitch_deg - 4.0) < 0.15 and abs(est.mount.roll_deg + 3.0) < 0.15
    assert 0.3 < est.inlier_share < 0.4


def test_a_sensor_with_more_noise_gets_a_wider_inlier_band():
    truth = TopViewMount(K, 4200.0, -6.0, 5.0, "realsense_d435")
    frames = frames_of(truth, sigma_mm_per_m2=4.0)  # ~70 mm at 4.2 m, stereo-like
    est = estimate_mount(frames, K, "realsense_d435")
    assert abs(est.mount.height_mm - 4200.0) < 10.0
    assert abs(est.mount.pitch_deg + 6.0) < 0.2 and abs(est.mount.roll_deg - 5.0) < 0.2
    assert est.inlier_share > 0.5


@pytest.mark.parametrize("quieter", [1.0, 0.35])
def test_the_noise_scale_is_the_floors_noise_over_the_sensor_models(quieter):
    # a camera as noisy as its model gets 1; a time-of-flight camera taken for a Kinect v1
    # (a third of its noise) gets about a third, and so a narrower floor gate
    height = 3300.0
    model = float(depth_sigma_mm(np.float32(height), "kinect_v1"))
    truth = TopViewMount(K, height, 2.0, -1.0, "kinect_v1")
    per_m2 = quieter * model / (height / 1000.0) ** 2
    est = estimate_mount(frames_of(truth, sigma_mm_per_m2=per_m2), K, "kinect_v1")
    assert est.mount.noise_scale == pytest.approx(quieter, rel=0.15)
    assert est.mount.noise_scale == round(est.mount.noise_scale, 2)
    assert f"x{est.mount.noise_scale:.2f} the kinect_v1 noise model" in est.summary()


def test_noise_scale_is_bounded_and_1_without_a_model():
    assert noise_scale(10.0, np.array([]), "kinect_v1") == 1.0
    assert noise_scale(1e-9, np.array([3000.0]), "kinect_v1") == NOISE_SCALE_RANGE[0]
    assert noise_scale(1e9, np.array([3000.0]), "kinect_v1") == NOISE_SCALE_RANGE[1]


def test_floor_mask_marks_the_floor():
    truth = TopViewMount(K, 3300.0, 5.0, 5.0)
    depth = frames_of(truth, n=1, cover=0.4)[0]
    mask = floor_mask(depth, truth)
    h = truth.height_map_mm(depth)
    assert mask.dtype == bool and not mask[depth == 0].any()
    assert np.nanmax(np.abs(h[mask])) < 100.0
    assert 0.5 < mask.mean() < 0.6


def one_line(exc: pytest.ExceptionInfo) -> str:
    text = str(exc.value)
    assert "\n" not in text
    return text


def test_no_depth_is_refused():
    with pytest.raises(CalibrationError, match="no depth") as exc:
        estimate_mount([np.zeros(K.shape, np.uint16)] * 3, K)
    one_line(exc)
    with pytest.raises(CalibrationError, match="no frames"):
        estimate_mount([], K)


@pytest.mark.slow
def test_no_plane_covering_enough_of_the_view_is_refused():
    rng = np.random.default_rng(0)
    clutter = [rng.integers(1500, 4000, K.shape).astype(np.uint16) for _ in range(3)]
    with pytest.raises(CalibrationError, match="no plane covers enough of the view") as exc:
        estimate_mount(clutter, K)
    assert "radial" not in one_line(exc)
    # a table over 85 % of the view: the floor (15 %) is the farthest plane but too small
    truth = TopViewMount(K, 3000.0)
    table = ((slice(5, 235), slice(10, 305)), 750.0)
    with pytest.raises(CalibrationError, match="no plane covers enough of the view"):
        estimate_mount(frames_of(truth, cover=0.0, tables=(table,)), K)


def as_range(depth: np.ndarray, k: Intrinsics) -> np.ndarray:
    """A depth frame as a radial-distance camera sends it: range along each pixel's ray."""
    v, u = np.indices(k.shape, dtype=np.float64)
    norm = np.sqrt(1.0 + ((u - k.cx) / k.fx) ** 2 + ((v - k.cy) / k.fy) ** 2)
    return np.where(depth > 0, np.rint(depth * norm), 0).astype(np.uint16)


@pytest.mark.parametrize("pitch", [0.0, 4.0])
def test_a_radial_distance_camera_is_found_out_and_its_mount_fitted(pitch):
    """Range along each ray makes the floor a bowl as depth: no plane fits it, but read as
    range it does, and the mount says so."""
    truth = TopViewMount(K, 3300.0, pitch, -1.0)
    frames = frames_of(truth, cover=0.2)
    as_depth = estimate_mount(frames, K)
    assert not as_depth.mount.radial
    est = estimate_mount([as_range(f, K) for f in frames], K)
    assert est.mount.radial
    dh, angle = mount_difference(est.mount, truth)
    assert abs(dh) < 10 and angle < 0.1
    assert abs(est.mount.height_mm - as_depth.mount.height_mm) < 3
    assert "radial distance" in est.summary() and "along the optical axis" in as_depth.summary()
    # the picture's floor is the floor, read through the mount
    mask = floor_mask(as_range(frames[0], K), est.mount)
    assert mask.sum() >= 0.95 * floor_mask(frames[0], as_depth.mount).sum()


def test_readings_of_65535_are_no_plane_below_the_floor():
    """Some cameras send 65535 for "no reading": 20 % of the view so (a band down each side)
    vetoed the true floor as a table top, and the far band came out as the floor."""
    truth = TopViewMount(K, 3300.0, 2.0, -1.0)
    frames = frames_of(truth, cover=0.2)
    for f in frames:
        f[:, :32] = 65535
        f[:, -32:] = 65535
    dh, angle = mount_difference(estimate_mount(frames, K).mount, truth)
    assert abs(dh) < 10 and angle < 0.1


def test_clutter_read_as_range_is_still_refused():
    rng = np.random.default_rng(1)
    clutter = [as_range(rng.integers(1500, 4000, K.shape).astype(np.uint16), K) for _ in range(3)]
    with pytest.raises(CalibrationError, match="no plane covers enough of the view") as exc:
        estimate_mount(clutter, K)
    one_line(exc)


def test_frames_that_disagree_are_refused():
    a = frames_of(TopViewMount(K, 3000.0, 2.0, 0.0), n=2, seed=1)
    b = frames_of(TopViewMount(K, 3000.0, 6.0, 0.0), n=2, seed=2)  # the camera was bumped
    with pytest.raises(CalibrationError, match="frames disagree") as exc:
        estimate_mount(a + b, K)
    one_line(exc)
    c = frames_of(TopViewMount(K, 3300.0, 2.0, 0.0), n=2, seed=3)  # ... or moved up
    with pytest.raises(CalibrationError, match="frames disagree"):
        estimate_mount(a + c, K)


def test_a_crowded_frame_that_found_another_plane_is_dropped_not_refused():
    clear = frames_of(TopViewMount(K, 3000.0, 2.0, 0.0), n=3, seed=4)
    # a frame with only ~20 % floor in view, whose plane is not the others' (a stand-in for
    # a frame where a crowd or a big table hid the floor and RANSAC found some other plane)
    crowded = frames_of(TopViewMount(K, 2400.0, -5.0, 4.0), n=1, seed=5, cover=0.8)
    est = estimate_mount([*clear, *crowded], K)
    assert est.frames_used == 3 and est.frames_given == 4
    assert abs(est.mount.height_mm - 3000.0) < 5.0 and abs(est.mount.pitch_deg - 2.0) < 0.1


def test_a_tilt_beyond_the_supported_range_is_refused():
    truth = TopViewMount(K, 3000.0, 22.0, 5.0)
    with pytest.raises(CalibrationError, match=r"tilted 22\.5 deg") as exc:
        estimate_mount(frames_of(truth, cover=0.2), K)
    one_line(exc)
    # the limit is a setting: 10 deg supported plus a margin by default
    assert CalibrationConfig().max_tilt_deg == 15.0


def test_frames_of_another_camera_are_refused():
    with pytest.raises(CalibrationError, match="does not match"):
        estimate_mount([np.zeros((10, 10), np.uint16)], K)


def an_estimate() -> MountEstimate:
    truth = TopViewMount(Intrinsics(640, 400, 441.25, 441.25, 319.5, 199.5), 2875.0, 3, -1, "oak_d")
    return estimate_mount(frames_of(truth, n=2), truth.intrinsics, "oak_d")


def test_mount_file_round_trip(tmp_path):
    est = an_estimate()
    path = tmp_path / "cell1.json"
    write_mount_file(path, est)
    assert read_mount_file(path) == est.mount
    doc = json.loads(path.read_text())
    assert doc["topseg_mount"] == 1
    assert doc["fit"]["frames_used"] == 2 and doc["fit"]["made_at"] == est.made_at
    assert read_mount_document(path)["fit"]["residual_mm"] == pytest.approx(est.residual_mm, 1e-3)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cell1.json"]  # no temporary left
    assert "radial" not in doc["mount"]
    radial = replace(est, mount=replace(est.mount, radial=True))
    write_mount_file(path, radial)
    assert read_mount_file(path) == radial.mount and json.loads(path.read_text())["mount"]["radial"]


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (None, "no such file"),
        (b'{"topseg_mount": 1, "mount": {"intrinsics"', "not JSON"),
        (b"\x89PNG\r\n\x1a\n", "not a mount file"),
        (b'{"model": 1}', "no 'topseg_mount' key"),
        (b'{"topseg_mount": 7, "mount": {}}', "newer"),
        (b'{"topseg_mount": 1}', "no 'mount' section"),
        (b'{"topseg_mount": 1, "mount": {"height_mm": 3000}}', "missing key 'intrinsics'"),
        (b'{"topseg_mount": 1, "mount": {"intrinsics": {}, "height_mm": 3000}}', "width"),
    ],
)
def test_a_damaged_mount_file_is_one_config_error_line(tmp_path, content, message):
    path = tmp_path / "m.json"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(ConfigError, match=message) as exc:
        read_mount_file(path)
    text = one_line(exc)
    assert str(path) in text


def test_a_damaged_mount_value_names_the_key(tmp_path):
    doc = {"topseg_mount": 1, "mount": an_estimate().mount.to_dict()}
    doc["mount"]["roll_deg"] = "level"
    path = tmp_path / "m.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(ConfigError, match="roll_deg must be a number"):
        read_mount_file(path)
