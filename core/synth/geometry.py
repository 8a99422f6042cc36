"""Small geometry kit shared by the scene modules: primitive shapes, rotations, footprints.

Quaternions are (x, y, z, w), pybullet's order, so values pass to pybullet unchanged.
Footprints are convex polygons on the floor, (N, 2) arrays in metres, counter-clockwise;
the density function measures how much two items overlap with them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Primitive kinds, the four shapes every scene is built from (the renderer's ids).
SPHERE = 0
CAPSULE = 1
BOX = 2
CYLINDER = 3
KIND_NAMES = ("sphere", "capsule", "box", "cylinder")

IDENTITY_QUAT = (0.0, 0.0, 0.0, 1.0)

#: the most parts one item (a pooled pybullet body) can have: pybullet keeps at most 16
#: shapes of a visual shape array and drops the rest without a word
MAX_PARTS = 16


@dataclass(frozen=True)
class Part:
    """One primitive in its owner's frame.

    `size`: box -> half extents (hx, hy, hz); sphere -> (r, 0, 0);
    capsule and cylinder -> (r, half_length, 0), axis along local z.
    """

    kind: int
    size: tuple[float, float, float]
    pos: tuple[float, float, float] = (0.0, 0.0, 0.0)
    quat: tuple[float, float, float, float] = IDENTITY_QUAT

    def top_z(self) -> float:
        """Highest point of the part in its owner's frame (owner upright)."""
        return float(self.pos[2] + half_height(self.kind, self.size, quat_to_matrix(self.quat)))


def half_height(kind: int, size, rot: np.ndarray) -> float:
    """Half of the vertical (z) extent of a primitive rotated by `rot`."""
    if kind == SPHERE:
        return float(size[0])
    if kind == BOX:
        return float(np.abs(rot[2, :]) @ np.asarray(size, np.float64))
    r, h = float(size[0]), float(size[1])
    az = abs(float(rot[2, 2]))
    if kind == CAPSULE:
        return r + h * az
    # cylinder: axis contributes h*|az|, the rim contributes r*sqrt(1-az^2)
    return h * az + r * float(np.sqrt(max(0.0, 1.0 - az * az)))


def aabb(kind: int, size, center: np.ndarray, rot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds (lo, hi) of a primitive placed at `center` with rotation `rot`."""
    c = np.asarray(center, np.float64)
    if kind == SPHERE:
        e = np.full(3, float(size[0]))
    elif kind == BOX:
        e = np.abs(rot) @ np.asarray(size, np.float64)
    else:
        r, h = float(size[0]), float(size[1])
        axis = rot[:, 2]
        if kind == CAPSULE:
            e = np.abs(axis) * h + r
        else:
            e = np.abs(axis) * h + r * np.sqrt(np.clip(1.0 - axis * axis, 0.0, 1.0))
    return c - e, c + e


def half_extents(kind: np.ndarray, size: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """(n, 3) half extents of the axis-aligned boxes around n primitives rotated by `rot`."""
    ext = np.empty((len(kind), 3))
    r = size[:, 0:1]
    h = size[:, 1:2]
    axis = rot[:, :, 2]
    box = kind == BOX
    ext[box] = np.einsum("nij,nj->ni", np.abs(rot[box]), size[box])
    sph = kind == SPHERE
    ext[sph] = r[sph]
    cap = kind == CAPSULE
    ext[cap] = np.abs(axis[cap]) * h[cap] + r[cap]
    cyl = kind == CYLINDER
    ext[cyl] = np.abs(axis[cyl]) * h[cyl] + r[cyl] * np.sqrt(
        np.clip(1.0 - axis[cyl] ** 2, 0.0, 1.0)
    )
    return ext


# --- rotations ------------------------------------------------------------------------------


def quats_to_matrices(q: np.ndarray) -> np.ndarray:
    """(n, 4) quaternions (x, y, z, w), not necessarily unit -> (n, 3, 3) rotation matrices."""
    q = np.asarray(q, np.float64)
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    n = x * x + y * y + z * z + w * w
    s = np.where(n > 0, 2.0 / np.where(n > 0, n, 1.0), 0.0)
    m = np.empty((len(q), 3, 3))
    m[:, 0, 0] = 1 - s * (y * y + z * z)
    m[:, 0, 1] = s * (x * y - z * w)
    m[:, 0, 2] = s * (x * z + y * w)
    m[:, 1, 0] = s * (x * y + z * w)
    m[:, 1, 1] = 1 - s * (x * x + z * z)
    m[:, 1, 2] = s * (y * z - x * w)
    m[:, 2, 0] = s * (x * z - y * w)
    m[:, 2, 1] = s * (y * z + x * w)
    m[:, 2, 2] = 1 - s * (x * x + y * y)
    return m


def quat_mul(a, b) -> np.ndarray:
    """Hamilton product a*b of (x, y, z, w) quaternions (apply b first, then a)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ]
    )


def quat_conj(q) -> np.ndarray:
    """The conjugate of an (x, y, z, w) quaternion: the inverse rotation of a unit one."""
    return np.array([-q[0], -q[1], -q[2], q[3]], np.float64)


def quat_normalize(q) -> np.ndarray:
    """`q` scaled to unit length, so it is a pure rotation again after arithmetic."""
    q = np.asarray(q, np.float64)
    return q / np.linalg.norm(q)


def quat_from_axis_angle(axis, angle: float) -> np.ndarray:
    """Rotation by `angle` radians about `axis` (any length, not zero) as (x, y, z, w)."""
    axis = np.asarray(axis, np.float64)
    axis = axis / np.linalg.norm(axis)
    s = np.sin(angle / 2.0)
    return np.array([axis[0] * s, axis[1] * s, axis[2] * s, np.cos(angle / 2.0)])


def yaw_quat(yaw: float) -> np.ndarray:
    """Rotation by `yaw` radians about the vertical (z) axis."""
    return quat_from_axis_angle((0.0, 0.0, 1.0), yaw)


def quat_from_euler_xyz(rx: float, ry: float, rz: float) -> np.ndarray:
    """Rotate about x, then y, then z (fixed axes), like pybullet's getQuaternionFromEuler."""
    qx = quat_from_axis_angle((1.0, 0.0, 0.0), rx)
    qy = quat_from_axis_angle((0.0, 1.0, 0.0), ry)
    qz = quat_from_axis_angle((0.0, 0.0, 1.0), rz)
    return quat_mul(qz, quat_mul(qy, qx))


def quat_to_matrix(q) -> np.ndarray:
    """3x3 rotation matrix of an (x, y, z, w) quaternion; a non-unit one is normalised."""
    x, y, z, w = (float(v) for v in q)
    n = x * x + y * y + z * z + w * w
    s = 2.0 / n if n > 0 else 0.0
    return np.array(
        [
            [1 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w)],
            [s * (x * y + z * w), 1 - s * (x * x + z * z), s * (y * z - x * w)],
            [s * (x * z - y * w), s * (y * z + x * w), 1 - s * (x * x + y * y)],
        ]
    )


def matrix_to_quat(m: np.ndarray) -> np.ndarray:
    """Rotation matrix -> unit (x, y, z, w) quaternion with w >= 0."""
    m = np.asarray(m, np.float64)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = np.sqrt(tr + 1.0) * 2
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    q = quat_normalize(q)
    return -q if q[3] < 0 else q


def rotation_between(a, b) -> np.ndarray:
    """The smallest rotation (quaternion) that turns direction a into direction b."""
    a = np.asarray(a, np.float64) / np.linalg.norm(a)
    b = np.asarray(b, np.float64) / np.linalg.norm(b)
    c = float(a @ b)
    if c < -1.0 + 1e-9:  # opposite: any perpendicular axis
        perp = np.cross(a, (1.0, 0.0, 0.0))
        if np.linalg.norm(perp) < 1e-6:
            perp = np.cross(a, (0.0, 1.0, 0.0))
        return quat_from_axis_angle(perp, np.pi)
    v = np.cross(a, b)
    return quat_normalize([v[0], v[1], v[2], 1.0 + c])


def rot2(yaw: float) -> np.ndarray:
    """2x2 rotation matrix on the floor."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s], [s, c]])


# --- footprints -----------------------------------------------------------------------------


def rect_footprint(x: float, y: float, width: float, depth: float, yaw: float) -> np.ndarray:
    """Oriented rectangle: `width` along the item's local x, `depth` along its local y."""
    hw, hd = width / 2.0, depth / 2.0
    local = np.array([[-hw, -hd], [hw, -hd], [hw, hd], [-hw, hd]])
    return local @ rot2(yaw).T + np.array([x, y])


def disc_footprint(x: float, y: float, radius: float, n: int = 24) -> np.ndarray:
    """A circle of `radius` around (x, y) as an `n`-gon, CCW (round tables, pots)."""
    a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return np.stack([x + radius * np.cos(a), y + radius * np.sin(a)], axis=1)


def polygon_area(poly: np.ndarray) -> float:
    """Area (m^2) of a simple polygon by the shoelace formula; 0 for fewer than 3 points."""
    if len(poly) < 3:
        return 0.0
    x, y = poly[:, 0], poly[:, 1]
    return float(0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def clip_convex(subject: np.ndarray, clip: np.ndarray) -> np.ndarray:
    """Intersection of two convex polygons (Sutherland-Hodgman); clip must be CCW."""
    out = [tuple(p) for p in subject]
    n = len(clip)
    for i in range(n):
        if not out:
            break
        a, b = clip[i], clip[(i + 1) % n]
        ex, ey = b[0] - a[0], b[1] - a[1]

        def inside(p, a=a, ex=ex, ey=ey):
            return ex * (p[1] - a[1]) - ey * (p[0] - a[0]) >= -1e-12

        def cross_point(p, q, a=a, ex=ex, ey=ey):
            dpx, dpy = q[0] - p[0], q[1] - p[1]
            den = ex * dpy - ey * dpx
            t = (ey * (p[0] - a[0]) - ex * (p[1] - a[1])) / den if den != 0 else 0.0
            return (p[0] + t * dpx, p[1] + t * dpy)

        inp, out = out, []
        for j in range(len(inp)):
            cur, prev = inp[j], inp[j - 1]
            if inside(cur):
                if not inside(prev):
                    out.append(cross_point(prev, cur))
                out.append(cur)
            elif inside(prev):
                out.append(cross_point(prev, cur))
    return np.array(out, np.float64).reshape(-1, 2)


def overlap_fraction(a: np.ndarray, b: np.ndarray) -> float:
    """Area shared by two footprints, as a fraction of the smaller one (0 = apart, 1 = inside)."""
    lo = np.maximum(a.min(0), b.min(0))
    hi = np.minimum(a.max(0), b.max(0))
    if np.any(lo >= hi):
        return 0.0
    inter = polygon_area(clip_convex(a, b))
    smaller = min(polygon_area(a), polygon_area(b))
    return inter / smaller if smaller > 0 else 0.0


def inside_rect(poly: np.ndarray, lo: tuple[float, float], hi: tuple[float, float]) -> bool:
    """True when every vertex of `poly` lies within the axis-aligned rectangle [lo, hi]."""
    eps = 1e-9
    return bool(
        np.all(poly[:, 0] >= lo[0] - eps)
        and np.all(poly[:, 0] <= hi[0] + eps)
        and np.all(poly[:, 1] >= lo[1] - eps)
        and np.all(poly[:, 1] <= hi[1] + eps)
    )


def points_in_convex(points, poly: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """Which (..., 2) points lie inside the CCW convex polygon, at least `margin` from its edges."""
    p = np.asarray(points, np.float64)
    a = poly
    b = np.roll(poly, -1, axis=0)
    e = b - a
    length = np.hypot(e[:, 0], e[:, 1])
    # signed distance to each edge's line, positive inside
    d = (e[:, 0] * (p[..., None, 1] - a[:, 1]) - e[:, 1] * (p[..., None, 0] - a[:, 0])) / length
    return np.all(d >= margin - 1e-9, axis=-1)
