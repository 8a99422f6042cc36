"""Procedural top-view scenes: boxes, cylinders and spheres on the floor, rendered exactly.

Until the density-function scenes exist, tests, the demo and the benches need labelled
top-view frames with the right geometry: a floor 3.5 m below the camera and a few solids
standing on it. Each solid is an analytic primitive with a topseg label; every pixel's ray
from the pinhole camera is intersected with every primitive in closed form (vectorised
numpy, no rasterisation error), the nearest hit wins, and Gaussian noise is added in mm.

Shape kinds and their labels (`KINDS`): a large low box is a table, a long narrow box
taller than a person is storage (a shelf), a short cylinder is a plant, and a "person" is
a body cylinder with a head sphere resting on it. The kinds differ in size and height the way the real classes do, so a forest
can learn them from depth-difference features.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from topseg.core import labels
from topseg.core.camera import TOP_VIEW, TopViewMount


@dataclass(frozen=True)
class Box:
    """A box standing on the floor: centre (x, y) m, size (sx, sy) m, yaw rad, height m."""

    x: float
    y: float
    sx: float
    sy: float
    yaw: float
    height: float
    label: int


@dataclass(frozen=True)
class Cylinder:
    """A vertical cylinder: axis at (x, y) m, radius m, from z0 to z1 m above the floor."""

    x: float
    y: float
    radius: float
    z0: float
    z1: float
    label: int


@dataclass(frozen=True)
class Sphere:
    """A sphere with centre (x, y, z) m and radius m."""

    x: float
    y: float
    z: float
    radius: float
    label: int


Primitive = Box | Cylinder | Sphere

#: shape kind -> the labels its primitives carry
KINDS: dict[str, tuple[int, ...]] = {
    "table": (labels.TABLE,),
    "storage": (labels.STORAGE,),
    "plant": (labels.PLANT,),
    "person": (labels.BODY, labels.HEAD),
}


def _rays(mount: TopViewMount) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel ray slopes (a, b): the camera-frame point at depth z is (a z, b z, z)."""
    k = mount.intrinsics
    v, u = np.indices(k.shape, dtype=np.float64)
    return (u - k.cx) / k.fx, (v - k.cy) / k.fy


def _hit_box(box: Box, a: np.ndarray, b: np.ndarray, h: float) -> np.ndarray:
    """Depth (m) at which each ray enters the box; inf where it misses (slab method).

    The ray is world (a t, -b t, h - t) for depth t; in the box frame the x and y slabs
    are |.| <= s/2 and the z slab is 0 <= h - t <= height.
    """
    c, s = np.cos(box.yaw), np.sin(box.yaw)
    # world ray origin (0, 0, h), direction (a, -b, -1); rotate into the box frame
    ox, oy = -box.x * c - box.y * s, box.x * s - box.y * c
    dx, dy = a * c - b * s, -a * s - b * c
    t_in = np.full(a.shape, h - box.height)
    t_out = np.full(a.shape, h)
    with np.errstate(divide="ignore", invalid="ignore"):
        for o, d, half in ((ox, dx, box.sx / 2), (oy, dy, box.sy / 2)):
            t1, t2 = (-half - o) / d, (half - o) / d
            lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
            parallel = d == 0
            inside = abs(o) <= half
            lo = np.where(parallel, np.where(inside, -np.inf, np.inf), lo)
            hi = np.where(parallel, np.where(inside, np.inf, -np.inf), hi)
            t_in, t_out = np.maximum(t_in, lo), np.minimum(t_out, hi)
    return np.where(t_in <= t_out, t_in, np.inf)


def _hit_cylinder(cyl: Cylinder, a: np.ndarray, b: np.ndarray, h: float) -> np.ndarray:
    """Depth (m) at which each ray enters the vertical cylinder; inf where it misses."""
    # |(a t - x, -b t - y)|^2 = r^2  ->  A t^2 + B t + Cc = 0
    qa = a * a + b * b
    qb = -2.0 * (a * cyl.x - b * cyl.y)
    qc = cyl.x**2 + cyl.y**2 - cyl.radius**2
    with np.errstate(divide="ignore", invalid="ignore"):
        disc = qb * qb - 4 * qa * qc
        root = np.sqrt(np.maximum(disc, 0.0))
        lo = (-qb - root) / (2 * qa)
        hi = (-qb + root) / (2 * qa)
    axis_ray = qa == 0
    lo = np.where(axis_ray, np.where(qc <= 0, -np.inf, np.inf), np.where(disc >= 0, lo, np.inf))
    hi = np.where(axis_ray, np.where(qc <= 0, np.inf, -np.inf), np.where(disc >= 0, hi, -np.inf))
    t_in = np.maximum(lo, h - cyl.z1)
    t_out = np.minimum(hi, h - cyl.z0)
    return np.where(t_in <= t_out, t_in, np.inf)


def _hit_sphere(sph: Sphere, a: np.ndarray, b: np.ndarray, h: float) -> np.ndarray:
    """Depth (m) at which each ray enters the sphere; inf where it misses."""
    # |(a t - x, -b t - y, h - t - z)|^2 = r^2
    dz = h - sph.z
    qa = a * a + b * b + 1.0
    qb = -2.0 * (a * sph.x - b * sph.y + dz)
    qc = sph.x**2 + sph.y**2 + dz**2 - sph.radius**2
    disc = qb * qb - 4 * qa * qc
    t = (-qb - np.sqrt(np.maximum(disc, 0.0))) / (2 * qa)
    return np.where(disc >= 0, t, np.inf)


def hit_depth_m(prim: Primitive, mount: TopViewMount = TOP_VIEW) -> np.ndarray:
    """(H, W) depth in metres at which each pixel's ray first meets `prim` (inf: misses)."""
    a, b = _rays(mount)
    h = mount.height_mm / 1000.0
    if isinstance(prim, Box):
        return _hit_box(prim, a, b, h)
    if isinstance(prim, Cylinder):
        return _hit_cylinder(prim, a, b, h)
    if isinstance(prim, Sphere):
        return _hit_sphere(prim, a, b, h)
    raise TypeError(f"not a primitive: {prim!r}")


def render(prims: list[Primitive], mount: TopViewMount = TOP_VIEW) -> tuple[np.ndarray, np.ndarray]:
    """Exact noise-free render: (depth in metres float64, labels uint8), nearest hit wins.

    Rays that meet nothing see the floor (depth = camera height, label background).
    """
    depth = np.full(mount.intrinsics.shape, mount.height_mm / 1000.0)
    label = np.full(mount.intrinsics.shape, labels.BACKGROUND, np.uint8)
    for prim in prims:
        t = hit_depth_m(prim, mount)
        nearer = t < depth
        depth[nearer] = t[nearer]
        label[nearer] = prim.label
    return depth, label


def _spot(
    rng: np.random.Generator, mount: TopViewMount, margin: float, top_m: float = 0.0
) -> tuple[float, float]:
    """A floor position whose point `top_m` above it is in view, `margin` m from the edge."""
    w, d = mount.floor_extent_m()
    shrink = max(1.0 - 1000.0 * top_m / mount.height_mm, 0.0)  # perspective at that height
    hx, hy = max(w * shrink / 2 - margin, 0.0), max(d * shrink / 2 - margin, 0.0)
    return float(rng.uniform(-hx, hx)), float(rng.uniform(-hy, hy))


def random_object(rng: np.random.Generator, kind: str, mount: TopViewMount = TOP_VIEW):
    """The primitives of one object of `kind` (see `KINDS`) at a random pose."""
    yaw = float(rng.uniform(0, np.pi))
    if kind == "table":
        x, y = _spot(rng, mount, 0.3)
        sx, sy = rng.uniform(0.8, 1.4), rng.uniform(0.6, 0.9)
        return [Box(x, y, sx, sy, yaw, rng.uniform(0.7, 0.9), labels.TABLE)]
    if kind == "storage":
        height = rng.uniform(1.8, 2.1)
        x, y = _spot(rng, mount, 0.3, height)
        sx, sy = rng.uniform(1.0, 1.5), rng.uniform(0.35, 0.5)
        return [Box(x, y, sx, sy, yaw, height, labels.STORAGE)]
    if kind == "plant":
        x, y = _spot(rng, mount, 0.2)
        return [Cylinder(x, y, rng.uniform(0.1, 0.2), 0.0, rng.uniform(0.15, 0.35), labels.PLANT)]
    if kind == "person":
        top = rng.uniform(1.3, 1.55)
        r_head = rng.uniform(0.1, 0.13)
        x, y = _spot(rng, mount, 0.15, top)
        return [
            Cylinder(x, y, rng.uniform(0.18, 0.24), 0.0, top, labels.BODY),
            Sphere(x, y, top + 0.8 * r_head, r_head, labels.HEAD),
        ]
    raise ValueError(f"unknown shape kind {kind!r}; known: {', '.join(KINDS)}")


def random_scene(
    rng: np.random.Generator, mount: TopViewMount = TOP_VIEW, n_objects: int | None = None
) -> list[Primitive]:
    """A few objects (default 3..6, at least one person) dropped anywhere on the floor."""
    n = int(rng.integers(3, 7)) if n_objects is None else n_objects
    kinds = ["person", *rng.choice(list(KINDS), size=max(n - 1, 0))]
    return [p for kind in kinds[:n] for p in random_object(rng, str(kind), mount)]


def procedural_frame(
    rng: np.random.Generator,
    mount: TopViewMount = TOP_VIEW,
    noise_sigma_mm: float = 15.0,
    n_objects: int | None = None,
    missing_fraction: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """A random top-view frame: (depth uint16 mm, labels uint8).

    `noise_sigma_mm` is additive white Gaussian noise on depth (DESIGN section 1.3: 15 mm by
    default); `missing_fraction` of the pixels, drawn at random, read 0 (no depth) and carry
    the NO_DEPTH label, as a sensor's dropouts would.
    """
    if noise_sigma_mm < 0:
        raise ValueError(f"noise_sigma_mm must be >= 0, got {noise_sigma_mm}")
    if not 0.0 <= missing_fraction < 1.0:
        raise ValueError(f"missing_fraction must be in [0, 1), got {missing_fraction}")
    depth_m, label = render(random_scene(rng, mount, n_objects), mount)
    depth = depth_m * 1000.0
    if noise_sigma_mm > 0:
        depth = depth + rng.normal(0.0, noise_sigma_mm, depth.shape)
    depth_u16 = np.clip(np.rint(depth), 1, np.iinfo(np.uint16).max).astype(np.uint16)
    if missing_fraction > 0:
        missing = rng.random(depth.shape) < missing_fraction
        depth_u16[missing] = 0
        label[missing] = labels.NO_DEPTH
    return depth_u16, label


def procedural_frames(
    rng: np.random.Generator, n: int, mount: TopViewMount = TOP_VIEW, **kwargs
) -> tuple[np.ndarray, np.ndarray]:
    """`n` frames stacked: (N, H, W) uint16 depth and (N, H, W) uint8 labels, a training set.

    `kwargs` go to `procedural_frame` (noise_sigma_mm, n_objects, missing_fraction).
    """
    frames = [procedural_frame(rng, mount, **kwargs) for _ in range(n)]
    shape = (n, *mount.intrinsics.shape)
    depth = np.stack([d for d, _ in frames]) if frames else np.zeros(shape, np.uint16)
    label = np.stack([lab for _, lab in frames]) if frames else np.zeros(shape, np.uint8)
    return depth, label
