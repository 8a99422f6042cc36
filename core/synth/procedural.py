"""Procedural top-view scenes: boxes, cylinders and spheres on the floor, for tests and benches.

A quick source of labelled top-view frames with the right geometry, far cheaper than the
paper's density-function scenes (`synthesis`): a floor 3.5 m below the camera and a few
solids standing on it. Each solid is an analytic primitive with a topseg label, rendered by
the package's ray caster (`render.raycast_m`: every pixel's centre ray meets the primitives in
closed form, the nearest hit wins) and given the shared Gaussian noise model
(`noise.GaussianNoise`).

Shape kinds and their labels (`KINDS`): a large low box is a table, a long narrow box
taller than a person is storage (a shelf), a short cylinder is a plant, and a "person" is
a body cylinder with a head sphere resting on it. The kinds differ in size and height the
way the real classes do, so a forest can learn them from depth-difference features.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from topseg.core import labels
from topseg.core.camera import PAPER_MOUNT, TopViewMount, metres_to_mm
from topseg.core.synth.geometry import BOX, CYLINDER, SPHERE
from topseg.core.synth.noise import GaussianNoise
from topseg.core.synth.render import Primitives, raycast_m
from topseg.core.synth.rooms import view_rect


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


def primitives(prims: list[Primitive]) -> Primitives:
    """The solids as the ray caster's `render.Primitives` (world frame, z up, floor at 0)."""
    n = len(prims)
    kind = np.empty(n, np.int32)
    size = np.zeros((n, 3))
    center = np.zeros((n, 3))
    rot = np.tile(np.eye(3), (n, 1, 1))
    label = np.empty(n, np.uint8)
    for i, prim in enumerate(prims):
        label[i] = prim.label
        if isinstance(prim, Box):
            c, s = np.cos(prim.yaw), np.sin(prim.yaw)
            kind[i] = BOX
            size[i] = (prim.sx / 2, prim.sy / 2, prim.height / 2)
            center[i] = (prim.x, prim.y, prim.height / 2)
            rot[i] = ((c, -s, 0.0), (s, c, 0.0), (0.0, 0.0, 1.0))
        elif isinstance(prim, Cylinder):
            kind[i] = CYLINDER
            size[i] = (prim.radius, (prim.z1 - prim.z0) / 2, 0.0)
            center[i] = (prim.x, prim.y, (prim.z0 + prim.z1) / 2)
        elif isinstance(prim, Sphere):
            kind[i] = SPHERE
            size[i] = (prim.radius, 0.0, 0.0)
            center[i] = (prim.x, prim.y, prim.z)
        else:
            raise TypeError(f"not a primitive: {prim!r}")
    return Primitives(kind, size, center, rot, label)


def hit_depth_m(prim: Primitive, mount: TopViewMount = PAPER_MOUNT) -> np.ndarray:
    """(H, W) depth in metres at which each pixel's ray first meets `prim` (inf: misses)."""
    return raycast_m(primitives([prim]), mount)[0]


def render(
    prims: list[Primitive], mount: TopViewMount = PAPER_MOUNT
) -> tuple[np.ndarray, np.ndarray]:
    """Exact noise-free render through `render.raycast_m`: (depth in metres float64, labels
    uint8), nearest hit wins. Rays that meet nothing see the floor (depth = camera height,
    label background)."""
    depth, label = raycast_m(primitives(prims), mount)
    floor = ~np.isfinite(depth)
    depth[floor] = mount.height_mm / 1000.0
    label[floor] = labels.BACKGROUND
    return depth, label


def _spot(
    rng: np.random.Generator, mount: TopViewMount, margin: float, top_m: float = 0.0
) -> tuple[float, float]:
    """A floor position whose point `top_m` above it is in view, `margin` m from the edge."""
    (x0, y0), (x1, y1) = view_rect(mount)
    shrink = max(1.0 - 1000.0 * top_m / mount.height_mm, 0.0)  # perspective at that height
    mx, my = (x0 + x1) / 2 * shrink, (y0 + y1) / 2 * shrink
    hx = max((x1 - x0) * shrink / 2 - margin, 0.0)
    hy = max((y1 - y0) * shrink / 2 - margin, 0.0)
    return float(rng.uniform(mx - hx, mx + hx)), float(rng.uniform(my - hy, my + hy))


def random_object(rng: np.random.Generator, kind: str, mount: TopViewMount = PAPER_MOUNT):
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
    rng: np.random.Generator, mount: TopViewMount = PAPER_MOUNT, n_objects: int | None = None
) -> list[Primitive]:
    """A few objects (default 3..6, at least one person) dropped anywhere on the floor."""
    n = int(rng.integers(3, 7)) if n_objects is None else n_objects
    kinds = ["person", *rng.choice(list(KINDS), size=max(n - 1, 0))]
    return [p for kind in kinds[:n] for p in random_object(rng, str(kind), mount)]


def procedural_frame(
    rng: np.random.Generator,
    mount: TopViewMount = PAPER_MOUNT,
    noise_sigma_mm: float = 15.0,
    n_objects: int | None = None,
    missing_fraction: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """A random top-view frame: (depth uint16 mm, labels uint8).

    `noise_sigma_mm` is `noise.GaussianNoise`, additive white Gaussian noise on depth (DESIGN
    section 1.3: 15 mm by default); `missing_fraction` of the pixels, drawn at random, read 0 (no depth) and carry
    the NO_DEPTH label, as a sensor's dropouts would.
    """
    if noise_sigma_mm < 0:
        raise ValueError(f"noise_sigma_mm must be >= 0, got {noise_sigma_mm}")
    if not 0.0 <= missing_fraction < 1.0:
        raise ValueError(f"missing_fraction must be in [0, 1), got {missing_fraction}")
    depth_m, label = render(random_scene(rng, mount, n_objects), mount)
    depth = GaussianNoise(noise_sigma_mm).apply(metres_to_mm(depth_m), rng)
    if missing_fraction > 0:
        missing = rng.random(depth.shape) < missing_fraction
        depth[missing] = 0
        label[missing] = labels.NO_DEPTH
    return depth, label


def procedural_frames(
    rng: np.random.Generator, n: int, mount: TopViewMount = PAPER_MOUNT, **kwargs
) -> tuple[np.ndarray, np.ndarray]:
    """`n` frames stacked: (N, H, W) uint16 depth and (N, H, W) uint8 labels, a training set.

    `kwargs` go to `procedural_frame` (noise_sigma_mm, n_objects, missing_fraction).
    """
    frames = [procedural_frame(rng, mount, **kwargs) for _ in range(n)]
    shape = (n, *mount.intrinsics.shape)
    depth = np.stack([d for d, _ in frames]) if frames else np.zeros(shape, np.uint16)
    label = np.stack([lab for _, lab in frames]) if frames else np.zeros(shape, np.uint8)
    return depth, label
