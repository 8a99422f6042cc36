"""The messages a cell recording carries beside depth and labels: the robot's joint states
and the truth separation of each person from the robot, and how a replay restamps them.

Joint states, on `topseg/<cell>/robot/<name>/joints`: a msgpack map `v` (1), `stamp_ns`,
`name` (list of joint names), `position` (list of floats, radians or metres).

Safety truth, on `topseg/<cell>/safety/separation`: a msgpack map `v` (1), `stamp_ns`, `seq`
(the depth frame's), `persons`: a list of maps per person on stage: `id`, `distance_m` (the
least distance between the person's body and the robot's links, 0 when they touch),
`part` (label name of the person's nearest part), `link` (the robot's nearest link),
`point_m` and `link_point_m` (the nearest pair, cell frame, [x, y, z]) and `in_view`
(whether any of the person's body is in the camera's image).
"""

from __future__ import annotations

from typing import Any

import msgpack

from topseg.core.formats import joint_states, small_message
from topseg.core.formats.joint_states import JointState
from topseg.core.formats.wire import WireError

#: the version both maps are written with
TRUTH_VERSION = 1
#: the largest companion message restamped (a joint state of many joints, a few people)
MAX_COMPANION_BYTES = 1 << 20
_MAX_STAMP = 2**63 - 1


joints_key = joint_states.joints_key


def safety_truth_key(cell: str) -> str:
    """`topseg/<cell>/safety/separation`."""
    return f"topseg/{cell}/safety/separation"


def encode_joint_state(stamp_ns: int, names, positions) -> bytes:
    """A joint-state message (`joint_states.encode_joint_state`) from its parts."""
    state = JointState(
        int(stamp_ns), tuple(str(n) for n in names), tuple(float(p) for p in positions)
    )
    return joint_states.encode_joint_state(state)


def encode_safety_truth(stamp_ns: int, seq: int, persons: list[dict]) -> bytes:
    """A safety truth message (see the module doc); `persons` as `PersonTruth.to_dict()`."""
    return msgpack.packb(
        {"v": TRUTH_VERSION, "stamp_ns": int(stamp_ns), "seq": int(seq), "persons": persons},
        use_bin_type=True,
    )


def companion_kind(key: str) -> str | None:
    """ "joints" or "safety_truth" for the keys a replay passes on with the depth frames,
    None for any other key."""
    parts = key.split("/")
    if len(parts) == 5 and parts[0] == "topseg" and parts[2] == "robot" and parts[4] == "joints":
        return "joints"
    if len(parts) == 4 and parts[0] == "topseg" and parts[2:] == ["safety", "separation"]:
        return "safety_truth"
    return None


def in_cell(key: str, cell: str) -> str:
    """A companion key moved to `cell` (its second part replaced)."""
    parts = key.split("/")
    parts[1] = cell
    return "/".join(parts)


def _unpack_map(data: bytes) -> dict[str, Any]:
    msg = small_message.unpack_map(data, "companion", MAX_COMPANION_BYTES)
    stamp = msg.get("stamp_ns")
    if isinstance(stamp, bool) or not isinstance(stamp, int) or not 0 <= stamp <= _MAX_STAMP:
        raise WireError("a companion message needs an integer stamp_ns >= 0")
    return msg


def stamp_of(data: bytes) -> int:
    """The `stamp_ns` of a joint-state or safety truth message; WireError when it has none."""
    return int(_unpack_map(data)["stamp_ns"])


def restamped(data: bytes, stamp_ns: int, seq: int | None = None) -> bytes:
    """The message with `stamp_ns` replaced (clamped to the valid range) and, when it has
    one and `seq` is given, its `seq`; WireError when it is no such message."""
    msg = _unpack_map(data)
    msg["stamp_ns"] = min(max(int(stamp_ns), 0), _MAX_STAMP)
    if seq is not None and "seq" in msg:
        msg["seq"] = int(seq)
    return msgpack.packb(msg, use_bin_type=True)


def decode_safety_truth(data: bytes) -> dict:
    """A safety truth message as a dict (`seq`, `stamp_ns`, `persons`); WireError when it is
    not one (each person needs `distance_m`, `part`, `link`)."""
    msg = _unpack_map(data)
    seq, persons = msg.get("seq"), msg.get("persons")
    if isinstance(seq, bool) or not isinstance(seq, int) or seq < 0:
        raise WireError("a safety truth message needs an integer seq >= 0")
    if not isinstance(persons, list):
        raise WireError("a safety truth message needs a list of persons")
    for person in persons:
        if not isinstance(person, dict) or not {"distance_m", "part", "link"} <= set(person):
            raise WireError("each person of a safety truth needs distance_m, part and link")
    return msg
