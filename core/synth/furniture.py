"""Parametric furniture built from primitives: two kinds per class, a few variants each.

The paper used four CAD instances per class (chair with and without armrests, rectangular and
round table, flowers and plants in pots, shelves and wardrobes). Here each kind is a function
of (variant, height) that returns boxes, cylinders and spheres in the item's own frame: origin
on the floor at the centre of its footprint, z up, +x its front (the way a sitter faces, the
side a shelf opens to). The overall height is exactly `height`: the density function draws
it, the renderer shows it.

Variants are a small catalogue of footprints and styles (as in a furniture catalogue), so
the scene builder can keep one pybullet body per (kind, variant, height on a 1 cm grid) alive
between frames instead of creating shapes per frame.

The tables also list the cell objects of `cell_objects` (class "object": boxes, drums, racks,
...), and `model` builds them too, so they are placed, pooled and rendered like furniture.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from topseg.core import labels
from topseg.core.synth import cell_objects
from topseg.core.synth.geometry import BOX, CYLINDER, SPHERE, Part, rect_footprint

#: kind -> label class, the paper's two instances per class, then the cell objects
KINDS: dict[str, int] = {
    "chair_plain": labels.CHAIR,
    "chair_armrest": labels.CHAIR,
    "table_rect": labels.TABLE,
    "table_round": labels.TABLE,
    "plant_potted": labels.PLANT,
    "plant_flowers": labels.PLANT,
    "storage_shelf": labels.STORAGE,
    "storage_wardrobe": labels.STORAGE,
    **dict.fromkeys(cell_objects.KINDS, cell_objects.LABEL),
}
#: class name -> its kinds
KINDS_OF: dict[str, tuple[str, ...]] = {
    "chair": ("chair_plain", "chair_armrest"),
    "table": ("table_rect", "table_round"),
    "plant": ("plant_potted", "plant_flowers"),
    "storage": ("storage_shelf", "storage_wardrobe"),
    cell_objects.CLASS: cell_objects.KINDS,
}
CLASS_OF_KIND: dict[str, str] = {k: c for c, ks in KINDS_OF.items() for k in ks}
N_VARIANTS = 4
#: heights are realised on this grid (metres) so bodies can be pooled
HEIGHT_STEP_M = 0.01

# Footprints of the catalogue, (size along local x, size along local y) in metres.
_CHAIR_SEATS = ((0.46, 0.46), (0.44, 0.48), (0.42, 0.44), (0.45, 0.50))
_TABLE_RECTS = ((1.20, 0.70), (1.40, 0.80), (1.60, 0.80), (1.00, 0.60))
_TABLE_RADII = (0.40, 0.50, 0.60, 0.45)
_POT_RADII = (0.07, 0.09, 0.11, 0.08)
_SHELVES = ((0.35, 0.80), (0.40, 1.00), (0.40, 1.20), (0.30, 0.60))  # (depth x, width y)
_WARDROBES = ((0.50, 0.80), (0.55, 1.00), (0.45, 0.60), (0.60, 1.20))


@dataclass(frozen=True)
class FurnitureModel:
    """One furniture item in its own frame (see module doc).

    `shape` is "rect" (size_x by size_y) or "disc" (radius size_x / 2). `features` holds the
    heights and extents relations need (seat_z, top_thickness, ...).
    """

    kind: str
    variant: int
    height: float
    size_x: float
    size_y: float
    shape: str
    parts: tuple[Part, ...]
    features: dict = field(default_factory=dict, hash=False, compare=False)

    @property
    def label(self) -> int:
        """The label id of the item's class (one of the paper's four, or `object`)."""
        return KINDS[self.kind]

    @property
    def cls(self) -> str:
        """The class name ("chair", "table", "plant", "storage" or "object") of this kind."""
        return CLASS_OF_KIND[self.kind]

    def footprint(self, x: float, y: float, yaw: float) -> np.ndarray:
        """The floor polygon of the item at (x, y), turned by `yaw` rad (a disc ignores yaw)."""
        if self.shape == "disc":
            from topseg.core.synth.geometry import disc_footprint

            return disc_footprint(x, y, self.size_x / 2.0)
        return rect_footprint(x, y, self.size_x, self.size_y, yaw)

    def top_z(self) -> float:
        """Height (m) of the highest point of any part: what a top-view camera sees first."""
        return max(p.top_z() for p in self.parts)


def quantize_height(h: float) -> float:
    """Snap a height to the 1 cm grid the bodies are pooled on."""
    return round(round(h / HEIGHT_STEP_M) * HEIGHT_STEP_M, 4)


def _box(cx, cy, cz, hx, hy, hz) -> Part:
    return Part(BOX, (hx, hy, hz), (cx, cy, cz))


def _cyl(cx, cy, z0, z1, r) -> Part:
    """Vertical cylinder from z0 to z1."""
    return Part(CYLINDER, (r, (z1 - z0) / 2.0, 0.0), (cx, cy, (z0 + z1) / 2.0))


def _chair(variant: int, height: float, armrests: bool) -> FurnitureModel:
    sx, sy = _CHAIR_SEATS[variant]
    seat_t = 0.05
    seat_z = 0.40 + 0.08 * np.clip((height - 0.70) / 0.20, 0.0, 1.0)  # seat top
    back_t = 0.04
    parts: list[Part] = []
    swivel = (variant % 2 == 1) if not armrests else (variant % 2 == 0)
    if swivel:  # office chair: five-star base and a gas column
        parts.append(_cyl(0.0, 0.0, 0.0, seat_z - seat_t, 0.03))
        for k in range(5):
            a = 2 * np.pi * k / 5
            arm = 0.28
            parts.append(
                Part(
                    BOX,
                    (arm / 2, 0.025, 0.02),
                    (np.cos(a) * arm / 2, np.sin(a) * arm / 2, 0.06),
                    tuple(_yaw_q(a)),
                )
            )
    else:  # four legs
        lx, ly = sx / 2 - 0.03, sy / 2 - 0.03
        for ix in (-1, 1):
            for iy in (-1, 1):
                parts.append(
                    _box(ix * lx, iy * ly, (seat_z - seat_t) / 2, 0.02, 0.02, (seat_z - seat_t) / 2)
                )
    parts.append(_box(0.0, 0.0, seat_z - seat_t / 2, sx / 2, sy / 2, seat_t / 2))
    # backrest: a panel at the back (-x), from the seat to the top
    bz0 = seat_z + 0.05
    parts.append(
        _box(
            -sx / 2 + back_t / 2,
            0.0,
            (bz0 + height) / 2,
            back_t / 2,
            sy / 2 - 0.02,
            (height - bz0) / 2,
        )
    )
    parts.append(
        _box(
            -sx / 2 + back_t / 2,
            0.0,
            (seat_z + bz0) / 2,
            back_t / 2,
            0.03,
            (bz0 - seat_z) / 2 + 0.01,
        )
    )
    arm_z = seat_z + 0.20
    if armrests:
        for iy in (-1, 1):
            y = iy * (sy / 2 - 0.03)
            parts.append(_box(0.0, y, arm_z - 0.015, sx * 0.38, 0.03, 0.015))
            parts.append(_box(0.05, y, (seat_z + arm_z) / 2, 0.015, 0.015, (arm_z - seat_z) / 2))
    features = {
        "seat_z": float(seat_z),
        "seat_front_x": sx / 2,
        "seat_back_x": -sx / 2 + back_t,
        "back_x": -sx / 2 + back_t / 2,
        "back_top_z": height,
        "armrest_z": arm_z if armrests else None,
    }
    return FurnitureModel(
        "chair_armrest" if armrests else "chair_plain",
        variant,
        height,
        sx,
        sy,
        "rect",
        tuple(parts),
        features,
    )


def _table_rect(variant: int, height: float) -> FurnitureModel:
    sx, sy = _TABLE_RECTS[variant]
    t = 0.03
    leg = 0.025
    parts = [_box(0.0, 0.0, height - t / 2, sx / 2, sy / 2, t / 2)]
    lx, ly = sx / 2 - 0.04, sy / 2 - 0.04
    for ix in (-1, 1):
        for iy in (-1, 1):
            parts.append(_box(ix * lx, iy * ly, (height - t) / 2, leg, leg, (height - t) / 2))
    if variant % 2 == 1:  # modesty panel between the back legs
        parts.append(_box(0.0, ly, height - t - 0.15, lx - leg, 0.01, 0.12))
    features = {"top_thickness": t, "leg_inset": 0.04 + leg, "underside_z": height - t}
    return FurnitureModel("table_rect", variant, height, sx, sy, "rect", tuple(parts), features)


def _table_round(variant: int, height: float) -> FurnitureModel:
    r = _TABLE_RADII[variant]
    t = 0.03
    parts = [_cyl(0.0, 0.0, height - t, height, r)]
    if variant % 2 == 0:  # pedestal and disc foot
        parts.append(_cyl(0.0, 0.0, 0.02, height - t, 0.04))
        parts.append(_cyl(0.0, 0.0, 0.0, 0.02, 0.6 * r))
    else:  # four legs
        for k in range(4):
            a = np.pi / 4 + k * np.pi / 2
            parts.append(
                _box(
                    0.7 * r * np.cos(a),
                    0.7 * r * np.sin(a),
                    (height - t) / 2,
                    0.02,
                    0.02,
                    (height - t) / 2,
                )
            )
    features = {"top_thickness": t, "underside_z": height - t, "radius": r}
    return FurnitureModel(
        "table_round", variant, height, 2 * r, 2 * r, "disc", tuple(parts), features
    )


def _plant(variant: int, height: float, flowers: bool) -> FurnitureModel:
    pr = _POT_RADII[variant]
    pot_h = 0.45 * height
    parts = [_cyl(0.0, 0.0, 0.0, pot_h, pr)]
    rng = np.random.default_rng(
        1000 + variant + (100 if flowers else 0)
    )  # a fixed layout per variant
    if flowers:
        n = 3 + variant
        head = min(0.035, 0.25 * (height - pot_h))
        for _ in range(n):
            a = rng.uniform(0, 2 * np.pi)
            rr = rng.uniform(0.0, 0.6) * pr
            top = height - head - rng.uniform(0.0, 0.3) * (height - pot_h - 2 * head)
            cx, cy = rr * np.cos(a), rr * np.sin(a)
            parts.append(_cyl(cx, cy, pot_h, top, 0.006))
            parts.append(Part(SPHERE, (head, 0.0, 0.0), (cx, cy, top)))
        # the tallest flower reaches the full height
        parts[-1] = Part(
            SPHERE, (head, 0.0, 0.0), (parts[-1].pos[0], parts[-1].pos[1], height - head)
        )
        parts[-2] = _cyl(parts[-1].pos[0], parts[-1].pos[1], pot_h, height - head, 0.006)
    else:
        foliage = height - pot_h
        r0 = min(pr * 1.3, foliage / 2)
        parts.append(Part(SPHERE, (r0, 0.0, 0.0), (0.0, 0.0, height - r0)))
        for k in range(3 + variant % 2):
            a = 2 * np.pi * k / (3 + variant % 2) + rng.uniform(0, 0.5)
            r1 = 0.7 * r0
            d = 0.8 * r0
            parts.append(
                Part(SPHERE, (r1, 0.0, 0.0), (d * np.cos(a), d * np.sin(a), pot_h + r1 * 0.9))
            )
    features = {"pot_radius": pr, "pot_height": pot_h}
    size = 2 * max(pr, max(np.hypot(p.pos[0], p.pos[1]) + p.size[0] for p in parts[1:]))
    return FurnitureModel(
        "plant_flowers" if flowers else "plant_potted",
        variant,
        height,
        size,
        size,
        "disc",
        tuple(parts),
        features,
    )


def _storage(variant: int, height: float, closed: bool) -> FurnitureModel:
    sx, sy = (_WARDROBES if closed else _SHELVES)[variant]
    t = 0.02
    parts: list[Part] = []
    if closed:  # carcass with a plinth and two handles on the front (+x)
        parts.append(_box(0.0, 0.0, (0.05 + height) / 2, sx / 2, sy / 2, (height - 0.05) / 2))
        parts.append(_box(-0.02, 0.0, 0.025, sx / 2 - 0.02, sy / 2 - 0.02, 0.025))
        for iy in (-1, 1):
            parts.append(_box(sx / 2 + 0.01, iy * 0.05, height * 0.6, 0.01, 0.008, 0.06))
    else:  # two sides, a back, top, bottom and shelves between
        for iy in (-1, 1):
            parts.append(_box(0.0, iy * (sy / 2 - t / 2), height / 2, sx / 2, t / 2, height / 2))
        parts.append(_box(-sx / 2 + t / 2, 0.0, height / 2, t / 2, sy / 2 - t, height / 2))
        n_boards = 3 + variant % 2
        for k in range(n_boards):
            z = 0.05 + k * (height - 0.05 - t) / (n_boards - 1)
            parts.append(_box(0.0, 0.0, z + t / 2, sx / 2, sy / 2 - t, t / 2))
    features = {"front_x": sx / 2}
    return FurnitureModel(
        "storage_wardrobe" if closed else "storage_shelf",
        variant,
        height,
        sx,
        sy,
        "rect",
        tuple(parts),
        features,
    )


def _yaw_q(a: float) -> np.ndarray:
    return np.array([0.0, 0.0, np.sin(a / 2), np.cos(a / 2)])


@lru_cache(maxsize=4096)
def model(kind: str, variant: int, height: float) -> FurnitureModel:
    """The furniture item `kind` / `variant` with overall height `height` metres."""
    if kind not in KINDS:
        raise ValueError(f"unknown furniture kind {kind!r}; known: {', '.join(KINDS)}")
    if not 0 <= variant < N_VARIANTS:
        raise ValueError(f"variant must be in 0..{N_VARIANTS - 1}, got {variant}")
    if not 0.05 <= height <= 3.0:
        raise ValueError(f"furniture height {height} m is out of range")
    if kind in cell_objects.KINDS:
        c = cell_objects.build(kind, variant, height)
        return FurnitureModel(
            kind, variant, height, c.size_x, c.size_y, c.shape, c.parts, c.features
        )
    if kind.startswith("chair"):
        return _chair(variant, height, kind == "chair_armrest")
    if kind == "table_rect":
        return _table_rect(variant, height)
    if kind == "table_round":
        return _table_round(variant, height)
    if kind.startswith("plant"):
        return _plant(variant, height, kind == "plant_flowers")
    return _storage(variant, height, kind == "storage_wardrobe")
