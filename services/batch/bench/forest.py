"""Forest inference speed per frame: `topseg bench forest`.

By default the bundled model is timed on rendered modeled scenes with the sensor's own
noise (640x480 Kinect v1 at the paper's 3.5 m; `bench/frames.py`), as the worker labels
them: at full resolution (`stride 1`, every pixel the floor gate lets through) and as the
Segmenter runs by default: at its working resolution (`--downsample auto`: every other pixel
of every other row for this camera, the labels brought back to the frame's by depth; the
figures' suffix `_downsample2`) on its grid (`--stride auto`, upsampled by height;
`--adaptive 1`: the grid twice as coarse first, the grid itself only where that one is
unsure). `--model` times
another model file, `--forest trained` a T=5, D=19 forest trained here on procedural frames
(seconds), `--forest random` full binary trees of random splits (every pixel walks all D
levels: the worst case). The figures say which forest was timed, how deep pixels walk, wall
and CPU ms per frame, forest-only avg F1 and pixel accuracy at each stride, and the time to
load the model file. Wall figures on a loaded 2-core machine are inflated: the 1-minute load
average is reported beside them.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import numba
import numpy as np

from topseg.core import forest as forest_mod
from topseg.core.bundled_model import bundled_model_path
from topseg.core.camera import PAPER_MOUNT
from topseg.core.forest.features import FeatureConfig
from topseg.core.forest.inputs import header_fields
from topseg.core.forest.predict import apply, predict_proba
from topseg.core.forest.tree import node_depths
from topseg.core.scoring import score
from topseg.core.segmenter import Segmenter, SegmenterConfig
from topseg.core.segmenter_config import GridConfig
from topseg.core.synth import procedural
from topseg.services.batch.bench import frames as bench_frames
from topseg.services.cli.options import (
    add_segmenter_arguments,
    int_range,
    non_negative_int,
    segmenter_config,
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Which forest to time (the bundled model, a file, trained here or random), on what."""
    parser.add_argument(
        "--forest",
        choices=("bundled", "trained", "random"),
        default="bundled",
        help="the bundled model (default), one trained here on procedural frames, or random",
    )
    parser.add_argument("--model", help="time this model file instead (see --forest)")
    parser.add_argument(
        "--trees", type=int_range(1, 1000), default=5, help="--forest trained/random: trees"
    )
    parser.add_argument(
        "--depth", type=int_range(0, 30), default=19, help="--forest trained/random: depth"
    )
    parser.add_argument("--split", choices=("linear", "axis"), default="linear")
    parser.add_argument(
        "--train-frames",
        type=int_range(1, 100000),
        default=40,
        help="--forest trained: procedural frames",
    )
    parser.add_argument("--frames", type=int_range(1, 100000), default=10, help="frames to time")
    parser.add_argument(
        "--repeats", type=int_range(1, 100000), default=3, help="passes over the frames"
    )
    add_segmenter_arguments(parser, ("grid",))
    parser.add_argument(
        "--threads", type=int_range(0, 1024), default=0, help="numba threads (0: all cores)"
    )
    parser.add_argument("--seed", type=non_negative_int, default=0)
    bench_frames.add_arguments(parser)


def _forest(args, rng, procedural, forest_mod):
    """(forest, description) for the chosen kind."""
    if args.model or args.forest == "bundled":
        from topseg.core.bundled_model import bundled_model_path

        path = args.model or bundled_model_path()
        model, _ = forest_mod.load_model(path)
        return model, f"model file {path}" if args.model else f"bundled model {path.name}"
    k = 2 if args.split == "linear" else 1
    if args.forest == "random":
        m = FeatureConfig().max_offset
        trees = [forest_mod.random_tree(rng, args.depth, k, m) for _ in range(args.trees)]
        return forest_mod.Forest.from_trees(trees), "random splits, full depth"
    depth, truth = procedural.procedural_frames(rng, args.train_frames)
    config = forest_mod.TrainConfig(n_trees=args.trees, max_depth=args.depth, split=args.split)
    t0 = time.perf_counter()
    mounts = [_mount(procedural)] * len(depth)
    model = forest_mod.train_forest(depth, truth, config, seed=args.seed, mounts=mounts)
    seconds = time.perf_counter() - t0
    return model, f"trained on {args.train_frames} procedural frames in {seconds:.0f} s"


def _mount(procedural):
    """The mount `procedural` renders frames from by default (the paper's)."""
    return PAPER_MOUNT


def _time_frames(predict, frames, repeats):
    """Median wall and CPU ms per frame over `repeats` passes."""
    predict(frames[0])  # compile and warm caches outside the timings
    wall, cpu = [], []
    for _ in range(repeats):
        for frame in frames:
            w0, c0 = time.perf_counter(), time.process_time()
            predict(frame)
            wall.append(time.perf_counter() - w0)
            cpu.append(time.process_time() - c0)
    return 1000 * float(np.median(wall)), 1000 * float(np.median(cpu))


def _node_visits(model, segmenter, frame) -> tuple[int, int, int, float]:
    """(node visits, factor, stride, mean levels a walk takes) of `segmenter`'s forest on
    `frame`, at the resolution it works at (`Segmenter.prepare`: its plan and pre-processing):
    the trees each pixel walks (none between grid pixels and at the adaptive grid's settled
    pixels, fewer than all where the early exit stops it) times the levels of the leaf it
    reaches in each."""
    prepared = segmenter.prepare(frame)
    inp, stride, factor = prepared.inp, prepared.plan.stride, prepared.plan.downsample
    walked = np.zeros(inp.shape, np.uint8)
    config = segmenter.config
    predict_proba(
        model,
        inp,
        stride=stride,
        adaptive=config.grid.adaptive,
        walked=walked,
        early_exit=config.grid.early_exit,
    )
    leaves = apply(model, inp)
    levels = node_depths(model.left, model.roots)
    # trees are walked in order: a pixel that walked n went through the first n
    visits = sum(int(levels[leaves[t][walked > t]].sum()) for t in range(model.n_trees))
    mean_levels = float(levels[leaves[leaves >= 0]].mean()) if np.any(leaves >= 0) else 0.0
    return visits, factor, stride, mean_levels


def measure(args: argparse.Namespace) -> dict:
    """Time the forest stage of a Segmenter at full resolution and at --stride; accuracy."""
    if args.threads:
        numba.set_num_threads(args.threads)
    rng = np.random.default_rng(args.seed)
    model, kind = _forest(args, rng, procedural, forest_mod)
    if args.model or args.forest == "bundled":
        header = forest_mod.load_model(args.model or bundled_model_path())[1]
    else:
        header = header_fields(forest_mod.FeatureConfig()) if args.forest == "trained" else None
    mount = bench_frames.bench_mount(args)
    pairs, what = bench_frames.bench_frames(args.frames_from, args.frames, args.seed + 1, mount)
    frames = [d for d, _ in pairs]
    # the forest stage as `Segmenter.label` runs it with no CRF (model input, walk, the
    # upsampled summary; on a grid the posteriors between grid pixels are left to the CRF's
    # band); no camera check: a model file's camera need not be these frames'
    full = Segmenter(
        model,
        header,
        SegmenterConfig(
            check_camera=False,
            mount=mount,
            grid=GridConfig(stride=1, early_exit=None, downsample=1),
        ),
        crf="none",
    )
    grid = Segmenter(model, header, segmenter_config(args, full.config), crf="none")
    figures: dict = {
        "forest": kind,
        "frames": f"{len(frames)} {what}",
        "trees": model.n_trees,
        "depth": model.depth,
        "nodes": model.n_nodes,
        "features_per_node": model.features_per_node,
        "threads": numba.get_num_threads(),
        "adaptive_levels": args.adaptive,
    }
    for segmenter in (full, grid):
        visits, factor, stride, mean_levels = _node_visits(model, segmenter, frames[0])
        if segmenter is full:
            figures["mean_levels_walked"] = round(mean_levels, 2)
        # the figures' suffix: the grid's stride, and the resolution when not the frame's
        s = str(stride) if factor == 1 else f"{stride}_downsample{factor}"
        wall, cpu = _time_frames(segmenter.label, frames, args.repeats)
        figures[f"forest_ms_per_frame_stride{s}"] = round(wall, 2)
        figures[f"forest_cpu_ms_per_frame_stride{s}"] = round(cpu, 2)
        figures[f"node_visits_per_frame_stride{s}"] = visits
        figures[f"ns_per_node_visit_cpu_stride{s}"] = round(1e6 * cpu / max(visits, 1), 2)
        if args.forest != "random":
            figures[f"avg_f1_forest_only_stride{s}"] = round(
                score(segmenter, pairs).forest.scores()["avg_f1"], 4
            )
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "model.npz")
        forest_mod.save_model(path, model, {})
        t0 = time.perf_counter()
        forest_mod.load_model(path)
        figures["model_load_ms"] = round(1000 * (time.perf_counter() - t0), 1)
        figures["model_file_mb"] = round(os.path.getsize(path) / 2**20, 2)
    figures["target_ms_per_frame"] = 8.0
    figures["load_average_1min"] = round(os.getloadavg()[0], 2)
    return figures
