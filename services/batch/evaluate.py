"""Score a model on a dataset from `topseg datagen`: the forest and the CRF label every
complete frame through its own mount, and it prints the per-class precision / recall / F1
table in the paper's Table I layout, with mAP, mAR and avg F1 over the paper's ten classes
(and over all twelve, robot and object included, where they differ) and heads counted as
blobs. `--json FILE` writes the scores, `--plots DIR` the confusion matrix and example frames.

The forest runs on every complete frame of the dataset, each read through its own mount
(`Dataset.mount`; cropped to its camera); the CRF mode (`none`, `exact`,
`realtime`) smooths its posteriors. Prints the per-class precision / recall / F1 table
(Table I's layout) with mAP, mAR and avg F1 over ids 1..10, and over ids 1..12 where those
differ; robot and object get their rows when the truth holds them or the model predicts them.
With `--plots DIR` it draws the confusion matrix and a few frames (depth, truth, forest, CRF)
side by side.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from topseg.core import metrics
from topseg.core.atomic import atomic_write
from topseg.core.bundled_model import MODEL_HELP
from topseg.core.errors import TopsegError
from topseg.core.formats.dataset import open_dataset
from topseg.core.scoring import dataset_frames, score
from topseg.core.segmenter import Segmenter
from topseg.services.cli.options import (
    add_segmenter_arguments,
    non_negative_int,
    positive_int,
    segmenter_config,
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """--model (default: the bundled model), --data, --crf, --smoothness and what to write."""
    parser.add_argument("--model", type=Path, default=None, help=MODEL_HELP)
    parser.add_argument("--data", required=True, type=Path, help="dataset from `topseg datagen`")
    add_segmenter_arguments(parser)
    parser.add_argument(
        "--frames", type=positive_int, default=None, help="score only the first N frames"
    )
    parser.add_argument("--json", type=Path, dest="json_out", help="write the scores as JSON here")
    parser.add_argument("--plots", type=Path, help="write confusion.png and frames.png here")
    parser.add_argument(
        "--examples", type=non_negative_int, default=4, help="frames drawn in frames.png"
    )


def run(args: argparse.Namespace) -> int:
    """Score the model on the dataset; print the tables, write the JSON and plots asked for."""
    from tqdm import tqdm

    segmenter = Segmenter.from_file(args.model, segmenter_config(args))
    ds = open_dataset(args.data)
    if args.json_out:  # before the scoring: a folder we cannot write costs no work
        _check_writable(args.json_out.parent, args.json_out)
    if args.plots:
        _check_writable(args.plots, args.plots / "confusion.png")
    n = len(ds) if args.frames is None else min(args.frames, len(ds))
    frames = tqdm(
        dataset_frames(ds, range(n)), total=n, desc="evaluate", unit="frame", disable=None
    )
    result = score(segmenter, frames, examples=args.examples)

    forest_scores, final_scores = result.forest.scores(), result.crf.scores()
    print(metrics.format_table(forest_scores, title=f"forest alone, {n} frames of {args.data}"))
    if args.crf != "none":
        print()
        title = (
            f"forest + CRF ({args.crf}, smoothness {args.smoothness:g}, "
            f"{max(args.smoothness, args.noisy_smoothness):g} on noisy cameras)"
        )
        print(metrics.format_table(final_scores, title=title))
    timing = result.ms_per_frame()
    stride = "auto (from each frame's mount)" if args.stride is None else str(args.stride)
    downsample = "auto" if args.downsample is None else str(args.downsample)
    print(
        f"\nms per frame: forest {timing['forest']:.1f} (downsample {downsample}, stride "
        f"{stride}, adaptive {args.adaptive}), crf {timing['crf']:.1f}"
    )
    print(result.heads.summary())
    if segmenter.reads_height and result.frames:
        share = result.floor_share / result.frames
        print(f"floor skipped: {100 * share:.1f} % of the pixels with depth (each frame's mount)")

    if args.json_out:
        doc = json.loads(metrics.to_json(final_scores))
        doc.update(
            crf=args.crf,
            smoothness=args.smoothness,
            noisy_smoothness=args.noisy_smoothness,
            downsample="auto" if args.downsample is None else args.downsample,
            stride="auto" if args.stride is None else args.stride,
            adaptive=args.adaptive,
            model=str(segmenter.path),
            data=str(args.data),
            forest_only=json.loads(metrics.to_json(forest_scores)),
            ms_per_frame=timing,
            confusion=result.crf.confusion.tolist(),
            head_detections=result.heads.to_dict(),
        )
        _writing(args.json_out, lambda: _write_text(args.json_out, json.dumps(doc, indent=2)))
    if args.plots:
        from topseg.services.batch.plots import confusion_figure, frames_figure

        confusion, frames_png = args.plots / "confusion.png", args.plots / "frames.png"
        _writing(
            confusion,
            lambda: confusion_figure(result.crf.confusion, confusion, title=f"CRF: {args.crf}"),
        )
        _writing(frames_png, lambda: frames_figure(result.examples, frames_png, crf_name=args.crf))
        print(f"wrote {confusion} and {frames_png}")
    return 0


def _check_writable(folder: Path, target: Path) -> None:
    """TopsegError (one line naming `target`) unless a file can be made in `folder`."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise TopsegError(f"cannot write {target}: {exc.strerror or exc}") from None


def _writing(path: Path, write) -> None:
    """Run `write()`; an OSError becomes one line naming `path` (the scores were printed)."""
    try:
        write()
    except OSError as exc:
        raise TopsegError(
            f"cannot write {path}: {exc.strerror or exc}; the scores above are complete, "
            "nothing partial was left there"
        ) from None


def _write_text(path: Path, text: str) -> None:
    """Atomic: a reader sees the old file or the whole new one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as f:
        f.write((text + "\n").encode())
