"""`topseg experiment safety` on one short rendered sequence: a table and JSON with the
decisions scored against the truth."""

import json

from topseg.services.cli import main


def test_safety_experiment_scores_a_sequence(tmp_path):
    out = tmp_path / "safety"
    args = ["-q", "experiment", "safety", "--sequences", "1", "--sequence-seconds", "2",
            "--validation", "--out", str(out)]  # fmt: skip
    assert main(args) == 0
    doc = json.loads((out / "safety.json").read_text())
    (row,) = doc["sequences"]
    assert row["robot"] == "panda" and row["frames"] == 30
    overall = doc["overall"]
    assert overall["frames"] == 30 and 0.0 <= overall["state_agreement"] <= 1.0
    assert overall["clear_when_truth_stop"] >= 0
    md = (out / "safety.md").read_text()
    assert "| all |" in md and "state equal" in md
