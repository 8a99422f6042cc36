"""What the viewers and the ROS 2 bridge show of a cell's safety state, in one place: the
colour of each state, the zones' outlines, the robot's capsules as posed shapes, and the
optional cell file (`--cell CELL.toml`) that gives the zones, the cameras' placements and
the robot.

Colours: `clear` green, `warning` amber, `stop` red; a zone or cell with no state yet grey.
A zone is drawn as its floor polygon at `z_min_m` and at `z_max_m`, each closed, joined by
one vertical edge per vertex, in the cell frame (the floor, z up). The viewers draw it in a
camera's world frame (`CameraPlacement.to_camera_world`), where that camera's point cloud is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from topseg.core.errors import TopsegError
from topseg.core.formats import joint_states as joint_wire
from topseg.core.formats import ros2_messages as ros2
from topseg.core.formats import safety_wire
from topseg.core.safety.cell import CameraPlacement, CellConfig, Zone, load_cell
from topseg.core.safety.robot import CellRobot

#: (r, g, b) of each state
STATE_COLOURS = {"clear": (40, 170, 70), "warning": (255, 170, 0), "stop": (220, 30, 30)}
#: a zone or cell with no state yet
UNKNOWN_COLOUR = (140, 140, 140)
#: a state as a number for plots: clear 0, warning 1, stop 2
STATE_LEVELS = {state: float(i) for i, state in enumerate(safety_wire.STATES)}


def state_colour(state: str | None) -> tuple[int, int, int]:
    """The colour of a state; grey for None or anything unknown."""
    return STATE_COLOURS.get(state or "", UNKNOWN_COLOUR)


def zone_strips(zone: Zone, placement: CameraPlacement | None = None) -> list[np.ndarray]:
    """A zone's outline as line strips ((n, 3) float64 each): the polygon closed at z_min
    and at z_max, then one vertical edge per vertex; in the cell frame, or in `placement`'s
    camera world frame when given."""
    xy = np.asarray(zone.polygon_m, np.float64)
    ring = np.vstack([xy, xy[:1]])

    def at(z: float) -> np.ndarray:
        return np.column_stack([ring, np.full(len(ring), z)])

    strips = [at(zone.z_min_m), at(zone.z_max_m)]
    strips += [np.array([[x, y, zone.z_min_m], [x, y, zone.z_max_m]]) for x, y in xy]
    if placement is not None:
        strips = [placement.to_camera_world(s) for s in strips]
    return strips


def in_frame(points: np.ndarray, placement: CameraPlacement | None) -> np.ndarray:
    """(n, 3) cell-frame points in `placement`'s camera world frame (as they are for None)."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    return points if placement is None else placement.to_camera_world(points)


@dataclass(frozen=True)
class PosedCapsules:
    """Capsules as posed shapes: capsule i runs `length[i]` along its local +z from
    `translation[i]`, turned by `quaternion[i]` (x, y, z, w), radius `radius[i]`."""

    translation: np.ndarray
    quaternion: np.ndarray
    length: np.ndarray
    radius: np.ndarray
    link: tuple[str, ...]


def posed_capsules(capsules, placement: CameraPlacement | None = None) -> PosedCapsules:
    """The robot's capsules (`CellRobot.capsules`, cell frame) as posed shapes, in
    `placement`'s camera world frame when given."""
    a = in_frame(capsules.a, placement)
    b = in_frame(capsules.b, placement)
    axis = b - a
    length = np.linalg.norm(axis, axis=1)
    quats = np.array([_z_to(v, n) for v, n in zip(axis, length, strict=True)]).reshape(-1, 4)
    return PosedCapsules(a, quats, length, np.asarray(capsules.radius, np.float64), capsules.link)


def _z_to(vector: np.ndarray, norm: float) -> tuple[float, float, float, float]:
    """The shortest rotation (x, y, z, w) taking +z to `vector` (identity for a zero one)."""
    if not norm > 1e-12:
        return (0.0, 0.0, 0.0, 1.0)
    d = vector / norm
    if d[2] < -1.0 + 1e-12:  # straight down: half a turn about x
        return (1.0, 0.0, 0.0, 0.0)
    q = np.array([-d[1], d[0], 0.0, 1.0 + d[2]])
    q /= math.sqrt(float(q @ q))
    return tuple(float(v) for v in q)


@dataclass(frozen=True)
class CellView:
    """A cell file as the viewers and the bridge use it: its zones, cameras and robot."""

    config: CellConfig
    robot: CellRobot | None

    @property
    def name(self) -> str:
        """The cell's name on the wire."""
        return self.config.cell

    def joints_key(self) -> str | None:
        """The Zenoh key of the robot's joint states (msgpack), None without a robot or when
        the cell file takes them from ROS 2."""
        robot = self.config.robot
        if robot is None or robot.joints_source != "zenoh":
            return None
        return joint_wire.joints_key(self.config.cell, robot.name)

    def capsules(self, joints: joint_wire.JointState):
        """The robot's capsules (cell frame) at a joint state; ValueError for a state that
        does not fit the robot."""
        if self.robot is None:
            raise ValueError(f"cell {self.name} has no robot")
        return self.robot.capsules(joints.as_dict())


def load_cell_view(path: str | None) -> CellView | None:
    """The cell file at `path` with its robot loaded, None without a path; one TopsegError
    line for a file that cannot be used."""
    if not path:
        return None
    config = load_cell(path)  # ConfigError (a TopsegError) names the file and key
    robot = None
    if config.robot is not None:
        try:
            robot = CellRobot(config.robot, Path(path).resolve().parent)
        except (OSError, ValueError) as exc:
            raise TopsegError(f"{path}: cannot load robot {config.robot.name!r}: {exc}") from None
    return CellView(config, robot)


def rgba(state: str | None, alpha: float = 1.0) -> tuple[float, float, float, float]:
    """The colour of a state as (r, g, b, a) in 0..1 (ROS 2 and Foxglove colours)."""
    r, g, b = state_colour(state)
    return (r / 255.0, g / 255.0, b / 255.0, alpha)


def safety_markers(zones, state) -> list:
    """A cell's zones (`Zone`s) and its state's nearest pair as ROS 2 markers in the cell
    frame: per zone (ns `zone/<name>`) its outline at z_min (id 0) and z_max (id 1) as
    LINE_STRIPs and its vertical edges (id 2) as a LINE_LIST, coloured by the zone's state;
    the nearest pair (ns `nearest`) as an ARROW from the person to the robot (id 0) and its
    distance as text (id 1), both deleted when there is no pair."""
    markers = []
    for zone in zones:
        colour = rgba(state.zones.get(zone.name))
        bottom, top, *edges = zone_strips(zone)
        ns = f"zone/{zone.name}"
        markers += [
            ros2.MarkerSpec(ns, 0, ros2.LINE_STRIP, bottom, colour),
            ros2.MarkerSpec(ns, 1, ros2.LINE_STRIP, top, colour),
            ros2.MarkerSpec(ns, 2, ros2.LINE_LIST, np.vstack(edges), colour),
        ]
    if state.nearest_m is None:
        markers += [
            ros2.MarkerSpec("nearest", 0, ros2.ARROW, delete=True),
            ros2.MarkerSpec("nearest", 1, ros2.TEXT_VIEW_FACING, delete=True),
        ]
        return markers
    person, robot = (np.asarray(p, np.float64) for p in state.nearest_m)
    colour = rgba(state.state)
    text = "" if state.min_distance_m is None else f"{state.min_distance_m:.2f} m"
    markers += [
        ros2.MarkerSpec("nearest", 0, ros2.ARROW, [person, robot], colour, width_m=0.02),
        ros2.MarkerSpec(
            "nearest", 1, ros2.TEXT_VIEW_FACING, rgba=colour, text=text,
            position=tuple((person + robot) / 2 + (0.0, 0.0, 0.1)),
        ),
    ]  # fmt: skip
    return markers
