"""Each relation places its item where the relation says, and its check notices when it is broken."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from topseg.core.synth import furniture, humanoid, relations
from topseg.core.synth.density import DensityFunction
from topseg.core.synth.geometry import clip_convex, points_in_convex, polygon_area
from topseg.core.synth.scene import HUMAN, PlacedObject, Scene

H_CHAIR = (0.70, 0.90)
H_STORAGE = (0.70, 0.90)
H_PLANT = (0.15, 0.35)


def _scene(*objects, human=None, rels=()):
    return Scene("modeled", "office", (-5, -5), (5, 5), 0.3, 0.3, list(objects), human, list(rels))


def _table(kind="table_rect", variant=1, height=0.85, yaw=0.4):
    return PlacedObject(0, kind, variant, height, 0.2, -0.1, 0.0, yaw)


def _draws(n=12, seed=0):
    rng = np.random.default_rng(seed)
    return [np.random.default_rng(int(s)) for s in rng.integers(0, 2**31, n)]


def test_tables_joined_share_an_edge_and_a_height():
    table = _table()
    placed = 0
    for rng in _draws():
        obj, rel = relations.place_tables_joined(rng, table, 1)
        s = _scene(table, obj, rels=[rel])
        assert relations.holds(s, rel) and obj.height == table.height
        # edge to edge: touching, not overlapping
        inter = polygon_area(clip_convex(obj.footprint(), table.footprint()))
        assert inter < 1e-6
        placed += 1
        moved = copy.deepcopy(obj)
        moved.x += 0.05
        assert not relations.holds(_scene(table, moved, rels=[rel]), rel)
    assert (
        placed and relations.place_tables_joined(_draws(1)[0], _table("table_round", 0), 1) is None
    )


def test_storage_under_table_fits_below_the_top_and_between_the_legs():
    table = _table(height=0.90)
    done = 0
    for rng in _draws(20):
        res = relations.place_storage_under_table(rng, table, 1, H_STORAGE)
        if res is None:
            continue
        obj, rel = res
        tm = table.model()
        assert obj.height <= tm.features["underside_z"] - 0.01 + 1e-9
        fp = obj.footprint()
        covered = polygon_area(clip_convex(fp, table.footprint())) / polygon_area(fp)
        assert covered >= 0.5 - 1e-6
        assert relations.holds(_scene(table, obj, rels=[rel]), rel)
        done += 1
    assert done > 5
    # a table too low for any storage of 70..90 cm takes none
    assert (
        relations.place_storage_under_table(_draws(1)[0], _table(height=0.72), 1, H_STORAGE) is None
    )


def test_chair_partly_under_table_faces_it_with_its_backrest_out():
    for kind, variant in (("table_rect", 0), ("table_round", 0), ("table_round", 1)):
        table = _table(kind, variant, height=0.74)
        done = 0
        for rng in _draws(15):
            res = relations.place_chair_under_table(rng, table, 1, H_CHAIR)
            if res is None:
                continue
            chair, rel = res
            s = _scene(table, chair, rels=[rel])
            assert relations.holds(s, rel)
            cm = chair.model()
            front = chair.to_world(np.array([cm.size_x / 2 - 0.01, 0.0]))
            assert points_in_convex(front, table.footprint())  # the seat's front is under the top
            if chair.height >= table.model().features["underside_z"] - 0.01:
                back = chair.to_world(np.array([-cm.size_x / 2, 0.0]))
                assert not points_in_convex(back, table.footprint())
            turned = copy.deepcopy(chair)
            turned.yaw = (turned.yaw + np.pi) % (2 * np.pi)  # facing away
            assert not relations.holds(_scene(table, turned, rels=[rel]), rel)
            done += 1
        assert done > 3, kind


def test_plant_stands_on_the_table_top():
    for kind in ("table_rect", "table_round"):
        table = _table(kind, 2, height=0.78)
        for rng in _draws(10):
            plant, rel = relations.place_plant_on_table(rng, table, 1, H_PLANT)
            assert plant.support == table.id
            assert plant.z == table.height  # the pot's base is at the table top's height
            assert np.all(points_in_convex(plant.footprint(), table.footprint()))
            assert relations.holds(_scene(table, plant, rels=[rel]), rel)
            lifted = copy.deepcopy(plant)
            lifted.z += 0.01
            assert not relations.holds(_scene(table, lifted, rels=[rel]), rel)


def _hand_heights(scene, rel):
    h = scene.human
    return [
        humanoid.wrist_position(h.pose, h.scale, h.base_pos, h.base_quat, s)[2]
        for s in rel.params["hands"]
    ]


def test_hand_on_table_puts_the_hand_on_the_top():
    table = _table(height=0.80)
    done = 0
    for i, rng in enumerate(_draws(12)):
        pose, src = humanoid.sample_pose("working", rng)
        res = relations.place_hand_on_table(rng, table, 1.6 + 0.025 * i, "working", pose, src)
        if res is None:
            continue
        human, rel = res
        s = _scene(table, human=human, rels=[rel])
        hr = humanoid.limb_lengths(human.scale)["hand_radius"]
        assert np.allclose(_hand_heights(s, rel), table.height + hr, atol=2e-3)
        assert relations.holds(s, rel)
        human.z += 0.05
        assert not relations.holds(s, rel)
        done += 1
    assert done >= 6


def test_holding_a_chairs_back_and_standing_by_storage():
    chair = PlacedObject(0, "chair_plain", 0, 0.85, 0.0, 0.0, 0.0, 1.0)
    storage = PlacedObject(0, "storage_wardrobe", 1, 0.80, 0.0, 0.0, 0.0, 2.0)
    held = stood = 0
    for i, rng in enumerate(_draws(10)):
        pose, src = humanoid.sample_pose("standing", rng)
        res = relations.place_holding_chair_back(rng, chair, 1.65 + 0.02 * i, "standing", pose, src)
        if res is not None:
            human, rel = res
            s = _scene(chair, human=human, rels=[rel])
            hr = humanoid.limb_lengths(human.scale)["hand_radius"]
            assert np.allclose(_hand_heights(s, rel), chair.height + hr, atol=2e-3)
            lx, _ = chair.to_local(np.array([human.x, human.y]))
            assert lx < 0  # behind the chair
            held += 1
        res = relations.place_standing_by_storage(rng, storage, 1.75, "standing", pose, src)
        if res is not None:
            human, rel = res
            s = _scene(storage, human=human, rels=[rel])
            assert relations.holds(s, rel)
            lx, _ = storage.to_local(np.array([human.x, human.y]))
            assert lx > storage.model().size_x / 2  # in front of it
            stood += 1
    assert held >= 5 and stood >= 5


def test_sitting_puts_the_hips_at_seat_height_and_the_feet_on_or_above_the_floor():
    for kind, variant, height in (("chair_plain", 0, 0.70), ("chair_armrest", 3, 0.90)):
        chair = PlacedObject(0, kind, variant, height, 0.3, 0.2, 0.0, 0.7)
        for i, rng in enumerate(_draws(6)):
            pose, src = humanoid.sample_pose("sitting", rng)
            human, rel = relations.place_sitting_on_chair(rng, chair, 1.60 + 0.06 * i, pose, src)
            s = _scene(chair, human=human, rels=[rel])
            assert relations.holds(s, rel)
            seat = chair.model().features["seat_z"]
            r = humanoid.limb_lengths(human.scale)["thigh_radius"]
            hip = humanoid.hip_position(human.pose, human.scale, human.base_pos, human.base_quat)
            assert hip[2] == pytest.approx(seat + r, abs=1e-6)
            lo, _ = humanoid.prims_z_range(human.primitives())
            assert lo >= -1e-3


def test_sampled_scenes_use_every_relation():
    d = DensityFunction()
    rng = np.random.default_rng(2024)
    seen = set()
    for _ in range(60):
        s = d.sample(rng)
        seen |= {r.kind for r in s.relations}
        for r in s.relations:
            assert relations.holds(s, r), r.kind
            assert (r.subject == HUMAN) == (r.kind in relations.HO_RELATIONS)
            if r.kind == "plant_on_table":
                assert s.object(r.subject).z == s.object(r.object).height
    assert set(relations.OO_RELATIONS) <= seen
    assert {"sitting_on_chair", "holding_chair_back", "standing_by_storage"} <= seen


def test_holds_refuses_unknown_kinds_and_missing_objects():
    table = _table()
    assert not relations.holds(_scene(table), relations.Relation("levitating", 1, 0))
    assert not relations.holds(_scene(table), relations.Relation("plant_on_table", 7, 0))
    assert set(furniture.KINDS) >= {"chair_plain", "chair_armrest", "table_rect", "table_round"}
