"""Depth and label images of a pybullet scene from the ceiling camera: two renderers.

- `raycast` (the one datagen uses): a numba ray caster over the scene's primitives (spheres,
  capsules, boxes, cylinders) read from pybullet. Each pixel's ray is intersected analytically
  with every primitive whose projected bounding box covers it, rows in parallel; the nearest
  hit gives the depth (z along the optical axis, rounded to mm) and its primitive's label.
  Exact: a pixel's label is the surface its centre ray meets first.
- `render_tiny`: pybullet's own TinyRenderer (`getCameraImage`), kept as the reference the ray
  caster is tested against. It rasterises tessellated shapes, so curved silhouettes differ by
  a pixel or so, and it is ~80 ms per frame here.

`Primitives` are flat arrays in the world frame (z up, as pybullet has them). The camera is
`camera.TopViewMount`: camera x = world x, camera y = -world y, depth = height - world z.
A pixel (u, v) looks along ((u - cx) / fx, (v - cy) / fy, 1) in the camera frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from topseg.core import labels
from topseg.core.camera import TOP_VIEW, TopViewMount
from topseg.core.synth.geometry import BOX, CAPSULE, SPHERE, half_extents

#: world -> camera rotation of the top-view mount (x stays, y and z flip)
_FLIP = np.diag([1.0, -1.0, -1.0])
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
        return Primitives(
            np.zeros(0, np.int32),
            np.zeros((0, 3)),
            np.zeros((0, 3)),
            np.zeros((0, 3, 3)),
            np.zeros(0, np.uint8),
        )

    @staticmethod
    def concat(parts: list[Primitives]) -> Primitives:
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


def to_camera(prims: Primitives, mount: TopViewMount) -> tuple[np.ndarray, np.ndarray]:
    """Centres and rotations of the primitives in the camera frame."""
    h = mount.height_mm / 1000.0
    center = prims.center @ _FLIP.T + np.array([0.0, 0.0, h])
    rot = np.einsum("ij,njk->nik", _FLIP, prims.rot)
    return center, rot


def _half_extents(kind: np.ndarray, size: np.ndarray, rot: np.ndarray) -> np.ndarray:
    return half_extents(kind, size, rot)


def screen_boxes(center_c: np.ndarray, ext: np.ndarray, mount: TopViewMount) -> np.ndarray:
    """(n, 4) int32 pixel bounds (u0, u1, v0, v1), inclusive, of each primitive; empty = u0 > u1.

    The projection of a box's eight corners bounds the projection of anything inside it when
    the box lies in front of the camera; boxes reaching behind the near plane are dropped.
    """
    k = mount.intrinsics
    n = len(center_c)
    out = np.empty((n, 4), np.int32)
    out[:] = (1, 0, 1, 0)
    if n == 0:
        return out
    lo = center_c - ext
    hi = center_c + ext
    ok = (lo[:, 2] > NEAR_M) & np.all(np.isfinite(lo), axis=1) & np.all(np.isfinite(hi), axis=1)
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
            mm = np.floor(depth_m[v, u] * 1000.0 + 0.5)
            if mm > 0.0 and mm <= 65535.0:
                depth_mm[v, u] = np.uint16(mm)
            else:
                depth_mm[v, u] = 0
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


def depth_to_mm(depth_m: np.ndarray) -> np.ndarray:
    """Metres (inf = no hit) -> uint16 millimetres rounded half up, 0 where nothing was hit or
    out of range (what the kernel does per pixel)."""
    mm = np.floor(depth_m * 1000.0 + 0.5)
    ok = np.isfinite(mm) & (mm > 0) & (mm <= 65535)
    out = np.zeros(depth_m.shape, np.uint16)
    out[ok] = mm[ok].astype(np.uint16)
    return out


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


def raycast_m(prims: Primitives, mount: TopViewMount = TOP_VIEW) -> tuple[np.ndarray, np.ndarray]:
    """Depth in metres (float64, inf where nothing is hit) and the label of each pixel's hit."""
    depth, _, lab = _run(prims, mount)
    return depth, lab


def raycast(prims: Primitives, mount: TopViewMount = TOP_VIEW) -> tuple[np.ndarray, np.ndarray]:
    """(depth uint16 mm, labels uint8) of the primitives seen by `mount`; 0 / NO_DEPTH = no hit."""
    _, depth_mm, lab = _run(prims, mount)
    return depth_mm, lab


# --- plain numpy reference of the ray caster (for tests) ------------------------------------


def _np_sphere(o, d, r):
    b = np.einsum("...i,...i->...", o, d)
    c = np.einsum("...i,...i->...", o, o) - r * r
    disc = b * b - c
    with np.errstate(invalid="ignore"):
        t = -b - np.sqrt(disc)
    return np.where((disc >= 0) & (t > 0), t, np.inf)


def _np_side(o, d, r, h):
    a = d[..., 0] ** 2 + d[..., 1] ** 2
    b = o[..., 0] * d[..., 0] + o[..., 1] * d[..., 1]
    c = o[..., 0] ** 2 + o[..., 1] ** 2 - r * r
    disc = b * b - a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-b - np.sqrt(disc)) / a
        z = o[..., 2] + t * d[..., 2]
    ok = (a >= 1e-14) & (disc >= 0) & (t > 0) & (np.abs(z) <= h)
    return np.where(ok, t, np.inf)


def _np_hit(kind, size, o, d):
    if kind == SPHERE:
        return _np_sphere(o, d, size[0])
    if kind == BOX:
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-size - o) / d
            t2 = (size - o) / d
        t1 = np.where(np.abs(d) < 1e-12, np.where(np.abs(o) <= size, -np.inf, np.inf), t1)
        t2 = np.where(np.abs(d) < 1e-12, np.where(np.abs(o) <= size, np.inf, -np.inf), t2)
        tn = np.minimum(t1, t2).max(-1)
        tf = np.maximum(t1, t2).min(-1)
        return np.where((tn <= tf) & (tn > 0), tn, np.inf)
    r, h = size[0], size[1]
    best = _np_side(o, d, r, h)
    if kind == CAPSULE:
        for s in (-1.0, 1.0):
            best = np.minimum(best, _np_sphere(o - np.array([0.0, 0.0, s * h]), d, r))
        return best
    for s in (-1.0, 1.0):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (s * h - o[..., 2]) / d[..., 2]
            x = o[..., 0] + t * d[..., 0]
            y = o[..., 1] + t * d[..., 1]
        ok = (np.abs(d[..., 2]) > 1e-12) & (t > 0) & (x * x + y * y <= r * r)
        best = np.minimum(best, np.where(ok, t, np.inf))
    return best


def raycast_reference(
    prims: Primitives, mount: TopViewMount = TOP_VIEW
) -> tuple[np.ndarray, np.ndarray]:
    """The ray caster in plain numpy, every primitive against every pixel (no culling)."""
    k = mount.intrinsics
    prims = front_to_back(prims, mount)  # the same order, so equal depths resolve the same way
    v, u = np.indices(k.shape, dtype=np.float64)
    ray = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u)], -1)
    norm = np.linalg.norm(ray, axis=-1)
    w = ray / norm[..., None]
    center_c, rot_c = to_camera(prims, mount)
    depth = np.full(k.shape, np.inf)
    lab = np.full(k.shape, labels.NO_DEPTH, np.uint8)
    for i in range(len(prims)):
        o = rot_c[i].T @ (-center_c[i])
        d = w @ rot_c[i]  # R^T w for each pixel
        z = _np_hit(int(prims.kind[i]), prims.size[i], o, d) / norm
        closer = z < depth
        depth[closer] = z[closer]
        lab[closer] = prims.label[i]
    return depth, lab


# --- pybullet's TinyRenderer (the reference) -------------------------------------------------


def camera_matrices(mount: TopViewMount = TOP_VIEW, near: float = 0.1, far: float = 10.0):
    """pybullet view and projection matrices equivalent to `mount` (square pixels, centred)."""
    import pybullet as p

    k = mount.intrinsics
    h = mount.height_mm / 1000.0
    if (
        abs(k.cx - (k.width - 1) / 2) > 1e-6
        or abs(k.cy - (k.height - 1) / 2) > 1e-6
        or k.fx != k.fy
    ):
        raise ValueError("pybullet's camera needs a centred principal point and square pixels")
    view = p.computeViewMatrix(
        cameraEyePosition=[0, 0, h], cameraTargetPosition=[0, 0, 0], cameraUpVector=[0, 1, 0]
    )
    fov_y = 2 * np.degrees(np.arctan2(k.height / 2, k.fy))
    proj = list(
        p.computeProjectionMatrixFOV(fov=fov_y, aspect=k.width / k.height, nearVal=near, farVal=far)
    )
    # TinyRenderer samples pixel corners; shift its image half a pixel so it samples pixel
    # centres at (u - cx) / fx like the ray caster and the Kinect model (found by rendering a
    # box with both: with this shift they agree on every pixel)
    proj[8] += 1.0 / k.width
    proj[9] += 1.0 / k.height
    return view, proj


def render_tiny(
    client: int, label_of, mount: TopViewMount = TOP_VIEW, near: float = 0.1, far: float = 10.0
):
    """(depth uint16 mm, labels uint8) from pybullet's TinyRenderer.

    `label_of(body_id, link_index)` maps pybullet's segmentation to a label id.
    """
    import pybullet as p

    k = mount.intrinsics
    view, proj = camera_matrices(mount, near, far)
    _, _, _, zbuf, seg = p.getCameraImage(
        k.width, k.height, view, proj, renderer=p.ER_TINY_RENDERER,
        flags=p.ER_SEGMENTATION_MASK_OBJECT_AND_LINKINDEX, physicsClientId=client,
    )  # fmt: skip
    zbuf = np.asarray(zbuf, np.float64).reshape(k.height, k.width)
    seg = np.asarray(seg, np.int64).reshape(k.height, k.width)
    z = far * near / (far - (far - near) * zbuf)
    z[seg < 0] = np.inf
    depth = depth_to_mm(z)
    lab = np.full(k.shape, labels.NO_DEPTH, np.uint8)
    hit = seg >= 0
    body = seg & ((1 << 24) - 1)
    link = (seg >> 24) - 1
    cache: dict[tuple[int, int], int] = {}
    for b, li in set(zip(body[hit].tolist(), link[hit].tolist(), strict=True)):
        cache[(b, li)] = label_of(b, li)
    lut_keys = body * 64 + (link + 1)
    for (b, li), lab_id in cache.items():
        lab[hit & (lut_keys == b * 64 + li + 1)] = lab_id
    lab[depth == 0] = labels.NO_DEPTH
    return depth, lab
