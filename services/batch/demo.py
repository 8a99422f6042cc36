"""Run the main job end to end and print what it measured: the bundled recording (synthetic
scenes with ground truth) is replayed through driver -> worker -> viewer, each its own process
on loopback Zenoh, with the bundled model; it prints fps, latency p50/p99 and the per-class F1
table, and the viewer writes a Rerun file (`out/demo.rrd`). Needs no sensor and no display.
`--core` runs the segmentation core alone on procedural scenes instead.

By default: the bundled recording (`recordings/demo.mcap`, synthetic robot cells with
ground truth) is replayed through driver -> Zenoh -> worker -> Zenoh -> viewer, each a
separate process, with the bundled model; the viewer writes an `.rrd` (and serves the web
viewer with `--web`). Prints fps, latency p50/p99 and the per-class table against the
recording's ground truth. Needs no sensor and no display.

`--core` instead exercises the segmentation core alone: it trains a small forest on
procedural top-view scenes and scores forest, realtime and exact CRF on held-out ones.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from topseg.core import forest, metrics
from topseg.core.bundled_model import MODEL_HELP, bundled_model_path
from topseg.core.crf import CRFConfig
from topseg.core.errors import TopsegError
from topseg.core.segmenter import Segmenter
from topseg.core.segmenter_config import SegmenterConfig
from topseg.core.synth import procedural
from topseg.services.batch.cell_pipeline import cell_summary, run_cell_pipeline
from topseg.services.batch.pipeline import run_pipeline, summary
from topseg.services.cli.options import finite, int_range, non_negative_int

REPO = Path(__file__).resolve().parents[2]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The live demo's recording, model and CRF; the --core demo's sizes."""
    parser.add_argument("--recording", type=Path, default=REPO / "recordings" / "demo.mcap")
    parser.add_argument("--model", type=Path, default=None, help=MODEL_HELP)
    parser.add_argument("--crf", choices=("none", "exact", "realtime"), default="realtime")
    parser.add_argument(
        "--rrd", type=Path, default=Path("out/demo.rrd"), help="Rerun file the viewer writes"
    )
    parser.add_argument("--web", action="store_true", help="also serve Rerun's web viewer")
    parser.add_argument(
        "--fps",
        type=finite(0.1, 1000),
        default=None,
        help="replay rate (default: the recorded rate, 30 fps)",
    )
    parser.add_argument(
        "--lossless",
        action="store_true",
        help="label every frame (the replay waits for the worker)",
    )
    cell = parser.add_argument_group("--cell: the safety service on a robot cell")
    cell.add_argument(
        "--cell",
        action="store_true",
        help="replay the cell recording (recordings/cell.mcap, its cell file beside it) through "
        "driver -> worker -> safety and score the states against its truth",
    )
    cell.add_argument(
        "--cell-recording", type=Path, default=REPO / "recordings" / "cell.mcap", metavar="FILE"
    )
    cell.add_argument("--json", action="store_true", help="--cell: print the figures as JSON")
    core = parser.add_argument_group("--core: the segmentation core on procedural scenes")
    core.add_argument(
        "--core", action="store_true", help="run the core demo instead of the live one"
    )
    core.add_argument(
        "--train-frames",
        type=int_range(1, 100000),
        default=24,
        help="procedural frames to train on",
    )
    core.add_argument(
        "--test-frames", type=int_range(1, 100000), default=8, help="held-out frames to score"
    )
    core.add_argument("--trees", type=int_range(1, 1000), default=3)
    core.add_argument("--depth", type=int_range(0, 30), default=14, help="maximum tree depth")
    core.add_argument("--seed", type=non_negative_int, default=0)


def run(args: argparse.Namespace) -> int:
    """The live demo, the cell demo with --cell, or the core demo with --core."""
    if args.cell:
        return run_cell(args)
    return run_core(args) if args.core else run_live(args)


def run_cell(args: argparse.Namespace) -> int:
    """Replay the cell recording through driver -> worker -> safety; print how the states
    agree with the truth, the separation error and the reaction time."""
    recording = args.cell_recording
    cell_file = recording.with_suffix(".toml")
    if not args.json:
        print(
            f"replaying {recording} through driver -> worker -> safety ({cell_file.name}) -> "
            "viewer, each a separate process on loopback Zenoh"
        )
    args.rrd.parent.mkdir(parents=True, exist_ok=True)
    rrd = args.rrd.with_name("cell.rrd") if args.rrd == Path("out/demo.rrd") else args.rrd
    figures = run_cell_pipeline(recording, cell_file, args.model, rrd)
    if args.json:
        print(json.dumps(figures))
    else:
        print(cell_summary(figures))
        print(f"Rerun recording: {rrd}; logs: {figures['logs']}")
    return 0


def run_live(args: argparse.Namespace) -> int:
    """Replay the recording through driver -> worker -> viewer; print the figures and F1."""
    model = bundled_model_path() if args.model is None else args.model
    for what, path in (("recording", args.recording), ("model", model)):
        if not path.exists():
            raise TopsegError(f"no {what} at {path} (rebuild it with `make {what}`)")
    args.rrd.parent.mkdir(parents=True, exist_ok=True)
    print(
        f"replaying {args.recording} through driver -> worker (--crf {args.crf}) -> viewer, "
        "each a separate process on loopback Zenoh"
    )
    if args.web:
        print("the viewer serves Rerun's web viewer; its address is in the viewer's log")
    figures = run_pipeline(
        f"replay:{args.recording}",
        model,
        duration_s=None,
        fps=args.fps,
        config=SegmenterConfig(crf=CRFConfig(mode=args.crf)),
        rrd=args.rrd,
        lossless=args.lossless,
        web=args.web,
    )
    if figures.get("scores"):
        print(
            metrics.format_table(
                figures["scores"],
                title=f"labels vs ground truth, {figures['frames_scored']} frames",
            )
        )
    print(summary(figures))
    print(
        f"Rerun recording: {args.rrd} (open it with `.venv/bin/rerun {args.rrd}`); logs: {figures['logs']}"
    )
    return 0


def run_core(args: argparse.Namespace) -> int:
    """Train a small forest on procedural frames; score forest, realtime and exact CRF."""
    rng = np.random.default_rng(args.seed)
    t0 = time.perf_counter()
    train = [procedural.procedural_frame(rng) for _ in range(args.train_frames)]
    test = [procedural.procedural_frame(rng) for _ in range(args.test_frames)]
    print(
        f"drew {len(train)} training and {len(test)} held-out procedural top-view frames "
        f"in {time.perf_counter() - t0:.1f} s"
    )

    depth = np.stack([d for d, _ in train])
    truth = np.stack([lab for _, lab in train])
    config = forest.TrainConfig(n_trees=args.trees, max_depth=args.depth)
    t0 = time.perf_counter()
    model = forest.train_forest(depth, truth, config, seed=args.seed)
    print(
        f"trained {args.trees} trees of depth <= {args.depth} in {time.perf_counter() - t0:.1f} s"
    )

    modes = ("none", "realtime", "exact")
    # one Segmenter per CRF mode on the same forest: the forest runs once a frame (through
    # the first one) and each mode smooths the same posteriors
    segmenters = {mode: Segmenter(model, crf=mode) for mode in modes}
    totals = {mode: metrics.ConfusionAccumulator() for mode in modes}
    seconds = dict.fromkeys(("forest", *modes[1:]), 0.0)
    segmenters["none"].posteriors(test[0][0])  # compile once, outside the timings
    for frame_depth, frame_truth in test:
        segmenters["none"].plan(frame_depth)  # a frame of the model's camera, or an error
        t0 = time.perf_counter()
        proba = segmenters["none"].posteriors(frame_depth)
        seconds["forest"] += time.perf_counter() - t0
        for mode in modes:
            t0 = time.perf_counter()
            pred = segmenters[mode].smooth(proba, frame_depth)
            if mode != "none":
                seconds[mode] += time.perf_counter() - t0
            totals[mode].add(frame_truth, pred)

    for mode in modes:
        scores = totals[mode].scores()
        title = "forest alone" if mode == "none" else f"forest + CRF ({mode})"
        print(f"\n{title} on {len(test)} held-out frames")
        print(metrics.format_table(scores))
    n = len(test)
    print(
        "\nms per 640x480 frame: "
        + ", ".join(f"{k} {1000 * v / n:.1f}" for k, v in seconds.items())
    )
    return 0
