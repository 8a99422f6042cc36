"""Cell objects from meshes (label `object`): shapes nobody modelled, at real sizes.

The procedural cell objects (`cell_objects`) are boxes, cylinders and spheres; a model that
has seen only those may still call an object of another shape a person. The catalogue
(`CATALOGUE`) adds triangle meshes, read by trimesh and rendered as `render.Triangles`:

- from pybullet_data: `random_urdf` (its 1000 irregular `random_urdfs/NNN/NNN.obj` shapes as
  machine parts, castings, fixtures and sacks), `kiva_shelf` (a warehouse rack), `husky` (a
  mobile platform without an arm: an AGV), `racecar` (its chassis and wheels as a cart) and
  `teddy`, `duck`, `bunny`, `stone`, `soccerball` (lumpy parts on tables, sacks on the floor);
- made by trimesh from a seed, so the catalogue is not a fixed list: `tank`, `bottle`,
  `bucket`, `reel`, `stand` (a random profile revolved) and `bracket`, `guard`,
  `machine_base`, `beam` (random polygons and L, U, T profiles extruded).

Each entry is drawn at a real size: its `measure` (overall height, largest extent or footprint
length) uniform in its floor range, or in its table range as a part on a table top, the mesh
scaled uniformly to it; at a random yaw; some lying on a side (`lie` 1: turned 90 degrees
about x, 2: about y). A mesh keeps at most `robots.MAX_LINK_FACES` triangles (denser ones are
decimated as robot links are) and is cached per process (`mesh_model`).

`PlacedMeshObject` places one in a scene (`Scene.mesh_objects`): entry, its parameters (a
file's index, a generator's seed), scale, lie and pose, all JSON, so a frame's scene
reproduces exactly. trimesh, shapely and pybullet_data come with the `train` extra.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import ConvexHull

from topseg.core import labels
from topseg.core.errors import TopsegError
from topseg.core.synth.geometry import quat_from_axis_angle, quat_to_matrix, yaw_quat
from topseg.core.synth.render import Triangles
from topseg.core.synth.robots import data_root, decimated, import_train_module, robot_model

#: how many shapes pybullet_data's random_urdfs holds
N_RANDOM_URDFS = 1000
#: the sizes a mesh object's dimension is measured by (`MeshEntry.measure`)
MEASURES = ("height", "extent", "length")
#: lie codes: upright, on its side (about x), on its end (about y)
LIES = (0, 1, 2)


def _train_module(module: str):
    """A package of the `train` extra that mesh objects need (a TopsegError without it)."""
    return import_train_module(module, "mesh cell objects")


@dataclass(frozen=True)
class MeshEntry:
    """One catalogue entry: where its mesh comes from and the sizes it is drawn at.

    `source`: "file" (`path` in pybullet_data, `up` "y" for a mesh drawn y up), "random_urdf"
    (params {"index": n}), "husky", "racecar", or a generator's name (params {"seed": n}).
    `floor_m` / `table_m`: range (m) of `measure` standing on the floor / as a part on a table
    top (None: never there). `lies`: the lie codes it may be drawn in.
    """

    source: str
    floor_m: tuple[float, float] | None
    table_m: tuple[float, float] | None = None
    measure: str = "height"
    lies: tuple[int, ...] = (0,)
    path: str = ""
    up: str = "z"


_LUMPY = (0, 1, 2)
CATALOGUE: dict[str, MeshEntry] = {
    "random_urdf": MeshEntry("random_urdf", (0.2, 1.4), (0.08, 0.4), "extent", _LUMPY),
    "kiva_shelf": MeshEntry("file", (1.5, 2.2), None, "height",
                            path="kiva_shelf/meshes/pod_lowres.stl", up="y"),
    "husky": MeshEntry("husky", (0.8, 1.4), None, "length"),
    "racecar": MeshEntry("racecar", (0.8, 1.5), None, "length"),
    "teddy": MeshEntry("file", (0.4, 0.9), (0.15, 0.4), "extent", _LUMPY,
                       "teddy2_VHACD_CHs.obj", "y"),
    "duck": MeshEntry("file", (0.3, 0.7), (0.1, 0.35), "extent", _LUMPY, "duck_vhacd.obj", "y"),
    "bunny": MeshEntry("file", (0.3, 0.7), (0.1, 0.35), "extent", _LUMPY, "bunny.obj"),
    "stone": MeshEntry("file", (0.3, 0.8), (0.1, 0.4), "extent", (0,), "stone.obj"),
    "soccerball": MeshEntry("file", (0.25, 0.6), (0.1, 0.3), "extent", (0,), "soccerball.obj"),
    "tank": MeshEntry("tank", (0.6, 1.9)),
    "bottle": MeshEntry("bottle", None, (0.15, 0.45), "extent", (0, 1)),
    "bucket": MeshEntry("bucket", (0.25, 0.5), (0.12, 0.3)),
    "reel": MeshEntry("reel", (0.3, 1.2), (0.1, 0.3), "extent", (0, 1)),
    "stand": MeshEntry("stand", (0.6, 1.6)),
    "bracket": MeshEntry("bracket", (0.3, 0.9), (0.08, 0.35), "extent", _LUMPY),
    "guard": MeshEntry("guard", (0.8, 2.0)),
    "machine_base": MeshEntry("machine_base", (0.6, 2.2), None, "length"),
    "beam": MeshEntry("beam", (0.6, 2.2), (0.2, 0.6), "extent", (1, 2)),
}  # fmt: skip
#: the catalogue's entry names
MESH_OBJECTS: tuple[str, ...] = tuple(CATALOGUE)
#: entries that may stand on the floor / lie on a table top
FLOOR_ENTRIES = tuple(k for k, e in CATALOGUE.items() if e.floor_m is not None)
TABLE_ENTRIES = tuple(k for k, e in CATALOGUE.items() if e.table_m is not None)


# --- the meshes ----------------------------------------------------------------------------


@dataclass(frozen=True)
class MeshModel:
    """One entry's mesh at unit scale, upright: triangles (n, 3, 3) with the bounding box's
    floor centre at the origin, and the corners of their convex hull (what footprints and
    extents are computed from)."""

    name: str
    triangles: np.ndarray = field(repr=False)
    hull: np.ndarray = field(repr=False)

    def size(self, measure: str, lie: int = 0) -> float:
        """The mesh's `measure` at unit scale, lying as `lie` says."""
        ext = np.ptp(self.hull @ lie_matrix(lie).T, axis=0)
        if measure == "height":
            return float(ext[2])
        if measure == "length":
            return float(ext[:2].max())
        return float(ext.max())


def lie_matrix(lie: int) -> np.ndarray:
    """The rotation that lays a mesh down: 0 none, 1 90 degrees about x, 2 about y."""
    if lie == 0:
        return np.eye(3)
    axis = (1.0, 0.0, 0.0) if lie == 1 else (0.0, 1.0, 0.0)
    return quat_to_matrix(quat_from_axis_angle(axis, np.pi / 2))


def _trimesh(vertices, faces):
    return _train_module("trimesh").Trimesh(np.asarray(vertices), np.asarray(faces), process=True)


def _load(path: Path, name: str):
    """A mesh file through trimesh, as one mesh; TopsegError naming the file when unreadable."""
    trimesh = _train_module("trimesh")
    try:
        mesh = trimesh.load(str(path), force="mesh")
    except Exception as exc:
        raise TopsegError(f"mesh object {name}: cannot read {path}: {exc}") from None
    if len(getattr(mesh, "faces", ())) == 0:
        raise TopsegError(f"mesh object {name}: {path} has no triangles")
    return mesh


def _placed_copy(mesh, xyz=(0.0, 0.0, 0.0), yaw: float = 0.0):
    mesh = mesh.copy()
    m = np.eye(4)
    m[:3, :3] = quat_to_matrix(yaw_quat(yaw))
    m[:3, 3] = xyz
    mesh.apply_transform(m)
    return mesh


def _husky(root: Path):
    """The Husky platform from its URDF's meshes and offsets (base link frame): body, top
    plate, rail, bumpers and four wheels; the URDF itself needs ROS environment values."""
    trimesh = _train_module("trimesh")
    d = root / "husky" / "meshes"
    wheel = _load(d / "wheel.stl", "husky")
    bumper = _load(d / "bumper.stl", "husky")
    parts = [_load(d / "base_link.stl", "husky"), _load(d / "top_plate.stl", "husky"),
             _placed_copy(_load(d / "user_rail.stl", "husky"), (0.272, 0.0, 0.245)),
             _placed_copy(bumper, (0.48, 0.0, 0.091)),
             _placed_copy(bumper, (-0.48, 0.0, 0.091), np.pi)]  # fmt: skip
    parts += [_placed_copy(wheel, (sx * 0.256, sy * 0.2854, 0.03282))
              for sx in (-1, 1) for sy in (-1, 1)]  # fmt: skip
    return trimesh.util.concatenate(parts)


def _racecar(root: Path):
    """pybullet's racecar at rest: chassis and wheels (its URDF posed by the robots' reader),
    its primitive shapes turned into triangles."""
    model = robot_model(str(root / "racecar" / "racecar.urdf"))
    prims, tris = model.link_geometry({}, np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))
    trimesh = _train_module("trimesh")
    meshes = [_trimesh(tris.vertices.reshape(-1, 3), np.arange(3 * len(tris)).reshape(-1, 3))]
    for kind, size, centre, rot in zip(prims.kind, prims.size, prims.center, prims.rot,
                                       strict=True):  # fmt: skip
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = rot, centre
        if kind == 2:  # BOX: half sizes
            meshes.append(trimesh.creation.box(extents=2 * size, transform=m))
        elif kind == 1:  # CYLINDER: radius, half length
            meshes.append(trimesh.creation.cylinder(size[0], 2 * size[1], transform=m))
        else:
            meshes.append(trimesh.creation.icosphere(2, size[0]).apply_transform(m))
    return trimesh.util.concatenate(meshes)


# --- generated meshes: a seed's random profile, revolved or extruded ------------------------


def _revolve(profile):
    """A closed solid of revolution about z from (radius, z) points running from the axis
    at the bottom to the axis at the top."""
    trimesh = _train_module("trimesh")
    return trimesh.creation.revolve(np.asarray(profile, np.float64), sections=24)


def _tank(rng):
    """A storage tank or drum: a cylinder on a short skirt, domed or coned top."""
    r = rng.uniform(0.25, 0.5)
    dome = rng.uniform(0.02, 0.3)
    neck = rng.uniform(0.04, 0.12)
    skirt = rng.uniform(0.85, 1.0) * r
    return _revolve([(0, 0), (skirt, 0), (skirt, 0.05), (r, 0.06), (r, 1 - dome - 0.04),
                     (r * 0.5, 1 - 0.04), (neck, 1 - 0.04), (neck, 1), (0, 1)])  # fmt: skip


def _bottle(rng):
    """A bottle or gas cartridge: body, shoulder, neck, cap."""
    r = rng.uniform(0.12, 0.22)
    shoulder = rng.uniform(0.55, 0.8)
    neck = rng.uniform(0.25, 0.5) * r
    return _revolve([(0, 0), (r, 0), (r, shoulder), (neck, shoulder + 0.12), (neck, 0.92),
                     (neck * 1.2, 0.92), (neck * 1.2, 1), (0, 1)])  # fmt: skip


def _bucket(rng):
    """An open bucket or tub: tapered wall, its inside visible from above."""
    r0, r1 = rng.uniform(0.3, 0.45), rng.uniform(0.4, 0.6)
    t = 0.03
    return _revolve([(0, 0), (r0, 0), (r1, 1), (r1 - t, 1), (r0 - t, t), (0, t)])


def _reel(rng):
    """A cable reel standing on its flanges: two discs and a core, its axis horizontal."""
    length = rng.uniform(0.6, 1.4)  # along the axis, against a flange diameter of 1
    f = rng.uniform(0.03, 0.08)
    core = rng.uniform(0.15, 0.35)
    mesh = _revolve([(0, 0), (0.5, 0), (0.5, f), (core, f), (core, length - f),
                     (0.5, length - f), (0.5, length), (0, length)])  # fmt: skip
    m = np.eye(4)
    m[:3, :3] = lie_matrix(1)
    return mesh.apply_transform(m)


def _stand(rng):
    """A stand: a round foot, a pole and a plate or ring on top."""
    foot = rng.uniform(0.12, 0.25)
    pole = rng.uniform(0.015, 0.04)
    top = rng.uniform(0.05, 0.25)
    return _revolve([(0, 0), (foot, 0), (foot, 0.02), (pole, 0.04), (pole, 0.97), (top, 0.97),
                     (top, 1), (0, 1)])  # fmt: skip


def _extrude(points, height: float):
    """A prism: the polygon `points` (x, y) extruded along z by `height`."""
    geometry = _train_module("shapely.geometry")
    trimesh = _train_module("trimesh")
    polygon = geometry.Polygon(points).buffer(0)
    return trimesh.creation.extrude_polygon(polygon, height)


def _profile(rng, kind: str, t: float):
    """An L, U or T cross-section of unit width with walls `t` thick, as polygon points."""
    a = rng.uniform(0.5, 1.0)  # the flange's length against the web's 1
    if kind == "L":
        return [(0, 0), (1, 0), (1, t), (t, t), (t, a), (0, a)]
    if kind == "U":
        return [(0, 0), (1, 0), (1, a), (1 - t, a), (1 - t, t), (t, t), (t, a), (0, a)]
    return [(0, 0), (1, 0), (1, t), (0.5 + t / 2, t), (0.5 + t / 2, a), (0.5 - t / 2, a),
            (0.5 - t / 2, t), (0, t)]  # fmt: skip


def _bracket(rng):
    """A bracket or angle: an L or T profile extruded to a short length, standing."""
    kind = "L" if rng.random() < 0.6 else "T"
    mesh = _extrude(_profile(rng, kind, rng.uniform(0.06, 0.15)), rng.uniform(0.3, 0.9))
    m = np.eye(4)
    m[:3, :3] = lie_matrix(1)  # the profile stands in the x-z plane
    return mesh.apply_transform(m)


def _guard(rng):
    """A machine guard: a U (or L) of thin panels around a spot, its walls extruded up."""
    kind = "U" if rng.random() < 0.7 else "L"
    width = rng.uniform(0.5, 1.2)  # against a height of 1
    pts = np.array(_profile(rng, kind, rng.uniform(0.02, 0.05) / width)) * width
    return _extrude(pts, 1.0)


def _machine_base(rng):
    """A machine base or plinth: a random convex polygon, or an L or T block, extruded."""
    if rng.random() < 0.5:
        pts = rng.uniform(-0.5, 0.5, (int(rng.integers(5, 10)), 2))
        pts = pts[ConvexHull(pts).vertices]
    else:
        pts = _profile(rng, "L" if rng.random() < 0.5 else "T", rng.uniform(0.3, 0.5))
    return _extrude(pts, rng.uniform(0.2, 0.8))


def _beam(rng):
    """A length of profile (L, U or T section) lying along x."""
    kind = ("L", "U", "T")[int(rng.integers(3))]
    section = np.array(_profile(rng, kind, rng.uniform(0.08, 0.2))) * rng.uniform(0.06, 0.15)
    return _extrude(section, 1.0)


GENERATORS = {
    "tank": _tank, "bottle": _bottle, "bucket": _bucket, "reel": _reel, "stand": _stand,
    "bracket": _bracket, "guard": _guard, "machine_base": _machine_base, "beam": _beam,
}  # fmt: skip


def _raw_mesh(name: str, params: dict):
    """The entry's mesh as trimesh gives or makes it, in its own frame and units."""
    entry = CATALOGUE[name]
    if entry.source in GENERATORS:
        return GENERATORS[entry.source](np.random.default_rng(int(params["seed"])))
    root = data_root("pybullet")
    if entry.source == "husky":
        return _husky(root)
    if entry.source == "racecar":
        return _racecar(root)
    if entry.source == "random_urdf":
        n = int(params["index"])
        if not 0 <= n < N_RANDOM_URDFS:
            raise TopsegError(f"mesh object random_urdf: index {n} outside 0..999")
        return _load(root / "random_urdfs" / f"{n:03d}" / f"{n:03d}.obj", name)
    mesh = _load(root / entry.path, name)
    if entry.up == "y":
        m = np.eye(4)
        m[:3, :3] = quat_to_matrix(quat_from_axis_angle((1.0, 0.0, 0.0), np.pi / 2))
        mesh.apply_transform(m)
    return mesh


@functools.lru_cache(maxsize=128)
def _model(name: str, key: tuple) -> MeshModel:
    mesh = _raw_mesh(name, dict(key))
    mesh.merge_vertices()
    mesh = decimated(mesh, f"mesh object {name}")
    tris = np.asarray(mesh.vertices, np.float64)[np.asarray(mesh.faces)]
    points = np.unique(tris.reshape(-1, 3), axis=0)
    hull = points[ConvexHull(points).vertices]
    lo, hi = hull.min(axis=0), hull.max(axis=0)
    origin = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    tris, hull = tris - origin, hull - origin
    tris.flags.writeable = False
    return MeshModel(name, tris, hull)


def mesh_model(name: str, params: dict | None = None) -> MeshModel:
    """The unit-scale model of catalogue entry `name` with `params` (cached per process)."""
    if name not in CATALOGUE:
        raise TopsegError(f"unknown mesh object {name!r}; known: {', '.join(MESH_OBJECTS)}")
    return _model(name, tuple(sorted((params or {}).items())))


def draw_params(rng, name: str) -> dict:
    """The parameters of a new `name` mesh: a random_urdf's index, a generator's seed."""
    source = CATALOGUE[name].source
    if source == "random_urdf":
        return {"index": int(rng.integers(N_RANDOM_URDFS))}
    if source in GENERATORS:
        return {"seed": int(rng.integers(2**31))}
    return {}


# --- a mesh object in a scene ---------------------------------------------------------------


@dataclass(frozen=True)
class Extents:
    """A placed mesh object's size (m) in its own frame: what relations ask an item's model."""

    size_x: float
    size_y: float
    size_z: float


@dataclass
class PlacedMeshObject:
    """A catalogue mesh in a scene, labelled object.

    `name` its catalogue entry and `params` that entry's parameters; `scale` the uniform
    factor from unit to real size; `lie` how it is laid down (LIES); `x, y` the centre of its
    footprint's bounding box (world, m), `z` the height its lowest point rests at, `yaw` its
    heading; `support` the id of the table it lies on (None: the floor). `id` shares the id
    space of the scene's objects and robots.
    """

    id: int
    name: str
    params: dict
    scale: float
    lie: int
    x: float
    y: float
    z: float = 0.0
    yaw: float = 0.0
    support: int | None = None

    def __post_init__(self) -> None:
        if self.lie not in LIES:
            raise ValueError(f"mesh object lie {self.lie!r}: one of {LIES}")

    #: what the scene's overlap rules and people relations see it as
    cls = "object"

    @property
    def kind(self) -> str:
        """Its kind as scene records name kinds: "mesh:" and its entry."""
        return f"mesh:{self.name}"

    def mesh(self) -> MeshModel:
        """Its unit-scale mesh (cached)."""
        return mesh_model(self.name, self.params)

    def _local(self, points: np.ndarray) -> np.ndarray:
        """Unit-mesh points -> its own frame (scaled, laid down, bounding box floor centre at
        the origin), before yaw."""
        lie = lie_matrix(self.lie)
        hull = self.mesh().hull @ lie.T
        lo, hi = hull.min(axis=0), hull.max(axis=0)
        origin = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
        return self.scale * (points @ lie.T - origin)

    def _world(self, points: np.ndarray) -> np.ndarray:
        rot = quat_to_matrix(yaw_quat(self.yaw))
        return self._local(points) @ rot.T + np.array([self.x, self.y, self.z])

    def model(self) -> Extents:
        """Its extents in its own frame (relations read `size_x` and `size_y`)."""
        ext = self.scale * np.ptp(self.mesh().hull @ lie_matrix(self.lie).T, axis=0)
        return Extents(float(ext[0]), float(ext[1]), float(ext[2]))

    @property
    def height(self) -> float:
        """Its height (m) as it lies."""
        return self.model().size_z

    def size(self) -> float:
        """Its entry's measure (m): what its drawn size range bounds."""
        return self.scale * self.mesh().size(CATALOGUE[self.name].measure, self.lie)

    def geometry(self) -> Triangles:
        """Its triangles in the world frame, labelled object."""
        tris = self._world(self.mesh().triangles.reshape(-1, 3)).reshape(-1, 3, 3)
        return Triangles(tris, np.full(len(tris), labels.OBJECT, np.uint8))

    def footprint(self) -> np.ndarray:
        """(k, 2) convex polygon (CCW) on the floor under it."""
        points = self._world(self.mesh().hull)[:, :2]
        return points[ConvexHull(points).vertices]

    def z_range(self) -> tuple[float, float]:
        """Lowest and highest z (m)."""
        return float(self.z), float(self.z + self.height)

    def to_world(self, local_xy) -> np.ndarray:
        """Its own frame -> world floor point(s)."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        p = np.asarray(local_xy, np.float64)
        return np.stack(
            [self.x + c * p[..., 0] - s * p[..., 1], self.y + s * p[..., 0] + c * p[..., 1]],
            axis=-1,
        )

    def to_dict(self) -> dict:
        """JSON-able record; `from_dict` reads it back exactly."""
        return {
            "id": self.id,
            "name": self.name,
            "params": dict(self.params),
            "scale": self.scale,
            "lie": self.lie,
            "x": self.x,
            "y": self.y,
            "z": self.z,
            "yaw": self.yaw,
            "support": self.support,
        }

    @classmethod
    def from_dict(cls, d: dict) -> PlacedMeshObject:
        """The mesh object a `to_dict` record describes."""
        return cls(
            id=int(d["id"]), name=str(d["name"]),
            params={str(k): int(v) for k, v in d.get("params", {}).items()},
            scale=float(d["scale"]), lie=int(d.get("lie", 0)), x=float(d["x"]),
            y=float(d["y"]), z=float(d.get("z", 0.0)), yaw=float(d.get("yaw", 0.0)),
            support=None if d.get("support") is None else int(d["support"]),
        )  # fmt: skip


def draw(rng, oid: int, on_table: bool, x: float = 0.0, y: float = 0.0) -> PlacedMeshObject:
    """A random catalogue mesh at a real size for the floor (or a table top), random yaw and
    lie, at (x, y)."""
    pool = TABLE_ENTRIES if on_table else FLOOR_ENTRIES
    name = str(pool[int(rng.integers(len(pool)))])
    entry = CATALOGUE[name]
    params = draw_params(rng, name)
    lie = int(entry.lies[int(rng.integers(len(entry.lies)))])
    lo, hi = entry.table_m if on_table else entry.floor_m
    unit = mesh_model(name, params).size(entry.measure, lie)
    scale = float(rng.uniform(lo, hi)) / unit
    return PlacedMeshObject(oid, name, params, scale, lie, float(x), float(y), 0.0,
                            float(rng.uniform(0, 2 * np.pi)))  # fmt: skip


def size_ok(obj: PlacedMeshObject, tol: float = 1e-6) -> bool:
    """Whether a placed mesh object's size and lie are within its entry's ranges (the table
    range when it lies on a support)."""
    entry = CATALOGUE.get(obj.name)
    if entry is None or obj.lie not in entry.lies:
        return False
    bounds = entry.table_m if obj.support is not None else entry.floor_m
    if bounds is None:
        return False
    return bounds[0] - tol <= obj.size() <= bounds[1] + tol
