"""Potts CRF speed and quality: `topseg bench crf`.

Runs `exact` (gco alpha-expansion over the full grid) and `realtime` (the band solver)
on the same 640x480 frames and unaries, and reports milliseconds per frame and how close
realtime's energy comes to exact's:

- crf_energy_ratio: E(realtime) / E(exact), mean over frames (max in *_max; the same
  as a percentage above exact in crf_energy_excess_pct); the target is <= 1.02.
- crf_gain_fraction: (E(argmax) - E(realtime)) / (E(argmax) - E(exact)), the share of
  the smoothing exact achieves that realtime also achieves (a stricter measure: the
  unaries of the floor alone make the ratio close to 1).

Unaries are the bundled model's posteriors (or --model's), as the Segmenter makes them by
default (at its working resolution, `--downsample auto`: half the frame's for this camera; on
its grid, upsampled by height), on rendered modeled scenes with the sensor's own
noise (`bench/frames.py`; `--frames-from procedural` for procedural top views).
`--unaries quick-forest` uses a small forest trained here on procedural frames (seeded,
~20 s), `--unaries synthetic` the stand-in forest-like posteriors of `bench.crf_standin`.
The realtime CRF is timed as the Segmenter runs it: given the per-pixel argmax and top two
posteriors that the forest computes as it writes the posteriors (`crf.Summary`), and with
its labels brought back to the frame's resolution (`resolution.upsample_labels`); energies
are those of the working resolution's problem, which both solvers solve. Timings
are per-frame medians of --repeat runs, wall clock (*_ms_*) and this process's CPU time
(*_cpu_ms_*: both solvers are single-threaded, so on an idle machine the two agree); the
load average is reported beside them, since other processes on a 2-core machine inflate
the wall-clock figures.
"""

from __future__ import annotations

import argparse
import functools
import os
import time
from pathlib import Path

import numpy as np

from topseg.core import forest
from topseg.core.crf import CRFConfig, Summary, argmax_confidence, potts_energy, segment_crf
from topseg.core.crf.realtime import band_mask
from topseg.core.forest import FeatureConfig, fill_posteriors
from topseg.core.forest.inputs import header_fields
from topseg.core.resolution import upsample_labels
from topseg.core.segmenter import Segmenter
from topseg.core.synth import procedural
from topseg.services.batch.bench import frames as bench_frames
from topseg.services.cli.options import (
    add_segmenter_arguments,
    finite,
    int_range,
    non_negative_int,
    segmenter_config,
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Frames, repeats, where the unaries come from and CRF setting overrides."""
    parser.add_argument(
        "--frames", type=int_range(1, 10000), default=4, help="frames to measure on"
    )
    parser.add_argument(
        "--repeat", type=int_range(1, 100000), default=10, help="realtime runs per frame"
    )
    parser.add_argument("--seed", type=non_negative_int, default=0)
    parser.add_argument(
        "--unaries",
        choices=("model", "quick-forest", "synthetic"),
        default="model",
        help="the model's posteriors (default), a small forest trained here, or the stand-in",
    )
    parser.add_argument("--model", type=Path, help="topseg model file (default: the bundled one)")
    add_segmenter_arguments(parser, ("grid",))
    bench_frames.add_arguments(parser)
    parser.add_argument(
        "--smoothness", type=finite(0, 1e6), default=None, help="Potts weight (nats)"
    )
    parser.add_argument("--confidence", type=finite(0, 1e6), default=None)
    parser.add_argument("--ring", type=int_range(0, 1000), default=None)
    parser.add_argument("--cycles", type=int_range(0, 100000), default=None)


def _quick_forest(rng: np.random.Generator):
    """A small forest on procedural frames: enough for forest-shaped posteriors."""
    frames = [procedural.procedural_frame(rng) for _ in range(60)]
    depth = np.stack([d for d, _ in frames])
    labels = np.stack([lab for _, lab in frames])
    config = forest.TrainConfig(
        n_trees=3,
        max_depth=16,
        frames_per_tree=60,
        pixels_per_frame=1500,
        n_candidates=40,
        n_thresholds=40,
    )
    seed = int(rng.integers(2**31))
    mounts = [bench_frames.bench_mount()] * len(depth)
    return forest.train_forest(depth, labels, config, seed=seed, mounts=mounts)


def _frames(args: argparse.Namespace) -> tuple[list[tuple], str]:
    """[(posteriors, depth, summary, fill, frame, factor)] and a sentence saying where the
    unaries came from: `segment_crf`'s arguments at the resolution the Segmenter works at
    (summary and fill None where the Segmenter has none), the frame at its own resolution
    and the factor between the two (`Segmenter.prepare`)."""
    rng = np.random.default_rng(args.seed)
    if args.unaries == "synthetic":
        from topseg.services.batch.bench.crf_standin import forest_like_posteriors, synthetic_scene

        out = []
        for _ in range(args.frames):
            depth, truth = synthetic_scene(rng)
            out.append((forest_like_posteriors(truth, rng), depth, None, None, depth, 1))
        return out, "stand-in forest-like posteriors on synthetic scenes (bench/crf_standin)"

    # the model's camera need not be these frames'; a height model reads them through theirs
    mount = bench_frames.bench_mount(args)
    config = segmenter_config(args, check_camera=False, mount=mount)
    if args.unaries == "quick-forest":
        segmenter = Segmenter(_quick_forest(rng), header_fields(FeatureConfig()), config)
        source = "small forest (3 trees, depth 16, 60 frames) trained here"
    else:
        segmenter = Segmenter.from_file(args.model, config)
        source = f"{'model ' + str(args.model) if args.model else 'the bundled model'}"
    pairs, what = bench_frames.bench_frames(args.frames_from, args.frames, args.seed + 1, mount)
    out = []
    for frame, _ in pairs:
        prepared = segmenter.prepare(frame)
        depth, stride, factor = prepared.depth, prepared.plan.stride, prepared.plan.downsample
        forest = segmenter.stages[segmenter.stage_names.index("forest")]
        proba = forest.predict(prepared.inp, stride).copy()  # the buffer is reused
        # what the forest hands the CRF beside the posteriors (it computes them as it writes)
        summary = Summary(*argmax_confidence(proba, depth > 0))
        # on a grid the Segmenter stores the band's posteriors when the CRF asks for them
        # (`stages.forest`): the realtime CRF's time includes that
        fill = None
        if stride > 1 and segmenter.reads_height:
            fill = functools.partial(fill_posteriors, prepared.inp, proba, stride)
        out.append((proba, depth, summary, fill, prepared.full_depth, factor))
    resolution = f"downsample {factor}, " if factor > 1 else ""
    return out, f"{source} ({resolution}stride {stride}) on {what}"


def _smooth(proba, depth, config, summary, fill, frame, factor):
    """The CRF stage as the Segmenter runs it (less the island rules): `segment_crf` at the
    working resolution, then the labels brought back to the frame's. Returns both labels."""
    labels = segment_crf(proba, depth, config, summary, fill)
    return labels, labels if factor == 1 else upsample_labels(frame, labels, depth, factor)


def measure(args: argparse.Namespace) -> dict:
    """Time exact and realtime CRF on the same posteriors; compare their energies.

    The CRF stage is timed by itself (`segment_crf`, which `Segmenter.smooth` runs), on
    posteriors made once per frame.
    """
    overrides = {
        k: getattr(args, k)
        for k in ("smoothness", "confidence", "ring", "cycles")
        if getattr(args, k) is not None
    }
    realtime = CRFConfig(mode="realtime", **overrides)
    exact = CRFConfig(**{**realtime.to_dict(), "mode": "exact"})
    none = CRFConfig(**{**realtime.to_dict(), "mode": "none"})
    frames, source = _frames(args)
    proba0, depth0, summary0, fill0, frame0, factor0 = frames[0]
    _smooth(proba0, depth0, realtime, summary0, fill0, frame0, factor0)  # compile the kernels
    segment_crf(proba0, depth0, realtime)
    rows = []
    for proba, depth, summary, fill, frame, factor in frames:
        t0, c0 = time.perf_counter(), time.process_time()
        lab_exact = _smooth(proba, depth, exact, None, None, frame, factor)[0]
        t_exact, c_exact = time.perf_counter() - t0, time.process_time() - c0
        times, cpu = [], []
        for _ in range(args.repeat):
            t0, c0 = time.perf_counter(), time.process_time()
            lab_rt = _smooth(proba, depth, realtime, summary, fill, frame, factor)[0]
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        lab_none = segment_crf(proba, depth, none)
        e_exact, e_rt, e_none = (
            potts_energy(lab, proba, depth, realtime) for lab in (lab_exact, lab_rt, lab_none)
        )
        valid = depth > 0
        band = band_mask(proba, depth, realtime)
        rows.append(
            {
                "exact_ms": 1e3 * t_exact,
                "exact_cpu_ms": 1e3 * c_exact,
                "rt_ms": 1e3 * float(np.median(times)),
                "rt_cpu_ms": 1e3 * float(np.median(cpu)),
                "rt_min_ms": 1e3 * min(times),
                "ratio": e_rt / e_exact,
                "gain": (e_none - e_rt) / (e_none - e_exact) if e_none > e_exact else 1.0,
                "agree": float((lab_rt == lab_exact)[valid].mean()),
                "band": float(band.sum() / valid.sum()),
            }
        )

    def col(key: str) -> np.ndarray:
        return np.array([r[key] for r in rows])

    return {
        "crf_exact_ms_per_frame": round(float(np.median(col("exact_ms"))), 1),
        "crf_realtime_ms_per_frame": round(float(np.median(col("rt_ms"))), 2),
        "crf_exact_cpu_ms_per_frame": round(float(np.median(col("exact_cpu_ms"))), 1),
        "crf_realtime_cpu_ms_per_frame": round(float(np.median(col("rt_cpu_ms"))), 2),
        "crf_realtime_ms_best": round(float(col("rt_min_ms").min()), 2),
        "crf_realtime_ms_worst_frame": round(float(col("rt_ms").max()), 2),
        "crf_energy_ratio": round(float(col("ratio").mean()), 5),
        "crf_energy_ratio_max": round(float(col("ratio").max()), 5),
        "crf_energy_excess_pct": round(100 * float(col("ratio").mean() - 1), 4),
        "crf_gain_fraction": round(float(col("gain").mean()), 4),
        "crf_gain_fraction_min": round(float(col("gain").min()), 4),
        "crf_label_agreement": round(float(col("agree").mean()), 4),
        "crf_band_fraction": round(float(col("band").mean()), 4),
        "frames": len(rows),
        "frame_shape": "x".join(str(s) for s in frames[0][4].shape[::-1]),
        "working_shape": "x".join(str(s) for s in frames[0][1].shape[::-1]),
        "unaries": source,
        "realtime_config": realtime.to_dict(),
        "load_average_1min": round(os.getloadavg()[0], 2),
    }
