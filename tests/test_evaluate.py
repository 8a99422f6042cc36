"""`topseg evaluate` against a confusion matrix computed by hand with numpy."""

import json
import subprocess
import sys

import numpy as np
import pytest

from topseg.core import forest
from topseg.core import labels as L
from topseg.core.forest.train import TrainConfig
from topseg.core.formats import dataset as D
from topseg.core.labels import LABELS, NO_DEPTH, NUM_CLASSES
from topseg.core.metrics import HeadDetections


def test_scores_match_a_hand_computed_confusion_matrix(data, tmp_path):
    ds = D.open_dataset(data)
    model = forest.train_forest(
        ds.depth,
        ds.labels,
        TrainConfig(
            n_trees=1,
            max_depth=6,
            frames_per_tree=6,
            pixels_per_frame=300,
            n_candidates=10,
            n_thresholds=10,
        ),
        seed=1,
    )
    forest.save_model(tmp_path / "m.npz", model, {})
    out = tmp_path / "ev"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "topseg.services.cli",
            "evaluate",
            "--model",
            str(tmp_path / "m.npz"),
            "--data",
            str(data),
            "--crf",
            "none",
            "--frames",
            "5",
            "--json",
            str(out / "s.json"),
            "--plots",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    )
    doc = json.loads((out / "s.json").read_text())

    cm = np.zeros((NUM_CLASSES, NUM_CLASSES), np.int64)
    for i in range(5):
        truth = np.asarray(ds.labels[i]).ravel()
        pred = forest.predict_labels(model, np.asarray(ds.depth[i])).ravel()
        keep = truth != NO_DEPTH
        pred = np.where(pred[keep] == NO_DEPTH, 0, pred[keep])
        cm += np.bincount(truth[keep] * NUM_CLASSES + pred, minlength=NUM_CLASSES**2).reshape(
            cm.shape
        )
    np.testing.assert_array_equal(np.array(doc["confusion"]), cm)
    heads = HeadDetections()
    for i in range(5):
        heads.add(np.asarray(ds.labels[i]), forest.predict_labels(model, np.asarray(ds.depth[i])))
    assert doc["head_detections"] == heads.to_dict()

    # the scores of that matrix, by hand: 0/0 is undefined and left out of the means
    tp = np.diag(cm).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        precision, recall = tp / cm.sum(0), tp / cm.sum(1)
    assert doc["mAP"] == pytest.approx(np.nanmean(precision[1:]), abs=1e-12)
    assert doc["mAR"] == pytest.approx(np.nanmean(recall[1:]), abs=1e-12)
    for c in range(1, NUM_CLASSES):
        got = doc["per_class"][LABELS[c].name]
        if np.isnan(precision[c]):
            assert got["precision"] is None
        else:
            assert got["precision"] == pytest.approx(precision[c], abs=1e-12)
    assert "mean (1-10)" in r.stdout
    assert heads.summary() in r.stdout
    assert (out / "confusion.png").stat().st_size > 10_000
    assert (out / "frames.png").stat().st_size > 10_000


def test_a_height_model_is_scored_through_each_frames_mount(data, tmp_path):
    from topseg.core.forest.inputs import dataset_mount, header_fields, model_input, trained_for
    from topseg.core.forest.predict import grid_stride
    from topseg.core.resolution import (
        auto_downsample,
        decimate,
        decimated_mount,
        upsample_labels,
    )
    from topseg.core.segmenter_config import ADAPTIVE_LEVELS

    ds = D.open_dataset(data)
    config = TrainConfig(
        n_trees=1,
        max_depth=6,
        frames_per_tree=6,
        pixels_per_frame=300,
        n_candidates=10,
        n_thresholds=10,
    )
    mounts = [dataset_mount(ds, i) for i in range(len(ds))]
    model = forest.train_forest(ds.depth, ds.labels, config, seed=1, mounts=mounts)
    forest.save_model(
        tmp_path / "h.npz", model, header_fields(config.features, trained_for(mounts))
    )
    r = subprocess.run(
        [sys.executable, "-m", "topseg.services.cli", "evaluate", "--model",
         str(tmp_path / "h.npz"), "--data", str(data), "--crf", "none", "--frames", "3",
         "--json", str(tmp_path / "s.json")],
        capture_output=True, text=True, timeout=300, check=True,
    )  # fmt: skip
    assert "floor skipped:" in r.stdout
    cm = np.zeros((NUM_CLASSES, NUM_CLASSES), np.int64)
    for i in range(3):
        m = mounts[i]
        h, w = m.intrinsics.shape
        depth = np.asarray(ds.depth[i])[:h, :w]
        truth = np.asarray(ds.labels[i])[:h, :w].ravel()
        # at the working resolution (halved where a pixel spans little of the floor), walked
        # on that mount's grid and brought back by depth, as by default
        f = auto_downsample(m)
        small, sm = (depth, m) if f == 1 else (decimate(depth, f), decimated_mount(m, f))
        inp = model_input(small, sm, config.features)
        pred = forest.predict_labels(model, inp, grid_stride(sm), ADAPTIVE_LEVELS)
        if f > 1:
            pred = upsample_labels(depth, pred, small, f)
        pred = pred.ravel()
        keep = truth != NO_DEPTH
        pred = np.where(pred[keep] == NO_DEPTH, 0, pred[keep])
        cm += np.bincount(truth[keep] * NUM_CLASSES + pred, minlength=NUM_CLASSES**2).reshape(
            cm.shape
        )
    doc = json.loads((tmp_path / "s.json").read_text())
    assert doc["stride"] == doc["downsample"] == "auto" and doc["adaptive"] == ADAPTIVE_LEVELS
    np.testing.assert_array_equal(np.array(doc["confusion"]), cm)


@pytest.mark.slow
def test_smoothness_is_the_crfs_potts_weight(data, tmp_path):
    from topseg.core.crf import CRFConfig
    from topseg.core.scoring import dataset_frames, score
    from topseg.core.segmenter import Segmenter, SegmenterConfig
    from topseg.core.segmenter_config import PostConfig

    ds = D.open_dataset(data)
    config = TrainConfig(
        n_trees=1, max_depth=6, frames_per_tree=6, pixels_per_frame=300, n_candidates=10,
        n_thresholds=10,
    )  # fmt: skip
    model = forest.train_forest(ds.depth, ds.labels, config, seed=1)
    forest.save_model(tmp_path / "m.npz", model, {})
    docs = {}
    for s in ("0", "5"):
        subprocess.run(
            [sys.executable, "-m", "topseg.services.cli", "evaluate", "--model",
             str(tmp_path / "m.npz"), "--data", str(data), "--frames", "3", "--smoothness", s,
             "--min-head-cm2", "0", "--min-furniture-cm2", "0", "--min-plant-cm2", "0",
             "--satellite-head-cm2", "0",
             "--json",
             str(tmp_path / f"s{s}.json")],
            capture_output=True, text=True, timeout=300, check=True,
        )  # fmt: skip
        docs[s] = json.loads((tmp_path / f"s{s}.json").read_text())
    # no weight on a cut edge (and every blob kept): the CRF keeps the forest's argmax
    assert docs["0"]["smoothness"] == 0.0
    assert docs["0"]["per_class"] == docs["0"]["forest_only"]["per_class"]
    # a weight of 5 nats: what the Segmenter labels with that CRF, and not the argmax
    segmenter = Segmenter(
        model,
        {},
        SegmenterConfig(
            post=PostConfig(
                min_head_cm2=0, min_furniture_cm2=0, min_plant_cm2=0, satellite_head_cm2=0
            )
        ),
        crf=CRFConfig(mode="realtime", smoothness=5.0),
    )
    want = score(segmenter, dataset_frames(ds, range(3))).crf.confusion
    assert docs["5"]["smoothness"] == 5.0
    np.testing.assert_array_equal(np.array(docs["5"]["confusion"]), want)
    assert docs["5"]["confusion"] != docs["0"]["confusion"]


def test_robots_and_objects_get_their_rows_and_the_twelve_class_means(tmp_path):
    from topseg.core.synth import procedural

    path = tmp_path / "open.zarr"
    attrs = D.make_attrs(
        seed=6, mode="procedural", noise="none", room=None, generator={"name": "t"}, frames=4
    )
    rng = np.random.default_rng(6)
    with D.DatasetWriter.open(path, attrs) as w:
        fw = D.FrameWriter(path)
        for i in range(4):
            depth, labels = procedural.procedural_frame(rng)
            labels[labels == L.TABLE] = L.ROBOT  # tables become robots, other furniture objects
            labels[np.isin(labels, L.FURNITURE_IDS)] = L.OBJECT
            fw.write(i, depth, labels, {"index": i})
        w.mark_complete(range(4))
    ds = D.open_dataset(path)
    config = TrainConfig(
        n_trees=1, max_depth=6, frames_per_tree=4, pixels_per_frame=300, n_candidates=10,
        n_thresholds=10,
    )  # fmt: skip
    model = forest.train_forest(ds.depth, ds.labels, config, seed=1)
    assert model.n_classes == L.NUM_CLASSES
    forest.save_model(tmp_path / "m.npz", model, {})
    r = subprocess.run(
        [sys.executable, "-m", "topseg.services.cli", "evaluate", "--model",
         str(tmp_path / "m.npz"), "--data", str(path), "--crf", "none", "--json",
         str(tmp_path / "s.json")],
        capture_output=True, text=True, timeout=300, check=True,
    )  # fmt: skip
    doc = json.loads((tmp_path / "s.json").read_text())
    rows = [line.split()[0] for line in r.stdout.splitlines() if line.strip()]
    assert "robot" in rows and "object" in rows
    assert doc["per_class"]["robot"]["support"] > 0
    assert doc["mAP"] != pytest.approx(doc["mAP_10"])
    assert "mean (1-10)" in r.stdout and "mean (1-12)" in r.stdout
    assert f"{doc['mAP']:.3f}" in r.stdout and f"{doc['mAP_10']:.3f}" in r.stdout
