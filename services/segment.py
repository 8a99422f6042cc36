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
from collections.abc import Iterator
from pathlib import Path

log = logging.getLogger("topseg.segment")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "inputs", nargs="+", type=Path, metavar="INPUT", help="PNG files, folders of PNGs, .mcap"
    )
    parser.add_argument("--model", required=True, type=Path, help="model file from `topseg train`")
    parser.add_argument(
        "--out", required=True, type=Path, help="folder for the label PNGs and overlays"
    )
    parser.add_argument("--crf", choices=("none", "exact", "realtime"), default="realtime")


def model_camera(header: dict):
    """The intrinsics the model was trained for (Kinect v1 when the header does not say)."""
    from topseg.core.camera import KINECT_V1, TopViewMount

    cam = header.get("dataset", {}).get("attrs", {}).get("camera")
    return TopViewMount.from_dict(cam).intrinsics if cam else KINECT_V1


def read_depth_png(path: Path):
    """A 16-bit single-channel PNG as uint16 mm; anything else is a clear error."""
    import numpy as np
    from PIL import Image, UnidentifiedImageError

    from topseg.core.errors import TopsegError
    from topseg.core.formats.wire import MAX_SIDE

    try:
        with Image.open(path) as img:
            if max(img.size) > MAX_SIDE:  # before load(): a lying header must not allocate
                raise TopsegError(f"{path}: a {img.width}x{img.height} image is no depth frame")
            img.load()
            if img.mode not in ("I;16", "I;16B", "I;16L", "I"):
                raise TopsegError(
                    f"{path}: a depth PNG must be 16-bit greyscale (mm), this one is {img.mode}"
                )
            depth = np.asarray(img)
    except (
        UnidentifiedImageError,
        OSError,
        SyntaxError,
        ValueError,
        Image.DecompressionBombError,
    ) as exc:
        raise TopsegError(f"{path}: not a readable PNG ({exc})") from None
    if depth.ndim != 2 or depth.min() < 0 or depth.max() > 65535:
        raise TopsegError(f"{path}: depth must be one channel of 0..65535 mm")
    return depth.astype(np.uint16)


def frames_of(path: Path) -> Iterator[tuple[str, object, object]]:
    """(name, depth, intrinsics or None) for every frame an input holds."""
    from topseg.core.errors import TopsegError
    from topseg.core.formats import recording, wire

    if path.is_dir():
        pngs = sorted(path.glob("*.png"))
        if not pngs:
            raise TopsegError(f"{path}: no .png files in this folder")
        for p in pngs:
            yield p.stem, read_depth_png(p), None
    elif path.suffix.lower() == ".png":
        yield path.stem, read_depth_png(path), None
    elif path.suffix.lower() == ".mcap":
        rejected = frames = 0
        for msg in recording.read_messages(path):
            try:
                if wire.parse_key(msg.key).kind != "depth":
                    continue
                frame = wire.decode_depth(msg.data)
            except wire.WireError as exc:
                rejected += 1
                log.warning("%s: skipping a damaged message: %s", path, exc)
                continue
            frames += 1
            yield f"{path.stem}_{frame.seq:06d}", frame.depth, frame.intrinsics
        if rejected:
            log.warning("%s: %d damaged messages skipped", path, rejected)
        if not frames:
            raise TopsegError(f"{path}: no readable depth frame in this recording")
    elif not path.exists():
        raise TopsegError(f"{path}: no such file or folder")
    else:
        raise TopsegError(f"{path}: expected a .png, a folder of PNGs or an .mcap recording")


def check_camera(name: str, depth, intrinsics, expected) -> None:
    from topseg.core.errors import TopsegError

    if depth.shape != expected.shape:
        raise TopsegError(
            f"{name}: frame is {depth.shape[1]}x{depth.shape[0]} but the model was trained for "
            f"{expected.width}x{expected.height}; resample it to that camera first"
        )
    if intrinsics is not None and abs(intrinsics.fx - expected.fx) > 0.01 * expected.fx:
        raise TopsegError(
            f"{name}: focal length {intrinsics.fx:.1f} px differs from the model's {expected.fx:.1f} px"
        )


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
    from topseg.core import crf, forest
    from topseg.core.errors import TopsegError

    model, header = forest.load_model(args.model)
    expected = model_camera(header)
    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise TopsegError(f"cannot create {args.out}: {exc.strerror}") from None
    config = crf.CRFConfig(mode=args.crf)
    count = 0
    inputs = [p for arg in args.inputs for p in _expand(arg)]
    skipped = 0
    for source in inputs:
        try:
            for name, depth, intrinsics in frames_of(source):
                check_camera(name, depth, intrinsics, expected)
                proba = forest.predict_proba(model, depth)
                if args.crf == "none":
                    labels = forest.labels_from_proba(proba, depth)
                else:
                    labels = crf.segment_crf(proba, depth, config)
                save_png(args.out / f"{name}_labels.png", labels)
                save_png(args.out / f"{name}_overlay.png", overlay(depth, labels))
                count += 1
        except TopsegError as exc:  # this input is damaged: say so once, go on with the rest
            skipped += 1
            print(f"topseg segment: skipped {exc}", file=sys.stderr)
    print(f"segmented {count} frames into {args.out}")
    if skipped:
        raise TopsegError(f"{skipped} of {len(inputs)} inputs could not be segmented (see above)")
    return 0


def _expand(path: Path) -> list[Path]:
    """A folder of PNGs -> its PNGs (each one an input of its own); anything else as is."""
    if path.is_dir():
        pngs = sorted(path.glob("*.png"))
        return pngs or [path]  # an empty folder: frames_of says so
    return [path]
