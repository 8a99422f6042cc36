"""`topseg datagen preview PATH`: a PNG contact sheet of a dataset, to check scenes by eye.

Each tile is one frame: depth on the left (grey, nearer is brighter, no depth dark red; the
floor of the frame's own mount dark) and its coloured labels on the right, both downsampled
by `--scale`, under a caption with the frame index, its camera (sensor, height, pitch/roll)
and what its scene holds; a legend of the label colours runs along the bottom. Frames of a
smaller sensor are drawn at their own size, top-left in the tile.

Layout, in pixels, for frames of at most H x W at 1/scale (h = H // scale, w = W // scale):
a tile is (2 w + GAP) wide and (h + CAPTION) tall; the sheet is SPACE + cols (tile + SPACE)
wide and SPACE + rows (tile + SPACE) + LEGEND tall.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from topseg.core import labels as label_table
from topseg.core.atomic import atomic_write
from topseg.core.errors import TopsegError
from topseg.core.formats.dataset import DatasetError, open_dataset
from topseg.services.cli.options import int_range

HELP = "write a PNG contact sheet (depth and labels side by side) of a dataset"
GAP = 4  # between a frame's depth and its labels
SPACE = 12  # between tiles
CAPTION = 16
LEGEND = 20
NO_DEPTH_RGB = (120, 0, 0)
BACKGROUND_RGB = (255, 255, 255)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """`topseg datagen preview`'s options."""
    parser.add_argument("path", help="dataset directory")
    parser.add_argument("--png", help="output PNG (default: PATH without .zarr + -preview.png)")
    parser.add_argument(
        "--count",
        type=int_range(1, 10000),
        default=12,
        help="frames on the sheet, evenly spaced (12)",
    )
    parser.add_argument("--cols", type=int_range(1, 1000), default=3, help="tiles per row (3)")
    parser.add_argument("--scale", type=int_range(1, 64), default=2, help="downsampling factor (2)")


def depth_rgb(depth: np.ndarray, far_mm: float, span_mm: float = 2500.0) -> np.ndarray:
    """(H, W) uint16 mm -> (H, W, 3) grey: `far_mm` (the floor) dark, `span_mm` nearer white."""
    d = depth.astype(np.float32)
    v = np.clip((far_mm - d) / span_mm, 0.0, 1.0)
    grey = (40 + 215 * v).astype(np.uint8)
    rgb = np.repeat(grey[..., None], 3, axis=2)
    rgb[depth == 0] = NO_DEPTH_RGB
    return rgb


def caption(index: int, scene: dict) -> str:
    """A short line about a frame's scene and camera, from whatever keys it has."""
    parts = [f"#{index}"]
    mount = scene.get("mount")
    if isinstance(mount, dict) and "height_mm" in mount:
        parts.append(
            f"{mount.get('sensor', '?')} {float(mount['height_mm']) / 1000:.2f}m "
            f"{float(mount.get('pitch_deg', 0)):+.0f}/{float(mount.get('roll_deg', 0)):+.0f}deg"
        )
    if isinstance(scene.get("room"), (str, dict)):
        room = scene["room"]
        parts.append(room if isinstance(room, str) else str(room.get("name", "")))
    human = scene.get("human")
    if isinstance(human, dict) and human.get("pose"):
        parts.append(str(human["pose"]))
    extra = scene.get("extra_humans")
    if isinstance(extra, list) and extra:
        parts.append(f"+{len(extra)} people")
    robots = scene.get("robots")
    if isinstance(robots, list) and robots:
        parts.append(f"{len(robots)} robots")
    objects = scene.get("objects")
    if isinstance(objects, list):
        meshes = scene.get("mesh_objects")
        meshes = meshes if isinstance(meshes, list) else []
        parts.append(f"{len(objects) + len(meshes)} objects")
    relations = scene.get("relations")
    if isinstance(relations, list) and relations:
        parts.append(f"{len(relations)} relations")
    return "  ".join(p for p in parts if p)


def contact_sheet(
    frames: list[tuple], cols: int, scale: int, far_mm: float | None = None
) -> np.ndarray:
    """(depth, labels, caption[, far_mm]) tuples -> one (rows, cols) RGB sheet (see the module
    layout); a frame's own far_mm (its floor depth) wins over the sheet's."""
    from PIL import Image, ImageDraw

    H = max(f[0].shape[0] for f in frames)
    W = max(f[0].shape[1] for f in frames)
    h, w = H // scale, W // scale
    tile_w, tile_h = 2 * w + GAP, h + CAPTION
    rows = -(-len(frames) // cols)
    width = SPACE + cols * (tile_w + SPACE)
    height = SPACE + rows * (tile_h + SPACE) + LEGEND
    sheet = np.empty((height, width, 3), np.uint8)
    sheet[:] = BACKGROUND_RGB
    for k, f in enumerate(frames):
        depth, labels = f[0], f[1]
        far = f[3] if len(f) > 3 and f[3] is not None else far_mm
        y = SPACE + (k // cols) * (tile_h + SPACE) + CAPTION
        x = SPACE + (k % cols) * (tile_w + SPACE)
        d = depth[::scale, ::scale][:h, :w]
        fh, fw = d.shape
        sheet[y : y + fh, x : x + fw] = depth_rgb(d, far if far is not None else 3600.0)
        sheet[y : y + fh, x + w + GAP : x + w + GAP + fw] = label_table.colorize(
            labels[::scale, ::scale][:h, :w]
        )
    image = Image.fromarray(sheet)
    draw = ImageDraw.Draw(image)
    for k, f in enumerate(frames):
        text = f[2]
        y = SPACE + (k // cols) * (tile_h + SPACE)
        x = SPACE + (k % cols) * (tile_w + SPACE)
        draw.text((x + 2, y + 2), text, fill=(0, 0, 0))
    x, y = SPACE, height - LEGEND + 2
    for lab in (*label_table.LABELS, label_table.NO_DEPTH_LABEL):
        draw.rectangle((x, y, x + 11, y + 11), fill=lab.color, outline=(0, 0, 0))
        draw.text((x + 15, y), lab.name, fill=(0, 0, 0))
        x += 20 + int(draw.textlength(lab.name))
    return np.asarray(image)


def write_png(rgb: np.ndarray, out: Path) -> None:
    """Write atomically: a temp file beside `out`, then rename."""
    from PIL import Image

    with atomic_write(out) as f:
        Image.fromarray(rgb).save(f, format="PNG")


def default_png(path: str) -> Path:
    """Where the sheet of dataset `path` goes by default: beside it, `<stem>-preview.png`."""
    p = Path(path.rstrip("/"))
    stem = p.name[: -len(".zarr")] if p.name.endswith(".zarr") else p.name
    return p.with_name(f"{stem}-preview.png")


def run(args: argparse.Namespace) -> int:
    """`topseg datagen preview`: draw a contact sheet of the dataset's frames into a PNG."""
    if args.count < 1 or args.cols < 1 or args.scale < 1:
        raise TopsegError("--count, --cols and --scale must be >= 1")
    ds = open_dataset(args.path)
    if len(ds) == 0:
        raise DatasetError(f"{ds.path} has no complete frames yet")
    picks = np.unique(np.linspace(0, len(ds) - 1, min(args.count, len(ds))).round().astype(int))
    frames = []
    for k in picks:
        depth, labels, mount = ds.frame(int(k))
        far_mm = mount.depth_of_height(0.0) + 100.0  # the floor on the optical axis, dark
        frames.append((depth, labels, caption(int(ds.indices[k]), ds.scene(k)), far_mm))
    sheet = contact_sheet(frames, min(args.cols, len(frames)), args.scale)
    out = Path(args.png) if args.png else default_png(args.path)
    try:
        write_png(sheet, out)
    except OSError as exc:
        raise TopsegError(f"cannot write {out}: {exc.strerror or exc}") from exc
    print(f"wrote {out} ({sheet.shape[1]}x{sheet.shape[0]}, {len(frames)} frames of {len(ds)})")
    return 0
