"""`topseg calibrate robot`: the robot's base pose in the cell frame from a few depth frames
of one of the cell's cameras and the robot's joint states at their times.

    topseg calibrate robot --cell /etc/topseg/cell1.toml --source zenoh
    topseg calibrate robot --cell cell1.toml --source replay:cell1.mcap --write

`--source zenoh` takes the camera's depth (`topseg/<cell>/<camera>/depth`) and the robot's
joint states (`topseg/<cell>/robot/<name>/joints`, or ROS 2 `/joint_states` over rmw_zenoh
when the cell file says `joints_source = "ros2"`) live; `--source replay:FILE.mcap` reads
them from a recording. Either way each depth frame is paired with the joint state nearest in
stamp, none more than 20 ms away (`core/safety/robot_calibration.py`), and the base is
fitted from the cell file's (`fit_base_pose`). It prints the fitted pose, the change from
the cell file's and the residual, then the `[robot]` lines to paste, or with `--write`
rewrites them in the cell file (atomically, every other line and comment kept).

Refuses with one line: the cell has no robot or no such camera, no depth or no joint
states came, they are stale (more than 20 ms apart), the frames carry no mount and the cell
file names none, the robot is not in view, or the fit does not converge.
"""

from __future__ import annotations

import argparse
import logging
import math
import re
import time
import tomllib
from pathlib import Path

from topseg.core.atomic import atomic_write
from topseg.core.errors import ConfigError, TopsegError
from topseg.core.formats import joint_states as joint_wire
from topseg.core.formats import wire
from topseg.core.formats.recording import read_messages
from topseg.core.formats.rmw_zenoh import topic_key
from topseg.core.formats.wire import WireError
from topseg.core.printable import printable
from topseg.core.safety.cell import CameraPlacement, CellConfig, cell_from_dict, load_cell
from topseg.core.safety.robot import CellRobot
from topseg.core.safety.robot_calibration import (
    BasePose,
    FramePairer,
    RobotView,
    fit_base_pose,
)
from topseg.services.runtime import zenoh_session
from topseg.services.runtime.inbox import Inbox

log = logging.getLogger("topseg.calibrate")

#: depth frames fitted over by default
DEFAULT_FRAMES = 10
#: ROS 2 joint states: the type on the wire
JOINT_STATE_TYPE = "sensor_msgs/msg/JointState"
#: messages waiting to be read, at most (live)
QUEUE = 64


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The flags of `topseg calibrate robot` (besides --source and --frames)."""
    group = parser.add_argument_group("calibrate robot")
    group.add_argument(
        "--cell", metavar="CELL.toml", default=None, help="the cell file (robot: required)"
    )
    group.add_argument(
        "--camera",
        metavar="NAME",
        default=None,
        help="robot: the cell's camera to fit with (default: its only one)",
    )
    group.add_argument(
        "--write",
        action="store_true",
        help="robot: rewrite the [robot] base lines in the cell file (default: print them)",
    )
    group.add_argument(
        "--timeout",
        type=float,
        default=10.0,
        metavar="S",
        help="robot, --source zenoh: give up after this many seconds (default: %(default)s)",
    )
    group.add_argument(
        "--ros-domain",
        type=int,
        default=0,
        metavar="N",
        help="robot: the ROS 2 domain of /joint_states when the cell file takes them from "
        "ROS 2 (default: %(default)s)",
    )
    zenoh_session.add_arguments(parser)


def run(args: argparse.Namespace) -> int:
    """Pair frames with joint states, fit the base, print it, and write or print the lines."""
    if args.cell is None:
        raise TopsegError("calibrate robot needs --cell CELL.toml")
    frames = DEFAULT_FRAMES if args.frames is None else args.frames
    cell = load_cell(args.cell)
    if cell.robot is None:
        raise TopsegError(f"cell file {args.cell} has no [robot]: nothing to calibrate")
    camera = pick_camera(cell, args.camera)
    robot = CellRobot(cell.robot, Path(args.cell).resolve().parent)
    keys = Keys(cell, camera, args.ros_domain)
    pairer = FramePairer(frames)
    if args.source == "zenoh":
        read_live(args, keys, pairer)
    elif args.source.startswith("replay:") and args.source != "replay:":
        read_replay(Path(args.source.partition(":")[2]), keys, pairer)
    else:
        raise TopsegError(
            f"calibrate robot reads --source zenoh (live) or replay:FILE.mcap, not {args.source!r}"
        )
    pairer.finish()
    if not pairer.done:
        raise TopsegError(
            f"{pairer.shortfall(keys.depth, keys.joints)}; {frames} paired frames needed"
        )
    views = [view(robot, camera, frame, state) for frame, state in pairer.pairs]
    fit = fit_base_pose(robot, camera, views)
    print(
        f"topseg calibrate: base of robot {cell.robot.name} from {fit.frames} frames of "
        f"camera {camera.name} ({keys.dropped} messages dropped)"
    )
    print(fit.summary())
    lines = base_lines(fit.pose)
    if args.write:
        write_cell(Path(args.cell), fit.pose)
        print(f"cell file  {args.cell}: [robot] base written")
    else:
        print("paste into the cell file's [robot] table (or run again with --write):")
        print("\n".join(lines))
    return 0


def pick_camera(cell: CellConfig, name: str | None) -> CameraPlacement:
    """The camera called `name`, else the cell's only one; TopsegError otherwise."""
    names = ", ".join(c.name for c in cell.cameras)
    if name is None:
        if len(cell.cameras) > 1:
            raise TopsegError(f"the cell has cameras {names}: name one with --camera")
        return cell.cameras[0]
    camera = cell.camera(name)
    if camera is None:
        raise TopsegError(f"the cell has no camera {name!r}; it has {names}")
    return camera


class Keys:
    """The camera's depth key and the robot's joints key, and decoding messages on them
    into a pairer (a bad message is dropped and counted)."""

    def __init__(self, cell: CellConfig, camera: CameraPlacement, ros_domain: int) -> None:
        robot = cell.robot
        self.depth = wire.depth_key(cell.cell, camera.name)
        self.ros2 = robot.joints_source == "ros2"
        if self.ros2:
            self.joints = topic_key(ros_domain, robot.ros2_topic, JOINT_STATE_TYPE)
        else:
            self.joints = joint_wire.joints_key(cell.cell, robot.name)
        self.dropped = 0

    def feed(self, pairer: FramePairer, key: str, data: bytes) -> None:
        """Decode a message and give it to `pairer`."""
        try:
            if key == self.depth:
                pairer.add_frame(wire.decode_depth(data))
            elif key == self.joints:
                decode = (
                    joint_wire.decode_ros2_joint_state
                    if self.ros2
                    else joint_wire.decode_joint_state
                )
                pairer.add_state(decode(data))
        except WireError as exc:
            self.dropped += 1
            log.warning("dropped a message on %s: %s", printable(key), printable(exc))


def read_live(args: argparse.Namespace, keys: Keys, pairer: FramePairer) -> None:
    """Feed live messages until the pairer is done or `--timeout` passed."""
    if not (math.isfinite(args.timeout) and args.timeout > 0):
        raise TopsegError(f"--timeout must be a number of seconds > 0, got {args.timeout}")
    inbox = Inbox(QUEUE)
    with zenoh_session.open_config(zenoh_session.config_from_args(args)) as session:
        subs = [session.declare_subscriber(k, inbox.on_sample) for k in (keys.depth, keys.joints)]
        log.info("reading %s and %s", keys.depth, keys.joints)
        deadline = time.monotonic() + args.timeout
        while not pairer.done and time.monotonic() < deadline:
            item = inbox.get(max(0.0, deadline - time.monotonic()))
            if item is not None:
                keys.feed(pairer, item[0], item[1])
        for sub in subs:
            sub.undeclare()


def read_replay(path: Path, keys: Keys, pairer: FramePairer) -> None:
    """Feed a recording's depth and joint messages, in file order, until the pairer is done."""
    if not path.is_file():
        raise TopsegError(f"no such recording {path}")
    for message in read_messages(path, keys=(keys.depth, keys.joints)):
        keys.feed(pairer, message.key, message.data)
        if pairer.done:
            break


def view(robot: CellRobot, camera: CameraPlacement, frame, state) -> RobotView:
    """A paired frame and joint state as a RobotView; TopsegError for a frame without a
    mount (when the cell file names none) or a joint state that does not fit the robot."""
    mount = frame.mount or camera.mount
    if mount is None:
        raise TopsegError(
            f"camera {camera.name}'s frames carry no mount and the cell file gives it no "
            "mount_file: calibrate the camera first (topseg calibrate --out)"
        )
    try:
        joints = robot.check_joints(state.as_dict())
    except ValueError as exc:
        raise TopsegError(str(exc)) from None
    return RobotView(frame.depth, mount, joints)


def base_lines(pose: BasePose) -> list[str]:
    """The `[robot]` lines of a base pose, as TOML."""
    x, y, z = pose.xyz_m
    return [f"base_xyz_m = [{x:.4f}, {y:.4f}, {z:.4f}]", f"base_yaw_deg = {pose.yaw_deg:.3f}"]


#: a table header line, `[name]` or `[[name]]`, with an optional comment
_HEADER = re.compile(r"^\s*\[\[?\s*([A-Za-z0-9_.\"' -]+?)\s*\]\]?\s*(#.*)?$")


def with_base(text: str, pose: BasePose) -> str:
    """The cell file's text with its `[robot]` table's base lines set to `pose`: existing
    one-line `base_xyz_m` / `base_yaw_deg` values replaced (their comments kept), missing
    ones added under the header; every other line as it was. TopsegError when the file has
    no `[robot]` table to edit (an inline one) or a base value spans lines."""
    lines = text.splitlines(keepends=True)
    start = next((i for i, ln in enumerate(lines) if _is_header(ln, "robot")), None)
    if start is None:
        raise TopsegError("the cell file has no [robot] table line to edit: set the base by hand")
    end = next((i for i in range(start + 1, len(lines)) if _HEADER.match(lines[i])), len(lines))
    newline = "\r\n" if lines[start].endswith("\r\n") else "\n"
    missing = []
    for key, value in zip(("base_xyz_m", "base_yaw_deg"), base_values(pose), strict=True):
        pattern = re.compile(rf"^(\s*{key}\s*=\s*)(\[[^\]]*\]|[^#\s\[]+)(.*)$", re.S)
        at = [i for i in range(start + 1, end) if re.match(rf"\s*{key}\s*=", lines[i])]
        if not at:
            missing.append(f"{key} = {value}{newline}")
            continue
        m = pattern.match(lines[at[0]])
        if m is None:
            raise TopsegError(f"the cell file's {key} spans lines: set the base by hand")
        lines[at[0]] = f"{m[1]}{value}{m[3]}"
    lines[start + 1 : start + 1] = missing
    return "".join(lines)


def base_values(pose: BasePose) -> tuple[str, str]:
    """The TOML values of `base_xyz_m` and `base_yaw_deg`."""
    return tuple(line.split(" = ", 1)[1] for line in base_lines(pose))


def _is_header(line: str, name: str) -> bool:
    """Whether `line` is the header `[name]` (not an array of tables)."""
    m = _HEADER.match(line)
    return bool(m) and not line.lstrip().startswith("[[") and m[1].strip("\"'") == name


def write_cell(path: Path, pose: BasePose) -> None:
    """Set the base in the cell file at `path`, atomically; the new text is read back as a
    cell file first (its robot at `pose`), so a bad edit is never written."""
    text = path.read_text(encoding="utf-8")
    new = with_base(text, pose)
    try:
        cell = cell_from_dict(tomllib.loads(new), str(path), base_dir=path.resolve().parent)
    except (tomllib.TOMLDecodeError, ConfigError) as exc:
        raise TopsegError(
            f"the edited cell file would not read back ({exc}): not written"
        ) from None
    got = BasePose(tuple(cell.robot.base_xyz_m), cell.robot.base_yaw_deg)
    if max(abs(got.as_vector() - pose.as_vector())) > 1e-3:
        raise TopsegError("the edited cell file reads back another base: not written")
    try:
        with atomic_write(path) as f:
            f.write(new.encode("utf-8"))
    except OSError as exc:
        raise TopsegError(f"cannot write {path}: {exc.strerror or exc}") from exc
