"""The separation of people from the robot: human pixels as cell-frame points, and the
nearest pair of a human point and the robot (its own shapes, or its bounding capsules).

`human_points` back-projects every pixel labelled as a human part (`labels.HUMAN_IDS`, and
`carry.UNIDENTIFIED`: something new the labels have not caught up with; `IS_HUMAN`) that has
depth, through the camera's mount (a `radial` camera's frame read as depth first) into the
camera's world frame and by the camera's placement into the cell frame; its blobs are
the 4-connected components of those pixels (one blob is roughly one person: two people who
touch in the image are one blob).

`nearest` measures each point's distance to the surface of the nearest capsule (0 inside
one, never negative) with a numba kernel, then the overall nearest pair and the nearest per
blob. The capsules bound the robot's links (`robot.CellRobot.capsules`), so that distance is
never more than the true one; given the robot's posed surface (`surface.RobotSurface`), the
capsule distances only bound the search and the nearest pairs are measured to the robot's
own shapes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from topseg.core import labels
from topseg.core.camera import backproject_pixels, project
from topseg.core.safety.carry import UNIDENTIFIED
from topseg.core.safety.surface import RobotSurface, refine, segment_distance
from topseg.core.union_find import find_root

#: label -> whether the safety path counts it as a person's: the body parts, and what
#: appeared since the labels were made
IS_HUMAN = np.zeros(256, bool)
IS_HUMAN[[*labels.HUMAN_IDS, UNIDENTIFIED]] = True


@dataclass(frozen=True, eq=False)
class Capsules:
    """Bounding capsules in the cell frame: capsule i is every point within `radius[i]` of
    the segment `a[i]`..`b[i]` (a == b: a sphere), bounding the link named `link[i]`."""

    a: np.ndarray
    b: np.ndarray
    radius: np.ndarray
    link: tuple[str, ...]

    def __len__(self) -> int:
        return len(self.radius)


@dataclass(frozen=True, eq=False)
class HumanPoints:
    """The human pixels of one camera's frame as cell-frame points.

    `points_m` (n, 3) float64 cell frame; `part` (n,) uint8 their label ids; `rows`, `cols`
    (n,) int32 their pixels (v, u); `blob` (n,) int32 the 4-connected component of human
    pixels each belongs to, 0 .. blob_count - 1 in raster order of their first pixel;
    `shape` the frame's (height, width).
    """

    points_m: np.ndarray
    part: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    blob: np.ndarray
    blob_count: int
    shape: tuple[int, int]

    def __len__(self) -> int:
        return len(self.part)

    @property
    def pixel_index(self) -> np.ndarray:
        """(n,) int64 flat pixel index of each point, `row * width + col`."""
        return self.rows.astype(np.int64) * self.shape[1] + self.cols


@dataclass(frozen=True)
class PersonSeparation:
    """One blob of human pixels: its nearest point's distance to the robot, that point's
    part (label id) and the robot link nearest to it, and how many pixels the blob has."""

    blob: int
    distance_m: float
    part: int
    link: str
    pixel_count: int


@dataclass(frozen=True, eq=False)
class Nearest:
    """The nearest pair of a human point and the robot (cell frame, metres): its distance
    (0 when the point is inside the robot's shape, or its capsule when measured to
    capsules), the point's part (label id), the link, the human point and the nearest
    point of that link (of its capsule when measured to capsules); and the same per blob."""

    distance_m: float
    part: int
    link: str
    point_m: np.ndarray
    link_point_m: np.ndarray
    per_person: tuple[PersonSeparation, ...]


def human_points(depth_mm: np.ndarray, label_img: np.ndarray, mount, placement) -> HumanPoints:
    """The human pixels with depth of a frame as cell-frame points with their parts, pixels
    and blobs. `mount` is the camera's `TopViewMount`, `placement` its `CameraPlacement` (any
    object with `to_cell(points_world)`); ValueError when the frames' shapes do not match
    the camera's."""
    k = mount.intrinsics
    depth_mm = np.asarray(depth_mm)
    label_img = np.asarray(label_img)
    if depth_mm.shape != k.shape or label_img.shape != k.shape:
        raise ValueError(
            f"depth {depth_mm.shape} and labels {label_img.shape} must both be the camera's "
            f"{k.shape} (height, width)"
        )
    depth_mm = mount.z_depth(depth_mm)
    human = IS_HUMAN[label_img] & (depth_mm > 0)
    blob_img, blob_count = label4(human)
    rows, cols = np.nonzero(human)
    return HumanPoints(
        points_m=cell_points(depth_mm, rows, cols, mount, placement),
        part=label_img[rows, cols].astype(np.uint8),
        rows=rows.astype(np.int32),
        cols=cols.astype(np.int32),
        blob=blob_img[rows, cols],
        blob_count=blob_count,
        shape=(int(k.height), int(k.width)),
    )


def cell_points(
    depth_mm: np.ndarray, rows: np.ndarray, cols: np.ndarray, mount, placement
) -> np.ndarray:
    """(n, 3) float64 cell-frame points (m) of the pixels (rows, cols) of an axis-depth frame
    seen through `mount` from `placement`."""
    camera = backproject_pixels(depth_mm, rows, cols, mount.intrinsics).astype(np.float64)
    world = mount.camera_to_world(camera)
    return np.asarray(placement.to_cell(world), np.float64).reshape(-1, 3)


def camera_pixels(
    points_cell: np.ndarray, mount, placement
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`cell_points`' inverse for (n, 3) cell-frame points (m): their (n, 2) pixel
    coordinates (u, v), (n,) depths along the optical axis (m) and (n,) whether they lie in
    front of the camera and inside its image."""
    world = placement.to_camera_world(np.asarray(points_cell, np.float64).reshape(-1, 3))
    cam = mount.world_to_camera(world)
    k = mount.intrinsics
    ahead = cam[:, 2] > 0
    uv = project(np.where(ahead[:, None], cam, 1.0), k)
    inside = (
        ahead & (uv[:, 0] >= 0) & (uv[:, 0] < k.width) & (uv[:, 1] >= 0) & (uv[:, 1] < k.height)
    )
    return uv, cam[:, 2], inside


def image_pixels(
    points_cell: np.ndarray, mount, placement
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where (n, 3) cell-frame points fall in the image (`camera_pixels`): (n,) whether each
    lies inside it, and for those that do their pixel's row and column and their depth
    along the optical axis (m)."""
    uv, z_m, inside = camera_pixels(points_cell, mount, placement)
    cols = np.floor(uv[inside, 0]).astype(np.int64)
    rows = np.floor(uv[inside, 1]).astype(np.int64)
    return inside, rows, cols, z_m[inside]


def blob_areas_m2(blob: np.ndarray, depth_mm: np.ndarray, intrinsics, count: int) -> np.ndarray:
    """(count,) how much of a floor-parallel plane at their depth each blob's pixels cover (m²):
    `blob` the blob id of each pixel, `depth_mm` its axis depth."""
    z = np.asarray(depth_mm, np.float64) / 1000.0
    return np.bincount(blob, weights=z * z / (intrinsics.fx * intrinsics.fy), minlength=count)


def label4(mask: np.ndarray) -> tuple[np.ndarray, int]:
    """(H, W) int32 4-connected component ids of `mask`'s pixels (-1 elsewhere), numbered
    0.. in raster order of each component's first pixel, and how many there are."""
    mask = np.ascontiguousarray(mask, dtype=np.bool_)
    out = np.empty(mask.shape, np.int32)
    count = _label4_kernel(mask, out)
    return out, int(count)


@numba.njit(cache=True)
def _label4_kernel(mask, out):
    """Union-find over the mask's 4-neighbours, then roots renumbered in raster order."""
    h, w = mask.shape
    parent = np.arange(h * w, dtype=np.int32)
    for v in range(h):
        for u in range(w):
            if not mask[v, u]:
                continue
            i = v * w + u
            if u > 0 and mask[v, u - 1]:
                _union(parent, i, i - 1)
            if v > 0 and mask[v - 1, u]:
                _union(parent, i, i - w)
    ids = np.full(h * w, -1, np.int32)
    count = 0
    for v in range(h):
        for u in range(w):
            out[v, u] = -1
            if not mask[v, u]:
                continue
            root = find_root(parent, v * w + u)
            if ids[root] < 0:
                ids[root] = count
                count += 1
            out[v, u] = ids[root]
    return count


@numba.njit(cache=True)
def _union(parent, a, b):
    """Join the trees of a and b, the smaller root under the larger's."""
    ra = find_root(parent, a)
    rb = find_root(parent, b)
    if ra < rb:
        parent[rb] = ra
    elif rb < ra:
        parent[ra] = rb


@numba.njit(cache=True)
def _nearest_kernel(points, a, b, radius, distance, capsule):
    """Per point: the distance to the nearest capsule's surface (0 inside) and its index."""
    n = points.shape[0]
    m = a.shape[0]
    for i in range(n):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        best = np.inf
        best_j = -1
        for j in range(m):
            d = segment_distance(px, py, pz, a[j], b[j]) - radius[j]
            if d < best:
                best = d
                best_j = j
        distance[i] = max(best, 0.0)
        capsule[i] = best_j


def point_distances(points_m: np.ndarray, capsules: Capsules) -> tuple[np.ndarray, np.ndarray]:
    """(n,) float64 distance of each point to the nearest capsule's surface (0 inside one)
    and (n,) int32 that capsule's index; the kernel behind `nearest`."""
    points = np.ascontiguousarray(points_m, np.float64).reshape(-1, 3)
    distance = np.empty(len(points), np.float64)
    capsule = np.empty(len(points), np.int32)
    _nearest_kernel(
        points,
        np.ascontiguousarray(capsules.a, np.float64).reshape(-1, 3),
        np.ascontiguousarray(capsules.b, np.float64).reshape(-1, 3),
        np.ascontiguousarray(capsules.radius, np.float64).reshape(-1),
        distance,
        capsule,
    )
    return distance, capsule


def nearest(
    points: HumanPoints, capsules: Capsules, surface: RobotSurface | None = None
) -> Nearest | None:
    """The nearest pair of a human point and the robot, overall and per blob; None when
    there is no human point or no capsule. With the robot's `surface` (posed as the
    capsules are) the distances are to the robot itself, the capsules' only bounding the
    search (`surface.refine`); without it, to the capsules."""
    if len(points) == 0 or len(capsules) == 0:
        return None
    distance, capsule = point_distances(points.points_m, capsules)
    if surface is None:
        links = np.asarray(capsules.link, dtype=object)[capsule]
        on_robot = None
    else:
        exact = refine(surface, points.points_m, points.blob, distance)
        distance = exact.distance_m
        links = np.asarray(surface.links, dtype=object)[np.maximum(exact.link, 0)]
        on_robot = exact.surface_point_m
    i = int(np.argmin(distance))
    point = points.points_m[i].copy()
    if on_robot is None:
        link_point = surface_point(point, capsules, int(capsule[i]))
    else:
        link_point = on_robot[i].copy()
    return Nearest(
        distance_m=float(distance[i]),
        part=int(points.part[i]),
        link=str(links[i]),
        point_m=point,
        link_point_m=link_point,
        per_person=_per_person(points, distance, links),
    )


def surface_point(point: np.ndarray, capsules: Capsules, j: int) -> np.ndarray:
    """The point of capsule j's surface nearest to `point` (the point itself inside it)."""
    a, b = np.asarray(capsules.a[j], np.float64), np.asarray(capsules.b[j], np.float64)
    axis = b - a
    length2 = float(axis @ axis)
    t = 0.0 if length2 == 0.0 else float(np.clip((point - a) @ axis / length2, 0.0, 1.0))
    centre = a + t * axis
    offset = point - centre
    dist = float(np.linalg.norm(offset))
    r = float(capsules.radius[j])
    if dist <= r:
        return point.copy()
    return centre + offset * (r / dist)


def _per_person(points: HumanPoints, distance, links) -> tuple[PersonSeparation, ...]:
    """The nearest point of every blob, in blob order."""
    order = np.lexsort((distance, points.blob))  # by blob, nearest first within it
    blobs = points.blob[order]
    first = np.flatnonzero(np.r_[True, blobs[1:] != blobs[:-1]])
    counts = np.diff(np.r_[first, len(order)])
    out = []
    for start, count in zip(first, counts, strict=True):
        i = order[start]
        out.append(
            PersonSeparation(
                blob=int(points.blob[i]),
                distance_m=float(distance[i]),
                part=int(points.part[i]),
                link=str(links[i]),
                pixel_count=int(count),
            )
        )
    return tuple(out)
