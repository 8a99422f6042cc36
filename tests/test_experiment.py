"""`topseg experiment` at the tiny scale: every experiment writes its files, reruns resume,
and the paper's numbers in core/paper_results.py are the ones in the paper's .tex."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from topseg.services.batch.experiment import EXPERIMENTS, paper_results
from topseg.services.cli import main

#: the paper's experiments (`mounts` scores a given model and has its own test module)
PAPER_EXPERIMENTS = tuple(e for e in EXPERIMENTS if e not in ("mounts", "open-world", "safety"))
TEX = Path(__file__).resolve().parents[2] / "shared" / "paper" / "sharma2016.tex"


def _run(out: Path, cache: Path, experiment: str, *extra: str) -> int:
    args = ["experiment", experiment, "--scale", "tiny", "--out", str(out)]
    return main(["-q", *args, "--data-cache", str(cache), *extra])


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    """Every experiment at the tiny scale, sharing one data cache (datasets made once)."""
    root = tmp_path_factory.mktemp("experiment")
    out, cache = root / "out", root / "cache"
    for name in PAPER_EXPERIMENTS:
        assert _run(out, cache, name) == 0, name
    return out, cache


@pytest.mark.slow
@pytest.mark.parametrize("name", PAPER_EXPERIMENTS)
def test_experiment_writes_table_json_and_plot(results, name):
    out, _ = results
    doc = json.loads((out / f"{name}.json").read_text())
    assert doc["scale"] == "tiny" and doc["crf"] == "realtime"
    assert doc["finished"] == doc["points_total"] >= 2 and not doc["missing"]
    for p in doc["points"]:
        for metric in ("mAP", "mAR", "avg_f1"):
            assert p[metric] is None or 0.0 <= p[metric] <= 1.0
    md = (out / f"{name}.md").read_text()
    assert "paper" in md and md.count("\n|") >= 3
    assert (out / f"{name}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    if name == "table":
        assert {p["curve"] for p in doc["points"]} == {"modeled", "non-modeled"}
        assert "| avg |" in md and "0.840" in md  # the paper's modeled average beside ours


@pytest.mark.slow
def test_datasets_are_shared_between_experiments(results):
    _, cache = results
    names = sorted(p.name.split("-seed")[0] for p in cache.glob("*.zarr"))
    # test set, modeled gaussian 15 (table, features, frames, overlap 30 %), gaussian 0,
    # non-modeled (table and frames), theta' 0: five recipes for 5 experiments
    assert names == [
        "modeled-gaussian0",
        "modeled-gaussian15",
        "modeled-gaussian15-theta0",
        "modeled-kinect",
        "non-modeled-gaussian15",
    ]


@pytest.mark.slow
def test_rerun_skips_finished_points_and_redoes_a_missing_one(results, capsys):
    out, cache = results
    points = sorted((out / "points" / "table").glob("*.json"))
    assert [p.stem for p in points] == ["modeled", "non-modeled"]
    before = {p: p.stat().st_mtime_ns for p in points}
    capsys.readouterr()
    assert _run(out, cache, "table") == 0
    text = capsys.readouterr().out
    assert text.count("finished before, skipped") == 2 and "train:" not in text
    assert {p: p.stat().st_mtime_ns for p in points} == before

    points[1].unlink()  # as if the run had been killed before this point finished
    assert _run(out, cache, "table") == 0
    text = capsys.readouterr().out
    assert text.count("finished before, skipped") == 1
    # frames scored the same model on the same test frames (tiny F = 4): reused, not rerun
    assert "non-modeled: the same as frames non-modeled-4" in text and "train:" not in text
    assert points[1].exists()


@pytest.mark.slow
def test_report_only_runs_no_point(results, tmp_path, capsys):
    out, cache = results
    (out / "noise.md").unlink()
    (out / "points" / "noise" / "gaussian-0.json").unlink()
    capsys.readouterr()
    assert _run(out, cache, "noise", "--report-only") == 0
    text = capsys.readouterr().out
    assert "finished 1 of 2 points" in text and "model " not in text
    assert "missing: gaussian-0" in (out / "noise.md").read_text()


def test_bad_arguments_are_one_line_errors(tmp_path, capsys):
    assert _run(tmp_path / "o", tmp_path / "c", "noise", "--workers", "0") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--workers must be >= 1" in err[0]
    assert _run(tmp_path / "o", tmp_path / "c", "noise", "--memory-gb", "0") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--memory-gb must be > 0" in err[0]


@pytest.mark.parametrize(
    ("frames", "budget_gb", "workers"),
    [(1600, 6.0, 2), (4800, 6.0, 1), (4800, 12.0, 2), (40, 0.001, 1)],
)
def test_training_workers_are_as_many_as_the_feature_budget_holds(frames, budget_gb, workers):
    """A paper-scale tree's int16 features: F x 2000 px x 300 features x 2 bytes."""
    from topseg.services.batch.experiment import runs as runs

    scale = runs.SCALES["paper"]
    model = runs.ModelRecipe(
        data=runs.DataRecipe(mode="modeled", noise=runs.TRAIN_NOISE, theta=0.3, seed=0),
        frames=frames, trees=scale.trees, depth=scale.depth, features=scale.features,
        responses=scale.responses, thresholds=scale.thresholds,
        pixels_per_frame=scale.pixels_per_frame,
    )  # fmt: skip
    job = model.train_job(Path("d.zarr"), Path("m.npz"), None, False, budget_gb)
    assert job.workers == workers
    assert job.config.n_trees == scale.trees and job.config.features.n_features == 300


# ---------------------------------------------------------------- the paper's numbers


def _coordinates(block: str) -> list[tuple[float, float]]:
    return [(float(x), float(y)) for x, y in re.findall(r"\(([\d.]+),([\d.]+)\)", block)]


@pytest.fixture(scope="module")
def tex() -> str:
    if not TEX.exists():
        pytest.skip(f"{TEX} is not here")
    return TEX.read_text()


def test_fig4_curves_match_the_tex(tex):
    # each axis: its xlabel, then its \addplot coordinate blocks in order
    axes = re.findall(r"xlabel=\{\$\\?(\w+)\$\},\s*ylabel=\$(\w+)\$(.*?)\\end\{axis\}", tex, re.S)
    assert len(axes) == 6
    names = {"sigma": ("noise", ["gaussian"]), "PC": ("features", ["linear", "axis"])}
    names["F"] = ("frames", ["modeled", "non-modeled"])
    seen = 0
    for xlabel, metric, body in axes:
        experiment, curves = names[xlabel]
        blocks = re.findall(r"coordinates\s*\{(.*?)\}", body, re.S)
        assert len(blocks) == len(curves)
        for curve, block in zip(curves, blocks, strict=True):
            assert paper_results.CURVES[experiment][metric][curve] == _coordinates(block)
            seen += 1
    assert seen == 10


def test_table_i_matches_the_tex(tex):
    # the paper's columns, in its names, are the label table's scored classes in its order
    header = next(ln for ln in tex.splitlines() if ln.strip().startswith("F1-measure"))
    columns = [c.strip() for c in header.split("\\\\")[0].split("&")[2:]]
    ours = {"UArm": "upper-arm", "LArm": "lower-arm"}
    assert [ours.get(c, c.lower()) for c in columns] == list(paper_results.TABLE_CLASSES)
    for mode, tag in (("non-modeled", "Non-Modeled"), ("modeled", "Modeled")):
        line = next(ln for ln in tex.splitlines() if ln.startswith(f"$CRF_{{{tag}}}$"))
        values = [float(v) for v in re.findall(r"(?<![\w.])(\d\.\d+)", line)]
        assert (
            dict(zip(("avg", *paper_results.TABLE_CLASSES), values, strict=True))
            == (paper_results.TABLE_I[mode])
        )
