"""`topseg segment`: PNGs and recordings in, label PNGs out, bad input refused clearly."""

import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from topseg.core import forest
from topseg.core.camera import KINECT_V1
from topseg.core.forest.train import TrainConfig
from topseg.core.formats import recording, wire
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
