"""`topseg train` end to end on a small procedural dataset: Dask = serial, resume, header."""

import subprocess
import sys

import numpy as np
import pytest

from topseg.core import forest
from topseg.core.forest.features import FeatureConfig
from topseg.core.forest.train import TrainConfig
from topseg.core.formats import dataset as D

SMALL = [
    "--trees",
    "2",
    "--depth",
    "8",
    "--frames-per-tree",
    "10",
    "--pixels-per-frame",
    "400",
    "--features",
    "40",
    "--responses",
    "20",
    "--thresholds",
    "20",
    "--seed",
    "3",
]


def topseg(*args, check=True):
    return subprocess.run(
        [sys.executable, "-m", "topseg.services.cli", *args],
        capture_output=True,
        text=True,
        timeout=300,
        check=check,
    )


def test_dask_training_equals_serial_and_in_process(data, tmp_path):
    topseg(
        "train", "--data", str(data), "--out", str(tmp_path / "dask.npz"), "--workers", "2", *SMALL
    )
    topseg("train", "--data", str(data), "--out", str(tmp_path / "serial.npz"), "--serial", *SMALL)
    a, ha = forest.load_model(tmp_path / "dask.npz")
    b, _ = forest.load_model(tmp_path / "serial.npz")
    for name, arr in a.arrays().items():
        np.testing.assert_array_equal(arr, b.arrays()[name], err_msg=name)
    assert not (tmp_path / "dask.npz.parts").exists()

    # the same trees as core's serial trainer on the same training frames
    from topseg.services.batch.train import FrameSubset, split_frames

    ds = D.open_dataset(data)
    train_idx, val_idx = split_frames(len(ds), 0.1, 3)
    config = TrainConfig(
        n_trees=2,
        max_depth=8,
        frames_per_tree=10,
        pixels_per_frame=400,
        n_candidates=20,
        n_thresholds=20,
        features=FeatureConfig(n_features=40),
    )
    from topseg.core.forest.inputs import dataset_mount

    c = forest.train_forest(
        FrameSubset(ds.depth, train_idx),
        FrameSubset(ds.labels, train_idx),
        config,
        seed=3,
        mounts=lambda k: dataset_mount(ds, train_idx[k]),
    )
    for name, arr in c.arrays().items():
        np.testing.assert_array_equal(arr, a.arrays()[name], err_msg=name)

    val = ha["validation"]
    assert val["frames"] == len(val_idx) == 1
    assert 0.0 <= val["scores"]["mAR"] <= 1.0
    assert ha["recipe"]["config"]["max_depth"] == 8
    # a height model, saying what it was trained for
    assert ha["input"] == "height" and ha["features"]["n_features"] == 40
    # probes off the image read the nearest edge pixel, unless asked otherwise
    assert ha["features"]["off_image"] == ha["forest"]["off_image"] == "nearest"
    assert a.nearest_off_image and ha["features"]["edge_gaps"] == "nearest"
    out = tmp_path / "bg.npz"
    topseg("train", "--data", str(data), "--out", str(out), "--serial", "--off-image",
           "background", "--edge-gaps", "background", *SMALL)  # fmt: skip
    bg, hb = forest.load_model(out)
    assert not bg.nearest_off_image and hb["forest"]["off_image"] == "background"
    assert hb["features"]["edge_gaps"] == "background"
    bad = topseg("train", "--data", str(data), "--out", str(out), "--off-image", "mirror",
                 check=False)  # fmt: skip
    assert bad.returncode == 2 and "--off-image" in bad.stderr
    mounts = [dataset_mount(ds, i) for i in train_idx]
    tf = ha["trained_for"]
    assert tf["height_mm"] == [min(m.height_mm for m in mounts), max(m.height_mm for m in mounts)]
    assert tf["sensors"] and tf["resolutions"]


@pytest.mark.slow
def test_resume_keeps_finished_trees_and_discards_damaged_ones(data, tmp_path):
    out = tmp_path / "m.npz"
    topseg("train", "--data", str(data), "--out", str(out), "--serial", *SMALL)
    whole, _ = forest.load_model(out)
    # simulate an interrupted run: tree 0 finished, tree 1's part damaged
    parts = tmp_path / "m.npz.parts"
    parts.mkdir()
    from topseg.services.batch.train import train_one_tree  # noqa: F401  (the task the parts come from)

    forest.save_model(
        parts / "tree-0.npz", forest.Forest.from_trees([whole.tree(0)]), {"recipe": _recipe_of(out)}
    )
    (parts / "tree-1.npz").write_bytes(b"PK\x03\x04 damaged")
    out.unlink()
    r = topseg("-v", "train", "--data", str(data), "--out", str(out), "--serial", *SMALL)
    assert "1 of 2 trees already trained" in r.stderr
    assert "damaged" in r.stderr
    again, _ = forest.load_model(out)
    for name, arr in again.arrays().items():
        np.testing.assert_array_equal(arr, whole.arrays()[name], err_msg=name)


def _recipe_of(model_path):
    return forest.load_model(model_path)[1]["recipe"]


def test_bad_dataset_path_is_one_clear_line(tmp_path):
    r = topseg(
        "train", "--data", str(tmp_path / "missing"), "--out", str(tmp_path / "m.npz"), check=False
    )
    assert r.returncode == 2
    assert "error" in r.stderr and "missing" in r.stderr
    assert "Traceback" not in r.stderr
