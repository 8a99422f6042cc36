"""`topseg datagen cell-sequence --out FILE.mcap`: a rendered robot-cell sequence with its
truth, as a msgpack recording the safety service can be replayed against
(`topseg driver --source replay:FILE.mcap`), the cell file `FILE.toml` beside it, and the
static cell's background `FILE.background.npz` (the table and its parts without people or the
robot, as `topseg calibrate --background` records it) for the camera's worker.

The recording holds, per frame at the sequence's rate: depth (with the camera's mount) on
`topseg/<cell>/<camera>/depth`, exact labels on `.../truth`, the robot's joint state on
`topseg/<cell>/robot/<name>/joints` and the truth separation of each person on stage on
`topseg/<cell>/safety/separation` (`core/formats/cell_truth.py`); with two cameras, each
camera's depth and labels on its own keys, and the second camera's background in
`FILE.<camera>.background.npz`. The cell file places the camera at (0, 0, yaw 0)
(two cameras where `CellSequenceConfig.camera_positions` hangs them) and the robot where it
was rendered, with a protective zone around what the robot's links sweep and a warning zone
a metre beyond.
"""

from __future__ import annotations

import argparse
import logging
import math
import time
from pathlib import Path

import numpy as np

from topseg.core.atomic import atomic_write
from topseg.core.background import save_background
from topseg.core.errors import TopsegError
from topseg.core.formats import cell_truth, wire
from topseg.core.formats.recording import RecordingWriter
from topseg.core.synth.sequences import CellSequence, CellSequenceConfig
from topseg.core.synth.static_cell import sequence_background
from topseg.services.batch.cell_pipeline import BACKGROUND_SUFFIX
from topseg.services.cli.options import finite, int_range, non_negative_int

log = logging.getLogger("topseg.datagen")

HELP = "render a robot-cell sequence with its truth (joint states, separations) to an MCAP"
#: the recording's first frame is stamped at this time (ns since the epoch): 2025-01-01
START_NS = 1_735_689_600_000_000_000
#: the warning zone reaches this far (m) beyond the protective one
WARNING_MARGIN_M = 1.0
#: the protective zone reaches this far (m) beyond what the robot's links sweep
PROTECTIVE_MARGIN_M = 0.2
ZONE_SIDES = 16


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """`topseg datagen cell-sequence`'s options."""
    parser.add_argument("--out", required=True, help="the recording to write (FILE.mcap)")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="sequence seed (0)")
    parser.add_argument(
        "--duration", type=finite(0.1, 3600), default=20.0, help="length in seconds (20)"
    )
    parser.add_argument("--fps", type=finite(0.5, 120), default=30.0, help="frame rate (30)")
    parser.add_argument("--robot", default="panda", help="catalogue robot (panda)")
    parser.add_argument("--people", type=int_range(1, 2), default=2, help="1 or 2 people (2)")
    parser.add_argument("--sensor", default="kinect_v1", help="camera model (kinect_v1)")
    parser.add_argument(
        "--height", type=finite(2.0, 6.0), default=3.0, help="camera height in metres (3.0)"
    )
    parser.add_argument(
        "--size", default="320x240", help="image size WxH, or native for the sensor's (320x240)"
    )
    parser.add_argument("--noise", default="sensor", help="sensor (its own noise) | none | ...")
    parser.add_argument("--cell", default=wire.DEFAULT_CELL, help="cell name (default)")
    parser.add_argument("--camera", default=wire.DEFAULT_CAMERA, help="camera name (cam0)")
    parser.add_argument(
        "--cameras", type=int_range(1, 2), default=1,
        help="1, or 2 cameras side by side whose views abut at head height (1); the second "
        "is named CAMERA-2",
    )  # fmt: skip


def parse_size(text: str) -> tuple[int, int] | None:
    """'WxH' -> (W, H); 'native' -> None; TopsegError otherwise."""
    if text == "native":
        return None
    w, sep, h = text.lower().partition("x")
    if (
        not sep
        or not w.isdigit()
        or not h.isdigit()
        or not (16 <= int(w) <= 4096 and 16 <= int(h) <= 4096)
    ):
        raise TopsegError(f"--size must be WxH (16..4096 each) or native, got {text!r}")
    return int(w), int(h)


def cell_toml(seq: CellSequence) -> str:
    """The cell file of a sequence: its cameras where they were rendered (yaw 0), its robot
    as rendered, and zones around the robot (the safety service's `core/safety/cell.py`
    format)."""
    c, r = seq.config, seq.robot
    reach = seq.reach_radius()
    lines = [f'cell = "{c.cell}"']
    for name, (x, y) in zip(c.camera_names(), seq.positions, strict=True):
        lines += ["", "[[camera]]", f'name = "{name}"', f"x_m = {x:.6f}", f"y_m = {y:.6f}",
                  "yaw_deg = 0.0"]  # fmt: skip
    lines += [
        "",
        "[robot]",
        f'name = "{r.name}"',
        f'urdf = "{r.name}"',
        f"base_xyz_m = [{r.x:.6f}, {r.y:.6f}, {r.base_z:.6f}]",
        f"base_yaw_deg = {math.degrees(r.yaw):.6f}",
        'joints_source = "zenoh"',
        f'pedestal = "{"cylinder" if r.pedestal[1] else "box"}"',
        f"pedestal_size_m = {r.pedestal[0]:.4f}",
        "# the fastest any point of its links moves in the recorded task",
        f"max_speed_mps = {seq.max_link_speed():.3f}",
    ]
    for name, kind, radius, z_max in (
        ("robot", "protective", reach + PROTECTIVE_MARGIN_M, 2.2),
        ("approach", "warning", reach + PROTECTIVE_MARGIN_M + WARNING_MARGIN_M, 2.2),
    ):
        angles = np.arange(ZONE_SIDES) * 2 * np.pi / ZONE_SIDES
        poly = ", ".join(
            f"[{r.x + radius * np.cos(a):.4f}, {r.y + radius * np.sin(a):.4f}]" for a in angles
        )
        lines += [
            "",
            "[[zone]]",
            f'name = "{name}"',
            f'kind = "{kind}"',
            f"polygon_m = [{poly}]",
            "z_min_m = 0.0",
            f"z_max_m = {z_max}",
        ]
    return "\n".join(lines) + "\n"


def write_recording(seq: CellSequence, out: Path) -> dict:
    """Render `seq` into the msgpack recording `out` (and its cell file beside it); what was
    written: frames, seconds, the closest and farthest truth separations."""
    c = seq.config
    names = c.camera_names()
    keys = {
        "joints": cell_truth.joints_key(c.cell, seq.robot.name),
        "safety": cell_truth.safety_truth_key(c.cell),
    }
    t0 = time.perf_counter()
    closest, farthest = math.inf, 0.0
    metadata = {"generator": "cell-sequence", "seed": str(seq.seed), "robot": seq.robot.name}
    with RecordingWriter(out, metadata=metadata) as writer:
        for f in seq.frames():
            stamp = START_NS + round(f.time_s * 1e9)
            for name, (depth_mm, labels) in zip(names, f.views(), strict=True):
                depth = wire.DepthFrame(
                    depth_mm, seq.mount.intrinsics, f.index, stamp, name, seq.mount
                )
                # depth first: a replay publishes what follows a depth frame with it
                writer.write(wire.depth_key(c.cell, name), wire.encode_depth(depth), stamp)
                truth = wire.LabelFrame(labels, f.index, stamp, name)
                writer.write(wire.truth_key(c.cell, name), wire.encode_labels(truth), stamp)
            writer.write(
                keys["joints"],
                cell_truth.encode_joint_state(stamp, f.joint_names, f.joint_positions),
                stamp,
            )
            persons = [p.to_dict() for p in f.persons]
            writer.write(
                keys["safety"], cell_truth.encode_safety_truth(stamp, f.index, persons), stamp
            )
            for p in f.persons:
                closest, farthest = min(closest, p.distance_m), max(farthest, p.distance_m)
    with atomic_write(out.with_suffix(".toml")) as f:
        f.write(cell_toml(seq).encode())
    for k, name in enumerate(names):
        path = out.with_suffix(BACKGROUND_SUFFIX if k == 0 else f".{name}{BACKGROUND_SUFFIX}")
        save_background(path, sequence_background(seq, k))
    return {
        "frames": c.frame_count,
        "seconds": time.perf_counter() - t0,
        "closest_m": closest,
        "farthest_m": farthest,
    }


def run(args: argparse.Namespace) -> int:
    """`topseg datagen cell-sequence`: render and write the recording and its cell file."""
    out = Path(args.out)
    if out.suffix.lower() != ".mcap":
        raise TopsegError(f"--out must name an .mcap file, got {out}")
    config = CellSequenceConfig(
        duration_s=args.duration, fps=args.fps, sensor=args.sensor, height_m=args.height,
        size=parse_size(args.size), robot=args.robot, people=args.people, noise=args.noise,
        cell=args.cell, camera=args.camera, cameras=args.cameras,
    )  # fmt: skip
    for name in config.camera_names():
        wire.depth_key(config.cell, name)  # names a key can hold, or one line
    seq = CellSequence(config, args.seed)
    done = write_recording(seq, out)
    print(
        f"wrote {done['frames']} frames to {out} ({out.stat().st_size / 1e6:.1f} MB) and "
        f"{out.with_suffix('.toml')} and {out.with_suffix(BACKGROUND_SUFFIX)} in "
        f"{done['seconds']:.1f} s; people came within "
        f"{done['closest_m']:.2f} m of the robot, and went {done['farthest_m']:.2f} m away"
    )
    return 0
