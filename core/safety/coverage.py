"""How much of the space around the robot the cell's cameras see.

A person is measured only where a camera sees them. The space that matters is the disc on
the floor around the robot's base out to its reach plus the protective separation distance
S_p at full speed (ISO/TS 15066 5.5.4, at the worst reaction time the service accepts: the
frames' deadline): a person anywhere in it may be closer to the robot than S_p. Beyond a
camera's view a person is unseen until they step into it, and a person only partly in view
at the image's edge (legs in, body out) is easily read as background: the decision cannot
be right about them. `coverage` samples that disc at the floor and at shoulder height (a
camera sees less of the room the higher up) and returns the share any camera sees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from topseg.core.camera import TopViewMount
from topseg.core.safety.cell import CameraPlacement, CellConfig
from topseg.core.safety.iso15066 import protective_distance
from topseg.core.safety.separation import camera_pixels

#: the heights (m) the disc is looked at: the floor (feet) and shoulders
HEIGHTS_M = (0.0, 1.5)
#: the spacing (m) of the points the disc is sampled at, at least; a disc wider than
#: MAX_STEPS spacings across is sampled at MAX_STEPS points across
SPACING_M = 0.05
MAX_STEPS = 200


@dataclass(frozen=True)
class Coverage:
    """The disc that matters and the share of it the cameras see at each height."""

    radius_m: float  # the robot's reach + s_p_m
    reach_m: float  # a bound on the robot's reach: its joints' offsets from base to tool
    s_p_m: float
    seen: dict[float, float]  # height (m) -> share of the disc seen by any camera

    def worst(self) -> float:
        """The least share over the heights."""
        return min(self.seen.values())

    def sentence(self) -> str:
        """One line for the log."""
        shares = ", ".join(f"{100 * v:.0f} % at {h:g} m" for h, v in sorted(self.seen.items()))
        line = (
            f"the cameras see {shares} of the floor within {self.radius_m:.2f} m of the "
            f"robot's base (its reach, at most {self.reach_m:.2f} m, + S_p {self.s_p_m:.2f} m "
            "at full speed)"
        )
        if self.worst() < 1.0:
            line += (
                ": a person outside that view is unseen until they step into it, and one "
                "at the image's edge may be missed; widen the view (a higher or wider "
                "camera, or another camera)"
            )
        return line


def disc_points(centre_xy, radius_m: float, spacing_m: float = SPACING_M) -> np.ndarray:
    """(n, 2) points of a square grid of `spacing_m` inside the disc (its centre always)."""
    steps = max(1, math.ceil(radius_m / spacing_m))
    axis = np.arange(-steps, steps + 1) * spacing_m
    xx, yy = np.meshgrid(axis, axis)
    inside = xx**2 + yy**2 <= radius_m**2
    return np.stack([xx[inside], yy[inside]], axis=1) + np.asarray(centre_xy, np.float64)


def seen_by(points_cell: np.ndarray, placement: CameraPlacement, mount: TopViewMount):
    """(n,) bool: which (n, 3) cell-frame points lie inside the camera's image."""
    return camera_pixels(points_cell, mount, placement)[2]


def coverage(cell: CellConfig, reach_m: float, mounts: dict[str, TopViewMount]) -> Coverage | None:
    """The share of the disc around the robot's base the cameras with a mount in `mounts`
    (camera name -> mount) see; None for a cell without a robot."""
    robot = cell.robot
    if robot is None:
        return None
    s_p = float(
        protective_distance(cell.separation, robot, cell.deadline_ms / 1000.0, robot.max_speed_mps)
    )
    radius = reach_m + s_p
    if not math.isfinite(radius):  # S_p has no bound: nothing is covered
        return Coverage(radius, reach_m, s_p, {h: 0.0 for h in HEIGHTS_M})
    xy = disc_points(robot.base_xyz_m[:2], radius, max(SPACING_M, 2 * radius / MAX_STEPS))
    seen = {}
    for height in HEIGHTS_M:
        points = np.column_stack([xy, np.full(len(xy), height)])
        any_camera = np.zeros(len(xy), bool)
        for placement in cell.cameras:
            mount = mounts.get(placement.name)
            if mount is not None:
                any_camera |= seen_by(points, placement, mount)
        seen[height] = float(any_camera.mean())
    return Coverage(radius, reach_m, s_p, seen)
