"""The static cell's recorded background: the fit, the file, the gate kernel against its numpy
reference, and the Segmenter's background stage (people stay foreground, fixtures that went
are counted, and without a background nothing changes)."""

from __future__ import annotations

import zipfile
from dataclasses import replace

import numpy as np
import pytest
from reference import gate_background_reference

from topseg.core import labels as L
from topseg.core.background import (
    MAX_GATE_MM,
    BackgroundFileError,
    GateGrid,
    background_id,
    fit_background,
    gate_background,
    gate_grid,
    load_background,
    save_background,
)
from topseg.core.camera import KINECT_V1, TopViewMount, depth_to_range
from topseg.core.errors import TopsegError
from topseg.core.segmenter import Segmenter
from topseg.core.segmenter_config import BackgroundConfig, SegmenterConfig
from topseg.core.sensors import depth_sigma_mm

K = KINECT_V1.scaled_to(160, 120)
MOUNT = TopViewMount(K, 3000.0, sensor="kinect_v1")
TABLE = (slice(20, 60), slice(20, 80))  # a table top 0.75 m up
CABINET = (slice(70, 110), slice(100, 140))  # a cabinet 1.8 m up: a person's height


def cell_depth() -> np.ndarray:
    """The empty cell's true depth (mm): floor, a table and a tall cabinet."""
    depth = np.full(K.shape, 3000.0)
    depth[TABLE] = 2250.0
    depth[CABINET] = 1200.0
    return depth


def noisy(depth: np.ndarray, rng, scale: float = 1.0) -> np.ndarray:
    """One frame of `depth` with the Kinect v1's depth noise (times `scale`)."""
    sigma = scale * depth_sigma_mm(depth, "kinect_v1")
    return np.rint(depth + rng.normal(0.0, 1.0, depth.shape) * sigma).astype(np.uint16)


@pytest.fixture(scope="module")
def recorded():
    """30 noisy frames of the empty cell and their background."""
    rng = np.random.default_rng(1)
    frames = [noisy(cell_depth(), rng) for _ in range(30)]
    return frames, fit_background(frames, K, "kinect_v1", MOUNT, source="test")


@pytest.fixture(scope="module")
def background_file(recorded, tmp_path_factory):
    path = tmp_path_factory.mktemp("bg") / "cell.npz"
    save_background(path, recorded[1])
    return path


# ---------------------------------------------------------------------------- fit


def test_the_fit_recovers_depth_and_noise():
    rng = np.random.default_rng(2)
    truth = cell_depth()
    frames = [noisy(truth, rng, scale=2.0) for _ in range(60)]  # twice the model's noise
    bg = fit_background(frames, K, "kinect_v1")
    assert bg.valid.all() and bg.unstable_px == 0
    # a median of 60 readings: its error is about 1.25 sigma / sqrt(60), 4 mm at the floor
    error = np.abs(bg.depth_mm - truth)
    assert error.mean() < 4.0 and np.percentile(error, 99.9) < 20.0
    want = 2.0 * depth_sigma_mm(truth, "kinect_v1")
    ratio = bg.sigma_mm / want
    assert 0.85 < np.median(ratio) < 1.15 and np.percentile(ratio, 95) < 1.5
    # a camera quieter than its model: the model's noise is the floor
    quiet = fit_background([np.rint(truth).astype(np.uint16)] * 6, K, "kinect_v1")
    np.testing.assert_allclose(quiet.sigma_mm, depth_sigma_mm(truth, "kinect_v1"), rtol=1e-6)


def test_one_pixel_noisier_than_its_neighbours_does_not_widen_the_gate():
    rng = np.random.default_rng(10)
    truth = cell_depth()
    frames = [noisy(truth, rng) for _ in range(60)]
    for f in frames:  # one floor pixel reads 2.5 times as noisy (still not unstable)
        f[90, 30] = np.uint16(round(3000 + 2.5 * (float(f[90, 30]) - 3000)))
    bg = fit_background(frames, K, "kinect_v1")
    assert bg.valid[90, 30]
    assert bg.sigma_mm[90, 30] < 1.3 * np.median(bg.sigma_mm[85:95, 25:35])


def test_pixels_that_moved_or_had_no_reading_are_not_background():
    rng = np.random.default_rng(3)
    frames = []
    for i in range(40):
        f = noisy(cell_depth(), rng)
        if i % 4 == 0:  # a robot arm through the left edge in a quarter of the frames
            f[:, :10] = 1500
        if i % 2 == 0:  # no reading half the time in the top right corner
            f[:8, -8:] = 0
        f[-5:, :5] = 65535  # "no reading" in every frame
        frames.append(f)
    bg = fit_background(frames, K, "kinect_v1")
    assert not bg.valid[:, :10].any() and not bg.valid[:8, -8:].any()
    assert not bg.valid[-5:, :5].any()
    assert bg.valid[:, 12:-10].all()
    # the arm's pixels but the 25 that never had a reading are unstable
    assert bg.unstable_px == 120 * 10 - 25 and bg.unstable_share == pytest.approx(1175 / 19200)
    assert bg.valid_share == pytest.approx(1 - (1200 + 64) / 19200)
    text = bg.summary()
    assert "background   93.4 %" in text and "unstable      6.1 %" in text and bg.id in text


def test_an_edge_flickering_between_two_surfaces_is_not_background():
    rng = np.random.default_rng(4)
    frames = []
    for i in range(20):
        f = noisy(cell_depth(), rng)
        f[:, 85] = 2250 if i % 2 else 3000  # half table, half floor
        frames.append(f)
    bg = fit_background(frames, K, "kinect_v1")
    assert not bg.valid[:, 85].any() and bg.valid[:, 90].all()


def test_the_fit_refuses_too_few_frames_or_another_size():
    f = np.full(K.shape, 3000, np.uint16)
    with pytest.raises(TopsegError, match="at least 5 frames"):
        fit_background([f] * 4, K)
    with pytest.raises(TopsegError, match=r"frame 3 is uint16 \(60, 80\)"):
        fit_background([f, f, f[::2, ::2], f, f], K)


# ---------------------------------------------------------------------------- file


def test_the_file_round_trips(recorded, background_file):
    bg = recorded[1]
    back = load_background(background_file, K)
    assert back.id == bg.id == background_id(K, bg.depth_mm, bg.sigma_mm, bg.valid)
    for name in ("depth_mm", "sigma_mm", "valid"):
        np.testing.assert_array_equal(getattr(back, name), getattr(bg, name))
    assert (back.intrinsics, back.mount, back.sensor, back.frames) == (K, MOUNT, "kinect_v1", 30)
    assert back.source == "test" and back.created == bg.created


def rezip(src, dst, change):
    """`src` rewritten member by member into `dst`, `change(name, data)` giving new bytes."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for info in zin.infolist():
            zout.writestr(info.filename, change(info.filename, zin.read(info.filename)))


def npy(array) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()


def test_a_damaged_or_foreign_file_is_one_line_naming_it(background_file, tmp_path):
    raw = background_file.read_bytes()
    cases = {
        "missing.npz": (None, "no such file"),
        "text.npz": (b"hello", "not a zip archive"),
        "cut.npz": (raw[: len(raw) // 2], "damaged or truncated"),
    }
    for name, (data, why) in cases.items():
        path = tmp_path / name
        if data is not None:
            path.write_bytes(data)
        with pytest.raises(BackgroundFileError) as err:
            load_background(path)
        assert str(err.value).startswith(f"background file {path}: ") and why in str(err.value)
        assert "\n" not in str(err.value)

    def changed(what):
        def change(name, data):
            if name == "depth_mm.npy" and what == "values":
                arr = np.load(__import__("io").BytesIO(data))
                arr[0, 0] += 100.0  # a valid zip whose arrays are not the id's
                return npy(arr)
            if name == "sigma_mm.npy" and what == "shape":
                return npy(np.zeros((2, 2), np.float32))
            if name == "valid.npy" and what == "dtype":
                return npy(np.zeros(K.shape, np.uint8))
            return data

        return change

    for what, why in (
        ("values", "do not match its id"),
        ("shape", r"array 'sigma_mm' is float32 \(2, 2\); its camera needs float32 \(120, 160\)"),
        ("dtype", "array 'valid' is uint8"),
    ):
        path = tmp_path / f"{what}.npz"
        rezip(background_file, path, changed(what))
        with pytest.raises(BackgroundFileError, match=why):
            load_background(path)
    newer = tmp_path / "newer.npz"
    header = b'{"magic": "topseg-background", "format_version": 2}'
    rezip(background_file, newer, lambda n, d: npy(np.frombuffer(header, np.uint8)) if n == "header.npy" else d)  # fmt: skip
    with pytest.raises(BackgroundFileError, match="format version 2; this topseg reads version 1"):
        load_background(newer)
    model = tmp_path / "model.npz"
    rezip(background_file, model, lambda n, d: npy(np.frombuffer(b'{"magic": "x"}', np.uint8)) if n == "header.npy" else d)  # fmt: skip
    with pytest.raises(BackgroundFileError, match="not a background file"):
        load_background(model)


def test_another_camera_is_refused_at_load(background_file):
    with pytest.raises(BackgroundFileError, match=r"recorded with another camera \(160x120"):
        load_background(background_file, KINECT_V1)
    with pytest.raises(BackgroundFileError, match="another camera"):
        load_background(background_file, replace(K, fx=K.fx * 1.05))
    load_background(background_file, replace(K, fx=K.fx * 1.001))  # within rounding: the same
    config = SegmenterConfig(mount=TopViewMount(KINECT_V1, 3000.0), background=BackgroundConfig(str(background_file)))  # fmt: skip
    with pytest.raises(BackgroundFileError, match="another camera"):
        Segmenter.from_file(None, config)


# ---------------------------------------------------------------------------- gate


@pytest.mark.parametrize("apply", [True, False])
def test_the_gate_kernel_is_its_numpy_reference(apply):
    rng = np.random.default_rng(5)
    for shape in ((1, 1), (7, 13), (48, 64)):
        depth = rng.integers(0, 4000, shape).astype(np.uint16)
        values = np.where(rng.random(shape) < 0.1, 0, depth).astype(np.uint16)
        background = (depth + rng.normal(0, 60, shape)).astype(np.float32)
        tolerance = rng.uniform(-1, 100, shape).astype(np.float32)
        gate = rng.random(shape) < 0.2
        want, matched, missing = gate_background_reference(
            depth, values, background, tolerance, gate, apply
        )
        read_only = depth.copy()
        read_only.flags.writeable = False
        for d in (depth, read_only):
            got = gate.copy()
            counts = gate_background(d, values, GateGrid(background, tolerance, 0), got, apply)
            assert counts == (matched, missing)
            np.testing.assert_array_equal(got, want)


def test_the_grid_is_sampled_like_decimate_and_read_as_depth_for_a_range_camera(recorded):
    bg = recorded[1]
    grid = gate_grid(bg, 2, 3.0, 10.0)
    np.testing.assert_array_equal(grid.depth_mm, bg.depth_mm[::2, ::2])
    tol = np.minimum(3.0 * bg.sigma_mm[::2, ::2] + 10.0, MAX_GATE_MM)
    np.testing.assert_allclose(grid.tolerance, tol, rtol=1e-6)
    assert grid.valid_px == bg.valid[::2, ::2].sum()
    # a range camera: the frame is read as depth, and so is its background
    rng = np.random.default_rng(6)
    ranges = [depth_to_range(noisy(cell_depth(), rng), K) for _ in range(10)]
    radial = fit_background(ranges, K, "kinect_v1")
    axis = gate_grid(radial, 1, 3.0, 10.0, radial=True)
    assert np.abs(axis.depth_mm - cell_depth()).max() < 30  # a median of 10 readings
    assert np.abs(radial.depth_mm - cell_depth()).max() > 300  # as sent: range, corners deeper


# ---------------------------------------------------------------------------- stage


@pytest.fixture(scope="module")
def segmenters(background_file):
    """The bundled model without and with the recorded background."""
    without = Segmenter.from_file(None, SegmenterConfig(mount=MOUNT))
    config = SegmenterConfig(mount=MOUNT, background=BackgroundConfig(str(background_file)))
    return without, Segmenter.from_file(None, config)


def test_a_segmenter_given_a_background_labels_as_one_loaded_with_it(segmenters):
    without, with_bg = segmenters
    gated = without.with_background(with_bg.background)
    assert without.background is None and gated.model_id == without.model_id
    frame = noisy(cell_depth(), np.random.default_rng(3))
    np.testing.assert_array_equal(gated.label(frame).labels, with_bg.label(frame).labels)


def test_a_person_on_a_background_table_stays_foreground(segmenters):
    without, with_bg = segmenters
    rng = np.random.default_rng(7)
    truth = cell_depth()
    person = (slice(30, 50), slice(60, 90))  # over the table's edge and the floor beside it
    truth[person] = 1400.0  # a head 1.6 m up
    truth[26:54, 56:94][truth[26:54, 56:94] > 1400] = 1700  # shoulders around it
    frame = noisy(truth, rng)
    got, plain = with_bg.label(frame), without.label(frame)
    person_px = truth < 2000
    person_px[CABINET] = False
    assert got.background_gated
    # the gate took the table, the floor and the cabinet and none of the person
    static = ~person_px
    assert (got.labels[static] == L.BACKGROUND).mean() > 0.99
    assert got.counts["background_px"] > 0.95 * static.sum()
    # (what the model itself calls background on this box-shaped person stays its call)
    kept = (got.labels[person_px] != L.BACKGROUND).mean()
    assert kept >= (plain.labels[person_px] != L.BACKGROUND).mean() - 0.02 and kept > 0.9
    # the person's own labels: as without the background, but where the CRF's neighbours
    # changed (a few pixels at its edge)
    assert (got.labels[person_px] == plain.labels[person_px]).mean() > 0.95
    # without it the cabinet, as tall as a person, is not background
    assert (plain.labels[CABINET] != L.BACKGROUND).mean() > 0.5
    assert got.floor_share == plain.floor_share  # the floor gate's own share, as before


def test_a_fixture_that_went_is_counted_missing_and_not_gated(segmenters, recorded):
    _, with_bg = segmenters
    rng = np.random.default_rng(8)
    truth = cell_depth()
    truth[CABINET] = 3000.0  # the cabinet was taken away: floor where it stood
    got = with_bg.label(noisy(truth, rng))
    cabinet = 40 * 40
    assert cabinet <= got.counts["background_missing_px"] < cabinet + 20
    valid = recorded[1].valid[::2, ::2].sum() if got.downsample == 2 else recorded[1].valid.sum()
    assert got.background_missing_share == pytest.approx(
        got.counts["background_missing_px"] / valid
    )
    assert (
        got.counts["background_px"]
        < with_bg.label(noisy(cell_depth(), rng)).counts["background_px"]
    )


def test_measuring_only_gates_nothing_and_counts_the_same(segmenters):
    without, with_bg = segmenters
    rng = np.random.default_rng(9)
    truth = cell_depth()
    truth[CABINET] = 3000.0
    frame = noisy(truth, rng)
    measured = with_bg.label(frame, gate_background=False)
    gated = with_bg.label(frame)
    plain = without.label(frame)
    np.testing.assert_array_equal(measured.labels, plain.labels)
    assert not measured.background_gated and measured.counts["background_px"] == 0
    assert measured.counts["background_missing_px"] == gated.counts["background_missing_px"] > 0


def test_frames_of_another_camera_are_refused_naming_the_file(segmenters, background_file):
    _, with_bg = segmenters
    other = TopViewMount(KINECT_V1.scaled_to(80, 60), 3000.0)
    with pytest.raises(TopsegError, match=f"background file {background_file} was recorded"):
        with_bg.label(np.full((60, 80), 3000, np.uint16), mount=other)


@pytest.mark.slow
def test_without_a_background_labels_are_those_of_the_stages_before_it():
    """No background: the stage changes nothing; labels are bit-identical to the Segmenter's
    path without the stage, on rendered frames with the bundled model."""
    from topseg.core.synth.synthesis import SynthesisConfig, Synthesizer

    mount = TopViewMount(K, 3300.0, 2.0, -1.0, "kinect_v1")
    seg = Segmenter.from_file(None, SegmenterConfig(mount=mount))
    before = Segmenter.from_file(None, SegmenterConfig(mount=mount))
    before.stages = tuple(s for s in before.stages if s.name != "background")
    assert "background" in seg.stage_names and "background" not in before.stage_names
    with Synthesizer(SynthesisConfig(mode="modeled", seed=11, camera=mount, noise="kinect")) as synth:  # fmt: skip
        for seed in range(3):
            depth = synth.render(seed).depth
            got, want = seg.label(depth), before.label(depth)
            np.testing.assert_array_equal(got.labels, want.labels)
            assert got.floor_share == want.floor_share
            assert got.counts == {**want.counts, "background_px": 0, "background_missing_px": 0}
            assert not got.background_gated and got.background_missing_share == 0.0


def test_the_settings_read_off_and_refuse_a_bad_value():
    from topseg.services import cli

    argv = ["worker", "--background", "off", "--background-sigmas", "2.5"]
    args = cli.build_parser(argv).parse_args(argv)
    assert (args.background, args.background_sigmas) == (None, 2.5)
    with pytest.raises(TopsegError, match=r"--background-mismatch must be in"):
        cli.build_parser(["worker"]).parse_args(["worker", "--background-mismatch", "0"])
    with pytest.raises(TopsegError, match="background sigmas must be > 0"):
        BackgroundConfig(sigmas=0.0)
