"""The exact separation of a person's body from a robot's body: the truth a rendered cell
sequence records beside its frames.

The robot is a triangle soup (its links' meshes, and its links' boxes, cylinders and spheres
tessellated finely: a cylinder's or sphere's facets stay within 0.1 mm of the true surface at
the radii robots have); each triangle knows its link. The person is the humanoid's posed
primitives (spheres, capsules and boxes). The distance between the two bodies is
the smallest distance between a point of one surface and a point of the other, 0 when they
touch or overlap.

A point's distance to the soup is exact (trimesh's closest point on a triangle, among the
triangles a k-d tree of their centres leaves as candidates). A sphere's distance is its
centre's less its radius. A capsule's is the least over its axis less its radius: the axis
is sampled every COARSE_M, and around every sample that could hold the minimum (distance
being 1-Lipschitz along the axis, those within COARSE_M of the best) sampled again every
COARSE_M / 20, so the answer is at most COARSE_M / 40 (0.25 mm) above the true one. A box's
(or cylinder's) surface is sampled on a grid the same way, coarse then fine around the
best, within FINE_SURFACE_M / sqrt(2) (0.7 mm). Primitives whose bounding sphere cannot come
nearer than the best found so far are skipped, so a person far from the robot costs one
query of 15 points.

A box point inside a closed robot link would read its distance to that link's surface, not
0; people and robots that interpenetrate that deeply do not occur in rendered sequences.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from topseg.core.synth.geometry import BOX, CAPSULE, CYLINDER, SPHERE
from topseg.core.synth.render import Primitives, Triangles
from topseg.core.synth.robots import import_train_module

#: sample spacing (m) along a capsule's axis and on a box's face before refining
COARSE_M = 0.01
#: spacing (m) of the fine grid on a surface around its best coarse samples
FINE_SURFACE_M = 0.001
#: at most this many coarse samples are refined per primitive
MAX_REFINED = 12
#: facets of a tessellated cylinder; sphere subdivisions (icosphere)
CYLINDER_SECTIONS = 128
SPHERE_SUBDIVISIONS = 4


@dataclass(frozen=True)
class RobotSurface:
    """The robot's posed surface: triangles (m, 3, 3) in the world frame, each one's link
    index into `links`, and a k-d tree of the triangles' centres with their radii."""

    triangles: np.ndarray
    link: np.ndarray
    links: tuple[str, ...]
    centres: np.ndarray
    radius: np.ndarray
    tree: cKDTree


@dataclass(frozen=True)
class BodySeparation:
    """The nearest pair between a person's body and the robot's: distance (m, 0 when they
    touch), the person's primitive index and part label, the robot link, and the two points
    (world frame, m)."""

    distance_m: float
    primitive: int
    part: int
    link: str
    point_m: np.ndarray
    link_point_m: np.ndarray


def tessellated(prims: Primitives) -> np.ndarray:
    """(m, 3, 3) triangles of boxes, cylinders, spheres and capsules, in the world frame."""
    trimesh = import_train_module("trimesh", "the separation truth")
    out = [np.zeros((0, 3, 3))]
    for kind, size, centre, rot in zip(
        prims.kind, prims.size, prims.center, prims.rot, strict=True
    ):
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = rot, centre
        if kind == BOX:
            mesh = trimesh.creation.box(extents=2 * np.asarray(size[:3]), transform=pose)
        elif kind == CYLINDER:
            mesh = trimesh.creation.cylinder(
                radius=size[0], height=2 * size[1], sections=CYLINDER_SECTIONS, transform=pose
            )
        elif kind == SPHERE:
            mesh = trimesh.creation.icosphere(SPHERE_SUBDIVISIONS, radius=size[0])
            mesh.apply_transform(pose)
        else:
            mesh = trimesh.creation.capsule(height=2 * size[1], radius=size[0], count=[64, 64])
            mesh.apply_transform(pose)
        out.append(np.asarray(mesh.vertices, np.float64)[np.asarray(mesh.faces)])
    return np.concatenate(out)


def robot_surface(
    prims: Primitives,
    prim_link: np.ndarray,
    tris: Triangles,
    tri_link: np.ndarray,
    links: tuple[str, ...],
) -> RobotSurface:
    """The surface of a posed robot from its primitives and triangles (`link_geometry`'s)
    with each one's link index (`RobotModel.shape_links`)."""
    parts = [np.asarray(tris.vertices, np.float64).reshape(-1, 3, 3)]
    owner = [np.asarray(tri_link, np.int64)]
    for i in range(len(prims)):
        one = Primitives(
            prims.kind[i : i + 1], prims.size[i : i + 1], prims.center[i : i + 1],
            prims.rot[i : i + 1], prims.label[i : i + 1],
        )  # fmt: skip
        t = tessellated(one)
        parts.append(t)
        owner.append(np.full(len(t), int(prim_link[i]), np.int64))
    triangles = np.concatenate(parts)
    if not len(triangles):
        raise ValueError("a robot surface needs at least one triangle")
    centres = triangles.mean(axis=1)
    radius = np.linalg.norm(triangles - centres[:, None, :], axis=2).max(axis=1)
    return RobotSurface(
        triangles, np.concatenate(owner), tuple(links), centres, radius, cKDTree(centres)
    )


def _pairs_closest(surface: RobotSurface, points: np.ndarray, pi: np.ndarray, ti: np.ndarray):
    """Per point, the nearest of its candidate triangles (pairs pi, ti): distance (inf
    without candidates), closest point, triangle."""
    trimesh = import_train_module("trimesh", "the separation truth")
    n = len(points)
    best_d = np.full(n, np.inf)
    best_p = np.zeros((n, 3))
    best_t = np.zeros(n, np.int64)
    if len(pi) == 0:
        return best_d, best_p, best_t
    cp = trimesh.triangles.closest_point(surface.triangles[ti], points[pi])
    d = np.linalg.norm(cp - points[pi], axis=1)
    order = np.lexsort((d, pi))  # per point, nearest first
    first = order[np.r_[True, pi[order][1:] != pi[order][:-1]]]
    best_d[pi[first]] = d[first]
    best_p[pi[first]] = cp[first]
    best_t[pi[first]] = ti[first]
    return best_d, best_p, best_t


def _candidate_pairs(surface: RobotSurface, points: np.ndarray, bound: np.ndarray):
    """(point, triangle) pairs whose triangle may lie within `bound[point]` of the point."""
    near = np.flatnonzero(
        np.linalg.norm(surface.centres - points.mean(axis=0), axis=1) - surface.radius
        <= bound.max() + np.linalg.norm(points - points.mean(axis=0), axis=1).max()
    )
    gap = (
        np.linalg.norm(surface.centres[near][None] - points[:, None], axis=2)
        - surface.radius[near][None]
    )
    pi, k = np.nonzero(gap <= bound[:, None] + 1e-12)
    return pi, near[k]


def closest_points(
    surface: RobotSurface, points: np.ndarray, bound_m: float | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each point (n, 3): its distance to the surface, the closest surface point and the
    index of that point's triangle, exact (trimesh's point-triangle closest point).

    With `bound_m`, exact only for the points within `bound_m` of the surface; the others
    read farther than `bound_m` (what refining a sampled body needs, at a fraction of the
    cost)."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if len(points) == 0:
        return np.zeros(0), np.zeros((0, 3)), np.zeros(0, np.int64)
    # an upper bound per point: its nearest triangle centre's distance plus that one's radius
    near_d, near_i = surface.tree.query(points)
    bound = near_d + surface.radius[near_i]
    if bound_m is not None:
        bound = np.minimum(bound, bound_m)
    pi, ti = _candidate_pairs(surface, points, bound)
    return _pairs_closest(surface, points, pi, ti)


def _bounding_radius(kind: int, size: np.ndarray) -> float:
    if kind == SPHERE:
        return float(size[0])
    if kind == CAPSULE:
        return float(size[0] + size[1])
    if kind == CYLINDER:
        return float(np.hypot(size[0], size[1]))
    return float(np.linalg.norm(size[:3]))


def _candidates(d: np.ndarray, slack: float) -> np.ndarray:
    """Indices of the coarse samples that may hold the minimum (within `slack` of the best),
    the MAX_REFINED nearest."""
    cand = np.flatnonzero(d <= d.min() + slack)
    return cand[np.argsort(d[cand])][:MAX_REFINED]


def _axis_separation(surface, a: np.ndarray, b: np.ndarray, r: float, upper: float):
    """(distance, body point, surface point, triangle) of a capsule of axis a-b, radius r,
    whose axis comes within `upper` of the surface."""
    length = float(np.linalg.norm(b - a))
    n = max(2, int(np.ceil(length / COARSE_M)) + 1)
    t = np.linspace(0.0, 1.0, n)
    step = 1.0 / (n - 1)
    d, _, _ = closest_points(surface, a + t[:, None] * (b - a), upper + step * length)
    fine = [t]
    for i in _candidates(d, step * length):
        fine.append(np.clip(t[i] + np.linspace(-step / 2, step / 2, 21), 0.0, 1.0))
    t = np.concatenate(fine[1:])
    pts = a + t[:, None] * (b - a)
    d2, cp2, tri2 = closest_points(surface, pts, d.min() + step * length)
    k = int(np.argmin(d2))
    return _offset(pts[k], cp2[k], d2[k], r), int(tri2[k])


def _offset(centre: np.ndarray, target: np.ndarray, d: float, r: float):
    """A round body's nearest point: `r` from its axis point `centre` towards `target`."""
    direction = (target - centre) / d if d > 1e-12 else np.zeros(3)
    return max(0.0, d - r), centre + min(r, d) * direction, target


def _box_faces(size, centre, rot) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """A box's six faces as (corner, edge u, edge v): face point = corner + s u + t v."""
    h = np.asarray(size[:3], np.float64)
    faces = []
    for axis in range(3):
        j, k = [a for a in range(3) if a != axis]
        for sign in (-1.0, 1.0):
            o = np.zeros(3)
            o[axis], o[j], o[k] = sign * h[axis], -h[j], -h[k]
            u, v = np.zeros(3), np.zeros(3)
            u[j], v[k] = 2 * h[j], 2 * h[k]
            faces.append((centre + rot @ o, rot @ u, rot @ v))
    return faces


def _grid(lu: float, lv: float, spacing: float) -> tuple[np.ndarray, float, float]:
    """(k, 2) parameters in [0, 1]^2 of a grid about `spacing` apart on a lu x lv face, and
    the parameter steps."""
    nu = max(2, int(np.ceil(lu / spacing)) + 1)
    nv = max(2, int(np.ceil(lv / spacing)) + 1)
    s, t = np.meshgrid(np.linspace(0, 1, nu), np.linspace(0, 1, nv), indexing="ij")
    return np.column_stack([s.ravel(), t.ravel()]), 1.0 / (nu - 1), 1.0 / (nv - 1)


def _face_separation(surface, o, u, v, upper: float):
    """(distance, body point, surface point, triangle) of one flat face o + s u + t v (None
    when it stays beyond `upper`)."""
    lu, lv = float(np.linalg.norm(u)), float(np.linalg.norm(v))
    params, su, sv = _grid(lu, lv, COARSE_M)
    slack = float(np.hypot(su * lu, sv * lv))
    d, _, _ = closest_points(surface, o + params[:, :1] * u + params[:, 1:] * v, upper + slack)
    if not np.isfinite(d).any() or d.min() > upper:
        return None
    local, _, _ = _grid(su * lu, sv * lv, FINE_SURFACE_M)
    fine = [np.clip(params[i] + (local - 0.5) * (su, sv), 0.0, 1.0) for i in _candidates(d, slack)]
    params = np.concatenate(fine)
    pts = o + params[:, :1] * u + params[:, 1:] * v
    d, cp, tri = closest_points(surface, pts, d.min() + slack)
    k = int(np.argmin(d))
    return (float(d[k]), pts[k], cp[k]), int(tri[k])


def primitive_separation(surface: RobotSurface, kind: int, size, centre, rot, upper: float):
    """(distance, body point, surface point, triangle) of one human primitive: a sphere, a
    capsule or a box (what the humanoid is made of); `upper` is its centre's distance to the
    surface (its surface and axis come at least that near)."""
    size = np.asarray(size, np.float64)
    centre = np.asarray(centre, np.float64)
    rot = np.asarray(rot, np.float64)
    if kind == SPHERE:
        d, cp, tri = closest_points(surface, centre[None])
        return _offset(centre, cp[0], float(d[0]), float(size[0])), int(tri[0])
    if kind == CAPSULE:
        axis = rot[:, 2] * size[1]
        return _axis_separation(surface, centre - axis, centre + axis, float(size[0]), upper)
    if kind != BOX:
        raise ValueError(f"a body primitive is a sphere, capsule or box, not kind {kind}")
    best = None
    for o, u, v in _box_faces(size, centre, rot):
        found = _face_separation(surface, o, u, v, upper if best is None else best[0][0])
        if found is not None and (best is None or found[0][0] < best[0][0]):
            best = found
    return best


def body_separation(surface: RobotSurface, body) -> BodySeparation:
    """The nearest pair between a person's posed primitives (`humanoid.Primitives`) and the
    robot's surface. Primitives whose bounding sphere lies beyond the best pair found so
    far are not refined."""
    centres = np.asarray(body.center, np.float64)
    d_centre, _, _ = closest_points(surface, centres)
    bound = np.array(
        [_bounding_radius(int(k), s) for k, s in zip(body.kind, body.size, strict=True)]
    )
    best = None
    for i in np.argsort(d_centre - bound):
        if best is not None and d_centre[i] - bound[i] > best[0][0]:
            break
        found = primitive_separation(
            surface, int(body.kind[i]), body.size[i], centres[i], body.rot[i], float(d_centre[i])
        )
        if best is None or found[0][0] < best[0][0]:
            best = (found[0], found[1], int(i))
    (distance, point, link_point), tri, i = best
    return BodySeparation(
        float(distance), i, int(body.label[i]), surface.links[int(surface.link[tri])],
        np.asarray(point, np.float64), np.asarray(link_point, np.float64),
    )  # fmt: skip
