"""`topseg experiment safety` on one short rendered sequence: a table and JSON with the
decisions scored against the truth."""

import json

import numpy as np
import pytest

from topseg.core import labels
from topseg.core.synth.static_cell import sequence_background
from topseg.services.batch.experiment import safety
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
    # labelled as the safety service's worker labels: without the model's context prior and
    # checks
    assert doc["precision_stages"] == "off"


def test_two_cameras_decide_together_and_see_more_of_the_floor(tmp_path):
    """`--cameras 2`: both cameras' labels feed one monitor; the floor within reach + S_p
    seen (the table's column) is larger than one camera's."""
    runs = {}
    for cameras in (1, 2):
        out = tmp_path / f"safety{cameras}"
        args = ["-q", "experiment", "safety", "--sequences", "1", "--sequence-seconds", "1",
                "--validation", "--cameras", str(cameras), "--out", str(out)]  # fmt: skip
        assert main(args) == 0
        runs[cameras] = json.loads((out / "safety.json").read_text())
    assert runs[2]["cameras"] == 2 and runs[2]["overall"]["frames"] == 15
    assert runs[2]["sequences"][0]["coverage"] > runs[1]["sequences"][0]["coverage"]
    assert "2 cameras" in (tmp_path / "safety2" / "safety.md").read_text()


def test_the_table_says_which_way_the_states_went_wrong():
    overall = {"frames": 10, "states_truth_to_service": {
        "clear->clear": 4, "warning->clear": 2, "stop->warning": 1, "clear->stop": 1,
        "stop->stop": 2, "warning->stop": 0,
    }, "distance_farther_p99_m": 0.2, "distance_nearer_p99_m": 0.05}  # fmt: skip
    md = safety.markdown({"model": "m", "overall": overall, "sequences": []})
    assert "clear -> stop 1, stop -> warning 1, warning -> clear 2; 3 of 4 less strict" in md
    assert "farther than the truth 20.0 cm, nearer 5.0 cm" in md
    none_wrong = {"frames": 1, "states_truth_to_service": {"stop->stop": 1}}
    assert "unlike" not in safety.markdown({"model": "m", "overall": none_wrong, "sequences": []})


def test_a_sequences_static_background_is_its_table_without_people_or_robot():
    """What `--background` gates with: the table's pixels match it, the robot's and the
    people's do not (they stand in front of it)."""
    config = safety.sequence_config(0, 2.0, 15.0)
    seq = safety.draw_sequence(config, safety.VALIDATION_SEED)
    bg = sequence_background(seq)
    frame = next(iter(seq.frames(20, 21)))
    depth = frame.depth.astype(np.float32)
    gated = bg.valid & (np.abs(depth - bg.depth_mm) <= 3 * bg.sigma_mm + 10)
    table = frame.labels == labels.TABLE
    robot = frame.labels == labels.ROBOT
    assert table.any() and robot.any()
    assert gated[table].mean() > 0.9
    assert gated[robot].mean() < 0.05
    people = np.isin(frame.labels, list(labels.HUMAN_IDS))
    if people.any():
        assert gated[people].mean() < 0.05


@pytest.mark.slow
def test_the_experiment_says_when_a_background_gated(tmp_path):
    out = tmp_path / "safety"
    args = ["-q", "experiment", "safety", "--sequences", "1", "--sequence-seconds", "1",
            "--validation", "--background", "--precision-stages", "on", "--out", str(out)]  # fmt: skip
    assert main(args) == 0
    doc = json.loads((out / "safety.json").read_text())
    assert doc["background"] is True and doc["overall"]["frames"] == 15
    assert doc["precision_stages"] == "on"
    assert "static background gating" in (out / "safety.md").read_text()


@pytest.mark.slow
def test_with_labels_a_frame_late_each_frame_is_decided_with_the_earlier_labels(tmp_path):
    out = tmp_path / "safety"
    args = ["-q", "experiment", "safety", "--sequences", "1", "--sequence-seconds", "1",
            "--validation", "--labels-lag", "2", "--out", str(out)]  # fmt: skip
    assert main(args) == 0
    doc = json.loads((out / "safety.json").read_text())
    assert doc["labels_lag"] == 2 and doc["overall"]["frames"] == 15
    assert doc["precision_stages"] == "off"
    assert "labels 2 frames old carried" in (out / "safety.md").read_text()
    assert main([*args[:-2], "--labels-lag", "31", "--out", str(out)]) == 2


def test_a_cell_recording_comes_with_its_cell_file_and_static_background(tmp_path):
    from topseg.core.background import load_background

    out = tmp_path / "cell.mcap"
    args = ["-q", "datagen", "cell-sequence", "--out", str(out), "--duration", "0.5",
            "--fps", "4", "--seed", "3", "--size", "160x120"]  # fmt: skip
    assert main(args) == 0
    bg = load_background(tmp_path / "cell.background.npz")
    assert (bg.intrinsics.width, bg.intrinsics.height) == (160, 120)
    assert bg.valid_share > 0.9 and (tmp_path / "cell.toml").is_file()
