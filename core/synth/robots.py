"""Robot arms from URDF: a catalogue of industrial and collaborative arms, posable, as geometry
the ray caster renders (labelled robot), and how a scene places one (`PlacedRobot`).

A `RobotModel` is one URDF, parsed by yourdfpy and posed by `kinematics` (one walk down its
tree, mimic joints included): each link's collision geometry where it has one, else its visual geometry. URDF
boxes, cylinders and spheres become `render.Primitives`; meshes are read by trimesh at the
URDF's scale and become `render.Triangles`. A link's meshes are kept at most
`MAX_LINK_FACES` triangles: a denser link is reduced by trimesh's quadric decimation
(fast-simplification), which keeps the link's silhouette and volume within a percent. Its
convex hull would not do: the shipped collision meshes are already convex hulls, as dense as
the visual ones (KUKA KR6's link_1 has 19 108 faces), so only decimation bounds them. Models
are cached per name or path, so each process reads a URDF and its meshes once.

The catalogue (`ROBOTS`) draws on pybullet_data (Franka Panda with its hand, KUKA LBR iiwa,
UFactory xArm 6 with its gripper) and rtb-data (ABB IRB 140, KUKA KR 3 / 6 / 10 / 16 / 120 /
150 / 210, LBR iiwa 14, Unimation Puma 560, Interbotix PincherX 150 / WidowX 250 s / ViperX
300 s): cobots of half a metre's reach to a 3 m KR 210. rtb-data ships some arms as xacro,
expanded by xacrodoc with the package names its files use mapped to its folders. Its IRB 140
URDF is drawn about 3.9 times too large (joint offsets 0.28 / 1.38 / 1.42 / 1.49 m against
ABB's 0.070 / 0.352 / 0.360 / 0.380 m): the catalogue scales it back. Mobile and
free-floating bases (rtb-data's Ridgeback and Frankie) are left out.

A random arm (`random_arms`) loads by its seed, `robot_model("random:17")`: its URDF is
generated and parsed like a file's, its tool link is `random_arms.TOOL_LINK`, and the last
RANDOM_CACHE of them stay cached. A malformed name (`random:x`) is a `TopsegError` naming it.

Any other fixed-base URDF loads by its path (`robot_model("/path/arm.urdf")`, `.xacro` too):
meshes by relative paths, `file://` or `package://NAME/...` resolved beside it (in NAME/... or
in ... in the URDF's folder or one above it). A missing or unparsable file, a missing or
unreadable mesh, no movable joint, or a floating base is a `TopsegError` naming the file.

The robot's base frame is its URDF root link; the tool is the catalogue's tool link, or for
another URDF the end of the chain that carries the most movable joints (where it forks into
fingers, the link before the fork).

`PlacedRobot` places a model in a scene: on the floor, on a pedestal, on a table (the table is
the scene's own object) or hanging upside down from a gantry's beam. yourdfpy, trimesh,
xacrodoc, rtb-data and pybullet_data come with the `train` extra and are imported when a
model is first loaded.
"""

from __future__ import annotations

import importlib
import io
import re
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from topseg.core import labels
from topseg.core.errors import TopsegError
from topseg.core.extras import import_failure
from topseg.core.synth.geometry import (
    BOX,
    CYLINDER,
    SPHERE,
    aabb,
    quat_from_axis_angle,
    quat_mul,
    quat_to_matrix,
    yaw_quat,
)
from topseg.core.synth.kinematics import Kinematics
from topseg.core.synth.random_arms import TOOL_LINK, random_arm_urdf
from topseg.core.synth.render import Primitives, Triangles

#: most triangles one link keeps; denser links are decimated
MAX_LINK_FACES = 1500

#: how a robot is mounted (`PlacedRobot.mount`)
MOUNTS = ("floor", "pedestal", "table", "gantry")
#: a gantry's beam: square section (m); its posts: square section (m); the posts stand this
#: far (m) beyond the robot's reach on either side of its base, along its local y
GANTRY_BEAM = 0.2
GANTRY_POST = 0.15
GANTRY_CLEARANCE = 0.3


@dataclass(frozen=True)
class CatalogueEntry:
    """Where a catalogue robot's URDF lives and what the catalogue adds to it.

    `source`: "pybullet" (pybullet_data) or "rtb" (rtb-data's xacro folder); `path` inside it;
    `tool`: the tool link; `scale`: a uniform factor for URDFs drawn at the wrong size;
    `xacro_args`: values of a xacro file's arguments.
    """

    source: str
    path: str
    tool: str
    scale: float = 1.0
    xacro_args: tuple[tuple[str, str], ...] = ()


def _trossen(name: str) -> CatalogueEntry:
    return CatalogueEntry(
        "rtb", f"trossen_descriptions/urdf/{name}.urdf.xacro", f"{name}/ee_gripper_link",
        xacro_args=(("robot_name", name),),
    )  # fmt: skip


_KUKA = "kuka_description"
CATALOGUE: dict[str, CatalogueEntry] = {
    "panda": CatalogueEntry("pybullet", "franka_panda/panda.urdf", "panda_grasptarget"),
    "kuka_iiwa": CatalogueEntry("pybullet", "kuka_iiwa/model.urdf", "lbr_iiwa_link_7"),
    "xarm6": CatalogueEntry("pybullet", "xarm/xarm6_with_gripper.urdf", "xarm_gripper_base_link"),
    "abb_irb140": CatalogueEntry(
        "rtb", "abb_irb140_description/urdf/irb140.urdf", "tool0", scale=0.254
    ),
    "kuka_kr3": CatalogueEntry("rtb", f"{_KUKA}/kuka_kr3/urdf/kr3r540.xacro", "tool0"),
    "kuka_kr6": CatalogueEntry("rtb", f"{_KUKA}/kuka_kr6/urdf/kr6r900sixx.xacro", "tool0"),
    "kuka_kr10": CatalogueEntry("rtb", f"{_KUKA}/kuka_kr10/urdf/kr10r1100sixx.xacro", "tool0"),
    "kuka_kr16": CatalogueEntry("rtb", f"{_KUKA}/kuka_kr16/urdf/kr16_2.urdf", "tool0"),
    "kuka_kr120": CatalogueEntry("rtb", f"{_KUKA}/kuka_kr120/urdf/kr120r2500pro.urdf", "tool0"),
    "kuka_kr150": CatalogueEntry("rtb", f"{_KUKA}/kuka_kr150/urdf/kr150_2.xacro", "tool0"),
    "kuka_kr210": CatalogueEntry("rtb", f"{_KUKA}/kuka_kr210/urdf/kr210l150.urdf", "tool0"),
    "lbr_iiwa14": CatalogueEntry(
        "rtb", f"{_KUKA}/kuka_lbr_iiwa/urdf/lbr_iiwa_14_r820.urdf", "tool0"
    ),
    "puma560": CatalogueEntry(
        "rtb", "unimation_puma560_description/urdf/puma560_robot.urdf", "link7"
    ),
    "interbotix_px150": _trossen("px150"),
    "interbotix_wx250s": _trossen("wx250s"),
    "interbotix_vx300s": _trossen("vx300s"),
}
#: the catalogue's robot names
ROBOTS: tuple[str, ...] = tuple(CATALOGUE)
#: a random arm is named RANDOM + ":" + its seed (`random_arm_name`); RANDOM alone, in a list
#: of robot names, asks for random arms
RANDOM = "random"
#: how many random arms stay cached (a dataset draws thousands of them)
RANDOM_CACHE = 64

#: ROS package names that rtb-data's xacro files ask for -> their folders in rtb-data
_RTB_PACKAGES = {
    **{
        f"kuka_{m}_support": f"{_KUKA}/kuka_{m}"
        for m in ("kr3", "kr5", "kr6", "kr10", "kr16", "kr120", "kr150", "kr210", "lbr_iiwa")
    },
    "kuka_resources": f"{_KUKA}/kuka_resources",
    "abb_irb140": "abb_irb140_description",
    "abb_irb140_support": "abb_irb140_description",
    "trossen_descriptions": "trossen_descriptions",
    "unimation_puma560_description": "unimation_puma560_description",
}


# --- reading a URDF -----------------------------------------------------------------------


def import_train_module(module: str, purpose: str = "robot models"):
    """An optional package of the `train` extra, or a TopsegError saying that `purpose` needs
    it and how to install it."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise TopsegError(import_failure(purpose, module, "train", exc)) from None


def data_root(source: str) -> Path:
    """pybullet_data's folder ("pybullet") or rtb-data's xacro folder ("rtb")."""
    if source == "pybullet":
        return Path(import_train_module("pybullet_data").getDataPath())
    return Path(import_train_module("rtbdata").__file__).parent / "xacro"


_XACRO_LOCK = threading.Lock()  # xacro keeps its state in module globals


def _expand_xacro(path: Path, args: dict[str, str], packages: dict[str, Path]) -> str:
    """The URDF text of a xacro file, its `$(find NAME)` and `package://NAME` resolved."""
    xacrodoc = import_train_module("xacrodoc")
    with _XACRO_LOCK:
        xacrodoc.packages.update_package_cache({k: str(v) for k, v in packages.items()})
        try:
            doc = xacrodoc.XacroDoc.from_file(str(path), walk_up=not packages, subargs=dict(args))
            return doc.to_urdf_string()
        except Exception as exc:
            raise TopsegError(f"robot {path}: cannot expand xacro: {_one_line(exc)}") from None


def _one_line(exc: BaseException) -> str:
    """An exception as one short line."""
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}".rstrip(": ")


def _resolve_mesh(filename: str, urdf_dir: Path) -> Path | None:
    """The file a URDF mesh name points to, or None: relative to the URDF's folder, file://,
    or package://NAME/REST found as NAME/REST or REST in the URDF's folder or one above it."""
    if filename.startswith("file://"):
        return Path(filename[len("file://") :])
    if filename.startswith("package://"):
        package, _, rest = filename[len("package://") :].partition("/")
        for folder in (urdf_dir, *urdf_dir.parents):
            for candidate in (folder / package / rest, folder / rest):
                if candidate.is_file():
                    return candidate
        return None
    return urdf_dir / filename


def _load_urdf(source, label: str):
    """yourdfpy's URDF (no meshes; `kinematics` poses it). The XML must be
    well formed: yourdfpy would recover what it can from a broken file."""
    yourdfpy = import_train_module("yourdfpy")
    etree = import_train_module("lxml.etree")
    try:
        etree.parse(source)
    except (OSError, etree.XMLSyntaxError) as exc:
        raise TopsegError(f"robot {label}: cannot read URDF: {_one_line(exc)}") from None
    if isinstance(source, io.StringIO):
        source.seek(0)
    try:
        return yourdfpy.URDF.load(
            source, load_meshes=False, build_scene_graph=True,
            load_collision_meshes=False, build_collision_scene_graph=False,
        )  # fmt: skip
    except Exception as exc:
        raise TopsegError(f"robot {label}: cannot read URDF: {_one_line(exc)}") from None


def decimated(mesh, what: str):
    """`mesh` reduced to at most MAX_LINK_FACES triangles by quadric decimation; `what` names
    the mesh in a TopsegError when it cannot be."""
    if len(mesh.faces) <= MAX_LINK_FACES:
        return mesh
    import_train_module("fast_simplification")
    try:
        return mesh.simplify_quadric_decimation(face_count=MAX_LINK_FACES)
    except Exception as exc:
        raise TopsegError(f"{what}: cannot simplify its mesh: {_one_line(exc)}") from None


def _read_mesh(element, urdf_dir: Path, label: str, link: str) -> np.ndarray:
    """(m, 3, 3) triangles of one URDF mesh element, at its scale, in its own frame."""
    trimesh = import_train_module("trimesh")
    name = element.filename
    path = _resolve_mesh(name, urdf_dir)
    if path is None or not path.is_file():
        raise TopsegError(f"robot {label}: link {link!r}: mesh {name!r} not found")
    try:
        mesh = trimesh.load(str(path), force="mesh")
    except Exception as exc:
        raise TopsegError(
            f"robot {label}: link {link!r}: cannot read mesh {path}: {_one_line(exc)}"
        ) from None
    if len(getattr(mesh, "faces", ())) == 0:
        raise TopsegError(f"robot {label}: link {link!r}: mesh {path} has no triangles")
    scale = np.ones(3) if element.scale is None else np.broadcast_to(element.scale, 3)
    return np.asarray(mesh.vertices, np.float64)[np.asarray(mesh.faces)] * scale


@dataclass
class _LinkShapes:
    """One link's geometry in the link's frame: triangles and primitives (kind, size, 4x4)."""

    triangles: np.ndarray
    kinds: list[int] = field(default_factory=list)
    sizes: list[tuple[float, float, float]] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)


def _transform(pose: np.ndarray | None) -> np.ndarray:
    return np.eye(4) if pose is None else np.asarray(pose, np.float64)


def _link_shapes(link, urdf_dir: Path, label: str) -> _LinkShapes | None:
    """A link's collision geometry, else its visual geometry; None when it has neither."""
    elements = link.collisions or link.visuals
    if not elements:
        return None
    trimesh = import_train_module("trimesh")
    shapes = _LinkShapes(np.zeros((0, 3, 3)))
    meshes = []
    for element in elements:
        pose = _transform(element.origin)
        g = element.geometry
        if g.mesh is not None:
            tris = _read_mesh(g.mesh, urdf_dir, label, link.name)
            meshes.append(tris @ pose[:3, :3].T + pose[:3, 3])
        elif g.box is not None:
            shapes.kinds.append(BOX)
            shapes.sizes.append(tuple(0.5 * float(s) for s in g.box.size))
            shapes.poses.append(pose)
        elif g.cylinder is not None:
            shapes.kinds.append(CYLINDER)
            shapes.sizes.append((float(g.cylinder.radius), 0.5 * float(g.cylinder.length), 0.0))
            shapes.poses.append(pose)
        elif g.sphere is not None:
            shapes.kinds.append(SPHERE)
            shapes.sizes.append((float(g.sphere.radius), 0.0, 0.0))
            shapes.poses.append(pose)
    if meshes:
        tris = np.concatenate(meshes)
        if len(tris) > MAX_LINK_FACES:
            mesh = trimesh.Trimesh(tris.reshape(-1, 3), np.arange(3 * len(tris)).reshape(-1, 3))
            mesh.merge_vertices()
            mesh = decimated(mesh, f"robot {label}: link {link.name!r}")
            tris = np.asarray(mesh.vertices, np.float64)[np.asarray(mesh.faces)]
        shapes.triangles = tris
    return shapes


def _movable(joint) -> bool:
    return joint.type not in ("fixed",)


def _children(urdf, link: str) -> list:
    return [j for j in urdf.robot.joints if j.parent == link]


def _movable_below(urdf, joint) -> int:
    """Movable joints in `joint` and the subtree under it."""
    below = sum(_movable_below(urdf, j) for j in _children(urdf, joint.child))
    return below + (1 if _movable(joint) else 0)


def _find_tool(urdf) -> str:
    """The end of the chain with the most movable joints; at a fork into equal movable
    branches (fingers), the link before it; past the last movable joint, fixed frames are
    followed (a tool frame first, by name)."""
    link = urdf.base_link
    while True:
        joints = _children(urdf, link)
        if not joints:
            return link
        counts = [_movable_below(urdf, j) for j in joints]
        best = max(counts)
        if best > 0:
            if counts.count(best) > 1:
                return link
            link = joints[counts.index(best)].child
            continue
        named = [j for j in joints if any(k in j.child.lower() for k in ("tool", "tcp", "ee"))]
        link = (named or joints)[0].child


def _chain(urdf, tool: str) -> list:
    """The joints from the root link to `tool`, in order."""
    by_child = {j.child: j for j in urdf.robot.joints}
    chain = []
    link = tool
    while link in by_child:
        chain.append(by_child[link])
        link = by_child[link].parent
    return chain[::-1]


def _limits(joint) -> tuple[float, float]:
    """A joint's range: continuous ones (and revolute ones with no limit) [-pi, pi]."""
    if joint.type == "continuous" or joint.limit is None:
        return (-np.pi, np.pi) if joint.type in ("continuous", "revolute") else (0.0, 0.0)
    lo = joint.limit.lower if joint.limit.lower is not None else 0.0
    hi = joint.limit.upper if joint.limit.upper is not None else 0.0
    return float(lo), float(hi)


class RobotModel:
    """One robot arm: its movable joints, their limits, its reach and its posed geometry.

    `joint_names` are the URDF's movable joints (mimic joints follow theirs); `lower` and
    `upper` their limits (continuous joints: [-pi, pi]); `reach_m` bounds the distance from
    the base (the root link's origin) to the tool. Poses are dicts joint name -> value
    (radians or metres); a joint left out is at 0 (within its limits).
    """

    def __init__(self, name: str, urdf, urdf_dir: Path, tool: str | None, scale: float = 1.0):
        self.name = name
        self._urdf = urdf
        self._scale = float(scale)
        # the last configuration posed and every link's pose there: a frame's capsules,
        # silhouette and hull ask for the same joints in turn
        self._last_poses: tuple[bytes, np.ndarray] | None = None
        label = name
        floating = [j.name for j in urdf.robot.joints if j.type in ("floating", "planar")]
        if floating:
            raise TopsegError(
                f"robot {label}: joint {floating[0]!r} is a floating or planar base: "
                "only fixed-base arms are supported"
            )
        self.joint_names: tuple[str, ...] = tuple(urdf.actuated_joint_names)
        if not self.joint_names:
            raise TopsegError(f"robot {label}: the URDF has no movable joint")
        limits = [_limits(urdf.joint_map[j]) for j in self.joint_names]
        self.lower = np.array([lo for lo, _ in limits])
        self.upper = np.array([hi for _, hi in limits])
        self.tool_link = tool or _find_tool(urdf)
        if self.tool_link not in urdf.link_map:
            raise TopsegError(f"robot {label}: no link {self.tool_link!r} for the tool")
        self._kinematics = Kinematics.of(urdf)
        self._link_index = {link: i for i, link in enumerate(self._kinematics.links)}
        self.reach_m = self._scale * self._chain_length()
        self._links, self._tri_blocks, self._tris, prims = self._collect(urdf_dir, label)
        self._prim_link, self._prim_kind, self._prim_size, self._prim_pose = prims
        if not len(self._tris) and not len(self._prim_kind):
            raise TopsegError(f"robot {label}: the URDF has no geometry")
        self._hull_points = [_hull_vertices(self._tris[lo:hi]) for lo, hi in self._tri_blocks]

    def _chain_length(self) -> float:
        """Sum of the joint offsets (and prismatic travel) from the base to the tool."""
        total = 0.0
        for joint in _chain(self._urdf, self.tool_link):
            total += float(np.linalg.norm(_transform(joint.origin)[:3, 3]))
            if joint.type == "prismatic":
                total += max(abs(v) for v in _limits(joint))
        return total

    def _collect(self, urdf_dir: Path, label: str):
        """Every link's shapes, flattened: the links' names, each one's block of the
        triangles (lo, hi), the triangles, and the primitives with their link's index."""
        links, tris = [], []
        p_link, p_kind, p_size, p_pose = [], [], [], []
        for link in self._urdf.robot.links:
            shapes = _link_shapes(link, urdf_dir, label)
            if shapes is None:
                continue
            index = len(links)
            links.append(link.name)
            tris.append(shapes.triangles)
            p_link += [index] * len(shapes.kinds)
            p_kind += shapes.kinds
            p_size += shapes.sizes
            p_pose += shapes.poses
        prims = (
            np.array(p_link, np.int64),
            np.array(p_kind, np.int32),
            np.array(p_size, np.float64).reshape(-1, 3),
            np.array(p_pose, np.float64).reshape(-1, 4, 4),
        )
        ends = np.cumsum([len(t) for t in tris], dtype=np.int64)
        blocks = [(int(e - len(t)), int(e)) for e, t in zip(ends, tris, strict=True)]
        tris = np.concatenate(tris) if tris else np.zeros((0, 3, 3))
        return links, blocks, tris, prims

    @property
    def triangle_count(self) -> int:
        """How many triangles the posed arm has."""
        return len(self._tris)

    def shape_links(self) -> tuple[tuple[str, ...], np.ndarray, np.ndarray]:
        """(link names, each triangle's link index, each primitive's link index), in the order
        `link_geometry` gives the triangles and primitives."""
        tri_link = np.zeros(len(self._tris), np.int64)
        for i, (lo, hi) in enumerate(self._tri_blocks):
            tri_link[lo:hi] = i
        return tuple(self._links), tri_link, self._prim_link.copy()

    def random_joints(self, rng: np.random.Generator) -> dict[str, float]:
        """Each joint uniform within its limits."""
        values = rng.uniform(self.lower, self.upper)
        return {n: float(v) for n, v in zip(self.joint_names, values, strict=True)}

    def _configuration(self, joints: dict[str, float]) -> np.ndarray:
        unknown = set(joints) - set(self.joint_names)
        if unknown:
            raise ValueError(f"robot {self.name}: no joint {sorted(unknown)[0]!r}")
        rest = np.clip(0.0, self.lower, self.upper)
        return np.array(
            [joints.get(n, rest[i]) for i, n in enumerate(self.joint_names)], np.float64
        )

    def _poses(self, joints: dict[str, float], frames: list[str]) -> np.ndarray:
        """(k, 4, 4) base-frame poses of `frames` at `joints` (read-only; the last one asked
        for is kept, so asking again for the same joints costs nothing)."""
        q = self._configuration(joints)
        key = q.tobytes()
        last = self._last_poses  # one read: another thread may replace it meanwhile
        if last is None or last[0] != key:
            last = (key, self._kinematics.poses(q))
            self._last_poses = last
        poses = last[1][[self._link_index[f] for f in frames]]
        poses.setflags(write=False)
        return poses

    def _to_world(self, base_pos, base_quat) -> tuple[np.ndarray, np.ndarray]:
        """(R, p): world = p + R @ (scale * base-frame point)."""
        return quat_to_matrix(base_quat), np.asarray(base_pos, np.float64).reshape(3)

    def link_geometry(self, joints, base_pos, base_quat) -> tuple[Primitives, Triangles]:
        """The posed arm in the world frame, every shape labelled robot."""
        poses = self._poses(joints, self._links)
        rot, pos = self._to_world(base_pos, base_quat)
        world_rot = rot @ poses[:, :3, :3] * self._scale  # (links, 3, 3), scale folded in
        world_pos = pos + self._scale * poses[:, :3, 3] @ rot.T
        vertices = np.empty_like(self._tris)
        for i, (lo, hi) in enumerate(self._tri_blocks):
            block = self._tris[lo:hi].reshape(-1, 3) @ world_rot[i].T + world_pos[i]
            vertices[lo:hi] = block.reshape(-1, 3, 3)
        triangles = Triangles(vertices, np.full(len(vertices), labels.ROBOT, np.uint8))
        frame = poses[self._prim_link] @ self._prim_pose  # (m, 4, 4) base frame
        prims = Primitives(
            self._prim_kind.copy(),
            self._scale * self._prim_size,
            (pos + self._scale * frame[:, :3, 3] @ rot.T).reshape(-1, 3),
            np.einsum("ij,njk->nik", rot, frame[:, :3, :3]).reshape(-1, 3, 3),
            np.full(len(self._prim_kind), labels.ROBOT, np.uint8),
        )
        return prims, triangles

    def hull_points(self, joints, base_pos, base_quat) -> np.ndarray:
        """(n, 3) world points: the corners of each posed link mesh's convex hull. Their
        hull and their lowest and highest points are the meshes' own, at a few percent of
        the cost of posing every triangle (placing a scene asks for them often)."""
        if not self._hull_points:
            return np.zeros((0, 3))
        poses = self._poses(joints, self._links)
        rot, pos = self._to_world(base_pos, base_quat)
        world_rot = rot @ poses[:, :3, :3] * self._scale
        world_pos = pos + self._scale * poses[:, :3, 3] @ rot.T
        return np.concatenate(
            [pts @ world_rot[i].T + world_pos[i] for i, pts in enumerate(self._hull_points)]
        )

    @property
    def links(self) -> tuple[str, ...]:
        """The links that have geometry, in the order of `link_poses` and `link_shapes`."""
        return tuple(self._links)

    def link_poses(self, joints, base_pos, base_quat) -> np.ndarray:
        """(k, 4, 4) rigid world poses of `links` at `joints`; a link's shapes
        (`link_shapes`, already at the model's scale) map to the world through them."""
        poses = self._poses(joints, self._links)
        rot, pos = self._to_world(base_pos, base_quat)
        out = np.zeros_like(poses)
        out[:, :3, :3] = rot @ poses[:, :3, :3]
        out[:, :3, 3] = pos + self._scale * poses[:, :3, 3] @ rot.T
        out[:, 3, 3] = 1.0
        return out

    def link_shapes(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Link `links[index]`'s geometry in its own frame, at the model's scale: (m, 3) the
        corners of its meshes' convex hull, and its primitives' kinds, sizes and (p, 4, 4)
        poses (as `render.Primitives` reads kind and size)."""
        chosen = self._prim_link == index
        poses = self._prim_pose[chosen].copy()
        poses[:, :3, 3] *= self._scale
        hull = self._scale * self._hull_points[index].reshape(-1, 3)
        return hull, self._prim_kind[chosen].copy(), self._scale * self._prim_size[chosen], poses

    def tool_position(self, joints, base_pos, base_quat) -> np.ndarray:
        """The tool link's origin in the world frame."""
        pose = self._poses(joints, [self.tool_link])[0]
        rot, pos = self._to_world(base_pos, base_quat)
        return pos + rot @ (self._scale * pose[:3, 3])


# --- the catalogue and user URDFs -----------------------------------------------------------

_MODELS: dict[str, RobotModel] = {}
_RANDOM_MODELS: OrderedDict[str, RobotModel] = OrderedDict()  # least recently used first
_MODELS_LOCK = threading.Lock()


def random_arm_name(seed: int) -> str:
    """The name `robot_model` knows the random arm of `seed` by."""
    return f"{RANDOM}:{int(seed)}"


def robot_model(name_or_urdf_path: str) -> RobotModel:
    """The model of a catalogue robot (`ROBOTS`), a random arm (`random:<seed>`) or a URDF
    (or xacro) file, cached (the last RANDOM_CACHE random arms)."""
    key = str(name_or_urdf_path)
    with _MODELS_LOCK:
        if key.startswith(RANDOM + ":"):
            return _cached_random(key)
        if key not in _MODELS:
            _MODELS[key] = _build(key)
        return _MODELS[key]


def _cached_random(key: str) -> RobotModel:
    """A random arm's model from the bounded cache (the caller holds _MODELS_LOCK)."""
    if key in _RANDOM_MODELS:
        _RANDOM_MODELS.move_to_end(key)
        return _RANDOM_MODELS[key]
    model = _random_model(key)
    _RANDOM_MODELS[key] = model
    while len(_RANDOM_MODELS) > RANDOM_CACHE:
        _RANDOM_MODELS.popitem(last=False)
    return model


def _random_model(key: str) -> RobotModel:
    """The model of `random:<seed>`, parsed from its generated URDF text like any other."""
    seed = key[len(RANDOM) + 1 :]
    if not re.fullmatch(r"[0-9]{1,19}", seed):
        raise TopsegError(
            f"robot {key!r}: a random arm is named {RANDOM}:<seed>, the seed a whole number >= 0"
        )
    urdf = _load_urdf(io.StringIO(random_arm_urdf(int(seed))), key)
    return RobotModel(key, urdf, Path("."), TOOL_LINK)


def _build(key: str) -> RobotModel:
    if key in CATALOGUE:
        entry = CATALOGUE[key]
        root = data_root(entry.source)
        path = root / entry.path
        packages = {k: root / v for k, v in _RTB_PACKAGES.items()} if entry.source == "rtb" else {}
        return _from_file(key, path, entry.tool, entry.scale, dict(entry.xacro_args), packages)
    if not any(key.endswith(ext) for ext in (".urdf", ".xacro", ".xml")) and "/" not in key:
        raise TopsegError(
            f"unknown robot {key!r}: known: {', '.join(ROBOTS)}, {RANDOM}:<seed>, "
            "or the path of a .urdf file"
        )
    return _from_file(key, Path(key).expanduser(), None, 1.0, {}, {})


def _from_file(name, path: Path, tool, scale, xacro_args, packages) -> RobotModel:
    """A model from a URDF or xacro file; `name` is what it is called by."""
    if not path.is_file():
        raise TopsegError(f"robot {path}: no such file")
    if path.suffix == ".xacro":
        source = io.StringIO(_expand_xacro(path, xacro_args, packages))
    else:
        source = str(path)
    urdf = _load_urdf(source, str(path))
    try:
        return RobotModel(name, urdf, path.parent, tool, scale)
    except TopsegError as exc:
        message = str(exc)
        if str(path) not in message:
            message = message.replace(f"robot {name}:", f"robot {name} ({path}):", 1)
        raise TopsegError(message) from None


# --- a robot in a scene ---------------------------------------------------------------------


@dataclass
class PlacedRobot:
    """A robot arm in a scene.

    `x, y` its base on the floor plane (world, m) and `yaw` its heading; `mount` one of
    MOUNTS; `base_z` the height of its base: 0 on the floor, the pedestal's or table's top, or
    for "gantry" the underside of the beam it hangs from, upside down. `pedestal` is
    (size, round): a square pedestal of half width `size` turned with the robot, or with
    round = 1 a cylinder of radius `size`, from the floor to `base_z`; used by the "pedestal"
    mount only. A gantry's beam runs along the robot's local y, GANTRY_CLEARANCE beyond its
    reach on either side, on two posts. `id` shares the id space of the scene's objects.
    """

    id: int
    name: str
    x: float
    y: float
    yaw: float
    mount: str
    base_z: float
    joints: dict[str, float]
    pedestal: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        if self.mount not in MOUNTS:
            raise ValueError(f"robot mount {self.mount!r}: one of {', '.join(MOUNTS)}")

    def to_dict(self) -> dict:
        """JSON-able record; `from_dict` reads it back exactly."""
        return {
            "id": self.id,
            "name": self.name,
            "x": self.x,
            "y": self.y,
            "yaw": self.yaw,
            "mount": self.mount,
            "base_z": self.base_z,
            "joints": dict(self.joints),
            "pedestal": [float(v) for v in self.pedestal],
        }

    @classmethod
    def from_dict(cls, d: dict) -> PlacedRobot:
        """The robot a `to_dict` record describes."""
        size, round_ = d.get("pedestal", (0.0, 0.0))
        return cls(
            id=int(d["id"]), name=str(d["name"]), x=float(d["x"]), y=float(d["y"]),
            yaw=float(d["yaw"]), mount=str(d["mount"]), base_z=float(d["base_z"]),
            joints={str(k): float(v) for k, v in d["joints"].items()},
            pedestal=(float(size), float(round_)),
        )  # fmt: skip

    def model(self) -> RobotModel:
        """The robot's model (cached)."""
        return robot_model(self.name)

    def base_pos(self) -> np.ndarray:
        """The base's origin in the world frame."""
        return np.array([self.x, self.y, self.base_z], np.float64)

    def base_quat(self) -> np.ndarray:
        """Upright (gantry: upside down, turned about x), then turned by yaw about the vertical."""
        if self.mount == "gantry":
            return quat_mul(yaw_quat(self.yaw), quat_from_axis_angle((1.0, 0.0, 0.0), np.pi))
        return yaw_quat(self.yaw)

    def geometry(self) -> tuple[Primitives, Triangles]:
        """The posed arm with its pedestal or gantry, world frame, all labelled robot."""
        prims, tris = self.model().link_geometry(self.joints, self.base_pos(), self.base_quat())
        return Primitives.concat([prims, self._structure()]), tris

    def _structure(self) -> Primitives:
        """The pedestal or the gantry's beam and posts; nothing on the floor or a table."""
        if self.mount == "pedestal" and self.pedestal[0] > 0 and self.base_z > 0:
            size, round_ = self.pedestal
            return pedestal_primitives(self.x, self.y, self.yaw, self.base_z, size, bool(round_))
        if self.mount == "gantry":
            half_span = self.model().reach_m + GANTRY_CLEARANCE
            top = self.base_z + GANTRY_BEAM
            b, p = GANTRY_BEAM / 2, GANTRY_POST / 2
            c, s = np.cos(self.yaw), np.sin(self.yaw)
            ends = [(self.x - s * d, self.y + c * d) for d in (-half_span, half_span)]
            return _boxes(
                [BOX, BOX, BOX],
                [(b, half_span + p, b), (p, p, top / 2), (p, p, top / 2)],
                [(self.x, self.y, self.base_z + b), (*ends[0], top / 2), (*ends[1], top / 2)],
                self.yaw,
            )
        return Primitives.empty()

    def tool_position(self) -> np.ndarray:
        """The tool's position in the world frame."""
        return self.model().tool_position(self.joints, self.base_pos(), self.base_quat())

    def footprint(self) -> np.ndarray:
        """(k, 2) convex polygon (CCW) on the floor under the posed arm and its pedestal; a
        gantry's beam and posts are left out (people and furniture pass under the beam)."""
        model = self.model()
        prims, _ = model.link_geometry(self.joints, self.base_pos(), self.base_quat())
        if self.mount == "pedestal":
            prims = Primitives.concat([prims, self._structure()])
        hull = model.hull_points(self.joints, self.base_pos(), self.base_quat())
        points = np.concatenate([hull[:, :2], _outline_xy(prims)])
        hull = ConvexHull(points)
        return points[hull.vertices]  # counter-clockwise in 2-D

    def z_range(self) -> tuple[float, float]:
        """Lowest and highest z (m) of the robot with its pedestal or gantry."""
        prims, tris = self.geometry()
        lo, hi = [np.inf], [-np.inf]
        if len(tris):
            lo.append(tris.vertices[:, :, 2].min())
            hi.append(tris.vertices[:, :, 2].max())
        for i in range(len(prims)):
            a, b = aabb(int(prims.kind[i]), prims.size[i], prims.center[i], prims.rot[i])
            lo.append(a[2])
            hi.append(b[2])
        return float(min(lo)), float(max(hi))


def _hull_vertices(triangles: np.ndarray) -> np.ndarray:
    """The corners of the convex hull of a link's triangles (all its distinct corners when
    they are flat or too few for a hull)."""
    points = np.unique(triangles.reshape(-1, 3), axis=0)
    if len(points) < 5:
        return points
    try:
        return points[ConvexHull(points).vertices]
    except QhullError:  # a flat or degenerate link
        return points


def pedestal_primitives(
    x: float, y: float, yaw: float, height: float, size: float, round_: bool
) -> Primitives:
    """A pedestal from the floor up to `height` under (x, y), labelled robot: a square column
    of half width `size` turned by `yaw` (radians), or with `round_` a cylinder of radius
    `size`."""
    h = height / 2
    kind, dims = (CYLINDER, (size, h, 0.0)) if round_ else (BOX, (size, size, h))
    return _boxes([kind], [dims], [(x, y, h)], yaw)


def _boxes(kinds, sizes, centres, yaw: float) -> Primitives:
    """Primitives labelled robot, upright and turned by `yaw`."""
    n = len(kinds)
    rot = quat_to_matrix(yaw_quat(yaw))
    return Primitives(
        np.array(kinds, np.int32),
        np.array(sizes, np.float64).reshape(n, 3),
        np.array(centres, np.float64).reshape(n, 3),
        np.repeat(rot[None], n, 0),
        np.full(n, labels.ROBOT, np.uint8),
    )


def _outline_xy(prims: Primitives, sides: int = 16) -> np.ndarray:
    """(k, 2) floor points whose convex hull covers each primitive's shadow: a box's corners,
    a round shape's circle of `sides` points around its axis' two ends."""
    points = [np.zeros((0, 2))]
    ring = np.stack([np.cos(np.linspace(0, 2 * np.pi, sides, endpoint=False))] * 2, 1)
    ring[:, 1] = np.sin(np.linspace(0, 2 * np.pi, sides, endpoint=False))
    ring /= np.cos(np.pi / sides)  # the polygon circumscribes the circle
    for kind, size, centre, rot in zip(
        prims.kind, prims.size, prims.center, prims.rot, strict=True
    ):
        if kind == BOX:
            corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
            points.append(((corners * size) @ rot.T + centre)[:, :2])
            continue
        r = size[0]
        h = 0.0 if kind == SPHERE else size[1]
        for end in (-h, h):
            points.append(centre[:2] + end * rot[:2, 2] + r * ring)
    return np.concatenate(points)
