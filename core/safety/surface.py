"""The robot's own surface, for separations measured to the robot itself rather than to the
capsules that bound it.

A `RobotSurface` (`posed_surface`, from the `SurfaceLayout` fixed once per robot) is the
posed robot's links as flat arrays: mesh triangles, and boxes, cylinders, spheres and
capsules as they are (the shapes `CellRobot` renders, without the pedestal), grouped by
link, each link with its bounding capsule. `refine` gives, for the
human points that can hold a blob's nearest pair, the exact distance to that surface, the
link and the surface point (a numba kernel: Ericson's closest point on a triangle, and the
primitives' closed forms).

The capsules make it cheap. A capsule contains its link, so a point's distance to the
capsules is a lower bound of its distance to the surface. Points are taken nearest capsule
first; a point whose bound is no nearer than its blob's best exact distance so far cannot
beat it and is skipped, and within a point, a link whose capsule is no nearer than the best
so far, and a triangle whose bounding sphere is not, are skipped. What is left is the band
of points between a capsule and its link's surface.

A point inside a closed mesh reads its distance to the mesh's surface, inside a primitive
0; a person's point is never inside the robot but where depth or labels are wrong, and
there the surface is within a pixel anyway.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from topseg.core.synth.geometry import BOX, CAPSULE, CYLINDER, SPHERE
from topseg.core.synth.render import Primitives, Triangles


@dataclass(frozen=True, eq=False)
class RobotSurface:
    """A posed robot's shapes by link (cell frame, metres).

    Link l owns triangles `tri_start[l]` .. `tri_start[l + 1]` of `triangles` (m, 3, 3)
    and primitives `prim_start[l]` .. `prim_start[l + 1]` of `kind` / `size` / `center` /
    `rot` (`render.Primitives`' conventions); `tri_radius` bounds each triangle about its
    centroid; `cap_a`, `cap_b`, `cap_radius` are each link's bounding capsule.
    """

    links: tuple[str, ...]
    triangles: np.ndarray
    tri_radius: np.ndarray
    tri_start: np.ndarray
    kind: np.ndarray
    size: np.ndarray
    center: np.ndarray
    rot: np.ndarray
    prim_start: np.ndarray
    cap_a: np.ndarray
    cap_b: np.ndarray
    cap_radius: np.ndarray


@dataclass(frozen=True, eq=False)
class SurfaceLayout:
    """What a robot's surface keeps from posing to posing: the links with shapes, the order
    that groups shapes by link, where each link's run starts, each triangle's bounding
    radius (posing moves a triangle rigidly) and each link's capsule index."""

    links: tuple[str, ...]
    tri_order: np.ndarray | None  # None: the triangles come grouped by link already
    tri_start: np.ndarray
    tri_radius: np.ndarray
    prim_order: np.ndarray
    prim_start: np.ndarray
    capsule: np.ndarray


def surface_layout(
    prims: Primitives,
    prim_link: np.ndarray,
    tris: Triangles,
    tri_link: np.ndarray,
    links: tuple[str, ...],
    capsule_links: tuple[str, ...],
) -> SurfaceLayout:
    """The layout of a robot's shapes (any posing of them) whose link indices into `links`
    are `prim_link` and `tri_link` (`RobotModel.shape_links`), with the capsules named by
    `capsule_links`; ValueError when a link with shapes has no capsule or a primitive is of
    a kind this module does not measure."""
    prim_link = np.asarray(prim_link, np.int64).reshape(-1)
    tri_link = np.asarray(tri_link, np.int64).reshape(-1)
    if len(prim_link) != len(prims) or len(tri_link) != len(tris.vertices):
        raise ValueError("every shape of a robot surface needs its link")
    if not np.isin(prims.kind, (BOX, CAPSULE, CYLINDER, SPHERE)).all():
        raise ValueError("a robot surface's primitives are boxes, capsules, cylinders, spheres")
    has = np.zeros(len(links), bool)
    has[prim_link] = True
    has[tri_link] = True
    keep = np.flatnonzero(has)
    capsule_of = {name: i for i, name in enumerate(capsule_links)}
    missing = [links[i] for i in keep if links[i] not in capsule_of]
    if missing:
        raise ValueError(f"link {missing[0]!r} has shapes and no bounding capsule")
    new_index = np.full(len(links), -1, np.int64)
    new_index[keep] = np.arange(len(keep))
    tri_order = np.argsort(new_index[tri_link], kind="stable")
    prim_order = np.argsort(new_index[prim_link], kind="stable")
    triangles = np.asarray(tris.vertices, np.float64)[tri_order]
    centre = triangles.mean(axis=1)
    radius = np.linalg.norm(triangles - centre[:, None, :], axis=2).max(axis=1, initial=0.0)
    bounds = np.arange(len(keep) + 1)
    in_order = np.array_equal(tri_order, np.arange(len(tri_order)))
    return SurfaceLayout(
        links=tuple(links[i] for i in keep),
        tri_order=None if in_order else tri_order,
        tri_start=np.searchsorted(np.sort(new_index[tri_link]), bounds).astype(np.int64),
        tri_radius=radius,
        prim_order=prim_order,
        prim_start=np.searchsorted(np.sort(new_index[prim_link]), bounds).astype(np.int64),
        capsule=np.array([capsule_of[links[i]] for i in keep], np.int64),
    )


def posed_surface(
    layout: SurfaceLayout, prims: Primitives, tris: Triangles, capsules
) -> RobotSurface:
    """The surface of the robot's shapes at one posing (`layout`'s shapes, in its order of
    `link_geometry`), with its capsules at the same posing (`separation.Capsules`)."""
    triangles = np.asarray(tris.vertices, np.float64)
    if layout.tri_order is not None:
        triangles = triangles[layout.tri_order]
    o, cap = layout.prim_order, layout.capsule
    return RobotSurface(
        links=layout.links,
        triangles=np.ascontiguousarray(triangles),
        tri_radius=layout.tri_radius,
        tri_start=layout.tri_start,
        kind=np.ascontiguousarray(np.asarray(prims.kind, np.int64)[o]),
        size=np.ascontiguousarray(np.asarray(prims.size, np.float64)[o]),
        center=np.ascontiguousarray(np.asarray(prims.center, np.float64)[o]),
        rot=np.ascontiguousarray(np.asarray(prims.rot, np.float64)[o]),
        prim_start=layout.prim_start,
        cap_a=np.ascontiguousarray(np.asarray(capsules.a, np.float64)[cap]).reshape(-1, 3),
        cap_b=np.ascontiguousarray(np.asarray(capsules.b, np.float64)[cap]).reshape(-1, 3),
        cap_radius=np.ascontiguousarray(np.asarray(capsules.radius, np.float64)[cap]),
    )


@dataclass(frozen=True, eq=False)
class Refined:
    """`refine`'s answer per point: `distance_m` (inf for a point that cannot be its blob's
    nearest), `link` (index into the surface's links, -1 with inf) and `surface_point_m`."""

    distance_m: np.ndarray
    link: np.ndarray
    surface_point_m: np.ndarray


def refine(
    surface: RobotSurface, points_m: np.ndarray, blob: np.ndarray, lower_m: np.ndarray
) -> Refined:
    """Exact distances to `surface` of the points (n, 3) that may be their blob's nearest.

    `blob` (n,) numbers each point's blob (0 .. k-1), `lower_m` (n,) is a lower bound of
    each point's distance (its distance to the capsules). Every blob's nearest point gets
    its exact distance; a point that cannot beat its blob's best reads inf."""
    points = np.ascontiguousarray(points_m, np.float64).reshape(-1, 3)
    n = len(points)
    blob = np.ascontiguousarray(blob, np.int64).reshape(-1)
    lower = np.ascontiguousarray(lower_m, np.float64).reshape(-1)
    if len(blob) != n or len(lower) != n:
        raise ValueError("refine needs one blob number and one lower bound per point")
    distance = np.full(n, np.inf)
    link = np.full(n, -1, np.int64)
    closest = np.zeros((n, 3))
    if n == 0:
        return Refined(distance, link, closest)
    best = np.full(int(blob.max()) + 1, np.inf)
    _refine_kernel(points, np.argsort(lower, kind="stable"), blob, lower, best,
                   surface.cap_a, surface.cap_b, surface.cap_radius,
                   surface.triangles, surface.tri_radius, surface.tri_start,
                   surface.kind, surface.size, surface.center, surface.rot, surface.prim_start,
                   distance, link, closest)  # fmt: skip
    return Refined(distance, link, closest)


@numba.njit(cache=True)
def _refine_kernel(points, order, blob, lower, best_of_blob, cap_a, cap_b, cap_r,
                   tris, tri_r, tri_start, kind, size, center, rot, prim_start,
                   distance, link, closest):  # fmt: skip
    """`refine`'s branch and bound (module doc); fills `distance`, `link` and `closest`."""
    q = np.empty(3)
    for k in range(points.shape[0]):
        i = order[k]
        b = blob[i]
        if lower[i] >= best_of_blob[b]:
            continue
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        best = best_of_blob[b]
        best_link = -1
        bx = by = bz = 0.0
        for li in range(cap_r.shape[0]):
            if segment_distance(px, py, pz, cap_a[li], cap_b[li]) - cap_r[li] >= best:
                continue
            for t in range(tri_start[li], tri_start[li + 1]):
                dx = px - (tris[t, 0, 0] + tris[t, 1, 0] + tris[t, 2, 0]) / 3.0
                dy = py - (tris[t, 0, 1] + tris[t, 1, 1] + tris[t, 2, 1]) / 3.0
                dz = pz - (tris[t, 0, 2] + tris[t, 1, 2] + tris[t, 2, 2]) / 3.0
                if np.sqrt(dx * dx + dy * dy + dz * dz) - tri_r[t] >= best:
                    continue
                d = triangle_closest(px, py, pz, tris[t], q)
                if d < best:
                    best, best_link = d, li
                    bx, by, bz = q[0], q[1], q[2]
            for j in range(prim_start[li], prim_start[li + 1]):
                d = primitive_closest(px, py, pz, kind[j], size[j], center[j], rot[j], q)
                if d < best:
                    best, best_link = d, li
                    bx, by, bz = q[0], q[1], q[2]
        if best_link >= 0:
            best_of_blob[b] = best
            distance[i] = best
            link[i] = best_link
            closest[i, 0], closest[i, 1], closest[i, 2] = bx, by, bz


@numba.njit(cache=True, inline="always")
def segment_distance(px, py, pz, a, b):
    """Distance from (px, py, pz) to the segment a..b (a point when a == b)."""
    ex, ey, ez = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    wx, wy, wz = px - a[0], py - a[1], pz - a[2]
    length2 = ex * ex + ey * ey + ez * ez
    t = 0.0
    if length2 > 0.0:
        t = min(max((wx * ex + wy * ey + wz * ez) / length2, 0.0), 1.0)
    dx, dy, dz = wx - t * ex, wy - t * ey, wz - t * ez
    return np.sqrt(dx * dx + dy * dy + dz * dz)


@numba.njit(cache=True)
def triangle_closest(px, py, pz, tri, out):
    """Distance from the point to triangle `tri` (3, 3), its closest point written to `out`
    (Ericson, Real-Time Collision Detection, 5.1.5); a triangle with no area is its edges."""
    ax, ay, az = tri[0, 0], tri[0, 1], tri[0, 2]
    abx, aby, abz = tri[1, 0] - ax, tri[1, 1] - ay, tri[1, 2] - az
    acx, acy, acz = tri[2, 0] - ax, tri[2, 1] - ay, tri[2, 2] - az
    nx, ny, nz = aby * acz - abz * acy, abz * acx - abx * acz, abx * acy - aby * acx
    ab2, ac2 = abx * abx + aby * aby + abz * abz, acx * acx + acy * acy + acz * acz
    if nx * nx + ny * ny + nz * nz <= 1e-24 * max(ab2 * ac2, 1e-300):
        return _degenerate_closest(px, py, pz, tri, out)
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    v = w = 0.0
    done = d1 <= 0.0 and d2 <= 0.0  # vertex a
    if not done:
        bpx, bpy, bpz = apx - abx, apy - aby, apz - abz
        d3 = abx * bpx + aby * bpy + abz * bpz
        d4 = acx * bpx + acy * bpy + acz * bpz
        cpx, cpy, cpz = apx - acx, apy - acy, apz - acz
        d5 = abx * cpx + aby * cpy + abz * cpz
        d6 = acx * cpx + acy * cpy + acz * cpz
        vc = d1 * d4 - d3 * d2
        vb = d5 * d2 - d1 * d6
        va = d3 * d6 - d5 * d4
        if d3 >= 0.0 and d4 <= d3:  # vertex b
            v = 1.0
        elif d6 >= 0.0 and d5 <= d6:  # vertex c
            w = 1.0
        elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:  # edge ab
            v = d1 / (d1 - d3) if d1 - d3 > 0.0 else 0.0
        elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:  # edge ac
            w = d2 / (d2 - d6) if d2 - d6 > 0.0 else 0.0
        elif va <= 0.0 and d4 - d3 >= 0.0 and d5 - d6 >= 0.0:  # edge bc
            den = (d4 - d3) + (d5 - d6)
            w = (d4 - d3) / den if den > 0.0 else 0.0
            v = 1.0 - w
        else:  # inside the face
            den = va + vb + vc
            if den > 0.0:
                v, w = vb / den, vc / den
    qx = ax + v * abx + w * acx
    qy = ay + v * aby + w * acy
    qz = az + v * abz + w * acz
    out[0], out[1], out[2] = qx, qy, qz
    dx, dy, dz = px - qx, py - qy, pz - qz
    return np.sqrt(dx * dx + dy * dy + dz * dz)


@numba.njit(cache=True)
def _degenerate_closest(px, py, pz, tri, out):
    """`triangle_closest` of a triangle with no area: the nearest of its three edges."""
    best = np.inf
    for e in range(3):
        a, b = tri[e], tri[(e + 1) % 3]
        ex, ey, ez = b[0] - a[0], b[1] - a[1], b[2] - a[2]
        length2 = ex * ex + ey * ey + ez * ez
        t = 0.0
        if length2 > 0.0:
            t = ((px - a[0]) * ex + (py - a[1]) * ey + (pz - a[2]) * ez) / length2
            t = min(max(t, 0.0), 1.0)
        qx, qy, qz = a[0] + t * ex, a[1] + t * ey, a[2] + t * ez
        d = np.sqrt((px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2)
        if d < best:
            best = d
            out[0], out[1], out[2] = qx, qy, qz
    return best


@numba.njit(cache=True)
def primitive_closest(px, py, pz, kind, size, center, rot, out):
    """Distance from the point to a primitive (0 inside it), its closest point of the
    primitive written to `out` (the point itself inside)."""
    wx, wy, wz = px - center[0], py - center[1], pz - center[2]
    # the point in the primitive's frame: rot is world-from-local
    lx = rot[0, 0] * wx + rot[1, 0] * wy + rot[2, 0] * wz
    ly = rot[0, 1] * wx + rot[1, 1] * wy + rot[2, 1] * wz
    lz = rot[0, 2] * wx + rot[1, 2] * wy + rot[2, 2] * wz
    qx, qy, qz = lx, ly, lz
    if kind == BOX:
        qx = min(max(lx, -size[0]), size[0])
        qy = min(max(ly, -size[1]), size[1])
        qz = min(max(lz, -size[2]), size[2])
    elif kind == CYLINDER:
        rr = np.sqrt(lx * lx + ly * ly)
        if rr > size[0]:
            qx, qy = lx * size[0] / rr, ly * size[0] / rr
        qz = min(max(lz, -size[1]), size[1])
    else:  # a sphere is a capsule of no length
        half = size[1] if kind == CAPSULE else 0.0
        cz = min(max(lz, -half), half)
        dx, dy, dz = lx, ly, lz - cz
        r = np.sqrt(dx * dx + dy * dy + dz * dz)
        if r > size[0]:
            qx, qy, qz = dx * size[0] / r, dy * size[0] / r, cz + dz * size[0] / r
    out[0] = center[0] + rot[0, 0] * qx + rot[0, 1] * qy + rot[0, 2] * qz
    out[1] = center[1] + rot[1, 0] * qx + rot[1, 1] * qy + rot[1, 2] * qz
    out[2] = center[2] + rot[2, 0] * qx + rot[2, 1] * qy + rot[2, 2] * qz
    dx, dy, dz = lx - qx, ly - qy, lz - qz
    return np.sqrt(dx * dx + dy * dy + dz * dz)


__all__ = [
    "Refined",
    "RobotSurface",
    "SurfaceLayout",
    "posed_surface",
    "primitive_closest",
    "refine",
    "segment_distance",
    "surface_layout",
    "triangle_closest",
]
