"""Synthetic frames in one process: `topseg bench synthesis`.

Renders `--frames` frames with `topseg.core.synth.synthesis.Synthesizer` after `--warmup` frames
(numba compilation and the first loads of pooled pybullet bodies) and reports the median
and 90th percentile of each stage: sampling the scene from the density function, building
it in pybullet (pose pooled bodies, read back their primitives), ray casting, noise. The
budget is build + raycast + noise <= 25 ms per frame (docs/performance.md); datagen runs one such process
per core.
"""

from __future__ import annotations

import argparse
import time

import numba
import numpy as np

from topseg.core.errors import TopsegError
from topseg.core.metrics import percentile
from topseg.core.synth.synthesis import SynthesisConfig, Synthesizer
from topseg.services.cli.options import int_range


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Frames timed and rendered before timing, mode, noise spec, numba threads."""
    parser.add_argument("--frames", type=int_range(1, 10**7), default=200)
    parser.add_argument(
        "--warmup", type=int_range(0, 10**7), default=300, help="frames rendered before timing"
    )
    parser.add_argument("--mode", choices=("modeled", "non-modeled"), default="modeled")
    parser.add_argument("--noise", default="kinect", help="none | gaussian:<sigma_mm> | kinect")
    parser.add_argument(
        "--threads", type=int_range(0, 1024), default=0, help="numba threads (0 = numba's default)"
    )


def measure(args: argparse.Namespace) -> dict:
    """p50 and p90 ms of each stage and of build + raycast + noise; frames/s; pooled bodies."""
    if args.frames < 1 or args.warmup < 0:
        raise TopsegError("--frames must be >= 1 and --warmup >= 0")
    if args.threads:
        numba.set_num_threads(args.threads)
    cfg = SynthesisConfig(mode=args.mode, noise=args.noise)
    stages: dict[str, list[float]] = {}
    with Synthesizer(cfg) as synth:
        for i in range(args.warmup):
            synth.render(10_000_000 + i)
        t0 = time.perf_counter()
        for i in range(args.frames):
            frame = synth.render(i)
            for k, v in frame.timings_ms.items():
                stages.setdefault(k, []).append(v)
        wall = time.perf_counter() - t0
        bodies = synth.builder.n_bodies
    per = {k: np.asarray(v) for k, v in stages.items()}
    render_ms = per["build"] + per["raycast"] + per["noise"]
    out: dict = {
        "frames": args.frames,
        "mode": args.mode,
        "noise": cfg.noise,
        "numba_threads": numba.get_num_threads(),
    }
    for k, v in per.items():
        out[f"{k}_ms_p50"] = round(percentile(v, 50), 2)
        out[f"{k}_ms_p90"] = round(percentile(v, 90), 2)
    out["build_raycast_noise_ms_p50"] = round(percentile(render_ms, 50), 2)
    out["build_raycast_noise_ms_p90"] = round(percentile(render_ms, 90), 2)
    out["frames_per_s"] = round(args.frames / wall, 1)
    out["pooled_bodies"] = bodies
    return out
