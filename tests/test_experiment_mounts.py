"""`topseg experiment mounts`: one model scored on rendered frames across mounts and sensors."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

from topseg.core.errors import TopsegError
from topseg.services.batch.experiment import mounts
from topseg.services.cli import main

BUNDLED = Path(__file__).resolve().parents[1] / "models" / "default.npz"


@pytest.mark.slow
def test_every_cell_is_scored_for_both_models_and_the_report_is_written(tmp_path):
    out = tmp_path / "out"
    args = ["experiment", "mounts", "--out", str(out), "--test-frames", "1"]
    args += ["--sensors", "kinect_v1,oak_d", "--baseline", str(BUNDLED)]
    args += ["--baseline-downsample", "1"]  # the same model at the frames' own resolution
    assert main(["-q", *args]) == 0
    doc = json.loads((out / "mounts.json").read_text())
    assert set(doc["cells"]) == {"model", "baseline"}
    assert doc["models"]["model"]["downsample"] == "auto"
    assert doc["models"]["baseline"]["downsample"] == 1
    for cells in doc["cells"].values():
        assert len(cells) == 2 * len(mounts.MOUNTS)
        assert {c["sensor"] for c in cells} == {"kinect_v1", "oak_d"}
        for c in cells:
            assert 0.0 <= c["avg_f1"] <= 1.0 and c["frames"] == 1
            assert "head_detection_precision" in c and "head_detection_recall" in c
    v = doc["verdict"]
    assert 0.0 <= v["lowest_f1"] <= v["reference_f1"] + v["largest_gap"] + 1e-9
    md = (out / "mounts.md").read_text()
    assert md.count("| oak_d |") == 8 and "largest gap" in md  # four tables per model
    assert "(downsample auto)" in md and "(downsample 1)" in md
    assert "Heads as blobs" in md and "bootstrap interval" in md
    assert "reference |" in md and "of 10 (" in md  # the gap table and the cell counts
    for cells in doc["cells"].values():  # one frame a cell: every interval is a single value
        for c in cells:
            assert c["gap_low"] == pytest.approx(c["gap_high"])
    assert (out / "mounts.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the same model both ways at two resolutions: their means and the paired difference
    d = doc["comparison"]
    assert d["difference"] == pytest.approx(d["mean_model"] - d["mean_baseline"])
    assert d["low"] <= d["high"] and "model minus baseline" in md
    # --report-only rewrites the table and figure from mounts.json (edited here), runs no cell
    doc["models"]["model"]["path"] = "renamed.npz"
    (out / "mounts.json").write_text(json.dumps(doc))
    (out / "mounts.png").unlink()
    assert main(["-q", *args, "--report-only"]) == 0
    assert "## model: renamed.npz" in (out / "mounts.md").read_text()
    assert (out / "mounts.png").exists() and json.loads((out / "mounts.json").read_text()) == doc
    with pytest.raises(TopsegError, match="no such file"):
        mounts.read_report(tmp_path)


def _cell(sensor, height, tilt, f1):
    return mounts.Cell(sensor, height, tilt, f1, f1, 0.0, 1)


def test_verdict_measures_gaps_from_the_reference_cell():
    cells = [_cell("kinect_v1", 3.5, 0.0, 0.80), _cell("oak_d", 2.5, 0.0, 0.78)]
    v = mounts.verdict(cells)
    assert v["reference_f1"] == 0.80 and abs(v["largest_gap"] - 0.02) < 1e-12
    assert v["all_within_gap"] and v["none_below_floor"]
    v = mounts.verdict([*cells, _cell("kinect_v2", 4.5, 3.0, 0.69)])
    assert not v["all_within_gap"] and not v["none_below_floor"] and v["lowest_f1"] == 0.69
    assert (v["cells"], v["within_gap"], v["at_least_floor"]) == (3, 2, 2)


def frame_confusions(rng, flip: float, frames: int, shape=(16, 16)):
    """(frames, C, C) confusions of random label maps in which a `flip` share of the
    pixels is predicted as the next class."""
    import numpy as np

    from topseg.core.metrics import confusion_matrix

    out = []
    for _ in range(frames):
        truth = rng.integers(0, 11, shape).astype(np.uint8)
        pred = np.where(rng.random(truth.shape) < flip, (truth + 1) % 11, truth)
        out.append(confusion_matrix(truth, pred.astype(np.uint8)))
    return np.stack(out)


def draws_of(frame_confusions):
    """A cell's bootstrap avg F1 as `run_mounts` keeps it."""
    from topseg.core.metrics import avg_f1_draws

    return avg_f1_draws(frame_confusions, mounts.BOOTSTRAP_DRAWS, mounts.BOOTSTRAP_SEED)


def cells_and_draws(per_cell: list):
    """Cells scored on these per-frame confusions, and their draws, as `run_mounts` keeps them."""
    from topseg.core.metrics import scores

    cells = [
        replace(_cell("oak_d", 2.5, 0.0, scores(cm.sum(0))["avg_f1"]), frames=len(cm))
        for cm in per_cell
    ]
    return cells, [draws_of(cm) for cm in per_cell]


def test_gap_intervals_are_the_paired_bootstrap_of_cell_minus_reference():
    import numpy as np

    from topseg.core.metrics import avg_f1_draws, scores

    rng = np.random.default_rng(5)
    ref, worse = frame_confusions(rng, 0.1, 12, (20, 30)), frame_confusions(rng, 0.4, 12, (20, 30))
    cells = [
        replace(_cell("kinect_v1", 3.5, 0.0, scores(ref.sum(0))["avg_f1"]), frames=12),
        replace(_cell("oak_d", 4.5, 3.0, scores(worse.sum(0))["avg_f1"]), frames=12),
        replace(_cell("oak_d", 2.5, 0.0, 0.5), frames=5),  # fewer frames: no paired interval
    ]
    draws = [draws_of(ref), draws_of(worse), draws_of(ref[:5])]
    got = mounts.with_gap_intervals(cells, draws)
    assert got[0].gap_low == got[0].gap_high == 0.0  # the reference against itself
    d = avg_f1_draws(worse, mounts.BOOTSTRAP_DRAWS) - avg_f1_draws(ref, mounts.BOOTSTRAP_DRAWS, 0)
    assert (got[1].gap_low, got[1].gap_high) == tuple(np.percentile(d, [2.5, 97.5]))
    assert got[1].gap_low < cells[1].avg_f1 - cells[0].avg_f1 < got[1].gap_high
    assert got[1].gap_high < -mounts.MAX_GAP  # 30 % more pixels wrong: beyond sampling
    assert np.isnan(got[2].gap_low)
    assert mounts.verdict(got)["beyond_gap_surely"] == 1
    # without the reference cell there is nothing to measure a gap from
    assert mounts.with_gap_intervals(cells[1:], draws[1:]) == cells[1:]


def test_mean_difference_is_zero_for_a_model_against_itself_and_signed_otherwise():
    import numpy as np

    rng = np.random.default_rng(6)
    good = [frame_confusions(rng, 0.1, 10), frame_confusions(rng, 0.2, 10)]
    same = mounts.mean_difference(*cells_and_draws(good), *cells_and_draws(good))
    assert same["difference"] == same["low"] == same["high"] == 0.0
    worse = [cm.copy() for cm in good]
    for cm in worse:  # a third of every class's hits become misses
        hits = np.diagonal(cm, axis1=1, axis2=2).copy()
        for k in range(cm.shape[1]):
            cm[:, k, k] -= hits[:, k] // 3
            cm[:, k, (k + 1) % cm.shape[1]] += hits[:, k] // 3
    d = mounts.mean_difference(*cells_and_draws(worse), *cells_and_draws(good))
    assert d["high"] < 0 and d["low"] <= d["difference"] <= d["high"]
