"""The cell's decision from its newest inputs: labelled frames per camera, the robot's joint
state and the clock. Pure state, no I/O: the safety service feeds it and publishes what it
says (`topseg.services.live.safety`).

Per depth frame of a camera with its labels (`CellMonitor.frame`), or with an earlier frame's
labels carried onto it (`carry.carry_labels`: what appeared since is a person of unknown part):

1. Faults of the frame itself: no mount to place its pixels, a blinded camera (too little of
   the image has depth, or what it sees is at the lens), a camera that moved (the pixels
   labelled background no longer lie on the floor its mount predicts).
2. The robot's own pixels: with a fresh joint state the robot is rendered as this camera sees
   it, its silhouette grown by the state's age times the robot's fastest speed; pixels in it
   that are not in front of the rendered robot (a person's hand above a link is) are `robot`.
   With no fresh state the model's `robot` class stands and the robot is where those pixels
   are.
3. People: every human pixel in 3-D, in the cell frame; blobs smaller than
   `MIN_PERSON_AREA_M2` on the floor are dropped as noise. Their separation from the robot
   (its own shapes posed by the joint state, found through its bounding capsules; or its
   pixels' points), the zones they are in, and how much of each
   protective zone the camera does not see.

`CellMonitor.decision(now)` combines every camera's newest frame (the nearest person over all,
zones occupied by any, a protective zone's part unseen only when no camera sees it; a person's point
that another camera sees past, or sees as a surface that is no person or robot, counts for
neither: `seen_otherwise`) and decides with
the reaction time measured now: depth stamp of the oldest frame in use to this moment. A
camera whose labels in use arrived longer ago than the cell's deadline, or that sent none yet,
is a fault: `stop`; so is a camera whose driver or worker went away (its liveliness token was
dropped: a killed process's is as soon as its link closes), at once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import ndimage

from topseg.core import labels as label_table
from topseg.core.camera import KINECT_V1, TopViewMount, axis_depth
from topseg.core.formats.joint_states import JointState
from topseg.core.formats.wire import DepthFrame, LabelFrame
from topseg.core.resolution import decimate, decimated_mount
from topseg.core.safety.carry import carry_labels
from topseg.core.safety.cell import CameraPlacement, CellConfig
from topseg.core.safety.decision import Decision, decide
from topseg.core.safety.robot import CellRobot, padded_box
from topseg.core.safety.separation import (
    IS_HUMAN,
    Capsules,
    HumanPoints,
    Nearest,
    blob_areas_m2,
    cell_points,
    human_points,
    image_pixels,
    label4,
    nearest,
)
from topseg.core.safety.surface import RobotSurface
from topseg.core.safety.zones import (
    ZoneMasks,
    missing_depth,
    occupied_zones,
    unseen_by_all,
    unseen_fraction,
    zone_masks,
    zone_samples,
)
from topseg.core.sensors import depth_sigma_mm

#: The services whose liveliness tokens the monitor follows per camera: one that goes away (a
#: killed driver's token is dropped as soon as its link closes) stops the cell at once,
#: without waiting for the frames' deadline.
WATCHED_ROLES = ("driver", "worker")
#: Blobs labelled robot outside the silhouette of a robot placed by its joint state are a
#: person's body (`stray_robot_as_person`).
STRAY_ROBOT_AS_PERSON = True
#: ... when its heights above the floor span at least this (m): a person's do, standing,
#: kneeling or lying on their side; a table top the model read as robot is flat. On the
#: validation sequences (1800 frames) states equal: no span rule 97.6 %, 0.15 m 98.7 %,
#: 0.25 m 98.9 %, 0.4 m 99.0 %; never clear when the truth says stop with any (without
#: the stray rule at all: 99.0 % and once); 0.25 m keeps thinner people.
STRAY_MIN_SPAN_M = 0.25
#: The widest frame the monitor reads at its own resolution (pixels); wider ones are read at
#: every n-th pixel (a 640x480 Kinect's at 160x120: 2.2 cm of floor a pixel from 3 m). On the
#: validation sequences 160 decided as well as 320 (states 99.0 against 98.7 % equal,
#: separation error p95 8.3 against 8.2 cm) at about half the monitor's time.
WORKING_WIDTH = 160
#: A blob of human pixels smaller than this on the floor plane (m^2) is noise, not a person.
MIN_PERSON_AREA_M2 = 0.01
#: ... except a blob the image's edge cuts: its area in view says nothing of its size (a
#: person stepping in shows a sliver of legs first). On 24 validation sequences (3600
#: frames) clear-when-the-truth-says-stop 2 -> 1, states equal 98.61 -> 98.56 %.
BORDER_BLOBS_KEPT = True
#: A camera whose image has depth on less than this share of its pixels is blinded.
MIN_DEPTH_SHARE = 0.3
#: A camera whose median depth is nearer than this (m) has something on its lens.
MIN_MEDIAN_DEPTH_M = 0.5
#: Pixels labelled background whose height above the floor (m) is within this of 0 lie on
#: the floor; with fewer than MIN_FLOOR_SHARE of them the camera moved (or its mount is wrong).
FLOOR_TOLERANCE_M = 0.08
MIN_FLOOR_SHARE = 0.5
#: Fewer background pixels than this share of the image: too few to judge the floor by.
MIN_BACKGROUND_SHARE = 0.05
#: The silhouette's margin beyond the joint state's age times the robot's speed (m).
SILHOUETTE_MARGIN_M = 0.03
#: A pixel this much (m) nearer the camera than the rendered robot is in front of it.
IN_FRONT_M = 0.06
#: The robot is rendered at every this-many pixels of the working frame.
SILHOUETTE_STEP = 1
#: The widest (pixels) the rendered robot's depth is carried across the silhouette's margin.
MAX_REACH_PX = 60
#: Without a joint state the robot's pixels stand for it, thinned to one point per cell of
#: this side (m).
ROBOT_POINT_GRID_M = 0.03
#: With several cameras, a person's point one camera measured is dropped from the
#: separation and the zones when another camera sees that place and no person there
#: (`seen_otherwise`):
#: it sees past the point by more than this (m), or a surface within it that is not labelled
#: a person or the robot, anywhere in the 3x3 pixels around where the point falls.
CROSS_CHECK_M = 0.1
CROSS_CHECK = True


@dataclass
class CameraView:
    """What one camera's newest labelled frame said."""

    seq: int
    stamp_ns: int
    received_ns: int  # when the labels in use arrived (the deadline runs from it)
    faults: tuple[str, ...] = ()
    nearest: Nearest | None = None
    occupied: frozenset[str] = frozenset()
    unseen: dict[str, float] = field(default_factory=dict)
    robot_source: str = "none"  # "joints" | "labels" | "none"
    labels: np.ndarray | None = None  # the labels after the robot's own pixels
    #: what another camera's points are checked against (`seen_otherwise`), and what this
    #: camera's nearest pair is measured from
    sight: Sight | None = None
    people: HumanPoints | None = None
    robot_shapes: tuple[Capsules, RobotSurface | None] | None = None
    zone_masks: ZoneMasks | None = None


@dataclass(frozen=True)
class Sight:
    """What a camera saw, as another camera's points are checked against it and the zones
    are looked up in it: its working mount and placement, the nearest depth (m) within 3x3
    pixels of each pixel (inf where none has depth), whether a person or the robot is
    labelled within them, and the pixels without depth the robot's shadow does not explain."""

    mount: TopViewMount
    placement: CameraPlacement
    nearest_m: np.ndarray
    person_or_robot: np.ndarray
    missing: np.ndarray


@dataclass(frozen=True)
class Gathered:
    """Every camera's newest view at one moment, together: the nearest pair over them, the
    zones any of them sees a person in, each protective zone's unseen share (with several
    cameras `unseen_by_all`'s), the faults, the oldest view's depth stamp and the frame the
    nearest pair (or that) is from."""

    nearest: Nearest | None
    occupied: list[str]
    unseen: dict[str, float]
    faults: tuple[str, ...]
    oldest_stamp_ns: int | None
    frame: tuple[str, int] | None


@dataclass(frozen=True)
class CellDecision:
    """The cell's decision at one moment and what it rests on."""

    decision: Decision
    reaction_ms: float | None
    zones: dict[str, str]
    nearest: Nearest | None
    frame: tuple[str, int] | None


class CellMonitor:
    """The decision of one cell from its cameras' labelled frames and the robot's joints."""

    def __init__(self, cell: CellConfig, robot: CellRobot | None) -> None:
        self.cell = cell
        self.robot = robot
        self.placements = {c.name: c for c in cell.cameras}
        self.views: dict[str, CameraView] = {}
        self.joints: JointState | None = None
        self.joints_received_ns = 0
        self._zone_masks: dict[str, tuple[dict, ZoneMasks]] = {}
        # camera -> role -> instances whose liveliness token is there; a role whose last
        # instance went away is a fault until one is back (one never seen is none)
        self.alive: dict[str, dict[str, set[str]]] = {c.name: {} for c in cell.cameras}
        self.counts = {"frames": 0, "joint_states": 0, "joint_states_refused": 0}
        # camera -> (its view and the views it was checked against, what the check gave): a
        # decision taken again between frames checks nothing again
        self._checked: dict[str, tuple] = {}
        self._zone_samples: dict[str, np.ndarray] | None = None
        self._unseen: tuple[tuple[Sight, ...], dict[str, float]] | None = None  # for these views

    # ------------------------------------------------------------------ inputs

    def joint_state(self, state: JointState, received_ns: int) -> None:
        """Take the robot's newest joint state; ValueError (and counted) when it does not
        name the robot's joints (it is then not used)."""
        if self.robot is None:
            return
        missing = set(self.robot.joint_names) - set(state.name)
        if missing:
            self.counts["joint_states_refused"] += 1
            raise ValueError(
                f"joint state without {', '.join(sorted(missing)[:4])} of robot "
                f"{self.cell.robot.name}"
            )
        if self.joints is not None and state.stamp_ns < self.joints.stamp_ns:
            return  # an older state arriving late
        self.joints, self.joints_received_ns = state, received_ns
        self.counts["joint_states"] += 1

    def set_joints(self, state: JointState | None, received_ns: int = 0) -> None:
        """Hold `state` as the robot's joint state even when it is older than the one held
        (scoring or replaying frames out of order), or forget the state held (None); the
        checks and counts of `joint_state` apply."""
        self.joints = None
        if state is not None:
            self.joint_state(state, received_ns)

    def token(self, camera: str, role: str, instance: str, present: bool) -> None:
        """A liveliness token of `role` (driver, worker) for `camera` came or went."""
        if camera not in self.alive or role not in WATCHED_ROLES:
            return
        instances = self.alive[camera].setdefault(role, set())
        if present:
            instances.add(instance)
        else:
            instances.discard(instance)

    def gone(self, camera: str) -> list[str]:
        """The roles of `camera` whose every instance went away."""
        return [role for role, ids in sorted(self.alive.get(camera, {}).items()) if not ids]

    def decides_on_depth(self, now_ns: int) -> bool:
        """Whether a depth frame can be decided on before its own labels come, with an earlier
        frame's carried onto it: with the robot posed by a fresh joint state (its silhouette
        explains what its moving links cover) or in a cell without a robot."""
        return self.robot is None or self.fresh_joints(now_ns) is not None

    def joints_age_s(self, now_ns: int) -> float:
        """Seconds since the joint state in use was measured (its stamp); inf with none."""
        if self.joints is None:
            return math.inf
        return max(0.0, (now_ns - self.joints.stamp_ns) / 1e9)

    def fresh_joints(self, now_ns: int) -> dict[str, float] | None:
        """The joint values, when the state is younger than the robot's limit; else None."""
        if self.joints is None or self.robot is None:
            return None
        if self.joints_age_s(now_ns) * 1000.0 > self.cell.robot.joint_state_max_age_ms:
            return None
        values = dict(zip(self.joints.name, self.joints.position, strict=True))
        return {n: values[n] for n in self.robot.joint_names}

    def frame(
        self,
        camera: str,
        depth: DepthFrame,
        labels: LabelFrame,
        now_ns: int,
        labels_depth: DepthFrame | None = None,
        labels_received_ns: int | None = None,
    ) -> CameraView:
        """Judge one camera's depth frame with its labels and keep it as that camera's newest
        view. Labels of an earlier frame come with that frame's depth (`labels_depth`) and
        are carried onto this one (`carry.carry_labels`); `labels_received_ns` is when they
        arrived (default `now_ns`), which the deadline runs from."""
        placement = self.placements.get(camera)
        if placement is None:
            raise ValueError(f"camera {camera!r} is not in cell file {self.cell.source}")
        if depth.depth.shape != labels.labels.shape:
            raise ValueError(
                f"camera {camera}: labels {labels.labels.shape} do not match depth "
                f"{depth.depth.shape}"
            )
        self.counts["frames"] += 1
        received = now_ns if labels_received_ns is None else labels_received_ns
        view = CameraView(seq=depth.seq, stamp_ns=depth.stamp_ns, received_ns=received)
        mount = depth.mount or placement.mount
        if mount is None:
            view.faults = (f"{camera}: no mount (the frames carry none and the cell file "
                           "gives none): run topseg calibrate",)  # fmt: skip
            self.views[camera] = view
            return view
        factor = working_factor(mount)
        mount = decimated_mount(mount, factor)
        depth_mm = axis_depth(decimate(depth.depth, factor), mount)
        # its frames are read as axis depth from here on
        radial_mount, mount = mount, replace(mount, radial=False)
        lab = np.ascontiguousarray(labels.labels[::factor, ::factor])
        heights_m = floor_heights(depth_mm, mount)
        if labels_depth is not None:
            if labels_depth.depth.shape != depth.depth.shape:
                raise ValueError(
                    f"camera {camera}: the labels' depth {labels_depth.depth.shape} does not "
                    f"match the depth {depth.depth.shape}"
                )
            then_mm = axis_depth(decimate(labels_depth.depth, factor), radial_mount)
            pixels_per_m = 1000.0 * mount.intrinsics.fx / max(float(mount.height_mm), 1.0)
            noise_mm = depth_sigma_mm(then_mm, mount.sensor) * np.float32(mount.noise_scale)
            lab = carry_labels(lab, then_mm, depth_mm, heights_m, pixels_per_m, noise_mm)
        view.faults = camera_faults(camera, depth_mm, lab, heights_m)
        joints = self.fresh_joints(now_ns)
        capsules: Capsules | None = None
        surface: RobotSurface | None = None
        shadow = np.zeros(lab.shape, bool)
        if self.robot is not None and joints is not None:
            capsules = self.robot.capsules(joints)
            surface = self.robot.surface(joints)
            age_s = self.joints_age_s(now_ns)
            margin = SILHOUETTE_MARGIN_M + age_s * self.cell.robot.max_speed_mps
            robot_depth, grown = silhouette(self.robot, joints, mount, placement, margin)
            lab = robot_pixels(lab, depth_mm, robot_depth, grown, margin, mount)
            if STRAY_ROBOT_AS_PERSON:
                lab = stray_robot_as_person(lab, depth_mm, grown, mount, heights_m)
            shadow = grown
            view.robot_source = "joints"
        elif self.robot is not None:
            capsules = robot_points_as_capsules(depth_mm, lab, mount, placement)
            shadow = lab == label_table.ROBOT
            view.robot_source = "labels" if capsules is not None else "none"
        view.labels = lab
        if len(self.cell.cameras) > 1:  # only the cameras together read it
            view.sight = sight(depth_mm, lab, mount, placement, shadow)
        people = people_points(depth_mm, lab, mount, placement)
        view.people = people
        if capsules is not None:
            view.robot_shapes = (capsules, surface)
        if capsules is not None and people is not None:
            view.nearest = nearest(people, capsules, surface)
        elif self.robot is not None and people is not None:
            view.faults += (
                f"{camera}: a person in view and robot {self.cell.robot.name} nowhere known "
                "(no fresh joint state, no pixel labelled robot)",
            )
        masks = self._masks(camera, mount, placement)
        view.zone_masks = masks
        if people is not None:
            pixels = np.stack([people.rows, people.cols], axis=1)
            view.occupied = frozenset(occupied_zones(masks, people.points_m, pixels))
        view.unseen = unseen_fraction(masks, depth_mm, shadow)
        self.views[camera] = view
        return view

    def _masks(self, camera: str, mount: TopViewMount, placement: CameraPlacement) -> ZoneMasks:
        key = mount.to_dict()
        cached = self._zone_masks.get(camera)
        if cached is None or cached[0] != key:
            cached = (key, zone_masks(self.cell.zones, mount, placement))
            self._zone_masks[camera] = cached
        return cached[1]

    def warm_up(self) -> None:
        """Run every kernel once on a small made-up frame (numba compiles or loads them), so
        that the first real frame is decided in milliseconds; leaves this monitor as it was."""
        mount = TopViewMount(KINECT_V1.scaled_to(64, 48), 3000.0)
        depth = np.full((48, 64), 3000, np.uint16)
        lab = np.zeros((48, 64), np.uint8)
        lab[20:30, 20:30] = label_table.BODY
        lab[5:9, 5:9] = label_table.ROBOT
        camera = self.cell.cameras[0].name
        trial = CellMonitor(self.cell, self.robot)
        if self.robot is not None:
            rest = np.clip(0.0, self.robot.model.lower, self.robot.model.upper)
            trial.joint_state(JointState(1, self.robot.joint_names, tuple(map(float, rest))), 1)
        for joints in (True, False):
            if not joints:
                trial.set_joints(None)
            trial.frame(camera, DepthFrame(depth, mount.intrinsics, 0, 1, camera, mount),
                        LabelFrame(lab, 0, 1, camera), 1)  # fmt: skip
            trial.decision(1)

    # ------------------------------------------------------------------ the decision

    def gathered(self, now_ns: int) -> Gathered:
        """What every camera's newest view says now, together: a camera without a view
        younger than the deadline, or whose driver or worker went away, is a fault."""
        faults: list[str] = []
        deadline_ms = self.cell.deadline_ms
        nearest_all: Nearest | None = None
        occupied: set[str] = set()
        unseen: dict[str, float] = {}
        oldest_stamp: int | None = None
        frame = None
        ages_ms = {name: (now_ns - v.received_ns) / 1e6 for name, v in self.views.items()}
        fresh = [self.views[c.name] for c in self.cell.cameras
                 if ages_ms.get(c.name, math.inf) <= deadline_ms]  # fmt: skip
        sights = [v.sight for v in fresh if v.sight is not None]
        by_all = len(sights) > 1  # the zones looked up in every camera, not camera by camera
        for placement in self.cell.cameras:
            view = self.views.get(placement.name)
            for role in self.gone(placement.name):
                faults.append(f"{placement.name}: its {role} went away")
            if view is None:
                faults.append(f"{placement.name}: no labelled frame yet")
                continue
            age_ms = ages_ms[placement.name]
            if age_ms > deadline_ms:
                faults.append(
                    f"{placement.name}: no labelled frame for {age_ms:.0f} ms "
                    f"(deadline {deadline_ms:g} ms)"
                )
                continue
            faults.extend(view.faults)
            near, held = self._cross_checked(placement.name, view, fresh)
            occupied |= held
            if not by_all:
                for zone, share in view.unseen.items():
                    unseen[zone] = min(share, unseen.get(zone, math.inf))
            if near is not None and (
                nearest_all is None or near.distance_m < nearest_all.distance_m
            ):
                nearest_all, frame = near, (placement.name, view.seq)
            if oldest_stamp is None or view.stamp_ns < oldest_stamp:
                oldest_stamp = view.stamp_ns
                frame = frame or (placement.name, view.seq)
        if by_all:
            unseen = self._unseen_by_all(sights)
        return Gathered(nearest_all, sorted(occupied), unseen, tuple(faults), oldest_stamp, frame)

    def _unseen_by_all(self, sights: list[Sight]) -> dict[str, float]:
        """Per protective zone, the share of it no camera with a fresh view sees
        (`zones.unseen_by_all`; the zones' samples are drawn once)."""
        if self._zone_samples is None:
            self._zone_samples = {z.name: zone_samples(z) for z in self.cell.zones
                                  if z.kind == "protective"}  # fmt: skip
        cached = self._unseen
        if cached is not None and same_objects(cached[0], sights):
            return dict(cached[1])
        cameras = [(s.mount, s.placement, s.missing) for s in sights]
        unseen = {
            name: unseen_by_all(points, cameras) for name, points in self._zone_samples.items()
        }
        self._unseen = (tuple(sights), unseen)
        return unseen

    def _cross_checked(
        self, camera: str, view: CameraView, fresh: list[CameraView]
    ) -> tuple[Nearest | None, frozenset[str]]:
        """`cross_checked` of `camera`'s view against the other fresh views, once for each
        set of views (the views themselves, not copies, are what is compared)."""
        views = (view, *(v for v in fresh if v is not view))
        cached = self._checked.get(camera)
        if cached is None or not same_objects(cached[0], views):
            cached = (views, cross_checked(view, list(views[1:])))
            self._checked[camera] = cached
        return cached[1]

    def decision(self, now_ns: int) -> CellDecision:
        """The cell's decision now, over every camera's newest view."""
        seen = self.gathered(now_ns)
        oldest = seen.oldest_stamp_ns
        reaction_ms = None if oldest is None else max(0.0, (now_ns - oldest) / 1e6)
        reaction_s = math.inf if reaction_ms is None else reaction_ms / 1000.0
        decision = decide(
            self.cell, seen.nearest, seen.occupied, seen.unseen, reaction_s, seen.faults
        )
        zones = zone_states(self.cell, set(seen.occupied), seen.unseen, decision)
        return CellDecision(decision, reaction_ms, zones, seen.nearest, seen.frame)


# ---------------------------------------------------------------------------- pure steps


def same_objects(held, now) -> bool:
    """Whether two sequences hold the very same objects, in order (what the monitor's
    caches are keyed by: a camera's newest view is a new object with each frame)."""
    return len(held) == len(now) and all(a is b for a, b in zip(held, now, strict=True))


def sight(
    depth_mm: np.ndarray,
    lab: np.ndarray,
    mount: TopViewMount,
    placement: CameraPlacement,
    robot_shadow: np.ndarray | None = None,
) -> Sight:
    """A camera's frame as the other cameras read it (see `Sight`)."""
    metres = np.where(depth_mm > 0, depth_mm / 1000.0, np.inf)
    near = ndimage.minimum_filter(metres, size=3, mode="nearest")
    marked = ndimage.maximum_filter(IS_HUMAN[lab] | (lab == label_table.ROBOT), size=3,
                                    mode="nearest")  # fmt: skip
    return Sight(mount, placement, near, marked, missing_depth(depth_mm, robot_shadow))


def seen_otherwise(
    points_m: np.ndarray, other: Sight, margin_m: float = CROSS_CHECK_M
) -> np.ndarray:
    """(n,) whether camera `other` sees each cell-frame point's place without a person
    there: the point falls inside its image, and within the 3x3 pixels around it its
    nearest depth lies beyond the point by more than `margin_m` (it sees past it), or within
    `margin_m` of it with no pixel labelled a person or the robot (a surface that is not
    one). Nothing nearer than the point by more than `margin_m` (the point hidden from it)
    or outside its image says nothing."""
    inside, rows, cols, z = image_pixels(points_m, other.mount, other.placement)
    out = np.zeros(len(points_m), bool)
    seen_m = other.nearest_m[rows, cols]
    past = seen_m > z + margin_m
    other_surface = (np.abs(seen_m - z) <= margin_m) & ~other.person_or_robot[rows, cols]
    out[inside] = past | other_surface
    return out


def cross_checked(
    view: CameraView, others: list[CameraView]
) -> tuple[Nearest | None, frozenset[str]]:
    """`view`'s nearest pair and occupied zones, taken again without the person points a
    camera of `others` sees otherwise (`seen_otherwise`); its own when there is nothing to
    check against (CROSS_CHECK off, no other camera or no person)."""
    people = view.people
    checks = [v.sight for v in others if v.sight is not None]
    if not CROSS_CHECK or people is None or not checks:
        return view.nearest, view.occupied
    drop = np.zeros(len(people), bool)
    for other in checks:
        drop |= seen_otherwise(people.points_m, other)
    if not drop.any():
        return view.nearest, view.occupied
    if drop.all():
        return None, frozenset()
    keep = ~drop
    kept = replace(people, points_m=people.points_m[keep], part=people.part[keep],
                   rows=people.rows[keep], cols=people.cols[keep], blob=people.blob[keep])  # fmt: skip
    near = None if view.robot_shapes is None else nearest(kept, *view.robot_shapes)
    held = frozenset()
    if view.zone_masks is not None:
        pixels = np.stack([kept.rows, kept.cols], axis=1)
        held = frozenset(occupied_zones(view.zone_masks, kept.points_m, pixels))
    return near, held


def working_factor(mount: TopViewMount) -> int:
    """Every how many pixels the monitor reads a frame: the frame's own up to WORKING_WIDTH
    pixels across, every fourth pixel of every fourth row of a 640-wide frame."""
    return max(1, math.ceil(mount.intrinsics.width / WORKING_WIDTH))


def camera_faults(
    camera: str, depth_mm: np.ndarray, lab: np.ndarray, heights_m: np.ndarray
) -> tuple[str, ...]:
    """Why this frame cannot be trusted: a blinded camera or one that moved; () when none.
    `heights_m`: each pixel's height above the floor its mount predicts (`floor_heights`)."""
    valid = depth_mm > 0
    share = float(valid.mean())
    if share < MIN_DEPTH_SHARE:
        return (f"{camera}: blinded: {share:.0%} of the image has depth",)
    median_m = float(np.median(depth_mm[valid])) / 1000.0
    if median_m < MIN_MEDIAN_DEPTH_M:
        return (f"{camera}: blinded: something {median_m:.2f} m from the lens",)
    background = (lab == label_table.BACKGROUND) & valid
    if background.mean() < MIN_BACKGROUND_SHARE:
        return ()
    heights = heights_m[background]
    on_floor = float((np.abs(heights) <= FLOOR_TOLERANCE_M).mean())
    if on_floor < MIN_FLOOR_SHARE:
        off = float(np.median(heights))
        return (
            f"{camera}: moved: only {on_floor:.0%} of the background lies on the floor its "
            f"mount predicts (median {off:+.2f} m)",
        )
    return ()


def floor_heights(depth_mm: np.ndarray, mount: TopViewMount) -> np.ndarray:
    """(H, W) float64 height above the floor (m) of each pixel of axis depth `depth_mm`
    through `mount` (not radial); computed once a frame for every step that reads it."""
    return mount.height_map_mm(depth_mm).astype(np.float64) / 1000.0


def silhouette(
    robot: CellRobot, joints: dict[str, float], mount: TopViewMount, placement, margin_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """The robot's rendered depth and grown silhouette at the working resolution of `mount`,
    rendered at every SILHOUETTE_STEP-th pixel (ray casting the robot's meshes is most of the
    monitor's time) and spread back over the pixels between; the margin grows by the pixels
    that skips so the mask never comes out smaller."""
    step = SILHOUETTE_STEP
    coarse = decimated_mount(mount, step)
    pad = step * mount.floor_pixel_mm() / 1000.0
    depth, grown = robot.silhouette(joints, coarse, placement, margin_m + pad)
    h, w = mount.intrinsics.shape
    depth = np.repeat(np.repeat(depth, step, axis=0), step, axis=1)[:h, :w]
    grown = np.repeat(np.repeat(grown, step, axis=0), step, axis=1)[:h, :w]
    return depth, grown


def robot_pixels(
    lab: np.ndarray,
    depth_mm: np.ndarray,
    robot_depth_mm: np.ndarray,
    grown: np.ndarray,
    margin_m: float,
    mount: TopViewMount,
) -> np.ndarray:
    """The labels with the robot's own pixels made `robot`: inside the grown silhouette,
    every pixel with depth that is not background and not in front of the rendered robot
    (nearer the camera by more than IN_FRONT_M than the nearest rendered robot within the
    margin). A person's hand over a link is in front of it and keeps its label; the floor
    beside a link keeps background. All depths are along the optical axis (mm)."""
    out = lab.copy()
    robot = robot_depth_mm > 0
    if not robot.any():
        return out
    rendered = np.where(robot, robot_depth_mm.astype(np.float32), np.float32(np.inf))
    near_m = float(robot_depth_mm[robot].min()) / 1000.0
    k = mount.intrinsics
    reach_px = math.ceil(margin_m * max(k.fx, k.fy) / max(near_m, 0.1)) + 1
    reach = min(reach_px, MAX_REACH_PX)
    # the filter only matters under the grown silhouette: it runs on that box (and the reach)
    box = padded_box(grown, reach, reach)
    if box is None:
        return out
    nearest_robot = ndimage.minimum_filter(rendered[box], size=2 * reach + 1)
    in_front = depth_mm[box].astype(np.float32) < nearest_robot - np.float32(IN_FRONT_M * 1000.0)
    take = grown[box] & (depth_mm[box] > 0) & ~in_front & (lab[box] != label_table.BACKGROUND)
    out[box][take] = label_table.ROBOT
    return out


def stray_robot_as_person(
    lab: np.ndarray,
    depth_mm: np.ndarray,
    grown: np.ndarray,
    mount: TopViewMount,
    heights_m: np.ndarray,
) -> np.ndarray:
    """With the robot placed by its joint state, pixels labelled robot outside its grown
    silhouette are not the robot: blobs of them that cover at least MIN_PERSON_AREA_M2 and
    whose heights span STRAY_MIN_SPAN_M (a person standing close to the robot is read as
    robot more often than anything else is) are taken as a person's body; smaller or flat
    ones are left as they are."""
    stray = (lab == label_table.ROBOT) & ~grown & (depth_mm > 0)
    if not stray.any():
        return lab
    blobs, count = label4(stray)
    area = blob_areas_m2(blobs[stray], depth_mm[stray], mount.intrinsics, count)
    heights = heights_m[stray]
    top, bottom = np.full(count, -np.inf), np.full(count, np.inf)
    np.maximum.at(top, blobs[stray], heights)
    np.minimum.at(bottom, blobs[stray], heights)
    big = (area >= MIN_PERSON_AREA_M2) & (top - bottom >= STRAY_MIN_SPAN_M)
    if not big.any():
        return lab
    out = lab.copy()
    out[stray & big[np.maximum(blobs, 0)]] = label_table.BODY
    return out


def people_points(
    depth_mm: np.ndarray, lab: np.ndarray, mount: TopViewMount, placement: CameraPlacement
) -> HumanPoints | None:
    """The human pixels in 3-D (`separation.human_points`), blobs whose pixels cover less
    than MIN_PERSON_AREA_M2 of the floor-parallel plane at their depth left out unless the
    image's edge cuts them (BORDER_BLOBS_KEPT); None when no person is left."""
    if not IS_HUMAN[lab].any():
        return None
    people = human_points(depth_mm, lab, mount, placement)
    if not len(people):
        return None
    z_mm = depth_mm[people.rows, people.cols]
    area = blob_areas_m2(people.blob, z_mm, mount.intrinsics, people.blob_count)
    big = area >= MIN_PERSON_AREA_M2
    if BORDER_BLOBS_KEPT:
        h, w = lab.shape
        edge = (
            (people.rows == 0)
            | (people.rows == h - 1)
            | (people.cols == 0)
            | (people.cols == w - 1)
        )
        cut = np.zeros(people.blob_count, bool)
        cut[people.blob[edge]] = True
        big |= cut
    keep = big[people.blob]
    if keep.all():
        return people
    if not keep.any():
        return None
    return replace(
        people,
        points_m=people.points_m[keep],
        part=people.part[keep],
        rows=people.rows[keep],
        cols=people.cols[keep],
        blob=people.blob[keep],
    )


def robot_points_as_capsules(
    depth_mm: np.ndarray, lab: np.ndarray, mount: TopViewMount, placement: CameraPlacement
) -> Capsules | None:
    """The robot's labelled pixels as points (capsules of no length or radius), thinned to
    one per ROBOT_POINT_GRID_M cell; None when no pixel is labelled robot."""
    v, u = np.nonzero((lab == label_table.ROBOT) & (depth_mm > 0))
    if not len(v):
        return None
    points = cell_points(depth_mm, v, u, mount, placement)
    cells = np.floor(points / ROBOT_POINT_GRID_M).astype(np.int64)
    _, first = np.unique(cells, axis=0, return_index=True)
    points = points[np.sort(first)]
    return Capsules(points, points.copy(), np.zeros(len(points)), ("robot pixels",) * len(points))


def zone_states(
    cell: CellConfig, occupied: set[str], unseen: dict[str, float], decision: Decision
) -> dict[str, str]:
    """Each zone's state for the viewers: `stop` when a protective zone is occupied or
    unseen, `warning` when a warning zone is occupied, else `clear`; every zone `stop` when
    the cell decided `stop` for a fault."""
    out = {}
    for zone in cell.zones:
        state = "clear"
        if zone.name in occupied:
            state = "stop" if zone.kind == "protective" else "warning"
        if zone.kind == "protective" and unseen.get(zone.name, 0.0) > cell.max_unseen_fraction:
            state = "stop"
        out[zone.name] = state
    return out
