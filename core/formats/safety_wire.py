"""The safety state on the wire: `topseg/<cell>/safety`, one msgpack map per decision.

    v               schema version (SAFETY_VERSION)
    seq             the decision's number, counting from 0 when the service starts
    stamp_ns        when it was decided (ns since the Unix epoch)
    state           "clear" | "warning" | "stop"
    speed_scale     0..1: the share of the robot's full speed it may move at
    min_distance_m  the nearest person's distance from the robot (m), nil when no person or
                    no robot is seen
    part, link      the body part and the robot link of the nearest pair ("" when none)
    reaction_ms     depth stamp of the frame decided on to the decision (ms), nil when the
                    decision rests on no frame (none yet, or the frames went stale)
    reasons         short sentences, why the state is not `clear` (at most MAX_REASONS)
    zones           optional: zone name -> its state ("clear" | "warning" | "stop")
    nearest_m       optional: the nearest pair [[x, y, z] of the person, [x, y, z] on the
                    robot], cell frame, metres
    frame           optional: {camera, seq} of the labelled frame decided on

Decoding trusts nothing: every field's type and range is checked, one `WireError` otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import msgpack

from topseg.core.formats import small_message as sm
from topseg.core.formats.wire import WireError, alive_key, camera_prefix

SAFETY_VERSION = 1
#: The key chunk after the cell's name, and the role of the service's token.
SAFETY = "safety"
STATES = ("clear", "warning", "stop")
MAX_REASONS = 16
MAX_REASON_CHARS = 200
MAX_ZONES = 64
MAX_NAME = 64
_MAX_INT = 2**63 - 1
_REQUIRED = frozenset(
    ("v", "seq", "stamp_ns", "state", "speed_scale", "min_distance_m", "part", "link",
     "reaction_ms", "reasons")
)  # fmt: skip
_OPTIONAL = frozenset(("zones", "nearest_m", "frame"))


def safety_key(cell: str) -> str:
    """`topseg/<cell>/safety`, where a cell's safety service publishes its state."""
    return camera_prefix(cell, SAFETY)  # the cell's name checked as in every topseg key


def safety_alive_key(cell: str, instance: str) -> str:
    """The liveliness token of a cell's safety service: `topseg/<cell>/safety/alive/safety/
    <instance>`, a token of the shape every service holds (`wire.alive_key`)."""
    return alive_key(cell, SAFETY, SAFETY, instance)


@dataclass(frozen=True)
class SafetyState:
    """One decision of a cell's safety service (the fields of the module's docstring)."""

    seq: int
    stamp_ns: int
    state: str
    speed_scale: float
    min_distance_m: float | None = None
    part: str = ""
    link: str = ""
    reaction_ms: float | None = None
    reasons: tuple[str, ...] = ()
    zones: dict[str, str] = field(default_factory=dict)
    nearest_m: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    frame: tuple[str, int] | None = None

    def __post_init__(self) -> None:
        sm.int_in("seq", self.seq, 0, _MAX_INT)
        sm.int_in("stamp_ns", self.stamp_ns, 0, _MAX_INT)
        if self.state not in STATES:
            raise WireError(f"state {sm.short(self.state)} is not one of {', '.join(STATES)}")
        sm.finite_float("speed_scale", self.speed_scale, 0.0, 1.0)
        if self.state == "stop" and self.speed_scale != 0.0:
            raise WireError(f"state stop with speed_scale {self.speed_scale:g}: stop is 0")
        if self.min_distance_m is not None:
            sm.finite_float("min_distance_m", self.min_distance_m, 0.0)
        if self.reaction_ms is not None:
            sm.finite_float("reaction_ms", self.reaction_ms, 0.0)
        sm.text("part", self.part, MAX_NAME)
        sm.text("link", self.link, 256)
        if not isinstance(self.reasons, tuple) or len(self.reasons) > MAX_REASONS:
            raise WireError(f"reasons must be a tuple of at most {MAX_REASONS} strings")
        for reason in self.reasons:
            sm.text("a reason", reason, MAX_REASON_CHARS)
        if not isinstance(self.zones, dict) or len(self.zones) > MAX_ZONES:
            raise WireError(f"zones must be a map of at most {MAX_ZONES} zones")
        for name, state in self.zones.items():
            sm.text("a zone's name", name, MAX_NAME)
            if state not in STATES:
                raise WireError(f"zone {name!r}: state {sm.short(state)} is not one of {STATES}")
        if self.nearest_m is not None:
            pair = self.nearest_m
            if len(pair) != 2 or any(len(p) != 3 for p in pair):
                raise WireError("nearest_m must be two points of three coordinates")
            for point in pair:
                for value in point:
                    sm.finite_float("a nearest_m coordinate", value)
        if self.frame is not None:
            camera, seq = self.frame
            sm.text("frame.camera", camera, MAX_NAME)
            sm.int_in("frame.seq", seq, 0, _MAX_INT)


def cut_reason(reason: str) -> str:
    """A reason cut to MAX_REASON_CHARS characters (the service's reasons never fail the wire)."""
    return reason if len(reason) <= MAX_REASON_CHARS else reason[: MAX_REASON_CHARS - 3] + "..."


def encode_safety(state: SafetyState) -> bytes:
    """One decision as one msgpack map."""
    msg: dict[str, Any] = {
        "v": SAFETY_VERSION,
        "seq": state.seq,
        "stamp_ns": state.stamp_ns,
        "state": state.state,
        "speed_scale": float(state.speed_scale),
        "min_distance_m": state.min_distance_m,
        "part": state.part,
        "link": state.link,
        "reaction_ms": state.reaction_ms,
        "reasons": list(state.reasons),
    }
    if state.zones:
        msg["zones"] = dict(state.zones)
    if state.nearest_m is not None:
        msg["nearest_m"] = [[float(v) for v in p] for p in state.nearest_m]
    if state.frame is not None:
        msg["frame"] = {"camera": state.frame[0], "seq": int(state.frame[1])}
    return msgpack.packb(msg, use_bin_type=True)


def _optional_float(name: str, value: Any) -> float | None:
    return None if value is None else sm.finite_float(name, value, 0.0)


def decode_safety(data: bytes) -> SafetyState:
    """The decision in a `topseg/<cell>/safety` message; WireError for anything else."""
    msg = sm.unpack_map(data, "safety")
    sm.check_keys(msg, "safety", _REQUIRED, _OPTIONAL)
    version = msg["v"]
    if type(version) is not int or version != SAFETY_VERSION:
        raise WireError(
            f"safety schema version {sm.short(version)} is not {SAFETY_VERSION}"
            + (": upgrade topseg on this host" if type(version) is int and version > 1 else "")
        )
    reasons = msg["reasons"]
    if not isinstance(reasons, list):
        raise WireError(f"reasons must be a list, got {type(reasons).__name__}")
    zones = msg.get("zones", {})
    if not isinstance(zones, dict):
        raise WireError(f"zones must be a map, got {type(zones).__name__}")
    nearest = msg.get("nearest_m")
    if nearest is not None:
        if not isinstance(nearest, list) or not all(isinstance(p, list) for p in nearest):
            raise WireError("nearest_m must be a list of two points")
        nearest = tuple(tuple(p) for p in nearest)
    frame = msg.get("frame")
    if frame is not None:
        if not isinstance(frame, dict) or set(frame) != {"camera", "seq"}:
            raise WireError("frame must be a map of camera and seq")
        frame = (frame["camera"], frame["seq"])
    return SafetyState(
        seq=msg["seq"],
        stamp_ns=msg["stamp_ns"],
        state=msg["state"],
        speed_scale=sm.finite_float("speed_scale", msg["speed_scale"], 0.0, 1.0),
        min_distance_m=_optional_float("min_distance_m", msg["min_distance_m"]),
        part=msg["part"],
        link=msg["link"],
        reaction_ms=_optional_float("reaction_ms", msg["reaction_ms"]),
        reasons=tuple(reasons),
        zones=zones,
        nearest_m=nearest,
        frame=frame,
    )


__all__ = [
    "MAX_REASONS", "SAFETY", "SAFETY_VERSION", "STATES", "SafetyState", "cut_reason",
    "decode_safety", "encode_safety", "safety_alive_key", "safety_key",
]  # fmt: skip
