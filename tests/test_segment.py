"""`topseg segment`: PNGs and recordings in, label PNGs out, bad input refused clearly."""

import subprocess
import sys

import numpy as np
import pytest
from PIL import Image
from segmenter_rules import relabel_as_the_segmenter

from topseg.core import forest
from topseg.core.camera import KINECT_V1, TopViewMount, metres_to_mm
from topseg.core.forest.inputs import header_fields, model_input, trained_for
from topseg.core.forest.predict import grid_stride
from topseg.core.forest.train import TrainConfig
from topseg.core.formats import recording, wire
from topseg.core.labels import NUM_CLASSES
from topseg.core.segmenter_config import ADAPTIVE_LEVELS
from topseg.core.synth import procedural


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    rng = np.random.default_rng(2)
    frames = [procedural.procedural_frame(rng) for _ in range(4)]
    depth = np.stack([d for d, _ in frames])
    labels = np.stack([lab for _, lab in frames])
    cfg = TrainConfig(
        n_trees=1,
        max_depth=6,
        frames_per_tree=4,
        pixels_per_frame=300,
        n_candidates=10,
        n_thresholds=10,
    )
    path = tmp_path_factory.mktemp("seg") / "m.npz"
    trained = forest.train_forest(depth, labels, cfg, seed=0)
    forest.save_model(path, trained, {})
    return path, trained


def segment(*args):
    return subprocess.run(
        [sys.executable, "-m", "topseg.services.cli", "segment", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_png_and_recording_round_trip(model, tmp_path):
    path, trained = model
    rng = np.random.default_rng(9)
    depth, _ = procedural.procedural_frame(rng)
    Image.fromarray(depth).save(tmp_path / "f.png")
    rec = tmp_path / "r.mcap"
    w = recording.RecordingWriter(rec)
    w.write(wire.depth_key(), wire.encode_depth(wire.DepthFrame(depth, KINECT_V1, seq=7)))
    w.write(wire.depth_key(), b"\x93garbage")
    w.close()
    r = segment(
        tmp_path / "f.png", rec, "--model", path, "--out", tmp_path / "out", "--crf", "none"
    )
    assert r.returncode == 0, r.stderr
    assert "segmented 2 frames" in r.stdout
    assert "damaged" in r.stderr
    expected = forest.predict_labels(trained, depth)
    for name in ("f", "r_000007"):
        got = np.asarray(Image.open(tmp_path / "out" / f"{name}_labels.png"))
        np.testing.assert_array_equal(got, expected)
        ov = Image.open(tmp_path / "out" / f"{name}_overlay.png")
        assert ov.size == (640, 480) and ov.mode == "RGB"


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda p: Image.fromarray(np.zeros((240, 320), np.uint16)).save(p), "trained for 640x480"),
        (lambda p: Image.fromarray(np.zeros((480, 640, 3), np.uint8)).save(p), "16-bit"),
        (lambda p: p.write_bytes(b"\x89PNG\r\n\x1a\n truncated"), "not a readable PNG"),
    ],
)
def test_bad_pngs_are_refused_with_one_line(model, tmp_path, make, message):
    bad = tmp_path / "bad.png"
    make(bad)
    r = segment(bad, "--model", model[0], "--out", tmp_path / "out")
    assert r.returncode == 2
    assert message in r.stderr
    assert "Traceback" not in r.stderr


# --- a height model: the mount from --mount, from the recording, or estimated ----------------

MOUNT = TopViewMount(KINECT_V1, 3200.0, 2.0, -1.0)


def floor_scene(rng, mount, n=3):
    """Procedural frames seen from a tilted `mount` (the floor as a primitive)."""
    floor = procedural.Box(0.0, 0.0, 40.0, 40.0, 0.0, 0.001, 0)
    out = []
    for _ in range(n):
        prims = procedural.random_scene(rng, mount, 3)
        depth_m, lab = procedural.render([*prims, floor], mount)
        out.append((metres_to_mm(depth_m), lab))
    return out


@pytest.fixture(scope="module")
def height_model(tmp_path_factory):
    rng = np.random.default_rng(4)
    frames = floor_scene(rng, MOUNT, 4)
    cfg = TrainConfig(
        n_trees=1,
        max_depth=6,
        frames_per_tree=4,
        pixels_per_frame=300,
        n_candidates=10,
        n_thresholds=10,
    )
    trained = forest.train_forest(
        np.stack([d for d, _ in frames]),
        np.stack([lab for _, lab in frames]),
        cfg,
        seed=0,
        mounts=[MOUNT] * 4,
    )
    path = tmp_path_factory.mktemp("seg") / "h.npz"
    forest.save_model(path, trained, header_fields(cfg.features, trained_for([MOUNT])))
    return path, trained, cfg.features


@pytest.mark.parametrize(
    ("option", "value"),
    [
        ("--stride", "-1"),
        ("--downsample", "0"),
        ("--downsample", "5"),
        ("--adaptive", "-1"),
        ("--early-exit", "0"),
        ("--early-exit", "1.5"),
        ("--min-head-cm2", "-1"),
    ],
)
def test_segment_refuses_a_bad_grid(tmp_path, option, value):
    r = segment(tmp_path, option, value, "--out", tmp_path / "o")
    assert r.returncode == 2 and option in r.stderr and "Traceback" not in r.stderr


@pytest.mark.slow
def test_height_model_estimates_the_mount_of_a_png_folder(height_model, tmp_path):
    path, trained, features = height_model
    frames = floor_scene(np.random.default_rng(5), MOUNT, 3)
    folder = tmp_path / "frames"
    folder.mkdir()
    for i, (depth, _) in enumerate(frames):
        Image.fromarray(depth).save(folder / f"f{i}.png")
    r = segment(
        folder, "--model", path, "--out", tmp_path / "out", "--crf", "none", "--stride", "1",
        "--downsample", "1",
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "estimated mount: height 3.20 m, pitch 2.0 deg, roll -1.0 deg" in r.stdout
    assert "floor noise" in r.stdout and "the kinect_v1 model)" in r.stdout
    assert "segmented 3 frames" in r.stdout and "floor skipped:" in r.stdout
    assert "warning" not in r.stderr
    depth = frames[0][0]
    got = np.asarray(Image.open(tmp_path / "out" / "f0_labels.png"))
    # labelled through (nearly) the true mount: the same labels but at the gate's edge
    expected = forest.predict_labels(trained, model_input(depth, MOUNT, features))
    assert (got == expected).mean() > 0.995


@pytest.mark.slow
def test_a_folder_of_range_images_is_found_out_and_labelled_as_depth(height_model, tmp_path):
    """PNGs from a radial-distance camera (range along each ray): the estimate says so and
    the labels are those of the depth frames they stand for."""
    from topseg.core.camera import depth_to_range

    path, _, _ = height_model
    frames = floor_scene(np.random.default_rng(5), MOUNT, 3)
    for kind, convert in (
        ("depth", lambda d: d),
        ("range", lambda d: depth_to_range(d, KINECT_V1)),
    ):
        folder = tmp_path / kind
        folder.mkdir()
        for i, (depth, _) in enumerate(frames):
            Image.fromarray(convert(depth)).save(folder / f"f{i}.png")
        r = segment(folder, "--model", path, "--out", tmp_path / f"{kind}-out", "--crf", "none")
        assert r.returncode == 0, r.stderr
        assert "estimated mount: height 3.20 m, pitch 2.0 deg, roll -1.0 deg" in r.stdout
        assert ("radial distance read as depth" in r.stdout) == (kind == "range")
    for i in range(3):
        got = np.asarray(Image.open(tmp_path / "range-out" / f"f{i}_labels.png"))
        want = np.asarray(Image.open(tmp_path / "depth-out" / f"f{i}_labels.png"))
        assert (got == want).mean() > 0.995  # depth back from whole-mm range: +-1 mm


@pytest.mark.slow
def test_sensor_names_the_optics_of_pngs(height_model, tmp_path):
    """PNGs say no optics: 640x480 is read as a Kinect v1's unless `--sensor` names another
    camera of that size; one of another size is refused in one line."""
    from topseg.core.sensors import get_sensor

    path, _, _ = height_model
    d435 = TopViewMount(
        get_sensor("realsense_d435").intrinsics, 3200.0, 2.0, -1.0, "realsense_d435"
    )
    folder = tmp_path / "frames"
    folder.mkdir()
    for i, (depth, _) in enumerate(floor_scene(np.random.default_rng(6), d435, 3)):
        Image.fromarray(depth).save(folder / f"f{i}.png")
    common = ["--model", path, "--crf", "none", "--stride", "1", "--downsample", "1"]
    r = segment(folder, "--sensor", "realsense_d435", "--out", tmp_path / "a", *common)
    assert r.returncode == 0, r.stderr
    assert "estimated mount: height 3.20 m, pitch 2.0 deg, roll -1.0 deg" in r.stdout
    assert "the realsense_d435 model)" in r.stdout  # its noise model; noise-free: no smoothing
    r = segment(folder, "--out", tmp_path / "b", *common)  # read with a Kinect v1's optics
    assert r.returncode == 0, r.stderr
    assert "the kinect_v1 model)" in r.stdout
    assert "estimated mount: height 3.20 m, pitch 2.0 deg, roll -1.0 deg" not in r.stdout
    r = segment(folder, "--sensor", "oak_d", "--out", tmp_path / "c", *common)
    assert r.returncode == 2
    assert "640x480 frames that say no intrinsics, but the oak_d's are 640x400" in r.stderr


@pytest.mark.slow
def test_height_model_with_a_mount_file_and_a_recording_that_carries_one(height_model, tmp_path):
    from topseg.core.calibration import estimate_mount
    from topseg.core.formats.mount_file import write_mount_file

    path, trained, features = height_model
    frames = floor_scene(np.random.default_rng(6), MOUNT, 2)
    depth = frames[0][0]
    est = estimate_mount([d for d, _ in frames], KINECT_V1, "kinect_v1")
    write_mount_file(tmp_path / "mount.json", est)
    Image.fromarray(depth).save(tmp_path / "f.png")
    r = segment(
        tmp_path / "f.png", "--mount", tmp_path / "mount.json", "--model", path,
        "--out", tmp_path / "a", "--crf", "none", "--stride", "1", "--downsample", "1",
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "estimated" not in r.stdout
    assert (
        f"mount from {tmp_path / 'mount.json'}: height {est.mount.height_mm / 1000:.2f} m"
        in r.stdout
    )
    expected = forest.predict_labels(trained, model_input(depth, est.mount, features))
    np.testing.assert_array_equal(np.asarray(Image.open(tmp_path / "a" / "f_labels.png")), expected)
    # a recording whose messages carry the mount: used as it is, nothing estimated
    rec = tmp_path / "r.mcap"
    w = recording.RecordingWriter(rec)
    w.write(wire.depth_key(), wire.encode_depth(wire.DepthFrame(depth, KINECT_V1, 3, mount=MOUNT)))
    w.close()
    r = segment(  # stride auto, at the frame's own resolution (the reference's)
        rec, "--model", path, "--out", tmp_path / "b", "--crf", "none", "--downsample", "1"
    )
    assert r.returncode == 0, r.stderr
    assert "estimated" not in r.stdout
    inp = model_input(depth, MOUNT, features)
    expected = forest.predict_labels(trained, inp, grid_stride(MOUNT), ADAPTIVE_LEVELS)
    got = np.asarray(Image.open(tmp_path / "b" / "r_000003_labels.png"))
    np.testing.assert_array_equal(got, expected)


@pytest.mark.slow
def test_height_model_skips_an_input_without_a_floor(height_model, tmp_path):
    path = height_model[0]
    rng = np.random.default_rng(7)
    Image.fromarray(rng.integers(500, 4000, (480, 640)).astype(np.uint16)).save(tmp_path / "n.png")
    r = segment(tmp_path / "n.png", "--model", path, "--out", tmp_path / "out")
    assert r.returncode == 2
    assert "skipped" in r.stderr and "Traceback" not in r.stderr
    assert len([ln for ln in r.stderr.splitlines() if "skipped" in ln]) == 1


@pytest.mark.slow
def test_small_head_and_furniture_blobs_are_relabelled_and_counted(tmp_path):
    """The bundled model on the demo's frames as PNGs (mount estimated): the labels are those
    with every blob kept, then the small head and furniture ones and the satellite heads
    relabelled; the counts are printed."""
    from pathlib import Path

    from topseg.core.holes import fill_holes
    from topseg.core.islands import FURNITURE_COUNTED

    demo = Path(__file__).resolve().parents[1] / "recordings" / "demo.mcap"
    folder = tmp_path / "frames"
    folder.mkdir()
    depths = []
    for msg in recording.read_messages(demo):
        if msg.key.endswith("/depth") and len(depths) < 4:
            depths.append(wire.decode_depth(msg.data).depth)
            Image.fromarray(depths[-1]).save(folder / f"f{len(depths)}.png")
    # at the frames' own resolution, where the rules run on the labels written (at half
    # resolution they run before the labels are brought back: tests/test_segmenter.py)
    kept = segment(
        folder, "--out", tmp_path / "kept", "--min-head-cm2", "0", "--min-furniture-cm2", "0", "--min-plant-cm2", "0",
        "--satellite-head-cm2", "0", "--downsample", "1",
    )  # fmt: skip
    cleaned = segment(folder, "--out", tmp_path / "cleaned", "--downsample", "1")
    assert kept.returncode == 0 == cleaned.returncode, kept.stderr + cleaned.stderr
    assert "relabelled" not in kept.stdout
    relabelled, satellites = np.zeros(NUM_CLASSES, np.int64), 0
    for i, depth in enumerate(depths, 1):
        want = np.array(Image.open(tmp_path / "kept" / f"f{i}_labels.png"))
        depth, _ = fill_holes(depth, KINECT_V1)  # the rules measure the frame as labelled
        small, n = relabel_as_the_segmenter(want, depth, KINECT_V1)
        relabelled, satellites = relabelled + small, satellites + n
        got = np.asarray(Image.open(tmp_path / "cleaned" / f"f{i}_labels.png"))
        np.testing.assert_array_equal(got, want)
    heads, furniture = relabelled[1], relabelled[list(FURNITURE_COUNTED)].sum()
    assert heads > 0 and furniture > 0
    assert (
        f"blobs relabelled as too small: {heads} head (under 50 cm2), {furniture} furniture "
        f"(under 300 cm2, plants 100); head blobs beside a larger head: {satellites} (under "
        "150 cm2) in 4 frames"
    ) in cleaned.stdout
    assert "holes filled: " in cleaned.stdout and "took that surface's depth" in cleaned.stdout
    assert "holes filled: " in kept.stdout  # the filling is not one of the blob rules
