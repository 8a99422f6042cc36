"""The live path for real: driver, worker and viewer processes on loopback Zenoh."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from topseg.core import forest, metrics
from topseg.core.crf import CRFConfig
from topseg.core.errors import TopsegError
from topseg.core.segmenter_config import SegmenterConfig
from topseg.core.synth.synthesis import SynthesisConfig, Synthesizer
from topseg.drivers import synthetic
from topseg.services.batch.pipeline import run_pipeline, summary
from topseg.services.live.worker import load_segmenter

N = 8

#: the forest's argmax, no CRF
NO_CRF = SegmenterConfig(crf=CRFConfig(mode="none"))


@pytest.fixture(scope="module")
def model_path(tmp_path_factory):
    """A tiny forest trained on a few synthetic frames."""
    with Synthesizer(SynthesisConfig(seed=100)) as synth:
        train = [synth.render(i) for i in range(8)]
    config = forest.TrainConfig(
        n_trees=2, max_depth=10, frames_per_tree=8, pixels_per_frame=500,
        n_candidates=20, n_thresholds=10,
    )  # fmt: skip
    depth = np.stack([f.depth for f in train])
    truth = np.stack([f.labels for f in train])
    path = tmp_path_factory.mktemp("model") / "tiny.npz"
    forest.save_model(path, forest.train_forest(depth, truth, config, seed=0))
    return path


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    return synthetic.record(tmp_path_factory.mktemp("rec") / "demo.mcap", N, "seed=9", fps=10)


def test_replay_lossless_labels_every_frame_and_scores_them_like_the_segmenter(
    recording, model_path, tmp_path
):
    rrd = tmp_path / "out.rrd"
    figures = run_pipeline(f"replay:{recording}", model_path, None, 10.0, NO_CRF, rrd, True)
    assert figures["exit_codes"] == {"worker": 0, "viewer": 0, "driver": 0}
    assert figures["frames_sent"] == figures["frames_labelled"] == figures["frames_scored"] == N
    assert 0 < figures["latency_p50_ms"] <= figures["latency_p99_ms"]
    # the worker's own stage timings, from its stats (the first frames are warm-up)
    assert 0 < figures["worker_forest_p50_ms"] <= figures["worker_total_p99_ms"]
    assert figures["worker_total_p50_ms"] <= figures["worker_total_p99_ms"]
    assert figures["fps"] > 0
    assert rrd.stat().st_size > 0
    # the driver kept its session open until the worker had labelled its last frame
    driver_log = (Path(figures["logs"]) / "driver.log").read_text()
    assert f"frame {N - 1} labelled" in driver_log

    segmenter = load_segmenter(str(model_path), NO_CRF)
    want = metrics.ConfusionAccumulator()
    with synthetic.open("seed=9", synthetic.SourceOptions(realtime=False)) as src:
        for i, frame in zip(range(N), src.frames(), strict=False):
            assert frame.depth.seq == i
            want.add(frame.truth.labels, segmenter.label(frame.depth.depth).labels)
    np.testing.assert_array_equal(figures["confusion"], want.confusion)
    assert figures["scores"]["avg_f1"] == pytest.approx(want.scores()["avg_f1"], nan_ok=True)
    assert "F1" in summary(figures)


@pytest.mark.slow
def test_live_synthetic_source_runs_for_the_duration(model_path, tmp_path):
    figures = run_pipeline("synthetic:seed=4", model_path, 2.0, 15.0, None, None, False)
    assert figures["exit_codes"] == {"worker": 0, "driver": 0}
    assert 0 < figures["frames_labelled"] <= figures["frames_sent"]
    assert figures["frames_scored"] > 0


def test_missing_model_is_a_clear_error(tmp_path):
    with pytest.raises(TopsegError, match="does not exist"):
        run_pipeline("synthetic", tmp_path / "none.npz", 1.0, None, NO_CRF, None, False)


@pytest.mark.slow
def test_bench_pipeline_prints_the_figures_as_json(model_path):
    cmd = [sys.executable, "-m", "topseg.services.cli", "bench", "pipeline", "--json"]
    cmd += ["--duration", "1.5", "--fps", "15", "--model", str(model_path)]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    figures = json.loads(out.stdout)
    for key in ("fps", "latency_p50_ms", "latency_p99_ms", "frames_sent", "frames_labelled"):
        assert key in figures
    assert figures["frames_labelled"] > 0


@pytest.mark.slow
def test_one_worker_labels_two_cameras(recording, model_path):
    figures = run_pipeline(
        f"replay:{recording}", model_path, None, 10.0, NO_CRF, None, True, cameras=2
    )
    assert figures["exit_codes"] == {"worker": 0, "driver-cam0": 0, "driver-cam1": 0}
    assert figures["cameras"] == 2
    # both cameras' frames, each scored against its own truth
    assert figures["frames_sent"] == figures["frames_labelled"] == figures["frames_scored"] == 2 * N
