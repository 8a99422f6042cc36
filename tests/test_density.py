"""The density function: its factors carry the paper's ranges, every sample lies in its support,
and scenes pushed outside a factor's range score -inf."""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest

from topseg.core.errors import TopsegError
from topseg.core.synth import furniture, humanoid, rooms
from topseg.core.synth.density import FACTORS, DensityConfig, DensityFunction
from topseg.core.synth.geometry import overlap_fraction
from topseg.core.synth.scene import HUMAN, Scene


@pytest.fixture(scope="module")
def modeled_scenes():
    d = DensityFunction()
    rng = np.random.default_rng(123)
    return d, [d.sample(rng) for _ in range(40)]


@pytest.fixture(scope="module")
def baseline_scenes():
    d = DensityFunction(mode="non-modeled")
    rng = np.random.default_rng(321)
    return d, [d.sample(rng) for _ in range(40)]


def test_factors_carry_the_papers_ranges():
    d = DensityFunction()
    assert (d.human_height.low, d.human_height.high) == (1.60, 1.90)
    for cls in ("table", "chair", "storage"):
        assert (d.object_height[cls].low, d.object_height[cls].high) == (0.70, 0.90)
    assert (d.object_height["plant"].low, d.object_height["plant"].high) == (0.15, 0.35)
    assert (d.theta_ho.low, d.theta_ho.high) == (0.0, 0.30)
    assert (d.theta_oo.low, d.theta_oo.high) == (0.0, 0.30)
    assert (d.orientation.low, d.orientation.high) == (0.0, 2 * math.pi)
    paper_poses = {"sitting", "standing", "stretching", "walking", "working", "dancing", "bending",
                   "bowing", "swinging", "boxing", "tilting"}  # fmt: skip
    assert paper_poses <= set(d.pose.choices)
    assert len(rooms.ROOMS) >= 4
    assert set(FACTORS) == {
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
    }


def test_every_sample_lies_in_the_support(modeled_scenes, baseline_scenes):
    for d, scenes in (modeled_scenes, baseline_scenes):
        for s in scenes:
            f = d.log_factors(s)
            assert all(math.isfinite(v) for v in f.values()), (d.mode, f)
            assert d.log_density(s) == pytest.approx(sum(f.values()))


def test_samples_respect_the_ranges(modeled_scenes):
    d, scenes = modeled_scenes
    for s in scenes:
        assert 0.0 <= s.theta_oo <= 0.30 and 0.0 <= s.theta_ho <= 0.30
        assert s.human is not None and 1.60 <= s.human.height <= 1.90
        for o in s.objects:
            lo, hi = d.config.object_height_m[o.cls]
            assert lo <= o.height <= hi
            assert 0.0 <= o.yaw < 2 * math.pi
        # items stand with their centre on the floor the camera sees; footprints may reach
        # a margin past it where there is no wall
        lo, hi = rooms.get(s.room).floor()
        assert (tuple(lo), tuple(hi)) == (s.floor_lo, s.floor_hi)
        assert s.bounds == tuple(tuple(c) for c in rooms.get(s.room).bounds())
        for x, y in [(o.x, o.y) for o in s.objects] + [(s.human.x, s.human.y)]:
            assert lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1]


def test_unrelated_overlaps_stay_within_theta(modeled_scenes):
    d, scenes = modeled_scenes
    checked = 0
    for s in scenes:
        for i, a in enumerate(s.objects):
            for b in s.objects[i + 1 :]:
                if d._stacked(s, a.id, b.id) or a.support == b.id or b.support == a.id:
                    continue
                assert overlap_fraction(a.footprint(), b.footprint()) <= s.theta_oo + 1e-9
                checked += 1
        exempt = d._ho_exempt(s)
        for o in s.objects:
            if o.id not in exempt:
                assert overlap_fraction(s.human.footprint(), o.footprint()) <= s.theta_ho + 1e-9
    assert checked > 20


def test_objects_rest_on_the_floor_or_their_support(modeled_scenes):
    _, scenes = modeled_scenes
    on_tables = 0
    for s in scenes:
        for o in s.objects:
            if o.support is None:
                assert o.z == 0.0
            else:
                table = s.object(o.support)
                assert table.cls == "table" and o.z == pytest.approx(table.height)
                on_tables += 1
        if (
            s.human.pose_name != "sitting"
        ):  # standing humans touch the floor with their lowest point
            lo, _ = humanoid.prims_z_range(s.human.primitives())
            assert abs(lo) < 1e-6
    assert on_tables > 0


def test_baseline_has_one_item_and_no_relations(baseline_scenes):
    _, scenes = baseline_scenes
    humans = 0
    for s in scenes:
        assert not s.relations
        assert len(s.objects) + (s.human is not None) == 1
        humans += s.human is not None
        if s.human is not None:
            assert s.human.pose_name != "sitting"
    assert 0 < humans < len(scenes)


def _first(scenes, pred):
    for s in scenes:
        if pred(s):
            return copy.deepcopy(s)
    raise AssertionError("no sampled scene matches")


def test_leaving_a_factors_range_gives_minus_infinity(modeled_scenes):
    d, scenes = modeled_scenes
    s = _first(scenes, lambda s: len(s.objects) >= 2)
    cases = {
        "H_h": lambda s: setattr(s.human, "height", 1.95),
        "O_h": lambda s: setattr(
            s.objects[0], "height", 0.95 if s.objects[0].cls != "plant" else 0.40
        ),
        "O_pos": lambda s: setattr(s.objects[0], "x", s.floor_hi[0] + 2.0),
        "O_ori": lambda s: setattr(s.objects[0], "yaw", -0.5),
        "H_ori": lambda s: setattr(s.human, "yaw", 7.0),
        "OO_theta": lambda s: setattr(s, "theta_oo", 0.31),
        "HO_theta": lambda s: setattr(s, "theta_ho", -0.01),
        "H_p": lambda s: setattr(s.human, "pose_name", "flying"),
    }
    for factor, edit in cases.items():
        bad = copy.deepcopy(s)
        edit(bad)
        f = d.log_factors(bad)
        assert f[factor] == -math.inf, factor
        assert d.log_density(bad) == -math.inf


def test_a_floating_object_or_human_leaves_the_support(modeled_scenes):
    d, scenes = modeled_scenes
    s = _first(scenes, lambda s: s.human.pose_name != "sitting")
    s.objects[0].z = 0.05 if s.objects[0].support is None else s.objects[0].z + 0.05
    assert d.log_factors(s)["O_pos"] == -math.inf
    s = _first(scenes, lambda s: s.human.pose_name != "sitting")
    s.human.z += 0.03
    assert d.log_factors(s)["H_pos"] == -math.inf


def test_overlapping_unrelated_objects_exceed_theta(modeled_scenes):
    d, scenes = modeled_scenes
    s = _first(scenes, lambda s: sum(o.support is None for o in s.objects) >= 2)
    free = [
        o
        for o in s.objects
        if o.support is None and not any(r.subject == o.id for r in s.relations)
    ]
    a = free[0]
    b = next(
        o for o in s.objects if o.id != a.id and o.support is None and not d._stacked(s, a.id, o.id)
    )
    a.x, a.y = b.x, b.y  # stacked on top of each other, no relation says so
    assert d.log_factors(s)["OO_theta"] == -math.inf


def test_breaking_a_relation_gives_minus_infinity(modeled_scenes):
    d, scenes = modeled_scenes
    s = _first(scenes, lambda s: any(r.kind == "plant_on_table" for r in s.relations))
    rel = next(r for r in s.relations if r.kind == "plant_on_table")
    plant, table = s.object(rel.subject), s.object(rel.object)
    plant.x, plant.y = table.x + 3.0, table.y  # off the table, still claiming it
    assert d.log_factors(s)["OO_rel"] == -math.inf or d.log_factors(s)["O_pos"] == -math.inf
    s = _first(scenes, lambda s: any(r.kind == "sitting_on_chair" for r in s.relations))
    s.human.z += 0.02  # hips above the seat
    assert d.log_factors(s)["HO_rel"] == -math.inf


def test_scenes_round_trip_through_json(modeled_scenes):
    d, scenes = modeled_scenes
    for s in scenes[:10]:
        text = json.dumps(s.to_dict())
        back = Scene.from_dict(json.loads(text))
        assert back.to_dict() == s.to_dict()
        assert d.log_density(back) == pytest.approx(d.log_density(s))


def test_same_seed_same_scene_and_rooms_can_be_fixed():
    d = DensityFunction(room="office")
    a = d.sample(np.random.default_rng(7)).to_dict()
    b = d.sample(np.random.default_rng(7)).to_dict()
    assert a == b and a["room"] == "office"
    assert DensityFunction().log_density(Scene.from_dict(a)) > -math.inf
    assert d.log_density(Scene.from_dict({**a, "room": "lab_corridor"})) == -math.inf


def test_config_round_trips_and_rejects_bad_values():
    c = DensityConfig(theta_max_oo=0.1, n_objects=(1, 2))
    assert DensityConfig.from_dict(json.loads(json.dumps(c.to_dict()))) == c
    with pytest.raises(TopsegError, match="theta_max_ho"):
        DensityConfig(theta_max_ho=1.5)
    with pytest.raises(TopsegError, match="human_height_m"):
        DensityConfig(human_height_m=(1.9, 1.6))
    with pytest.raises(TopsegError, match="unknown poses"):
        DensityConfig(pose_weights={"moonwalk": 1.0})
    with pytest.raises(TopsegError, match="unknown key"):
        DensityConfig.from_dict({"theta": 0.3})
    with pytest.raises(TopsegError, match="mode"):
        DensityFunction(mode="semi")
    with pytest.raises(TopsegError, match="room"):
        DensityFunction(room="kitchen")


def test_theta_max_zero_forbids_any_unrelated_overlap():
    d = DensityFunction(DensityConfig(theta_max_ho=0.0, theta_max_oo=0.0))
    rng = np.random.default_rng(5)
    for _ in range(5):
        s = d.sample(rng)
        assert s.theta_oo == 0.0 and s.theta_ho == 0.0
        assert d._worst_oo_overlap(s) <= 1e-9
        assert math.isfinite(d.log_density(s))


def test_furniture_has_two_kinds_per_class_and_exact_heights():
    for cls in ("chair", "table", "plant", "storage"):
        kinds = furniture.KINDS_OF[cls]
        assert len(kinds) == 2
        for kind in kinds:
            for variant in range(furniture.N_VARIANTS):
                h = 0.20 if cls == "plant" else 0.80
                m = furniture.model(kind, variant, h)
                assert m.cls == cls and m.top_z() == pytest.approx(h)
                assert min(p.pos[2] - p.size[0] if p.kind == 0 else 0.0 for p in m.parts) >= -1e-9


def test_room_templates_have_walls_inside_the_view():
    from topseg.core.camera import PAPER_MOUNT

    w, d = PAPER_MOUNT.floor_extent_m()
    lo, hi = rooms.get("industrial_workspace").floor()  # no walls: the floor is the view
    assert np.allclose((*lo, *hi), (-w / 2, -d / 2, w / 2, d / 2))
    blo, bhi = rooms.get("industrial_workspace").bounds()
    assert np.allclose(
        (*blo, *bhi),
        (
            -w / 2 - rooms.MARGIN_M,
            -d / 2 - rooms.MARGIN_M,
            w / 2 + rooms.MARGIN_M,
            d / 2 + rooms.MARGIN_M,
        ),
    )
    for name in rooms.ROOMS:
        t = rooms.get(name)
        lo, hi = t.floor()
        assert hi[0] - lo[0] > 2.0 and hi[1] - lo[1] > 1.5
        for side in t.walls:
            edge = {"north": hi[1], "south": -lo[1], "east": hi[0], "west": -lo[0]}[side]
            assert edge < (d if side in ("north", "south") else w) / 2  # the camera sees the wall
        assert len(t.wall_boxes()) == len(t.walls)
    assert HUMAN == "human"


def test_people_walk_in_and_out_of_view_with_full_headings():
    """With human_edge_share, free humans stand across the view's open edges (so the border
    cuts them), every such scene stays in the support, and headings cover [0, 360)."""
    import dataclasses

    from topseg.core.camera import PAPER_MOUNT
    from topseg.core.synth.density import HUMAN_EDGE_M, DensityConfig

    mount = dataclasses.replace(PAPER_MOUNT, pitch_deg=6.0, roll_deg=-8.0, height_mm=2600.0)
    d = DensityFunction(DensityConfig(human_edge_share=0.5), mode="non-modeled")
    rng = np.random.default_rng(11)
    scenes = [d.sample(rng, mount) for _ in range(150)]
    humans = [s for s in scenes if s.human is not None]
    outside = 0
    for s in humans:
        assert math.isfinite(d.log_density(s)) and s.mount == mount
        h = s.human
        lo, hi = np.array(s.floor_lo), np.array(s.floor_hi)
        if not (lo[0] <= h.x <= hi[0] and lo[1] <= h.y <= hi[1]):
            outside += 1
            assert np.all(np.array([h.x, h.y]) >= lo - HUMAN_EDGE_M - 1e-9)
            assert np.all(np.array([h.x, h.y]) <= hi + HUMAN_EDGE_M + 1e-9)
    assert 0.1 < outside / len(humans) < 0.5  # about half land on the band, half of them out
    yaws = np.degrees([s.human.yaw for s in humans])
    assert yaws.min() >= 0 and yaws.max() < 360 and np.histogram(yaws, 4, (0, 360))[0].min() > 5
    # the paper's density draws no edge humans and leaves their position factor as it was
    paper = DensityFunction(mode="non-modeled")
    s = next(x for x in (paper.sample(rng) for _ in range(20)) if x.human is not None)
    assert paper.log_factors(s)["H_pos"] == pytest.approx(-math.log(s.floor_area))
