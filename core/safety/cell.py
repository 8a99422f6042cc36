"""The cell file: where the cameras hang, the robot and its stopping data, the zones, the
separation parameters and the body-region limits, read from TOML.

    cell = "cell1"                      # topseg/<cell>/... on the wire
    contact_allowed = false             # power and force limiting allowed in this cell
    [robot]  name = "arm", urdf = "panda", stopping_time_s = 0.5, ...
    [[camera]]  name = "cam0", x_m = 0, y_m = 0, yaw_deg = 0
    [[zone]]  name = "press", kind = "protective", polygon_m = [[0, 0], [1, 0], [1, 1]]
    [separation]  human_speed_mps = 1.6, ...
    [regions.hand]  max_force_n = 140, ...

Every table is read through `topseg.core.config.from_dict`: an unknown key (with the closest
known one suggested), a value of the wrong type or out of range is one `ConfigError` naming
the file and the table. Metres and seconds throughout. The cell frame is the floor, z up;
a camera's own world frame (`TopViewMount`'s) is the cell frame turned by `yaw_deg` about z
and moved by (`x_m`, `y_m`).

The defaults cite their sources. ISO/TS 15066:2016 clause 5.5.4 gives the protective
separation distance S_p; ISO 13855:2010 the human approach speed and the intrusion distance
C; ISO/TS 15066 Annex A tables A.2 and A.3 the body-region limits. A monitoring aid, not a
certified safety device: the integrator sets the robot's datasheet values and checks them.
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from topseg.core import labels
from topseg.core.camera import TopViewMount
from topseg.core.config import describe, from_dict, suggest
from topseg.core.errors import ConfigError
from topseg.core.formats.mount_file import read_mount_file
from topseg.core.synth.robots import RANDOM, ROBOTS

#: a cell, camera, robot or zone name: a plain Zenoh key chunk, as the wire's names
_NAME = re.compile(r"[A-Za-z0-9_.-]{1,64}")
#: zone kinds: a person in a warning zone slows the cell, in a protective zone stops it
ZONE_KINDS = ("warning", "protective")
#: where the robot's joint states come from
JOINT_SOURCES = ("zenoh", "ros2")
#: the URDF suffixes that mark `RobotSpec.urdf` as a file, not a catalogue name
_URDF_SUFFIXES = (".urdf", ".xacro", ".xml")
#: ISO 13855:2010 clause 6.2.3: the intrusion distance C of body detection (no hand or
#: finger detection), metres
BODY_INTRUSION_M = 0.850
#: ISO 13855:2010: C = 8 (d - 14) mm holds for a detection capability d up to this, mm
FINGER_DETECTION_MAX_MM = 40.0


def _check_name(what: str, name: str) -> None:
    """ValueError unless `name` is a plain key chunk (letters, digits, `_`, `.`, `-`)."""
    if not _NAME.fullmatch(name):
        raise ValueError(
            f"{what} {name!r} must be 1-64 characters of letters, digits, '_', '.', '-'"
        )


def _check_finite(**values: float) -> None:
    """ValueError naming the first value that is not finite."""
    for key, value in values.items():
        if not math.isfinite(value):
            raise ValueError(f"{key} must be a finite number, got {value}")


def _check_positive(**values: float) -> None:
    """ValueError naming the first value that is not finite and > 0."""
    for key, value in values.items():
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{key} must be a positive number, got {value}")


def _check_non_negative(**values: float) -> None:
    """ValueError naming the first value that is not finite and >= 0."""
    for key, value in values.items():
        if not (math.isfinite(value) and value >= 0):
            raise ValueError(f"{key} must be a number >= 0, got {value}")


def _rz(yaw_deg: float) -> np.ndarray:
    """(3, 3) rotation by `yaw_deg` about z."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class CameraPlacement:
    """Where a camera hangs over the cell (`[[camera]]`): its world frame (`TopViewMount`'s,
    origin on the floor under the camera centre) is the cell frame turned by `yaw_deg` about
    z and moved by (`x_m`, `y_m`): `p_cell = Rz(yaw) @ p_cam_world + (x, y, 0)`. `name` is
    the camera's name on the wire (`topseg/<cell>/<camera>/labels`). `mount_file`: the
    camera's mount file (`topseg calibrate`), for frames that carry no mount; "" when the
    frames carry it (`topseg driver --mount`). The loader reads it into `mount`."""

    name: str = "cam0"
    x_m: float = 0.0
    y_m: float = 0.0
    yaw_deg: float = 0.0
    mount_file: str = ""
    mount: TopViewMount | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        _check_name("camera name", self.name)
        _check_finite(x_m=self.x_m, y_m=self.y_m, yaw_deg=self.yaw_deg)
        if self.mount is not None and not isinstance(self.mount, TopViewMount):
            raise ValueError("mount is read from mount_file; give the mount file's path")

    def rotation(self) -> np.ndarray:
        """(3, 3) Rz(yaw): camera world -> cell directions."""
        return _rz(self.yaw_deg)

    def offset(self) -> np.ndarray:
        """(3,) the camera world's origin in the cell frame: (x, y, 0)."""
        return np.array([self.x_m, self.y_m, 0.0])

    def to_cell(self, points_world: np.ndarray) -> np.ndarray:
        """(n, 3) points in the camera's world frame -> the cell frame (float64)."""
        p = np.asarray(points_world, np.float64)
        return p @ self.rotation().T + self.offset()

    def to_camera_world(self, points_cell: np.ndarray) -> np.ndarray:
        """(n, 3) points in the cell frame -> the camera's world frame (`to_cell`'s inverse)."""
        p = np.asarray(points_cell, np.float64)
        return (p - self.offset()) @ self.rotation()


#: what a robot's base may stand on
PEDESTALS = ("none", "box", "cylinder")


@dataclass(frozen=True)
class RobotSpec:
    """The cell's robot (`[robot]`): its model, where its base stands, where its joint states
    come from, and its datasheet stopping data. The defaults are placeholders of a small
    collaborative arm at full speed, on the conservative side; set the robot's own."""

    name: str  # the robot's name on topseg/<cell>/robot/<name>/joints
    # a URDF path (a relative one: to the cell file's folder) or a robot catalogue name of
    # core/synth/robots.py ("panda", ...)
    urdf: str
    base_xyz_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    base_yaw_deg: float = 0.0
    upside_down: bool = False  # hangs from a gantry
    joints_source: str = "zenoh"  # "zenoh" (the msgpack key) or "ros2" (/joint_states)
    ros2_topic: str = "/joint_states"
    joint_state_max_age_ms: float = 100.0
    # T_s, ISO/TS 15066 5.5.4: the time from the stop command to standstill. ISO 10218-1
    # annex B has the maker publish it (category 0 and 1 stops at full speed and payload);
    # 0.5 s is at the slow end of small cobots' published category 1 stops: a placeholder.
    stopping_time_s: float = 0.5
    # S_s, ISO/TS 15066 5.5.4: the distance the robot travels while stopping (same source);
    # 0.3 m: a placeholder of the same kind.
    stopping_distance_m: float = 0.3
    # the fastest point of the robot, m/s: v_r in S_p at full speed, and the silhouette's
    # margin. 1.5 m/s: a common cobot TCP speed limit; set the robot's own.
    max_speed_mps: float = 1.5
    # m_R, ISO/TS 15066 A.3.2: half the moving mass plus the payload (M/2 + m_L). 15 kg: a
    # 20 kg cobot with a 5 kg payload; set the robot's own.
    effective_mass_kg: float = 15.0
    # what the base stands on, from the floor up to base_xyz_m's z: "none", "box" (a square
    # column of half width pedestal_size_m, turned with the robot) or "cylinder" (of radius
    # pedestal_size_m). Its pixels are the robot's, like the links' (never a person's legs);
    # the separation is measured to the links only.
    pedestal: str = "none"
    pedestal_size_m: float = 0.0

    def __post_init__(self) -> None:
        _check_name("robot name", self.name)
        if not self.urdf:
            raise ValueError("urdf must be a URDF path or a robot catalogue name, got ''")
        _check_finite(
            base_x_m=self.base_xyz_m[0],
            base_y_m=self.base_xyz_m[1],
            base_z_m=self.base_xyz_m[2],
            base_yaw_deg=self.base_yaw_deg,
        )
        if self.joints_source not in JOINT_SOURCES:
            raise ValueError(
                f"joints_source must be one of {', '.join(JOINT_SOURCES)}, "
                f"got {self.joints_source!r}{suggest(self.joints_source, JOINT_SOURCES)}"
            )
        if self.pedestal not in PEDESTALS:
            raise ValueError(
                f"pedestal must be one of {', '.join(PEDESTALS)}, got {self.pedestal!r}"
            )
        if self.pedestal != "none" and not (
            math.isfinite(self.pedestal_size_m) and self.pedestal_size_m > 0
        ):
            raise ValueError(f"a {self.pedestal} pedestal needs pedestal_size_m > 0")
        if not self.ros2_topic.startswith("/"):
            raise ValueError(f"ros2_topic must start with '/', got {self.ros2_topic!r}")
        _check_positive(
            joint_state_max_age_ms=self.joint_state_max_age_ms,
            stopping_time_s=self.stopping_time_s,
            max_speed_mps=self.max_speed_mps,
            effective_mass_kg=self.effective_mass_kg,
        )
        _check_non_negative(stopping_distance_m=self.stopping_distance_m)

    @property
    def is_catalogue(self) -> bool:
        """Whether `urdf` names a catalogue robot (or a random arm), not a file."""
        return is_catalogue_name(self.urdf)


def is_catalogue_name(urdf: str) -> bool:
    """Whether a `[robot] urdf` value names a catalogue robot or a random arm, not a file:
    no `/` and no URDF suffix (as `core.synth.robots.robot_model` tells them apart)."""
    return "/" not in urdf and not urdf.endswith(_URDF_SUFFIXES)


@dataclass(frozen=True)
class Zone:
    """A zone (`[[zone]]`): a floor polygon in the cell frame and a height range, a prism. A
    person in a `warning` zone slows the cell (at least `warning`); a person in a
    `protective` zone, or too much of it unseen, stops it."""

    name: str
    kind: str  # "warning" | "protective"
    polygon_m: tuple[tuple[float, float], ...]  # cell frame, >= 3 vertices, a simple polygon
    z_min_m: float = 0.0
    z_max_m: float = 2.5

    def __post_init__(self) -> None:
        _check_name("zone name", self.name)
        if self.kind not in ZONE_KINDS:
            raise ValueError(
                f"zone kind must be one of {', '.join(ZONE_KINDS)}, got {self.kind!r}"
                f"{suggest(self.kind, ZONE_KINDS)}"
            )
        _check_finite(z_min_m=self.z_min_m, z_max_m=self.z_max_m)
        if not self.z_min_m < self.z_max_m:
            raise ValueError(f"z_min_m ({self.z_min_m:g}) must be below z_max_m ({self.z_max_m:g})")
        problem = polygon_problem(self.polygon_m)
        if problem:
            raise ValueError(f"polygon_m {problem}")


def polygon_problem(polygon: tuple[tuple[float, float], ...]) -> str | None:
    """Why `polygon` is not a simple polygon (>= 3 finite vertices, no zero area, no two
    edges that meet except neighbours at their shared vertex), or None when it is."""
    if len(polygon) < 3:
        return f"needs at least 3 vertices, got {len(polygon)}"
    pts = np.asarray(polygon, np.float64)
    if not np.isfinite(pts).all():
        return "has a vertex that is not finite"
    n = len(pts)
    for i in range(n):
        a, b = pts[i], pts[(i + 1) % n]
        if np.array_equal(a, b):
            return f"repeats vertex {i} ({a[0]:g}, {a[1]:g})"
        for j in range(i + 1, n):
            if j == i + 1 or (i == 0 and j == n - 1):
                continue  # neighbours share a vertex
            c, d = pts[j], pts[(j + 1) % n]
            if _segments_meet(a, b, c, d):
                return f"crosses itself: edges {i} and {j} meet (not a simple polygon)"
    if abs(_signed_area(pts)) < 1e-9:
        return "has no area (its vertices are on one line)"
    return None


def _signed_area(pts: np.ndarray) -> float:
    """The shoelace area of a closed polygon (positive counter-clockwise)."""
    x, y = pts[:, 0], pts[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def _cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """The z of (a - o) x (b - o)."""
    return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))


def _on_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> bool:
    """Whether `p`, collinear with a-b, lies within the segment's bounding box."""
    return min(a[0], b[0]) <= p[0] <= max(a[0], b[0]) and min(a[1], b[1]) <= p[1] <= max(a[1], b[1])


def _segments_meet(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> bool:
    """Whether the closed segments a-b and c-d share a point (touching counts)."""
    d1, d2 = _cross(c, d, a), _cross(c, d, b)
    d3, d4 = _cross(a, b, c), _cross(a, b, d)
    if ((d1 > 0 > d2) or (d1 < 0 < d2)) and ((d3 > 0 > d4) or (d3 < 0 < d4)):
        return True
    return (
        (d1 == 0 and _on_segment(a, c, d))
        or (d2 == 0 and _on_segment(b, c, d))
        or (d3 == 0 and _on_segment(c, a, b))
        or (d4 == 0 and _on_segment(d, a, b))
    )


def intrusion_distance_m(detection_capability_mm: float) -> float:
    """ISO 13855:2010 clause 6.2.3: the intrusion distance C (m) for a sensor that detects
    objects of `detection_capability_mm` (d): C = 8 (d - 14) mm for d <= 40 mm (0 below
    14 mm), 850 mm when only larger objects (arms, the body) are detected."""
    d = float(detection_capability_mm)
    if d > FINGER_DETECTION_MAX_MM:
        return BODY_INTRUSION_M
    return max(0.0, 8.0 * (d - 14.0)) / 1000.0


@dataclass(frozen=True)
class SeparationParams:
    """Speed and separation monitoring (`[separation]`), ISO/TS 15066:2016 clause 5.5.4:
    S_p = S_h + S_r + S_s + C + Z_d + Z_r, with S_h = v_h (T_r + T_s) and S_r = v_r T_r, T_r
    the reaction time (topseg's, measured per frame, plus `controller_reaction_s`)."""

    # v_h: ISO 13855:2010 clause 6.2.3 (and ISO/TS 15066 5.5.4, absent other data): 1.6 m/s
    # for approach at separation distances beyond 0.5 m (2.0 m/s below; the separations this
    # service measures are used with 1.6 m/s, the standard's default for S_p).
    human_speed_mps: float = 1.6
    # the robot controller's own part of T_r: from the speed command reaching it to the robot
    # starting to brake (safety bus and controller cycle). 0.1 s: a placeholder, not a
    # standard value; measure the cell's.
    controller_reaction_s: float = 0.1
    # d, ISO 13855:2010: the smallest object the monitoring reliably detects, mm. topseg
    # segments top-view depth into body parts: hands and forearms are labelled (a hand is
    # ~80 mm across, several pixels at a ceiling camera's height), single fingers are not.
    # 40 mm is the largest d the standard still treats as hand detection, so C = 8 (40 - 14)
    # = 208 mm: a finger or tool reaching past a detected hand. A camera too high or too
    # coarse to label hands should set d > 40 (body detection, C = 850 mm).
    detection_capability_mm: float = 40.0
    # C: the intrusion distance, m; left out, it is derived from d (`intrusion_distance_m`)
    intrusion_m: float | None = None
    # Z_d: the position uncertainty of a person: depth noise at a ceiling camera's range
    # (about 1-3 cm at 3.5 m for a structured-light sensor), label boundaries a few pixels
    # off and the mount's calibration. 0.1 m: a placeholder with margin; measure the cell's.
    sensor_uncertainty_m: float = 0.1
    # Z_r: the robot's position uncertainty: encoders and the bounding capsules' fit (which
    # already enclose each link). 0.05 m: a placeholder; set from the robot's data.
    robot_uncertainty_m: float = 0.05
    # how far beyond S_p at full speed a person gives `warning` (not part of the standard)
    warning_margin_m: float = 0.5

    def __post_init__(self) -> None:
        _check_positive(
            human_speed_mps=self.human_speed_mps,
            detection_capability_mm=self.detection_capability_mm,
        )
        _check_non_negative(
            controller_reaction_s=self.controller_reaction_s,
            sensor_uncertainty_m=self.sensor_uncertainty_m,
            robot_uncertainty_m=self.robot_uncertainty_m,
            warning_margin_m=self.warning_margin_m,
        )
        if self.intrusion_m is None:
            object.__setattr__(
                self, "intrusion_m", intrusion_distance_m(self.detection_capability_mm)
            )
        else:
            _check_non_negative(intrusion_m=self.intrusion_m)


@dataclass(frozen=True)
class BodyRegion:
    """A body region's limits for power and force limiting (`[regions.<part>]`), ISO/TS
    15066 Annex A: the quasi-static force limit (table A.2), transient contact allowed at
    `transient_factor` times it, the region's effective mass and spring constant (table A.3),
    and whether the robot may touch it at all."""

    max_force_n: float  # F_max quasi-static, table A.2
    effective_mass_kg: float  # m_H, table A.3
    spring_constant_n_per_mm: float  # k, table A.3
    contact_allowed: bool = True
    transient_factor: float = 2.0  # ISO/TS 15066 A.3.2: transient contact at 2x quasi-static

    def __post_init__(self) -> None:
        _check_positive(
            max_force_n=self.max_force_n,
            effective_mass_kg=self.effective_mass_kg,
            spring_constant_n_per_mm=self.spring_constant_n_per_mm,
        )
        if not (math.isfinite(self.transient_factor) and self.transient_factor >= 1):
            raise ValueError(f"transient_factor must be >= 1, got {self.transient_factor}")

    @property
    def transient_force_n(self) -> float:
        """The force a transient contact may reach: `transient_factor` x `max_force_n`."""
        return self.transient_factor * self.max_force_n


# ISO/TS 15066:2016 Annex A, per topseg part. Each part takes the stricter of the standard's
# regions it covers. Values as quoted by open literature and code that reproduce the tables:
# the spring constants (table A.3: skull/forehead 150, face 75, chest 25, abdomen 10, upper
# arm 30, lower arm 40, hand/finger 75, thigh 50, lower leg 60 N/mm) were checked against a
# public body-region table; the effective masses (table A.3: head 4.4, torso 40, upper arm 3,
# lower arm 2, hand 0.6, legs 75 kg) against open-source implementations of the standard.
# The quasi-static forces (table A.2: skull/forehead 130, face 65, chest 140, abdomen 110,
# upper arm 150, lower arm 160, hand/finger 140, thigh/knee 220, lower leg 130 N) are the
# widely quoted values; they could not be confirmed against the standard's own text here.
DEFAULT_REGIONS: dict[int, BodyRegion] = {
    # skull/forehead, face: the face's 65 N and the skull's 150 N/mm; the standard allows no
    # contact with the head (A.2 note: face, skull, forehead), so a head within S_p stops
    labels.HEAD: BodyRegion(65.0, 4.4, 150.0, contact_allowed=False),
    # chest (140 N, 25 N/mm) and abdomen (110 N, 10 N/mm): the abdomen's force, the chest's
    # spring constant (the stiffer gives the lower permissible speed), 40 kg either
    labels.BODY: BodyRegion(110.0, 40.0, 25.0),
    labels.UPPER_ARM: BodyRegion(150.0, 3.0, 30.0),  # upper arm and elbow
    labels.LOWER_ARM: BodyRegion(160.0, 2.0, 40.0),  # lower arm and wrist
    labels.HAND: BodyRegion(140.0, 0.6, 75.0),  # hand and finger
    # thigh/knee (220 N, 50 N/mm) and lower leg (130 N, 60 N/mm): the lower leg's, 75 kg
    labels.LEGS: BodyRegion(130.0, 75.0, 60.0),
}


@dataclass(frozen=True)
class CellConfig:
    """A cell: its name on the wire, robot (None: no robot, no separation), cameras, zones,
    separation parameters and body regions (label id -> `BodyRegion`), read from `source`."""

    cell: str
    robot: RobotSpec | None = None
    cameras: tuple[CameraPlacement, ...] = (CameraPlacement(),)
    zones: tuple[Zone, ...] = ()
    separation: SeparationParams = field(default_factory=SeparationParams)
    regions: dict[int, BodyRegion] = field(default_factory=lambda: dict(DEFAULT_REGIONS))
    contact_allowed: bool = False  # power and force limiting allowed in this cell
    deadline_ms: float = 100.0  # no fresh labelled frame within it: stop
    publish_period_ms: float = 33.0
    # the share of a protective zone's pixels with no depth (not explained by the robot)
    # above which the zone counts as occupied (zones.py); 5 %: a few noise holes pass, a
    # person-sized blind spot in a small zone does not
    max_unseen_fraction: float = 0.05
    source: str = "<cell>"  # the file it came from (messages name it)

    def __post_init__(self) -> None:
        _check_name("cell", self.cell)
        _check_positive(deadline_ms=self.deadline_ms, publish_period_ms=self.publish_period_ms)
        if not (math.isfinite(self.max_unseen_fraction) and 0 <= self.max_unseen_fraction <= 1):
            raise ValueError(
                f"max_unseen_fraction must be within 0..1, got {self.max_unseen_fraction}"
            )
        if not self.cameras:
            raise ValueError("a cell needs at least one [[camera]]")
        for what, names in (
            ("camera", [c.name for c in self.cameras]),
            ("zone", [z.name for z in self.zones]),
        ):
            dup = sorted({n for n in names if names.count(n) > 1})
            if dup:
                raise ValueError(f"{what} name {dup[0]!r} is used twice")
        missing = [labels.name_of(i) for i in labels.HUMAN_IDS if i not in self.regions]
        if missing:
            raise ValueError(f"regions lacks {', '.join(missing)}")
        head = self.regions[labels.HEAD]
        if head.contact_allowed:
            raise ValueError(
                "regions.head: contact_allowed must be false (ISO/TS 15066 Annex A allows "
                "no contact with the skull, forehead or face)"
            )

    def camera(self, name: str) -> CameraPlacement | None:
        """The placement of the camera called `name`, None when the cell has no such camera."""
        return next((c for c in self.cameras if c.name == name), None)

    def zone(self, name: str) -> Zone | None:
        """The zone called `name`, None when the cell has none."""
        return next((z for z in self.zones if z.name == name), None)


#: the top-level keys of a cell file
_TOP_KEYS = (
    "cell",
    "robot",
    "camera",
    "zone",
    "separation",
    "regions",
    "contact_allowed",
    "deadline_ms",
    "publish_period_ms",
    "max_unseen_fraction",
)
#: top-level scalars read into CellConfig as they are
_SCALARS = ("contact_allowed", "deadline_ms", "publish_period_ms", "max_unseen_fraction")


def load_cell(path: str | Path) -> CellConfig:
    """The cell file at `path`; a ConfigError naming the file and key for anything wrong.
    A relative `[robot] urdf` path is taken relative to the file's folder."""
    path = Path(path)
    try:
        text = path.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such cell file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read the cell file: {exc}") from None
    try:
        table = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    return cell_from_dict(table, str(path), base_dir=path.parent)


def cell_from_dict(table: dict, source: str, base_dir: Path | None = None) -> CellConfig:
    """The cell described by `table` (a parsed cell file); `source` names it in errors. With
    `base_dir`, a relative URDF path is resolved against it and must exist."""
    if not isinstance(table, dict):
        raise ConfigError(f"{source}: expected a table of settings, got {describe(table)}")
    for key in table:
        if key not in _TOP_KEYS:
            raise ConfigError(
                f"{source}: unknown key {key!r}{suggest(str(key), _TOP_KEYS)}; "
                f"known: {', '.join(_TOP_KEYS)}"
            )
    if "cell" not in table:
        raise ConfigError(f"{source}: missing key 'cell' (the cell's name on the wire)")
    kwargs: dict[str, Any] = {k: table[k] for k in ("cell", *_SCALARS) if k in table}
    if "robot" in table:
        kwargs["robot"] = _robot(table["robot"], source, base_dir)
    if "camera" in table:
        cameras = _array(CameraPlacement, table["camera"], source, "camera")
        kwargs["cameras"] = tuple(_with_mount(c, source, base_dir) for c in cameras)
    if "zone" in table:
        kwargs["zones"] = _array(Zone, table["zone"], source, "zone")
    if "separation" in table:
        kwargs["separation"] = from_dict(
            SeparationParams, table["separation"], f"{source} [separation]"
        )
    kwargs["regions"] = _regions(table.get("regions", {}), source)
    return from_dict(CellConfig, {**kwargs, "source": source}, source)


def _robot(table: Any, source: str, base_dir: Path | None) -> RobotSpec:
    """`[robot]`, its URDF resolved against `base_dir` or checked against the catalogue."""
    where = f"{source} [robot]"
    spec = from_dict(RobotSpec, table, where, required=("name", "urdf"))
    if spec.is_catalogue:
        known = (*ROBOTS, f"{RANDOM}:<seed>")
        if spec.urdf not in ROBOTS and not re.fullmatch(rf"{RANDOM}:[0-9]{{1,19}}", spec.urdf):
            raise ConfigError(
                f"{where}: urdf {spec.urdf!r} is neither a robot catalogue name nor a .urdf "
                f"path{suggest(spec.urdf, ROBOTS)}; known: {', '.join(known)}"
            )
        return spec
    if base_dir is None:
        return spec
    path = Path(spec.urdf).expanduser()
    if not path.is_absolute():
        path = Path(base_dir) / path
    if not path.is_file():
        raise ConfigError(f"{where}: urdf {spec.urdf!r}: no such file ({path})")
    return replace(spec, urdf=str(path))


def _with_mount(camera: CameraPlacement, source: str, base_dir: Path | None) -> CameraPlacement:
    """The placement with its mount file (resolved against `base_dir`) read into `mount`."""
    if not camera.mount_file:
        return camera
    path = Path(camera.mount_file).expanduser()
    if not path.is_absolute() and base_dir is not None:
        path = Path(base_dir) / path
    try:
        mount = read_mount_file(path)
    except ConfigError as exc:
        raise ConfigError(f"{source} [camera {camera.name!r}]: {exc}") from None
    return replace(camera, mount_file=str(path), mount=mount)


def _array(cls: type, items: Any, source: str, key: str) -> tuple:
    """An array of tables (`[[camera]]`, `[[zone]]`) as a tuple of `cls`."""
    if not isinstance(items, list):
        raise ConfigError(f"{source}: {key} must be an array of tables ([[{key}]]), "
                          f"got {describe(items)}")  # fmt: skip
    out = []
    for i, item in enumerate(items):
        name = item.get("name") if isinstance(item, dict) else None
        label = f"{key} {name!r}" if isinstance(name, str) else f"{key} #{i + 1}"
        out.append(from_dict(cls, item, f"{source} [{label}]", required=("name",)))
    return tuple(out)


def _regions(table: Any, source: str) -> dict[int, BodyRegion]:
    """`[regions.<part>]` over the defaults: each part a human label name, each table's
    keys replacing the default's."""
    if not isinstance(table, dict):
        raise ConfigError(f"{source}: regions must be a table, got {describe(table)}")
    human = [labels.name_of(i) for i in labels.HUMAN_IDS]
    regions = dict(DEFAULT_REGIONS)
    for part, values in table.items():
        if part not in human:
            raise ConfigError(
                f"{source} [regions]: unknown part {part!r}{suggest(str(part), human)}; "
                f"known: {', '.join(human)}"
            )
        label_id = labels.by_name(part).id
        where = f"{source} [regions.{part}]"
        if not isinstance(values, dict):
            raise ConfigError(f"{where}: expected a table of settings, got {describe(values)}")
        region = from_dict(BodyRegion, {**asdict(regions[label_id]), **values}, where)
        if label_id == labels.HEAD and region.contact_allowed:
            raise ConfigError(
                f"{where}: contact_allowed must be false (ISO/TS 15066 Annex A allows no "
                "contact with the skull, forehead or face)"
            )
        regions[label_id] = region
    return regions
