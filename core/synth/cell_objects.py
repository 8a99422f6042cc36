"""Cell objects: the things in a robot cell that are neither people nor furniture (label `object`).

Boxes, crates, totes, drums, gas cylinders, carts, pallets, racks, lockers, machine housings,
control cabinets, coat stands, cones, bollards, guard panels, conveyors, and the small parts
and tools that lie on tables. A model that has seen only people and the paper's four furniture
classes calls every one of them a person; the ones a person's size from above (drums, gas
cylinders, lockers, racks, coat stands, stacked crates, loaded pallets) most of all, so their
variants mix round tops, flat tops and a smaller part on top, like a head on shoulders.

Each kind is a function of (variant, height) built like `furniture`'s kinds: boxes, cylinders
and spheres in the item's own frame (origin on the floor at the centre of its footprint, z up,
+x its front), overall height exactly `height`, real sizes in metres. `furniture` lists these
kinds in its tables (class "object") and its `model()` builds them through `build()`, so
placed cell objects are pooled, posed and rendered exactly like furniture. This module imports
nothing from `furniture`. Objects of arbitrary shape, from meshes, are `mesh_objects`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from topseg.core import labels
from topseg.core.synth.geometry import (
    BOX,
    CYLINDER,
    MAX_PARTS,
    SPHERE,
    Part,
    aabb,
    quat_from_axis_angle,
    quat_to_matrix,
    rotation_between,
    yaw_quat,
)

#: label id of every cell object
LABEL = labels.OBJECT
#: the class name cell objects go by in furniture's tables and scene descriptions
CLASS = "object"
N_VARIANTS = 4


@dataclass(frozen=True)
class CellShape:
    """A cell object's geometry: footprint size and shape ("rect" or "disc") and its parts.

    The same fields a `furniture.FurnitureModel` holds besides kind, variant and height.
    `features` holds what placement rules need, e.g. `stack_top_z` for stackable kinds: the
    height another item can stand at on top of this one, None when its top is not flat.
    """

    size_x: float
    size_y: float
    shape: str
    parts: tuple[Part, ...]
    features: dict = field(default_factory=dict, hash=False, compare=False)


# --- primitives -----------------------------------------------------------------------------


def _block(cx: float, cy: float, z0: float, z1: float, sx: float, sy: float) -> Part:
    """Axis-aligned box, `sx` by `sy` around (cx, cy), from height z0 to z1."""
    return Part(BOX, (sx / 2.0, sy / 2.0, (z1 - z0) / 2.0), (cx, cy, (z0 + z1) / 2.0))


def _cyl(cx: float, cy: float, z0: float, z1: float, r: float) -> Part:
    """Vertical cylinder of radius `r` from z0 to z1."""
    return Part(CYLINDER, (r, (z1 - z0) / 2.0, 0.0), (cx, cy, (z0 + z1) / 2.0))


def _ball(cx: float, cy: float, cz: float, r: float) -> Part:
    """Sphere of radius `r` around (cx, cy, cz)."""
    return Part(SPHERE, (r, 0.0, 0.0), (cx, cy, cz))


def _rod(p0, p1, r: float) -> Part:
    """Cylinder of radius `r` whose axis runs from point p0 to point p1 (any direction)."""
    a, b = np.asarray(p0, np.float64), np.asarray(p1, np.float64)
    d = b - a
    quat = rotation_between((0.0, 0.0, 1.0), d)
    c = (a + b) / 2.0
    return Part(
        CYLINDER,
        (r, float(np.linalg.norm(d)) / 2.0, 0.0),
        (float(c[0]), float(c[1]), float(c[2])),
        tuple(float(q) for q in quat),
    )


def _tilted_slab(cx: float, top: float, length: float, sy: float, t: float, rise: float) -> Part:
    """A board `length` deep (x) and `sy` wide, tilted so its back (-x) edge is `rise` higher
    than its front; its highest point is at `top`."""
    a = float(np.arctan2(rise, length))
    hx = length / (2.0 * np.cos(a))
    quat = quat_from_axis_angle((0.0, 1.0, 0.0), a)  # turns +x downwards: the back rises
    half_z = hx * np.sin(a) + (t / 2.0) * np.cos(a)
    return Part(
        BOX, (hx, sy / 2.0, t / 2.0), (cx, 0.0, top - half_z), tuple(float(q) for q in quat)
    )


def _yawed_block(cx, cy, z0, z1, sx, sy, yaw: float) -> Part:
    """Box `sx` by `sy` (in its own frame) around (cx, cy), turned by `yaw` about z."""
    b = _block(cx, cy, z0, z1, sx, sy)
    return Part(BOX, b.size, b.pos, tuple(float(q) for q in yaw_quat(yaw)))


def _open_box(cx, cy, z0, z1, sx, sy, wall: float, floor: float) -> list[Part]:
    """Four walls `wall` thick around an `sx` by `sy` outline and, if `floor` > 0, a floor."""
    parts = []
    if floor > 0:
        parts.append(_block(cx, cy, z0, z0 + floor, sx, sy))
    for s in (-1, 1):
        parts.append(_block(cx, cy + s * (sy - wall) / 2, z0, z1, sx, wall))
        parts.append(_block(cx + s * (sx - wall) / 2, cy, z0, z1, wall, sy - 2 * wall))
    return parts


def _ring(cx, cy, z0, z1, r_out: float, thickness: float, n: int) -> list[Part]:
    """A vertical ring (a valve guard) of `n` boxes, a polygon inside radius `r_out`."""
    half_len = r_out * np.tan(np.pi / n)
    rc = float(np.sqrt(r_out**2 - half_len**2)) - thickness / 2.0
    parts = []
    for k in range(n):
        a = 2 * np.pi * k / n
        parts.append(
            _yawed_block(
                cx + rc * np.cos(a), cy + rc * np.sin(a), z0, z1, thickness, 2 * half_len, a
            )
        )
    return parts


def _scaled(parts: list[Part], s: float) -> list[Part]:
    """The parts scaled by `s` about the origin (sizes and positions)."""
    return [
        Part(
            p.kind, tuple(float(v) * s for v in p.size), tuple(float(v) * s for v in p.pos), p.quat
        )
        for p in parts
    ]


# --- footprints -----------------------------------------------------------------------------


def _xy_bounds(parts: list[Part]) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) of the parts on the floor plane, exact for every primitive."""
    los, his = zip(
        *(aabb(p.kind, p.size, np.asarray(p.pos), quat_to_matrix(p.quat)) for p in parts),
        strict=True,
    )
    return np.min(los, axis=0)[:2], np.max(his, axis=0)[:2]


def _radial_extent(p: Part) -> float:
    """How far from the z axis any point of the part reaches."""
    c = np.asarray(p.pos, np.float64)
    if p.kind == SPHERE:
        return float(np.hypot(c[0], c[1]) + p.size[0])
    rot = quat_to_matrix(p.quat)
    if p.kind == BOX:
        corners = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)])
        pts = c + (corners * np.asarray(p.size)) @ rot.T
        return float(np.max(np.hypot(pts[:, 0], pts[:, 1])))
    r, h = float(p.size[0]), float(p.size[1])
    if abs(rot[2, 2]) > 1.0 - 1e-12:  # upright: its rim circles
        return float(np.hypot(c[0], c[1]) + r)
    a = np.linspace(0.0, 2 * np.pi, 720, endpoint=False)
    rim = np.stack([r * np.cos(a), r * np.sin(a), np.zeros_like(a)], 1) / np.cos(np.pi / 720)
    pts = np.concatenate([c + (rim + np.array((0.0, 0.0, s * h))) @ rot.T for s in (-1, 1)])
    return float(np.max(np.hypot(pts[:, 0], pts[:, 1])))


def _rect(parts: list[Part], **features) -> CellShape:
    """The parts moved so their floor bounding rectangle is centred on the origin."""
    lo, hi = _xy_bounds(parts)
    cx, cy = (lo + hi) / 2.0
    moved = tuple(
        Part(p.kind, p.size, (float(p.pos[0] - cx), float(p.pos[1] - cy), p.pos[2]), p.quat)
        for p in parts
    )
    sx, sy = hi - lo
    return CellShape(float(sx), float(sy), "rect", moved, features)


def _disc(parts: list[Part], **features) -> CellShape:
    """The parts as they are, with the smallest disc around the z axis that holds them."""
    r = max(_radial_extent(p) for p in parts)
    return CellShape(2 * r, 2 * r, "disc", tuple(parts), features)


# --- the kinds ------------------------------------------------------------------------------

_BOXES = ((0.60, 0.40), (0.40, 0.30), (0.80, 0.60), (0.50, 0.50))


def _box(v: int, h: float) -> CellShape:
    """Cardboard box, lidded plastic crate, wooden crate on skids, box with its flaps up."""
    sx, sy = _BOXES[v]
    if v == 0:  # taped cardboard box
        return _rect([_block(0, 0, 0, h, sx, sy)], stack_top_z=h)
    if v == 1:  # plastic crate, its lid overhangs the body
        parts = [_block(0, 0, 0, h - 0.02, sx - 0.03, sy - 0.03), _block(0, 0, h - 0.02, h, sx, sy)]
        return _rect(parts, stack_top_z=h)
    if v == 2:  # wooden crate on two skids, battens round the top
        skid = 0.06
        parts = [_block(0, s * (sy / 2 - 0.04), 0, skid, sx, 0.08) for s in (-1, 1)]
        parts.append(_block(0, 0, skid, h, sx - 0.02, sy - 0.02))
        parts.append(_block(0, 0, h - 0.08, h - 0.02, sx, sy))
        return _rect(parts, stack_top_z=h)
    flap = min(sy / 2 - 0.02, 0.35 * h)  # opened box: four flaps stand up round the rim
    body = h - flap
    parts = _open_box(0, 0, 0, body, sx, sy, 0.006, 0.006)
    parts.append(_block(0, 0, 0, 0.5 * body, sx - 0.02, sy - 0.02))  # what it holds
    parts += _open_box(0, 0, body, h, sx, sy, 0.004, 0.0)
    return _rect(parts, stack_top_z=None)


#: crate footprint (x, y) and the height one crate of the stack has about
_CRATE_STACKS = ((0.60, 0.40, 0.32), (0.60, 0.40, 0.42), (0.40, 0.30, 0.27), (0.80, 0.60, 0.60))


def _crate(ox: float, oy: float, z0: float, z1: float, sx: float, sy: float, open_top: bool):
    """One crate: a body under a rim, or open (walls and a floor) when `open_top`."""
    if open_top:
        return _open_box(ox, oy, z0, z1, sx, sy, 0.015, 0.01)
    return [
        _block(ox, oy, z0, z1 - 0.015, sx - 0.02, sy - 0.02),
        _block(ox, oy, z1 - 0.015, z1, sx, sy),
    ]


def _crate_stack(v: int, h: float) -> CellShape:
    """Two to four crates on each other, each a little offset; the top one open in odd ones."""
    sx, sy, nominal = _CRATE_STACKS[v]
    n = int(np.clip(round(h / nominal), 2, 4))
    step = h / n
    offsets = np.random.default_rng(2000 + v).uniform(-0.04, 0.04, (4, 2))
    offsets[0] = 0.0
    parts = []
    for k in range(n):
        top = h if k == n - 1 else (k + 1) * step
        parts += _crate(*offsets[k], k * step, top, sx, sy, open_top=(k == n - 1 and v % 2 == 1))
    return _rect(parts)


_TOTES = ((0.60, 0.40), (0.40, 0.30), (0.30, 0.20), (0.80, 0.60))


def _tote(v: int, h: float) -> CellShape:
    """Open bin: plain, with a rim lip, a tapered stacking tote, with a divider."""
    sx, sy = _TOTES[v]
    if v == 0:
        parts = _open_box(0, 0, 0, h, sx, sy, 0.01, 0.01)
    elif v == 1:
        parts = _open_box(0, 0, 0, h - 0.015, sx - 0.03, sy - 0.03, 0.01, 0.01)
        parts += _open_box(0, 0, h - 0.015, h, sx, sy, 0.025, 0.0)
    elif v == 2:
        parts = _open_box(0, 0, 0, h / 2, sx - 0.04, sy - 0.04, 0.01, 0.01)
        parts += _open_box(0, 0, h / 2, h, sx, sy, 0.01, 0.0)
    else:
        parts = _open_box(0, 0, 0, h, sx, sy, 0.01, 0.01)
        parts.append(_block(0, 0, 0.01, 0.7 * h, 0.006, sy - 0.02))
    return _rect(parts, stack_top_z=h)


_DRUM_RADII = (0.286, 0.29, 0.28, 0.30)


def _drum_parts(cx: float, cy: float, z0: float, h: float, r: float, style: int) -> list[Part]:
    """A drum of radius `r` standing at height z0, its top at `h`: 0 steel with a chime and
    hoops and a bung on its lid, 1 plastic with a domed top, 2 open-head with a clamp ring,
    3 steel with a funnel in its bung."""
    body_top = h - 0.16 if style == 3 else h
    parts: list[Part] = []
    if style in (0, 3):
        lid = body_top - 0.005 if style == 0 else body_top
        parts.append(_cyl(cx, cy, z0, lid - 0.02, r - 0.004))
        parts.append(_cyl(cx, cy, lid - 0.02, lid, r))  # the chime round the lid
        for f in (1 / 3, 2 / 3):
            zf = z0 + f * (lid - z0)
            parts.append(_cyl(cx, cy, zf - 0.01, zf + 0.01, r))
    if style == 0:
        parts.append(_cyl(cx + 0.6 * r, cy, h - 0.005, h, 0.03))
    if style == 1:
        dome = r - 0.03
        parts.append(_cyl(cx, cy, z0, h - 0.08, r))
        parts.append(_cyl(cx, cy, h - 0.08, h - 0.05, r - 0.015))
        parts.append(_ball(cx, cy, h - dome, dome))
        for s in (-1, 1):
            parts.append(_cyl(cx + s * 0.21 * r / 0.29, cy, h - 0.05, h - 0.03, 0.03))
    if style == 2:
        parts.append(_cyl(cx, cy, z0, h, r - 0.005))
        parts.append(_cyl(cx, cy, h - 0.045, h - 0.015, r))
        parts.append(_cyl(cx, cy, z0 + 0.3 * (h - z0) - 0.01, z0 + 0.3 * (h - z0) + 0.01, r))
    if style == 3:
        fx = cx + 0.12
        parts.append(_cyl(fx, cy, body_top - 0.02, body_top + 0.04, 0.02))
        parts.append(_cyl(fx, cy, body_top + 0.04, body_top + 0.10, 0.08))
        parts.append(_cyl(fx, cy, body_top + 0.10, h, 0.14))
    return parts


def _drum(v: int, h: float) -> CellShape:
    """A 200 l drum, person-wide from above (see `_drum_parts` for the four styles)."""
    r = _DRUM_RADII[v]
    return _disc(_drum_parts(0.0, 0.0, 0.0, h, r, v), radius=r)


_GAS_RADII = (0.10, 0.115, 0.12, 0.11)
#: height of what stands on the shoulder (neck, valve, cap), per variant
_GAS_TOPS = (0.16, 0.12, 0.13, 0.14)


def _gas_cylinder(v: int, h: float) -> CellShape:
    """Gas bottle: domed shoulder under a tulip cap, a bare valve and handwheel, a valve
    guard collar, or a round cap."""
    r = _GAS_RADII[v]
    zc = h - _GAS_TOPS[v] - r  # centre of the shoulder dome
    apex = zc + r
    parts = [_cyl(0, 0, 0, zc, r), _ball(0, 0, zc, r)]
    if v == 0:
        parts += [_cyl(0, 0, apex - 0.01, apex + 0.03, 0.035), _cyl(0, 0, apex + 0.03, h, 0.065)]
    elif v == 1:
        parts.append(_cyl(0, 0, apex - 0.01, apex + 0.02, 0.03))
        parts.append(_block(0, 0, apex + 0.02, h - 0.03, 0.06, 0.04))
        parts.append(_block(0.04, 0, h - 0.07, h - 0.05, 0.04, 0.02))  # outlet
        parts.append(_cyl(0, 0, h - 0.03, h - 0.015, 0.006))
        parts.append(_cyl(0, 0, h - 0.015, h, 0.035))  # handwheel
    elif v == 2:
        parts.append(_cyl(0, 0, 0, 0.08, r))  # foot ring
        parts.append(_block(0, 0, apex - 0.01, h - 0.04, 0.05, 0.04))
        parts += _ring(0, 0, apex - 0.03, h, 0.085, 0.008, n=8)
    else:
        parts.append(_cyl(0, 0, apex - 0.01, apex + 0.03, 0.035))
        parts.append(_cyl(0, 0, apex + 0.03, h - 0.06, 0.06))
        parts.append(_ball(0, 0, h - 0.06, 0.06))
    return _disc(parts, radius=r)


#: (length x, width y) of the platform trolleys and, last, the sack truck
_HAND_CARTS = ((0.90, 0.60), (0.75, 0.50), (1.20, 0.80), (0.50, 0.45))
_CART_WHEELS = (0.06, 0.05, 0.08, 0.10)


def _push_handle(x: float, half_w: float, z0: float, h: float, r: float = 0.012) -> list[Part]:
    """Two uprights at `x`, `half_w` either side, and a bar across whose top is at `h`."""
    bar_z = h - r
    parts = [_rod((x, s * half_w, z0), (x, s * half_w, bar_z), r) for s in (-1, 1)]
    parts.append(_rod((x, -half_w - r, bar_z), (x, half_w + r, bar_z), r))
    return parts


def _hand_cart(v: int, h: float) -> CellShape:
    """Platform trolley with a push handle (plain, with a rim, with a box on it) or an upright
    sack truck; `h` is the handle's top."""
    sx, sy = _HAND_CARTS[v]
    wr = _CART_WHEELS[v]
    if v == 3:  # sack truck: two wheels behind an upright frame, a nose plate in front
        parts = [_block(0.04, 0, 0, 0.01, 0.32, 0.35)]
        for s in (-1, 1):
            parts.append(_rod((-0.16, s * 0.17, wr), (-0.16, s * 0.22, wr), wr))
            parts.append(_block(-0.10, s * 0.17, 0.01, h - 0.03, 0.03, 0.03))
        parts.append(_block(-0.10, 0, 0.45 * h, 0.45 * h + 0.02, 0.02, 0.34))
        parts.append(_block(-0.10, 0, 0.75 * h, 0.75 * h + 0.02, 0.02, 0.34))
        parts.append(_rod((-0.10, -0.2, h - 0.015), (-0.10, 0.2, h - 0.015), 0.015))
        return _rect(parts)
    deck0 = 2 * wr + 0.01
    deck1 = deck0 + 0.03
    parts = [_block(0, 0, deck0, deck1, sx, sy)]
    for ix in (-1, 1):
        for iy in (-1, 1):
            x, y = ix * (sx / 2 - 0.1), iy * (sy / 2 - 0.06)
            parts.append(_rod((x, y - 0.02, wr), (x, y + 0.02, wr), wr))
            parts.append(_block(x, y, 2 * wr - 0.01, deck0, 0.04, 0.05))  # fork
    parts += _push_handle(-sx / 2 + 0.02, sy / 2 - 0.04, deck1, h)
    if v == 1:  # a lip round the deck
        parts += _open_box(0, 0, deck1, deck1 + 0.03, sx, sy, 0.015, 0.0)
    if v == 2:  # a box on the deck
        parts.append(_block(0.1, 0, deck1, deck1 + min(0.35, h - deck1 - 0.25), sx / 2, 0.8 * sy))
    return _rect(parts)


_SHELF_CARTS = ((0.80, 0.50), (1.00, 0.60), (0.70, 0.45), (1.20, 0.70))


def _shelf_cart(v: int, h: float) -> CellShape:
    """Transport cart on casters with two or three shelves: with a push handle (and a box on
    its top shelf), or with corner posts up to a flat top shelf or to the top tray's lip."""
    sx, sy = _SHELF_CARTS[v]
    n = 2 + v % 2
    handle = v in (0, 1)
    lip = 0.04 if v == 3 else 0.0
    top_shelf = h - 0.12 if handle else h - lip
    parts: list[Part] = []
    for ix in (-1, 1):
        for iy in (-1, 1):
            x, y = ix * (sx / 2 - 0.06), iy * (sy / 2 - 0.06)
            parts.append(_rod((x - 0.015, y, 0.05), (x + 0.015, y, 0.05), 0.05))  # caster
            x, y = ix * (sx / 2 - 0.0125), iy * (sy / 2 - 0.0125)
            parts.append(_block(x, y, 0.1, top_shelf + lip, 0.025, 0.025))
    for z in np.linspace(0.2, top_shelf, n):
        parts.append(_block(0, 0, z - 0.025, z, sx, sy))
    if lip:  # a tray's lip round the top shelf
        parts += _open_box(0, 0, top_shelf, h, sx, sy, 0.01, 0.0)
    if handle:
        parts += _push_handle(-sx / 2 + 0.015, sy / 2 - 0.05, top_shelf, h)
    if v == 1:
        parts.append(_block(0.1, 0, top_shelf, top_shelf + 0.08, 0.4 * sx, 0.6 * sy))
    return _rect(parts)


_PALLETS = ((1.20, 0.80), (1.20, 1.00), (1.14, 1.14), (1.20, 0.80))
#: board thickness of the wooden pallets
_BOARD = 0.022


def _pallet_parts(sx: float, sy: float, h: float, plastic: bool, deck_boards: int) -> list[Part]:
    """A pallet `sx` by `sy`, `h` tall: wooden (three bottom boards, three rows of blocks
    under `deck_boards` deck boards, or one solid deck when that is 0) or plastic (a solid
    deck on three rows of feet and three runners)."""
    cols_x = (-sx / 2 + 0.0725, 0.0, sx / 2 - 0.0725)
    rows_y = (-sy / 2 + 0.0725, 0.0, sy / 2 - 0.0725)
    t = 0.035 if plastic else _BOARD
    parts = [_block(0, y, 0, 0.02 if plastic else t, sx, 0.145) for y in rows_y]
    parts += [_block(x, 0, parts[0].top_z(), h - t, 0.145, sy) for x in cols_x]
    if plastic or deck_boards == 0:
        return [*parts, _block(0, 0, h - t, h, sx, sy)]
    ys = np.linspace(-sy / 2 + 0.0725, sy / 2 - 0.0725, deck_boards)
    for k, y in enumerate(ys):
        w = 0.145 if k in (0, deck_boards - 1, deck_boards // 2) else 0.10
        parts.append(_block(0, y, h - t, h, sx, w))
    return parts


def _pallet(v: int, h: float) -> CellShape:
    """Empty pallet: Euro, industrial 1.2 x 1.0, 1.14 square, plastic."""
    sx, sy = _PALLETS[v]
    return _rect(_pallet_parts(sx, sy, h, plastic=(v == 3), deck_boards=7 if v == 1 else 5))


_LOADED_PALLET_H = 0.144


def _cartons(hp: float, h: float) -> list[Part]:
    """Layers of 0.4 m cartons on a Euro pallet (a full layer reads as one block); the top
    layer is two cartons only."""
    layers = max(1, round((h - hp) / 0.25))
    lh = (h - hp) / layers
    parts = [_block(0, 0, hp + k * lh, hp + (k + 1) * lh, 1.19, 0.79) for k in range(layers - 1)]
    top = hp + (layers - 1) * lh
    parts += [_block(x, -0.2, top, h, 0.395, 0.395) for x in (-0.4, 0.0)]
    return parts


def _ibc(sx: float, sy: float, hp: float, h: float) -> list[Part]:
    """An IBC: the tank in its cage (corner posts, top bars), the filler cap on top."""
    top = h - 0.06
    hx, hy = sx / 2 - 0.015, sy / 2 - 0.015
    parts = [_block(0, 0, hp, top, sx - 0.06, sy - 0.06), _cyl(0, 0, top, h, 0.075)]
    for ix in (-1, 1):
        for iy in (-1, 1):
            parts.append(_rod((ix * hx, iy * hy, hp), (ix * hx, iy * hy, top + 0.01), 0.012))
    parts += [_rod((-hx, y, top + 0.01), (hx, y, top + 0.01), 0.01) for y in (-hy, hy)]
    parts.append(_rod((0, -hy, top + 0.01), (0, hy, top + 0.01), 0.01))
    return parts


def _drums_2x2(sx: float, sy: float, hp: float, h: float) -> list[Part]:
    """Four drums with clamp rings, or two layers of four kegs with a board between when
    that is taller than a drum."""
    r, c = 0.28, 0.285
    spots = [(ix * c, iy * c) for ix in (-1, 1) for iy in (-1, 1)]
    if h - hp <= 0.95:
        return [_cyl(x, y, hp, h, r - 0.005) for x, y in spots] + [
            _cyl(x, y, h - 0.045, h - 0.015, r) for x, y in spots
        ]
    each = (h - hp - 0.02) / 2
    parts = [_cyl(x, y, hp, hp + each, r) for x, y in spots]
    parts.append(_block(0, 0, hp + each, hp + each + 0.02, sx, sy))
    parts += [_cyl(x, y, h - each, h, r) for x, y in spots]
    return parts


def _pallet_loaded(v: int, h: float) -> CellShape:
    """Pallet with a load: a wrapped block (flat), carton layers with a part layer on top, an
    IBC tank in its cage with the filler cap on top, or drums (kegs in two layers when
    taller than a drum)."""
    hp = _LOADED_PALLET_H
    sx, sy = ((1.20, 0.80), (1.20, 0.80), (1.20, 1.00), (1.14, 1.14))[v]
    parts = _pallet_parts(sx, sy, hp, plastic=False, deck_boards=0)
    if v == 0:
        parts.append(_block(0, 0, hp, h, sx - 0.02, sy - 0.02))
    elif v == 1:
        parts += _cartons(hp, h)
    elif v == 2:
        parts += _ibc(sx, sy, hp, h)
    else:
        parts += _drums_2x2(sx, sy, hp, h)
    return _rect(parts)


_RACKS = ((0.50, 1.00), (0.60, 1.20), (0.40, 0.90), (0.80, 1.80))  # (depth x, width y)


def _rack_boxes(rng, z: float, gap: float, sx: float, sy: float, ratios) -> list[Part]:
    """Boxes side by side on a shelf at height `z`, as tall as `ratios` times `gap`."""
    n = len(ratios)
    width = sy / n
    parts = []
    for k, ratio in enumerate(ratios):
        w = width * rng.uniform(0.6, 0.9)
        d = sx * rng.uniform(0.6, 0.9)
        y = -sy / 2 + (k + 0.5) * width
        parts.append(_block(sx / 2 - d / 2 - 0.01, y, z, z + ratio * gap, d, w))
    return parts


def _rack(v: int, h: float) -> CellShape:
    """Open shelving with boxes on its shelves: flat top board, boxes standing highest on the
    top shelf, boxes under the posts' tops, or pallet-rack beams with loads."""
    sx, sy = _RACKS[v]
    rng = np.random.default_rng(3000 + v)
    posts_top = h - 0.3 if v == 1 else h
    top_level = {0: h, 1: h - 0.3, 2: h - 0.28, 3: h}[v]
    levels = np.linspace(0.15, top_level, 5 if v == 1 else 4)
    shelf_t = 0.08 if v == 3 else 0.025
    parts = [
        _block(ix * (sx / 2 - 0.02), iy * (sy / 2 - 0.02), 0, posts_top, 0.04, 0.04)
        for ix in (-1, 1)
        for iy in (-1, 1)
    ]
    for z in levels:
        if v == 3:  # beams front and back
            parts += [_block(s * (sx / 2 - 0.03), 0, z - 0.08, z, 0.05, sy) for s in (-1, 1)]
        else:
            parts.append(_block(0, 0, z - 0.025, z, sx, sy))
    if v == 1:  # on top: boxes, the tallest 0.3 m
        parts += _rack_boxes(rng, h - 0.3, 0.3, sx, sy, (1.0, 0.6, 0.8))
    if v == 2:
        parts += _rack_boxes(rng, h - 0.28, 0.28, sx, sy, (0.5, 0.8))
    # the lower shelves' loads, from the top one down, as far as a pooled body has room
    for z, above in zip(levels[-2::-1], levels[:0:-1], strict=True):
        gap = above - z - shelf_t
        if v == 3 and len(parts) < MAX_PARTS:
            parts.append(_block(0, 0, z, z + 0.75 * gap, sx - 0.1, 0.8 * sy))
        elif v != 3 and len(parts) + 2 <= MAX_PARTS:
            parts += _rack_boxes(rng, z, gap, sx, sy, rng.uniform(0.4, 0.85, 2))
    return _rect(parts)


_LOCKERS = ((0.50, 0.40), (0.50, 0.80), (0.45, 1.20), (0.60, 1.00))  # (depth x, width y)


def _door_handles(front_x: float, sy: float, z: float) -> list[Part]:
    """One handle per door (a door every 0.4 m or so) on the front face at `front_x`."""
    doors = max(1, round(sy / 0.4))
    return [
        _block(front_x + 0.01, -sy / 2 + (k + 0.5) * sy / doors + 0.12, z, z + 0.12, 0.02, 0.02)
        for k in range(doors)
    ]


def _locker(v: int, h: float) -> CellShape:
    """Tall steel cabinet / locker: flat top, sloped anti-dust roof, boxes stored on top, or
    a top cornice."""
    sx, sy = _LOCKERS[v]
    d = sx - 0.02  # the carcass; its door handles stand 2 cm proud in front
    cx = -0.01
    plinth = [_block(cx - 0.02, 0, 0, 0.08, d - 0.04, sy - 0.04)]
    if v == 0:
        parts = [*plinth, _block(cx, 0, 0.08, h, d, sy)]
    elif v == 1:
        rise = 0.18 * d
        top = h - rise
        parts = [*plinth, _block(cx, 0, 0.08, top, d, sy)]
        parts.append(_tilted_slab(cx, h, d - 0.02, sy, 0.015, rise))
        parts.append(_block(cx - d / 2 + 0.02, 0, top, h - 0.03, 0.02, sy))  # back panel
    elif v == 2:
        top = h - 0.28
        parts = [*plinth, _block(cx, 0, 0.08, top, d, sy)]
        parts.append(_block(cx - 0.04, -0.1 * sy, top, top + 0.18, 0.7 * d, 0.45 * sy))
        parts.append(_block(cx - 0.06, -0.12 * sy, top + 0.18, h, 0.55 * d, 0.35 * sy))
    else:
        parts = [*plinth, _block(cx, 0, 0.08, h - 0.04, d - 0.03, sy - 0.03)]
        parts.append(_block(cx, 0, h - 0.04, h, d, sy))
        d -= 0.03
    parts += _door_handles(cx + d / 2, sy if v != 3 else sy - 0.03, min(1.05, 0.55 * h))
    return _rect(parts)


_MACHINES = ((1.50, 2.00), (1.20, 1.60), (1.00, 1.20), (1.40, 1.80))  # (depth x, width y)


def _machine(v: int, h: float) -> CellShape:
    """Machine-tool housing: a door window recessed in its front, a hood on top, a sloped
    front top, or a flat housing with a signal tower at a corner."""
    sx, sy = _MACHINES[v]
    parts: list[Part] = []
    if v == 0:  # window band recessed 6 cm between a base and a top band, pillars each side
        rd, zw0, zw1 = 0.06, 0.9, min(h - 0.15, 1.7)
        parts.append(_block(-rd / 2, 0, 0, h, sx - rd, sy))
        parts.append(_block(sx / 2 - rd / 2, 0, 0, zw0, rd, sy))
        parts.append(_block(sx / 2 - rd / 2, 0, zw1, h, rd, sy))
        parts += [_block(sx / 2 - rd / 2, s * (sy / 2 - 0.1), zw0, zw1, rd, 0.2) for s in (-1, 1)]
    elif v == 1:  # a hood (extraction, a cabinet) on the back half of the roof
        top = h - 0.3
        parts.append(_block(0, 0, 0, top, sx, sy))
        parts.append(_block(-sx / 4, 0.1 * sy, top, h, 0.45 * sx, 0.4 * sy))
    elif v == 2:  # low front, sloped window up to the back block
        front = h - 0.35
        parts.append(_block(0, 0, 0, front, sx, sy))
        parts.append(_block(-sx / 4, 0, front, h, sx / 2, sy))
        parts.append(_tilted_slab(sx / 4, h, sx / 2, sy - 0.04, 0.02, 0.35))
    else:  # flat roof, a signal tower at the back corner, a control pendant in front
        top = h - 0.4
        parts.append(_block(0, 0, 0, top, sx - 0.15, sy))
        parts.append(_block(sx / 2 - 0.1, sy / 2 - 0.25, 0.55 * top, 0.9 * top, 0.1, 0.4))
        tx, ty = -sx / 2 + 0.15, sy / 2 - 0.15
        parts.append(_cyl(tx, ty, top, h - 0.24, 0.015))
        parts += [_cyl(tx, ty, h - 0.24 + 0.08 * k, h - 0.16 + 0.08 * k, 0.035) for k in range(3)]
    return _rect(parts)


_CONTROL_CABINETS = ((0.50, 0.80), (0.40, 0.60), (0.60, 1.20), (0.50, 0.80))  # (depth, width)


def _control_cabinet(v: int, h: float) -> CellShape:
    """Electrical enclosure on a plinth: flat, a roof fan unit, a double bay, or a signal
    tower on its roof."""
    sx, sy = _CONTROL_CABINETS[v]
    d = sx - 0.02
    cx = -0.01
    top = {0: h, 1: h - 0.12, 2: h, 3: h - 0.35}[v]
    parts = [_block(cx, 0, 0, 0.1, d - 0.02, sy - 0.02), _block(cx, 0, 0.1, top, d, sy)]
    if v == 1:
        parts.append(_block(cx, 0, top, h, 0.32, 0.32))
    if v == 2:  # the seam between two bays
        parts.append(_block(cx + d / 2 - 0.005, 0, 0.1, top, 0.01, 0.02))
    if v == 3:
        ty = sy / 2 - 0.08
        parts.append(_cyl(cx - d / 4, ty, top, h - 0.18, 0.015))
        parts += [
            _cyl(cx - d / 4, ty, h - 0.18 + 0.06 * k, h - 0.12 + 0.06 * k, 0.035) for k in range(3)
        ]
    parts += _door_handles(cx + d / 2, sy, min(1.1, 0.6 * top))
    return _rect(parts)


_COAT_POLES = (0.018, 0.02, 0.015, 0.025)


def _coat(a: float, hook_z: float, radius: float) -> list[Part]:
    """A coat on a hook at angle `a`: shoulders, a longer skirt, a hood (round, head-like)."""
    c, s = np.cos(a), np.sin(a)
    r_mid = radius + 0.07
    return [
        _yawed_block(r_mid * c, r_mid * s, hook_z - 0.4, hook_z - 0.02, 0.14, 0.42, a),
        _yawed_block(
            (r_mid + 0.01) * c, (r_mid + 0.01) * s, hook_z - 0.95, hook_z - 0.4, 0.16, 0.46, a
        ),
        _ball((radius + 0.05) * c, (radius + 0.05) * s, hook_z - 0.04, 0.09),
    ]


def _coat_stand(v: int, h: float) -> CellShape:
    """Coat stand, a person's height but thin: a pole on a base or feet, hooks near the top,
    a ball, a cap or a hat on top; coats (or a bag) hanging in three variants."""
    rp = _COAT_POLES[v]
    parts: list[Part] = []
    if v in (0, 2):
        parts.append(_cyl(0, 0, 0, 0.03, 0.2 if v == 0 else 0.17))
    else:
        n_feet = 4 if v == 1 else 3
        for k in range(n_feet):
            a = 2 * np.pi * k / n_feet
            parts.append(_yawed_block(0.14 * np.cos(a), 0.14 * np.sin(a), 0, 0.03, 0.28, 0.04, a))
    if v == 1:
        pole_top = h - 0.02
        parts.append(_cyl(0, 0, pole_top, h, 0.03))
    elif v == 2:  # a hat on the pole: crown and brim
        pole_top = h - 0.11
        parts += [_cyl(0, 0, pole_top, pole_top + 0.01, 0.15), _cyl(0, 0, pole_top, h, 0.09)]
    else:
        pole_top = h - 0.035
        parts.append(_ball(0, 0, h - 0.035, 0.035))
    parts.append(_cyl(0, 0, 0.0, pole_top, rp))
    hook_z = h - 0.18
    for k in range(4):
        a = np.pi * k / 2 + 0.3
        end = (0.15 * np.cos(a), 0.15 * np.sin(a), hook_z + 0.05)
        parts.append(_rod((0.0, 0.0, hook_z), end, 0.01))
    coats = {0: (0.3,), 1: (0.3, 0.3 + np.pi), 2: (), 3: (0.3,)}[v]
    for a in coats:
        parts += _coat(a, hook_z, 0.14)
    if v == 3:  # a bag on the opposite hook
        a = 0.3 + np.pi
        parts.append(
            _yawed_block(
                0.2 * np.cos(a), 0.2 * np.sin(a), hook_z - 0.45, hook_z - 0.1, 0.12, 0.3, a
            )
        )
    return _disc(parts)


def _stacked_cone(z0: float, z1: float, r0: float, r1: float, n: int = 10) -> list[Part]:
    """A cone from radius r0 at z0 to r1 at z1 as `n` stacked cylinders."""
    zs = np.linspace(z0, z1, n + 1)
    return [_cyl(0, 0, zs[k], zs[k + 1], r0 + (r1 - r0) * (k + 0.5) / n) for k in range(n)]


def _traffic_cone(v: int, h: float) -> CellShape:
    """Traffic cone on a square base (large, small), on a round base, or a slim delineator post."""
    if v in (0, 2):
        b, r0, r1 = (0.34, 0.13, 0.025) if v == 0 else (0.26, 0.10, 0.02)
        return _rect([_block(0, 0, 0, 0.03, b, b), *_stacked_cone(0.03, h, r0, r1)])
    if v == 1:
        return _disc([_cyl(0, 0, 0, 0.04, 0.2), *_stacked_cone(0.04, h, 0.12, 0.025)])
    parts = [
        _cyl(0, 0, 0, 0.05, 0.2),
        _cyl(0, 0, 0.05, h - 0.03, 0.05),
        _cyl(0, 0, h - 0.03, h, 0.06),
    ]
    return _disc(parts)


def _bollard(v: int, h: float) -> CellShape:
    """Bollard or stanchion: steel post with a dome, post with a flat cap, chain stanchion
    with a knob on a heavy base, square plastic post."""
    if v == 0:
        r = 0.07
        return _rect(
            [_block(0, 0, 0, 0.01, 0.2, 0.2), _cyl(0, 0, 0.01, h - r, r), _ball(0, 0, h - r, r)]
        )
    if v == 1:
        return _disc(
            [
                _cyl(0, 0, 0, 0.01, 0.12),
                _cyl(0, 0, 0.01, h - 0.02, 0.06),
                _cyl(0, 0, h - 0.02, h, 0.07),
            ]
        )
    if v == 2:
        return _disc(
            [
                _cyl(0, 0, 0, 0.05, 0.18),
                _cyl(0, 0, 0.05, h - 0.07, 0.025),
                _ball(0, 0, h - 0.04, 0.04),
            ]
        )
    return _rect(
        [
            _block(0, 0, 0, 0.03, 0.3, 0.3),
            _block(0, 0, 0.03, h - 0.03, 0.1, 0.1),
            _block(0, 0, h - 0.03, h, 0.12, 0.12),
        ]
    )


_PANEL_WIDTHS = (0.60, 1.00, 1.20, 1.50)


def _guard_panel(v: int, h: float) -> CellShape:
    """Machine guard section (mesh between two posts on foot plates; top rail below or flush
    with the posts; a solid lower half) or a portable fence panel on two long feet."""
    w = _PANEL_WIDTHS[v]
    if v == 3:
        r = 0.02
        parts = [_block(0, s * (w / 2 - r), 0, 0.05, 0.6, 0.08) for s in (-1, 1)]
        parts += [_rod((0, s * (w / 2 - r), 0.05), (0, s * (w / 2 - r), h - r), r) for s in (-1, 1)]
        parts.append(_rod((0, -w / 2 + r, h - r), (0, w / 2 - r, h - r), r))
        parts.append(_rod((0, -w / 2 + r, 0.15), (0, w / 2 - r, 0.15), r))
        parts.append(_block(0, 0, 0.15, h - r, 0.004, w - 4 * r))
        return _rect(parts)
    rail_top = h - 0.05 if v == 0 else h
    py = w / 2 - 0.03
    parts = [_block(0, s * py, 0, 0.01, 0.12, 0.06) for s in (-1, 1)]
    parts += [_block(0, s * py, 0.01, h, 0.06, 0.06) for s in (-1, 1)]
    parts.append(_block(0, 0, rail_top - 0.02, rail_top, 0.02, w - 0.12))
    parts.append(_block(0, 0, 0.1, 0.12, 0.02, w - 0.12))
    if v == 2:
        mid = 0.12 + (rail_top - 0.14) / 2
        parts.append(_block(0, 0, 0.12, mid, 0.01, w - 0.12))
        parts.append(_block(0, 0, mid, rail_top - 0.02, 0.004, w - 0.12))
    else:
        parts.append(_block(0, 0, 0.12, rail_top - 0.02, 0.004, w - 0.12))
    return _rect(parts)


_CONVEYORS = ((1.50, 0.50), (2.00, 0.60), (1.00, 0.40), (1.20, 0.80))  # (length x, width y)


def _conveyor(v: int, h: float) -> CellShape:
    """Conveyor section on legs: a flat belt, a belt between side guides, rollers, or a belt
    round end drums with its motor below."""
    sx, sy = _CONVEYORS[v]
    belt = h - 0.05 if v == 1 else h  # the top of the belt or the rollers
    rail_top = belt - 0.005 if v != 2 else belt - 0.01
    frame0 = rail_top - 0.12
    parts = [
        _block(ix * (sx / 2 - 0.1), iy * (sy / 2 - 0.04), 0, frame0, 0.05, 0.05)
        for ix in (-1, 1)
        for iy in (-1, 1)
    ]
    parts += [_block(0, s * (sy / 2 - 0.015), frame0, rail_top, sx, 0.03) for s in (-1, 1)]
    inner = sy - 0.06
    if v in (0, 1):
        parts.append(_block(0, 0, belt - 0.06, belt, sx - 0.02, inner))
    if v == 1:
        parts += [_block(0, s * (sy / 2 - 0.005), rail_top, h, sx, 0.01) for s in (-1, 1)]
    if v == 2:
        for x in np.arange(-sx / 2 + 0.05, sx / 2 - 0.049, 0.1):
            parts.append(_rod((x, -inner / 2, belt - 0.025), (x, inner / 2, belt - 0.025), 0.025))
    if v == 3:
        for s in (-1, 1):
            parts.append(
                _rod(
                    (s * (sx / 2 - 0.05), -inner / 2, h - 0.05),
                    (s * (sx / 2 - 0.05), inner / 2, h - 0.05),
                    0.05,
                )
            )
        parts.append(_block(0, 0, h - 0.1, h, sx - 0.1, inner))
        parts.append(_block(sx / 2 - 0.25, 0, frame0 - 0.25, frame0, 0.25, 0.2))  # motor
    return _rect(parts)


_TRAYS = ((0.40, 0.30), (0.60, 0.40), (0.30, 0.20), (0.50, 0.35))


def _parts_tray(v: int, h: float) -> CellShape:
    """Shallow tray for parts: empty, with upright parts in it, with dividers, with a foam
    insert and tools."""
    sx, sy = _TRAYS[v]
    parts = _open_box(0, 0, 0, h, sx, sy, 0.006, 0.005)
    if v == 1:
        for i in range(3):
            for j in range(2):
                parts.append(_cyl(-sx / 3 + i * sx / 3, -sy / 4 + j * sy / 2, 0.005, 0.6 * h, 0.02))
    if v == 2:
        parts += [_block(x, 0, 0.005, h - 0.01, 0.004, sy - 0.012) for x in (-sx / 6, sx / 6)]
        parts.append(_block(0, 0, 0.005, h - 0.01, sx - 0.012, 0.004))
    if v == 3:
        parts.append(_block(0, 0, 0.005, 0.4 * h, sx - 0.012, sy - 0.012))
        parts.append(_block(-0.05, 0.03, 0.4 * h, 0.7 * h, 0.18, 0.03))
        parts.append(_block(0.06, -0.04, 0.4 * h, 0.6 * h, 0.05, 0.05))
    return _rect(parts)


_TOOLBOXES = ((0.50, 0.22), (0.40, 0.20), (0.60, 0.28), (0.45, 0.25))


def _toolbox(v: int, h: float) -> CellShape:
    """Toolbox: an arched carrying handle, a flat lid, two cantilever trays out on top, or a
    rounded lid."""
    sx, sy = _TOOLBOXES[v]
    if v == 0:
        body = h - 0.06
        parts = [_block(0, 0, 0, body, sx, sy)]
        parts += [_block(s * 0.1, 0, body, h - 0.012, 0.02, 0.02) for s in (-1, 1)]
        parts.append(_rod((-0.11, 0, h - 0.012), (0.11, 0, h - 0.012), 0.012))
        return _rect(parts, stack_top_z=None)
    if v == 1:
        parts = [_block(0, 0, 0, h - 0.02, sx - 0.01, sy - 0.01), _block(0, 0, h - 0.02, h, sx, sy)]
        parts += [
            _block(s * sx / 4, sy / 2 - 0.01, h - 0.06, h - 0.03, 0.04, 0.02) for s in (-1, 1)
        ]
        return _rect(parts, stack_top_z=h)
    if v == 2:
        body = h - 0.06
        parts = _open_box(0, 0, 0, body, sx, sy, 0.01, 0.01)
        parts += _open_box(-sx / 4, -sy / 4, body, h, sx / 2, sy / 2, 0.008, 0.006)
        parts += _open_box(sx / 4, sy / 4, body, h, sx / 2, sy / 2, 0.008, 0.006)
        return _rect(parts, stack_top_z=None)
    r = min(sy / 2, 0.45 * h)
    parts = [_block(0, 0, 0, h - 0.6 * r, sx, sy), _rod((-sx / 2, 0, h - r), (sx / 2, 0, h - r), r)]
    return _rect(parts, stack_top_z=None)


def _part_block(v: int, h: float) -> CellShape:
    """A workpiece: a stepped machined block, an upright shaft, a flange with a boss, an
    L-bracket."""
    if v == 0:
        step = 0.6 * h
        return _rect([_block(0, 0, 0, step, 0.15, 0.10), _block(-0.035, 0, step, h, 0.08, 0.10)])
    if v == 1:
        return _disc([_cyl(0, 0, 0, h, 0.04)])
    if v == 2:
        return _disc([_cyl(0, 0, 0, 0.3 * h, 0.09), _cyl(0, 0, 0.3 * h, h, 0.04)])
    return _rect([_block(0, 0, 0, 0.02, 0.16, 0.10), _block(-0.07, 0, 0.02, h, 0.02, 0.10)])


_DRILL_NOMINAL_H = 0.24


def _drill(v: int, h: float) -> CellShape:
    """Cordless drill standing on its battery, drawn at 24 cm and scaled to `h`: plain, with
    a side handle, a short impact driver, a big battery and a long bit."""
    battery = (0.12, 0.09, 0.08) if v == 3 else (0.11, 0.075, 0.07)
    motor = (-0.06, 0.05) if v == 2 else (-0.07, 0.08)
    z = _DRILL_NOMINAL_H - 0.04
    parts = [
        _block(-0.01, 0, 0, battery[2], battery[0], battery[1]),
        _block(-0.01, 0, battery[2], z - 0.03, 0.045, 0.04),
        _rod((motor[0], 0, z), (motor[1], 0, z), 0.04),
    ]
    if v == 2:
        parts.append(_block(motor[1] + 0.02, 0, z - 0.012, z + 0.012, 0.04, 0.024))
    else:
        parts.append(_rod((motor[1], 0, z), (motor[1] + 0.05, 0, z), 0.022))
        bit = 0.12 if v == 3 else 0.07
        parts.append(_rod((motor[1] + 0.05, 0, z), (motor[1] + 0.05 + bit, 0, z), 0.004))
    if v == 1:
        parts.append(_rod((motor[1] + 0.01, -0.12, z), (motor[1] + 0.01, 0, z), 0.015))
    return _rect(_scaled(parts, h / _DRILL_NOMINAL_H))


# --- the catalogue --------------------------------------------------------------------------

_BUILDERS: dict[str, Callable[[int, float], CellShape]] = {
    "box": _box,
    "crate_stack": _crate_stack,
    "tote": _tote,
    "drum": _drum,
    "gas_cylinder": _gas_cylinder,
    "hand_cart": _hand_cart,
    "shelf_cart": _shelf_cart,
    "pallet": _pallet,
    "pallet_loaded": _pallet_loaded,
    "rack": _rack,
    "locker": _locker,
    "machine": _machine,
    "control_cabinet": _control_cabinet,
    "coat_stand": _coat_stand,
    "traffic_cone": _traffic_cone,
    "bollard": _bollard,
    "guard_panel": _guard_panel,
    "conveyor": _conveyor,
    "parts_tray": _parts_tray,
    "toolbox": _toolbox,
    "part_block": _part_block,
    "drill": _drill,
}

#: every cell-object kind, in catalogue order
KINDS: tuple[str, ...] = tuple(_BUILDERS)

#: kind -> (lowest, highest) overall height in metres, on the 1 cm grid
HEIGHT_RANGE_M: dict[str, tuple[float, float]] = {
    "box": (0.30, 0.80),
    "crate_stack": (1.00, 1.80),
    "tote": (0.20, 0.50),
    "drum": (0.60, 0.90),
    "gas_cylinder": (1.20, 1.60),
    "hand_cart": (0.90, 1.10),
    "shelf_cart": (0.80, 1.10),
    "pallet": (0.12, 0.15),
    "pallet_loaded": (0.50, 1.50),
    "rack": (1.60, 2.20),
    "locker": (1.60, 2.00),
    "machine": (1.20, 2.20),
    "control_cabinet": (1.20, 2.20),
    "coat_stand": (1.70, 1.90),
    "traffic_cone": (0.30, 0.75),
    "bollard": (0.70, 1.10),
    "guard_panel": (1.40, 2.00),
    "conveyor": (0.70, 1.00),
    "parts_tray": (0.05, 0.12),
    "toolbox": (0.15, 0.30),
    "part_block": (0.05, 0.20),
    "drill": (0.18, 0.30),
}

#: small parts and tools that lie on a table (they stand on one as their `support`)
TABLE_TOP_KINDS: tuple[str, ...] = ("parts_tray", "toolbox", "part_block", "drill")
#: kinds that stand on the floor
FLOOR_KINDS: tuple[str, ...] = tuple(k for k in KINDS if k not in TABLE_TOP_KINDS)
#: kinds that can stand on another item (on a stackable one's `stack_top_z`, or on a table)
STACKABLE: tuple[str, ...] = ("box", "tote", "toolbox")
#: kinds a person's height or width from above: what a depth forest takes for head on shoulders
PERSON_LIKE: tuple[str, ...] = (
    "drum",
    "gas_cylinder",
    "crate_stack",
    "pallet_loaded",
    "rack",
    "locker",
    "coat_stand",
)

#: kind -> one line for the docs
DESCRIPTIONS: dict[str, str] = {
    "box": "cardboard box, lidded plastic crate, wooden crate on skids, open box with flaps up",
    "crate_stack": "two to four crates on each other, slightly offset, the top one open or closed",
    "tote": "open plastic bin: plain, with a rim lip, tapered, with a divider",
    "drum": "200 l drum (r 0.28-0.30 m): steel with rim, domed plastic, open-head, with a funnel",
    "gas_cylinder": "gas bottle (r 0.10-0.12 m): domed shoulder, cap, valve, guard collar",
    "hand_cart": "platform trolley with a push handle (plain, rim, box on it) or a sack truck",
    "shelf_cart": "transport cart on casters with two or three shelves, handle or corner posts",
    "pallet": "empty pallet: Euro 1.2 x 0.8, 1.2 x 1.0, 1.14 square, plastic",
    "pallet_loaded": "pallet with a wrapped block, carton layers, an IBC tank, drums or kegs",
    "rack": "open shelving rack, posts and shelves with boxes, or pallet-rack beams",
    "locker": "tall steel cabinet / locker: flat, sloped roof, boxes on top, cornice",
    "machine": "machine-tool housing up to 1.5 x 2.0 m: window recess, hood, sloped front, tower",
    "control_cabinet": "electrical enclosure on a plinth: flat, roof fan, double bay, signal tower",
    "coat_stand": "coat stand 1.7-1.9 m: thin pole, hooks, ball / cap / hat, coats hanging",
    "traffic_cone": "traffic cone on a square or round base, or a slim delineator post",
    "bollard": "bollard or stanchion: domed, capped, chain stanchion with a knob, square post",
    "guard_panel": "machine guard mesh panel between posts, or a portable fence panel",
    "conveyor": "conveyor section on legs: flat belt, side guides, rollers, end drums",
    "parts_tray": "shallow parts tray: empty, with parts, with dividers, foam insert",
    "toolbox": "toolbox: carrying handle, flat lid, cantilever trays, rounded lid",
    "part_block": "workpiece: stepped block, upright shaft, flange with a boss, L-bracket",
    "drill": "cordless drill standing on its battery, or an impact driver",
}


def build(kind: str, variant: int, height: float) -> CellShape:
    """The geometry of cell object `kind` / `variant`, `height` metres tall overall.

    A ValueError names an unknown kind, a variant out of 0..N_VARIANTS-1 or a height outside
    the kind's `HEIGHT_RANGE_M`."""
    if kind not in _BUILDERS:
        raise ValueError(f"unknown cell object kind {kind!r}; known: {', '.join(KINDS)}")
    if not 0 <= variant < N_VARIANTS:
        raise ValueError(f"variant must be in 0..{N_VARIANTS - 1}, got {variant}")
    lo, hi = HEIGHT_RANGE_M[kind]
    if not lo - 1e-9 <= height <= hi + 1e-9:
        raise ValueError(f"a {kind} is {lo:.2f}-{hi:.2f} m tall, got {height} m")
    return _BUILDERS[kind](variant, float(height))
