"""Zones in the image: which pixels of a camera look through each zone's prism, which zones
hold a person, and how much of each protective zone the camera cannot see.

A zone is a floor polygon in the cell frame with a height range, a prism. `zone_masks`
marks, once per camera mount and placement, every pixel whose ray passes through the prism
anywhere between its bottom and top (the ray's stretch within the height range, projected
on the floor, meets the polygon). `occupied_zones` names the zones a person's point lies in.

Unseen rule: a protective zone's unseen fraction is the share of its pixels that have no
depth (0, or the 65535 some cameras send) and are not inside the robot's shadow mask (its
silhouette grown by its margin and the sensor's shadow band, which the robot itself
explains). Above the cell's `max_unseen_fraction` the zone counts as occupied; a zone a
camera does not see at all is wholly unseen by it (1.0). Over several cameras a place in the
zone is unseen when no camera that looks at it has depth there (`unseen_by_all`: the zone
sampled on a grid at its bottom, middle and top, each point looked up in every camera's
image): one camera's clear view of one part of a zone says nothing of another part only a
second camera looks at.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from topseg.core.camera import NO_READING_MM, TopViewMount, check_depth
from topseg.core.safety.cell import CameraPlacement, Zone
from topseg.core.safety.separation import image_pixels

#: how far along a pixel's ray (m) a zone can be seen: rays that never reach the floor (a
#: strongly tilted wide-angle camera's top rows) are followed this far
MAX_RAY_M = 50.0


@dataclass(frozen=True, eq=False)
class ZoneMasks:
    """Per zone, the pixels (of one camera) whose ray passes through the zone's prism:
    `masks[i]` is the (H, W) bool image of `zones[i]`."""

    zones: tuple[Zone, ...]
    masks: np.ndarray  # (n_zones, H, W) bool
    shape: tuple[int, int]

    def mask(self, name: str) -> np.ndarray:
        """The (H, W) mask of the zone called `name`; KeyError naming the known zones."""
        for zone, mask in zip(self.zones, self.masks, strict=True):
            if zone.name == name:
                return mask
        known = ", ".join(z.name for z in self.zones) or "none"
        raise KeyError(f"no zone {name!r}; known: {known}")

    def pixel_counts(self) -> dict[str, int]:
        """How many pixels of this camera look through each zone."""
        return {z.name: int(m.sum()) for z, m in zip(self.zones, self.masks, strict=True)}


def pixel_rays_cell(mount: TopViewMount, placement: CameraPlacement) -> tuple:
    """(centre (3,), directions (H, W, 3)): the camera centre and each pixel's ray direction
    (not normalised; z along the optical axis is 1 in the camera frame), in the cell frame."""
    k = mount.intrinsics
    v, u = np.indices(k.shape, dtype=np.float64)
    rays_cam = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u)], axis=-1)
    rot = mount.rotation_world_to_camera()  # p_cam = R (p_world - c)
    rays_world = rays_cam @ rot  # R^T applied to each ray
    directions = rays_world @ placement.rotation().T
    centre = placement.to_cell(mount.centre_world_m()[None])[0]
    return centre, directions


def _slab_interval(
    cz: float, dz: np.ndarray, z_lo: float, z_hi: float
) -> tuple[np.ndarray, np.ndarray]:
    """(t0, t1) per ray: the stretch 0 <= t <= MAX_RAY_M of `c + t d` with z within
    [z_lo, z_hi]; empty where t0 > t1."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (z_lo - cz) / dz
        tb = (z_hi - cz) / dz
    t0 = np.minimum(ta, tb)
    t1 = np.maximum(ta, tb)
    level = dz == 0  # a horizontal ray: all of it or none
    inside = z_lo <= cz <= z_hi
    t0 = np.where(level, 0.0 if inside else np.inf, t0)
    t1 = np.where(level, MAX_RAY_M if inside else -np.inf, t1)
    return np.maximum(t0, 0.0), np.minimum(t1, MAX_RAY_M)


def points_in_polygon(xy: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """(n,) bool: which of the (n, 2) points lie inside the polygon (even-odd rule; points
    exactly on an edge may go either way)."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    x, y = xy[:, 0], xy[:, 1]
    inside = np.zeros(len(xy), bool)
    n = len(polygon)
    for i in range(n):
        (x1, y1), (x2, y2) = polygon[i], polygon[(i - 1) % n]
        crosses = (y1 > y) != (y2 > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            x_at = x1 + (y - y1) * (x2 - x1) / (y2 - y1)
        inside ^= crosses & (x < x_at)
    return inside


def _cross2(ax, ay, bx, by) -> np.ndarray:
    """The z of the 2D cross product (a x b), elementwise."""
    return ax * by - ay * bx


def segments_meet_polygon(p: np.ndarray, q: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """(n,) bool: which of the (n, 2) segments p-q touch the polygon (an end inside it, or
    the segment crossing or touching one of its edges)."""
    hit = points_in_polygon(p, polygon) | points_in_polygon(q, polygon)
    rx, ry = q[:, 0] - p[:, 0], q[:, 1] - p[:, 1]
    n = len(polygon)
    for i in range(n):
        a, b = polygon[i], polygon[(i + 1) % n]
        sx, sy = b[0] - a[0], b[1] - a[1]
        denom = _cross2(rx, ry, sx, sy)
        wx, wy = a[0] - p[:, 0], a[1] - p[:, 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = _cross2(wx, wy, sx, sy) / denom
            s = _cross2(wx, wy, rx, ry) / denom
        hit |= (denom != 0) & (t >= 0) & (t <= 1) & (s >= 0) & (s <= 1)
    return hit


def zone_mask(zone: Zone, centre: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels whose ray (from `centre` along `directions`, cell frame)
    passes through `zone`'s prism."""
    shape = directions.shape[:2]
    d = directions.reshape(-1, 3)
    t0, t1 = _slab_interval(float(centre[2]), d[:, 2], zone.z_min_m, zone.z_max_m)
    some = t0 <= t1
    polygon = np.asarray(zone.polygon_m, np.float64)
    p = centre[None, :2] + t0[some, None] * d[some, :2]
    q = centre[None, :2] + t1[some, None] * d[some, :2]
    mask = np.zeros(len(d), bool)
    mask[np.flatnonzero(some)] = segments_meet_polygon(p, q, polygon)
    return mask.reshape(shape)


def zone_masks(
    zones: tuple[Zone, ...], mount: TopViewMount, placement: CameraPlacement
) -> ZoneMasks:
    """Each zone's pixels in the camera of `mount` (its intrinsics and tilt) hanging at
    `placement`; compute once per mount and placement, not per frame."""
    centre, directions = pixel_rays_cell(mount, placement)
    shape = mount.intrinsics.shape
    masks = np.zeros((len(zones), *shape), bool)
    for i, zone in enumerate(zones):
        masks[i] = zone_mask(zone, centre, directions)
    return ZoneMasks(tuple(zones), masks, shape)


def points_in_zone(zone: Zone, points_cell: np.ndarray) -> np.ndarray:
    """(n,) bool: which (n, 3) cell-frame points lie in `zone`'s prism (inside the polygon,
    z within the height range); non-finite points never do."""
    p = np.asarray(points_cell, np.float64).reshape(-1, 3)
    finite = np.isfinite(p).all(axis=1)
    z_ok = finite & (p[:, 2] >= zone.z_min_m) & (p[:, 2] <= zone.z_max_m)
    out = np.zeros(len(p), bool)
    if z_ok.any():
        out[z_ok] = points_in_polygon(p[z_ok, :2], np.asarray(zone.polygon_m, np.float64))
    return out


def occupied_zones(
    masks: ZoneMasks,
    human_points_cell: np.ndarray,
    human_pixel_index: np.ndarray | None = None,
    min_points: int = 1,
) -> list[str]:
    """The names of the zones at least `min_points` of a person's (n, 3) cell-frame points lie
    in. With `human_pixel_index` ((n, 2) (row, col) of each point's pixel), a point that is
    not finite (a person's pixel with no usable depth) counts for every zone its pixel looks
    through: where along the ray the person is, is unknown, so the zone is taken as held."""
    points = np.asarray(human_points_cell, np.float64).reshape(-1, 3)
    lost = None
    if human_pixel_index is not None:
        index = np.asarray(human_pixel_index).reshape(-1, 2)
        if len(index) != len(points):
            raise ValueError(f"human_pixel_index has {len(index)} pixels for {len(points)} points")
        bad = ~np.isfinite(points).all(axis=1)
        lost = index[bad].astype(np.intp)
        inside_image = (
            (lost[:, 0] >= 0) & (lost[:, 0] < masks.shape[0])
            & (lost[:, 1] >= 0) & (lost[:, 1] < masks.shape[1])
        )  # fmt: skip
        lost = lost[inside_image]
    held = []
    for zone, mask in zip(masks.zones, masks.masks, strict=True):
        count = int(points_in_zone(zone, points).sum())
        if lost is not None and len(lost):
            count += int(mask[lost[:, 0], lost[:, 1]].sum())
        if count >= max(1, min_points):
            held.append(zone.name)
    return held


def unseen_fraction(
    masks: ZoneMasks, depth_mm: np.ndarray, robot_shadow_mask: np.ndarray | None
) -> dict[str, float]:
    """Per protective zone, the share of its pixels with no depth that `robot_shadow_mask`
    ((H, W) bool, the robot's grown silhouette and shadow; None: no robot) does not explain.
    1.0 for a zone this camera does not see at all. The module docstring states the rule."""
    depth = check_depth(depth_mm, "unseen_fraction")
    if depth.shape != masks.shape:
        raise ValueError(f"depth is {depth.shape} but the zone masks are {masks.shape}")
    if robot_shadow_mask is not None and np.shape(robot_shadow_mask) != masks.shape:
        raise ValueError(
            f"robot_shadow_mask is {np.shape(robot_shadow_mask)} but the zone masks are "
            f"{masks.shape}"
        )
    missing = missing_depth(depth, robot_shadow_mask)
    out = {}
    for zone, mask in zip(masks.zones, masks.masks, strict=True):
        if zone.kind != "protective":
            continue
        pixels = int(mask.sum())
        out[zone.name] = 1.0 if pixels == 0 else int((missing & mask).sum()) / pixels
    return out


#: the grid (m) a protective zone is sampled on for `unseen_by_all`, at least; a zone wider
#: than MAX_SAMPLE_STEPS spacings is sampled at MAX_SAMPLE_STEPS points across
SAMPLE_SPACING_M = 0.05
MAX_SAMPLE_STEPS = 120
#: the highest a zone is sampled (m): above a person's head nothing is asked of it
MAX_SAMPLE_HEIGHT_M = 2.0


def zone_samples(zone: Zone) -> np.ndarray:
    """(n, 3) cell-frame points of `zone`'s prism: a square grid over its polygon at its
    bottom, its middle and its top (no higher than MAX_SAMPLE_HEIGHT_M)."""
    polygon = np.asarray(zone.polygon_m, np.float64)
    lo, hi = polygon.min(axis=0), polygon.max(axis=0)
    step = max(SAMPLE_SPACING_M, float((hi - lo).max()) / MAX_SAMPLE_STEPS)
    xs = np.arange(lo[0] + step / 2, hi[0], step)
    ys = np.arange(lo[1] + step / 2, hi[1], step)
    xx, yy = np.meshgrid(xs, ys)
    xy = np.stack([xx.ravel(), yy.ravel()], axis=1)
    xy = xy[points_in_polygon(xy, polygon)]
    top = min(zone.z_max_m, MAX_SAMPLE_HEIGHT_M)
    heights = sorted({zone.z_min_m, (zone.z_min_m + top) / 2, top})
    return np.concatenate([np.column_stack([xy, np.full(len(xy), h)]) for h in heights])


def unseen_by_all(samples: np.ndarray, cameras: list[tuple]) -> float:
    """The share of a zone's `samples` (`zone_samples`) that some camera looks at and none
    has depth at: `cameras` holds each camera's (mount, placement, missing), `missing` its
    (H, W) bool pixels with no depth that the robot's shadow does not explain. 1.0 when no
    camera looks at any of them."""
    looked = np.zeros(len(samples), bool)
    known = np.zeros(len(samples), bool)
    for mount, placement, missing in cameras:
        inside, rows, cols, _ = image_pixels(samples, mount, placement)
        looked |= inside
        known[inside] |= ~missing[rows, cols]
    if not looked.any():
        return 1.0
    return float((looked & ~known).sum() / looked.sum())


def missing_depth(depth_mm: np.ndarray, robot_shadow_mask: np.ndarray | None) -> np.ndarray:
    """(H, W) bool: the pixels with no depth (0, or NO_READING_MM) that `robot_shadow_mask`
    (None: no robot) does not explain."""
    missing = (depth_mm == 0) | (depth_mm == NO_READING_MM)
    if robot_shadow_mask is not None:
        missing &= ~np.asarray(robot_shadow_mask, bool)
    return missing
