"""A robot's joint states as the safety service reads them (DESIGN section 4).

Two carriers, one `JointState`:

- topseg's own key `topseg/<cell>/robot/<name>/joints` (`joints_key`), one msgpack map::

      v         schema version (JOINT_STATE_VERSION)
      stamp_ns  when the positions were measured, ns since the Unix epoch, 0 <= stamp_ns < 2**63
      name      list of joint names (URDF joint names), 1..MAX_JOINTS, each 1..MAX_JOINT_NAME
                characters, no name twice
      position  list of numbers (radians or metres), as long as `name`, all finite

- ROS 2 `sensor_msgs/msg/JointState` as CDR, the bytes rmw_zenoh carries for `/joint_states`
  (`decode_ros2_joint_state`): the stamp is `header.stamp`; velocity and effort are ignored.
  Serialisation comes from rosbags' typestore (`ros2_messages`), which the `cell` extra
  installs; it is imported only when a ROS 2 message is decoded or encoded.

Decoding trusts nothing from the sender: any failure is one `WireError` naming what is wrong
(the service drops and counts it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

from topseg.core.errors import TopsegError
from topseg.core.extras import import_failure
from topseg.core.formats import small_message as sm
from topseg.core.formats.wire import ROOT, WireError, _check_name, _short

#: the version every joint-state message is written with, and the only one read
JOINT_STATE_VERSION = 1
#: the most joints one message may carry
MAX_JOINTS = 64
#: the longest joint name
MAX_JOINT_NAME = 64
#: no valid message is larger (64 names of 64 characters, 64 doubles, the header)
MAX_JOINT_STATE_BYTES = 16384
#: the ROS 2 type of `/joint_states`
ROS2_JOINT_STATE = "sensor_msgs/msg/JointState"
_MAX_STAMP = 2**63 - 1
_FIELDS = frozenset(("v", "stamp_ns", "name", "position"))


@dataclass(frozen=True)
class JointState:
    """The robot's joint positions at `stamp_ns`: `name[i]` is at `position[i]` (rad or m)."""

    stamp_ns: int
    name: tuple[str, ...]
    position: tuple[float, ...]

    def as_dict(self) -> dict[str, float]:
        """{joint name: position}, what `CellRobot` poses the robot with."""
        return dict(zip(self.name, self.position, strict=True))


def joints_key(cell: str, robot: str) -> str:
    """`topseg/<cell>/robot/<robot>/joints`, where a robot's joint states are published."""
    return f"{ROOT}/{_check_name('cell', cell)}/robot/{_check_name('robot', robot)}/joints"


def check_joint_state(stamp_ns: Any, name: Any, position: Any) -> JointState:
    """A JointState from loosely typed fields, every one checked; WireError for anything
    wrong (a stamp outside 0..2**63-1, names not strings or too long or repeated, positions
    not finite numbers, the two lists of different lengths, none or more than MAX_JOINTS)."""
    if type(stamp_ns) is not int or not 0 <= stamp_ns <= _MAX_STAMP:
        raise WireError(f"joint state stamp_ns {_short(stamp_ns)} is not an integer 0..2**63-1")
    names = _names(name)
    positions = _positions(position)
    if len(positions) != len(names):
        raise WireError(
            f"joint state has {len(names)} names but {len(positions)} positions: "
            "one position per name"
        )
    return JointState(stamp_ns, names, positions)


def _names(value: Any) -> tuple[str, ...]:
    """The joint names, checked: 1..MAX_JOINTS strings of 1..MAX_JOINT_NAME, each once."""
    if not isinstance(value, list | tuple):
        raise WireError(f"joint state name must be a list, got {type(value).__name__}")
    if not 1 <= len(value) <= MAX_JOINTS:
        raise WireError(f"joint state has {len(value)} joints: 1..{MAX_JOINTS}")
    for item in value:
        if not isinstance(item, str) or not 1 <= len(item) <= MAX_JOINT_NAME:
            raise WireError(
                f"joint name {_short(item)} must be a string of 1..{MAX_JOINT_NAME} characters"
            )
    if len(set(value)) != len(value):
        twice = next(n for n in value if list(value).count(n) > 1)
        raise WireError(f"joint state names joint {twice!r} twice")
    return tuple(value)


def _positions(value: Any) -> tuple[float, ...]:
    """The joint positions, checked: finite numbers (at most MAX_JOINTS of them)."""
    if not isinstance(value, list | tuple) or len(value) > MAX_JOINTS:
        raise WireError(f"joint state position must be a list of at most {MAX_JOINTS} numbers")
    out = []
    for i, item in enumerate(value):
        if type(item) not in (int, float) or not math.isfinite(item):
            raise WireError(f"joint state position[{i}] = {_short(item)} is not a finite number")
        out.append(float(item))
    return tuple(out)


def encode_joint_state(js: JointState) -> bytes:
    """The msgpack message of a joint state (checked first: ValueError if it is not valid)."""
    try:
        js = check_joint_state(js.stamp_ns, list(js.name), list(js.position))
    except WireError as exc:
        raise ValueError(str(exc)) from None
    message = {
        "v": JOINT_STATE_VERSION,
        "stamp_ns": js.stamp_ns,
        "name": list(js.name),
        "position": list(js.position),
    }
    return msgpack.packb(message, use_bin_type=True)


def decode_joint_state(data: bytes) -> JointState:
    """The JointState of a msgpack message; WireError naming what is wrong with a bad one."""
    msg = sm.unpack_map(
        data, "joint state", MAX_JOINT_STATE_BYTES, max_items=MAX_JOINTS,
        max_str_len=MAX_JOINT_NAME * 4, max_map_len=8,
    )  # fmt: skip
    if "v" in msg and msg["v"] != JOINT_STATE_VERSION:
        raise WireError(
            f"joint state schema version {_short(msg['v'])} is not {JOINT_STATE_VERSION}"
        )
    sm.check_keys(msg, "joint state", _FIELDS, frozenset())
    return check_joint_state(msg["stamp_ns"], msg["name"], msg["position"])


# ---------------------------------------------------------------------------- ROS 2


def _ros2():
    """core.formats.ros2_messages (rosbags), or a TopsegError naming the extra to install."""
    try:
        from topseg.core.formats import ros2_messages
    except ImportError as exc:
        raise TopsegError(import_failure("ROS 2 joint states", "rosbags", "cell", exc)) from None
    return ros2_messages


def decode_ros2_joint_state(cdr: bytes) -> JointState:
    """The JointState of a `sensor_msgs/msg/JointState` CDR payload (as rmw_zenoh carries
    it): names and positions checked as `decode_joint_state` does, the stamp from
    header.stamp; WireError for a payload that is not one."""
    if not isinstance(cdr, bytes | bytearray | memoryview):
        raise WireError(f"a ROS 2 joint state must be bytes, got {type(cdr).__name__}")
    if len(cdr) > MAX_JOINT_STATE_BYTES:
        raise WireError(
            f"ROS 2 joint state of {len(cdr)} bytes exceeds the {MAX_JOINT_STATE_BYTES}-byte limit"
        )
    ros2 = _ros2()
    try:
        msg = ros2.typestore().deserialize_cdr(bytes(cdr), ROS2_JOINT_STATE)
    except Exception as exc:  # rosbags raises struct, index, value and unicode errors
        raise WireError(
            f"not a ROS 2 {ROS2_JOINT_STATE} ({type(exc).__name__}: {_short(str(exc))})"
        ) from None
    stamp = msg.header.stamp
    if not 0 <= stamp.sec < 2**31 or not 0 <= stamp.nanosec < 1_000_000_000:
        raise WireError(
            f"ROS 2 joint state stamp {stamp.sec}.{stamp.nanosec:09d} is not a time since 1970"
        )
    stamp_ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
    return check_joint_state(stamp_ns, list(msg.name), [float(p) for p in msg.position])


def encode_ros2_joint_state(js: JointState, frame_id: str = "") -> bytes:
    """A `sensor_msgs/msg/JointState` CDR payload of a joint state (no velocity, no effort):
    what a ROS 2 robot driver publishes, for tests and replays."""
    ros2 = _ros2()
    types = ros2.typestore().types
    sec, nanosec = divmod(int(js.stamp_ns), 1_000_000_000)
    header = types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id
    )
    message = types[ROS2_JOINT_STATE](
        header=header,
        name=list(js.name),
        position=np.asarray(js.position, np.float64),
        velocity=np.zeros(0),
        effort=np.zeros(0),
    )
    return bytes(ros2.typestore().serialize_cdr(message, ROS2_JOINT_STATE))
