"""Depth and label images of a pybullet scene from the ceiling camera: the ray caster.

`raycast` (the one datagen and the procedural scenes use) is a numba ray caster over the
scene's primitives (spheres, capsules, boxes, cylinders) read from pybullet. Each pixel's ray
is intersected analytically with every primitive whose projected bounding box covers it, rows
in parallel; the nearest hit gives the depth (z along the optical axis, rounded to mm by
`camera.metres_to_mm`) and its primitive's label. Exact: a pixel's label is the surface its
centre ray meets first. Its references (a plain numpy caster and pybullet's TinyRenderer)
live in tests/reference.py.

`Primitives` are flat arrays in the world frame (z up, as pybullet has them). The camera is a
`camera.TopViewMount` of any height, tilt (pitch, roll) and intrinsics: primitives go into the
camera frame by the mount's `rotation_world_to_camera()` about its `centre_world_m()`, and a
pixel (u, v) looks along ((u - cx) / fx, (v - cy) / fy, 1) there; depth is z along the optical
axis. Straight down, camera x = world x, camera y = -world y, depth = height - world z.

`Triangles` (world-frame triangle soups: robot arms from their meshes) are cast in the same
pass by Moller-Trumbore, exact per pixel centre and two-sided. Each triangle's screen box bins
it into the rows it covers, front to back, so a row tests only the triangles over it: a
20 000-triangle arm costs milliseconds. A triangle wins a pixel only when strictly nearer than
the primitives' hit there (a tie goes to the primitive).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from topseg.core import labels
from topseg.core.camera import TopViewMount, metres_to_mm_scalar
from topseg.core.synth.geometry import half_extents

NEAR_M = 0.05


@dataclass
class Primitives:
    """n primitives in the world frame.

    kind (n,) int32: geometry.SPHERE/CAPSULE/BOX/CYLINDER; size (n, 3): box half extents,
    sphere (r, 0, 0), capsule and cylinder (r, half length, 0) along local z;
    center (n, 3); rot (n, 3, 3) world-from-local; label (n,) uint8.
    """

    kind: np.ndarray
    size: np.ndarray
    center: np.ndarray
    rot: np.ndarray
    label: np.ndarray

    def __len__(self) -> int:
        return len(self.kind)

    @staticmethod
    def empty() -> Primitives:
        """No primitives."""
        return Primitives(
            np.zeros(0, np.int32),
            np.zeros((0, 3)),
            np.zeros((0, 3)),
            np.zeros((0, 3, 3)),
            np.zeros(0, np.uint8),
        )

    @staticmethod
    def concat(parts: list[Primitives]) -> Primitives:
        """The primitives of `parts`, in order, as one set."""
        parts = [p for p in parts if len(p)]
        if not parts:
            return Primitives.empty()
        return Primitives(
            np.concatenate([p.kind for p in parts]).astype(np.int32),
            np.concatenate([p.size for p in parts]).astype(np.float64),
            np.concatenate([p.center for p in parts]).astype(np.float64),
            np.concatenate([p.rot for p in parts]).astype(np.float64),
            np.concatenate([p.label for p in parts]).astype(np.uint8),
        )


@dataclass
class Triangles:
    """n triangles in the world frame: vertices (n, 3, 3) float64, triangle i's three corners;
    label (n,) uint8."""

    vertices: np.ndarray
    label: np.ndarray

    def __len__(self) -> int:
        return len(self.label)

    @staticmethod
    def empty() -> Triangles:
        """No triangles."""
        return Triangles(np.zeros((0, 3, 3)), np.zeros(0, np.uint8))

    @staticmethod
    def concat(parts: list[Triangles]) -> Triangles:
        """The triangles of `parts`, in order, as one set."""
        parts = [t for t in parts if len(t)]
        if not parts:
            return Triangles.empty()
        return Triangles(
            np.concatenate([t.vertices for t in parts]).astype(np.float64).reshape(-1, 3, 3),
            np.concatenate([t.label for t in parts]).astype(np.uint8),
        )


def camera_pose(mount: TopViewMount) -> tuple[np.ndarray, np.ndarray]:
    """(R, c): p_cam = R @ (p_world - c), the mount's rotation and centre (metres, world)."""
    rot = np.asarray(mount.rotation_world_to_camera(), np.float64).reshape(3, 3)
    centre = np.asarray(mount.centre_world_m(), np.float64).reshape(3)
    return rot, centre


def to_camera(prims: Primitives, mount: TopViewMount) -> tuple[np.ndarray, np.ndarray]:
    """Centres and rotations of the primitives in the camera frame of `mount` (tilt included)."""
    r, c = camera_pose(mount)
    center = (np.asarray(prims.center, np.float64) - c) @ r.T
    rot = np.einsum("ij,njk->nik", r, prims.rot)
    return center, rot


def _half_extents(kind: np.ndarray, size: np.ndarray, rot: np.ndarray) -> np.ndarray:
    return half_extents(kind, size, rot)


def screen_boxes(center_c: np.ndarray, ext: np.ndarray, mount: TopViewMount) -> np.ndarray:
    """(n, 4) int32 pixel bounds (u0, u1, v0, v1), inclusive, of each primitive; empty = u0 > u1.

    The projection of a box's eight corners bounds the projection of anything inside it when
    the box lies in front of the camera. A box wholly behind the near plane is dropped; one
    that straddles it (the floor or a wall seen by a tilted camera: its camera-frame box grows
    with the tilt) may cover any pixel, so it gets the whole image.
    """
    k = mount.intrinsics
    n = len(center_c)
    out = np.empty((n, 4), np.int32)
    out[:] = (1, 0, 1, 0)
    if n == 0:
        return out
    lo = center_c - ext
    hi = center_c + ext
    finite = np.all(np.isfinite(lo), axis=1) & np.all(np.isfinite(hi), axis=1)
    ok = (lo[:, 2] > NEAR_M) & finite
    straddle = (lo[:, 2] <= NEAR_M) & (hi[:, 2] > NEAR_M) & finite
    sx = np.stack([lo[:, 0], hi[:, 0]], 1)
    sy = np.stack([lo[:, 1], hi[:, 1]], 1)
    sz = np.stack([lo[:, 2], hi[:, 2]], 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        us = (sx[:, :, None] / sz[:, None, :]) * k.fx + k.cx
        vs = (sy[:, :, None] / sz[:, None, :]) * k.fy + k.cy
    u0 = np.floor(us.reshape(n, -1).min(1))
    u1 = np.ceil(us.reshape(n, -1).max(1))
    v0 = np.floor(vs.reshape(n, -1).min(1))
    v1 = np.ceil(vs.reshape(n, -1).max(1))
    u0 = np.clip(u0, 0, k.width)  # past the right edge -> u0 > u1: empty
    u1 = np.clip(u1, -1, k.width - 1)
    v0 = np.clip(v0, 0, k.height)
    v1 = np.clip(v1, -1, k.height - 1)
    out[ok, 0] = u0[ok]
    out[ok, 1] = u1[ok]
    out[ok, 2] = v0[ok]
    out[ok, 3] = v1[ok]
    out[straddle] = (0, k.width - 1, 0, k.height - 1)
    return out


# --- the ray caster -------------------------------------------------------------------------


@numba.njit(cache=True, inline="always")
def _sphere_t(ox, oy, oz, dx, dy, dz, r):
    # ray p = o + t d (|d| = 1) against a sphere at the origin
    b = ox * dx + oy * dy + oz * dz
    c = ox * ox + oy * oy + oz * oz - r * r
    disc = b * b - c
    if disc < 0.0:
        return np.inf
    t = -b - np.sqrt(disc)
    return t if t > 0.0 else np.inf


@numba.njit(cache=True, inline="always")
def _slab(o, d, h, tn, tf):
    # one pair of parallel faces: narrow [tn, tf] to where the ray is between them
    if abs(d) < 1e-12:
        if o < -h or o > h:
            return 1.0, 0.0  # empty
        return tn, tf
    t1 = (-h - o) / d
    t2 = (h - o) / d
    if t1 > t2:
        t1, t2 = t2, t1
    return max(tn, t1), min(tf, t2)


@numba.njit(cache=True, inline="always")
def _box_t(ox, oy, oz, dx, dy, dz, hx, hy, hz):
    tn, tf = _slab(ox, dx, hx, -np.inf, np.inf)
    tn, tf = _slab(oy, dy, hy, tn, tf)
    tn, tf = _slab(oz, dz, hz, tn, tf)
    if tn > tf or tn <= 0.0:
        return np.inf
    return tn


@numba.njit(cache=True, inline="always")
def _side_t(ox, oy, oz, dx, dy, dz, r, h):
    # the open side of a cylinder along z, |z| <= h
    a = dx * dx + dy * dy
    if a < 1e-14:
        return np.inf
    b = ox * dx + oy * dy
    c = ox * ox + oy * oy - r * r
    disc = b * b - a * c
    if disc < 0.0:
        return np.inf
    t = (-b - np.sqrt(disc)) / a
    if t <= 0.0:
        return np.inf
    z = oz + t * dz
    if z < -h or z > h:
        return np.inf
    return t


@numba.njit(cache=True, inline="always")
def _cylinder_t(ox, oy, oz, dx, dy, dz, r, h):
    best = _side_t(ox, oy, oz, dx, dy, dz, r, h)
    if abs(dz) > 1e-12:
        for s in (-1.0, 1.0):
            t = (s * h - oz) / dz
            if 0.0 < t < best:
                x = ox + t * dx
                y = oy + t * dy
                if x * x + y * y <= r * r:
                    best = t
    return best


@numba.njit(cache=True, inline="always")
def _capsule_t(ox, oy, oz, dx, dy, dz, r, h):
    best = _side_t(ox, oy, oz, dx, dy, dz, r, h)
    t = _sphere_t(ox, oy, oz - h, dx, dy, dz, r)
    if t < best:
        best = t
    t = _sphere_t(ox, oy, oz + h, dx, dy, dz, r)
    if t < best:
        best = t
    return best


@numba.njit(cache=True, inline="always")
def _hit(kind, sx, sy, sz, ox, oy, oz, dx, dy, dz):
    """Distance along the unit ray (local frame) to a primitive, inf when it misses."""
    if kind == 0:
        return _sphere_t(ox, oy, oz, dx, dy, dz, sx)
    if kind == 1:
        return _capsule_t(ox, oy, oz, dx, dy, dz, sx, sy)
    if kind == 2:
        return _box_t(ox, oy, oz, dx, dy, dz, sx, sy, sz)
    return _cylinder_t(ox, oy, oz, dx, dy, dz, sx, sy)


@numba.njit(parallel=True, cache=True)
def _raycast_kernel(
    kind,
    size,
    origin_local,
    rot_c,
    lab,
    boxes,
    zmin,
    fx,
    fy,
    cx,
    cy,
    depth_m,
    depth_mm,
    out_lab,
    no_hit,
):
    """Rows in parallel; per row, each primitive whose screen box covers it, per pixel the hit.

    origin_local[i] = R_i^T (camera origin - centre_i); rot_c[i] = R_i (camera from local);
    zmin[i] the nearest depth primitive i can have: pixels already nearer skip it.
    Writes depth in metres (inf = no hit), in rounded millimetres (0 = none) and labels.
    """
    height, width = depth_m.shape
    n = kind.shape[0]
    for v in numba.prange(height):
        ry = (v - cy) / fy
        wx = np.empty(width)
        wz = np.empty(width)
        for u in range(width):
            depth_m[v, u] = np.inf
            out_lab[v, u] = no_hit
            rx = (u - cx) / fx
            inv = 1.0 / np.sqrt(rx * rx + ry * ry + 1.0)
            wx[u] = rx * inv
            wz[u] = inv
        for i in range(n):
            if v < boxes[i, 2] or v > boxes[i, 3] or boxes[i, 0] > boxes[i, 1]:
                continue
            r00, r01, r02 = rot_c[i, 0, 0], rot_c[i, 0, 1], rot_c[i, 0, 2]
            r10, r11, r12 = rot_c[i, 1, 0], rot_c[i, 1, 1], rot_c[i, 1, 2]
            r20, r21, r22 = rot_c[i, 2, 0], rot_c[i, 2, 1], rot_c[i, 2, 2]
            ox, oy, oz = origin_local[i, 0], origin_local[i, 1], origin_local[i, 2]
            k = kind[i]
            sx, sy, sz = size[i, 0], size[i, 1], size[i, 2]
            near = zmin[i]
            for u in range(boxes[i, 0], boxes[i, 1] + 1):
                if depth_m[v, u] <= near:
                    continue  # something nearer already covers this pixel
                inv = wz[u]
                wy = ry * inv
                # direction in the primitive's frame: R^T w
                dx = r00 * wx[u] + r10 * wy + r20 * inv
                dy = r01 * wx[u] + r11 * wy + r21 * inv
                dz = r02 * wx[u] + r12 * wy + r22 * inv
                t = _hit(k, sx, sy, sz, ox, oy, oz, dx, dy, dz)
                if t < np.inf:
                    z = t * inv  # distance along the ray -> depth along the optical axis
                    if z < depth_m[v, u]:
                        depth_m[v, u] = z
                        out_lab[v, u] = lab[i]
        for u in range(width):  # millimetres, 0 (and no label) where nothing is in range
            mm = metres_to_mm_scalar(depth_m[v, u])
            depth_mm[v, u] = mm
            if mm == 0:
                out_lab[v, u] = no_hit


# --- triangles ------------------------------------------------------------------------------


@numba.njit(cache=True, inline="always")
def _finite9(t):
    """Whether a triangle's nine coordinates are all finite."""
    for j in range(3):
        for r in range(3):
            if not np.isfinite(t[j, r]):
                return False
    return True


@numba.njit(cache=True)
def _prepare_triangles(vertices, rot, centre, fx, fy, cx, cy, width, height, near):
    """Camera-frame triangles sorted front to back (stable), with what the kernel needs.

    Returns (order, zmin, coef, proj, boxes): `order` the sort, and per sorted triangle its
    nearest depth, Moller-Trumbore's per-triangle vectors (see `_triangle_kernel`), its
    corners projected to pixels (u, v) and its screen box (u0, u1, v0, v1) inclusive. The
    projection of a triangle in front of the near plane is the triangle of its projected
    corners, so the box holds every pixel centre it covers; one wholly behind the near plane
    gets an empty box (u0 > u1); one that straddles it, the whole image (and proj NaN).
    """
    n = vertices.shape[0]
    cam = np.empty((n, 3, 3))
    zmin = np.empty(n)
    for i in range(n):
        for j in range(3):
            px = vertices[i, j, 0] - centre[0]
            py = vertices[i, j, 1] - centre[1]
            pz = vertices[i, j, 2] - centre[2]
            for r in range(3):
                cam[i, j, r] = rot[r, 0] * px + rot[r, 1] * py + rot[r, 2] * pz
        zmin[i] = min(cam[i, 0, 2], cam[i, 1, 2], cam[i, 2, 2])
    order = np.argsort(zmin, kind="mergesort")
    coef = np.empty((n, 10))
    proj = np.full((n, 3, 2), np.nan)
    boxes = np.empty((n, 4), np.int32)
    zs = np.empty(n)
    for k in range(n):
        t = cam[order[k]]
        zs[k] = zmin[order[k]]
        # e1 = t1 - t0, e2 = t2 - t0, s = -t0 (the camera centre is the origin)
        e1x, e1y, e1z = t[1, 0] - t[0, 0], t[1, 1] - t[0, 1], t[1, 2] - t[0, 2]
        e2x, e2y, e2z = t[2, 0] - t[0, 0], t[2, 1] - t[0, 1], t[2, 2] - t[0, 2]
        sx, sy, sz = -t[0, 0], -t[0, 1], -t[0, 2]
        coef[k, 0] = e1y * e2z - e1z * e2y  # n = e1 x e2
        coef[k, 1] = e1z * e2x - e1x * e2z
        coef[k, 2] = e1x * e2y - e1y * e2x
        coef[k, 3] = e2y * sz - e2z * sy  # a = e2 x s
        coef[k, 4] = e2z * sx - e2x * sz
        coef[k, 5] = e2x * sy - e2y * sx
        qx, qy, qz = sy * e1z - sz * e1y, sz * e1x - sx * e1z, sx * e1y - sy * e1x  # q = s x e1
        coef[k, 6], coef[k, 7], coef[k, 8] = qx, qy, qz
        coef[k, 9] = e2x * qx + e2y * qy + e2z * qz
        zmax = max(t[0, 2], t[1, 2], t[2, 2])
        boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3] = 1, 0, 1, 0
        if not _finite9(t) or zmax <= near:
            continue  # wholly behind the near plane (or not a number): no pixel
        if zs[k] <= near:
            boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3] = 0, width - 1, 0, height - 1
            continue
        ulo, uhi, vlo, vhi = np.inf, -np.inf, np.inf, -np.inf
        for j in range(3):
            u = t[j, 0] / t[j, 2] * fx + cx
            v = t[j, 1] / t[j, 2] * fy + cy
            proj[k, j, 0] = u
            proj[k, j, 1] = v
            ulo, uhi, vlo, vhi = min(ulo, u), max(uhi, u), min(vlo, v), max(vhi, v)
        boxes[k, 0] = int(min(max(np.floor(ulo), 0.0), width))  # past the right: u0 > u1
        boxes[k, 1] = int(min(max(np.ceil(uhi), -1.0), width - 1))
        boxes[k, 2] = int(min(max(np.floor(vlo), 0.0), height))
        boxes[k, 3] = int(min(max(np.ceil(vhi), -1.0), height - 1))
    return order, zs, coef, proj, boxes


@numba.njit(cache=True)
def _bin_rows(boxes, height):
    """Per image row, the triangles whose screen box covers it, in their given order:
    row v's are index[start[v]:start[v + 1]]."""
    count = np.zeros(height + 1, np.int64)
    for i in range(boxes.shape[0]):
        if boxes[i, 0] > boxes[i, 1]:
            continue
        for v in range(boxes[i, 2], boxes[i, 3] + 1):
            count[v + 1] += 1
    start = np.cumsum(count)
    index = np.empty(start[height], np.int64)
    fill = start[:height].copy()
    for i in range(boxes.shape[0]):
        if boxes[i, 0] > boxes[i, 1]:
            continue
        for v in range(boxes[i, 2], boxes[i, 3] + 1):
            index[fill[v]] = i
            fill[v] += 1
    return start, index


@numba.njit(cache=True, inline="always")
def _row_span(proj, i, v, u0, u1):
    """The pixels (lo, hi) of row v that triangle i's projection may cover, within [u0, u1]
    and a pixel wider each side than the projection's chord along the row (rounding never
    loses a pixel: Moller-Trumbore decides each one); lo > hi when it misses the row."""
    lo, hi = np.inf, -np.inf
    for a in range(3):
        b = (a + 1) % 3
        ua, va, ub, vb = proj[i, a, 0], proj[i, a, 1], proj[i, b, 0], proj[i, b, 1]
        if v < min(va, vb) - 1e-6 or v > max(va, vb) + 1e-6:
            continue
        if abs(vb - va) < 1e-12:
            lo, hi = min(lo, ua, ub), max(hi, ua, ub)
            continue
        s = min(max((v - va) / (vb - va), 0.0), 1.0)
        x = ua + s * (ub - ua)
        lo, hi = min(lo, x), max(hi, x)
    if lo > hi:
        return 1, 0
    return max(u0, int(np.floor(lo)) - 1), min(u1, int(np.ceil(hi)) + 1)


@numba.njit(parallel=True, cache=True)
def _triangle_kernel(
    coef, proj, boxes, zmin, lab, start, index, fx, fy, cx, cy, depth_m, depth_mm, out_lab, no_hit
):
    """Rows in parallel; per row, each triangle binned to it over the pixels its projection
    crosses (the whole box row for one straddling the near plane), per pixel Moller-Trumbore.

    The ray of pixel (u, v) leaves the camera centre along d = ((u - cx) / fx, (v - cy) / fy, 1),
    so the distance t along d is the depth. With the origin fixed, Moller-Trumbore's
    determinant and barycentric numerators are dot products of d with per-triangle vectors
    (`coef[i]`: n = e1 x e2, a = e2 x s, q = s x e1 with s = -v0, e1 = v1 - v0, e2 = v2 - v0,
    and t * det = e2 . q in coef[i, 9]). A hit nearer than the pixel's depth replaces it;
    each touched row's millimetres and no-hit labels are written again.
    """
    height, width = depth_m.shape
    for v in numba.prange(height):
        lo, hi = start[v], start[v + 1]
        if lo == hi:
            continue
        dy = (v - cy) / fy
        for j in range(lo, hi):
            i = index[j]
            if np.isnan(proj[i, 0, 0]):
                u0, u1 = boxes[i, 0], boxes[i, 1]
            else:
                u0, u1 = _row_span(proj, i, float(v), boxes[i, 0], boxes[i, 1])
            near = zmin[i]
            nx, ny, nz = coef[i, 0], coef[i, 1], coef[i, 2]
            ax, ay, az = coef[i, 3], coef[i, 4], coef[i, 5]
            qx, qy, qz = coef[i, 6], coef[i, 7], coef[i, 8]
            tdet = coef[i, 9]
            for u in range(u0, u1 + 1):
                if depth_m[v, u] <= near:
                    continue  # something nearer already covers this pixel
                dx = (u - cx) / fx
                det = -(dx * nx + dy * ny + nz)
                if det == 0.0:
                    continue  # the ray runs along the triangle's plane
                inv = 1.0 / det
                bu = (dx * ax + dy * ay + az) * inv
                if bu < 0.0 or bu > 1.0:
                    continue
                bv = (dx * qx + dy * qy + qz) * inv
                if bv < 0.0 or bu + bv > 1.0:
                    continue
                t = tdet * inv
                if 0.0 < t < depth_m[v, u]:
                    depth_m[v, u] = t
                    out_lab[v, u] = lab[i]
        for u in range(width):
            mm = metres_to_mm_scalar(depth_m[v, u])
            depth_mm[v, u] = mm
            if mm == 0:
                out_lab[v, u] = no_hit


def _cast_triangles(tris: Triangles, mount: TopViewMount, depth, depth_mm, lab) -> None:
    """Add the triangles to images the primitives were cast into (in place)."""
    k = mount.intrinsics
    r, c = camera_pose(mount)
    vertices = np.ascontiguousarray(tris.vertices, np.float64).reshape(-1, 3, 3)
    order, zmin, coef, proj, boxes = _prepare_triangles(
        vertices, r, c, k.fx, k.fy, k.cx, k.cy, k.width, k.height, NEAR_M
    )
    start, index = _bin_rows(boxes, k.height)
    _triangle_kernel(
        coef, proj, boxes, zmin, np.asarray(tris.label, np.uint8)[order], start, index,
        k.fx, k.fy, k.cx, k.cy, depth, depth_mm, lab, labels.NO_DEPTH,
    )  # fmt: skip


def front_to_back(prims: Primitives, mount: TopViewMount) -> Primitives:
    """The primitives sorted by their nearest possible depth (stable), so far ones get skipped
    where near ones already cover a pixel. Equal depths go to the earlier primitive."""
    center_c, rot_c = to_camera(prims, mount)
    zmin = center_c[:, 2] - _half_extents(prims.kind, prims.size, rot_c)[:, 2]
    order = np.argsort(zmin, kind="stable")
    return Primitives(
        prims.kind[order],
        prims.size[order],
        prims.center[order],
        prims.rot[order],
        prims.label[order],
    )


def _prepare(prims: Primitives, mount: TopViewMount):
    center_c, rot_c = to_camera(prims, mount)
    origin_local = np.einsum("nji,nj->ni", rot_c, -center_c)
    ext = _half_extents(prims.kind, prims.size, rot_c)
    boxes = screen_boxes(center_c, ext, mount)
    zmin = np.ascontiguousarray(center_c[:, 2] - ext[:, 2])
    return origin_local, np.ascontiguousarray(rot_c), boxes, zmin


def _run(prims: Primitives, mount: TopViewMount, triangles: Triangles | None = None):
    k = mount.intrinsics
    depth = np.empty(k.shape, np.float64)
    depth_mm = np.empty(k.shape, np.uint16)
    lab = np.empty(k.shape, np.uint8)
    prims = front_to_back(prims, mount)
    origin_local, rot_c, boxes, zmin = _prepare(prims, mount)
    _raycast_kernel(
        prims.kind.astype(np.int32), np.ascontiguousarray(prims.size, np.float64), origin_local, rot_c,
        prims.label.astype(np.uint8), boxes, zmin, k.fx, k.fy, k.cx, k.cy, depth, depth_mm, lab, labels.NO_DEPTH,
    )  # fmt: skip
    if triangles is not None and len(triangles):
        _cast_triangles(triangles, mount, depth, depth_mm, lab)
    return depth, depth_mm, lab


def raycast_m(
    prims: Primitives, mount: TopViewMount, triangles: Triangles | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Depth in metres (float64, inf where nothing is hit) and the label of each pixel's hit,
    among the primitives and the triangles."""
    depth, _, lab = _run(prims, mount, triangles)
    return depth, lab


def raycast(
    prims: Primitives, mount: TopViewMount, triangles: Triangles | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(depth uint16 mm, labels uint8) of the primitives and triangles seen by `mount`;
    0 / NO_DEPTH = no hit."""
    _, depth_mm, lab = _run(prims, mount, triangles)
    return depth_mm, lab
