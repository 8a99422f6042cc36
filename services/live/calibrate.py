"""Find where a camera hangs: fit the floor in a few seconds of its frames, print the height
above the floor, pitch, roll and the fit's residual, and write a mount file for `topseg
driver --mount` with a picture to check by eye; refuses with one line when it finds no
floor, the camera moved, or it is tilted too far. `topseg calibrate robot --cell CELL.toml
--source zenoh` fits the robot's base pose in the cell file instead.

    topseg calibrate --source freenect --out cell1-mount.json

takes `--frames` frames from the source (the floor should be mostly clear and the camera
still), fits the floor plane robustly (RANSAC over the back-projected points), prints the
camera's height above the floor, its pitch and roll, the fit's residual and the share of the
view on the floor, and writes the mount file (`topseg driver --mount FILE` reads it) and a
picture beside it: the depth, the floor inliers over it, and the height above the floor (the
picture needs matplotlib, which `topseg[train]` installs; without it only the mount file).

It refuses with one line when the source gives no depth, its frames are not all of one
camera, no plane covers enough of the view (also said when the frames agree but the floors
found in them do not: a still camera that sees too little floor, or a flat surface shows
below the plane found: a table over most of the view), the frames disagree (the camera
moved), or the camera is tilted beyond what is supported.
A camera that sends range along each pixel's ray instead of depth is recognised, and its
mount says so (`radial`, docs/howto/calibrate.md). A stereo camera's edges are thinned before
labelling (`core/fattening.py`); `--no-edge-thinning` writes a mount that says its edges are
not fattened (a camera whose own filters already clean them), so they are left as they are.

    topseg calibrate --source freenect --background cell1-background.npz

records the empty cell instead (or as well, with `--out`): over the same frames, the depth of
what does not move at every pixel and its noise (`core/background.py`), written as a
background file for `topseg worker --background FILE` and `topseg segment --background FILE`,
which send pixels matching it to background without the forest. Pixels with too few
readings, or whose readings moved (a robot at work while recording), are not background and
are always labelled. It prints the share of the view that is background, the median noise,
the share that was unstable and the file's id. Record it again after a fixture or the camera
moved (the worker reports that: docs/howto/static-cell-background.md).

    topseg calibrate robot --cell cell1.toml --source zenoh [--write]

fits the robot's base pose (`[robot] base_xyz_m`, `base_yaw_deg` of the cell file) to
`--frames` (10) depth frames of one of the cell's cameras, each paired with the robot's
joint state nearest in stamp (within 20 ms), live from Zenoh or from a recording
(`--source replay:FILE.mcap`): it prints the fitted pose, the change from the cell file's
and the residual, and the lines to paste, or with `--write` rewrites them in the cell file
(`services/live/calibrate_robot.py`).
"""

from __future__ import annotations

import argparse
import logging
import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from topseg.core.atomic import atomic_write
from topseg.core.background import fit_background, save_background
from topseg.core.calibration import CalibrationConfig, estimate_mount, floor_mask
from topseg.core.errors import TopsegError
from topseg.core.extras import is_installed, needs_extra
from topseg.core.formats.mount_file import write_mount_file
from topseg.core.sensors import get_sensor, sensor_of_frames
from topseg.drivers import SourceOptions, open_source
from topseg.drivers.spec import parse_spec
from topseg.services.cli.options import positive_int
from topseg.services.live import calibrate_robot

log = logging.getLogger("topseg.calibrate")

#: the sensor a driver kind most likely is, when --sensor is not given
SENSOR_OF_KIND = {"freenect": "kinect_v1", "openni2": "kinect_v1", "oak": "oak_d"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """[robot], --source, --frames, --sensor, --edge-thinning, --out, --picture,
    --background; and the robot's flags (`calibrate_robot.add_arguments`)."""
    parser.add_argument(
        "target",
        nargs="?",
        choices=("robot",),
        help="robot: fit the robot's base pose in the cell file instead of the camera's mount",
    )
    parser.add_argument(
        "--source",
        required=True,
        help="replay:FILE, freenect, openni2, oak or synthetic[:...]; robot: zenoh or "
        "replay:FILE.mcap",
    )
    parser.add_argument(
        "--frames",
        type=positive_int,
        default=None,
        help="frames to fit over (default 60, ~2 s at 30 fps; robot: 10 paired with joint states)",
    )
    parser.add_argument(
        "--sensor",
        default=None,
        help="sensor model name in core/sensors.py (default: the frames' own, the source "
        "kind's usual one; for PNG frames, which say no optics, the supported sensor of "
        "their size; else 'unknown')",
    )
    parser.add_argument(
        "--edge-thinning",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="whether a stereo camera's fattened depth edges are thinned before labelling "
        "(default: as the frames' own mount says, else on; --no-edge-thinning for a camera "
        "whose own filters already clean its edges: thinning clean edges costs accuracy)",
    )
    parser.add_argument("--out", type=Path, default=None, help="the mount file to write (JSON)")
    parser.add_argument(
        "--background",
        type=Path,
        default=None,
        metavar="OUT.npz",
        help="record the empty cell: the background file to write (the depth of what does not "
        "move and its noise, for `worker --background`); with --out as well, both from the "
        "same frames",
    )
    parser.add_argument(
        "--picture", type=Path, default=None, help="picture to write (default: OUT with .png)"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the point subsample")
    calibrate_robot.add_arguments(parser)


def check_writable(path: Path) -> None:
    """Create `path`'s folder when missing; TopsegError now, before the camera is read, if
    `path` cannot be written."""
    parent = path.parent if str(path.parent) else Path(".")
    if path.is_dir():
        raise TopsegError(f"{path} is a folder; --out needs a file name")
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise TopsegError(f"cannot write {path}: cannot create {parent}: {exc.strerror}") from None
    if not os.access(parent, os.W_OK):
        raise TopsegError(f"cannot write {path}: folder {parent} is not writable")


def sensor_name(given: str | None, source: str, frame_mount) -> str:
    """--sensor (checked against `core.sensors`), else the sensor the frames' own mount
    names, else the usual sensor of the driver kind, else 'unknown'."""
    if given:
        if given != "unknown":
            get_sensor(given)  # a one-line ConfigError listing the known sensors
        return given
    if frame_mount is not None:
        return frame_mount.sensor
    return SENSOR_OF_KIND.get(parse_spec(source).kind, "unknown")


def camera_text(k, other) -> str:
    """'640x480' (when `other` is another size), else the optics too, numbers as %.4g:
    what tells `k` from `other` in a line."""
    size = f"{k.width}x{k.height}"
    if k.shape != other.shape:
        return size
    return f"{size} with fx {k.fx:.4g} fy {k.fy:.4g} cx {k.cx:.4g} cy {k.cy:.4g}"


def grab(source: str, n: int) -> tuple[list, object, object, bool]:
    """Up to `n` depth frames (uint16 arrays) from the source, their intrinsics, the mount
    the first frame carries (None when the source sends none), and whether the source knows
    its optics (a PNG does not: its frames carry `replay.png_intrinsics`, a guess)."""
    from tqdm import tqdm

    frames, intrinsics, mount = [], None, None
    with open_source(source, SourceOptions(realtime=False)) as src:
        known = getattr(src, "kind", None) != "png"
        bar = tqdm(total=n, desc="calibrate", unit="frame", disable=None)
        try:
            for item in src.frames():
                depth = item.depth
                if intrinsics is None:
                    intrinsics = depth.intrinsics
                    mount = getattr(depth, "mount", None)
                elif depth.intrinsics != intrinsics:
                    raise TopsegError(
                        f"the frames are not all of one camera: frame 1 is "
                        f"{camera_text(intrinsics, depth.intrinsics)}, frame {len(frames) + 1} "
                        f"{camera_text(depth.intrinsics, intrinsics)}; calibrate from the frames "
                        "of one camera (a folder of one size, a recording's one channel)"
                    )
                frames.append(depth.depth)
                bar.update(1)
                if len(frames) >= n:
                    break
        finally:
            bar.close()
    if not frames:
        raise TopsegError(f"the source {source} gave no frames")
    return frames, intrinsics, mount, known


def png_optics(intrinsics, sensor: str | None):
    """The optics and sensor of PNG frames, which say none (`core.sensors.sensor_of_frames`,
    as `topseg segment` reads them): `--sensor`'s (refused in one line when its frames are
    another size), else the supported sensor of the frames' size, else (and for `--sensor
    unknown`) the guess they came with, a Kinect v1's scaled to their size, sensor
    'unknown'; and a line saying which."""
    found = None if sensor == "unknown" else sensor_of_frames(intrinsics.shape, sensor)
    if found is not None:
        k = found.intrinsics
        return k, found.name, f"PNG frames say no optics: using the {found.name}'s (fx {k.fx:.1f})"
    return (
        intrinsics,
        "unknown",
        (
            f"PNG frames say no optics: assuming a Kinect v1's scaled to "
            f"{intrinsics.width}x{intrinsics.height} (fx {intrinsics.fx:.1f}); --sensor names "
            "a supported sensor of that size"
        ),
    )


def picture(path: Path, depth, estimate) -> None:
    """Three panels: depth, floor inliers over depth, height above the floor (colour bar)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mount = estimate.mount
    valid = depth > 0
    shown = np.where(valid, depth.astype(np.float32), np.nan)
    floor = floor_mask(depth, mount)
    height = mount.height_map_mm(depth)
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.4), dpi=90)
    im = axes[0].imshow(shown, cmap="gray_r")
    axes[0].set_title("range along each ray (mm), as sent" if mount.radial else "depth (mm)")
    fig.colorbar(im, ax=axes[0], fraction=0.046)
    lo, hi = np.nanpercentile(shown, [1, 99]) if valid.any() else (0, 1)
    grey = np.clip((np.nan_to_num(shown, nan=hi) - lo) / max(hi - lo, 1.0), 0, 1)
    rgb = np.repeat((0.25 + 0.6 * grey)[..., None], 3, axis=2)
    rgb[floor] = 0.45 * rgb[floor] + 0.55 * np.array([0.1, 0.8, 0.2])
    rgb[~valid] = 0
    axes[1].imshow(rgb)
    axes[1].set_title(f"floor inliers ({100 * floor[valid].mean() if valid.any() else 0:.0f} %)")
    im = axes[2].imshow(height, cmap="viridis", vmin=-100, vmax=2000)
    axes[2].set_title("height above the floor (mm)")
    fig.colorbar(im, ax=axes[2], fraction=0.046)
    for ax in axes:
        ax.set_axis_off()
    fig.suptitle(
        f"{mount.sensor}: {mount.height_mm:.0f} mm above the floor, pitch "
        f"{mount.pitch_deg:+.2f} deg, roll {mount.roll_deg:+.2f} deg, residual "
        f"{estimate.residual_mm:.1f} mm (x{mount.noise_scale:.2f} the noise model)"
    )
    fig.tight_layout()
    with atomic_write(path) as f:
        fig.savefig(f, format="png")
    plt.close(fig)


def with_edge_thinning(estimate, given: bool | None, frame_mount):
    """`estimate` whose mount's `edge_thinning` is `given`, else the frames' own mount's,
    else on (the fit measures the floor, not how the camera filters its edges)."""
    if given is None:
        given = frame_mount.edge_thinning if frame_mount is not None else True
    return replace(estimate, mount=replace(estimate.mount, edge_thinning=given))


def picture_path(asked: Path | None, out: Path) -> Path | None:
    """Where the picture goes (`asked`, else OUT with .png); None without matplotlib, which
    is an error when the picture was asked for."""
    if is_installed("matplotlib"):
        return asked or out.with_suffix(".png")
    if asked:
        raise TopsegError(needs_extra("--picture", "matplotlib", "train"))
    return None


def run(args: argparse.Namespace) -> int:
    """Grab frames; estimate the mount, print it, write the mount file and the picture
    (`--out`); fit the background, print it and write the background file (`--background`).
    `calibrate robot` fits the robot's base instead (`calibrate_robot.run`)."""
    check_flags(args)
    if args.target == "robot":
        return calibrate_robot.run(args)
    if args.frames is None:
        args.frames = 60
    if args.frames < 1:
        raise TopsegError(f"--frames must be at least 1, got {args.frames}")
    if args.out is None and args.background is None:
        raise TopsegError(
            "give --out FILE (the camera's mount) and/or --background FILE (the empty cell)"
        )
    if args.out is None and args.picture is not None:
        raise TopsegError("--picture shows the mount: it goes with --out")
    pic = picture_path(args.picture, args.out) if args.out is not None else None
    for path in (args.out, pic, args.background):
        if path is not None:
            check_writable(path)
    if args.sensor and args.sensor != "unknown":
        sensor_name(args.sensor, args.source, None)  # an unknown name fails before the camera
    frames, intrinsics, frame_mount, known = grab(args.source, args.frames)
    sensor = sensor_name(args.sensor, args.source, frame_mount)
    optics = None
    if not known:
        intrinsics, sensor, optics = png_optics(intrinsics, args.sensor)
    mount = frame_mount
    if args.out is not None:
        mount = write_mount(args, frames, intrinsics, sensor, optics, frame_mount, pic)
        optics = None  # said
    if args.background is not None:
        write_background(args, frames, intrinsics, sensor, optics, mount)
    return 0


#: flags of the camera's calibration only, and of `calibrate robot` only
_MOUNT_FLAGS = (("--out", "out"), ("--background", "background"), ("--picture", "picture"),
                ("--sensor", "sensor"))  # fmt: skip
_ROBOT_FLAGS = (("--cell", "cell"), ("--camera", "camera"), ("--write", "write"))


def check_flags(args: argparse.Namespace) -> None:
    """TopsegError for a flag of the other mode (`--out` with `robot`, `--cell` without)."""
    robot = args.target == "robot"
    for flag, dest in _MOUNT_FLAGS if robot else _ROBOT_FLAGS:
        if getattr(args, dest, None) not in (None, False):
            raise TopsegError(
                f"{flag} is not a flag of `topseg calibrate robot`"
                if robot
                else f"{flag} goes with `topseg calibrate robot`"
            )


def write_mount(args, frames, intrinsics, sensor: str, optics, frame_mount, pic):
    """Estimate the mount, print it, write the mount file and the picture; the mount."""
    out: Path = args.out
    estimate = estimate_mount(frames, intrinsics, sensor, CalibrationConfig(seed=args.seed))
    estimate = with_edge_thinning(estimate, args.edge_thinning, frame_mount)
    print(f"topseg calibrate: mount of {args.source} from {len(frames)} frames")
    if optics:
        print(optics)
    print(estimate.summary())
    try:
        write_mount_file(out, estimate)
        if pic:
            picture(pic, frames[-1], estimate)
    except OSError as exc:
        raise TopsegError(f"cannot write {exc.filename or out}: {exc.strerror or exc}") from exc
    print(f"mount file {out}")
    print(f"picture    {pic or needs_extra('not written', 'matplotlib', 'train')}")
    return estimate.mount


def write_background(args, frames, intrinsics, sensor: str, optics, mount) -> None:
    """Fit the empty cell's background over the frames, print it and write the file."""
    out: Path = args.background
    background = fit_background(frames, intrinsics, sensor, mount, source=args.source)
    print(f"topseg calibrate: background of {args.source} from {len(frames)} frames")
    if optics:
        print(optics)
    print(background.summary())
    try:
        save_background(out, background)
    except OSError as exc:
        raise TopsegError(f"cannot write {exc.filename or out}: {exc.strerror or exc}") from exc
    print(f"background file {out}")
