"""Forest inference speed on 640x480 top-view frames: `topseg bench forest`.

By default a T=5, D=19 forest is trained (paper defaults but fewer frames, so it takes
seconds) on procedural top-view frames and timed on held-out ones; `--forest random` times
full binary trees with random splits instead (every pixel walks all D levels: the worst
case), `--model` a saved model. The figures say which forest was timed, how deep pixels
actually walk, the wall and CPU milliseconds per frame, and the time to load its model file.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from dataclasses import replace


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Which forest to time (trained here, random or a model file) and on how many frames."""
    parser.add_argument(
        "--forest",
        choices=("trained", "random"),
        default="trained",
        help="time a forest trained on procedural frames (default) or one of random splits",
    )
    parser.add_argument(
        "--model", help="time this model file instead of a forest made here (see --forest)"
    )
    parser.add_argument("--trees", type=int, default=5)
    parser.add_argument("--depth", type=int, default=19, help="maximum tree depth")
    parser.add_argument("--split", choices=("linear", "axis"), default="linear")
    parser.add_argument(
        "--train-frames", type=int, default=40, help="procedural frames to train on"
    )
    parser.add_argument("--frames", type=int, default=10, help="held-out frames to time")
    parser.add_argument("--repeats", type=int, default=3, help="passes over the held-out frames")
    parser.add_argument("--stride", type=int, default=1, help="also time this evaluation stride")
    parser.add_argument("--threads", type=int, default=0, help="numba threads (0: all cores)")
    parser.add_argument("--seed", type=int, default=0)


def _forest(args, rng, procedural, forest_mod):
    """(forest, description) for the chosen kind."""
    from topseg.core.forest.features import FeatureConfig

    if args.model:
        model, _ = forest_mod.load_model(args.model)
        return model, f"model file {args.model}"
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
    from topseg.core.camera import PAPER_MOUNT

    return PAPER_MOUNT


def _time_frames(predict, frames, repeats):
    """Median wall and CPU ms per frame over `repeats` passes."""
    import numpy as np

    predict(frames[0])  # compile and warm caches outside the timings
    wall, cpu = [], []
    for _ in range(repeats):
        for frame in frames:
            w0, c0 = time.perf_counter(), time.process_time()
            predict(frame)
            wall.append(time.perf_counter() - w0)
            cpu.append(time.process_time() - c0)
    return 1000 * float(np.median(wall)), 1000 * float(np.median(cpu))


def measure(args: argparse.Namespace) -> dict:
    """Time the forest stage of a Segmenter (and a strided one); held-out accuracy."""
    import numba
    import numpy as np

    from topseg.core import forest as forest_mod
    from topseg.core import labels
    from topseg.core.forest.predict import apply
    from topseg.core.forest.tree import node_depths
    from topseg.core.segmenter import Segmenter, SegmenterConfig
    from topseg.core.synth import procedural

    if args.threads:
        numba.set_num_threads(args.threads)
    rng = np.random.default_rng(args.seed)
    from topseg.core.forest.inputs import header_fields

    model, kind = _forest(args, rng, procedural, forest_mod)
    header = forest_mod.load_model(args.model)[1] if args.model else None
    if header is None and args.forest == "trained":
        header = header_fields(forest_mod.FeatureConfig())  # trained on heights above
    test_depth, test_truth = procedural.procedural_frames(rng, args.frames)
    frames = list(test_depth)
    # the forest stage alone (`posteriors`, into the Segmenter's reused buffer); no camera
    # check: a model file's camera need not be the procedural frames'
    config = SegmenterConfig(check_camera=False, mount=_mount(procedural))
    segmenter = Segmenter(model, header, config, crf="none")
    wall, cpu = _time_frames(segmenter.posteriors, frames, args.repeats)
    figures: dict = {
        "forest": kind,
        "frame": f"{frames[0].shape[1]}x{frames[0].shape[0]} procedural top view",
        "trees": model.n_trees,
        "depth": model.depth,
        "nodes": model.n_nodes,
        "features_per_node": model.features_per_node,
        "threads": numba.get_num_threads(),
        "forest_ms_per_frame": round(wall, 2),
        "forest_cpu_ms_per_frame": round(cpu, 2),
    }
    leaves = apply(model, segmenter.model_input(frames[0]))
    walked = node_depths(model.left, model.roots)[leaves[leaves >= 0]]
    figures["mean_levels_walked"] = round(float(walked.mean()), 2)
    figures["node_visits_per_frame"] = int(walked.sum())
    figures["ns_per_node_visit_cpu"] = round(1e6 * cpu / max(int(walked.sum()), 1), 2)
    if args.stride > 1:
        strided = Segmenter(model, header, replace(config, stride=args.stride), crf="none")
        s_wall, _ = _time_frames(strided.posteriors, frames, args.repeats)
        figures[f"forest_ms_per_frame_stride{args.stride}"] = round(s_wall, 2)
    if args.forest == "trained" and not args.model:
        ok = total = 0
        for d, t in zip(test_depth, test_truth, strict=True):
            pred = segmenter.label(d).labels
            m = t != labels.NO_DEPTH
            ok += int((pred[m] == t[m]).sum())
            total += int(m.sum())
        figures["held_out_pixel_accuracy"] = round(ok / total, 4)
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "model.npz")
        forest_mod.save_model(path, model, {})
        t0 = time.perf_counter()
        forest_mod.load_model(path)
        figures["model_load_ms"] = round(1000 * (time.perf_counter() - t0), 1)
        figures["model_file_mb"] = round(os.path.getsize(path) / 2**20, 2)
    figures["target_ms_per_frame"] = 10.0
    return figures
