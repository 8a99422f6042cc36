"""The pybullet_data humanoid: its kinematics, its poses, and which body part each link is.

The human of every scene is pybullet_data's `humanoid/humanoid.urdf` (spheres, capsules and
boxes on 15 links), the character of pybullet's DeepMimic examples. This module reads that
URDF and does its forward kinematics in numpy, so the density function can reason about a
posed human (where its hips, hands and feet are) without a physics client; the scene builder
then applies the same pose to the pybullet body, and a test checks both agree.

Poses come from the motion-capture clips pybullet_data ships (`data/motions/humanoid3d_*.txt`,
read like DeepMimic's `humanoid_pose_interpolator.py`) and from presets for the paper's poses
that no clip covers (sitting, standing, stretching, working, bending, bowing, tilting,
swinging). Those are `PAPER_POSES`, what the density function draws by default; `CELL_POSES`
(kneeling, crouching, lying on the floor, reaching into a machine) are what people in a robot
cell do besides, drawn when a density config weights them. The model is y-up (x forward, z to
its right); `base_quat` turns it upright in the z-up world and faces it along +x rotated by the
human's yaw.

Seen from above, three of the URDF's shapes are far from people (docs/explanation/method.md measures
the body against ANSUR II): its head is a 205 mm ball (heads are ~150 mm broad and ~195 mm
long), its chest a 220 mm ball (chests are ~270-290 mm broad), its pelvis a 180 mm ball
(hips are ~350 mm broad). `PROPORTION_FIXES` replaces them with capsules of measured size;
`load_model` reads the fixed model and `urdf_path()` writes the same URDF for pybullet.
"""

from __future__ import annotations

import hashlib
import json
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from functools import cache, lru_cache
from pathlib import Path

import numpy as np

from topseg.core import labels
from topseg.core.atomic import atomic_write
from topseg.core.synth.geometry import (
    BOX,
    CAPSULE,
    CYLINDER,
    SPHERE,
    half_extents,
    matrix_to_quat,
    quat_conj,
    quat_from_axis_angle,
    quat_mul,
    quat_normalize,
    quat_to_matrix,
    quats_to_matrices,
    rot2,
    rotation_between,
    yaw_quat,
)

URDF_RELPATH = "humanoid/humanoid.urdf"
#: globalScaling of the DeepMimic humanoid, at which the clips were recorded (~1.62 m tall)
REFERENCE_SCALING = 0.25
#: heights are realised on this grid (metres) so the scene builder can pool bodies
HEIGHT_STEP_M = 0.01
#: turns the y-up model upright in the z-up world (rotation of +90 degrees about x)
Y_UP_TO_Z_UP = quat_from_axis_angle((1.0, 0.0, 0.0), np.pi / 2)

#: link name -> body part label; the head is the sphere on the neck link
LINK_LABELS: dict[str, int] = {
    "root": labels.BODY,
    "chest": labels.BODY,
    "neck": labels.HEAD,
    "right_hip": labels.LEGS,
    "right_knee": labels.LEGS,
    "right_ankle": labels.LEGS,
    "right_shoulder": labels.UPPER_ARM,
    "right_elbow": labels.LOWER_ARM,
    "right_wrist": labels.HAND,
    "left_hip": labels.LEGS,
    "left_knee": labels.LEGS,
    "left_ankle": labels.LEGS,
    "left_shoulder": labels.UPPER_ARM,
    "left_elbow": labels.LOWER_ARM,
    "left_wrist": labels.HAND,
}
SPHERICAL = (
    "chest",
    "neck",
    "right_hip",
    "right_ankle",
    "right_shoulder",
    "left_hip",
    "left_ankle",
    "left_shoulder",
)
REVOLUTE = ("right_knee", "right_elbow", "left_knee", "left_elbow")

# Motion-capture clips per pose name; presets are the paper's poses no clip covers.
CLIPS: dict[str, tuple[str, ...]] = {
    "walking": ("walk",),
    "running": ("run",),
    "dancing": ("dance_a", "dance_b"),
    "boxing": ("punch",),
    "kicking": ("kick", "spinkick"),
    "spinning": ("spin",),
    "jumping": ("jump",),
}
PAPER_PRESETS = (
    "sitting",
    "standing",
    "stretching",
    "working",
    "bending",
    "bowing",
    "tilting",
    "swinging",
)
#: what people in a robot cell do besides the paper's poses: work low, reach into a machine, fall
CELL_PRESETS = ("kneeling", "crouching", "lying", "reaching")
PRESETS = (*PAPER_PRESETS, *CELL_PRESETS)
#: the paper's poses, what the density function draws by default
PAPER_POSES: tuple[str, ...] = (*PAPER_PRESETS, *CLIPS)
CELL_POSES: tuple[str, ...] = CELL_PRESETS
POSES: tuple[str, ...] = (*PAPER_POSES, *CELL_POSES)

#: link -> (capsule radius, capsule cylinder length, origin xyz, origin rpy) replacing the
#: URDF's shape, in model units (x 0.25 m at REFERENCE_SCALING, ~1.6 m tall). Head: 140 x
#: 182 mm, long axis forward, centre 12 mm above the URDF's ball's; chest: 220 mm deep, 265 mm
#: broad (lateral capsule); pelvis: 180 mm deep, 330 mm broad. See docs/explanation/method.md.
PROPORTION_FIXES: dict[str, tuple[float, float, tuple, tuple]] = {
    "neck": (0.28, 0.167, (0.0, 0.75, 0.0), (0.0, 1.570796, 0.0)),
    "chest": (0.44, 0.18, (0.0, 0.48, 0.0), (0.0, 0.0, 0.0)),
    "root": (0.36, 0.60, (0.0, 0.28, 0.0), (0.0, 0.0, 0.0)),
}


def data_path() -> Path:
    """pybullet_data's folder, which holds the humanoid URDF and the mocap clips."""
    import pybullet_data

    return Path(pybullet_data.getDataPath())


# --- the model ------------------------------------------------------------------------------


@dataclass(frozen=True)
class Link:
    """One link (pybullet link index = position in `HumanoidModel.links`), unscaled."""

    name: str
    parent: int  # -1 = the base
    joint_type: str  # fixed | spherical | revolute
    joint_xyz: tuple[float, float, float]
    axis: tuple[float, float, float]
    shape_kind: int
    shape_size: tuple[float, float, float]  # geometry.Part convention, unscaled
    shape_xyz: tuple[float, float, float]
    shape_quat: tuple[float, float, float, float]

    @property
    def label(self) -> int:
        """The body-part label this link's shape is drawn with (LINK_LABELS)."""
        return LINK_LABELS[self.name]


@dataclass(frozen=True)
class HumanoidModel:
    """The URDF's links in pybullet's order and a name -> index map (`base` is -1)."""

    links: tuple[Link, ...]
    index: dict = field(hash=False, compare=False)

    def link(self, name: str) -> Link:
        """The link called `name`; KeyError for a name the URDF does not have."""
        return self.links[self.index[name]]


def _floats(s: str) -> tuple[float, ...]:
    return tuple(float(v) for v in s.split())


def _rpy_quat(rpy) -> np.ndarray:
    r, p, y = rpy
    qx = quat_from_axis_angle((1, 0, 0), r)
    qy = quat_from_axis_angle((0, 1, 0), p)
    qz = quat_from_axis_angle((0, 0, 1), y)
    return quat_mul(qz, quat_mul(qy, qx))


def _fixed_urdf_root(path: str | None = None) -> ET.Element:
    """The URDF's XML tree with PROPORTION_FIXES applied to its collision shapes (pybullet
    makes the visual shapes from them)."""
    raw = Path(path or data_path() / URDF_RELPATH).read_bytes().rstrip(b"\x00\r\n ")
    root = ET.fromstring(raw)
    for link in root.findall("link"):
        fix = PROPORTION_FIXES.get(link.get("name"))
        col = link.find("collision")
        if fix is None or col is None:
            continue
        radius, length, xyz, rpy = fix
        org = col.find("origin")
        org.set("xyz", " ".join(f"{v:.6f}" for v in xyz))
        org.set("rpy", " ".join(f"{v:.6f}" for v in rpy))
        geom = col.find("geometry")
        for child in list(geom):
            geom.remove(child)
        ET.SubElement(geom, "capsule", {"length": f"{length:.6f}", "radius": f"{radius:.6f}"})
    return root


@lru_cache(maxsize=1)
def urdf_path() -> str:
    """A URDF file of the fixed humanoid for pybullet's loadURDF (written once, atomically,
    under the temp folder, named by its content's hash)."""
    text = ET.tostring(_fixed_urdf_root(), encoding="utf-8")
    digest = hashlib.sha256(text).hexdigest()[:16]
    path = Path(tempfile.gettempdir()) / f"topseg-humanoid-{digest}.urdf"
    if not path.is_file() or path.read_bytes() != text:
        with atomic_write(path) as f:
            f.write(text)
    return str(path)


@lru_cache(maxsize=1)
def load_model(path: str | None = None) -> HumanoidModel:
    """Parse the humanoid URDF with PROPORTION_FIXES (links in file order = pybullet's with
    URDF_MAINTAIN_LINK_ORDER)."""
    root = _fixed_urdf_root(path)
    shapes = {}
    for link in root.findall("link"):
        col = link.find("collision")
        if col is None:
            continue
        org = col.find("origin")
        xyz = _floats(org.get("xyz", "0 0 0")) if org is not None else (0.0, 0.0, 0.0)
        rpy = _floats(org.get("rpy", "0 0 0")) if org is not None else (0.0, 0.0, 0.0)
        geom = col.find("geometry")[0]
        if geom.tag == "sphere":
            kind, size = SPHERE, (float(geom.get("radius")), 0.0, 0.0)
        elif geom.tag == "capsule":
            kind, size = CAPSULE, (float(geom.get("radius")), float(geom.get("length")) / 2, 0.0)
        elif geom.tag == "box":
            kind, size = BOX, tuple(v / 2 for v in _floats(geom.get("size")))
        elif geom.tag == "cylinder":
            kind, size = CYLINDER, (float(geom.get("radius")), float(geom.get("length")) / 2, 0.0)
        else:
            raise ValueError(f"humanoid link {link.get('name')}: unsupported geometry {geom.tag}")
        shapes[link.get("name")] = (kind, size, xyz, tuple(_rpy_quat(rpy)))
    links: list[Link] = []
    index: dict[str, int] = {"base": -1}
    for joint in root.findall("joint"):
        child = joint.find("child").get("link")
        parent = joint.find("parent").get("link")
        org = joint.find("origin")
        axis_el = joint.find("axis")
        axis = _floats(axis_el.get("xyz")) if axis_el is not None else (1.0, 0.0, 0.0)
        kind, size, sxyz, squat = shapes[child]
        index[child] = len(links)
        links.append(
            Link(
                child,
                index[parent],
                joint.get("type"),
                _floats(org.get("xyz")),
                axis,
                kind,
                size,
                sxyz,
                squat,
            )
        )
    return HumanoidModel(tuple(links), index)


# --- poses ----------------------------------------------------------------------------------


@dataclass
class Pose:
    """Joint rotations of the humanoid: quaternions for spherical joints, angles for revolute.

    `tilt` is the root's orientation in the model's own y-up frame with the heading removed
    (identity = upright, facing +x); mocap clips tilt the root, presets mostly do not.
    """

    joints: dict[str, list[float]]
    tilt: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)

    def to_dict(self) -> dict:
        """Plain lists of floats (JSON-able), as a frame's scene description stores a pose."""
        return {
            "joints": {k: [float(x) for x in v] for k, v in self.joints.items()},
            "tilt": [float(x) for x in self.tilt],
        }

    @classmethod
    def from_dict(cls, d: dict) -> Pose:
        """The pose a `to_dict` mapping describes."""
        return cls({k: list(v) for k, v in d["joints"].items()}, tuple(d["tilt"]))

    def copy(self) -> Pose:
        """A deep copy, so inverse kinematics can change joints without touching the original."""
        return Pose({k: list(v) for k, v in self.joints.items()}, tuple(self.tilt))


def identity_pose() -> Pose:
    """Every joint at rest and no tilt: the pose `reference_height` is measured in."""
    j = {n: [0.0, 0.0, 0.0, 1.0] for n in SPHERICAL}
    j.update({n: [0.0] for n in REVOLUTE})
    return Pose(j)


def scale_for_height(height_m: float) -> float:
    """pybullet globalScaling that makes the upright humanoid `height_m` tall."""
    return REFERENCE_SCALING * height_m / reference_height()


@lru_cache(maxsize=1)
def reference_height() -> float:
    """Standing height (m) of the identity pose at REFERENCE_SCALING."""
    prims = posed_primitives(identity_pose(), REFERENCE_SCALING, (0, 0, 0), Y_UP_TO_Z_UP)
    lo, hi = prims_z_range(prims)
    return hi - lo


def quantize_height(h: float) -> float:
    """Snap a height (m) to the 1 cm grid the scene builder pools human bodies on."""
    return round(round(h / HEIGHT_STEP_M) * HEIGHT_STEP_M, 4)


def base_quat(tilt, yaw: float) -> np.ndarray:
    """World orientation of the base: tilt in model frame, stood upright, turned by yaw."""
    return quat_normalize(quat_mul(yaw_quat(yaw), quat_mul(Y_UP_TO_Z_UP, tilt)))


# --- forward kinematics ---------------------------------------------------------------------


@lru_cache(maxsize=1)
def _model_arrays() -> dict:
    """The model's constants as arrays, for vectorised kinematics."""
    m = load_model()
    return {
        "parent": [lk.parent for lk in m.links],
        "joint_xyz": np.array([lk.joint_xyz for lk in m.links], np.float64),
        "spherical": [i for i, lk in enumerate(m.links) if lk.joint_type == "spherical"],
        "revolute": [i for i, lk in enumerate(m.links) if lk.joint_type == "revolute"],
        "axis": np.array([lk.axis for lk in m.links], np.float64),
        "kind": np.array([lk.shape_kind for lk in m.links], np.int32),
        "size": np.array([lk.shape_size for lk in m.links], np.float64),
        "shape_xyz": np.array([lk.shape_xyz for lk in m.links], np.float64),
        "shape_rot": quats_to_matrices(np.array([lk.shape_quat for lk in m.links])),
        "label": np.array([lk.label for lk in m.links], np.uint8),
    }


def _joint_rotations(pose: Pose) -> np.ndarray:
    """(15, 3, 3) rotation of each joint (identity for fixed joints)."""
    a = _model_arrays()
    names = [lk.name for lk in load_model().links]
    rot = np.broadcast_to(np.eye(3), (len(names), 3, 3)).copy()
    sph = a["spherical"]
    rot[sph] = quats_to_matrices(np.array([pose.joints[names[i]] for i in sph]))
    rev = a["revolute"]
    half = np.array([pose.joints[names[i]][0] for i in rev]) / 2
    axes = a["axis"][rev] / np.linalg.norm(a["axis"][rev], axis=1, keepdims=True)
    q = np.column_stack([axes * np.sin(half)[:, None], np.cos(half)])
    rot[rev] = quats_to_matrices(q)
    return rot


def link_frames(pose: Pose, scale: float, base_pos, base_q) -> tuple[np.ndarray, np.ndarray]:
    """World (positions (15, 3), rotations (15, 3, 3)) of each link frame (= its joint)."""
    a = _model_arrays()
    jr = _joint_rotations(pose)
    offsets = a["joint_xyz"] * scale
    n = len(offsets)
    pos = np.zeros((n, 3))
    rot = np.zeros((n, 3, 3))
    bp = np.asarray(base_pos, np.float64)
    br = quat_to_matrix(base_q)
    for i, parent in enumerate(a["parent"]):
        ppos, prot = (bp, br) if parent < 0 else (pos[parent], rot[parent])
        pos[i] = ppos + prot @ offsets[i]
        rot[i] = prot @ jr[i]
    return pos, rot


@dataclass
class Primitives:
    """Posed shapes of the human: kind, size (Part convention), world centre and rotation."""

    kind: np.ndarray
    size: np.ndarray
    center: np.ndarray
    rot: np.ndarray
    label: np.ndarray
    link: np.ndarray


def posed_primitives(pose: Pose, scale: float, base_pos, base_q) -> Primitives:
    """The human's shapes in the world: `pose` at `scale`, base at `base_pos` turned by `base_q`."""
    a = _model_arrays()
    pos, rot = link_frames(pose, scale, base_pos, base_q)
    center = pos + np.einsum("nij,nj->ni", rot, a["shape_xyz"] * scale)
    return Primitives(
        a["kind"], a["size"] * scale, center, rot @ a["shape_rot"], a["label"], np.arange(len(pos))
    )


def prims_z_range(p: Primitives) -> tuple[float, float]:
    """Lowest and highest point of the posed body (m)."""
    ext = half_extents(p.kind, p.size, p.rot)[:, 2]
    return float((p.center[:, 2] - ext).min()), float((p.center[:, 2] + ext).max())


def prims_xy_bounds(
    p: Primitives, yaw: float, origin, arms: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Bounds (lo, hi) of the body on the floor, in the frame of `origin` turned by `yaw`;
    `arms=False` leaves out upper arms, forearms and hands."""
    keep = (
        np.ones(len(p.kind), bool)
        if arms
        else ~np.isin(p.label, (labels.UPPER_ARM, labels.LOWER_ARM, labels.HAND))
    )
    ext = half_extents(p.kind[keep], p.size[keep], p.rot[keep])[:, :2]
    c = p.center[keep, :2] - np.asarray(origin, np.float64)[:2]
    # each shape's world box corners, turned into the human's frame
    corners = np.concatenate(
        [c + ext * np.array(sx_sy) for sx_sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    )
    loc = corners @ rot2(-yaw).T
    return loc.min(0), loc.max(0)


# --- motion capture -------------------------------------------------------------------------


@lru_cache(maxsize=32)
def load_clip(name: str) -> np.ndarray:
    """Frames of a DeepMimic clip as a (n_frames, 44) array."""
    path = data_path() / "data" / "motions" / f"humanoid3d_{name}.txt"
    with open(path) as f:
        frames = np.asarray(json.load(f)["Frames"], np.float64)
    if frames.ndim != 2 or frames.shape[1] != 44:
        raise ValueError(f"{path}: expected 44 values per frame, got {frames.shape}")
    return frames


# offsets of each joint in a DeepMimic frame (w, x, y, z quaternions; scalars for revolute)
_CLIP_LAYOUT = (
    ("chest", 8, 4),
    ("neck", 12, 4),
    ("right_hip", 16, 4),
    ("right_knee", 20, 1),
    ("right_ankle", 21, 4),
    ("right_shoulder", 25, 4),
    ("right_elbow", 29, 1),
    ("left_hip", 30, 4),
    ("left_knee", 34, 1),
    ("left_ankle", 35, 4),
    ("left_shoulder", 39, 4),
    ("left_elbow", 43, 1),
)


def _wxyz(v) -> np.ndarray:
    return quat_normalize([v[1], v[2], v[3], v[0]])


def slerp(a, b, t: float) -> np.ndarray:
    """Interpolate unit quaternions a (t = 0) to b (t = 1) along the shorter arc."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    d = float(a @ b)
    if d < 0:
        b, d = -b, -d
    if d > 0.9995:
        return quat_normalize(a + t * (b - a))
    th = np.arccos(d)
    return (np.sin((1 - t) * th) * a + np.sin(t * th) * b) / np.sin(th)


def clip_pose(name: str, phase: float) -> Pose:
    """The pose of clip `name` at `phase` in [0, 1), interpolated between key frames."""
    frames = load_clip(name)
    x = float(np.clip(phase, 0.0, 1.0)) * (len(frames) - 1)
    i = min(int(x), len(frames) - 2)
    t = x - i
    f0, f1 = frames[i], frames[i + 1]
    joints = {}
    for jname, off, n in _CLIP_LAYOUT:
        if n == 4:
            joints[jname] = list(slerp(_wxyz(f0[off : off + 4]), _wxyz(f1[off : off + 4]), t))
        else:
            joints[jname] = [float((1 - t) * f0[off] + t * f1[off])]
    root = slerp(_wxyz(f0[4:8]), _wxyz(f1[4:8]), t)
    # remove the heading (rotation about the model's vertical y); keep pitch and roll
    fwd = quat_to_matrix(root) @ np.array([1.0, 0.0, 0.0])
    heading = np.arctan2(-fwd[2], fwd[0])
    tilt = quat_mul(quat_from_axis_angle((0, 1, 0), -heading), root)
    return Pose(joints, tuple(quat_normalize(tilt)))


# --- presets --------------------------------------------------------------------------------


def limb_quat(
    flex: float = 0.0, abd: float = 0.0, twist: float = 0.0, side: str = "right"
) -> np.ndarray:
    """Spherical joint rotation from angles in degrees, in the model's frame.

    flex swings a hanging limb forward (or bends the trunk forward for the chest and neck,
    pass a negative value), abd lifts it sideways away from the body (right limbs sit at +z),
    twist turns it about its own axis.
    """
    f, a, t = np.radians([flex, abd, twist])
    a = -a if side == "right" else a
    return quat_mul(
        quat_from_axis_angle((0, 0, 1), f),
        quat_mul(quat_from_axis_angle((1, 0, 0), a), quat_from_axis_angle((0, 1, 0), t)),
    )


def trunk_quat(bend: float = 0.0, side_tilt: float = 0.0, twist: float = 0.0) -> np.ndarray:
    """Chest or neck rotation (degrees): bend forward, tilt to the right, twist about vertical."""
    b, s, t = np.radians([bend, side_tilt, twist])
    return quat_mul(
        quat_from_axis_angle((0, 0, 1), -b),
        quat_mul(quat_from_axis_angle((1, 0, 0), s), quat_from_axis_angle((0, 1, 0), t)),
    )


def _set_leg(p: Pose, side: str, hip_flex: float, hip_abd: float, knee: float) -> None:
    """Leg with the foot kept flat on the floor (ankle undoes hip and knee flexion)."""
    p.joints[f"{side}_hip"] = list(limb_quat(hip_flex, hip_abd, 0.0, side))
    p.joints[f"{side}_knee"] = [float(np.radians(-abs(knee)))]
    p.joints[f"{side}_ankle"] = list(limb_quat(-(hip_flex - abs(knee)), -hip_abd, 0.0, side))


def _set_arm(p: Pose, side: str, flex: float, abd: float, twist: float, elbow: float) -> None:
    p.joints[f"{side}_shoulder"] = list(limb_quat(flex, abd, twist, side))
    p.joints[f"{side}_elbow"] = [float(np.radians(np.clip(elbow, 0.0, 170.0)))]


def preset_pose(name: str, rng: np.random.Generator) -> Pose:
    """A preset pose (PRESETS) with its free angles drawn uniformly from natural ranges."""
    if name in CELL_PRESETS:
        return _CELL_BUILDERS[name](rng)
    u = rng.uniform
    p = identity_pose()
    if name == "sitting":  # legs are set against the seat by sitting_legs()
        p.joints["chest"] = list(trunk_quat(u(-5, 15), u(-5, 5), u(-10, 10)))
        for s in ("right", "left"):
            _set_arm(p, s, u(15, 45), u(5, 15), 0.0, u(50, 95))
        return p
    legs_straight = name not in ("bending",)
    if legs_straight:
        for s in ("right", "left"):
            _set_leg(p, s, u(-4, 6), u(0, 8), u(0, 8))
    if name == "standing":
        p.joints["chest"] = list(trunk_quat(u(-3, 6), u(-4, 4), u(-10, 10)))
        for s in ("right", "left"):
            _set_arm(p, s, u(-10, 20), u(3, 15), 0.0, u(0, 30))
    elif name == "stretching":
        p.joints["chest"] = list(trunk_quat(u(-12, 0), u(-8, 8), 0.0))
        if rng.random() < 0.5:  # both arms overhead
            for s in ("right", "left"):
                _set_arm(p, s, u(150, 178), u(0, 20), 0.0, u(0, 25))
        else:  # arms out to the sides
            for s in ("right", "left"):
                _set_arm(p, s, u(-10, 30), u(75, 110), 0.0, u(0, 20))
    elif name == "working":
        p.joints["chest"] = list(trunk_quat(u(8, 25), u(-5, 5), u(-10, 10)))
        for s in ("right", "left"):
            _set_arm(p, s, u(25, 65), u(5, 20), 0.0, u(40, 90))
    elif name == "bending":
        bend = u(45, 85)
        p.joints["chest"] = list(trunk_quat(bend, u(-5, 5), u(-10, 10)))
        p.joints["neck"] = list(trunk_quat(u(-30, 0), 0.0, 0.0))
        knee = u(0, 30)
        for s in ("right", "left"):
            _set_leg(p, s, knee / 2, u(0, 8), knee)
            _set_arm(p, s, bend + u(-15, 15), u(0, 15), 0.0, u(0, 40))
    elif name == "bowing":
        bend = u(20, 45)
        p.joints["chest"] = list(trunk_quat(bend, 0.0, 0.0))
        p.joints["neck"] = list(trunk_quat(u(5, 20), 0.0, 0.0))
        for s in ("right", "left"):
            _set_arm(p, s, bend * u(0.6, 1.0), u(0, 8), 0.0, u(0, 15))
    elif name == "tilting":  # trunk to one side, one or both arms up, angled or straight
        tilt = u(12, 30) * rng.choice([-1.0, 1.0])
        p.joints["chest"] = list(trunk_quat(u(-5, 8), tilt, u(-10, 10)))
        sides = (
            ("right", "left")
            if rng.random() < 0.5
            else (("right",) if rng.random() < 0.5 else ("left",))
        )
        for s in ("right", "left"):
            if s in sides:
                _set_arm(p, s, u(-20, 60), u(40, 160), 0.0, u(0, 100))
            else:
                _set_arm(p, s, u(-10, 15), u(3, 15), 0.0, u(0, 30))
    elif name == "swinging":  # a two-handed swing: arms together in front, trunk twisted
        twist = u(20, 60) * rng.choice([-1.0, 1.0])
        p.joints["chest"] = list(trunk_quat(u(5, 25), 0.0, twist))
        lift = u(30, 110)
        for s in ("right", "left"):
            inward = -u(10, 30)
            _set_arm(p, s, lift, inward, 0.0, u(0, 20))
    else:
        raise ValueError(f"unknown preset pose {name!r}; presets: {', '.join(PRESETS)}")
    return p


#: cosine of the largest lean of the root a mocap pose may have (60 degrees)
MIN_UPRIGHT = 0.5


def trunk_uprightness(pose: Pose) -> float:
    """Vertical component of the root's up axis (1 = upright, 0 = lying)."""
    return float(quat_to_matrix(pose.tilt)[1, 1])


def sample_pose(name: str, rng: np.random.Generator) -> tuple[Pose, dict]:
    """A pose called `name` (see POSES) and where it came from: preset or clip and phase."""
    if name in CLIPS:
        clip = str(rng.choice(CLIPS[name]))
        for _ in range(50):  # skip the moments a clip tumbles (a kick's horizontal trunk)
            phase = float(rng.uniform(0.0, 1.0))
            pose = clip_pose(clip, phase)
            if trunk_uprightness(pose) >= MIN_UPRIGHT:
                break
        return pose, {"source": "mocap", "clip": clip, "phase": phase}
    if name in PRESETS:
        return preset_pose(name, rng), {"source": "preset"}
    raise ValueError(f"unknown pose {name!r}; known: {', '.join(POSES)}")


# --- sitting and reaching -------------------------------------------------------------------


def limb_lengths(scale: float) -> dict[str, float]:
    """Segment lengths (m) at `scale`: thigh, shank, foot drop, upper arm, forearm, radii."""
    m = load_model()
    foot = m.link("right_ankle")
    return {
        "thigh": -m.link("right_knee").joint_xyz[1] * scale,
        "shank": -m.link("right_ankle").joint_xyz[1] * scale,
        "foot_drop": (-foot.shape_xyz[1] + foot.shape_size[1]) * scale,
        "thigh_radius": m.link("right_hip").shape_size[0] * scale,
        "upper_arm": -m.link("right_elbow").joint_xyz[1] * scale,
        "forearm": -m.link("right_wrist").joint_xyz[1] * scale,
        "hand_radius": m.link("right_wrist").shape_size[0] * scale,
        "pelvis_radius": m.link("root").shape_size[0] * scale,
        "pelvis_offset": m.link("root").shape_xyz[1] * scale,
    }


def sitting_legs(p: Pose, scale: float, hip_z: float) -> None:
    """Thighs on the seat and feet on the floor, for hip joints at height `hip_z`.

    Thighs stay horizontal while the shank can reach the floor by swinging forward; a short
    human on a high seat lowers the thighs' front a little; past that the feet hang.
    """
    L = limb_lengths(scale)
    reach = L["shank"] + L["foot_drop"]
    drop = 0.0
    if hip_z > reach:
        drop = float(
            np.degrees(
                np.arcsin(np.clip((hip_z - reach) / L["thigh"], 0.0, np.sin(np.radians(20))))
            )
        )
    knee_z = hip_z - L["thigh"] * np.sin(np.radians(drop))
    cos_a = np.clip((knee_z - L["foot_drop"]) / L["shank"], 0.0, 1.0)
    alpha = float(np.degrees(np.arccos(cos_a)))  # shank forward of vertical
    hip_flex = 90.0 - drop
    knee = 90.0 - drop - alpha
    for s in ("right", "left"):
        abd = 0.0  # legs in the sagittal plane keep the feet exactly flat
        p.joints[f"{s}_hip"] = list(limb_quat(hip_flex, abd, 0.0, s))
        p.joints[f"{s}_knee"] = [float(np.radians(-knee))]
        p.joints[f"{s}_ankle"] = list(limb_quat(-(hip_flex - knee), -abd, 0.0, s))


def reach(p: Pose, scale: float, base_pos, base_q, side: str, target) -> bool:
    """Bend arm `side` so its hand (wrist centre) lands on `target` (world, m).

    Analytic two-link IK: the elbow angle from the distance, the shoulder rotation that points
    the arm at the target, and the swivel about that line that keeps the elbow low and out.
    Returns False (pose unchanged) when the target is out of reach.
    """
    model = load_model()
    L = limb_lengths(scale)
    l1, l2 = L["upper_arm"], L["forearm"]
    pos, rot = link_frames(p, scale, base_pos, base_q)
    si = model.index[f"{side}_shoulder"]
    chest = model.links[si].parent
    shoulder = pos[si]
    t_world = np.asarray(target, np.float64) - shoulder
    dist = float(np.linalg.norm(t_world))
    if dist > (l1 + l2) * 0.999 or dist < abs(l1 - l2) + 1e-4:
        return False
    cos_g = (l1 * l1 + l2 * l2 - dist * dist) / (2 * l1 * l2)
    elbow = float(np.pi - np.arccos(np.clip(cos_g, -1.0, 1.0)))
    r_chest = rot[chest]
    t_local = r_chest.T @ t_world
    w0 = np.array([0.0, -l1, 0.0]) + quat_to_matrix(
        quat_from_axis_angle((0, 0, 1), elbow)
    ) @ np.array([0.0, -l2, 0.0])
    q_min = rotation_between(w0, t_local)
    axis = t_local / dist
    outward = np.array([0.0, 0.0, 1.0 if side == "right" else -1.0])
    best, best_score = None, np.inf
    for phi in np.linspace(-np.pi, np.pi, 36, endpoint=False):
        q = quat_mul(quat_from_axis_angle(axis, phi), q_min)
        e_local = quat_to_matrix(q) @ np.array([0.0, -l1, 0.0])
        e_world = r_chest @ e_local
        score = e_world[2] - 0.5 * float(e_local @ outward) + 0.3 * float(e_local[0])
        if score < best_score:
            best, best_score = q, score
    p.joints[f"{side}_shoulder"] = list(quat_normalize(best))
    p.joints[f"{side}_elbow"] = [elbow]
    return True


def wrist_position(p: Pose, scale: float, base_pos, base_q, side: str) -> np.ndarray:
    """World position (m) of the `side` ("left" or "right") wrist of a posed, placed human."""
    pos, _ = link_frames(p, scale, base_pos, base_q)
    return pos[load_model().index[f"{side}_wrist"]]


def hip_position(p: Pose, scale: float, base_pos, base_q, side: str = "right") -> np.ndarray:
    """World position (m) of the `side` hip joint of a posed, placed human."""
    pos, _ = link_frames(p, scale, base_pos, base_q)
    return pos[load_model().index[f"{side}_hip"]]


def top_view_dimensions(height_m: float) -> dict[str, float]:
    """What a ceiling camera sees of the upright, arms-down humanoid `height_m` tall (mm):
    head breadth and length, bideltoid (shoulders and upper arms) and hip breadth, chest
    breadth and depth, upper-arm, forearm and hand thickness; docs/explanation/method.md compares them
    with ANSUR II."""
    prims = posed_primitives(
        identity_pose(), scale_for_height(height_m), (0.0, 0.0, 0.0), base_quat((0, 0, 0, 1), 0.0)
    )
    ext = half_extents(prims.kind, prims.size, prims.rot)
    lo, hi = prims.center - ext, prims.center + ext  # world boxes: x forward, y lateral
    index = load_model().index

    def span(names, axis):
        ids = [index[n] for n in names]
        return 1000.0 * float(hi[ids, axis].max() - lo[ids, axis].min())

    def thick(name):
        return 2000.0 * float(prims.size[index[name], 0])

    return {
        "head_breadth": span(["neck"], 1),
        "head_length": span(["neck"], 0),
        "bideltoid_breadth": span(["chest", "right_shoulder", "left_shoulder"], 1),
        "chest_breadth": span(["chest"], 1),
        "chest_depth": span(["chest"], 0),
        "hip_breadth": span(["root", "right_hip", "left_hip"], 1),
        "upper_arm_thickness": thick("right_shoulder"),
        "forearm_thickness": thick("right_elbow"),
        "hand_breadth": thick("right_wrist"),
        "stature": 1000.0 * height_m,
    }


# --- the poses of a robot cell --------------------------------------------------------------
#
# Kneeling, crouching, lying and reaching people: a cell's camera sees them at maintenance,
# loading, teaching the robot, or after a fall. Their contacts with the floor are solved in model
# units (scale 1) for the base at the origin, facing +x, z up, y to the human's left: a pose's
# shape does not depend on its scale, so a contact solved here holds at every height, and
# `relations.stand_z` then puts the lowest point on the floor.

_ORIGIN = (0.0, 0.0, 0.0)
#: world axis about which a positive turn pitches +x (the facing direction) down
_LATERAL = np.array([0.0, 1.0, 0.0])
_UP = np.array([0.0, 0.0, 1.0])
#: a foot with its toes pointing back and its sole up (a kneeling leg's foot), in the world
_FOOT_BACK = matrix_to_quat(np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, -1.0, 0.0]]))
#: wrist height (share of stature) and reach ahead of the pelvis (share of stature) of a
#: `reaching` hand: 0.64-1.56 m high and at least 0.48 m ahead for people 1.6-1.9 m tall
REACH_HEIGHT_SHARE = (0.40, 0.82)
REACH_AHEAD_SHARE = 0.30
#: top of the head above the floor, as a share of standing height, when kneeling or crouching
KNEEL_HEAD_SHARE = (0.57, 0.78)
CROUCH_HEAD_SHARE = (0.47, 0.68)


def _stature() -> float:
    """Standing height of the identity pose in model units."""
    return reference_height() / REFERENCE_SCALING


def _index(name: str) -> int:
    return load_model().index[name]


def _unit_frames(p: Pose) -> tuple[np.ndarray, np.ndarray]:
    return link_frames(p, 1.0, _ORIGIN, base_quat(p.tilt, 0.0))


def _link_bottoms(p: Pose) -> np.ndarray:
    """Lowest point (model units) of each link's shape."""
    prims = posed_primitives(p, 1.0, _ORIGIN, base_quat(p.tilt, 0.0))
    return prims.center[:, 2] - half_extents(prims.kind, prims.size, prims.rot)[:, 2]


@cache
def _subtree(name: str) -> tuple[int, ...]:
    """Indices of link `name` and of every link below it (parents come before children)."""
    links = load_model().links
    out = [_index(name)]
    for i, lk in enumerate(links):
        if lk.parent in out:
            out.append(i)
    return tuple(out)


def _lowest(p: Pose, *names: str) -> float:
    """Lowest point (model units) of the named links and everything below them."""
    idx = [i for n in names for i in _subtree(n)]
    return float(_link_bottoms(p)[idx].min())


def _highest(p: Pose, *names: str) -> float:
    """Highest point (model units) of the named links alone (not the links below them)."""
    prims = posed_primitives(p, 1.0, _ORIGIN, base_quat(p.tilt, 0.0))
    idx = [_index(n) for n in names]
    ext = half_extents(prims.kind[idx], prims.size[idx], prims.rot[idx])
    return float((prims.center[idx, 2] + ext[:, 2]).max())


def _world_quat(p: Pose, name: str) -> np.ndarray:
    """World orientation of link `name` ("base" for the base)."""
    if name == "base":
        return base_quat(p.tilt, 0.0)
    return matrix_to_quat(_unit_frames(p)[1][_index(name)])


def _parent_quat(p: Pose, name: str) -> np.ndarray:
    """World orientation of the link that joint `name` hangs from."""
    parent = load_model().link(name).parent
    return base_quat(p.tilt, 0.0) if parent < 0 else matrix_to_quat(_unit_frames(p)[1][parent])


def _set_world(p: Pose, name: str, q_world, q_parent=None) -> None:
    """Turn the spherical joint `name` so that its link has world orientation `q_world`
    (`q_parent`: its parent's, when already known)."""
    q_parent = _parent_quat(p, name) if q_parent is None else q_parent
    p.joints[name] = list(quat_normalize(quat_mul(quat_conj(q_parent), q_world)))


def _turn(p: Pose, name: str, axis, angle: float) -> None:
    """Turn link `name` (a spherical joint, or "base") by `angle` (rad) about world `axis`."""
    r = quat_from_axis_angle(axis, angle)
    if name == "base":
        up_inv = quat_conj(Y_UP_TO_Z_UP)
        p.tilt = tuple(quat_normalize(quat_mul(up_inv, quat_mul(r, base_quat(p.tilt, 0.0)))))
    else:
        _set_world(p, name, quat_mul(r, _world_quat(p, name)))


def _bisect(f, lo: float, hi: float, iters: int = 26) -> float | None:
    """x in [lo, hi] where f changes sign; None when f has the same sign at both ends."""
    f_lo, f_hi = f(lo), f(hi)
    if f_lo == 0.0:
        return lo
    if f_hi == 0.0:
        return hi
    if (f_lo > 0) == (f_hi > 0):
        return None
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        f_mid = f(mid)
        if (f_mid > 0) == (f_lo > 0):
            lo, f_lo = mid, f_mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def _nearest_root(f, span: float, steps: int = 8) -> float | None:
    """The root of f in [-span, span] nearest 0 (a grid scan, then bisection), or None."""
    xs = np.linspace(-span, span, 2 * steps + 1)
    vals = [f(x) for x in xs]
    brackets = [
        (a, b)
        for a, b, fa, fb in zip(xs[:-1], xs[1:], vals[:-1], vals[1:], strict=True)
        if (fa > 0) != (fb > 0) or fa == 0.0
    ]
    if not brackets:
        return None
    a, b = min(brackets, key=lambda ab: min(abs(ab[0]), abs(ab[1])))
    return _bisect(f, a, b)


def _shapes(p: Pose, idx) -> tuple[np.ndarray, ...]:
    """(kind, size, centre, rotation) of the shapes of links `idx`, in model units."""
    prims = posed_primitives(p, 1.0, _ORIGIN, base_quat(p.tilt, 0.0))
    return prims.kind[idx], prims.size[idx], prims.center[idx], prims.rot[idx]


def _turned_bottoms(shapes, pivot, axis, angle: float) -> np.ndarray:
    """Lowest point of each of `shapes` once all are turned by `angle` about `axis` at `pivot`."""
    kind, size, center, rot = shapes
    turn = quat_to_matrix(quat_from_axis_angle(axis, angle))
    c = pivot + (center - pivot) @ turn.T
    return c[:, 2] - half_extents(kind, size, turn @ rot)[:, 2]


def _settle(
    p: Pose, name: str, floor_z: float, span_deg: float = 50.0, axis=None, touching=None
) -> bool:
    """Turn limb `name` by the least angle that puts its lowest point on `floor_z`, as gravity
    would: about the horizontal axis across the limb, or `axis` (world); `touching` names the
    sub-limb that must touch (default: all of it). False (limb unchanged) when no turn does."""
    pivot = _unit_frames(p)[0][_index(name)]
    shapes = _shapes(p, list(_subtree(touching or name)))
    if axis is None:
        axis = np.cross(shapes[2].mean(0) - pivot, _UP)
        if np.linalg.norm(axis) < 0.1:  # (nearly) vertical: no horizontal axis across it
            return False
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)

    def gap(angle: float) -> float:
        return float(_turned_bottoms(shapes, pivot, axis, angle).min()) - floor_z

    angle = _nearest_root(gap, np.radians(span_deg))
    if angle is None:
        return False
    _turn(p, name, axis, angle)
    return True


def _foot_flat(side: str, toe_out: float = 0.0, heel_up: float = 0.0) -> np.ndarray:
    """World orientation of a foot on the floor, toes turned out by `toe_out` degrees and the
    heel raised by `heel_up` degrees (then only the toes touch)."""
    toe = -toe_out if side == "right" else toe_out  # the human's right is -y
    pitch = quat_from_axis_angle(_LATERAL, np.radians(heel_up))
    return quat_mul(yaw_quat(np.radians(toe)), quat_mul(pitch, Y_UP_TO_Z_UP))


def _set_knee(p: Pose, side: str, bend_deg: float) -> None:
    p.joints[f"{side}_knee"] = [float(np.radians(-bend_deg))]


def _shin_quat(p: Pose, side: str, bend_deg: float, thigh_q=None) -> np.ndarray:
    """World orientation of the shin for a knee bent `bend_deg` (`thigh_q`: the thigh's)."""
    thigh_q = _world_quat(p, f"{side}_hip") if thigh_q is None else thigh_q
    axis = load_model().link(f"{side}_knee").axis
    return quat_mul(thigh_q, quat_from_axis_angle(axis, np.radians(-bend_deg)))


def _drop_below_joint(link: str, q_world) -> float:
    """How far (model units) the shape of `link` reaches below its joint at orientation q_world."""
    a, i = _model_arrays(), _index(link)
    r = quat_to_matrix(q_world)
    center_z = (r @ a["shape_xyz"][i])[2]
    ext = half_extents(a["kind"][i : i + 1], a["size"][i : i + 1], (r @ a["shape_rot"][i])[None])
    return float(ext[0, 2] - center_z)


def _plant_foot(p: Pose, side: str, floor_z: float, foot_q, knee_ahead: bool = True) -> bool:
    """Bend the knee until the foot, held at world orientation `foot_q`, rests on `floor_z`.

    Of the two bends that reach, `knee_ahead` takes the one with the knee ahead of the ankle.
    False (knee straight) when the foot cannot reach the floor.
    """
    ankle = f"{side}_ankle"
    thigh_q = _world_quat(p, f"{side}_hip")
    knee_z = _unit_frames(p)[0][_index(f"{side}_knee")][2]
    shin = np.array(load_model().link(ankle).joint_xyz)
    drop = _drop_below_joint(ankle, foot_q)

    def gap(bend: float) -> float:
        ankle_z = knee_z + (quat_to_matrix(_shin_quat(p, side, bend, thigh_q)) @ shin)[2]
        return ankle_z - drop - floor_z

    grid = np.arange(0.0, 165.1, 7.5)
    deepest = float(grid[int(np.argmin([gap(b) for b in grid]))])
    bend = _bisect(gap, deepest, 165.0) if knee_ahead else _bisect(gap, 0.0, deepest)
    ok = bend is not None
    bend = bend if ok else 0.0
    _set_knee(p, side, bend)
    _set_world(p, ankle, foot_q, _shin_quat(p, side, bend, thigh_q))
    return ok


def _kneel_leg(p: Pose, side: str) -> None:
    """The shin flat on the floor behind the knee, the foot pointing back, toes down on the
    floor (the hip set beforehand)."""
    knee = _index(f"{side}_knee")
    thigh_q = _world_quat(p, f"{side}_hip")

    def shin_rise(bend: float) -> float:
        shin = quat_to_matrix(_shin_quat(p, side, bend, thigh_q))
        return float(-shin[2, 1])  # z of the shin's downward axis

    _set_knee(p, side, _bisect(shin_rise, 0.0, 178.0) or 90.0)
    _set_world(p, f"{side}_ankle", _FOOT_BACK)
    _settle(p, f"{side}_ankle", float(_link_bottoms(p)[knee]))


def _hands_off_floor(p: Pose, floor_z: float) -> None:
    """Lift any arm that reaches below the floor until it just rests on it."""
    for side in ("right", "left"):
        if _lowest(p, f"{side}_shoulder") < floor_z:
            _settle(p, f"{side}_shoulder", floor_z, span_deg=90.0)


def _hand_to(p: Pose, side: str, target) -> bool:
    """Inverse kinematics of one arm to a wrist target (world, model units); False when out of
    reach."""
    return reach(p, 1.0, _ORIGIN, base_quat(p.tilt, 0.0), side, np.asarray(target, np.float64))


def _lean(p: Pose, pelvis: float, chest: float, side_tilt: float, twist: float) -> None:
    """Hinge the pelvis forward `pelvis` degrees and bend the chest `chest` more."""
    p.tilt = tuple(trunk_quat(pelvis))
    p.joints["chest"] = list(trunk_quat(chest, side_tilt, twist))


def _head_share(p: Pose, floor_z: float) -> float:
    """Height of the top of the head above `floor_z`, as a share of standing height."""
    return (_highest(p, "neck") - floor_z) / _stature()


def _keep_head_within(p: Pose, floor_z: float, lo: float, hi: float) -> None:
    """Bend the chest further forward (or less) until the head's top is within `lo`-`hi` of
    standing height above `floor_z`."""
    share = _head_share(p, floor_z)
    if lo <= share <= hi:
        return
    goal = hi if share > hi else lo
    chest0 = p.joints["chest"]

    def above_goal(extra: float) -> float:
        p.joints["chest"] = list(quat_mul(trunk_quat(extra), chest0))
        return _head_share(p, floor_z) - goal

    extra = _bisect(above_goal, -30.0, 60.0)
    p.joints["chest"] = list(quat_mul(trunk_quat(extra or 0.0), chest0))


def _relaxed_arm(p: Pose, side: str, rng, trunk_lean: float) -> None:
    """An arm hanging, a little forward and bent, whatever the trunk's lean."""
    u = rng.uniform
    _set_arm(p, side, trunk_lean + u(-5, 30), u(3, 15), 0.0, u(5, 60))


def _kneeling(rng: np.random.Generator) -> Pose:
    """Both knees, or one knee with the other foot in front, on the floor; trunk upright to
    leaning forward; hands working low, on a knee, on the floor, or at rest."""
    u = rng.uniform
    p = identity_pose()
    pelvis, chest = u(-5, 15), u(0, 30)
    _lean(p, pelvis, chest, u(-6, 6), u(-15, 15))
    p.joints["neck"] = list(trunk_quat(u(0, 30), 0.0, u(-20, 20)))
    front = str(rng.choice(["right", "left"])) if rng.random() < 0.5 else None
    down = tuple(s for s in ("right", "left") if s != front)
    thigh = u(-5, 12) if front else u(-5, 35)  # forward of vertical; 35: sitting back a little
    abd = u(2, 10)
    for s in down:
        _set_leg_hip(p, s, thigh + pelvis, abd)
        _kneel_leg(p, s)
    floor = min(float(_link_bottoms(p)[_index(f"{s}_knee")]) for s in down)
    if front:
        for hip_flex in (u(70, 86), 65.0, 55.0):
            _set_leg_hip(p, front, hip_flex + pelvis, u(0, 10))
            if _plant_foot(p, front, floor, _foot_flat(front, u(0, 15))):
                break
    _keep_head_within(p, floor, *KNEEL_HEAD_SHARE)
    _kneeling_arms(p, rng, floor, front, pelvis + chest)
    _hands_off_floor(p, floor)
    return p


def _set_leg_hip(p: Pose, side: str, flex: float, abd: float, twist: float = 0.0) -> None:
    p.joints[f"{side}_hip"] = list(limb_quat(flex, abd, twist, side))


def _kneeling_arms(p: Pose, rng, floor: float, front: str | None, lean: float) -> None:
    """Hands on a low work piece, on the front knee, on the floor, or at rest."""
    u = rng.uniform
    stature, hand_r = _stature(), limb_lengths(1.0)["hand_radius"]
    pos, _ = _unit_frames(p)
    mode = rng.choice(["low_work", "knee", "floor", "rest"], p=[0.4, 0.2, 0.2, 0.2])
    if mode == "knee" and front is None:
        mode = "low_work"
    for side in ("right", "left"):
        sh = pos[_index(f"{side}_shoulder")]
        if mode == "low_work":
            target = (u(0.12, 0.30) * stature, sh[1] * u(0.2, 0.9), floor + u(0.1, 0.3) * stature)
        elif mode == "floor":
            target = (u(0.10, 0.30) * stature, sh[1] * u(0.6, 1.4), floor + hand_r)
        elif mode == "knee" and side == front:
            knee = pos[_index(f"{front}_knee")]
            shin_r = load_model().link(f"{front}_knee").shape_size[0]
            target = knee + np.array([u(-0.1, 0.3), 0.0, shin_r + hand_r])
        else:
            target = None
        if target is None or not _hand_to(p, side, target):
            _relaxed_arm(p, side, rng, lean)


def _crouching(rng: np.random.Generator) -> Pose:
    """A deep squat, feet flat or on the toes, knees apart, trunk forward, hands in front, on
    the knees or on the floor."""
    u = rng.uniform
    p = identity_pose()
    pelvis, chest = u(15, 35), u(5, 25)
    _lean(p, pelvis, chest, u(-6, 6), u(-15, 15))
    p.joints["neck"] = list(trunk_quat(u(-15, 20), 0.0, u(-20, 20)))
    heel_up = u(15, 40) if rng.random() < 0.35 else 0.0
    first = str(rng.choice(["right", "left"]))
    second = "left" if first == "right" else "right"
    thigh, abd, shin = u(90, 120), u(8, 30), u(15, 40)
    _set_leg_hip(p, first, thigh + pelvis, abd)
    _set_knee(p, first, thigh + shin)
    _set_world(p, f"{first}_ankle", _foot_flat(first, u(5, 25), heel_up))
    floor = _lowest(p, f"{first}_ankle")
    for dthigh in (u(-8, 8), 0.0):
        _set_leg_hip(p, second, thigh + dthigh + pelvis, abd + u(-5, 5))
        if _plant_foot(p, second, floor, _foot_flat(second, u(5, 25), heel_up)):
            break
    _keep_head_within(p, floor, *CROUCH_HEAD_SHARE)
    _crouching_arms(p, rng, floor, pelvis + chest)
    _hands_off_floor(p, floor)
    return p


def _crouching_arms(p: Pose, rng, floor: float, lean: float) -> None:
    """Forearms on the knees, hands on the floor ahead, or hands together in front."""
    u = rng.uniform
    stature, hand_r = _stature(), limb_lengths(1.0)["hand_radius"]
    pos, _ = _unit_frames(p)
    mode = rng.choice(["knees", "floor", "front"], p=[0.35, 0.35, 0.3])
    for side in ("right", "left"):
        knee = pos[_index(f"{side}_knee")]
        if mode == "knees":
            target = knee + np.array([u(0.2, 0.6), -0.3 * np.sign(knee[1]), u(-0.4, 0.0)])
        elif mode == "floor":
            target = (knee[0] + u(0.1, 0.8), knee[1] * u(0.2, 1.0), floor + hand_r)
        else:
            target = (
                knee[0] + u(0.2, 0.6),
                knee[1] * u(0.0, 0.5),
                knee[2] + u(-0.2, 0.3) * stature,
            )
        if not _hand_to(p, side, target):
            _relaxed_arm(p, side, rng, lean)


def _reaching(rng: np.random.Generator) -> Pose:
    """Standing, trunk bent 10-60 degrees forward, one or both hands reaching ahead at 0.40-0.82
    of stature (into a machine, over a conveyor, to a robot's tool)."""
    u = rng.uniform
    stature = _stature()
    p = identity_pose()
    lead = str(rng.choice(["right", "left"]))
    other = "left" if lead == "right" else "right"
    stride = u(0, 15)
    target = None
    for _ in range(60):
        bend = u(10, 60)
        pelvis = bend * u(0.35, 0.65)
        _lean(p, pelvis, bend - pelvis, u(-5, 5), u(-10, 10))
        abd = u(0, 8)  # the same for both legs, so the leading foot can always reach down
        _set_leg_hip(p, other, pelvis - stride, abd)
        _set_knee(p, other, u(0, 8))
        _set_world(p, f"{other}_ankle", _foot_flat(other, u(0, 15)))
        floor = _lowest(p, f"{other}_ankle")
        _set_leg_hip(p, lead, pelvis + stride, abd)
        _plant_foot(p, lead, floor, _foot_flat(lead, u(0, 15)))
        hand = str(rng.choice(["right", "left"]))
        target = _reach_target(p, rng, hand, floor, stature)
        if target is not None and _hand_to(p, hand, target):
            break
        target = None
    if target is None:  # never seen: straight ahead of the shoulder, which is always in reach
        sh = _unit_frames(p)[0][_index(f"{hand}_shoulder")]
        arm = limb_lengths(1.0)
        target = sh + np.array([0.9 * (arm["upper_arm"] + arm["forearm"]), 0.0, 0.0])
        _hand_to(p, hand, target)
    p.joints["neck"] = list(trunk_quat(u(-35, 0), 0.0, u(-15, 15)))  # eyes on the target
    second = "left" if hand == "right" else "right"
    if rng.random() < 0.45:  # both hands: the second near the first
        pos, _ = _unit_frames(p)
        sh = pos[_index(f"{second}_shoulder")]
        t2 = np.array([target[0] + u(-0.3, 0.3), sh[1] * u(0.3, 1.0), target[2] + u(-0.3, 0.3)])
        if not _hand_to(p, second, t2):
            _relaxed_arm(p, second, rng, bend)
    else:
        _relaxed_arm(p, second, rng, bend)
    _hands_off_floor(p, floor)
    return p


def _reach_target(p: Pose, rng, side: str, floor: float, stature: float) -> np.ndarray | None:
    """A wrist target ahead of the `side` shoulder within REACH_HEIGHT_SHARE and at least
    REACH_AHEAD_SHARE ahead of the pelvis, nearly at arm's length; None when none is drawn."""
    u = rng.uniform
    arm = limb_lengths(1.0)
    arm_len = arm["upper_arm"] + arm["forearm"]
    sh = _unit_frames(p)[0][_index(f"{side}_shoulder")]
    inward = 1.0 if side == "right" else -1.0  # the right arm reaches across towards +y
    lo, hi = REACH_HEIGHT_SHARE
    for _ in range(20):
        el, az = np.radians(u(-45, 30)), np.radians(inward * u(-15, 25))
        d = u(0.85, 0.97) * arm_len
        t = sh + d * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        if lo <= (t[2] - floor) / stature <= hi and t[0] / stature >= REACH_AHEAD_SHARE:
            return t
    return None


def _lying(rng: np.random.Generator) -> Pose:
    """On the floor on the back, the front or three-quarters on a side (the recovery
    position), limbs spread, bent or alongside; trunk, head and limbs resting on the floor."""
    u = rng.uniform
    p = identity_pose()
    kind = str(rng.choice(["back", "front", "side"], p=[0.4, 0.3, 0.3]))
    sign = float(rng.choice([-1.0, 1.0]))
    roll = {"back": 180.0 + u(-12, 12), "front": u(-12, 12), "side": sign * u(40, 56)}[kind]
    # head towards +x: the body's axis (model y) pitched forward, rolled about itself
    roll_q = quat_from_axis_angle((0.0, 1.0, 0.0), np.radians(roll))
    p.tilt = tuple(quat_normalize(quat_mul(trunk_quat(90.0), roll_q)))
    p.joints["chest"] = list(trunk_quat(u(-8, 8), u(-12, 12), u(-10, 10)))
    knees_up = _lying_limbs(p, rng, kind)
    _settle_lying(p, knees_up)
    return p


def _lying_limbs(p: Pose, rng, kind: str) -> tuple[str, ...]:
    """Arms laid out on the floor around a lying body, legs set relative to it; returns the
    legs with a knee up."""
    u = rng.uniform
    knees_up: list[str] = []
    pos, _ = _unit_frames(p)
    hips_z = {s: pos[_index(f"{s}_hip")][2] for s in ("right", "left")}
    upper = max(hips_z, key=hips_z.get) if kind == "side" else None
    for side in ("right", "left"):
        # on the floor: beside the head, out to the side or along the body; then bent
        az, elbow = {
            "overhead": (u(15, 45), u(0, 60)),
            "out": (u(60, 120), u(0, 100)),
            "alongside": (u(145, 175), u(0, 40)),
        }[str(rng.choice(["overhead", "out", "alongside"]))]
        _point_limb(p, f"{side}_shoulder", _floor_direction(p, side, az))
        p.joints[f"{side}_elbow"] = [float(np.radians(elbow))]
        if kind == "back" and rng.random() < 0.3:
            _set_leg_hip(p, side, u(25, 40), u(0, 10))
            knees_up.append(side)
        elif side == upper:  # on a side, the upper leg is drawn up
            _set_leg_hip(p, side, u(40, 90), u(0, 10))
            _set_knee(p, side, u(40, 100))
        else:
            _set_leg_hip(p, side, u(-5, 15), u(0, 20))
            _set_knee(p, side, u(0, 20))
        if kind == "front":
            p.joints[f"{side}_ankle"] = list(limb_quat(u(-50, -20), 0.0, 0.0, side))
    if kind == "front":  # the face turned to one side
        p.joints["neck"] = list(trunk_quat(u(-20, 0), 0.0, float(rng.choice([-1, 1])) * u(50, 80)))
    return tuple(knees_up)


def _point_limb(p: Pose, name: str, direction) -> None:
    """Turn limb `name` the least way that points it (its link's -y axis) along `direction`."""
    q = _world_quat(p, name)
    along = quat_to_matrix(q) @ np.array([0.0, -1.0, 0.0])
    _set_world(p, name, quat_mul(rotation_between(along, direction), q))


def _floor_direction(p: Pose, side: str, azimuth: float) -> np.ndarray:
    """A horizontal direction `azimuth` degrees from the head's (+x) towards the `side` arm's
    side of a lying body (towards its front when the shoulders are stacked)."""
    pos, rot = _unit_frames(p)
    offset = pos[_index(f"{side}_shoulder")][1] - pos[_index("root")][1]
    if abs(offset) > 0.2:
        away = np.array([0.0, np.sign(offset), 0.0])
    else:
        front = rot[_index("root")] @ np.array([1.0, 0.0, 0.0])
        away = np.array([0.0, np.sign(front[1]) or 1.0, 0.0])
    a = np.radians(azimuth)
    return np.array([np.cos(a), 0.0, 0.0]) + np.sin(a) * away


def _settle_lying(p: Pose, knees_up: tuple[str, ...]) -> None:
    """Pitch the body until shoulders and hips both rest, then lower head, arms and legs."""
    upper = ("chest", "right_shoulder", "left_shoulder")
    lower = ("root", "right_hip", "left_hip")

    groups = [[_index(n) for n in upper], [_index(n) for n in lower]]
    shapes = _shapes(p, groups[0] + groups[1])
    k = len(groups[0])

    def head_low(angle: float) -> float:
        b = _turned_bottoms(shapes, np.zeros(3), _LATERAL, angle)
        return float(b[:k].min() - b[k:].min())

    angle = _bisect(head_low, np.radians(-25.0), np.radians(25.0))
    if angle is not None:
        _turn(p, "base", _LATERAL, angle)
    bottoms = _link_bottoms(p)
    floor = float(bottoms[groups[0] + groups[1]].min())
    _settle(p, "neck", floor, span_deg=30.0)
    trunk_top = _highest(p, "chest", "root")
    for side in ("right", "left"):
        _settle(p, f"{side}_shoulder", floor, span_deg=60.0)
        _rest_lower_limb(p, f"{side}_shoulder", f"{side}_elbow", floor, 180.0)
        if _highest(p, f"{side}_elbow", f"{side}_wrist") > trunk_top:  # propped up: straighten
            p.joints[f"{side}_elbow"] = [0.0]
            _settle(p, f"{side}_shoulder", floor, span_deg=90.0)
        if side in knees_up:
            foot = quat_mul(_world_quat(p, "base"), quat_from_axis_angle((0, 0, 1), -np.pi / 2))
            _plant_foot(p, side, floor, foot, knee_ahead=False)
        else:
            _settle(p, f"{side}_hip", floor, span_deg=40.0)
            _rest_lower_limb(p, f"{side}_hip", f"{side}_knee", floor, 60.0)
    _hands_off_floor(p, floor)


def _rest_lower_limb(p: Pose, root: str, lower: str, floor_z: float, span_deg: float) -> None:
    """Roll a limb about its upper segment until the bent lower segment (forearm or shin)
    rests on the floor, when the roll needed is within `span_deg`."""
    pos, _ = _unit_frames(p)
    along = pos[_index(lower)] - pos[_index(root)]
    if _lowest(p, lower) > floor_z:
        _settle(p, root, floor_z, span_deg, axis=along, touching=lower)


_CELL_BUILDERS = {
    "kneeling": _kneeling,
    "crouching": _crouching,
    "lying": _lying,
    "reaching": _reaching,
}
