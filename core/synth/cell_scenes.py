"""Robot cells: the density function's "cell" mode, an open world around the paper's scenes.

A cell scene holds robot arms (from URDF, joints drawn within their limits, on the floor, a
pedestal, a table or a gantry), the objects of a cell that are neither people nor furniture
(`cell_objects`: crates, drums, racks, cabinets, machine housings, parts on tables, ...; and,
a share `mesh_share` of them, meshes of arbitrary shape from `mesh_objects`), some of the
paper's furniture, and zero, one or two people, each placed freely or by a relation
(`cell_relations`: working at a robot's tool, standing under its arm, reaching into a machine,
or one of the paper's relations to furniture). A share `paper_share` of cell frames are the
paper's own modeled scenes, so a model trained on cells keeps knowing them.

| factor | what it scores | default |
|---|---|---|
| R_n, R_name, R_mount | robots per cell, which robot, what it stands on | 1-2; a random arm (`random_arms`, `random:<seed>`) 0.3, else uniform over the catalogue (the user's URDFs first, `user_robot_share`); floor 1, pedestal 2, table 1, gantry 0.3 |
| R_q | joint state | uniform within the URDF's limits, the arm clear of floor and support |
| R_pos, R_ori | base on the floor the camera sees, heading | uniform, U[0, 360) |
| C_n, C_rel | items per cell, the relation placing each | 2-8; free 2, stacked 1, beside a table 0.7, by a robot 1, a worktable by a robot 1, a part on a table 1.5 |
| C_mesh | whether an item placed free, beside a table, by a robot or on a table is a mesh object, which, its size, lie and yaw | 0.3; uniform over the catalogue entries that stand there; size uniform in the entry's range; lie uniform over the entry's; U[0, 360) |
| P_n, P_rel, P_p | people per cell, the relation placing each, pose | 0: 1, 1: 1.5, 2: 0.8; at a robot 2, under its arm 0.6, into a machine 0.6, the paper's furniture relations 0.8, free 2; the paper's poses 1, kneeling, crouching and reaching 3, lying 4 |
| theta | overlap of unrelated footprints (robots included) | U[0, theta'] as the paper's |

`log_factors` scores a cell scene's support: every height, pose, joint and position within
its range, every relation holding, every unrelated pair within theta.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from topseg.core.config import from_dict
from topseg.core.errors import TopsegError
from topseg.core.synth import (
    cell_objects,
    cell_relations,
    furniture,
    humanoid,
    mesh_objects,
    relations,
    robots,
)
from topseg.core.synth.cell_relations import CELL_STACKING
from topseg.core.synth.geometry import inside_rect, overlap_fraction
from topseg.core.synth.scene import PlacedHuman, PlacedObject, Relation, Scene, human_id

MOUNTS = ("floor", "pedestal", "table", "gantry")
PERSON_RELATIONS = ("works_at_robot", "under_arm", "into_machine", "furniture", "free")
ITEM_RELATIONS = (
    "free",
    "stacked",
    "beside_table",
    "item_by_robot",
    "table_by_robot",
    "part_on_table",
)
#: the most people a cell scene holds
MAX_PEOPLE = 2
#: spots a freely placed person tries before its pose is drawn again
FREE_SPOTS = 5
#: how far (m) below the camera a mesh object's top stays
MESH_CAMERA_CLEARANCE_M = 0.4
#: poses that lie or kneel on the floor: placed freely or at a robot, never by furniture
GROUND_POSES = ("kneeling", "crouching", "lying")


def _cell_pose_weights() -> dict:
    return {**{p: 1.0 for p in humanoid.PAPER_POSES}, **{p: 3.0 for p in humanoid.CELL_POSES},
            "lying": 4.0}  # fmt: skip


@dataclass
class CellConfig:
    """Every range and weight of cell scenes (see the module doc's table)."""

    paper_share: float = 0.35
    robots: tuple[int, int] = (1, 2)
    robot_names: tuple[str, ...] = ()  # empty: the whole catalogue; "random": random arms
    robot_urdfs: tuple[str, ...] = ()  # a user's own robots
    user_robot_share: float = 0.5  # of robots, when robot_urdfs are given
    random_robot_share: float = 0.3  # of the others, when random arms are allowed
    mount_weights: dict = field(
        default_factory=lambda: {"floor": 1.0, "pedestal": 2.0, "table": 1.0, "gantry": 0.3}
    )
    pedestal_height_m: tuple[float, float] = (0.2, 0.9)
    gantry_height_m: tuple[float, float] = (1.9, 2.6)
    n_items: tuple[int, int] = (2, 8)
    furniture_share: float = 0.3
    mesh_share: float = 0.3  # of items placed free, beside a table, by a robot or on a table
    item_relation_weights: dict = field(
        default_factory=lambda: {
            "free": 2.0,
            "stacked": 1.0,
            "beside_table": 0.7,
            "item_by_robot": 1.0,
            "table_by_robot": 1.0,
            "part_on_table": 1.5,
        }
    )
    people_weights: tuple[float, ...] = (1.0, 1.5, 0.8)
    person_relation_weights: dict = field(
        default_factory=lambda: {
            "works_at_robot": 2.0,
            "under_arm": 0.6,
            "into_machine": 0.6,
            "furniture": 0.8,
            "free": 2.0,
        }
    )
    pose_weights: dict = field(default_factory=_cell_pose_weights)

    def __post_init__(self) -> None:
        self.robots = tuple(int(v) for v in self.robots)
        self.robot_names = tuple(self.robot_names)
        self.robot_urdfs = tuple(str(v) for v in self.robot_urdfs)
        self.pedestal_height_m = tuple(float(v) for v in self.pedestal_height_m)
        self.gantry_height_m = tuple(float(v) for v in self.gantry_height_m)
        self.n_items = tuple(int(v) for v in self.n_items)
        self.people_weights = tuple(float(v) for v in self.people_weights)
        self.validate()

    def validate(self) -> None:
        """TopsegError naming the first value out of bounds (run on creation)."""

        def bad(msg: str):
            raise TopsegError(msg)

        shares = ("paper_share", "user_robot_share", "random_robot_share", "furniture_share",
                  "mesh_share")  # fmt: skip
        for name in shares:
            if not 0.0 <= getattr(self, name) <= 1.0:
                bad(f"{name} is a fraction in [0, 1], got {getattr(self, name)}")
        if not 0 <= self.robots[0] <= self.robots[1] <= 4:
            bad(f"robots must satisfy 0 <= min <= max <= 4, got {self.robots}")
        if not 0 <= self.n_items[0] <= self.n_items[1] <= 20:
            bad(f"n_items must satisfy 0 <= min <= max <= 20, got {self.n_items}")
        unknown = [n for n in self.robot_names if n not in (*robots.ROBOTS, robots.RANDOM)]
        if unknown:
            known = ", ".join((*robots.ROBOTS, robots.RANDOM))
            bad(f"robot_names: unknown robots {unknown}; known: {known}")
        for name, weights, known in (
            ("mount_weights", self.mount_weights, MOUNTS),
            ("item_relation_weights", self.item_relation_weights, ITEM_RELATIONS),
            ("person_relation_weights", self.person_relation_weights, PERSON_RELATIONS),
            ("pose_weights", self.pose_weights, humanoid.POSES),
        ):
            extra = set(weights) - set(known)
            if extra:
                bad(f"{name}: unknown {sorted(extra)}; known: {', '.join(known)}")
            if any(w < 0 for w in weights.values()) or sum(weights.values()) <= 0:
                bad(f"{name} must be >= 0 with a positive sum")
        if not (1 <= len(self.people_weights) <= MAX_PEOPLE + 1) or min(self.people_weights) < 0:
            bad(
                f"people_weights gives 0..{MAX_PEOPLE} people >= 0 weights, got {self.people_weights}"
            )
        lo, hi = self.pedestal_height_m
        if not 0.05 <= lo <= hi <= 1.5:
            bad(f"pedestal_height_m must satisfy 0.05 <= low <= high <= 1.5, got {(lo, hi)}")
        lo, hi = self.gantry_height_m
        if not 1.5 <= lo <= hi <= 4.0:
            bad(f"gantry_height_m must satisfy 1.5 <= low <= high <= 4.0, got {(lo, hi)}")

    def to_dict(self) -> dict:
        """Plain lists and dicts (TOML and JSON friendly) that `from_dict` reads back."""
        d = asdict(self)
        for k in ("robots", "robot_names", "robot_urdfs", "pedestal_height_m", "gantry_height_m",
                  "n_items", "people_weights"):  # fmt: skip
            d[k] = list(d[k])
        return d

    @classmethod
    def from_dict(cls, d: dict, source: str = "cell config") -> CellConfig:
        """The config a `to_dict` mapping or TOML table describes."""
        return from_dict(cls, d, source)


def _pick(rng, weights: dict, among=None) -> str | None:
    pool = [k for k, w in weights.items() if w > 0 and (among is None or k in among)]
    if not pool:
        return None
    p = np.array([weights[k] for k in pool], np.float64)
    return pool[int(rng.choice(len(pool), p=p / p.sum()))]


class CellSampler:
    """Draws and scores cell scenes for one `DensityFunction` (its rooms, thetas, heights)."""

    def __init__(self, density, config: CellConfig) -> None:
        self.density = density
        self.config = config

    # --- drawing -------------------------------------------------------------------------

    def sample_into(self, rng, scene: Scene) -> Scene | None:
        """Fill the empty `scene` as a cell (or, `paper_share` of the time, the paper's)."""
        c = self.config
        if rng.random() < c.paper_share:
            return self.density._fill_modeled(rng, scene)
        for _ in range(int(rng.integers(c.robots[0], c.robots[1] + 1))):
            self._add_robot(rng, scene)
        n = int(rng.integers(c.n_items[0], c.n_items[1] + 1))
        budget = 6 * max(n, 1)
        target = _n_items(scene) + n
        while _n_items(scene) < target and budget > 0:
            budget -= 1
            self._add_item(rng, scene, _pick(rng, c.item_relation_weights))
        weights = np.asarray(c.people_weights, np.float64)
        k = int(rng.choice(len(weights), p=weights / weights.sum()))
        for i in range(k):
            if not self._add_person(rng, scene, i) and i == 0:
                return None
        return scene

    def _robot_name(self, rng) -> str:
        """A user URDF, a random arm (`random:<seed>`) or a catalogue robot, by their shares."""
        c = self.config
        if c.robot_urdfs and (not robots.ROBOTS or rng.random() < c.user_robot_share):
            return str(c.robot_urdfs[int(rng.integers(len(c.robot_urdfs)))])
        names = [n for n in c.robot_names or robots.ROBOTS if n != robots.RANDOM]
        random_allowed = not c.robot_names or robots.RANDOM in c.robot_names
        if random_allowed and (not names or rng.random() < c.random_robot_share):
            return robots.random_arm_name(int(rng.integers(2**31)))
        return str(names[int(rng.integers(len(names)))])

    def _free_spot(self, rng, scene: Scene) -> tuple[float, float]:
        lo, hi = scene.floor_lo, scene.floor_hi
        return float(rng.uniform(lo[0], hi[0])), float(rng.uniform(lo[1], hi[1]))

    def _add_robot(self, rng, scene: Scene) -> robots.PlacedRobot | None:
        c, d = self.config, self.density
        mount_h = (scene.mount or d.mount).height_mm / 1000.0
        for _ in range(d.config.max_tries):
            mount = _pick(rng, c.mount_weights)
            if mount == "gantry" and mount_h < c.gantry_height_m[0] + 0.4:
                continue
            name = self._robot_name(rng)
            model = robots.robot_model(name)
            x, y = self._free_spot(rng, scene)
            robot = robots.PlacedRobot(
                scene.next_id(), name, x, y, float(rng.uniform(0, 2 * np.pi)), "floor", 0.0,
                model.random_joints(rng),
            )  # fmt: skip
            added: list[PlacedObject] = []
            rels: list[Relation] = []
            if mount == "pedestal":
                robot.mount = "pedestal"
                robot.base_z = float(rng.uniform(*c.pedestal_height_m))
                robot.pedestal = (float(rng.uniform(0.1, 0.3)), float(rng.random() < 0.5))
            elif mount == "gantry":
                robot.mount = "gantry"
                robot.base_z = float(
                    rng.uniform(c.gantry_height_m[0], min(c.gantry_height_m[1], mount_h - 0.4))
                )
            elif mount == "table":
                table = d._draw_object(rng, scene, "table", ("table_rect",))
                table.id = robot.id + 1
                table.x, table.y = x, y
                rel = cell_relations.place_robot_on_table(robot, table)
                if rel is None:
                    continue
                added, rels = [table], [rel]
            if not self._robot_fits(scene, robot, added):
                continue
            for _ in range(6):  # a joint state whose arm clears floor and support
                if cell_relations.arm_clear_of(robot, added):
                    break
                robot.joints = model.random_joints(rng)
            else:
                continue
            scene.robots.append(robot)
            scene.objects.extend(added)
            scene.relations.extend(rels)
            return robot
        return None

    def _robot_fits(self, scene: Scene, robot, added: list[PlacedObject]) -> bool:
        fp = cell_relations.robot_footprint(robot)
        if not inside_rect(np.array([[robot.x, robot.y]]), scene.floor_lo, scene.floor_hi):
            return False
        if not inside_rect(fp, *scene.bounds):
            return False
        for a in added:
            if not inside_rect(a.footprint(), *scene.bounds):
                return False
        others = [o.footprint() for o in _items(scene)] + [
            cell_relations.robot_footprint(r) for r in scene.robots
        ]
        mine = [fp] + [a.footprint() for a in added]
        return all(overlap_fraction(m, o) <= scene.theta_oo for m in mine for o in others)

    def _item_fits(self, scene: Scene, obj, rel: Relation | None) -> bool:
        if not self.density._fits_object(scene, obj, rel):
            return False
        if isinstance(obj, mesh_objects.PlacedMeshObject) and not self._below_camera(scene, obj):
            return False
        if obj.support is not None:  # on a table or a crate: clear of the arms is all it needs
            return True
        fp = obj.footprint()
        return all(
            overlap_fraction(fp, cell_relations.robot_footprint(r)) <= scene.theta_oo
            or (rel is not None and rel.object == r.id and rel.kind in CELL_STACKING)
            for r in scene.robots
        )

    def _below_camera(self, scene: Scene, obj) -> bool:
        """An item's top stays MESH_CAMERA_CLEARANCE_M below the camera."""
        mount_h = (scene.mount or self.density.mount).height_mm / 1000.0
        return obj.z_range()[1] <= mount_h - MESH_CAMERA_CLEARANCE_M

    def _draw_any(self, rng, scene: Scene, kinds, on_table: bool = False):
        """A mesh object `mesh_share` of the time (no draw at share 0), else a cell object of
        one of `kinds`."""
        if self.config.mesh_share > 0 and rng.random() < self.config.mesh_share:
            x, y = self._free_spot(rng, scene)
            return mesh_objects.draw(rng, scene.next_id(), on_table, x, y)
        return self._draw_item(rng, scene, kinds)

    def _draw_item(self, rng, scene: Scene, kinds) -> PlacedObject:
        kind = str(kinds[int(rng.integers(len(kinds)))])
        lo, hi = cell_objects.HEIGHT_RANGE_M[kind]
        x, y = self._free_spot(rng, scene)
        return PlacedObject(
            scene.next_id(), kind, int(rng.integers(furniture.N_VARIANTS)),
            furniture.quantize_height(float(rng.uniform(lo, hi))), x, y, 0.0,
            float(rng.uniform(0, 2 * np.pi)),
        )  # fmt: skip

    def _add_item(self, rng, scene: Scene, kind: str) -> None:
        c, d = self.config, self.density
        if kind == "free":
            if rng.random() < c.furniture_share:
                cls = str(rng.choice(list(d.object_height)))
                d._add_free_object(rng, scene, cls)  # its id is scene.next_id(): robots counted
                return
            for _ in range(d.config.max_tries):
                obj = self._draw_any(rng, scene, cell_objects.FLOOR_KINDS)
                if self._item_fits(scene, obj, None):
                    _append(scene, [obj])
                    return
            return
        for _ in range(4):
            placed = self._related_item(rng, scene, kind)
            if placed is None:
                continue
            objs, rel = placed
            if all(self._item_fits(scene, o, rel) for o in objs):
                _append(scene, objs)
                scene.relations.append(rel)
                return

    def _related_item(self, rng, scene: Scene, kind: str):
        d = self.density
        if kind == "stacked":
            pool = [o for o in scene.objects if o.kind in cell_objects.STACKABLE]
            if not pool:
                return None
            lower = pool[int(rng.integers(len(pool)))]
            upper = self._draw_item(rng, scene, cell_objects.STACKABLE)
            rel = cell_relations.place_stacked(rng, lower, upper)
            return None if rel is None else ([upper], rel)
        if kind == "part_on_table":
            pool = [o for o in scene.objects if o.cls == "table" and o.support is None]
            if not pool:
                return None
            table = pool[int(rng.integers(len(pool)))]
            part = self._draw_any(rng, scene, cell_objects.TABLE_TOP_KINDS, on_table=True)
            rel = cell_relations.place_on_table(rng, table, part)
            return None if rel is None else ([part], rel)
        if kind in ("item_by_robot", "table_by_robot"):
            if not scene.robots:
                return None
            robot = scene.robots[int(rng.integers(len(scene.robots)))]
            if kind == "table_by_robot":
                obj = d._draw_object(rng, scene, "table", ("table_rect",))
                obj.id = scene.next_id()
            else:
                obj = self._draw_any(rng, scene, cell_objects.FLOOR_KINDS)
            radius = float(np.ptp(cell_relations.robot_footprint(robot), axis=0).max() / 2)
            params = cell_relations.place_near(
                rng, (robot.x, robot.y), min(radius, 0.4), obj, (0.05, 0.5)
            )
            return [obj], Relation(kind, obj.id, robot.id, params)
        if kind == "beside_table":
            pool = [o for o in scene.objects if o.cls == "table" and o.support is None]
            if not pool:
                return None
            table = pool[int(rng.integers(len(pool)))]
            obj = self._draw_any(rng, scene, cell_objects.FLOOR_KINDS)
            tm = table.model()
            params = cell_relations.place_near(
                rng, (table.x, table.y), min(tm.size_x, tm.size_y) / 2, obj, (0.02, 0.3)
            )
            return [obj], Relation("beside_table", obj.id, table.id, params)
        return None

    def _person_fits(self, scene: Scene, human: PlacedHuman, exempt: set) -> bool:
        d = self.density
        if d._human_pos_log_pdf(scene, human.x, human.y) == -math.inf:
            return False
        if not d._human_in_bounds(scene, human.footprint(arms=True)):
            return False
        fp = human.footprint()
        exempt = exempt | {o.id for o in _items(scene) if o.support in exempt}
        others = [o.footprint() for o in _items(scene) if o.id not in exempt]
        others += [cell_relations.robot_footprint(r) for r in scene.robots if r.id not in exempt]
        others += [h.footprint() for h in scene.humans]
        return all(overlap_fraction(fp, o) <= scene.theta_ho for o in others)

    def _add_person(self, rng, scene: Scene, index: int) -> bool:
        c, d = self.config, self.density
        hid = human_id(index)
        for _ in range(d.config.max_tries):
            rel_kind = _pick(rng, c.person_relation_weights)
            if rel_kind == "furniture":
                if index > 0 or not any(o.cls != "object" for o in scene.objects):
                    continue
                n_before = len(scene.objects)
                if d._add_human(rng, scene):
                    return True
                del scene.objects[n_before:]
                continue
            height = humanoid.quantize_height(d.human_height.sample(rng))
            among = {
                "works_at_robot": cell_relations.AT_ROBOT_POSES,
                "into_machine": cell_relations.INTO_MACHINE_POSES,
                "under_arm": ("standing", "walking", "working"),
            }.get(rel_kind)
            pose_name = _pick(rng, c.pose_weights, among)
            if pose_name is None:
                continue
            pose, source = humanoid.sample_pose(pose_name, rng)
            # a free person tries a few spots before the pose is drawn again: a lying body
            # is 2 m long and rarely fits the first spot
            for _ in range(FREE_SPOTS if rel_kind == "free" else 1):
                placed = self._place_person(
                    rng, scene, rel_kind, hid, height, pose_name, pose, source
                )
                if placed is not None and self._person_fits(
                    scene, placed[0], {r.object for r in placed[1]}
                ):
                    break
            else:
                continue
            human, rels = placed
            if index == 0:
                scene.human = human
            else:
                scene.extra_humans.append(human)
            scene.relations.extend(rels)
            return True
        return False

    def _place_person(self, rng, scene: Scene, kind, hid, height, pose_name, pose, source):
        if kind == "free":
            human, _ = self.density._place_human(rng, scene, "free", pose_name, height, pose,
                                                 source)  # fmt: skip
            return human, []
        if kind in ("works_at_robot", "under_arm"):
            if not scene.robots:
                return None
            robot = scene.robots[int(rng.integers(len(scene.robots)))]
            place = (
                cell_relations.place_works_at_robot
                if kind == "works_at_robot"
                else cell_relations.place_under_arm
            )
            res = place(rng, robot, hid, height, pose_name, pose, source)
        else:
            pool = [o for o in scene.objects if cell_relations.is_machine(o)]
            if not pool:
                return None
            machine = pool[int(rng.integers(len(pool)))]
            res = cell_relations.place_into_machine(rng, machine, hid, height, pose_name, pose,
                                                    source)  # fmt: skip
        if res is None:
            return None
        human, rel = res
        probe = _probe(scene, human)
        return (human, [rel]) if _check_person(probe, rel, human) else None

    # --- scoring -------------------------------------------------------------------------

    def log_factors(self, scene: Scene) -> dict[str, float]:
        """Each cell factor's log value (-inf where the scene leaves its support)."""
        d, c = self.density, self.config
        f = {k: 0.0 for k in ("R_q", "R_pos", "R_mount", "P", "O", "theta", "rel")}
        for r in scene.robots:
            model = robots.robot_model(r.name)
            q = np.array([r.joints.get(n, np.nan) for n in model.joint_names])
            if not np.all((q >= model.lower - 1e-9) & (q <= model.upper + 1e-9)):
                f["R_q"] = -math.inf
            w = c.mount_weights.get(r.mount, 0.0)
            f["R_mount"] += math.log(w / sum(c.mount_weights.values())) if w > 0 else -math.inf
            on_floor = inside_rect(np.array([[r.x, r.y]]), scene.floor_lo, scene.floor_hi)
            f["R_pos"] += d.position_log_pdf(scene) if on_floor else -math.inf
        for h in scene.humans:
            f["P"] += d.human_height.log_pdf(h.height)
            if h.pose_name not in c.pose_weights or c.pose_weights[h.pose_name] <= 0:
                f["P"] = -math.inf
        for o in scene.objects:
            if o.cls == "object":
                lo, hi = cell_objects.HEIGHT_RANGE_M[o.kind]
                ok = lo - 0.006 <= o.height <= hi + 0.006
            else:
                ok = d.object_height[o.cls].log_pdf(o.height) > -math.inf
            f["O"] += 0.0 if ok else -math.inf
        for m in scene.mesh_objects:
            on_floor = inside_rect(np.array([[m.x, m.y]]), scene.floor_lo, scene.floor_hi)
            resting = m.support is not None or m.z == 0.0
            ok = mesh_objects.size_ok(m) and on_floor and resting and self._below_camera(scene, m)
            f["O"] += 0.0 if ok else -math.inf
        if not 0 <= scene.theta_oo <= d.config.theta_max_oo or not (
            0 <= scene.theta_ho <= d.config.theta_max_ho
        ):
            f["theta"] = -math.inf
        for rel in scene.relations:
            if not _holds(scene, rel):
                f["rel"] = -math.inf
        return f


def _items(scene: Scene) -> list:
    """The scene's objects and mesh objects."""
    return [*scene.objects, *scene.mesh_objects]


def _n_items(scene: Scene) -> int:
    return len(scene.objects) + len(scene.mesh_objects)


def _append(scene: Scene, items) -> None:
    """Add placed items to the scene: mesh objects to its mesh objects, others to its objects."""
    for item in items:
        if isinstance(item, mesh_objects.PlacedMeshObject):
            scene.mesh_objects.append(item)
        else:
            scene.objects.append(item)


def _probe(scene: Scene, human: PlacedHuman) -> Scene:
    return Scene(scene.mode, scene.room, scene.floor_lo, scene.floor_hi, 0, 0, scene.objects,
                 human, [], robots=scene.robots)  # fmt: skip


def _human_of(scene: Scene, hid: str) -> PlacedHuman | None:
    for i, h in enumerate(scene.humans):
        if human_id(i) == hid:
            return h
    return None


def _check_person(scene: Scene, rel: Relation, human: PlacedHuman) -> bool:
    check = {
        "works_at_robot": cell_relations.check_works_at_robot,
        "under_arm": cell_relations.check_under_arm,
        "into_machine": cell_relations.check_into_machine,
    }[rel.kind]
    return check(scene, rel, human)


def _holds(scene: Scene, rel: Relation) -> bool:
    """Whether a relation of a cell scene (a cell's own or the paper's) holds."""
    from_paper = _paper_relation_holds(scene, rel)
    if from_paper is not None:
        return from_paper
    try:
        if rel.kind in ("works_at_robot", "under_arm", "into_machine"):
            human = _human_of(scene, rel.subject)
            return human is not None and _check_person(scene, rel, human)
        if rel.kind == "robot_on_table":
            return cell_relations.check_robot_on_table(scene, rel)
        if rel.kind == "stacked":
            return cell_relations.check_stacked(scene, rel)
        if rel.kind == "part_on_table":
            return cell_relations.check_on_table(scene, rel)
        if rel.kind in ("item_by_robot", "table_by_robot", "beside_table"):
            return cell_relations.check_near(scene, rel)
    except KeyError:
        return False
    return False


def _paper_relation_holds(scene: Scene, rel: Relation) -> bool | None:
    """Whether one of the paper's relations holds; None for a cell's own."""
    if rel.kind in relations.OO_RELATIONS or rel.kind in relations.HO_RELATIONS:
        return relations.holds(scene, rel)
    return None
