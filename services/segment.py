"""Segment depth offline: 16-bit PNGs (mm) or MCAP recordings in, label PNGs and overlays out.

For each input frame NAME it writes `NAME_labels.png` (8-bit label ids, 255 = no depth) and
`NAME_overlay.png` (depth in grey with the label colours blended on top). Frames must come
from the camera the model was trained for (its size and focal length): the features are
metric offsets scaled by the focal length, so another camera is refused rather than
silently mis-segmented.

A damaged input (an unreadable or non-16-bit PNG, a frame of another camera, a file that is
not a recording) is skipped with one line on stderr and the others are still segmented; the
exit status is then 2. A recording cut short or with damaged messages gives what it holds.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

log = logging.getLogger("topseg.segment")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Inputs, --model (default: the bundled model), --out and --crf."""
    from topseg.core.segmenter import MODEL_HELP

    parser.add_argument(
        "inputs", nargs="+", type=Path, metavar="INPUT", help="PNG files, folders of PNGs, .mcap"
    )
    parser.add_argument("--model", type=Path, default=None, help=MODEL_HELP)
    parser.add_argument(
        "--out", required=True, type=Path, help="folder for the label PNGs and overlays"
    )
    parser.add_argument("--crf", choices=("none", "exact", "realtime"), default="realtime")


def overlay(depth, labels):
    """Depth in grey (near = bright) with label colours blended on the foreground."""
    import numpy as np

    from topseg.core.labels import BACKGROUND, NO_DEPTH, colorize

    valid = depth > 0
    grey = np.zeros(depth.shape, np.float32)
    if valid.any():
        lo, hi = np.percentile(depth[valid], [1, 99])
        grey = np.clip((hi - depth.astype(np.float32)) / max(hi - lo, 1.0), 0, 1)
    base = np.repeat((grey * 200 + 30)[..., None], 3, axis=2)
    colours = colorize(labels).astype(np.float32)
    fg = ((labels != BACKGROUND) & (labels != NO_DEPTH))[..., None]
    out = np.where(fg, 0.35 * base + 0.65 * colours, base)
    out[~valid] = 0
    return out.astype(np.uint8)


def save_png(path: Path, array) -> None:
    """Atomic PNG write."""
    from PIL import Image

    from topseg.core.atomic import atomic_write

    with atomic_write(path) as f:
        Image.fromarray(array).save(f, format="PNG")


def run(args: argparse.Namespace) -> int:
    """Segment every input; a damaged one is skipped with one line, and exit 2 at the end."""
    from topseg.core.errors import TopsegError
    from topseg.core.segmenter import Segmenter
    from topseg.drivers.replay import input_frames

    segmenter = Segmenter.from_file(args.model, crf=args.crf)
    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise TopsegError(f"cannot create {args.out}: {exc.strerror}") from None
    count = 0
    inputs = [p for arg in args.inputs for p in _expand(arg)]
    skipped = 0
    for source in inputs:
        try:
            for frame in input_frames(source, on_recording=_report_skipped):
                labels = segmenter.label(frame.depth, frame.intrinsics, name=frame.name).labels
                save_png(args.out / f"{frame.name}_labels.png", labels)
                save_png(args.out / f"{frame.name}_overlay.png", overlay(frame.depth, labels))
                count += 1
        except TopsegError as exc:  # this input is damaged: say so once, go on with the rest
            skipped += 1
            print(f"topseg segment: skipped {exc}", file=sys.stderr)
    print(f"segmented {count} frames into {args.out}")
    if skipped:
        raise TopsegError(f"{skipped} of {len(inputs)} inputs could not be segmented (see above)")
    return 0


def _report_skipped(reader) -> None:
    """One line for what a recording held but was not segmented."""
    if reader.rejected:
        log.warning("%s: %d damaged messages skipped", reader.path, reader.rejected)
    if reader.others:
        log.warning(
            "%s: segmented %s only; also holds %s",
            reader.path,
            reader.depth_key,
            ", ".join(sorted(reader.others)),
        )


def _expand(path: Path) -> list[Path]:
    """A folder of PNGs -> its PNGs (each one an input of its own); anything else as is."""
    from topseg.drivers.replay import png_files

    if path.is_dir():
        return png_files(path) or [path]  # an empty folder: input_frames says so
    return [path]
