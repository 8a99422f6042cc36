"""How the safety service's decisions compare with the truth of a rendered cell sequence.

A cell recording (`topseg datagen cell-sequence`) carries, per frame, the exact labels and
each person's exact separation from the robot's links. The truth's decision for a frame is
the cell's own rules (`decision.decide`) applied to what a perfect perception would give:
the nearest in-view person's exact distance, part and link; the zones the exactly labelled
person pixels occupy; the unseen share of the protective zones and the camera's faults as
the frame's depth shows them; and the reaction time the service measured for that decision
(so the protective distance is the same). So a disagreement is perception's: labels or
separation, not timing.

`score` reads the decisions taken on frames (the first the service published for each) and
gives: the share whose state equals the truth's, how often it said `clear` when the truth
said `stop` (must be never), the separation error (|measured - true| where both saw a person
and a robot) p50/p95, and its p95 apart over the frames whose true nearest point the camera
sees (any of its cameras) and those where none does (out of the image, under the robot or another body part, or
on the person's own side, which a camera above sees past: no perception measures those
exactly), the error's two sides apart at p99 (measured farther than the truth: the side
that could let the robot run on; nearer: the cautious side), the share of frames with one
person in view where the nearest part is the truth's, and the reaction time p50/p99.
"""

from __future__ import annotations

from dataclasses import dataclass

from topseg.core import labels as label_table
from topseg.core.camera import axis_depth
from topseg.core.formats.wire import DepthFrame, LabelFrame
from topseg.core.metrics import percentile
from topseg.core.safety.cell import CameraPlacement
from topseg.core.safety.decision import Decision, decide
from topseg.core.safety.monitor import CellMonitor
from topseg.core.safety.separation import image_pixels


@dataclass(frozen=True)
class TruthNearest:
    """The exact nearest pair of one frame (what `decide` reads)."""

    distance_m: float
    part: int
    link: str
    point_m: tuple[float, float, float] | None = None  # the person's point, cell frame


def truth_nearest(persons: list[dict]) -> tuple[TruthNearest | None, int]:
    """The nearest of the in-view persons of a safety truth message and how many were in view."""
    seen = [p for p in persons if p.get("in_view", True)]
    if not seen:
        return None, 0
    best = min(seen, key=lambda p: float(p["distance_m"]))
    part = label_table.by_name(str(best["part"])).id
    point = best.get("point_m")
    point = None if point is None else tuple(float(v) for v in point)
    return TruthNearest(float(best["distance_m"]), part, str(best["link"]), point), len(seen)


def truth_decision(
    monitor: CellMonitor,
    views: list[tuple[str, DepthFrame, LabelFrame]],
    persons: list[dict],
    reaction_s: float,
) -> Decision:
    """The truth's decision for one moment (see the module doc) from every camera's
    (name, depth, exact labels) of it: `monitor` is a monitor of the cell that holds the
    moment's exact joint state."""
    for camera, depth, truth in views:
        monitor.frame(camera, depth, truth, depth.stamp_ns)
    seen = monitor.gathered(max(depth.stamp_ns for _, depth, _ in views))
    nearest, _ = truth_nearest(persons)
    faults = tuple(f for f in seen.faults if "nowhere known" not in f)
    return decide(monitor.cell, nearest, seen.occupied, seen.unseen, reaction_s, faults)


#: The truth's nearest point is seen when the camera's depth at its pixel is no nearer than
#: the point by more than this (m): beyond it something (the robot, another body part) hides it.
SEEN_TOLERANCE_M = 0.05


def nearest_point_seen(point_cell, depth: DepthFrame, placement) -> bool:
    """Whether the camera of `depth` (placed in the cell by `placement`) sees a cell-frame
    point: it projects into the image, and the depth there is not nearer than the point by
    more than SEEN_TOLERANCE_M. A separation the camera cannot see is not perception's to
    measure: the experiment reports its error apart."""
    mount = depth.mount or placement.mount
    if mount is None:
        return False
    inside, rows, cols, z_m = image_pixels(point_cell, mount, placement)
    if not inside[0]:
        return False
    z_mm = float(axis_depth(depth.depth, mount)[rows[0], cols[0]])
    return bool(z_mm > 0 and z_mm / 1000.0 >= z_m[0] - SEEN_TOLERANCE_M)


def truth_point_seen(
    nearest: TruthNearest | None, seen_by: list[tuple[DepthFrame, CameraPlacement]]
) -> bool | None:
    """Whether some camera sees the truth's nearest point (`nearest_point_seen` over the
    (depth, placement) of each camera); None without one."""
    if nearest is None or nearest.point_m is None:
        return None
    return any(nearest_point_seen(nearest.point_m, d, placement) for d, placement in seen_by)


@dataclass
class Compared:
    """One decision the service took on a frame, beside the truth's."""

    state: str
    truth_state: str
    distance_m: float | None
    truth_distance_m: float | None
    part: str
    truth_part: str
    persons_in_view: int
    reaction_ms: float | None
    #: whether the camera sees the truth's nearest point (None: not known)
    truth_point_seen: bool | None = None


def score(compared: list[Compared]) -> dict:
    """The figures of the module doc over `compared` (JSON-able)."""
    n = len(compared)
    if not n:
        return {"frames": 0}
    equal = sum(c.state == c.truth_state for c in compared)
    unsafe = sum(c.state == "clear" and c.truth_state == "stop" for c in compared)
    both = [c for c in compared if c.distance_m is not None and c.truth_distance_m is not None]
    signed = [c.distance_m - c.truth_distance_m for c in both]
    errors = [abs(e) for e in signed]
    seen = [e for c, e in zip(both, errors, strict=True) if c.truth_point_seen]
    hidden = [e for c, e in zip(both, errors, strict=True) if c.truth_point_seen is False]
    single = [c for c in compared if c.persons_in_view == 1 and c.part and c.truth_part]
    reactions = [c.reaction_ms for c in compared if c.reaction_ms is not None]
    confusion = {
        f"{t}->{s}": sum(c.truth_state == t and c.state == s for c in compared)
        for t in ("clear", "warning", "stop")
        for s in ("clear", "warning", "stop")
    }
    return {
        "frames": n,
        "state_agreement": equal / n,
        "clear_when_truth_stop": unsafe,
        "states_truth_to_service": confusion,
        "distance_frames": len(errors),
        "distance_error_p50_m": percentile(errors, 50) if errors else None,
        "distance_error_p95_m": percentile(errors, 95) if errors else None,
        "distance_farther_p99_m": percentile([max(e, 0.0) for e in signed], 99) if both else None,
        "distance_nearer_p99_m": percentile([max(-e, 0.0) for e in signed], 99) if both else None,
        "distance_frames_seen": len(seen),
        "distance_error_p95_seen_m": percentile(seen, 95) if seen else None,
        "distance_frames_hidden": len(hidden),
        "distance_error_p95_hidden_m": percentile(hidden, 95) if hidden else None,
        "part_frames": len(single),
        "part_agreement": (
            sum(c.part == c.truth_part for c in single) / len(single) if single else None
        ),
        "reaction_p50_ms": percentile(reactions, 50) if reactions else None,
        "reaction_p99_ms": percentile(reactions, 99) if reactions else None,
    }


def one_decision_per_frame(states: list, key=lambda s: s.frame) -> list:
    """The first decision published on each frame (later ones on the same frame are the
    re-decisions between frames)."""
    seen, out = set(), []
    for state in states:
        frame = key(state)
        if frame is None or frame in seen:
            continue
        seen.add(frame)
        out.append(state)
    return out
