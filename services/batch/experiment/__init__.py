"""The paper's experiments (Sharma et al. 2016, Fig. 4 and Table I) on topseg's synthetic data:
`noise`, `features`, `frames`, `overlap` and `table` train forests and score them on one
held-out test set, beside the paper's figures; `mounts` scores one model across ceiling
heights, tilts and sensors. Each writes OUT/<experiment>.md, .json and .png; a rerun resumes.

    topseg experiment noise|features|frames|overlap|table [--scale tiny|quick|paper] --out DIR
    topseg experiment mounts [--model M] [--baseline OLD] --out DIR   (experiment/mounts.py)
    topseg experiment open-world [--model M] --out DIR   (experiment/open_world.py)
    topseg experiment safety [--model M] [--sequences N] --out DIR   (experiment/safety.py)

Every point trains a forest on a synthetic training set and scores it on one held-out test
set: modeled scenes from other seeds, with the Kinect noise model. Training sets are modeled
with gaussian:15 noise unless the experiment sweeps that (noise: sigma; frames and table:
modeled vs non-modeled; overlap: theta'). Scores are means over the ten classes of the
forest + CRF (`--crf`, default realtime) and of the forest alone.

Datasets are cached by recipe in `--data-cache` (default OUT/../data-cache) and shared by
all experiments; models in OUT/models/, points in OUT/points/<experiment>/. A rerun (after
Ctrl-C, SIGTERM or a crash) skips finished points and resumes the rest. After each point
OUT/<experiment>.md, .json and .png are rewritten with what has finished.
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

from topseg.core.bundled_model import MODEL_HELP
from topseg.core.errors import TopsegError
from topseg.core.resolution import MAX_DOWNSAMPLE
from topseg.core.sensors import get_sensor
from topseg.services.cli.options import auto_int

EXPERIMENTS = ("noise", "features", "frames", "overlap", "table", "mounts", "open-world", "safety")

# the paper's x values
NOISE_SIGMAS = (0, 5, 10, 15, 30, 50, 100)
FEATURE_COUNTS = (75, 150, 300, 400, 500, 600)
FRAME_COUNTS = (40, 200, 400, 1200, 1600, 2400, 4800)
OVERLAPS = (0, 5, 10, 15, 20, 30, 50)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """`topseg experiment`'s options."""
    from topseg.services.batch.experiment.runs import SCALES

    parser.add_argument("experiment", choices=EXPERIMENTS)
    parser.add_argument(
        "--scale", choices=tuple(SCALES), default="quick", help="sizes (default quick)"
    )
    parser.add_argument("--out", required=True, type=Path, help="results folder")
    parser.add_argument(
        "--data-cache", type=Path, help="dataset cache folder (default OUT/../data-cache)"
    )
    parser.add_argument(
        "--workers",
        type=int,
        help="Dask workers: datagen (default one per core) and training "
        "(default 2, fewer when their trees' features would not fit in --memory-gb)",
    )
    parser.add_argument(
        "--memory-gb",
        type=float,
        help="GB of training features the training workers may hold together (default 6; "
        "a paper-scale tree holds 1.2 GB per 1000 frames)",
    )
    parser.add_argument("--seed", type=int, default=0, help="training data and forest seed")
    parser.add_argument(
        "--crf",
        choices=("none", "exact", "realtime"),
        default="realtime",
        help="(default realtime)",
    )
    parser.add_argument("--test-frames", type=int, help="test set size (default: the scale's)")

    parser.add_argument(
        "--model", type=Path, help=f"mounts, open-world: the model scored; {MODEL_HELP}"
    )
    parser.add_argument(
        "--baseline", type=Path, help="mounts: a second model scored on the same frames"
    )

    parser.add_argument(
        "--downsample",
        type=auto_int(1, MAX_DOWNSAMPLE),
        default=None,
        metavar="auto|N",
        help="mounts: the resolution --model labels at (`topseg evaluate --downsample`; "
        "default auto)",
    )
    parser.add_argument(
        "--baseline-downsample",
        type=auto_int(1, MAX_DOWNSAMPLE),
        default=None,
        metavar="auto|N",
        help="mounts: the same for --baseline (e.g. the same model at 1, the frames' own "
        "resolution; default auto)",
    )
    parser.add_argument(
        "--sensors",
        default="kinect_v1,kinect_v2,oak_d,realsense_d435",
        help="mounts, open-world: comma-separated sensors (default: every supported one)",
    )
    parser.add_argument(
        "--background",
        action="store_true",
        help="open-world: also score each cell with its static background recorded and gating;"
        " safety: label every sequence with its static background gating",
    )
    parser.add_argument(
        "--cells",
        choices=("default", "generated"),
        default="default",
        help="open-world: the held-out cells: the density function's own (default), or every "
        "robot a random arm and every item that can be one a mesh object (robots and objects "
        "nobody modelled)",
    )
    parser.add_argument(
        "--sequences", type=int, default=8, metavar="N",
        help="safety: rendered cell sequences scored (default %(default)s)",
    )  # fmt: skip
    parser.add_argument(
        "--sequence-seconds", type=float, default=10.0, metavar="S",
        help="safety: each sequence's length at 15 fps (default %(default)s)",
    )  # fmt: skip
    parser.add_argument(
        "--labels-lag", type=int, default=0, metavar="N",
        help="safety: decide on each frame with the labels of the frame N frames before it "
        "carried onto it, as the live service does before a frame's own labels come "
        "(default %(default)s: its own)",
    )  # fmt: skip
    parser.add_argument(
        "--cameras", type=int, choices=(1, 2), default=1,
        help="safety: cameras over each sequence's cell: 1, or 2 side by side whose views abut "
        "at head height (default %(default)s)",
    )  # fmt: skip
    parser.add_argument(
        "--validation", action="store_true",
        help="safety: the validation sequences (other seeds), for choosing thresholds",
    )  # fmt: skip
    parser.add_argument(
        "--precision-stages", choices=("on", "off"), default=None,
        help="safety: label with the model's context prior and checks on or off (default: as "
        "the safety service's worker does, off)",
    )  # fmt: skip
    parser.add_argument(
        "--report-only",
        action="store_true",
        help="rewrite OUT/<experiment>.md/.json/.png from the finished points; run none",
    )


@dataclass(frozen=True)
class Point:
    """One point of an experiment: the model of `curve` at x value `x` (None in the table)."""

    curve: str
    x: float | None
    model: object  # runs.ModelRecipe

    @property
    def key(self) -> str:
        """The point's file name stem, unique within its experiment: `curve` or `curve-x`."""
        return self.curve if self.x is None else f"{self.curve}-{self.x:g}"


def points_of(experiment: str, scale, seed: int) -> list[Point]:
    """The experiment's points in the order they run (frames: smallest F first)."""
    from topseg.services.batch.experiment.runs import DataRecipe, ModelRecipe

    base = ModelRecipe(
        data=DataRecipe(seed=seed),
        frames=scale.frames,
        trees=scale.trees,
        depth=scale.depth,
        features=scale.features,
        responses=scale.responses,
        thresholds=scale.thresholds,
        pixels_per_frame=scale.pixels_per_frame,
        seed=seed,
    )
    non_modeled = DataRecipe(mode="non-modeled", seed=seed)
    if experiment == "noise":
        return [
            Point("gaussian", s, replace(base, data=DataRecipe(noise=f"gaussian:{s}", seed=seed)))
            for s in scale.sweep("noise", NOISE_SIGMAS)
        ]
    if experiment == "features":
        return [
            Point(split, pc, replace(base, features=pc, split=split))
            for pc in scale.sweep("features", FEATURE_COUNTS)
            for split in ("linear", "axis")
        ]
    if experiment == "frames":
        return [
            Point(name, f, replace(base, frames=f, data=data))
            for f in sorted(scale.sweep("frames", FRAME_COUNTS))
            for name, data in (("modeled", base.data), ("non-modeled", non_modeled))
        ]
    if experiment == "overlap":
        return [
            Point("modeled", t, replace(base, data=DataRecipe(theta=t / 100, seed=seed)))
            for t in scale.sweep("overlap", OVERLAPS)
        ]
    return [
        Point("modeled", None, base),
        Point("non-modeled", None, replace(base, data=non_modeled)),
    ]


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt


def run(args: argparse.Namespace) -> int:
    """`topseg experiment`: run (or resume) one experiment's points and write its reports."""
    from topseg.services.batch.experiment import runs as runs

    runs.check_positive("--workers", args.workers)
    runs.check_positive("--test-frames", args.test_frames)
    if args.memory_gb is None:
        args.memory_gb = runs.FEATURE_BUDGET_GB
    if not args.memory_gb > 0:
        raise TopsegError(f"--memory-gb must be > 0, got {args.memory_gb}")
    if args.seed < 0:
        raise TopsegError(f"--seed must be >= 0, got {args.seed}")
    scale = runs.SCALES[args.scale]
    test_frames = args.test_frames or scale.test_frames
    out = args.out.absolute()
    if args.experiment == "mounts":
        return _run_mounts(args, test_frames, out)
    if args.experiment == "open-world":
        return _run_open_world(args, args.test_frames or OPEN_WORLD_FRAMES, out)
    if args.experiment == "safety":
        return _run_safety(args, out)
    cache = (args.data_cache or out.parent / "data-cache").absolute()
    out.mkdir(parents=True, exist_ok=True)
    points = points_of(args.experiment, scale, args.seed)
    print(f"topseg experiment {args.experiment}: {scale.describe()}")
    print(
        f"  {len(points)} points; scores: forest + CRF ({args.crf}) and forest alone on "
        f"{test_frames} test frames; data cache {cache}; results {out}",
        flush=True,
    )
    old_handler = signal.signal(signal.SIGTERM, _raise_interrupt)
    try:
        return _run_points(args, scale, test_frames, out, cache, points)
    finally:
        signal.signal(signal.SIGTERM, old_handler)


def _run_safety(args, out: Path) -> int:
    """The safety decision on rendered cell sequences (experiment/safety.py)."""
    from topseg.services.batch.experiment import safety

    if args.sequences < 1 or not 1 <= args.sequence_seconds <= 600:
        raise TopsegError("--sequences must be >= 1 and --sequence-seconds within 1..600")
    if not 0 <= args.labels_lag <= 30:
        raise TopsegError("--labels-lag must be within 0..30 frames")
    seed = safety.VALIDATION_SEED if args.validation else safety.TEST_SEED
    result = safety.run(out, args.model, args.sequences, args.sequence_seconds, 15.0, seed,
                        background=args.background, lag=args.labels_lag,
                        precision=args.precision_stages, cameras=args.cameras)  # fmt: skip
    print(safety.markdown(result))
    return 0


def _run_mounts(args, frames: int, out: Path) -> int:
    """One model (and a baseline) across `mounts.MOUNTS` and every sensor: a table, no training."""
    from topseg.services.batch.experiment import mounts

    if args.report_only:  # the figure and table again from OUT/mounts.json, no cell run
        report = mounts.read_report(out)
        mounts.write_report(report, out)
    else:
        sensors = [get_sensor(s.strip()).name for s in args.sensors.split(",") if s.strip()]
        print(
            f"topseg experiment mounts: {len(sensors)} sensors x {len(mounts.MOUNTS)} mounts, "
            f"{frames} held-out modeled frames a cell; results {out}",
            flush=True,
        )
        report = mounts.run_mounts(
            args.model,
            args.baseline,
            sensors,
            frames,
            out,
            downsample=(args.downsample, args.baseline_downsample),
        )
    v = report["verdict"]
    print(
        f"reference cell {v['reference_f1']:.3f}; largest gap {v['largest_gap']:.3f} "
        f"(<= {mounts.MAX_GAP}: {v['all_within_gap']}); lowest cell {v['lowest_f1']:.3f} "
        f"(>= {mounts.MIN_F1}: {v['none_below_floor']}); wrote {out / 'mounts.md'}"
    )
    return 0


#: held-out cells per mount and sensor of `open-world` (5 mounts x 4 sensors: 600 frames)
OPEN_WORLD_FRAMES = 30


def _run_open_world(args, frames: int, out: Path) -> int:
    """One model on held-out robot cells across `mounts.MOUNTS` and every sensor."""
    from topseg.services.batch.experiment import open_world

    sensors = [get_sensor(s.strip()).name for s in args.sensors.split(",") if s.strip()]
    print(
        f"topseg experiment open-world: {len(sensors)} sensors x 5 mounts, {frames} held-out "
        f"{args.cells} cells a mount; results {out}",
        flush=True,
    )
    report = open_world.run_open_world(
        args.model, sensors, frames, out, background=args.background, cells=args.cells
    )
    missed = [k for k, ok in report["verdict"].items() if ok is False]
    print(f"targets missed: {', '.join(missed) or 'none'}; wrote {out / 'open-world.md'}")
    return 0


def _run_points(args, scale, test_frames: int, out: Path, cache: Path, points) -> int:
    from topseg.services.batch.experiment import report as report
    from topseg.services.batch.experiment import runs as runs

    done: dict[str, dict] = {}
    t_start = time.perf_counter()
    test = runs.test_recipe(args.seed)
    # every finished point first, so that the reports written after each new point (and
    # after an interrupt) list all of them, not only those the loop has reached
    for i, p in enumerate(points, 1):
        path = out / "points" / args.experiment / f"{p.key}.json"
        doc = runs.load_point(path, runs.point_recipe(p.model, test, test_frames, args.crf))
        if doc is not None:
            print(f"[{i}/{len(points)}] {p.key}: finished before, skipped")
            done[p.key] = doc
    try:
        test_ds = None
        for i, p in enumerate(points, 1):
            if p.key in done or args.report_only:
                continue
            path = out / "points" / args.experiment / f"{p.key}.json"
            recipe = runs.point_recipe(p.model, test, test_frames, args.crf)
            same = runs.scored_elsewhere(out, recipe)
            if same is not None:
                doc = {**same, "experiment": args.experiment, "curve": p.curve, "x": p.x}
                doc["key"] = p.key
                runs.write_json(path, doc)
                print(
                    f"[{i}/{len(points)}] {p.key}: the same as {same['experiment']} {same['key']}"
                )
                done[p.key] = doc
                continue
            print(f"[{i}/{len(points)}] {p.key}: model {p.model.key()}", flush=True)
            t0 = time.perf_counter()
            if test_ds is None:
                test_ds = runs.ensure_dataset(cache, test, test_frames, args.workers, scale.serial)
            model_path = runs.ensure_model(
                out, cache, p.model, args.workers, scale.serial, args.memory_gb
            )
            t1 = time.perf_counter()
            scores = runs.score(model_path, test_ds, test_frames, args.crf)
            doc = {
                "experiment": args.experiment,
                "scale": scale.name,
                "curve": p.curve,
                "x": p.x,
                "key": p.key,
                "model_file": str(model_path.relative_to(out)),
                "seconds": {
                    "data_and_train": round(t1 - t0, 1),
                    "score": round(time.perf_counter() - t1, 1),
                },
                "recipe": recipe,
                **scores,
            }
            runs.write_json(path, doc)
            done[p.key] = doc
            print(report.summary_line(doc), flush=True)
            report.write_all(out, args.experiment, scale, args.crf, test_frames, points, done)
    except KeyboardInterrupt:
        print(
            f"topseg experiment: interrupted; {len(done)} of {len(points)} points finished in "
            f"{out}; rerun the same command to resume",
            file=sys.stderr,
        )
        return 130
    paths = report.write_all(out, args.experiment, scale, args.crf, test_frames, points, done)
    print(
        f"finished {len(done)} of {len(points)} points in {time.perf_counter() - t_start:.0f} s; wrote "
        + ", ".join(str(p) for p in paths)
    )
    return 0
