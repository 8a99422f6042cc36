"""The relations of the density function: how one item is placed against another, and the test
that a placed scene still honours them.

Object-object (O-O): two tables joined, storage under a table, a chair partly under a table,
a plant on a table. Human-object (H-O): sitting on a chair (and at the table that chair is
under), a hand on a table, holding a chair's back, standing by storage.

Each `place_*` draws the free parameters of its relation from `rng` and returns the new item
and the relation's record, or None when the anchor cannot take it (a round table cannot be
joined, a storage too tall to go under the table, a target out of the arm's reach). Each
`check_*` re-derives the geometry from the scene alone (the human through forward kinematics)
so `DensityFunction.log_density` can score any scene, sampled here or edited by hand.
"""

from __future__ import annotations

import numpy as np

from topseg.core import labels as L
from topseg.core.synth import furniture, humanoid
from topseg.core.synth.geometry import (
    aabb,
    clip_convex,
    overlap_fraction,
    points_in_convex,
    polygon_area,
    quat_mul,
)
from topseg.core.synth.scene import HUMAN, PlacedHuman, PlacedObject, Relation, Scene

OO_RELATIONS = ("tables_joined", "storage_under_table", "chair_under_table", "plant_on_table")
HO_RELATIONS = (
    "sitting_on_chair",
    "sitting_at_table",
    "hand_on_table",
    "holding_chair_back",
    "standing_by_storage",
)
#: relations whose items may overlap beyond theta (they are stacked, not side by side)
STACKING = frozenset({"storage_under_table", "chair_under_table", "plant_on_table", *HO_RELATIONS})
#: poses each H-O relation can start from (the relation then bends the arms)
HO_POSES = {
    "sitting_on_chair": ("sitting",),
    "hand_on_table": ("standing", "working", "bending"),
    "holding_chair_back": ("standing", "working", "bowing"),
    "standing_by_storage": ("standing", "working", "stretching", "bending"),
}
HAND_TOL_M = 0.002
HIP_TOL_M = 0.001


def _wrap(a: float) -> float:
    return float(np.mod(a, 2 * np.pi))


def _angle_diff(a: float, b: float) -> float:
    d = np.mod(a - b + np.pi, 2 * np.pi) - np.pi
    return float(abs(d))


# --- object-object --------------------------------------------------------------------------


def place_tables_joined(
    rng, table: PlacedObject, new_id: int
) -> tuple[PlacedObject, Relation] | None:
    """A second rectangular table of the same height, edge to edge with `table`."""
    if table.kind != "table_rect":
        return None
    a = table.model()
    variant = int(rng.integers(furniture.N_VARIANTS))
    b = furniture.model("table_rect", variant, table.height)
    turn = float(rng.choice([0.0, np.pi / 2]))
    ex, ey = (b.size_x, b.size_y) if turn == 0.0 else (b.size_y, b.size_x)
    along_x = bool(rng.random() < 0.5)
    sign = float(rng.choice([-1.0, 1.0]))
    if along_x:
        slack = abs(a.size_y - ey) / 2
        local = (sign * (a.size_x + ex) / 2, rng.uniform(-slack, slack))
    else:
        slack = abs(a.size_x - ex) / 2
        local = (rng.uniform(-slack, slack), sign * (a.size_y + ey) / 2)
    x, y = table.to_world(np.array(local))
    obj = PlacedObject(
        new_id,
        "table_rect",
        variant,
        table.height,
        float(x),
        float(y),
        0.0,
        _wrap(table.yaw + turn),
    )
    return obj, Relation("tables_joined", new_id, table.id, {"axis": "x" if along_x else "y"})


def check_tables_joined(scene: Scene, rel: Relation) -> bool:
    """Two equally tall rectangular tables, a multiple of 90 degrees apart, meeting edge to edge."""
    b, a = scene.object(rel.subject), scene.object(rel.object)
    if a.kind != "table_rect" or b.kind != "table_rect" or abs(a.height - b.height) > 1e-6:
        return False
    turn = np.mod(b.yaw - a.yaw, np.pi / 2)
    if min(turn, np.pi / 2 - turn) > 1e-6:
        return False
    am, bm = a.model(), b.model()
    quarter = round(float(np.mod(b.yaw - a.yaw, np.pi)) / (np.pi / 2)) % 2
    ex, ey = (bm.size_x, bm.size_y) if quarter == 0 else (bm.size_y, bm.size_x)
    lx, ly = a.to_local(np.array([b.x, b.y]))
    tol = 1e-3
    on_x = abs(abs(lx) - (am.size_x + ex) / 2) < tol and abs(ly) <= abs(am.size_y - ey) / 2 + tol
    on_y = abs(abs(ly) - (am.size_y + ey) / 2) < tol and abs(lx) <= abs(am.size_x - ex) / 2 + tol
    return bool(on_x or on_y)


def place_storage_under_table(
    rng, table: PlacedObject, new_id: int, h_range
) -> tuple[PlacedObject, Relation] | None:
    """A storage unit slid under a rectangular table between its legs, half to fully covered."""
    if table.kind != "table_rect":
        return None
    t = table.model()
    underside = t.features["underside_z"]
    hi = min(h_range[1], underside - 0.01)
    if hi < h_range[0]:
        return None
    kind = str(rng.choice(furniture.KINDS_OF["storage"]))
    inner = t.size_x / 2 - t.features["leg_inset"]
    fits = [
        v
        for v in range(furniture.N_VARIANTS)
        if furniture.model(kind, v, h_range[0]).size_y / 2 + 0.01 <= inner
    ]
    if not fits:
        return None
    variant = int(rng.choice(fits))
    height = furniture.quantize_height(rng.uniform(h_range[0], hi))
    if height > underside - 0.01:
        height = furniture.quantize_height(height - furniture.HEIGHT_STEP_M)
    s = furniture.model(kind, variant, height)
    side = (
        -1.0 if table.variant % 2 == 1 else float(rng.choice([-1.0, 1.0]))
    )  # a modesty panel closes +y
    frac = rng.uniform(0.5, 1.0)
    covered = min(frac * s.size_x, t.size_y - 0.04)
    yc = side * (t.size_y / 2 + (s.size_x - covered) - s.size_x / 2)
    lim = inner - s.size_y / 2 - 0.01
    xc = rng.uniform(-lim, lim)
    x, y = table.to_world(np.array([xc, yc]))
    yaw = _wrap(table.yaw + side * np.pi / 2)  # its front (+x) faces out of the table's side
    obj = PlacedObject(new_id, kind, variant, height, float(x), float(y), 0.0, yaw)
    return obj, Relation(
        "storage_under_table", new_id, table.id, {"covered": float(covered / s.size_x)}
    )


def check_storage_under_table(scene: Scene, rel: Relation) -> bool:
    """Storage across a rect table, below its underside, at least half under it, inside the legs."""
    s, t = scene.object(rel.subject), scene.object(rel.object)
    if s.cls != "storage" or t.kind != "table_rect":
        return False
    tm = t.model()
    if s.height > tm.features["underside_z"] - 0.01 + 1e-9:
        return False
    if abs(_angle_diff(s.yaw, t.yaw) - np.pi / 2) > 1e-6:
        return False
    fp = s.footprint()
    covered = polygon_area(clip_convex(fp, t.footprint())) / polygon_area(fp)
    if covered < 0.5 - 1e-6:
        return False
    local = t.to_local(fp)
    inner = tm.size_x / 2 - tm.features["leg_inset"]
    return bool(np.all(np.abs(local[:, 0]) <= inner + 1e-6))


def _chair_max_under(chair: furniture.FurnitureModel, underside: float) -> float:
    """How far (m) a chair's front can go under a table top whose underside is at `underside`."""
    f = chair.features
    limit = chair.size_x - 0.02
    if chair.height >= underside - 0.01:  # the backrest stays out, 2 cm clear of the edge
        limit = min(limit, chair.size_x / 2 - f["seat_back_x"] - 0.02)
    if f["armrest_z"] is not None and f["armrest_z"] >= underside - 0.01:
        limit = min(limit, chair.size_x / 2 - 0.38 * chair.size_x - 0.01)
    return limit


def place_chair_under_table(
    rng, table: PlacedObject, new_id: int, h_range
) -> tuple[PlacedObject, Relation] | None:
    """A chair facing a table with the front of its seat `under` metres beneath the top."""
    t = table.model()
    kind = str(rng.choice(furniture.KINDS_OF["chair"]))
    variant = int(rng.integers(furniture.N_VARIANTS))
    height = furniture.quantize_height(rng.uniform(*h_range))
    c = furniture.model(kind, variant, height)
    max_under = _chair_max_under(c, t.features["underside_z"])
    if table.kind == "table_rect":
        sides = [((1.0, 0.0), t.size_x / 2, t.size_y / 2), ((-1.0, 0.0), t.size_x / 2, t.size_y / 2),
                 ((0.0, 1.0), t.size_y / 2, t.size_x / 2), ((0.0, -1.0), t.size_y / 2, t.size_x / 2)]  # fmt: skip
        weights = np.array([s[2] for s in sides])
        n, dist, half_len = sides[int(rng.choice(4, p=weights / weights.sum()))]
        lat_lim = half_len - t.features["leg_inset"] - c.size_y / 2 - 0.02
        if lat_lim < 0:
            return None
        lat = rng.uniform(-lat_lim, lat_lim)
        n = np.array(n)
        tangent = np.array([-n[1], n[0]])
    else:
        r = t.features["radius"]
        if table.variant % 2 == 0:  # pedestal: any angle, keep clear of the foot disc
            a = rng.uniform(0, 2 * np.pi)
        else:  # legs at 45 degrees: come in between them
            a = rng.integers(4) * np.pi / 2
        max_under = min(max_under, 0.4 * r)
        n = np.array([np.cos(a), np.sin(a)])
        tangent = np.array([-n[1], n[0]])
        dist, lat = r, 0.0
    if max_under < 0.03:
        return None
    under = rng.uniform(0.03, max_under)
    local = n * (dist + c.size_x / 2 - under) + tangent * lat
    x, y = table.to_world(local)
    yaw = _wrap(table.yaw + np.arctan2(-n[1], -n[0]))
    obj = PlacedObject(new_id, kind, variant, height, float(x), float(y), 0.0, yaw)
    return obj, Relation("chair_under_table", new_id, table.id, {"under": float(under)})


def check_chair_under_table(scene: Scene, rel: Relation) -> bool:
    """The chair faces the table, its seat front under the top; a tall backrest stays out."""
    c, t = scene.object(rel.subject), scene.object(rel.object)
    if c.cls != "chair" or t.cls != "table":
        return False
    cm, tm = c.model(), t.model()
    tfp = t.footprint()
    under = float(rel.params.get("under", 0.0))
    front = c.to_world(np.array([cm.size_x / 2 - under / 2, 0.0]))
    if not points_in_convex(front, tfp):  # the front of the seat is under the top
        return False
    if c.height >= tm.features["underside_z"] - 0.01:  # then the backrest must stay out
        back = c.to_world(np.array([[-cm.size_x / 2, -cm.size_y / 2 + 0.03], [-cm.size_x / 2, cm.size_y / 2 - 0.03],
                                    [cm.features["back_x"], 0.0]]))  # fmt: skip
        if np.any(points_in_convex(back, tfp, margin=1e-4)):
            return False
    # it faces the table: its forward axis points at the table's centre side
    fwd = np.array([np.cos(c.yaw), np.sin(c.yaw)])
    to_table = np.array([t.x - c.x, t.y - c.y])
    return bool(fwd @ to_table > 0)


def place_plant_on_table(
    rng, table: PlacedObject, new_id: int, h_range
) -> tuple[PlacedObject, Relation] | None:
    """A potted plant standing on the table top, clear of its edge."""
    t = table.model()
    kind = str(rng.choice(furniture.KINDS_OF["plant"]))
    variant = int(rng.integers(furniture.N_VARIANTS))
    height = furniture.quantize_height(rng.uniform(*h_range))
    p = furniture.model(kind, variant, height)
    r = p.size_x / 2 + 0.02
    if table.kind == "table_rect":
        lx, ly = t.size_x / 2 - r, t.size_y / 2 - r
        if lx < 0 or ly < 0:
            return None
        local = np.array([rng.uniform(-lx, lx), rng.uniform(-ly, ly)])
    else:
        rr = t.features["radius"] - r
        if rr < 0:
            return None
        a, d = rng.uniform(0, 2 * np.pi), rr * np.sqrt(rng.uniform())
        local = np.array([d * np.cos(a), d * np.sin(a)])
    x, y = table.to_world(local)
    obj = PlacedObject(
        new_id,
        kind,
        variant,
        height,
        float(x),
        float(y),
        table.height,
        rng.uniform(0, 2 * np.pi),
        table.id,
    )
    return obj, Relation("plant_on_table", new_id, table.id, {})


def check_plant_on_table(scene: Scene, rel: Relation) -> bool:
    """The plant stands on the table (support and height), its footprint wholly on the top."""
    p, t = scene.object(rel.subject), scene.object(rel.object)
    if p.cls != "plant" or t.cls != "table" or p.support != t.id:
        return False
    if abs(p.z - t.height) > 1e-9:
        return False
    return bool(np.all(points_in_convex(p.footprint(), t.footprint())))


# --- human-object ---------------------------------------------------------------------------


def stand_z(pose: humanoid.Pose, scale: float) -> float:
    """Base height that puts the lowest point of the posed body on the floor."""
    prims = humanoid.posed_primitives(
        pose, scale, (0.0, 0.0, 0.0), humanoid.base_quat(pose.tilt, 0.0)
    )
    lo, _ = humanoid.prims_z_range(prims)
    return -lo


def body_front(pose: humanoid.Pose, scale: float, base_z: float, below_z: float = np.inf) -> float:
    """How far (m) the torso, head and legs reach ahead of the base (human at the origin, yaw 0).

    Only parts that reach below `below_z` count: a trunk leaning over a table top may pass
    its edge, the legs may not.
    """
    prims = humanoid.posed_primitives(
        pose, scale, (0.0, 0.0, base_z), humanoid.base_quat(pose.tilt, 0.0)
    )
    front = 0.0
    for k, s, c, r, lab in zip(
        prims.kind, prims.size, prims.center, prims.rot, prims.label, strict=True
    ):
        lo, hi = aabb(int(k), s, c, r)
        if lab in (L.BODY, L.HEAD, L.LEGS) and lo[2] < below_z:
            front = max(front, float(hi[0]))
    return front


LEANS_DEG = (0, 8, 16, 24, 32, 40, 48, 56)


#: the most a relation leans the trunk (degrees from upright, the pose's own bend included)
MAX_TRUNK_TILT_DEG = 75.0
#: how much of the drawn gap to the furniture is kept, tried in turn at each lean
GAP_SCALES = (1.0, 0.4, 0.0)


def lean_to_reach(pose, scale, top_z, hands, target_of):
    """Step closer, then lean the trunk forward, until every hand in `hands` reaches its target.

    `target_of(front, shoulder, side, k)` gives a hand's target in the human's frame from the
    body's front (see body_front), the shoulder's position and the share k of the drawn gap
    kept. Returns (pose, base_z, front, k) or None when no allowed lean reaches.
    """
    index = humanoid.load_model().index
    chest0 = pose.joints["chest"]
    for bend in LEANS_DEG:
        p = pose.copy()
        p.joints["chest"] = list(quat_mul(humanoid.trunk_quat(bend), chest0))
        z0 = stand_z(p, scale)
        pos, rot = humanoid.link_frames(p, scale, (0.0, 0.0, z0), humanoid.base_quat(p.tilt, 0.0))
        up = rot[index["chest"]] @ np.array([0.0, 1.0, 0.0])
        if np.degrees(np.arccos(np.clip(up[2], -1.0, 1.0))) > MAX_TRUNK_TILT_DEG:
            return None
        front = body_front(p, scale, z0, below_z=top_z + 0.02)
        for k in GAP_SCALES:
            q = p.copy()
            if all(
                _reach_local(q, scale, z0, s, target_of(front, pos[index[f"{s}_shoulder"]], s, k))
                for s in hands
            ):
                return q, z0, front, k
    return None


def _human(
    height, pose_name, pose, source, local_xy, base_z, frame: PlacedObject, yaw_local: float
) -> PlacedHuman:
    x, y = frame.to_world(np.asarray(local_xy, np.float64))
    return PlacedHuman(
        height,
        pose_name,
        pose,
        source,
        float(x),
        float(y),
        float(base_z),
        _wrap(frame.yaw + yaw_local),
    )


def _reach_local(pose, scale, base_z, side, target_local) -> bool:
    return humanoid.reach(
        pose, scale, (0.0, 0.0, base_z), humanoid.base_quat(pose.tilt, 0.0), side, target_local
    )


def _hands(rng) -> tuple[str, ...]:
    u = rng.random()
    return ("right", "left") if u < 0.4 else ("right",) if u < 0.7 else ("left",)


def _check_hands(scene: Scene, rel: Relation, z_top: float, inside) -> bool:
    h = scene.human
    hr = humanoid.limb_lengths(h.scale)["hand_radius"]
    for side in rel.params.get("hands", []):
        w = humanoid.wrist_position(h.pose, h.scale, h.base_pos, h.base_quat, side)
        if abs(w[2] - (z_top + hr)) > HAND_TOL_M or not inside(w[:2]):
            return False
    return True


def place_hand_on_table(
    rng, table: PlacedObject, height, pose_name, pose, source
) -> tuple[PlacedHuman, Relation] | None:
    """The human at the table's edge, facing it, with one or both hands on the top."""
    scale = humanoid.scale_for_height(height)
    t = table.model()
    hr = humanoid.limb_lengths(scale)["hand_radius"]
    if table.kind == "table_rect":
        k = int(rng.integers(4))
        n = np.array([(1, 0), (-1, 0), (0, 1), (0, -1)][k], np.float64)
        dist = t.size_x / 2 if k < 2 else t.size_y / 2
        half_len = t.size_y / 2 if k < 2 else t.size_x / 2
    else:
        a = rng.uniform(0, 2 * np.pi)
        n = np.array([np.cos(a), np.sin(a)])
        dist, half_len = t.features["radius"], 0.15
    tangent = np.array([-n[1], n[0]])
    hands = _hands(rng)
    gap = rng.uniform(0.02, 0.12)
    inset = {s: rng.uniform(0.05, 0.25) for s in hands}
    side_off = {s: rng.uniform(-0.08, 0.04) for s in hands}

    def target_of(front, shoulder, side, k):
        return np.array(
            [front + k * gap + inset[side], shoulder[1] * (1 - side_off[side]), table.height + hr]
        )

    res = lean_to_reach(pose, scale, table.height, hands, target_of)
    if res is None:
        return None
    p, z0, front, k = res
    # human frame -> table frame: the human faces -n from `front + gap` metres outside the edge
    lat = rng.uniform(-max(0.0, half_len - 0.25), max(0.0, half_len - 0.25))
    origin_t = n * (dist + front + k * gap) + tangent * lat
    human = _human(
        height, pose_name, p, source, origin_t, z0, table, float(np.arctan2(-n[1], -n[0]))
    )
    rel = Relation("hand_on_table", HUMAN, table.id, {"hands": list(hands)})
    probe = Scene("modeled", "", (0, 0), (0, 0), 0, 0, [table], human, [])
    return (human, rel) if check_hand_on_table(probe, rel) else None


def check_hand_on_table(scene: Scene, rel: Relation) -> bool:
    """Every hand of the relation rests on the table top (wrist at top + hand radius, inside it)."""
    t = scene.object(rel.object)
    if t.cls != "table" or scene.human is None or not rel.params.get("hands"):
        return False
    fp = t.footprint()
    return _check_hands(scene, rel, t.height, lambda xy: points_in_convex(xy, fp))


def place_holding_chair_back(
    rng, chair: PlacedObject, height, pose_name, pose, source
) -> tuple[PlacedHuman, Relation] | None:
    """The human behind a chair, facing the way it faces, hands on top of the backrest."""
    scale = humanoid.scale_for_height(height)
    c = chair.model()
    hr = humanoid.limb_lengths(scale)["hand_radius"]
    back_t = 2 * (c.features["back_x"] + c.size_x / 2)
    hands = _hands(rng)
    gap = rng.uniform(0.03, 0.12)
    ys = {
        s: (-1.0 if s == "right" else 1.0) * rng.uniform(0.04, c.size_y / 2 - 0.04) for s in hands
    }

    def target_of(front, shoulder, side, k):
        return np.array([front + k * gap + back_t / 2, ys[side], chair.height + hr])

    res = lean_to_reach(pose, scale, chair.height, hands, target_of)
    if res is None:
        return None
    p, z0, front, k = res
    origin_c = np.array([c.features["back_x"] - back_t / 2 - k * gap - front, 0.0])
    human = _human(height, pose_name, p, source, origin_c, z0, chair, 0.0)
    rel = Relation("holding_chair_back", HUMAN, chair.id, {"hands": list(hands)})
    probe = Scene("modeled", "", (0, 0), (0, 0), 0, 0, [chair], human, [])
    return (human, rel) if check_holding_chair_back(probe, rel) else None


def check_holding_chair_back(scene: Scene, rel: Relation) -> bool:
    """Every hand of the relation rests on top of the chair's backrest."""
    c = scene.object(rel.object)
    if c.cls != "chair" or scene.human is None or not rel.params.get("hands"):
        return False
    cm = c.model()
    back_t = 2 * (cm.features["back_x"] + cm.size_x / 2)
    hr = humanoid.limb_lengths(scene.human.scale)["hand_radius"]

    def on_back(xy):
        lx, ly = c.to_local(xy)
        return abs(lx - cm.features["back_x"]) <= back_t / 2 + hr and abs(ly) <= cm.size_y / 2

    return _check_hands(scene, rel, c.height, on_back)


def place_standing_by_storage(
    rng, storage: PlacedObject, height, pose_name, pose, source
) -> tuple[PlacedHuman, Relation] | None:
    """The human in front of a storage unit, facing it, sometimes with a hand on its top."""
    scale = humanoid.scale_for_height(height)
    s = storage.model()
    hr = humanoid.limb_lengths(scale)["hand_radius"]
    hands: tuple[str, ...] = ()
    if pose_name in ("standing", "working") and rng.random() < 0.6:
        hands = (str(rng.choice(["right", "left"])),)
    gap = rng.uniform(0.03, 0.15) if hands else rng.uniform(0.05, 0.45)
    inset = rng.uniform(0.05, max(0.06, min(0.2, s.size_x - 0.05)))

    def target_of(front, shoulder, side, k):
        return np.array([front + k * gap + inset, shoulder[1] * 0.8, storage.height + hr])

    if hands:
        res = lean_to_reach(pose, scale, storage.height, hands, target_of)
        if res is None:
            return None
        p, z0, front, k = res
    else:
        p, k = pose.copy(), 1.0
        z0 = stand_z(p, scale)
        front = body_front(p, scale, z0)
    lat = rng.uniform(-max(0.0, s.size_y / 2 - 0.2), max(0.0, s.size_y / 2 - 0.2))
    origin_s = np.array([s.size_x / 2 + k * gap + front, lat])
    human = _human(height, pose_name, p, source, origin_s, z0, storage, np.pi)
    rel = Relation(
        "standing_by_storage", HUMAN, storage.id, {"hands": list(hands), "gap": float(k * gap)}
    )
    probe = Scene("modeled", "", (0, 0), (0, 0), 0, 0, [storage], human, [])
    return (human, rel) if check_standing_by_storage(probe, rel) else None


def check_standing_by_storage(scene: Scene, rel: Relation) -> bool:
    """The human faces the storage from within 1 m of its front; any hands rest on its top."""
    s, h = scene.object(rel.object), scene.human
    if s.cls != "storage" or h is None:
        return False
    if _angle_diff(h.yaw, s.yaw + np.pi) > 1e-6:
        return False
    lx, _ = s.to_local(np.array([h.x, h.y]))
    sm = s.model()
    if not (sm.size_x / 2 < lx < sm.size_x / 2 + 1.0):
        return False
    fp = s.footprint()
    return _check_hands(scene, rel, s.height, lambda xy: points_in_convex(xy, fp))


def place_sitting_on_chair(
    rng, chair: PlacedObject, height, pose, source
) -> tuple[PlacedHuman, Relation]:
    """The human on the chair's seat, facing its front, hips at seat height."""
    scale = humanoid.scale_for_height(height)
    c = chair.model()
    lim = humanoid.limb_lengths(scale)
    hip_z = c.features["seat_z"] + lim["thigh_radius"]
    p = pose.copy()
    humanoid.sitting_legs(p, scale, hip_z)
    x = c.features["seat_back_x"] + lim["pelvis_radius"] + rng.uniform(0.0, 0.04)
    human = _human(
        height, "sitting", p, source, np.array([x, rng.uniform(-0.02, 0.02)]), hip_z, chair, 0.0
    )
    return human, Relation("sitting_on_chair", HUMAN, chair.id, {})


def check_sitting_on_chair(scene: Scene, rel: Relation) -> bool:
    """A sitting human facing the chair's way with both hips on its seat, over its footprint."""
    c, h = scene.object(rel.object), scene.human
    if c.cls != "chair" or h is None or h.pose_name != "sitting":
        return False
    if _angle_diff(h.yaw, c.yaw) > 1e-6:
        return False
    cm = c.model()
    lim = humanoid.limb_lengths(h.scale)
    hips = [
        humanoid.hip_position(h.pose, h.scale, h.base_pos, h.base_quat, s)
        for s in ("right", "left")
    ]
    if any(abs(hp[2] - (cm.features["seat_z"] + lim["thigh_radius"])) > HIP_TOL_M for hp in hips):
        return False
    mid = (hips[0] + hips[1]) / 2
    return bool(points_in_convex(mid[:2], c.footprint()))


def place_sitting_at_table(rng, scene: Scene, table: PlacedObject) -> Relation:
    """A seated human at a table: hands on the top when the arms reach it."""
    h = scene.human
    hr = humanoid.limb_lengths(h.scale)["hand_radius"]
    hands = []
    for side in _hands(rng):
        p = h.pose.copy()
        w = humanoid.wrist_position(p, h.scale, h.base_pos, h.base_quat, side)
        fwd = np.array([np.cos(h.yaw), np.sin(h.yaw)])
        fp = table.footprint()
        # walk forward from the current hand until the point is on the table top
        for step in np.arange(0.0, 0.6, 0.03):
            xy = w[:2] + fwd * step
            if points_in_convex(xy, fp, margin=hr + 0.02):
                target = np.array([xy[0], xy[1], table.height + hr])
                if humanoid.reach(p, h.scale, h.base_pos, h.base_quat, side, target):
                    h.pose = p
                    hands.append(side)
                break
    return Relation("sitting_at_table", HUMAN, table.id, {"hands": hands})


def check_sitting_at_table(scene: Scene, rel: Relation) -> bool:
    """The human sits on a chair that is under this table; any hands rest on the top."""
    t = scene.object(rel.object)
    seats = [r for r in scene.relations if r.kind == "sitting_on_chair"]
    if not seats or not any(
        r.kind == "chair_under_table" and r.subject == seats[0].object and r.object == t.id
        for r in scene.relations
    ):
        return False
    fp = t.footprint()
    return _check_hands(scene, rel, t.height, lambda xy: points_in_convex(xy, fp))


CHECKS = {
    "tables_joined": check_tables_joined,
    "storage_under_table": check_storage_under_table,
    "chair_under_table": check_chair_under_table,
    "plant_on_table": check_plant_on_table,
    "sitting_on_chair": check_sitting_on_chair,
    "sitting_at_table": check_sitting_at_table,
    "hand_on_table": check_hand_on_table,
    "holding_chair_back": check_holding_chair_back,
    "standing_by_storage": check_standing_by_storage,
}


def holds(scene: Scene, rel: Relation) -> bool:
    """Whether relation `rel` is geometrically true in `scene`."""
    check = CHECKS.get(rel.kind)
    if check is None:
        return False
    try:
        return bool(check(scene, rel))
    except KeyError:  # it names an object the scene does not have
        return False


__all__ = [
    "CHECKS",
    "HO_POSES",
    "HO_RELATIONS",
    "OO_RELATIONS",
    "STACKING",
    "holds",
    "overlap_fraction",
]
