"""The cell's state from what the safety service measured: `clear`, `warning` or `stop`, a
speed scale 0..1 for the robot, and the reasons in words.

Rules, strictest first:

- any fault (stale frames, a blinded camera, a moved mount, stale joint states...) stops
  the cell with the faults as its reasons;
- a person in a protective zone, or a protective zone unseen beyond
  `max_unseen_fraction` (or with no unseen figure at all), stops it; a person in a warning
  zone gives at least `warning`;
- with a robot and a person, the speed scale is `allowed_robot_speed` at the nearest
  distance over the robot's full speed: 0 stops, below 1 warns, and a person within S_p at
  full speed plus the warning margin warns;
- in a cell that allows contact (power and force limiting), with the person within S_p at
  full speed: the nearest part's permissible transient contact speed over full speed caps
  the scale, and a part that allows no contact (the head) stops the cell.

Anything not finite (a NaN distance, reaction time or unseen fraction) stops the cell: the
decision fails towards `stop`, never towards `clear`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from topseg.core import labels
from topseg.core.safety.carry import UNIDENTIFIED
from topseg.core.safety.cell import CellConfig
from topseg.core.safety.iso15066 import (
    allowed_robot_speed,
    permissible_contact_speed,
    protective_distance,
)

CLEAR = "clear"
WARNING = "warning"
STOP = "stop"
#: the states, least strict first
STATES = (CLEAR, WARNING, STOP)


@dataclass(frozen=True)
class Decision:
    """The cell's state, the robot's speed scale, the nearest person's separation and why."""

    state: str  # "clear" | "warning" | "stop"
    speed_scale: float  # 0..1
    min_distance_m: float  # inf when no person
    part: str  # nearest human part's label name, "" when none
    link: str  # nearest robot link, "" when none
    reasons: tuple[str, ...]  # short, human readable


def stricter(a: str, b: str) -> str:
    """The stricter of two states."""
    return a if STATES.index(a) >= STATES.index(b) else b


def part_name(part: Any) -> str:
    """A part's label name, `unidentified` for something new the labels have not caught up
    with (`carry.UNIDENTIFIED`), or `part <id>` for an id the label table does not have."""
    if isinstance(part, int | np.integer) and part == UNIDENTIFIED:
        return "unidentified"
    try:
        return labels.name_of(int(part))
    except (KeyError, TypeError, ValueError, OverflowError):
        return f"part {part}"


def as_float(value: Any) -> float:
    """`value` as a float; NaN for anything that is not a number (bools included)."""
    if isinstance(value, bool | str | bytes):
        return math.nan
    try:
        return float(value)
    except (TypeError, ValueError, OverflowError):
        return math.nan


class _Verdict:
    """The state, speed scale and reasons gathered while deciding."""

    def __init__(self) -> None:
        self.state = CLEAR
        self.scale = 1.0
        self.reasons: list[str] = []

    def add(self, state: str, reason: str, scale: float = 1.0) -> None:
        """Raise the state to at least `state`, the scale to at most `scale`, note `reason`."""
        self.state = stricter(self.state, state)
        self.scale = min(self.scale, scale)
        self.reasons.append(reason)


def decide(
    cell: CellConfig,
    nearest: Any,
    zones_occupied: Any,
    unseen: dict[str, float],
    reaction_s: float,
    faults: tuple[str, ...],
) -> Decision:
    """The cell's state from the nearest person (anything with `distance_m`, `part` (label
    id) and `link`, or None when there is nobody), the zones that hold a person, each
    protective zone's unseen fraction, topseg's reaction time for this frame (s) and the
    faults found (each a short reason). The module docstring states the rules."""
    if isinstance(faults, str):
        faults = (faults,)
    distance, part, link = _nearest_fields(nearest)
    if faults:
        return Decision(STOP, 0.0, distance, part, link, tuple(str(f) for f in faults))
    verdict = _Verdict()
    reaction = as_float(reaction_s)
    if not (math.isfinite(reaction) and reaction >= 0):
        verdict.add(STOP, f"reaction time {reaction_s!r} s is not a time", 0.0)
    _zones(cell, zones_occupied, unseen, verdict)
    if cell.robot is not None and nearest is not None and verdict.state != STOP:
        _separation(cell, nearest, distance, reaction, verdict)
    if verdict.state == STOP:
        verdict.scale = 0.0
    elif verdict.state == CLEAR:
        verdict.scale = 1.0
    return Decision(
        verdict.state, float(verdict.scale), distance, part, link, tuple(verdict.reasons)
    )


def _nearest_fields(nearest: Any) -> tuple[float, str, str]:
    """(distance, part name, link) of the nearest person; (inf, '', '') for nobody."""
    if nearest is None:
        return math.inf, "", ""
    return as_float(nearest.distance_m), part_name(nearest.part), str(nearest.link)


def _zones(cell: CellConfig, occupied: Any, unseen: dict[str, float], verdict: _Verdict) -> None:
    """Zone rules: people in zones, unseen protective zones."""
    kinds = {z.name: z.kind for z in cell.zones}
    for name in occupied:
        kind = kinds.get(name, "protective")  # a zone the cell does not know: the strict kind
        if kind == "protective":
            verdict.add(STOP, f"person in protective zone {name}", 0.0)
        else:
            verdict.add(WARNING, f"person in warning zone {name}")
    limit = cell.max_unseen_fraction
    for zone in cell.zones:
        if zone.kind != "protective":
            continue
        share = unseen.get(zone.name) if isinstance(unseen, dict) else None
        if share is None:
            verdict.add(STOP, f"protective zone {zone.name}: no view of it", 0.0)
        elif not 0 <= as_float(share) <= 1:  # False for NaN too
            verdict.add(STOP, f"protective zone {zone.name}: unseen share {share!r}", 0.0)
        elif share > limit:
            verdict.add(STOP, f"protective zone {zone.name} {share:.0%} unseen > {limit:.0%}", 0.0)


def _separation(
    cell: CellConfig, nearest: Any, distance: float, reaction_s: float, verdict: _Verdict
) -> None:
    """Speed and separation monitoring and, where the cell allows contact, the body-region
    limit, for the nearest person."""
    robot, sep = cell.robot, cell.separation
    who = f"{part_name(nearest.part)} {distance:.2f} m from {nearest.link}"
    if not (math.isfinite(distance) and distance >= 0):
        verdict.add(STOP, f"{part_name(nearest.part)} at an unknown distance ({distance})", 0.0)
        return
    s_p_full = protective_distance(sep, robot, reaction_s, robot.max_speed_mps)
    scale = allowed_robot_speed(sep, robot, reaction_s, distance) / robot.max_speed_mps
    if scale <= 0:
        s_p_still = protective_distance(sep, robot, reaction_s, 0.0)
        verdict.add(STOP, f"{who} < S_p {s_p_still:.2f} m", 0.0)
        return
    if scale < 1:
        verdict.add(WARNING, f"{who} < S_p {s_p_full:.2f} m: speed {scale:.0%}", scale)
    elif distance < s_p_full + sep.warning_margin_m:
        verdict.add(
            WARNING, f"{who} within S_p {s_p_full:.2f} m + {sep.warning_margin_m:.2f} m margin"
        )
    if cell.contact_allowed and distance < s_p_full:
        _contact(cell, nearest, who, verdict)


def _contact(cell: CellConfig, nearest: Any, who: str, verdict: _Verdict) -> None:
    """The body-region limit for the nearest part within S_p at full speed."""
    robot = cell.robot
    try:
        region = cell.regions.get(int(nearest.part))
    except (TypeError, ValueError, OverflowError):
        region = None
    if region is None:
        verdict.add(STOP, f"{who}: no body-region limits for it", 0.0)
        return
    if not region.contact_allowed:
        verdict.add(STOP, f"{who}: no contact allowed", 0.0)
        return
    v_contact = permissible_contact_speed(region, robot.effective_mass_kg)
    scale = min(1.0, v_contact / robot.max_speed_mps)
    if scale <= 0:
        verdict.add(STOP, f"{who}: contact speed 0", 0.0)
    elif scale < 1:
        verdict.add(WARNING, f"{who}: contact limit {v_contact:.2f} m/s, speed {scale:.0%}", scale)
