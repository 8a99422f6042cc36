"""The Segmenter's stages in one process: `topseg bench stages`.

Labels the depth frames of a recording (default: the bundled cell recording, a robot, a
table, objects and people at 320x240, gated by the static background recorded beside it as
the live worker is) with the model, after `--warmup` frames, looping the recording when it
holds fewer than `--frames`. Reports, per frame:

- `<stage>_ms_p50` / `_p90` / `_p99`: each stage's own time (pre, model_input, background,
  forest, crf, context_check, person_check, surfaces, post), then `total_ms_*`;
- `cpu_ms_per_frame`: the process's CPU time (every thread) a frame, which on cores the
  worker shares with a driver, the safety service and a viewer is what it takes from them;
- `wall_ms_per_frame`, `frames`, the frame size and the numba threads.

`topseg bench pipeline` and `topseg bench safety` time the same stages live, between other
processes; this one says which stage a frame's time goes to.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Iterator
from pathlib import Path

import numba
import numpy as np

from topseg.core.bundled_model import MODEL_HELP
from topseg.core.errors import TopsegError
from topseg.core.metrics import percentile
from topseg.core.segmenter import Segmenter
from topseg.core.segmenter_config import BackgroundConfig, SegmenterConfig
from topseg.drivers.replay import RecordingFrames, ReplayFrame
from topseg.services.batch.cell_pipeline import recording_background
from topseg.services.batch.demo import REPO
from topseg.services.cli.options import int_range


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Recording, model, frames timed and before timing, background, numba threads."""
    parser.add_argument(
        "--recording", type=Path, default=REPO / "recordings" / "cell.mcap", metavar="FILE",
        help="a recording holding depth frames; the first camera's are labelled (default: "
        "the bundled cell recording)",
    )  # fmt: skip
    parser.add_argument("--model", type=Path, default=None, metavar="PATH", help=MODEL_HELP)
    parser.add_argument(
        "--frames", type=int_range(1, 10**6), default=300,
        help="frames timed (default: %(default)s)",
    )  # fmt: skip
    parser.add_argument(
        "--warmup", type=int_range(0, 10**6), default=20,
        help="frames labelled before timing (default: %(default)s)",
    )  # fmt: skip
    parser.add_argument(
        "--no-background", action="store_true",
        help="without the recording's static background (CELL.background.npz beside it), "
        "which gates the frames by default",
    )  # fmt: skip
    parser.add_argument(
        "--threads", type=int_range(0, 1024), default=0,
        help="numba threads (default 0: one per core)",
    )  # fmt: skip


def looped(path: Path, count: int) -> Iterator[ReplayFrame]:
    """`count` depth frames of the recording's first camera (`RecordingFrames`: frames that
    do not decode are skipped), from its start again when it runs out; TopsegError when it
    holds none."""
    frames = RecordingFrames(path)
    given = 0
    while given < count:
        before = given
        for frame in frames:
            yield frame
            given += 1
            if given == count:
                return
        if given == before:
            raise TopsegError(f"{path}: no depth frames to label")


def measure(args: argparse.Namespace) -> dict:
    """p50, p90 and p99 ms of each stage and of their total; CPU and wall ms a frame."""
    if not args.recording.is_file():
        raise TopsegError(f"{args.recording}: no such recording")
    if args.threads:
        numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    background = None if args.no_background else recording_background(args.recording)
    config = SegmenterConfig(
        background=BackgroundConfig(path=None if background is None else str(background))
    )
    segmenter = Segmenter.from_file(args.model, config)
    segmenter.warm_up()
    stages: dict[str, list[float]] = {}
    cpu = wall = 0.0
    shape = None
    for i, frame in enumerate(looped(args.recording, args.warmup + args.frames)):
        c0, w0 = time.process_time(), time.perf_counter()
        result = segmenter.label(frame.depth, frame.intrinsics, mount=frame.mount)
        if i < args.warmup:
            continue
        cpu += time.process_time() - c0
        wall += time.perf_counter() - w0
        shape = frame.depth.shape
        for name, ms in result.timings.stages_ms.items():
            stages.setdefault(name, []).append(ms)
    out: dict = {
        "recording": str(args.recording),
        "background": background is not None,
        "frames": args.frames,
        "frame_size": f"{shape[1]}x{shape[0]}",
        "numba_threads": numba.get_num_threads(),
    }
    total = np.sum([np.asarray(v) for v in stages.values()], axis=0)
    for name, values in [*stages.items(), ("total", total)]:
        for q in (50, 90, 99):
            out[f"{name}_ms_p{q}"] = round(percentile(np.asarray(values), q), 2)
    out["cpu_ms_per_frame"] = round(1000.0 * cpu / args.frames, 2)
    out["wall_ms_per_frame"] = round(1000.0 * wall / args.frames, 2)
    return out
