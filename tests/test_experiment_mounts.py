"""`topseg experiment mounts`: one model scored on rendered frames across mounts and sensors."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from topseg.core.errors import TopsegError
from topseg.services.cli import main
from topseg.services.experiment import mounts

BUNDLED = Path(__file__).resolve().parents[1] / "models" / "default.npz"


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
    assert md.count("| oak_d |") == 6 and "largest gap" in md  # three tables per model
    assert "(downsample auto)" in md and "(downsample 1)" in md
    assert "Heads as blobs" in md
    assert (out / "mounts.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
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
