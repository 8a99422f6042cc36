"""The relations of robot cells: how robots, cell objects and people are placed against each other.

Robot-object: a robot on a table (its base on the top), a worktable beside a robot, a cart or
bin by a robot. Object-object: crates stacked, a bin beside a table, parts and tools on a
table. Person-robot: working at the robot (a hand at its tool), standing partly under its arm.
Person-object: reaching into a machine. Each `place_*` draws its free parameters from `rng`
and returns the new item and its relation record, or None when the anchor cannot take it;
each `check_*` re-derives the geometry from the scene alone, as `relations` does for the
paper's relations, so a cell scene can be scored whatever made it.
"""

from __future__ import annotations

import functools

import numpy as np

from topseg.core.synth import humanoid
from topseg.core.synth.geometry import BOX, CYLINDER, points_in_convex, rot2
from topseg.core.synth.relations import lean_to_reach, stand_z
from topseg.core.synth.robots import PlacedRobot
from topseg.core.synth.scene import PlacedHuman, PlacedObject, Relation, Scene

#: object-object and robot-object relations of cells
CELL_OO_RELATIONS = (
    "robot_on_table",
    "table_by_robot",
    "item_by_robot",
    "stacked",
    "beside_table",
    "part_on_table",
)
#: person relations of cells
CELL_HO_RELATIONS = ("works_at_robot", "under_arm", "into_machine")
#: relations whose items may overlap beyond theta
CELL_STACKING = frozenset(
    {"robot_on_table", "stacked", "part_on_table", "works_at_robot", "under_arm", "into_machine"}
)
#: poses a person working at a robot or reaching into a machine starts from
AT_ROBOT_POSES = ("standing", "working", "reaching", "bending", "kneeling", "crouching")
INTO_MACHINE_POSES = ("reaching", "working", "standing")
#: how close (m) a hand's wrist must come to the tool it works at
TOOL_TOL_M = 0.2
#: clearance (m) the arm keeps above a person standing under it
UNDER_ARM_CLEARANCE_M = 0.05
#: how close (m) the floor and a support may come to the arm's shapes
SUPPORT_TOL_M = 0.01


def _state(robot: PlacedRobot) -> tuple:
    """What a robot's shape depends on, hashable: the key of the caches below."""
    return (robot.name, robot.x, robot.y, robot.yaw, robot.mount, robot.base_z,
            tuple(robot.pedestal), tuple(sorted(robot.joints.items())))  # fmt: skip


@functools.lru_cache(maxsize=256)
def _footprint(state: tuple) -> np.ndarray:
    name, x, y, yaw, mount, base_z, pedestal, joints = state
    return PlacedRobot(0, name, x, y, yaw, mount, base_z, dict(joints), pedestal).footprint()


def robot_footprint(robot: PlacedRobot) -> np.ndarray:
    """`robot.footprint()`, remembered per robot state (placing a cell asks for it often)."""
    return _footprint(_state(robot))


def robot_points(robot: PlacedRobot) -> np.ndarray:
    """(n, 3) points on the posed robot: its triangles' corners and its primitives' centres and
    box corners (enough to test clearance and support, not an exact surface); remembered per
    robot state."""
    return _points(_state(robot))


@functools.lru_cache(maxsize=256)
def _points(state: tuple) -> np.ndarray:
    name, x, y, yaw, mount, base_z, pedestal, joints = state
    robot = PlacedRobot(0, name, x, y, yaw, mount, base_z, dict(joints), pedestal)
    prims, _ = robot.geometry()
    pts = [robot.model().hull_points(robot.joints, robot.base_pos(), robot.base_quat()),
           prims.center]  # fmt: skip
    for kind, size, c, r in zip(prims.kind, prims.size, prims.center, prims.rot, strict=True):
        s = np.asarray(size, np.float64)
        if kind == BOX:
            ext = s
        elif kind == CYLINDER:
            ext = np.array([s[0], s[0], s[1]])
        else:  # a sphere or a capsule
            ext = np.array([s[0], s[0], s[0] + s[1]])
        corners = np.array(np.meshgrid(*[(-1.0, 1.0)] * 3)).reshape(3, -1).T * ext
        pts.append(c + corners @ np.asarray(r).T)
    return np.concatenate(pts)


def arm_clear_of(robot: PlacedRobot, supports: list[PlacedObject]) -> bool:
    """The posed arm stays above the floor and above the tops of `supports` over their
    footprints (a random joint state may fold the arm through its table)."""
    pts = robot_points(robot)
    if pts[:, 2].min() < -SUPPORT_TOL_M:
        return False
    for s in supports:
        top = s.z + s.height
        inside = points_in_convex(pts[:, :2], s.footprint())
        if np.any(pts[inside, 2] < top - SUPPORT_TOL_M) and top > robot.base_z + SUPPORT_TOL_M:
            return False
        if robot.base_z < top - SUPPORT_TOL_M and np.any(inside):
            return False
    return True


# --- robot and objects ---------------------------------------------------------------------


def place_robot_on_table(robot: PlacedRobot, table: PlacedObject) -> Relation | None:
    """Move `robot`'s base onto the top of `table` (its centre within the top, margin 0.1 m)."""
    if table.kind != "table_rect":
        return None
    robot.mount, robot.base_z = "table", float(table.z + table.height)
    return Relation("robot_on_table", robot.id, table.id, {})


def check_robot_on_table(scene: Scene, rel: Relation) -> bool:
    """The robot's base rests on the table top, inside it."""
    r, t = scene.robot(rel.subject), scene.object(rel.object)
    return (
        t.cls == "table"
        and r.mount == "table"
        and abs(r.base_z - (t.z + t.height)) < 1e-6
        and bool(points_in_convex(np.array([r.x, r.y]), t.footprint(), margin=-0.05))
    )


def place_near(
    rng, anchor_xy, anchor_radius: float, obj: PlacedObject, gap: tuple[float, float]
) -> dict:
    """`obj` moved to a random side of a point, `gap` (m) beyond `anchor_radius` and its own
    half size; returns the relation's params (the distance and the most it may be)."""
    m = obj.model()
    a = rng.uniform(0, 2 * np.pi)
    reach = anchor_radius + max(m.size_x, m.size_y) / 2
    d = reach + rng.uniform(*gap)
    obj.x = float(anchor_xy[0] + d * np.cos(a))
    obj.y = float(anchor_xy[1] + d * np.sin(a))
    obj.yaw = float(a + np.pi + rng.uniform(-0.4, 0.4))
    return {"distance": float(d), "max_distance": float(reach + gap[1])}


def check_near(scene: Scene, rel: Relation) -> bool:
    """The subject stands at its recorded distance from its anchor (object or robot),
    within the most the relation allows."""
    s = scene.object(rel.subject)
    a = (
        scene.robot(rel.object)
        if rel.kind in ("table_by_robot", "item_by_robot")
        else scene.object(rel.object)
    )
    d = float(np.hypot(s.x - a.x, s.y - a.y))
    p = rel.params
    return abs(d - p.get("distance", np.inf)) < 1e-6 and d <= p.get("max_distance", -1.0) + 1e-9


def place_stacked(rng, lower: PlacedObject, upper: PlacedObject) -> Relation | None:
    """`upper` on top of `lower`, offset a little, turned a little: crates on crates."""
    lm, um = lower.model(), upper.model()
    if um.size_x > lm.size_x * 1.15 or um.size_y > lm.size_y * 1.15:
        return None
    off = rng.uniform(-0.05, 0.05, 2)
    x, y = lower.to_world(off)
    upper.x, upper.y = float(x), float(y)
    upper.z = float(lower.z + lower.height)
    upper.yaw = float(lower.yaw + rng.uniform(-0.15, 0.15))
    upper.support = lower.id
    return Relation("stacked", upper.id, lower.id, {})


def check_stacked(scene: Scene, rel: Relation) -> bool:
    """The upper item rests on the lower's top with its centre over it."""
    u, lo = scene.object(rel.subject), scene.object(rel.object)
    return (
        u.support == lo.id
        and abs(u.z - (lo.z + lo.height)) < 1e-6
        and bool(points_in_convex(np.array([u.x, u.y]), lo.footprint()))
    )


def place_on_table(rng, table: PlacedObject, part: PlacedObject) -> Relation | None:
    """A part or tool on a table's top, inside it."""
    fp = table.footprint()
    m = part.model()
    for _ in range(10):
        tm = table.model()
        local = rng.uniform(-0.5, 0.5, 2) * np.array(
            [max(tm.size_x - m.size_x, 0.0), max(tm.size_y - m.size_y, 0.0)]
        )
        x, y = table.to_world(local)
        part.x, part.y, part.z = float(x), float(y), float(table.z + table.height)
        part.yaw = float(rng.uniform(0, 2 * np.pi))
        part.support = table.id
        if bool(points_in_convex(part.footprint(), fp).all()):
            return Relation("part_on_table", part.id, table.id, {})
    return None


def check_on_table(scene: Scene, rel: Relation) -> bool:
    """The part rests on the table's top, its footprint inside the top."""
    p, t = scene.object(rel.subject), scene.object(rel.object)
    return (
        t.cls == "table"
        and p.support == t.id
        and abs(p.z - (t.z + t.height)) < 1e-6
        and bool(points_in_convex(p.footprint(), t.footprint(), margin=1e-6).all())
    )


# --- people --------------------------------------------------------------------------------


def _placed(height, pose_name, pose, source, xy, z0, yaw) -> PlacedHuman:
    return PlacedHuman(height, pose_name, pose, source, float(xy[0]), float(xy[1]), float(z0),
                       float(np.mod(yaw, 2 * np.pi)))  # fmt: skip


def place_works_at_robot(
    rng, robot: PlacedRobot, hid: str, height, pose_name, pose, source
) -> tuple[PlacedHuman, Relation] | None:
    """A person facing the robot's tool with one or both hands at it (within TOOL_TOL_M)."""
    scale = humanoid.scale_for_height(height)
    tool = robot.tool_position()
    if not 0.3 < tool[2] < 0.92 * height:
        return None
    hands = (
        ("right",) if rng.random() < 0.5 else ("left",) if rng.random() < 0.6 else ("right", "left")
    )
    gap = rng.uniform(0.02, 0.15)

    def target_of(front, shoulder, side, k):
        return np.array([front + k * gap + 0.08, shoulder[1] * 0.6, tool[2]])

    res = lean_to_reach(pose, scale, tool[2], hands, target_of)
    if res is None:
        return None
    p, z0, front, k = res
    base = np.array([robot.x, robot.y])
    away = tool[:2] - base
    yaw_out = np.arctan2(away[1], away[0]) if np.linalg.norm(away) > 0.05 else rng.uniform(0, 6.3)
    yaw_out += rng.uniform(-0.8, 0.8)
    yaw = yaw_out + np.pi  # the person faces back towards the tool
    target_local = np.array([front + k * gap + 0.08, 0.0])
    origin = tool[:2] - rot2(yaw) @ target_local
    human = _placed(height, pose_name, p, source, origin, z0, yaw)
    rel = Relation("works_at_robot", hid, robot.id, {"hands": list(hands)})
    return human, rel


def check_works_at_robot(scene: Scene, rel: Relation, human: PlacedHuman) -> bool:
    """Every hand of the relation within TOOL_TOL_M of the robot's tool."""
    tool = scene.robot(rel.object).tool_position()
    hands = rel.params.get("hands") or []
    return bool(hands) and all(
        np.linalg.norm(
            humanoid.wrist_position(human.pose, human.scale, human.base_pos, human.base_quat, s)
            - tool
        )
        < TOOL_TOL_M
        for s in hands
    )


def place_under_arm(
    rng, robot: PlacedRobot, hid: str, height, pose_name, pose, source
) -> tuple[PlacedHuman, Relation] | None:
    """A person standing where the robot's arm passes overhead, clear of it."""
    scale = humanoid.scale_for_height(height)
    pts = robot_points(robot)
    high = pts[pts[:, 2] > 0.6 * height]
    if len(high) == 0:
        return None
    z0 = stand_z(pose, scale)
    spot = high[int(rng.integers(len(high)))][:2] + rng.normal(0, 0.1, 2)
    human = _placed(height, pose_name, pose.copy(), source, spot, z0, rng.uniform(0, 2 * np.pi))
    rel = Relation("under_arm", hid, robot.id, {})
    return human, rel


def check_under_arm(scene: Scene, rel: Relation, human: PlacedHuman) -> bool:
    """Some of the arm is over the person's footprint and all of it clears the person."""
    pts = robot_points(scene.robot(rel.object))
    over = points_in_convex(pts[:, :2], human.footprint(arms=True))
    if not np.any(over):
        return False
    _, top = humanoid.prims_z_range(human.primitives())
    return bool(pts[over, 2].min() > top + UNDER_ARM_CLEARANCE_M)


def place_into_machine(
    rng, machine: PlacedObject, hid: str, height, pose_name, pose, source
) -> tuple[PlacedHuman, Relation] | None:
    """A person at the front of a machine housing, reaching into it with one or both hands."""
    scale = humanoid.scale_for_height(height)
    m = machine.model()
    reach_z = float(np.clip(rng.uniform(0.85, 1.35), 0.5, machine.height - 0.15))
    depth_in = rng.uniform(0.05, 0.3)
    gap = rng.uniform(0.0, 0.1)
    hands = ("right", "left") if rng.random() < 0.5 else (str(rng.choice(["right", "left"])),)

    def target_of(front, shoulder, side, k):
        return np.array([front + k * gap + depth_in, shoulder[1] * 0.7, reach_z])

    res = lean_to_reach(pose, scale, reach_z, hands, target_of)
    if res is None:
        return None
    p, z0, front, k = res
    lat = rng.uniform(-1, 1) * max(0.0, m.size_y / 2 - 0.3)
    origin_local = np.array([m.size_x / 2 + front + k * gap, lat])
    xy = machine.to_world(origin_local)
    human = _placed(height, pose_name, p, source, xy, z0, machine.yaw + np.pi)
    return human, Relation("into_machine", hid, machine.id, {"hands": list(hands)})


def check_into_machine(scene: Scene, rel: Relation, human: PlacedHuman) -> bool:
    """Every hand of the relation inside the machine's footprint, below its top."""
    m = scene.object(rel.object)
    fp = m.footprint()
    for s in rel.params.get("hands") or []:
        w = humanoid.wrist_position(human.pose, human.scale, human.base_pos, human.base_quat, s)
        if not (points_in_convex(w[:2], fp) and w[2] < m.z + m.height):
            return False
    return bool(rel.params.get("hands"))


#: kinds of cell object a person may reach into
MACHINE_KINDS = ("machine",)


def is_machine(o: PlacedObject) -> bool:
    """A cell object a person can reach into (a machine housing)."""
    return o.kind in MACHINE_KINDS
