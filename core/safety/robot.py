"""The cell's robot, posed from its joint states: bounding capsules per link in the cell
frame, its silhouette as a camera sees it, and how fast its links move.

The robot is a `core/synth/robots.py` model (a catalogue name such as "panda", or a URDF or
xacro path, relative paths taken from the cell file's folder) placed at the cell file's base:
(x, y, z) in the cell frame, turned by its yaw about z, and for a robot hanging from a gantry
(`upside_down`) first turned about x by pi, as `PlacedRobot.base_quat` does.

Each link with geometry gets one capsule, fitted once in the link's frame: along the
principal axis of its shapes (of the three, the one giving the smallest capsule), its radius
then grown until every corner of the link's mesh hull, every box corner, every sphere and a
polygon circumscribing each cylinder's end circles lie inside. A capsule therefore contains
its link as the model holds it (meshes of more than `robots.MAX_LINK_FACES` triangles are
decimated on loading, which keeps them within about a percent). Posing moves the capsules
with their links.

A joint state must name every movable joint of the robot and no other (ValueError naming the
first missing or unknown joint): the service decides what a partial state means.
"""

from __future__ import annotations

import math
from pathlib import Path

import numba
import numpy as np

from topseg.core.camera import depth_to_range
from topseg.core.safety.separation import Capsules
from topseg.core.safety.surface import RobotSurface, posed_surface, surface_layout
from topseg.core.synth.geometry import (
    BOX,
    CAPSULE,
    CYLINDER,
    SPHERE,
    quat_from_axis_angle,
    quat_mul,
    yaw_quat,
)
from topseg.core.synth.render import Primitives, Triangles, raycast
from topseg.core.synth.robots import RANDOM, ROBOTS, pedestal_primitives, robot_model

__all__ = ["Capsules", "CellRobot", "base_quat", "fit_capsule", "grow_mask", "padded_box"]

#: sides of the polygon that stands in for a cylinder's end circle (circumscribing it)
_CIRCLE_SIDES = 16
#: added to every fitted radius (m), so that rounding never leaves a vertex outside
_RADIUS_SLACK_M = 1e-9


def base_quat(yaw_deg: float, upside_down: bool) -> np.ndarray:
    """The base's orientation (x, y, z, w): turned by yaw about z; upside down first turned
    about x by pi (a robot hanging from a gantry)."""
    yaw = yaw_quat(math.radians(yaw_deg))
    if upside_down:
        return quat_mul(yaw, quat_from_axis_angle((1.0, 0.0, 0.0), np.pi))
    return yaw


def model_name(urdf: str, base_dir: Path) -> str:
    """What `robot_model` loads a cell file's `urdf` by: a catalogue or random arm's name
    as it is, a relative path from `base_dir`."""
    if urdf in ROBOTS or urdf.startswith(RANDOM + ":"):
        return urdf
    path = Path(urdf).expanduser()
    if not path.is_absolute():
        path = Path(base_dir) / path
    return str(path)


class CellRobot:
    """The cell's robot: its model placed at the cell file's base (`spec`, a `RobotSpec`),
    posed by joint states into bounding capsules and silhouettes."""

    def __init__(self, spec, base_dir: Path):
        self.spec = spec
        self.model = robot_model(model_name(spec.urdf, Path(base_dir)))
        self.joint_names: tuple[str, ...] = tuple(self.model.joint_names)
        self.base_pos = np.asarray(spec.base_xyz_m, np.float64).reshape(3)
        self.base_quat = base_quat(float(spec.base_yaw_deg), bool(spec.upside_down))
        self.links: tuple[str, ...] = self.model.links
        fits = [fit_capsule(*self.model.link_shapes(i)) for i in range(len(self.links))]
        self._local_a = np.array([a for a, _, _ in fits]).reshape(-1, 3)
        self._local_b = np.array([b for _, b, _ in fits]).reshape(-1, 3)
        self._radius = np.array([r for _, _, r in fits], np.float64)
        links, tri_link, prim_link = self.model.shape_links()
        zero = {n: 0.0 for n in self.joint_names}
        prims, tris = self.model.link_geometry(zero, self.base_pos, self.base_quat)
        self._layout = surface_layout(prims, prim_link, tris, tri_link, links, self.links)
        #: the last posing's shapes: (joint values, (primitives, triangles)), read by
        #: `geometry` and `surface` alike (one frame asks both for the same joints)
        self._last_shapes: tuple[tuple[float, ...], tuple[Primitives, Triangles]] | None = None

    def check_joints(self, joints: dict[str, float]) -> dict[str, float]:
        """`joints` as {name: float}; ValueError naming a missing, unknown or not finite joint."""
        missing = [n for n in self.joint_names if n not in joints]
        if missing:
            raise ValueError(
                f"robot {self.spec.name}: joint state lacks joint {missing[0]!r}"
                + (f" and {len(missing) - 1} more" if len(missing) > 1 else "")
            )
        unknown = sorted(set(joints) - set(self.joint_names))
        if unknown:
            raise ValueError(f"robot {self.spec.name}: no joint {unknown[0]!r}")
        values = {n: float(joints[n]) for n in self.joint_names}
        bad = [n for n, v in values.items() if not math.isfinite(v)]
        if bad:
            raise ValueError(f"robot {self.spec.name}: joint {bad[0]!r} is {values[bad[0]]}")
        return values

    def capsules(self, joints: dict[str, float]) -> Capsules:
        """The posed robot's bounding capsules in the cell frame, one per link with geometry."""
        poses = self.model.link_poses(self.check_joints(joints), self.base_pos, self.base_quat)
        rot, pos = poses[:, :3, :3], poses[:, :3, 3]
        a = np.einsum("kij,kj->ki", rot, self._local_a) + pos
        b = np.einsum("kij,kj->ki", rot, self._local_b) + pos
        return Capsules(a, b, self._radius.copy(), self.links)

    def geometry(self, joints: dict[str, float]) -> tuple[Primitives, Triangles]:
        """The posed robot's shapes in the cell frame with its pedestal (what `silhouette`
        renders)."""
        prims, tris = self._link_shapes(joints)
        return Primitives.concat([prims, self.pedestal()]), tris

    def surface(self, joints: dict[str, float]) -> RobotSurface:
        """The posed robot's links as a surface to measure separations to (no pedestal: it
        does not move), each link with its capsule (`surface.posed_surface`)."""
        prims, tris = self._link_shapes(joints)
        return posed_surface(self._layout, prims, tris, self.capsules(joints))

    def _link_shapes(self, joints: dict[str, float]) -> tuple[Primitives, Triangles]:
        """The links' shapes posed at `joints`, in the cell frame (the last posing kept)."""
        values = self.check_joints(joints)
        key = tuple(values[n] for n in self.joint_names)
        last = self._last_shapes
        if last is not None and last[0] == key:
            return last[1]
        shapes = self.model.link_geometry(values, self.base_pos, self.base_quat)
        self._last_shapes = (key, shapes)
        return shapes

    def pedestal(self) -> Primitives:
        """The pedestal of the spec, from the floor to the base, labelled robot; none for a
        robot without one (or hanging upside down)."""
        height = float(self.base_pos[2])
        if self.spec.pedestal == "none" or height <= 0 or self.spec.upside_down:
            return Primitives.empty()
        return pedestal_primitives(
            float(self.base_pos[0]),
            float(self.base_pos[1]),
            math.radians(float(self.spec.base_yaw_deg)),
            height,
            float(self.spec.pedestal_size_m),
            self.spec.pedestal == "cylinder",
        )

    def silhouette(
        self, joints: dict[str, float], mount, placement, margin_m: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """The robot alone as the camera at `placement` (a `CameraPlacement`) with `mount`
        sees it: (H, W) uint16 depth in mm as that camera sends it (range for a `radial`
        camera), 0 where the robot is not; and a bool mask of the robot's pixels grown by
        `margin_m` at the depth of the robot's nearest pixel (`grow_mask`)."""
        if not (math.isfinite(margin_m) and margin_m >= 0):
            raise ValueError(f"silhouette margin must be a distance >= 0 m, got {margin_m}")
        prims, tris = self.geometry(joints)
        prims, tris = _to_camera_world(prims, tris, placement)
        depth_mm, _ = raycast(prims, mount, tris)
        k = mount.intrinsics
        mask = grow_mask(depth_mm > 0, depth_mm, margin_m, k.fx, k.fy)
        if mount.radial:
            depth_mm = depth_to_range(depth_mm, k)
        return depth_mm, mask

    def link_speeds(
        self, joints_a: dict[str, float], joints_b: dict[str, float], dt_s: float
    ) -> float:
        """The fastest capsule end's speed (m/s) from joint state a to b, `dt_s` apart."""
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"link speeds need a time step > 0 s, got {dt_s}")
        ca, cb = self.capsules(joints_a), self.capsules(joints_b)
        moved = np.concatenate([cb.a - ca.a, cb.b - ca.b])
        if not len(moved):
            return 0.0
        return float(np.linalg.norm(moved, axis=1).max() / dt_s)


def _rigid_of(placement) -> tuple[np.ndarray, np.ndarray]:
    """(M, t) with `placement.to_camera_world(p) = M @ p + t`, read off the placement."""
    probe = np.asarray(placement.to_camera_world(np.vstack([np.zeros(3), np.eye(3)])), np.float64)
    t = probe[0]
    return (probe[1:] - t).T, t


def _to_camera_world(prims: Primitives, tris: Triangles, placement):
    """Cell-frame shapes moved into the camera's world frame."""
    m, t = _rigid_of(placement)
    moved = Primitives(prims.kind, prims.size, prims.center @ m.T + t, m @ prims.rot, prims.label)
    # one (3n, 3) product: a stack of n (3, 3) products takes four times as long
    vertices = tris.vertices.reshape(-1, 3) @ m.T + t
    return moved, Triangles(vertices.reshape(tris.vertices.shape), tris.label)


# --- fitting a capsule to a link ------------------------------------------------------------


def _support(hull, kinds, sizes, poses) -> tuple[np.ndarray, np.ndarray]:
    """Points with pads (a ball of radius pad around each) whose convex hull of balls
    contains the link: hull corners, box corners, sphere centres, capsule ends, and the
    corners of prisms circumscribing the cylinders."""
    points, pads = [np.asarray(hull, np.float64).reshape(-1, 3)], [np.zeros(len(hull))]
    angles = np.linspace(0.0, 2 * np.pi, _CIRCLE_SIDES, endpoint=False)
    circle = np.stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)], 1)
    circle /= np.cos(np.pi / _CIRCLE_SIDES)
    for kind, size, pose in zip(kinds, sizes, poses, strict=True):
        rot, centre = pose[:3, :3], pose[:3, 3]
        if kind == BOX:
            local = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * size
            pad = 0.0
        elif kind == SPHERE:
            local, pad = np.zeros((1, 3)), size[0]
        elif kind == CAPSULE:
            local, pad = np.array([[0, 0, -size[1]], [0, 0, size[1]]]), size[0]
        elif kind == CYLINDER:
            rim, half = size[0] * circle, np.array([0.0, 0.0, size[1]])
            local = np.concatenate([rim - half, rim + half])
            pad = 0.0
        else:
            raise ValueError(f"unknown primitive kind {kind}")
        points.append(local @ rot.T + centre)
        pads.append(np.full(len(local), float(pad)))
    return np.concatenate(points), np.concatenate(pads)


def fit_capsule(hull, kinds, sizes, poses) -> tuple[np.ndarray, np.ndarray, float]:
    """(a, b, radius): a capsule containing a link's shapes (`RobotModel.link_shapes`), in
    the link's frame; of the capsules along the shapes' three principal axes, the smallest."""
    points, pads = _support(hull, kinds, sizes, poses)
    if not len(points):
        raise ValueError("a link without geometry has no capsule")
    centre = points.mean(axis=0)
    spread = points - centre
    _, _, axes = np.linalg.svd(spread.T @ spread)
    best = None
    for axis in axes:
        a, b = _capsule_along(points, pads, axis)
        radius = float((_segment_distances(points, a, b) + pads).max()) + _RADIUS_SLACK_M
        volume = np.pi * radius**2 * np.linalg.norm(b - a) + 4.0 / 3.0 * np.pi * radius**3
        if best is None or volume < best[0]:
            best = (volume, a, b, radius)
    return best[1], best[2], best[3]


def _capsule_along(points, pads, axis) -> tuple[np.ndarray, np.ndarray]:
    """The segment of a capsule along `axis`: its line through the middle of the points'
    spread across the axis, its ends pulled in as far as the radius that line needs allows."""
    axis = axis / np.linalg.norm(axis)
    t = points @ axis
    across = points - np.outer(t, axis)
    lo, hi = across.min(axis=0), across.max(axis=0)
    middle = (lo + hi) / 2
    middle -= (middle @ axis) * axis
    off_axis = np.linalg.norm(across - middle, axis=1)
    radius = float((off_axis + pads).max())
    reach = np.sqrt(np.maximum((radius - pads) ** 2 - off_axis**2, 0.0))
    t_hi, t_lo = float((t - reach).max()), float((t + reach).min())
    if t_lo > t_hi:
        t_lo = t_hi = (t_lo + t_hi) / 2
    return middle + t_lo * axis, middle + t_hi * axis


def _segment_distances(points, a, b) -> np.ndarray:
    """(n,) distance of each point to the segment a..b."""
    axis = b - a
    length2 = float(axis @ axis)
    t = np.zeros(len(points)) if length2 == 0 else np.clip((points - a) @ axis / length2, 0, 1)
    return np.linalg.norm(points - (a + t[:, None] * axis), axis=1)


# --- growing the silhouette ----------------------------------------------------------------


def grow_mask(mask: np.ndarray, depth_mm: np.ndarray, margin_m: float, fx: float, fy: float):
    """`mask` grown by `margin_m` as seen at the depth of its nearest pixel: every pixel
    within the ellipse of half axes margin * fx / z, margin * fy / z pixels (z the smallest
    depth under the mask, in m) of a mask pixel. The nearest depth grows it the most, so
    the margin is never less than `margin_m` anywhere on the robot."""
    mask = np.ascontiguousarray(mask, dtype=np.bool_)
    if not mask.any() or margin_m <= 0:
        return mask.copy()
    z_m = float(np.asarray(depth_mm)[mask].min()) / 1000.0
    if z_m <= 0:
        raise ValueError("grow_mask needs the depth of every pixel under the mask")
    half_widths = ellipse_half_widths(margin_m * fx / z_m, margin_m * fy / z_m)
    # only the mask's bounding box, widened by the ellipse, can grow: the kernel runs there
    box = padded_box(mask, (len(half_widths) - 1) // 2, int(half_widths.max()))
    out = np.zeros_like(mask)
    grown = np.zeros(out[box].shape, np.bool_)
    _grow_kernel(np.ascontiguousarray(mask[box]), half_widths, grown)
    out[box] = grown
    return out


def padded_box(mask: np.ndarray, reach_rows: int, reach_cols: int) -> tuple[slice, slice] | None:
    """The bounding box of `mask`'s True pixels widened by `reach_rows` rows and
    `reach_cols` columns on each side, clipped to the image; None when `mask` is empty."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if not len(rows):
        return None
    h, w = mask.shape
    return (
        slice(max(rows[0] - reach_rows, 0), min(rows[-1] + reach_rows + 1, h)),
        slice(max(cols[0] - reach_cols, 0), min(cols[-1] + reach_cols + 1, w)),
    )


def ellipse_half_widths(ru: float, rv: float) -> np.ndarray:
    """(2 * R + 1,) int64: for each row offset dv in -R..R (R = floor(rv)), the largest
    column offset du with (du / ru)^2 + (dv / rv)^2 <= 1."""
    reach = math.floor(rv)
    dv = np.arange(-reach, reach + 1, dtype=np.float64)
    return np.floor(ru * np.sqrt(np.maximum(1.0 - (dv / rv) ** 2, 0.0)) + 1e-9).astype(np.int64)


@numba.njit(cache=True)
def _grow_kernel(mask, half_widths, out):
    """out[v, u] = whether a mask pixel lies in row v + dv within half_widths[dv] columns of
    u, for some dv: row prefix counts answer each (pixel, dv) in constant time."""
    h, w = mask.shape
    reach = (half_widths.shape[0] - 1) // 2
    prefix = np.zeros((h, w + 1), np.int32)
    rows_with = np.zeros(h, np.bool_)
    for v in range(h):
        for u in range(w):
            prefix[v, u + 1] = prefix[v, u] + (1 if mask[v, u] else 0)
        rows_with[v] = prefix[v, w] > 0
    for v in range(h):
        for k in range(-reach, reach + 1):
            src = v + k
            if src < 0 or src >= h or not rows_with[src]:
                continue
            hw = half_widths[k + reach]
            for u in range(w):
                if out[v, u]:
                    continue
                lo = max(u - hw, 0)
                hi = min(u + hw + 1, w)
                if prefix[src, hi] > prefix[src, lo]:
                    out[v, u] = True
