"""`topseg bench train` at a tiny scale: real training on Dask, real figures, a loadable model."""

import json
import subprocess
import sys

import pytest

from topseg.core import forest


@pytest.mark.slow
def test_bench_train_json_figures_are_real(data, tmp_path):
    model = tmp_path / "kept.npz"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "topseg.services.cli",
            "bench",
            "train",
            "--json",
            "--scale",
            "0.004",
            "--data",
            str(data),
            "--keep-model",
            str(model),
            "--workers",
            "2",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    figures = json.loads(done.stdout)
    assert figures["scale"] == 0.004
    assert figures["config"]["frames_per_tree"] == 6
    assert figures["config"]["trees"] == 5 and figures["config"]["depth"] == 19
    assert figures["seconds"] > 0
    assert figures["cpu_seconds"] > 0
    assert figures["peak_rss_mb"] > 50
    # train and its two Dask workers were sampled, and the sum is above any one of them
    assert figures["processes"] >= 3
    assert figures["peak_rss_mb"] >= max(figures["per_process_peak_mb"])
    assert figures["n_samples"] == 5 * 6 * 2000
    assert figures["met"] is None  # the targets are for scale 1 only
    f, header = forest.load_model(model)
    assert f.n_trees == 5
    assert header["recipe"]["config"]["frames_per_tree"] == 6
    assert figures["nodes"] == f.n_nodes
