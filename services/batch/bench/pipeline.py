"""The live path end to end: driver -> Zenoh -> worker -> Zenoh, each a separate process.

Labelled fps, latency (driver stamp -> labels received) p50/p99, frames sent and labelled,
and the mean F1 against the source's ground truth when it has one. Target: >= 29.5 fps
labelled at 30 fps input, p50 <= 25 ms and p99 <= 40 ms on a 2-core machine.

The default source is the bundled recording replayed at 30 fps in a loop: the driver costs
~3 ms of CPU a frame (reading the MCAP chunks, publishing depth and truth) on the worker's
cores. `--source synthetic` renders scenes live in the driver instead (15-40 ms a frame on
one core), which takes a core from the worker. The figures include the worker's own ms per
stage (receive, mount, forest, CRF, publish, total; p50 and p99).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from topseg.core.bundled_model import MODEL_HELP
from topseg.services.batch.demo import REPO
from topseg.services.batch.pipeline import run_pipeline
from topseg.services.cli.options import (
    add_segmenter_arguments,
    finite,
    int_range,
    segmenter_config,
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Duration, rate, source, model (default: the bundled one) and the worker's mode."""
    parser.add_argument(
        "--duration",
        type=finite(0.1, 86400),
        default=10.0,
        metavar="S",
        help="seconds of labels (default: %(default)s)",
    )
    parser.add_argument(
        "--fps", type=finite(0.1, 1000), default=30.0, help="source rate (default: %(default)s)"
    )

    parser.add_argument(
        "--source",
        default=f"replay:{REPO / 'recordings' / 'demo.mcap'}",
        metavar="SPEC",
        help="depth source; a replay is looped (default: the bundled recording)",
    )
    parser.add_argument("--model", type=Path, default=None, metavar="PATH", help=MODEL_HELP)
    parser.add_argument("--lossless", action="store_true", help="worker labels every frame (FIFO)")
    add_segmenter_arguments(parser)
    parser.add_argument(
        "--cameras",
        type=int_range(1, 16),
        default=1,
        metavar="N",
        help="drivers of the source into the one worker, each at --fps (default: %(default)s)",
    )


def measure(args: argparse.Namespace) -> dict:
    """Run the pipeline for --duration seconds; its figures with the mean F1 only."""
    figures = run_pipeline(
        args.source,
        args.model,
        args.duration,
        args.fps,
        segmenter_config(args),
        None,
        args.lossless,
        cameras=args.cameras,
    )
    scores = figures.pop("scores")
    figures.pop("exit_codes")
    figures.pop("confusion")
    figures["avg_f1"] = None if scores is None else scores["avg_f1"]
    return figures
