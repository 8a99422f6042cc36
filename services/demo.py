"""Run the main job end to end and print what it measured.

Until the live pipeline lands, the demo exercises the segmentation core for real: it draws
procedural top-view scenes, trains a small forest on some, segments held-out ones with the
forest and both CRF modes, and prints the per-class table and each stage's time per frame.
"""

from __future__ import annotations

import argparse
import time


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--train-frames", type=int, default=24, help="procedural frames to train on"
    )
    parser.add_argument("--test-frames", type=int, default=8, help="held-out frames to score")
    parser.add_argument("--trees", type=int, default=3)
    parser.add_argument("--depth", type=int, default=14, help="maximum tree depth")
    parser.add_argument("--seed", type=int, default=0)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from topseg.core import crf, forest, metrics, procedural

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
    totals = {mode: metrics.ConfusionAccumulator() for mode in modes}
    seconds = dict.fromkeys(("forest", *modes[1:]), 0.0)
    forest.predict_proba(model, test[0][0])  # compile once, outside the timings
    for frame_depth, frame_truth in test:
        t0 = time.perf_counter()
        proba = forest.predict_proba(model, frame_depth)
        seconds["forest"] += time.perf_counter() - t0
        for mode in modes:
            t0 = time.perf_counter()
            if mode == "none":
                pred = forest.labels_from_proba(proba, frame_depth)
            else:
                pred = crf.segment_crf(proba, frame_depth, crf.CRFConfig(mode=mode))
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
