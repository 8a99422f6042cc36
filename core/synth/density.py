"""The scene density function Phi(S) = Psi(H, O; theta) * Psi(O, O; theta) of Sharma et al. 2016.

Phi is a product of named factors, each the paper's:

| factor | what it scores | paper's value (default) |
|---|---|---|
| H_h | human height | U[160, 190] cm |
| H_p | pose | categorical over POSES |
| H_pos, O_pos | position on the floor, resting on floor or support | uniform, 1 / (w h); humans: a share `human_edge_share` on the band across the view's open edges (0, the paper) |
| H_ori, O_ori | heading about the vertical | U[0, 360) degrees |
| O_h | object height | table, chair, storage U[70, 90] cm; plant U[15, 35] cm |
| HO_theta, OO_theta | allowed footprint overlap theta and every unrelated pair within it | theta ~ U[0, theta'], theta' = 30 % |
| HO_rel, OO_rel | which relation placed each item, and that it holds | categorical; indicator |

`DensityFunction.sample(rng)` draws a scene (`topseg.core.synth.scene.Scene`) and
`log_density(scene)` scores one: the sum of the factors' logs, -inf outside the support.
Phi is unnormalised, like the paper's: the sampler is a sequential rejection sampler whose
scenes all lie in the support, with each factor's own range as configured. The object factors
appear in both of the paper's Psi terms; they are counted once here. Modes: "modeled" (a human
and several objects with relations) and "non-modeled" (the baseline: one object or one human
alone, no interactions).

The floor is what the frame's camera sees (`rooms.view_rect` of the mount passed to `sample`,
PAPER_MOUNT by default), so a scene follows a mount drawn per frame; the scene records it.
People walk in and out of view in real sequences: with `human_edge_share` > 0 a freely placed
human stands, that often, with its centre in the band `HUMAN_EDGE_M` either side of an open
(wall-less) edge of the view, so the image border cuts it.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from topseg.core import labels
from topseg.core.camera import PAPER_MOUNT, TopViewMount
from topseg.core.config import from_dict
from topseg.core.errors import TopsegError
from topseg.core.synth import furniture, humanoid, relations, rooms
from topseg.core.synth.cell_scenes import CellConfig, CellSampler
from topseg.core.synth.geometry import inside_rect, overlap_fraction
from topseg.core.synth.scene import HUMAN, PlacedHuman, PlacedObject, Relation, Scene

MODES = ("modeled", "non-modeled", "cell")
FACTORS = (
    "H_h",
    "H_p",
    "H_pos",
    "H_ori",
    "O_h",
    "O_pos",
    "O_ori",
    "HO_theta",
    "HO_rel",
    "OO_theta",
    "OO_rel",
)
#: object classes by label name, in the label table's order (the draw order of `rng.choice`)
CLASSES: tuple[str, ...] = tuple(labels.name_of(i) for i in labels.FURNITURE_IDS)
REST_TOL_M = 1e-3
#: half width (m) of the band across an open edge of the view where edge humans stand
HUMAN_EDGE_M = 0.4


@dataclass(frozen=True)
class Uniform:
    """A uniform factor on [low, high] (a point mass when they are equal)."""

    name: str
    low: float
    high: float

    def log_pdf(self, x: float) -> float:
        """-log(high - low) on [low, high] (0 for a point mass); -inf outside or non-finite."""
        if not (self.low <= x <= self.high) or not math.isfinite(x):
            return -math.inf
        return 0.0 if self.high == self.low else -math.log(self.high - self.low)

    def sample(self, rng: np.random.Generator) -> float:
        """One draw from [low, high] with `rng` (the only randomness, so scenes are seeded)."""
        return float(rng.uniform(self.low, self.high))


@dataclass(frozen=True)
class Categorical:
    """A categorical factor over named choices with non-negative weights."""

    name: str
    weights: tuple[tuple[str, float], ...]

    @property
    def choices(self) -> tuple[str, ...]:
        """The names with a positive weight: the support of the factor."""
        return tuple(k for k, w in self.weights if w > 0)

    def prob(self, k: str, among=None) -> float:
        """P(k), renormalised over the choices in `among` (all when None); 0 outside them."""
        ws = dict(self.weights)
        pool = [c for c in self.choices if among is None or c in among]
        total = sum(ws[c] for c in pool)
        return ws.get(k, 0.0) / total if k in pool and total > 0 else 0.0

    def log_pmf(self, k: str, among=None) -> float:
        """log `prob(k, among)`, -inf where that is 0."""
        p = self.prob(k, among)
        return math.log(p) if p > 0 else -math.inf

    def sample(self, rng: np.random.Generator, among=None) -> str:
        """A choice in `among` (all when None) drawn by weight; ValueError if none is left."""
        pool = [c for c in self.choices if among is None or c in among]
        if not pool:
            raise ValueError(f"{self.name}: nothing to choose from")
        ws = dict(self.weights)
        p = np.array([ws[c] for c in pool], np.float64)
        return pool[int(rng.choice(len(pool), p=p / p.sum()))]


def _uniform_weights(names) -> dict:
    return {n: 1.0 for n in names}


@dataclass
class DensityConfig:
    """Every range of the density function; the defaults are the paper's."""

    human_height_m: tuple[float, float] = (1.60, 1.90)
    object_height_m: dict = field(
        default_factory=lambda: {
            "table": (0.70, 0.90),
            "chair": (0.70, 0.90),
            "storage": (0.70, 0.90),
            "plant": (0.15, 0.35),
        }
    )
    theta_max_ho: float = 0.30
    theta_max_oo: float = 0.30
    pose_weights: dict = field(default_factory=lambda: _uniform_weights(humanoid.PAPER_POSES))
    #: H-O relation given a pose that allows it ("free" = no relation)
    ho_relation_weights: dict = field(
        default_factory=lambda: {
            "hand_on_table": 1.0,
            "holding_chair_back": 1.0,
            "standing_by_storage": 1.0,
            "free": 0.5,
        }
    )
    human_probability: dict = field(default_factory=lambda: {"modeled": 1.0, "non-modeled": 0.5})
    #: (min, max) objects per modeled scene; None = the room template's
    n_objects: tuple[int, int] | None = None
    max_tries: int = 40
    #: share of freely placed humans centred on the band across the view's open edges
    human_edge_share: float = 0.0
    #: robot cells: robots, cell objects, people and their relations (the "cell" mode)
    cell: CellConfig = field(default_factory=CellConfig)

    def __post_init__(self) -> None:
        self.human_height_m = tuple(float(v) for v in self.human_height_m)
        self.object_height_m = {
            k: tuple(float(x) for x in v) for k, v in self.object_height_m.items()
        }
        if self.n_objects is not None:
            self.n_objects = tuple(int(v) for v in self.n_objects)
        self.validate()

    def validate(self) -> None:
        """TopsegError naming the first range, weight or name out of bounds (run on creation)."""

        def rng_ok(name, lo_hi, lo_bound, hi_bound):
            lo, hi = lo_hi
            if not (lo_bound <= lo <= hi <= hi_bound):
                raise TopsegError(
                    f"density config: {name} must satisfy {lo_bound} <= low <= high <= {hi_bound}, got {lo_hi}"
                )

        rng_ok("human_height_m", self.human_height_m, 1.0, 2.3)
        if set(self.object_height_m) != set(CLASSES):
            raise TopsegError(
                f"density config: object_height_m needs exactly {CLASSES}, got {sorted(self.object_height_m)}"
            )
        for k, v in self.object_height_m.items():
            rng_ok(f"object_height_m[{k}]", v, 0.1, 2.0)
        for name in ("theta_max_ho", "theta_max_oo", "human_edge_share"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise TopsegError(f"density config: {name} is a fraction in [0, 1], got {v}")
        unknown = set(self.pose_weights) - set(humanoid.POSES)
        if unknown:
            raise TopsegError(
                f"density config: unknown poses {sorted(unknown)}; known: {', '.join(humanoid.POSES)}"
            )
        if any(w < 0 for w in self.pose_weights.values()) or sum(self.pose_weights.values()) <= 0:
            raise TopsegError("density config: pose weights must be >= 0 with a positive sum")
        unknown = (
            set(self.ho_relation_weights) - {*relations.HO_POSES, "free"} - {"sitting_on_chair"}
        )
        if unknown:
            raise TopsegError(f"density config: unknown H-O relations {sorted(unknown)}")
        if self.n_objects is not None and not (0 <= self.n_objects[0] <= self.n_objects[1] <= 20):
            raise TopsegError(
                f"density config: n_objects must be 0 <= min <= max <= 20, got {self.n_objects}"
            )

    def to_dict(self) -> dict:
        """Plain lists and dicts (TOML and JSON friendly) that `from_dict` turns back into this."""
        d = asdict(self)
        d["human_height_m"] = list(self.human_height_m)
        d["object_height_m"] = {k: list(v) for k, v in self.object_height_m.items()}
        d["n_objects"] = None if self.n_objects is None else list(self.n_objects)
        d["cell"] = self.cell.to_dict()
        return d

    @classmethod
    def from_dict(cls, d: dict, source: str = "density config") -> DensityConfig:
        """The config a `to_dict` mapping or a TOML table describes; an unknown or mistyped
        key is a ConfigError naming it."""
        return from_dict(cls, d, source)


class DensityFunction:
    """Phi(S) for one mode (and optionally one room); see the module doc for the factors."""

    def __init__(
        self,
        config: DensityConfig | None = None,
        mode: str = "modeled",
        room: str | None = None,
        mount: TopViewMount = PAPER_MOUNT,
    ) -> None:
        if mode not in MODES:
            raise TopsegError(f"unknown mode {mode!r}; choose one of {', '.join(MODES)}")
        if room is not None and room not in rooms.TEMPLATES:
            raise TopsegError(f"unknown room {room!r}; choose one of {', '.join(rooms.ROOMS)}")
        self.config = config or DensityConfig()
        self.mode = mode
        self.room = room
        self.mount = mount
        c = self.config
        self.human_height = Uniform("H_h", *c.human_height_m)
        self.object_height = {k: Uniform("O_h", *v) for k, v in c.object_height_m.items()}
        weights = dict(c.pose_weights)
        if mode == "non-modeled":  # a lone human has no chair to sit on
            weights.pop("sitting", None)
        self.pose = Categorical("H_p", tuple(weights.items()))
        self.orientation = Uniform("ori", 0.0, 2 * math.pi)
        self.theta_ho = Uniform("HO_theta", 0.0, c.theta_max_ho)
        self.theta_oo = Uniform("OO_theta", 0.0, c.theta_max_oo)
        self.ho_relation = Categorical("HO_rel", tuple(c.ho_relation_weights.items()))
        self.rooms = Categorical(
            "room", tuple((r, 1.0 if room in (None, r) else 0.0) for r in rooms.ROOMS)
        )
        self.cell = CellSampler(self, c.cell)

    # --- factors ------------------------------------------------------------------------

    def oo_relation(self, room: str) -> Categorical:
        """OO_rel: the object-object relation placing an object, weighted by `room`'s template."""
        return Categorical("OO_rel", tuple(rooms.get(room).oo_relation_weights.items()))

    def position_log_pdf(self, scene: Scene) -> float:
        """H_pos / O_pos: log 1 / (w h), uniform over the scene's floor."""
        return -math.log(scene.floor_area)

    def ho_candidates(self, pose_name: str) -> tuple[str, ...]:
        """H-O relations a pose can take part in ("free" always can)."""
        if pose_name == "sitting":
            return ("sitting_on_chair",)
        return (*(k for k, poses in relations.HO_POSES.items() if pose_name in poses), "free")

    def ho_relation_log_pmf(self, kind: str, pose_name: str) -> float:
        """HO_rel: log P(kind | pose) among the relations the pose allows (sitting: on a chair)."""
        cands = self.ho_candidates(pose_name)
        if pose_name == "sitting":
            return 0.0 if kind == "sitting_on_chair" else -math.inf
        return self.ho_relation.log_pmf(kind, among=cands)

    def log_factors(self, scene: Scene) -> dict[str, float]:
        """Each factor's log value for `scene` (-inf where the scene leaves its support)."""
        f = dict.fromkeys(FACTORS, 0.0)
        bad = dict.fromkeys(FACTORS, -math.inf)
        if (
            scene.mode != self.mode
            or scene.room not in rooms.TEMPLATES
            or self.rooms.prob(scene.room) == 0
        ):
            return bad
        tmpl = rooms.get(scene.room)
        mount = scene.mount or self.mount
        (lo, hi), (blo, bhi) = tmpl.floor(mount), tmpl.bounds(mount)
        expect = np.array((*lo, *hi, *blo, *bhi))
        got = np.array((*scene.floor_lo, *scene.floor_hi, *scene.bounds[0], *scene.bounds[1]))
        if np.max(np.abs(expect - got)) > 1e-6:
            return bad
        ids = [o.id for o in [*scene.objects, *scene.mesh_objects]] + [r.id for r in scene.robots]
        if len(set(ids)) != len(ids):
            return bad
        if self.mode == "cell":
            return {**self.cell.log_factors(scene), "room": 0.0}
        if scene.robots or scene.extra_humans or scene.mesh_objects:
            return bad
        objects = {o.id: o for o in scene.objects}

        # human: height, pose, position (resting), orientation
        h = scene.human
        if h is not None:
            f["H_h"] = self.human_height.log_pdf(h.height)
            f["H_p"] = self.pose.log_pmf(h.pose_name)
            f["H_ori"] = self.orientation.log_pdf(h.yaw)
            f["H_pos"] = self._human_position(scene, h)

        # objects: height, position (resting on floor or support), orientation
        for o in scene.objects:
            rng_h = self.object_height.get(o.cls)
            f["O_h"] += rng_h.log_pdf(o.height) if rng_h else -math.inf
            f["O_ori"] += self.orientation.log_pdf(o.yaw)
            f["O_pos"] += self._object_position(scene, o, objects)

        # theta: drawn within range, and every unrelated pair within it
        f["OO_theta"] = self.theta_oo.log_pdf(scene.theta_oo)
        f["HO_theta"] = self.theta_ho.log_pdf(scene.theta_ho)
        if f["OO_theta"] > -math.inf and self._worst_oo_overlap(scene) > scene.theta_oo + 1e-9:
            f["OO_theta"] = -math.inf
        if f["HO_theta"] > -math.inf and self._worst_ho_overlap(scene) > scene.theta_ho + 1e-9:
            f["HO_theta"] = -math.inf

        # relations: which placed each item, and that each holds
        f["OO_rel"], f["HO_rel"] = self._relations(scene)
        if self.mode == "non-modeled" and (
            scene.relations or len(scene.objects) + (h is not None) != 1
        ):
            f["OO_rel"] = f["HO_rel"] = -math.inf
        return f

    def log_density(self, scene: Scene) -> float:
        """log Phi(scene): the sum of the factors' logs; -inf outside the support."""
        return float(sum(self.log_factors(scene).values()))

    def _in_bounds(self, scene: Scene, poly: np.ndarray) -> bool:
        """A footprint within the walls (or the margin past the camera's view)."""
        return inside_rect(poly, *scene.bounds)

    def _on_floor(self, scene: Scene, x: float, y: float) -> bool:
        """A position (an item's centre) on the floor the camera sees."""
        return inside_rect(np.array([[x, y]]), scene.floor_lo, scene.floor_hi)

    def _edge_rects(self, scene: Scene):
        """(inner, outer, bounds) rectangles of the edge band: the view floor shrunk and grown
        by HUMAN_EDGE_M on its open sides (where bounds reach past the floor), and the bounds
        grown by it there; None without edge humans or open sides."""
        if self.config.human_edge_share <= 0:
            return None
        lo, hi = np.array(scene.floor_lo, float), np.array(scene.floor_hi, float)
        blo, bhi = (np.array(b, float) for b in scene.bounds)
        open_lo, open_hi = blo < lo - 1e-9, bhi > hi + 1e-9
        if not (open_lo.any() or open_hi.any()):
            return None
        e = HUMAN_EDGE_M
        inner = (lo + e * open_lo, hi - e * open_hi)
        outer = (lo - e * open_lo, hi + e * open_hi)
        bounds = (blo - e * open_lo, bhi + e * open_hi)
        return inner, outer, bounds

    def _human_pos_log_pdf(self, scene: Scene, x: float, y: float) -> float:
        """H_pos: uniform on the view floor, mixed with `human_edge_share` uniform on the band."""
        rects = self._edge_rects(scene)
        on_floor = self._on_floor(scene, x, y)
        if rects is None:
            return self.position_log_pdf(scene) if on_floor else -math.inf
        (ilo, ihi), (olo, ohi), _ = rects
        p = np.array([[x, y]])
        in_band = inside_rect(p, olo, ohi) and not inside_rect(p, ilo, ihi)
        band_area = float(np.prod(ohi - olo)) - float(np.prod(np.maximum(ihi - ilo, 0.0)))
        s = self.config.human_edge_share
        dens = (1 - s) / scene.floor_area * on_floor + (s / band_area if in_band else 0.0)
        return math.log(dens) if dens > 0 else -math.inf

    def _human_in_bounds(self, scene: Scene, poly: np.ndarray) -> bool:
        rects = self._edge_rects(scene)
        if rects is None:
            return self._in_bounds(scene, poly)
        return inside_rect(poly, *rects[2])

    def _edge_spot(self, rng, scene: Scene) -> tuple[float, float] | None:
        """A point uniform on the edge band (rejection from its outer rectangle)."""
        (ilo, ihi), (olo, ohi), _ = self._edge_rects(scene)
        for _ in range(200):
            x, y = float(rng.uniform(olo[0], ohi[0])), float(rng.uniform(olo[1], ohi[1]))
            if not inside_rect(np.array([[x, y]]), ilo, ihi):
                return x, y
        return None

    def _human_position(self, scene: Scene, h: PlacedHuman) -> float:
        pos = self._human_pos_log_pdf(scene, h.x, h.y)
        if pos == -math.inf or not self._human_in_bounds(scene, h.footprint(arms=True)):
            return -math.inf
        lo, _ = humanoid.prims_z_range(h.primitives())
        seated = any(r.kind == "sitting_on_chair" for r in scene.relations)
        if seated:  # resting on the seat (checked by its relation); the feet not below the floor
            if lo < -REST_TOL_M:
                return -math.inf
        elif abs(lo) > REST_TOL_M:  # standing: the lowest point on the floor
            return -math.inf
        return pos

    def _object_position(self, scene: Scene, o: PlacedObject, objects: dict) -> float:
        if not self._on_floor(scene, o.x, o.y) or not self._in_bounds(scene, o.footprint()):
            return -math.inf
        if o.support is None:
            if o.z != 0.0:
                return -math.inf
        else:
            s = objects.get(o.support)
            if s is None or s.cls != "table" or abs(o.z - s.height) > 1e-9 or s.support is not None:
                return -math.inf
        return self.position_log_pdf(scene)

    def _stacked(self, scene: Scene, a, b) -> bool:
        return any(r.kind in relations.STACKING for r in scene.related(a, b))

    def _worst_oo_overlap(self, scene: Scene) -> float:
        worst = 0.0
        objs = scene.objects
        fps = [o.footprint() for o in objs]
        for i in range(len(objs)):
            for j in range(i + 1, len(objs)):
                a, b = objs[i], objs[j]
                if self._stacked(scene, a.id, b.id) or a.support == b.id or b.support == a.id:
                    continue
                worst = max(worst, overlap_fraction(fps[i], fps[j]))
        return worst

    def _ho_exempt(self, scene: Scene) -> set:
        """Objects the human may overlap: those it is related to, and what stands on them."""
        related = {r.object for r in scene.relations if r.subject == HUMAN}
        return related | {o.id for o in scene.objects if o.support in related}

    def _worst_ho_overlap(self, scene: Scene) -> float:
        if scene.human is None:
            return 0.0
        exempt = self._ho_exempt(scene)
        hfp = scene.human.footprint()
        return max(
            [overlap_fraction(hfp, o.footprint()) for o in scene.objects if o.id not in exempt],
            default=0.0,
        )

    def _relations(self, scene: Scene) -> tuple[float, float]:
        oo, ho = 0.0, 0.0
        table = self.oo_relation(scene.room)
        for r in scene.relations:
            if r.kind in relations.OO_RELATIONS:
                if r.subject == HUMAN or r.object == HUMAN:
                    return -math.inf, -math.inf
            elif r.kind in relations.HO_RELATIONS:
                if r.subject != HUMAN or scene.human is None:
                    return -math.inf, -math.inf
            else:
                return -math.inf, -math.inf
            if not relations.holds(scene, r):
                return (-math.inf, ho) if r.kind in relations.OO_RELATIONS else (oo, -math.inf)
        for o in scene.objects:
            placed_by = [r for r in scene.relations if r.subject == o.id]
            if len(placed_by) > 1:
                return -math.inf, ho
            kind = placed_by[0].kind if placed_by else "free"
            oo += table.log_pmf(kind) if self.mode == "modeled" else 0.0
        if scene.human is not None:
            mine = [
                r for r in scene.relations if r.subject == HUMAN and r.kind != "sitting_at_table"
            ]
            if len(mine) > 1:
                return oo, -math.inf
            kind = mine[0].kind if mine else "free"
            if self.mode == "modeled":
                ho += self.ho_relation_log_pmf(kind, scene.human.pose_name)
            elif kind != "free":
                ho = -math.inf
            at_table = [r for r in scene.relations if r.kind == "sitting_at_table"]
            if len(at_table) > 1 or (at_table and kind != "sitting_on_chair"):
                ho = -math.inf
        return oo, ho

    # --- sampling -----------------------------------------------------------------------

    def sample(self, rng: np.random.Generator, mount: TopViewMount | None = None) -> Scene:
        """Draw one scene description seen from `mount` (this function's mount when None)."""
        for _ in range(self.config.max_tries):
            scene = self._sample_once(rng, mount or self.mount)
            if scene is not None:
                return scene
        raise TopsegError(
            f"could not place a scene in {self.config.max_tries} tries; loosen the density config "
            "(theta_max, n_objects) or choose a larger room"
        )

    def _new_scene(self, rng, mount: TopViewMount) -> Scene:
        room = self.rooms.sample(rng)
        tmpl = rooms.get(room)
        (lo, hi), (blo, bhi) = tmpl.floor(mount), tmpl.bounds(mount)
        theta_ho, theta_oo = self.theta_ho.sample(rng), self.theta_oo.sample(rng)
        return Scene(
            self.mode,
            room,
            tuple(lo),
            tuple(hi),
            theta_ho,
            theta_oo,
            bounds_lo=tuple(blo),
            bounds_hi=tuple(bhi),
            mount=mount,
        )

    def _sample_once(self, rng, mount: TopViewMount) -> Scene | None:
        scene = self._new_scene(rng, mount)
        if self.mode == "cell":
            return self.cell.sample_into(rng, scene)
        if self.mode == "non-modeled":
            if rng.random() < self.config.human_probability.get(self.mode, 1.0):
                return scene if self._add_human(rng, scene, free_only=True) else None
            cls = str(rng.choice(CLASSES))
            return scene if self._add_free_object(rng, scene, cls) is not None else None
        return self._fill_modeled(rng, scene)

    def _fill_modeled(self, rng, scene: Scene) -> Scene | None:
        """Fill the empty `scene` as the paper's modeled scenes are: objects by the room's
        template and relations, then the human; None when the human does not fit."""
        p_human = self.config.human_probability.get("modeled", 1.0)
        tmpl = rooms.get(scene.room)
        n_lo, n_hi = self.config.n_objects or tmpl.n_objects
        n = int(rng.integers(n_lo, n_hi + 1))
        oo = self.oo_relation(scene.room)
        classes = Categorical("class", tuple(tmpl.class_weights.items()))
        budget = 6 * max(n, 1)
        while len(scene.objects) < n and budget > 0:
            budget -= 1
            kind = oo.sample(rng)
            if kind == "free":
                self._add_free_object(rng, scene, classes.sample(rng))
            else:
                self._add_related_object(rng, scene, kind)
        if rng.random() < p_human and not self._add_human(rng, scene):
            return None
        return scene

    def _fits_object(self, scene: Scene, obj: PlacedObject, rel: Relation | None) -> bool:
        fp = obj.footprint()
        if not self._on_floor(scene, obj.x, obj.y) or not self._in_bounds(scene, fp):
            return False
        for o in [*scene.objects, *scene.mesh_objects]:
            if rel is not None and rel.object == o.id and rel.kind in relations.STACKING:
                continue
            if obj.support == o.id:
                continue
            if overlap_fraction(fp, o.footprint()) > scene.theta_oo:
                return False
        return True

    def _draw_object(self, rng, scene: Scene, cls: str, kinds=None) -> PlacedObject:
        kind = str(rng.choice(kinds or furniture.KINDS_OF[cls]))
        lo, hi = scene.floor_lo, scene.floor_hi
        return PlacedObject(
            scene.next_id(),
            kind,
            int(rng.integers(furniture.N_VARIANTS)),
            furniture.quantize_height(self.object_height[cls].sample(rng)),
            float(rng.uniform(lo[0], hi[0])),
            float(rng.uniform(lo[1], hi[1])),
            0.0,
            self.orientation.sample(rng),
        )

    def _add_free_object(self, rng, scene: Scene, cls: str, kinds=None) -> PlacedObject | None:
        for _ in range(self.config.max_tries):
            obj = self._draw_object(rng, scene, cls, kinds)
            if self._fits_object(scene, obj, None):
                scene.objects.append(obj)
                return obj
        return None

    def _anchor(
        self, rng, scene: Scene, kinds: tuple[str, ...], free_kinds=None
    ) -> PlacedObject | None:
        """An object of one of `kinds` standing on the floor, added freely when there is none."""
        pool = [o for o in scene.objects if o.kind in kinds and o.support is None]
        if pool:
            return pool[int(rng.integers(len(pool)))]
        cls = furniture.CLASS_OF_KIND[kinds[0]]
        return self._add_free_object(rng, scene, cls, kinds=free_kinds or kinds)

    def _add_related_object(self, rng, scene: Scene, kind: str) -> None:
        h_rng = self.config.object_height_m
        rect = ("table_rect",)
        tables = furniture.KINDS_OF["table"]
        for _ in range(4):
            anchor = self._anchor(
                rng, scene, rect if kind in ("tables_joined", "storage_under_table") else tables
            )
            if anchor is None:
                return
            new_id = scene.next_id()
            if kind == "tables_joined":
                res = relations.place_tables_joined(rng, anchor, new_id)
            elif kind == "storage_under_table":
                res = relations.place_storage_under_table(rng, anchor, new_id, h_rng["storage"])
            elif kind == "chair_under_table":
                res = relations.place_chair_under_table(rng, anchor, new_id, h_rng["chair"])
            else:
                res = relations.place_plant_on_table(rng, anchor, new_id, h_rng["plant"])
            if res is None:
                continue
            obj, rel = res
            if self._fits_object(scene, obj, rel) and (
                kind != "tables_joined"
                or self.object_height["table"].log_pdf(obj.height) > -math.inf
            ):
                scene.objects.append(obj)
                scene.relations.append(rel)
                return

    def _fits_human(self, scene: Scene, human: PlacedHuman, related: set) -> bool:
        fp = human.footprint()
        if self._human_pos_log_pdf(scene, human.x, human.y) == -math.inf or not (
            self._human_in_bounds(scene, human.footprint(arms=True))
        ):
            return False
        items = [*scene.objects, *scene.mesh_objects]
        exempt = related | {o.id for o in items if o.support in related}
        return all(
            overlap_fraction(fp, o.footprint()) <= scene.theta_ho
            for o in items
            if o.id not in exempt
        )

    def _add_human(self, rng, scene: Scene, free_only: bool = False) -> bool:
        for _ in range(self.config.max_tries):
            pose_name = self.pose.sample(rng)
            height = humanoid.quantize_height(self.human_height.sample(rng))
            pose, source = humanoid.sample_pose(pose_name, rng)
            if pose_name == "sitting":
                kind = "sitting_on_chair"
            else:
                kind = (
                    "free"
                    if free_only
                    else self.ho_relation.sample(rng, among=self.ho_candidates(pose_name))
                )
            n_before = len(scene.objects)
            placed = self._place_human(rng, scene, kind, pose_name, height, pose, source)
            if placed is not None:
                human, rels = placed
                if self._fits_human(scene, human, {r.object for r in rels}):
                    scene.human = human
                    scene.relations.extend(rels)
                    return True
            del scene.objects[n_before:]  # an anchor added for this try goes with it
        return False

    def _place_human(self, rng, scene: Scene, kind, pose_name, height, pose, source):
        if kind == "free":
            lo, hi = scene.floor_lo, scene.floor_hi
            z0 = relations.stand_z(pose, humanoid.scale_for_height(height))
            edge = self._edge_rects(scene) is not None and (
                rng.random() < self.config.human_edge_share
            )  # no draw at share 0: the paper's scenes stay as they were
            spot = self._edge_spot(rng, scene) if edge else None
            if spot is None:
                spot = float(rng.uniform(lo[0], hi[0])), float(rng.uniform(lo[1], hi[1]))
            human = PlacedHuman(
                height, pose_name, pose, source, *spot, z0, self.orientation.sample(rng),
            )  # fmt: skip
            return human, []
        need = {"sitting_on_chair": "chair", "holding_chair_back": "chair", "hand_on_table": "table",
                "standing_by_storage": "storage"}[kind]  # fmt: skip
        taken = (
            {r.object for r in scene.relations if r.kind in ("chair_under_table",)}
            if kind == "holding_chair_back"
            else set()
        )
        pool = [
            o for o in scene.objects if o.cls == need and o.support is None and o.id not in taken
        ]
        if not pool:
            anchor = self._add_free_object(rng, scene, need)
            if anchor is None:
                return None
        else:
            anchor = pool[int(rng.integers(len(pool)))]
        if kind == "sitting_on_chair":
            human, rel = relations.place_sitting_on_chair(rng, anchor, height, pose, source)
            rels = [rel]
            under = [
                r
                for r in scene.relations
                if r.kind == "chair_under_table" and r.subject == anchor.id
            ]
            if under:
                probe = Scene(
                    scene.mode,
                    scene.room,
                    scene.floor_lo,
                    scene.floor_hi,
                    0,
                    0,
                    scene.objects,
                    human,
                )
                rels.append(
                    relations.place_sitting_at_table(rng, probe, scene.object(under[0].object))
                )
            return human, rels
        place = {
            "hand_on_table": relations.place_hand_on_table,
            "holding_chair_back": relations.place_holding_chair_back,
            "standing_by_storage": relations.place_standing_by_storage,
        }[kind]
        res = place(rng, anchor, height, pose_name, pose, source)
        return None if res is None else (res[0], [res[1]])


__all__ = [
    "CLASSES",
    "FACTORS",
    "MODES",
    "Categorical",
    "DensityConfig",
    "DensityFunction",
    "Uniform",
]
