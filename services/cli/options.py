"""Argparse `type=` helpers that refuse a bad number up front: finite, in range, positive.

`topseg`'s subcommand parsers turn the ArgumentTypeError into one line naming the option
(`cli.OneLineParser`), e.g. `topseg driver: error: argument --fps: must be in [0.1, 1000],
got 1e-300`, exit 2: never a crash or a day-long sleep later.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable


def _fmt(x: float) -> str:
    """A bound as the operator typed it: 1000, not 1000.0."""
    return f"{x:g}"


def finite(lo: float = -math.inf, hi: float = math.inf) -> Callable[[str], float]:
    """A `type=` for a finite float in [lo, hi] (NaN and inf always refused)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"must be in [{_fmt(lo)}, {_fmt(hi)}], got {text}")
        return value

    parse.__name__ = "number"
    return parse


def int_range(lo: int, hi: int | None = None) -> Callable[[str], int]:
    """A `type=` for an integer >= lo (and <= hi when given)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < lo or (hi is not None and value > hi):
            bound = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
            raise argparse.ArgumentTypeError(f"must be {bound}, got {text}")
        return value

    parse.__name__ = "integer"
    return parse


#: a `type=` for an integer >= 1
positive_int = int_range(1)
#: a `type=` for an integer >= 0
non_negative_int = int_range(0)


def stride(text: str) -> int | None:
    """A `type=` for the forest's `--stride`: `auto` (None: from each frame's mount) or >= 1."""
    if text == "auto":
        return None
    return positive_int(text)


stride.__name__ = "stride"


def downsample(text: str) -> int | None:
    """A `type=` for the Segmenter's `--downsample`: `auto` (None: from each frame's mount)
    or a factor 1-MAX_DOWNSAMPLE."""
    from topseg.core.resolution import MAX_DOWNSAMPLE  # here: --help compiles no numba

    if text == "auto":
        return None
    return int_range(1, MAX_DOWNSAMPLE)(text)


downsample.__name__ = "downsample"


def early_exit(text: str) -> float | None:
    """A `type=` for the forest's `--early-exit`: `off` (None: every tree) or a posterior in
    (0, 1]."""
    if text == "off":
        return None
    value = finite()(text)
    if not 0.0 < value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be in (0, 1] or off, got {text}")
    return value


early_exit.__name__ = "early exit"


def add_grid_arguments(parser: argparse.ArgumentParser) -> None:
    """`--downsample auto|N`, `--stride auto|N`, `--adaptive N` and `--early-exit P|off`: the
    resolution the Segmenter works at and where the forest walks (`SegmenterConfig.downsample`,
    `.stride`, `.adaptive` and `.early_exit`; `grid_config` reads them back)."""
    from topseg.core.segmenter import ADAPTIVE_LEVELS, EARLY_EXIT

    parser.add_argument(
        "--downsample",
        type=downsample,
        default=None,
        metavar="auto|N",
        help="label every N-th pixel of every N-th row (forest, CRF and blob rules) and give "
        "each pixel the label of its nearest neighbour in depth among them; auto (default) "
        "takes half where a labelled pixel then spans at most 14.4 mm of the floor (a Kinect v1 "
        "up to 4.1 m; 1 for coarser cameras); 1: the frame's own resolution",
    )
    parser.add_argument(
        "--stride",
        type=stride,
        default=None,
        metavar="auto|N",
        help="walk the forest at every N-th pixel of every N-th row and upsample the rest by "
        "height; auto (default) spaces walked pixels ~25 mm apart on the floor; 1: every pixel",
    )
    parser.add_argument(
        "--adaptive",
        type=non_negative_int,
        default=ADAPTIVE_LEVELS,
        metavar="N",
        help="on a grid, walk N coarser grids first and the finer ones only where the coarser "
        "one is unsure or crosses a height edge; 0 walks every grid pixel (default: %(default)s)",
    )
    parser.add_argument(
        "--early-exit",
        type=early_exit,
        default=EARLY_EXIT,
        metavar="P|off",
        help="a pixel stops walking trees once its first two (or more) give one class an "
        "average posterior >= P; off walks every tree (default: %(default)s)",
    )


def grid_config(args: argparse.Namespace) -> dict:
    """The `SegmenterConfig` fields of `add_grid_arguments`' options."""
    return {
        "downsample": args.downsample,
        "stride": args.stride,
        "adaptive": args.adaptive,
        "early_exit": args.early_exit,
    }


def add_crf_arguments(parser: argparse.ArgumentParser) -> None:
    """`--crf MODE`, `--smoothness S` and `--noisy-smoothness S`: how the CRF smooths the
    forest's posteriors (`SegmenterConfig.crf`; `crf_config` reads them back)."""
    from topseg.core.crf.energy import (
        DEFAULT_SMOOTHNESS,
        MAX_SMOOTHNESS,
        MODES,
        NOISY_SMOOTHNESS,
    )

    parser.add_argument(
        "--crf",
        choices=MODES,
        default="realtime",
        help="CRF smoothing after the forest (default: %(default)s)",
    )
    parser.add_argument(
        "--smoothness",
        type=finite(0, MAX_SMOOTHNESS),
        default=DEFAULT_SMOOTHNESS,
        metavar="S",
        help="the CRF's Potts weight per cut edge, in nats (default: %(default)s; 3 scores "
        "~0.015 avg F1 higher and costs the realtime CRF ~2 ms a frame: docs/explanation/crf.md)",
    )
    parser.add_argument(
        "--noisy-smoothness",
        type=finite(0, MAX_SMOOTHNESS),
        default=NOISY_SMOOTHNESS,
        metavar="S",
        help="the Potts weight for frames from a noisy camera (20 mm or more of depth noise "
        "at the floor, a stereo camera at range: the frames topseg smooths), when larger "
        "than --smoothness (default: %(default)s: docs/explanation/crf.md)",
    )


def add_island_arguments(parser: argparse.ArgumentParser) -> None:
    """`--min-head-cm2 A`, `--min-furniture-cm2 A`, `--min-plant-cm2 A`: after the CRF, head,
    furniture and plant blobs smaller than A cm2 take their border's label
    (`SegmenterConfig.min_head_cm2`, `min_furniture_cm2`, `min_plant_cm2`);
    `--satellite-head-cm2 A`: so do head blobs smaller than A beside a larger head
    (`satellite_head_cm2`); `--fill-holes-cm2 A`: before labelling, holes up to A cm2 inside
    one surface take its depth (`fill_holes_cm2`). `island_config` reads them back."""
    from topseg.core.segmenter import (
        EDGE_HEAD_SHARE,
        FILL_HOLES_CM2,
        MIN_FURNITURE_CM2,
        MIN_HEAD_CM2,
        MIN_PLANT_CM2,
        SATELLITE_HEAD_CM2,
        SATELLITE_RADIUS_CM,
    )

    parser.add_argument(
        "--min-head-cm2",
        type=finite(0, 10000),
        default=MIN_HEAD_CM2,
        metavar="A",
        help="after the CRF, blobs labelled head smaller than A cm2 on the surface (a whole "
        "head seen from above is 200-300) take their border's label, those at the image's "
        f"edge (cut by it) under {EDGE_HEAD_SHARE:g} A; 0 keeps them (default: %(default)s)",
    )
    parser.add_argument(
        "--min-furniture-cm2",
        type=finite(0, 100000),
        default=MIN_FURNITURE_CM2,
        metavar="A",
        help="the same for blobs labelled chair, storage or table (a chair's seat seen from "
        "above is ~1600 cm2) (default: %(default)s)",
    )
    parser.add_argument(
        "--min-plant-cm2",
        type=finite(0, 100000),
        default=MIN_PLANT_CM2,
        metavar="A",
        help="the same for blobs labelled plant (the smallest pot seen from above is ~150 "
        "cm2; a noisy camera leaves specks of plant on table tops) (default: %(default)s)",
    )
    parser.add_argument(
        "--satellite-head-cm2",
        type=finite(0, 10000),
        default=SATELLITE_HEAD_CM2,
        metavar="A",
        help="after the CRF, head blobs smaller than A cm2 whose centre lies within "
        f"{SATELLITE_RADIUS_CM:g} cm of a larger head blob's (an arm or a hand beside a head) "
        "take their border's label; 0 keeps them (default: %(default)s)",
    )

    parser.add_argument(
        "--fill-holes-cm2",
        type=finite(0, 10000),
        default=FILL_HOLES_CM2,
        metavar="A",
        help="before labelling, holes without depth up to A cm2 that lie inside one surface "
        "(dark hair on a time-of-flight camera) take its depth and its label; 0 leaves them "
        "(default: %(default)s)",
    )


def island_config(args: argparse.Namespace) -> dict:
    """The `SegmenterConfig` fields of `add_island_arguments`' options."""
    return {
        "min_head_cm2": args.min_head_cm2,
        "min_furniture_cm2": args.min_furniture_cm2,
        "min_plant_cm2": args.min_plant_cm2,
        "satellite_head_cm2": args.satellite_head_cm2,
        "fill_holes_cm2": args.fill_holes_cm2,
    }


def crf_config(args: argparse.Namespace):
    """The `CRFConfig` of `add_crf_arguments`' options."""
    from topseg.core.crf import CRFConfig

    return CRFConfig(
        mode=args.crf, smoothness=args.smoothness, noisy_smoothness=args.noisy_smoothness
    )
