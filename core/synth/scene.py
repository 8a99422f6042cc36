"""The scene description: plain data for one frame, what the density function samples and scores.

A scene holds the room, the overlap thresholds theta drawn for it, the objects (class, kind,
variant, size, pose on the floor, what supports them), the human (height, scale, pose and
place), the relations that placed them and the camera mount the frame is seen from (height,
tilt, intrinsics, sensor: drawn per frame for training). `to_dict()` is JSON-able and
`from_dict()` reads it back exactly, so a dataset stores each frame's description (and its
mount, under "mount") beside its pixels.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from topseg.core.camera import TopViewMount
from topseg.core.synth import furniture, humanoid
from topseg.core.synth.geometry import rect_footprint
from topseg.core.synth.mesh_objects import PlacedMeshObject
from topseg.core.synth.robots import PlacedRobot

HUMAN = "human"  # the id relations use for the human


def human_id(index: int) -> str:
    """The id relations use for person `index` of `Scene.humans` (0: HUMAN, the paper's)."""
    return HUMAN if index == 0 else f"{HUMAN}:{index}"


@dataclass
class PlacedObject:
    """A furniture item: `x, y` its footprint centre, `z` what it stands on, `yaw` its heading."""

    id: int
    kind: str
    variant: int
    height: float
    x: float
    y: float
    z: float = 0.0
    yaw: float = 0.0
    support: int | None = None  # id of the object it stands on; None = the floor

    @property
    def cls(self) -> str:
        """The item's class name ("chair", "table", "plant" or "storage")."""
        return furniture.CLASS_OF_KIND[self.kind]

    @property
    def label(self) -> int:
        """The label id its pixels get."""
        return furniture.KINDS[self.kind]

    def model(self) -> furniture.FurnitureModel:
        """The item's furniture model: its shape at its kind, variant and height (cached)."""
        return furniture.model(self.kind, self.variant, self.height)

    def footprint(self) -> np.ndarray:
        """The item's polygon on the floor (m, world frame), what overlaps are measured with."""
        return self.model().footprint(self.x, self.y, self.yaw)

    def to_local(self, xy) -> np.ndarray:
        """World floor point(s) -> this item's frame."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        d = np.asarray(xy, np.float64) - (self.x, self.y)
        return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], axis=-1)

    def to_world(self, local_xy) -> np.ndarray:
        """This item's frame -> world floor point(s); the inverse of `to_local`."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        p = np.asarray(local_xy, np.float64)
        return np.stack(
            [self.x + c * p[..., 0] - s * p[..., 1], self.y + s * p[..., 0] + c * p[..., 1]],
            axis=-1,
        )

    def to_dict(self) -> dict:
        """JSON-able record, with the class and size added for readers without this code."""
        m = self.model()
        return {
            "id": self.id,
            "class": self.cls,
            "kind": self.kind,
            "variant": self.variant,
            "height": self.height,
            "size": [m.size_x, m.size_y, self.height],
            "x": self.x,
            "y": self.y,
            "z": self.z,
            "yaw": self.yaw,
            "support": self.support,
        }

    @classmethod
    def from_dict(cls, d: dict) -> PlacedObject:
        """The item a `to_dict` record describes (the derived class and size are ignored)."""
        return cls(
            int(d["id"]), d["kind"], int(d["variant"]), float(d["height"]),
            float(d["x"]), float(d["y"]), float(d["z"]), float(d["yaw"]),
            None if d.get("support") is None else int(d["support"]),
        )  # fmt: skip


@dataclass
class PlacedHuman:
    """The human: `height` (m, upright), pose by name and joint values, base pose in the world."""

    height: float
    pose_name: str
    pose: humanoid.Pose
    source: dict
    x: float
    y: float
    z: float
    yaw: float

    @property
    def scale(self) -> float:
        """pybullet globalScaling that makes the humanoid `height` tall."""
        return humanoid.scale_for_height(self.height)

    @property
    def base_pos(self) -> tuple[float, float, float]:
        """World position (m) of the humanoid's base (root link)."""
        return (self.x, self.y, self.z)

    @property
    def base_quat(self) -> np.ndarray:
        """World orientation of the base: the pose's tilt, stood upright, turned by `yaw`."""
        return humanoid.base_quat(self.pose.tilt, self.yaw)

    def primitives(self) -> humanoid.Primitives:
        """The posed body's shapes in the world, for rendering and relation checks."""
        return humanoid.posed_primitives(self.pose, self.scale, self.base_pos, self.base_quat)

    def footprint(self, arms: bool = False) -> np.ndarray:
        """The body's bounding rectangle on the floor, aligned with the way it faces.

        Without `arms` (the default, what theta limits) it covers trunk, head and legs: a hand
        reaching over a table is an interaction, not an overlap.
        """
        lo, hi = humanoid.prims_xy_bounds(self.primitives(), self.yaw, self.base_pos, arms)
        c = (lo + hi) / 2
        cx = self.x + np.cos(self.yaw) * c[0] - np.sin(self.yaw) * c[1]
        cy = self.y + np.sin(self.yaw) * c[0] + np.cos(self.yaw) * c[1]
        return rect_footprint(cx, cy, hi[0] - lo[0], hi[1] - lo[1], self.yaw)

    def to_dict(self) -> dict:
        """JSON-able record with the pose's joints and the derived scale and base quaternion."""
        return {
            "height": self.height,
            "scale": self.scale,
            "pose": self.pose_name,
            "source": dict(self.source),
            "x": self.x,
            "y": self.y,
            "z": self.z,
            "yaw": self.yaw,
            "base_quat": [float(v) for v in self.base_quat],
            **self.pose.to_dict(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> PlacedHuman:
        """The human a `to_dict` record describes (derived scale and base_quat are recomputed)."""
        return cls(
            float(d["height"]), d["pose"], humanoid.Pose.from_dict(d), dict(d["source"]),
            float(d["x"]), float(d["y"]), float(d["z"]), float(d["yaw"]),
        )  # fmt: skip


@dataclass
class Relation:
    """`kind` links `subject` to `object` (object ids, or HUMAN); `params` says how."""

    kind: str
    subject: int | str
    object: int | str
    params: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """JSON-able record of the relation."""
        return {
            "kind": self.kind,
            "subject": self.subject,
            "object": self.object,
            "params": dict(self.params),
        }

    @classmethod
    def from_dict(cls, d: dict) -> Relation:
        """The relation a `to_dict` record describes (`params` may be missing)."""
        return cls(d["kind"], d["subject"], d["object"], dict(d.get("params", {})))


@dataclass
class Scene:
    """One frame's scene: room, floor (m), thetas, objects, human and the relations placing them."""

    mode: str  # "modeled" | "non-modeled"
    room: str
    floor_lo: tuple[float, float]
    floor_hi: tuple[float, float]
    theta_ho: float
    theta_oo: float
    objects: list[PlacedObject] = field(default_factory=list)
    human: PlacedHuman | None = None
    relations: list[Relation] = field(default_factory=list)
    #: what footprints must stay within (walls, or a margin past the view); None = the floor
    bounds_lo: tuple[float, float] | None = None
    bounds_hi: tuple[float, float] | None = None
    #: the camera the scene is seen from (its floor and bounds follow it); None = unrecorded
    mount: TopViewMount | None = None
    #: robot arms in the cell (their ids share the objects' id space)
    robots: list[PlacedRobot] = field(default_factory=list)
    #: people besides `human` (a robot cell may hold several); relations name them
    #: `human_id(i + 1)`
    extra_humans: list[PlacedHuman] = field(default_factory=list)
    #: cell objects from meshes (their ids share the objects' id space)
    mesh_objects: list[PlacedMeshObject] = field(default_factory=list)

    @property
    def humans(self) -> list[PlacedHuman]:
        """Every person in the scene: `human` first, then `extra_humans`."""
        return ([] if self.human is None else [self.human]) + list(self.extra_humans)

    def robot(self, rid: int) -> PlacedRobot:
        """The robot with id `rid`; KeyError when there is none."""
        for r in self.robots:
            if r.id == rid:
                return r
        raise KeyError(f"scene has no robot {rid}")

    @property
    def floor_area(self) -> float:
        """Area (m^2) of the floor where items' centres may go; H_pos and O_pos are 1 / it."""
        return (self.floor_hi[0] - self.floor_lo[0]) * (self.floor_hi[1] - self.floor_lo[1])

    @property
    def bounds(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """(lo, hi) corners footprints must stay within; the floor when no bounds are set."""
        lo = self.floor_lo if self.bounds_lo is None else self.bounds_lo
        hi = self.floor_hi if self.bounds_hi is None else self.bounds_hi
        return tuple(lo), tuple(hi)

    def object(self, oid: int) -> PlacedObject | PlacedMeshObject:
        """The object (or mesh object) with id `oid`; KeyError when there is none."""
        for o in [*self.objects, *self.mesh_objects]:
            if o.id == oid:
                return o
        raise KeyError(f"scene has no object {oid}")

    def next_id(self) -> int:
        """The id a new object or robot takes: one past the highest in use (0 in an empty
        scene; the paper's scenes number their objects 0, 1, 2, ...)."""
        ids = [o.id for o in [*self.objects, *self.mesh_objects]] + [r.id for r in self.robots]
        return 1 + max(ids, default=-1)

    def related(self, a, b) -> list[Relation]:
        """Relations between items `a` and `b`, in either direction (ids, or HUMAN)."""
        return [r for r in self.relations if {r.subject, r.object} == {a, b}]

    def to_dict(self) -> dict:
        """JSON-able description of the frame, as a dataset stores it; `from_dict` reads it back."""
        return {
            "mode": self.mode,
            "room": self.room,
            "floor_lo": list(self.floor_lo),
            "floor_hi": list(self.floor_hi),
            "bounds_lo": list(self.bounds[0]),
            "bounds_hi": list(self.bounds[1]),
            "theta_ho": self.theta_ho,
            "theta_oo": self.theta_oo,
            "objects": [o.to_dict() for o in self.objects],
            "human": None if self.human is None else self.human.to_dict(),
            "relations": [r.to_dict() for r in self.relations],
            "mount": None if self.mount is None else self.mount.to_dict(),
            # only cells have these: the paper's scenes keep their records as they were
            **({"robots": [r.to_dict() for r in self.robots]} if self.robots else {}),
            **(
                {"extra_humans": [h.to_dict() for h in self.extra_humans]}
                if self.extra_humans
                else {}
            ),
            **(
                {"mesh_objects": [m.to_dict() for m in self.mesh_objects]}
                if self.mesh_objects
                else {}
            ),
        }

    @classmethod
    def from_dict(cls, d: dict) -> Scene:
        """The scene a `to_dict` description records, exactly."""
        return cls(
            d["mode"],
            d["room"],
            tuple(d["floor_lo"]),
            tuple(d["floor_hi"]),
            float(d["theta_ho"]),
            float(d["theta_oo"]),
            [PlacedObject.from_dict(o) for o in d["objects"]],
            None if d.get("human") is None else PlacedHuman.from_dict(d["human"]),
            [Relation.from_dict(r) for r in d["relations"]],
            tuple(d["bounds_lo"]) if d.get("bounds_lo") is not None else None,
            tuple(d["bounds_hi"]) if d.get("bounds_hi") is not None else None,
            None if d.get("mount") is None else TopViewMount.from_dict(d["mount"], "scene mount"),
            [PlacedRobot.from_dict(r) for r in d.get("robots", [])],
            [PlacedHuman.from_dict(h) for h in d.get("extra_humans", [])],
            [PlacedMeshObject.from_dict(m) for m in d.get("mesh_objects", [])],
        )
