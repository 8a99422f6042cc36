"""Measure a stage's speed and memory: `topseg bench
forest|crf|stages|synthesis|datagen|transport|pipeline|safety|train|calibrate`, printed as a table or, with
`--json`, as one JSON object.

Each benchmark lives in its own module with `add_arguments(parser)` and
`measure(args) -> dict`; this module prints the figures as a table, or as one JSON
object with `--json`.
"""

from __future__ import annotations

import argparse
import importlib
import json
import resource
import sys

from topseg.services.cli import describe

#: benchmark -> (module, one-line help)
BENCHES: dict[str, tuple[str, str]] = {
    "forest": (
        "topseg.services.batch.bench.forest",
        "forest inference ms per frame: the bundled model on rendered frames, full and grid",
    ),
    "datagen": (
        "topseg.services.batch.bench.datagen",
        "datagen end to end on local Dask: frames/s, write cost",
    ),
    "transport": ("topseg.services.batch.bench.transport", "depth frames over loopback Zenoh"),
    "synthesis": ("topseg.services.batch.bench.synthesis", "synthetic frames, stage by stage"),
    "crf": ("topseg.services.batch.bench.crf", "Potts CRF: realtime vs exact, time and energy"),
    "stages": (
        "topseg.services.batch.bench.stages",
        "every stage of labelling a recording's frames in one process: ms p50/p90/p99, CPU ms",
    ),
    "pipeline": (
        "topseg.services.batch.bench.pipeline",
        "driver -> worker over Zenoh: fps, latency p50/p99, F1",
    ),
    "train": (
        "topseg.services.batch.bench.train",
        "topseg train, paper config x --scale: s, CPU s, peak RSS",
    ),
    "safety": (
        "topseg.services.batch.bench.safety",
        "driver -> worker -> safety at 30 fps: reaction p50/p99, stop after a killed or covered camera",
    ),
    "calibrate": (
        "topseg.services.batch.bench.calibrate",
        "mount calibration on rendered frames: height and tilt errors over random mounts",
    ),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """One subcommand per bench (each with `--json`); every bench module is imported here."""
    sub = parser.add_subparsers(dest="bench", metavar="STAGE")
    sub.required = True
    for name, (module_name, help_text) in BENCHES.items():
        module = importlib.import_module(module_name)
        p = sub.add_parser(
            name,
            help=help_text,
            description=describe.description(module.__doc__, "docs/performance.md"),
            formatter_class=describe.ParagraphFormatter,
        )
        p.add_argument(
            "--json", action="store_true", help="print one JSON object instead of a table"
        )
        module.add_arguments(p)
        p.set_defaults(_measure=module.measure)


def peak_rss_mb() -> float:
    """Peak resident memory of this process (and waited-for children), MiB."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return max(own, kids) / 1024.0


def format_table(figures: dict) -> str:
    """Aligned `name  value` lines; floats to 3 decimals (1 from 100 up) so columns stay short."""
    width = max(len(k) for k in figures)
    lines = []
    for key, value in figures.items():
        if isinstance(value, float):
            value = f"{value:.3f}" if abs(value) < 100 else f"{value:.1f}"
        lines.append(f"{key:<{width}}  {value}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Measure the chosen bench, add the peak RSS, print a table or one JSON object."""
    figures = args._measure(args)
    figures.setdefault("peak_rss_mb", round(peak_rss_mb(), 1))
    if args.json:
        json.dump(figures, sys.stdout)
        sys.stdout.write("\n")
    else:
        print(f"topseg bench {args.bench}")
        print(format_table(figures))
    return 0
