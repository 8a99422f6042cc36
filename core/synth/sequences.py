"""Rendered robot-cell sequences whose truth is known: a robot working through a task, people
walking up to it, reaching in and leaving, seen by a ceiling depth camera.

    seq = CellSequence(CellSequenceConfig(duration_s=20, fps=15), seed=3)
    for frame in seq.frames():   # depth (noisy mm), labels (exact), joints, separation truth
        ...

The cell frame is the render's world frame (`camera.TopViewMount`: x, y on the floor, z up).
One camera hangs over its origin (placement (0, 0, yaw 0)); two hang side by side, the same
camera twice, `camera_positions` apart along y so that their views abut at head height
(`HEAD_HEIGHT_M`) and overlap below it: the floor and the cell at the robot are seen from two
sides, and together they see more of the floor at head height.

The robot (a catalogue name of `robots`, default the Panda) stands on a pedestal near the
middle of the view beside a worktable with parts on it. Its task is a loop of joint waypoints
drawn within its joint limits: a raised home pose, then two or three poses with its tool over
the table (clear of the table's top and the parts on it), then home again; between waypoints
the joints follow a minimum-jerk profile timed so that no joint turns faster than
MAX_JOINT_SPEED, with a short dwell at each.

Each person (1 or 2) walks in from beyond the cameras' view to a spot beside the table, facing
it, at 1.0-1.6 m/s (the walk clip's phase advancing with the distance walked, feet on the
floor), stands, reaches one hand over the table towards the robot's working area (the arm
passes overhead at times), holds, lowers the hand and walks out beyond the opposite edge.
Off stage (before coming in, after leaving) a person is not in the scene.

Per frame: depth (uint16 mm, the sensor's noise as the Synthesizer applies it), exact labels
(NO_DEPTH where the noise left no depth), the joint state at the frame's time, and per person
on stage the truth separation (`body_distance`): the least distance between the person's
body and the robot's links (the pedestal is not part of the robot for this; the links are
what counts), its part and link and the two points. Everything is a pure function of the
config and the seed.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field, replace

import numpy as np

from topseg.core import labels
from topseg.core.camera import TopViewMount
from topseg.core.errors import TopsegError
from topseg.core.sensors import get_sensor
from topseg.core.synth import (
    body_distance,
    cell_objects,
    cell_relations,
    furniture,
    humanoid,
    robots,
)
from topseg.core.synth.relations import stand_z
from topseg.core.synth.rooms import view_rect
from topseg.core.synth.scene import PlacedHuman, PlacedObject, Scene
from topseg.core.synth.synthesis import SynthesisConfig, Synthesizer

#: fastest any joint of the task turns (rad/s; m/s for a prismatic one)
MAX_JOINT_SPEED = 0.9
#: the longest a task loop may take (s): people wait for the robot to come by
MAX_TASK_PERIOD_S = 10.0
#: the room the sequence plays in: the one without walls, so people come from any edge
ROOM = "industrial_workspace"
#: a person starts and ends this far (m) beyond the floor the image shows
OFFSTAGE_M = 0.6
#: walking speeds drawn (m/s)
WALK_SPEED = (1.0, 1.6)
#: what one cycle of the walk clip covers (m) per metre of the walker's height
WALK_CYCLE_PER_HEIGHT = 1.23859 / 1.598961
PEDESTAL_HALF_M = 0.15
#: two cameras' views abut at this height (m): a standing person's head
HEAD_HEIGHT_M = 1.8


@dataclass
class CellSequenceConfig:
    """What a sequence shows: its length and rate, the camera (sensor, height, image size),
    the robot and its pedestal, how many people, and the noise ("sensor": the sensor's own)."""

    duration_s: float = 20.0
    fps: float = 30.0
    sensor: str = "kinect_v1"
    height_m: float = 3.0
    size: tuple[int, int] | None = (320, 240)
    robot: str = "panda"
    pedestal_m: float = 0.8
    people: int = 2
    noise: str = "sensor"
    cell: str = "default"
    camera: str = "cam0"
    cameras: int = 1

    def __post_init__(self) -> None:
        if not 0 < self.duration_s <= 3600:
            raise TopsegError(f"duration must be in (0, 3600] s, got {self.duration_s}")
        if not 0 < self.fps <= 120:
            raise TopsegError(f"fps must be in (0, 120], got {self.fps}")
        if self.cameras not in (1, 2):
            raise TopsegError(f"a cell sequence has 1 or 2 cameras, got {self.cameras}")
        if self.people not in (1, 2):
            raise TopsegError(f"a cell sequence has 1 or 2 people, got {self.people}")
        if not 2.0 <= self.height_m <= 6.0:
            raise TopsegError(f"camera height must be within 2..6 m, got {self.height_m}")
        if not 0.2 <= self.pedestal_m <= 1.2:
            raise TopsegError(f"pedestal height must be within 0.2..1.2 m, got {self.pedestal_m}")
        get_sensor(self.sensor)  # one line naming the known sensors

    def mount(self) -> TopViewMount:
        """The camera: the sensor's optics (scaled to `size`), `height_m` straight down."""
        k = get_sensor(self.sensor).intrinsics
        if self.size is not None:
            k = k.scaled_to(*self.size)
        return TopViewMount(k, round(1000.0 * self.height_m, 1), 0.0, 0.0, self.sensor)

    def camera_names(self) -> tuple[str, ...]:
        """The cameras' names on the wire: `camera`, then `camera`-2."""
        return (self.camera, *(f"{self.camera}-{k + 1}" for k in range(1, self.cameras)))

    def camera_positions(self) -> tuple[tuple[float, float], ...]:
        """Each camera's (x, y) in the cell frame (m): the origin for one; for two, either
        side of it along y, as far apart as one camera's view is deep at HEAD_HEIGHT_M."""
        if self.cameras == 1:
            return ((0.0, 0.0),)
        k = self.mount().intrinsics
        apart = (self.height_m - HEAD_HEIGHT_M) * k.height / k.fy
        return ((0.0, -apart / 2), (0.0, apart / 2))

    @property
    def frame_count(self) -> int:
        """How many frames the sequence has."""
        return max(1, round(self.duration_s * self.fps))


# --- the robot's task ------------------------------------------------------------------------


def min_jerk(s: float) -> float:
    """The minimum-jerk profile 10 s^3 - 15 s^4 + 6 s^5 on [0, 1] (zero speed and acceleration
    at both ends; peak speed 1.875 at s = 0.5)."""
    s = min(max(s, 0.0), 1.0)
    return s * s * s * (10 - 15 * s + 6 * s * s)


@dataclass
class RobotTask:
    """Joint waypoints (k, joints) looped with a dwell at each: `times` are when each move
    starts, `moves` how long it takes, `period` the whole loop."""

    names: tuple[str, ...]
    waypoints: np.ndarray
    dwell_s: float
    moves: np.ndarray = field(init=False)
    period: float = field(init=False)

    def __post_init__(self) -> None:
        nxt = np.roll(self.waypoints, -1, axis=0)
        span = np.abs(nxt - self.waypoints).max(axis=1)
        self.moves = np.maximum(1.0, 1.875 * span / MAX_JOINT_SPEED)
        self.period = float(np.sum(self.moves + self.dwell_s))

    def at(self, t: float) -> np.ndarray:
        """The joint positions at time `t` (s)."""
        t = t % self.period
        for i, move in enumerate(self.moves):
            if t < self.dwell_s:
                return self.waypoints[i].copy()
            t -= self.dwell_s
            if t < move:
                a, b = self.waypoints[i], self.waypoints[(i + 1) % len(self.waypoints)]
                return a + min_jerk(t / move) * (b - a)
            t -= move
        return self.waypoints[0].copy()

    def joints(self, t: float) -> dict[str, float]:
        """`at(t)` as a joint name -> value dict."""
        return {n: float(v) for n, v in zip(self.names, self.at(t), strict=True)}


# --- people ----------------------------------------------------------------------------------


@dataclass
class Visit:
    """One person's visit: height, walking speed, the path in (start -> spot) and out (spot ->
    end), the heading at the spot, the reach target, and the times (s) of each phase: enter,
    arrive, reach start, hold start, lower start, leave, gone."""

    height: float
    speed: float
    start: np.ndarray
    spot: np.ndarray
    end: np.ndarray
    facing: float
    target: np.ndarray
    side: str
    times: tuple[float, ...]
    standing: humanoid.Pose
    #: (enter time, pause before reaching, hold, linger before leaving), s
    plan: tuple[float, ...] = ()


def _blend(a: humanoid.Pose, b: humanoid.Pose, t: float) -> humanoid.Pose:
    """Pose a (t = 0) to b (t = 1): spherical joints and tilt by slerp, angles linearly."""
    t = min(max(t, 0.0), 1.0)
    joints = {}
    for name, qa in a.joints.items():
        qb = b.joints[name]
        joints[name] = (
            list(humanoid.slerp(qa, qb, t)) if len(qa) == 4 else [(1 - t) * qa[0] + t * qb[0]]
        )
    return humanoid.Pose(joints, tuple(humanoid.slerp(a.tilt, b.tilt, t)))


def _turn(a: float, b: float, t: float) -> float:
    """Heading a (t = 0) to b (t = 1) the short way round."""
    d = (b - a + np.pi) % (2 * np.pi) - np.pi
    return a + min(max(t, 0.0), 1.0) * d


BLEND_S = 0.4  # walking <-> standing
TURN_S = 0.6
REACH_S = 1.0


def person_at(visit: Visit, t: float) -> PlacedHuman | None:
    """The person of `visit` at time `t`, or None off stage."""
    enter, arrive, reach0, _, lower, leave, gone = visit.times
    if t < enter or t >= gone:
        return None
    scale = humanoid.scale_for_height(visit.height)
    cycle = WALK_CYCLE_PER_HEIGHT * visit.height
    path_in = visit.spot - visit.start
    path_out = visit.end - visit.spot
    heading_in = math.atan2(path_in[1], path_in[0])
    heading_out = math.atan2(path_out[1], path_out[0])
    if t < arrive:  # walking in
        walked = visit.speed * (t - enter)
        xy = visit.start + path_in * walked / np.linalg.norm(path_in)
        pose = humanoid.clip_pose("walk", (walked / cycle) % 1.0)
        if arrive - t < BLEND_S:
            pose = _blend(pose, visit.standing, 1 - (arrive - t) / BLEND_S)
        yaw = heading_in
    elif t < leave:  # at the spot: turn, reach, hold, lower
        xy = visit.spot
        yaw = _turn(heading_in, visit.facing, (t - arrive) / TURN_S)
        if t > lower + REACH_S:
            yaw = _turn(visit.facing, heading_out, (t - lower - REACH_S) / TURN_S)
        pose = visit.standing.copy()
        share = (
            min_jerk((t - reach0) / REACH_S) if t < lower else 1 - min_jerk((t - lower) / REACH_S)
        )
        if share > 0:
            pose = _reaching(visit, pose, scale, xy, yaw, share)
    else:  # walking out
        walked = visit.speed * (t - leave)
        xy = visit.spot + path_out * walked / np.linalg.norm(path_out)
        pose = humanoid.clip_pose("walk", (walked / cycle) % 1.0)
        if t - leave < BLEND_S:
            pose = _blend(visit.standing, pose, (t - leave) / BLEND_S)
        yaw = heading_out
    z = stand_z(pose, scale)
    return PlacedHuman(visit.height, "walking", pose, {}, float(xy[0]), float(xy[1]), z, float(yaw))


def _reaching(visit: Visit, pose, scale, xy, yaw, share: float) -> humanoid.Pose:
    """The standing pose with one hand moved `share` of the way from where it hangs to the
    target (inverse kinematics; a target out of reach leaves the arm hanging)."""
    base = (float(xy[0]), float(xy[1]), stand_z(pose, scale))
    q = humanoid.base_quat(pose.tilt, yaw)
    rest = humanoid.wrist_position(pose, scale, base, q, visit.side)
    goal = rest + share * (visit.target - rest)
    reached = pose.copy()
    return reached if humanoid.reach(reached, scale, base, q, visit.side, goal) else pose


# --- the sequence ----------------------------------------------------------------------------


@dataclass
class PersonTruth:
    """One person's truth separation from the robot in a frame (cell frame, m)."""

    id: int
    distance_m: float
    part: int
    link: str
    point_m: np.ndarray
    link_point_m: np.ndarray
    in_view: bool

    def to_dict(self) -> dict:
        """The msgpack map the safety truth message carries per person."""
        return {
            "id": self.id,
            "distance_m": float(self.distance_m),
            "part": labels.name_of(self.part),
            "link": self.link,
            "point_m": [float(v) for v in self.point_m],
            "link_point_m": [float(v) for v in self.link_point_m],
            "in_view": bool(self.in_view),
        }


@dataclass
class CellFrame:
    """One frame: index, time (s from the start), the first camera's depth (uint16 mm) and
    labels (uint8), the robot's joint names and positions, the truth per person on stage, and
    the other cameras' (depth, labels)."""

    index: int
    time_s: float
    depth: np.ndarray
    labels: np.ndarray
    joint_names: tuple[str, ...]
    joint_positions: np.ndarray
    persons: list[PersonTruth]
    others: tuple[tuple[np.ndarray, np.ndarray], ...] = ()

    def views(self) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
        """Every camera's (depth, labels), in the order of `camera_names`."""
        return ((self.depth, self.labels), *self.others)


class CellSequence:
    """A cell sequence drawn from `seed` (see the module doc): `frames()` renders it."""

    def __init__(self, config: CellSequenceConfig | None = None, seed: int = 0) -> None:
        self.config = config or CellSequenceConfig()
        self.seed = int(seed)
        self.mount = self.config.mount()
        self.positions = self.config.camera_positions()
        self.model = robots.robot_model(self.config.robot)
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, 0]))
        self.robot, self.table, self.parts, self.task = _draw_cell(rng, self.config, self.model)
        self.visits = [_draw_visit(rng, self, i) for i in range(self.config.people)]
        self._centre()
        paths = np.random.default_rng(np.random.SeedSequence([self.seed, 2]))
        for visit in self.visits:
            _draw_path(
                paths, visit, self.table, self.stage(), self.nearest_time(visit.target),
                self.task.period,
            )  # fmt: skip

    def stage(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """(lo, hi) cell-frame corners (m) of the floor some camera shows (`view_rect`'s,
        over every camera)."""
        lo, hi = view_rect(self.mount)
        xs = [x for x, _ in self.positions]
        ys = [y for _, y in self.positions]
        return (lo[0] + min(xs), lo[1] + min(ys)), (hi[0] + max(xs), hi[1] + max(ys))

    def nearest_time(self, point: np.ndarray, samples: int = 48) -> float:
        """When (s, within the first task loop) the robot's links come nearest `point`."""
        times = np.arange(samples) * self.task.period / samples
        d = [
            body_distance.closest_points(self.robot_surface(self.robot_at(t)), point[None])[0][0]
            for t in times
        ]
        return float(times[int(np.argmin(d))])

    def _centre(self) -> None:
        """Move the cell so that the robot's base and the people's spots centre under the
        camera: what stands near the robot stays in view up to head height."""
        spots = [v.spot for v in self.visits]
        shift = -np.mean([np.array([self.robot.x, self.robot.y]), *spots], axis=0)
        self.robot.x, self.robot.y = (
            float(v) for v in np.array([self.robot.x, self.robot.y]) + shift
        )
        for item in (self.table, *self.parts):
            item.x, item.y = (float(v) for v in np.array([item.x, item.y]) + shift)
        for visit in self.visits:
            visit.spot = visit.spot + shift
            visit.target = visit.target + np.r_[shift, 0.0]

    # the robot

    def robot_at(self, t: float) -> robots.PlacedRobot:
        """The placed robot with its joints at time `t`."""
        r = self.robot
        return robots.PlacedRobot(
            r.id, r.name, r.x, r.y, r.yaw, r.mount, r.base_z, self.task.joints(t), r.pedestal
        )

    def robot_surface(self, robot: robots.PlacedRobot) -> body_distance.RobotSurface:
        """The posed robot's links (no pedestal) as a surface for separations."""
        prims, tris = self.model.link_geometry(robot.joints, robot.base_pos(), robot.base_quat())
        links, tri_link, prim_link = self.model.shape_links()
        return body_distance.robot_surface(prims, prim_link, tris, tri_link, links)

    def people_at(self, t: float) -> list[tuple[int, PlacedHuman]]:
        """(person id, person) of everyone on stage at `t`."""
        out = []
        for i, visit in enumerate(self.visits):
            human = person_at(visit, t)
            if human is not None:
                out.append((i, human))
        return out

    def scene_at(self, t: float) -> Scene:
        """The scene description of time `t`."""
        lo, hi = self.stage()
        people = [h for _, h in self.people_at(t)]
        return Scene(
            "cell", ROOM, lo, hi, 0.0, 0.0, [self.table, *self.parts],
            people[0] if people else None, [], mount=self.mount,
            robots=[self.robot_at(t)], extra_humans=people[1:],
        )  # fmt: skip

    def truth_at(self, t: float, robot: robots.PlacedRobot | None = None) -> list[PersonTruth]:
        """The truth separation of everyone on stage at `t`."""
        surface = self.robot_surface(robot or self.robot_at(t))
        out = []
        for i, human in self.people_at(t):
            prims = human.primitives()
            sep = body_distance.body_separation(surface, prims)
            in_view = any(
                _in_view(self.mount, prims.center - np.array([x, y, 0.0]))
                for x, y in self.positions
            )
            out.append(PersonTruth(i, sep.distance_m, sep.part, sep.link, sep.point_m,
                                   sep.link_point_m, in_view))  # fmt: skip
        return out

    def frames(self, start: int = 0, stop: int | None = None):
        """Render frames `start` .. `stop` (default: all) as `CellFrame`s."""
        stop = self.config.frame_count if stop is None else stop
        synth_config = SynthesisConfig(noise=self.config.noise, camera=self.mount, seed=self.seed)
        with Synthesizer(synth_config, warm=False) as synth:
            for index in range(start, stop):
                t = index / self.config.fps
                robot = self.robot_at(t)
                scene = self.scene_at(t)
                noise_rng = np.random.default_rng(np.random.SeedSequence([self.seed, 1, index]))
                frame = synth.render_scene(self.seen_from(scene, 0), noise_rng)
                others = []
                for k in range(1, len(self.positions)):
                    rng_k = np.random.default_rng(np.random.SeedSequence([self.seed, 1, index, k]))
                    other = synth.render_scene(self.seen_from(scene, k), rng_k)
                    others.append((other.depth, other.labels))
                yield CellFrame(
                    index, t, frame.depth, frame.labels, self.task.names,
                    self.task.at(t), self.truth_at(t, robot), tuple(others),
                )  # fmt: skip

    def seen_from(self, scene: Scene, camera: int) -> Scene:
        """`scene` in camera `camera`'s world frame (origin on the floor under it): every
        item moved by minus the camera's position; the scene itself for a camera at the
        origin."""
        x, y = self.positions[camera]
        if x == 0.0 and y == 0.0:
            return scene
        return shifted_scene(scene, -x, -y)

    def max_link_speed(self, samples: int = 400) -> float:
        """The fastest any point of the robot's links moves over one task loop (m/s), from
        its meshes' hull corners sampled `samples` times."""
        r = self.robot
        dt = self.task.period / samples
        pts = [
            self.model.hull_points(self.task.joints(k * dt), r.base_pos(), r.base_quat())
            for k in range(samples + 1)
        ]
        return float(
            max(np.linalg.norm(b - a, axis=1).max() for a, b in itertools.pairwise(pts)) / dt
        )

    def reach_radius(self) -> float:
        """The farthest (m, on the floor) any link gets from the robot's base over the task."""
        r = self.robot
        base = np.array([r.x, r.y])
        far = 0.0
        for k in range(60):
            pts = self.model.hull_points(
                self.task.joints(k * self.task.period / 60), r.base_pos(), r.base_quat()
            )
            far = max(far, float(np.linalg.norm(pts[:, :2] - base, axis=1).max()))
        return far


def shifted_scene(scene: Scene, dx: float, dy: float) -> Scene:
    """A copy of `scene` with its floor, bounds, items, robots and people moved by (dx, dy)
    (m) on the floor."""

    def moved(item):
        return replace(item, x=item.x + dx, y=item.y + dy)

    def corner(c):
        return None if c is None else (c[0] + dx, c[1] + dy)

    return replace(
        scene,
        floor_lo=corner(scene.floor_lo), floor_hi=corner(scene.floor_hi),
        bounds_lo=corner(scene.bounds_lo), bounds_hi=corner(scene.bounds_hi),
        objects=[moved(o) for o in scene.objects],
        human=None if scene.human is None else moved(scene.human),
        robots=[moved(r) for r in scene.robots],
        extra_humans=[moved(h) for h in scene.extra_humans],
        mesh_objects=[moved(m) for m in scene.mesh_objects],
    )  # fmt: skip


def _in_view(mount: TopViewMount, points: np.ndarray) -> bool:
    """Whether any of the world points projects into the image."""
    k = mount.intrinsics
    rot = np.asarray(mount.rotation_world_to_camera(), np.float64)
    cam = (np.asarray(points, np.float64) - np.asarray(mount.centre_world_m())) @ rot.T
    z = cam[:, 2]
    u = cam[:, 0] / z * k.fx + k.cx
    v = cam[:, 1] / z * k.fy + k.cy
    inside = (z > 0) & (u >= -0.5) & (u < k.width - 0.5) & (v >= -0.5) & (v < k.height - 0.5)
    return bool(inside.any())


# --- drawing a cell --------------------------------------------------------------------------


TABLE_KIND = "table_rect"
TABLE_HEIGHT_M = (0.72, 0.78)
TOOL_ABOVE_TABLE_M = (0.3, 0.55)
#: parts on the table: low ones, so the arm passes over them
PART_KINDS = ("parts_tray", "part_block")
PART_MAX_M = 0.1
#: the arm's links stay this far (m) above the table's parts and the floor
CLEARANCE_M = 0.04
#: the worktable (variant 3: 1.0 m x 0.6 m) stands with its short side towards the robot,
#: its near edge at least this far (m) from the robot's base
TABLE_VARIANT = 3
TABLE_DEPTH_M = 0.6
TABLE_NEAR_EDGE_M = 0.3
#: a person stands this far (m, body centre) from the table's edge, reaches a hand this far
#: in over the table (or as far as the arm goes) and this high above its top
SPOT_FROM_EDGE_M = 0.22
REACH_INTO_M = 0.3
HAND_ABOVE_TABLE_M = 0.2


def _draw_cell(rng, config: CellSequenceConfig, model: robots.RobotModel):
    """The robot on its pedestal, the table beside it with parts, and the robot's task;
    TopsegError when no task fits within the tries."""
    for _ in range(40):
        robot = robots.PlacedRobot(
            0, model.name, 0.0, 0.0, float(rng.uniform(0, 2 * np.pi)), "pedestal",
            float(config.pedestal_m), {},
            (PEDESTAL_HALF_M, 1.0),
        )  # fmt: skip
        height = furniture.quantize_height(float(rng.uniform(*TABLE_HEIGHT_M)))
        found = _draw_task(rng, robot, model, height)
        if found is None:
            continue
        task, table_xy, table_yaw = found
        table = PlacedObject(1, TABLE_KIND, TABLE_VARIANT, height, *table_xy, 0.0, table_yaw)
        robot.joints = task.joints(0.0)
        parts = _draw_parts(rng, table)
        if _task_clear(robot, task, table):
            return robot, table, parts, task
    raise TopsegError(f"no task with the tool over a table found for robot {model.name}")


def _draw_task(rng, robot, model, table_height):
    """(RobotTask, table centre, table yaw) with 2-3 work poses over a table beside the
    robot and a raised home pose, or None."""
    lo, hi = model.lower, model.upper
    mid = (lo + hi) / 2
    span = hi - lo
    candidates = []
    for _ in range(300):
        q = np.clip(mid + rng.uniform(-0.4, 0.4, len(lo)) * span, lo, hi)
        joints = dict(zip(model.joint_names, q, strict=True))
        tool = model.tool_position(joints, robot.base_pos(), robot.base_quat())
        candidates.append((q, tool))
    base = np.array([robot.x, robot.y])
    reach = max(np.linalg.norm(t[:2] - base) for _, t in candidates)
    z_lo, z_hi = (table_height + v for v in TOOL_ABOVE_TABLE_M)
    work = [
        (q, t) for q, t in candidates
        if z_lo <= t[2] <= z_hi and 0.4 * reach <= np.linalg.norm(t[:2] - base) <= 0.85 * reach
    ]  # fmt: skip
    if len(work) < 3:
        return None
    first = work[int(rng.integers(len(work)))]
    heading = math.atan2(*(first[1][:2] - base)[::-1])
    near = [
        w for w in work
        if np.linalg.norm(w[1][:2] - first[1][:2]) < 0.3 and w is not first
    ]  # fmt: skip
    raised = [c for c in candidates if c[1][2] > z_hi + 0.1]
    if not near or not raised:
        return None
    near.sort(key=lambda w: np.abs(w[0] - first[0]).max())
    picks = [first, *near[: int(rng.integers(1, 3))]]
    home = min(raised, key=lambda c: np.abs(c[0] - first[0]).max())
    centre = np.mean([t[:2] for _, t in picks], axis=0)
    out = centre - base
    dist = float(np.linalg.norm(out))
    centre = base + out / dist * max(dist, TABLE_NEAR_EDGE_M + TABLE_DEPTH_M / 2)
    task = RobotTask(
        model.joint_names, np.array([home[0]] + [q for q, _ in picks]), float(rng.uniform(0.4, 0.8))
    )
    if task.period > MAX_TASK_PERIOD_S:
        return None
    return task, (float(centre[0]), float(centre[1])), heading + np.pi / 2


def _task_clear(robot, task: RobotTask, table: PlacedObject) -> bool:
    """The arm clears the floor, its pedestal and the table (parts included) throughout."""
    for k in range(48):
        posed = robots.PlacedRobot(
            robot.id, robot.name, robot.x, robot.y, robot.yaw, robot.mount, robot.base_z,
            task.joints(k * task.period / 48), robot.pedestal,
        )  # fmt: skip
        pts = posed.model().hull_points(posed.joints, posed.base_pos(), posed.base_quat())
        if pts[:, 2].min() < CLEARANCE_M:
            return False
        over = cell_relations.points_in_convex(pts[:, :2], table.footprint())
        if np.any(pts[over, 2] < table.height + PART_MAX_M + CLEARANCE_M):
            return False
    return True


def _draw_parts(rng, table: PlacedObject) -> list[PlacedObject]:
    """Two or three parts and tools on the table."""
    parts = []
    for i in range(int(rng.integers(2, 4))):
        kind = PART_KINDS[int(rng.integers(len(PART_KINDS)))]
        lo, hi = cell_objects.HEIGHT_RANGE_M[kind]
        part = PlacedObject(
            2 + i, kind, int(rng.integers(furniture.N_VARIANTS)),
            furniture.quantize_height(float(rng.uniform(lo, min(hi, PART_MAX_M)))), 0.0, 0.0,
        )  # fmt: skip
        if cell_relations.place_on_table(rng, table, part) is not None:
            parts.append(part)
    return parts


def _draw_visit(rng, seq: CellSequence, index: int) -> Visit:
    """Person `index`'s visit: a spot at a side of the table away from the robot, facing
    it, a hand target over the table within the arm's reach, and the times of each phase
    (its path in and out is `_draw_path`'s)."""
    table, robot = seq.table, seq.robot
    tm = table.model()
    height = humanoid.quantize_height(float(rng.uniform(1.60, 1.90)))
    away = table.to_local(np.array([robot.x, robot.y]))
    sides = [(1.0, 0.0), (0.0, 1.0), (0.0, -1.0), (-1.0, 0.0)]
    sides = sorted(sides, key=lambda s: s[0] * away[0] + s[1] * away[1])[:3]
    first = int(rng.integers(3))
    side = np.array(sides[(first + index) % 3])
    half = np.array([tm.size_x, tm.size_y]) / 2
    edge = float(np.abs(side) @ half)
    along = float(rng.uniform(-0.2, 0.2)) * float(np.abs(side[::-1]) @ half)
    local = side * (edge + SPOT_FROM_EDGE_M) + side[::-1] * along
    spot = table.to_world(local)
    facing = math.atan2(*(table.to_world(local - side) - spot)[::-1])
    standing = humanoid.preset_pose("standing", rng)
    hand = "right" if rng.random() < 0.6 else "left"
    target = _reachable_target(table, side, along, edge, spot, facing, standing, height, hand)
    speed = float(rng.uniform(*WALK_SPEED))
    enter = float(rng.uniform(0.3, 1.2)) + index * float(rng.uniform(2.5, 4.5))
    hold = float(rng.uniform(1.5, 3.0))
    pause = float(rng.uniform(0.2, 0.8))
    linger = float(rng.uniform(0.1, 0.5))
    visit = Visit(height, speed, spot, spot, spot, facing, target, hand, (), standing)
    visit.plan = (enter, pause, hold, linger)
    return visit


def _reachable_target(table, side, along, edge, spot, facing, standing, height, hand):
    """The hand's target over the table: REACH_INTO_M in from the person's edge, drawn back
    towards the person until the arm reaches it."""
    scale = humanoid.scale_for_height(height)
    base = (float(spot[0]), float(spot[1]), stand_z(standing, scale))
    q = humanoid.base_quat(standing.tilt, facing)
    z = table.height + HAND_ABOVE_TABLE_M
    for inward in np.arange(REACH_INTO_M, -0.3, -0.03):
        target = np.array([*table.to_world(side * (edge - inward) + side[::-1] * along), z])
        if humanoid.reach(standing.copy(), scale, base, q, hand, target):
            return target
    return humanoid.wrist_position(standing, scale, base, q, hand)


def _draw_path(rng, visit: Visit, table, stage, nearest: float, period: float):
    """The visit's way in from beyond the floor the cameras show (`stage`: its (lo, hi)
    corners) and out again (roughly away from the table, so the path does not cross it) and
    its phase times: the hand is held out while the robot passes nearest its target (at
    `nearest` s into each task loop of `period` s)."""
    lo, hi = stage
    away = visit.spot - np.array([table.x, table.y])
    visit.start = _offstage(rng, visit.spot, away, lo, hi)
    visit.end = _offstage(rng, visit.spot, away, lo, hi)
    enter, pause, hold, linger = visit.plan
    arrive = enter + float(np.linalg.norm(visit.spot - visit.start)) / visit.speed
    # reach so that the hand is out while the robot passes nearest the hand's target
    held_from = arrive + TURN_S + pause + REACH_S
    k = math.ceil((held_from - nearest) / period)
    reach0 = max(held_from, nearest + k * period - 0.5 * hold) - REACH_S
    lower = reach0 + REACH_S + hold
    leave = lower + REACH_S + TURN_S + linger
    gone = leave + float(np.linalg.norm(visit.end - visit.spot)) / visit.speed
    visit.times = (enter, arrive, reach0, reach0 + REACH_S, lower, leave, gone)


def _offstage(rng, spot: np.ndarray, away: np.ndarray, lo, hi) -> np.ndarray:
    """Where a path from `spot`, heading roughly along `away` (within 35 degrees), leaves
    the floor the image shows by OFFSTAGE_M."""
    angle = math.atan2(away[1], away[0]) + float(rng.uniform(-0.6, 0.6))
    d = np.array([math.cos(angle), math.sin(angle)])
    box_lo = np.asarray(lo) - OFFSTAGE_M
    box_hi = np.asarray(hi) + OFFSTAGE_M
    with np.errstate(divide="ignore"):
        t = np.where(d > 0, (box_hi - spot) / d, np.where(d < 0, (box_lo - spot) / d, np.inf))
    return spot + float(t.min()) * d
