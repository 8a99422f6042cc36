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


def _run(prims: Primitives, mount: TopViewMount):
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
    return depth, depth_mm, lab


def raycast_m(prims: Primitives, mount: TopViewMount) -> tuple[np.ndarray, np.ndarray]:
    """Depth in metres (float64, inf where nothing is hit) and the label of each pixel's hit."""
    depth, _, lab = _run(prims, mount)
    return depth, lab


def raycast(prims: Primitives, mount: TopViewMount) -> tuple[np.ndarray, np.ndarray]:
    """(depth uint16 mm, labels uint8) of the primitives seen by `mount`; 0 / NO_DEPTH = no hit."""
    _, depth_mm, lab = _run(prims, mount)
    return depth_mm, lab
