"""Cell objects (label `object`): every kind and variant rendered straight down has its top at
its height and stays inside its footprint; they go through furniture's tables, the scene
description and the synthesizer like furniture; the paper's furniture is unchanged."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

from topseg.core import labels
from topseg.core.camera import KINECT_V1, PAPER_MOUNT, Intrinsics, TopViewMount
from topseg.core.synth import cell_objects, furniture
from topseg.core.synth.geometry import BOX, MAX_PARTS, Part, aabb, quat_to_matrix
from topseg.core.synth.render import Primitives, raycast_m
from topseg.core.synth.scene import PlacedObject, Scene
from topseg.core.synth.scene_builder import SceneBuilder, _create_compound
from topseg.core.synth.synthesis import SynthesisConfig, Synthesizer

PAPER_KINDS = (
    "chair_plain",
    "chair_armrest",
    "table_rect",
    "table_round",
    "plant_potted",
    "plant_flowers",
    "storage_shelf",
    "storage_wardrobe",
)


def _primitives(m: furniture.FurnitureModel) -> Primitives:
    """The model's parts standing on a floor at the world origin, as the renderer takes them."""
    floor = Primitives(
        np.array([BOX], np.int32),
        np.array([[10.0, 10.0, 0.05]]),
        np.array([[0.0, 0.0, -0.05]]),
        np.eye(3)[None],
        np.array([labels.BACKGROUND], np.uint8),
    )
    parts = Primitives(
        np.array([p.kind for p in m.parts], np.int32),
        np.array([p.size for p in m.parts], np.float64),
        np.array([p.pos for p in m.parts], np.float64),
        np.array([quat_to_matrix(p.quat) for p in m.parts]),
        np.full(len(m.parts), m.label, np.uint8),
    )
    return Primitives.concat([floor, parts])


def _mount_over(m: furniture.FurnitureModel) -> TopViewMount:
    """A Kinect straight down, as close over the item as sees all of it (whatever its size)."""
    return TopViewMount(KINECT_V1, 1000.0 * (m.height + 0.5 + 1.3 * max(m.size_x, m.size_y)))


#: far above and sharp: sees nearly straight down onto every side of an item
FAR_MOUNT = TopViewMount(Intrinsics(1280, 960, 2281.2, 2281.2, 639.5, 479.5), 12000.0)


def _hits(m: furniture.FurnitureModel, mount: TopViewMount | None = None):
    """Camera height (m), and depth (m) and world floor coordinates of every pixel that sees
    the object from `mount` (by default `_mount_over` it)."""
    mount = mount or _mount_over(m)
    depth, lab = raycast_m(_primitives(m), mount)
    k = mount.intrinsics
    v, u = np.nonzero(lab == m.label)
    z = depth[v, u]
    x = (u - k.cx) / k.fx * z  # straight down: camera x = world x, camera y = -world y
    y = -(v - k.cy) / k.fy * z
    return mount.height_mm / 1000.0, z, x, y


def _models(kind: str):
    """Every variant of `kind` at both ends of its height range."""
    lo, hi = cell_objects.HEIGHT_RANGE_M[kind]
    for variant in range(cell_objects.N_VARIANTS):
        for h in (lo, hi):
            yield furniture.model(kind, variant, h)


@pytest.mark.parametrize("kind", cell_objects.KINDS)
def test_every_variant_renders_with_its_top_at_its_height(kind):
    for m in _models(kind):
        cam_m, z, _, _ = _hits(m)
        assert len(z) > 0, (kind, m.variant, m.height)
        assert m.top_z() == pytest.approx(m.height, abs=1e-9)
        # nothing above the height; round tops are met within a pixel of their apex
        assert z.min() >= cam_m - m.height - 1e-9, (kind, m.variant, m.height)
        assert z.min() <= cam_m - m.height + 2e-3, (kind, m.variant, m.height)
        assert len(m.parts) <= MAX_PARTS, (kind, m.variant, m.height)
        lows = [aabb(p.kind, p.size, np.asarray(p.pos), quat_to_matrix(p.quat))[0] for p in m.parts]
        assert min(lo[2] for lo in lows) >= -1e-9  # nothing under the floor


@pytest.mark.parametrize("kind", cell_objects.KINDS)
def test_every_variant_fits_its_footprint_and_fills_it(kind):
    for m in _models(kind):
        _, _, x, y = _hits(m, FAR_MOUNT)
        where = (kind, m.variant, m.height)
        if m.shape == "disc":
            r = np.hypot(x, y)
            assert r.max() <= m.size_x / 2 + 1e-6, where
            assert r.max() >= m.size_x / 2 - 0.03, where
            continue
        assert m.shape == "rect", where
        assert np.abs(x).max() <= m.size_x / 2 + 1e-6, where
        assert np.abs(y).max() <= m.size_y / 2 + 1e-6, where
        # the footprint is no larger than the item: it reaches each side (a pixel is 5 mm)
        assert x.min() <= -m.size_x / 2 + 0.03 and x.max() >= m.size_x / 2 - 0.03, where
        assert y.min() <= -m.size_y / 2 + 0.03 and y.max() >= m.size_y / 2 - 0.03, where


def test_turned_footprints_turn_with_the_item():
    m = furniture.model("locker", 2, 1.8)
    poly = m.footprint(1.0, 2.0, np.pi / 2)
    assert np.allclose(poly.min(0), (1.0 - m.size_y / 2, 2.0 - m.size_x / 2))
    assert np.allclose(poly.max(0), (1.0 + m.size_y / 2, 2.0 + m.size_x / 2))
    d = furniture.model("drum", 0, 0.8)
    assert np.allclose(np.hypot(*d.footprint(0.0, 0.0, 1.0).T), d.size_x / 2)


@pytest.mark.parametrize("kind", cell_objects.PERSON_LIKE)
def test_person_like_kinds_have_a_variant_with_a_smaller_top(kind):
    """A round top or a smaller part on top: the top 5 cm cover under half of what is seen."""
    shares = []
    for m in _models(kind):
        cam_m, z, _, _ = _hits(m)
        shares.append(np.mean(z <= cam_m - m.height + 0.05))
    assert min(shares) < 0.5, (kind, shares)


def test_the_catalogue_is_listed_in_furnitures_tables():
    kinds = cell_objects.KINDS
    assert not set(kinds) & set(PAPER_KINDS)
    assert furniture.KINDS_OF["object"] == kinds
    assert cell_objects.N_VARIANTS == furniture.N_VARIANTS
    for kind in kinds:
        assert furniture.KINDS[kind] == labels.OBJECT and furniture.CLASS_OF_KIND[kind] == "object"
        m = furniture.model(kind, 1, cell_objects.HEIGHT_RANGE_M[kind][0])
        assert (m.kind, m.variant, m.label, m.cls) == (kind, 1, labels.OBJECT, "object")
    assert set(cell_objects.HEIGHT_RANGE_M) == set(kinds) == set(cell_objects.DESCRIPTIONS)
    for lo, hi in cell_objects.HEIGHT_RANGE_M.values():
        assert 0.05 <= lo < hi <= 3.0
        assert furniture.quantize_height(lo) == lo and furniture.quantize_height(hi) == hi
    assert set(cell_objects.FLOOR_KINDS) | set(cell_objects.TABLE_TOP_KINDS) == set(kinds)
    assert not set(cell_objects.FLOOR_KINDS) & set(cell_objects.TABLE_TOP_KINDS)
    assert set(cell_objects.STACKABLE) <= set(kinds)
    assert set(cell_objects.PERSON_LIKE) <= set(cell_objects.FLOOR_KINDS)
    for kind in cell_objects.TABLE_TOP_KINDS:
        assert cell_objects.HEIGHT_RANGE_M[kind][1] <= 0.3
    for kind in cell_objects.STACKABLE:
        for m in _models(kind):
            top = m.features["stack_top_z"]
            assert top is None or top == pytest.approx(m.height)


def test_a_placed_cell_object_round_trips_through_the_scene_description():
    o = PlacedObject(3, "gas_cylinder", 2, 1.42, 0.5, -0.3, 0.0, 0.7)
    d = json.loads(json.dumps(o.to_dict()))
    assert d["class"] == "object" and d["size"][0] == pytest.approx(0.24)
    back = PlacedObject.from_dict(d)
    assert back == o and back.label == labels.OBJECT and back.cls == "object"
    assert np.array_equal(back.footprint(), o.footprint())


@pytest.mark.parametrize(
    ("kind", "variant", "height", "says"),
    [
        ("forklift", 0, 1.0, "unknown cell object kind 'forklift'"),
        ("drum", 4, 0.8, "variant must be in 0..3"),
        ("drum", 0, 1.5, "a drum is 0.60-0.90 m tall"),
    ],
)
def test_bad_requests_are_refused_with_a_clear_message(kind, variant, height, says):
    with pytest.raises(ValueError, match=says):
        cell_objects.build(kind, variant, height)


def _digest(kinds, heights) -> str:
    """A hash of every part (float64 bytes), footprint and feature of the kinds' models."""
    h = hashlib.sha256()
    for kind in kinds:
        for variant in range(furniture.N_VARIANTS):
            for height in heights:
                m = furniture.model(kind, variant, height)
                h.update(f"{m.kind}|{m.variant}|{m.shape}|{m.label}|{m.cls}".encode())
                h.update(np.array([m.height, m.size_x, m.size_y], np.float64).tobytes())
                for p in m.parts:
                    h.update(np.array([p.kind, *p.size, *p.pos, *p.quat], np.float64).tobytes())
                h.update(json.dumps(m.features, sort_keys=True, default=float).encode())
    return h.hexdigest()


def test_the_papers_furniture_is_unchanged_to_the_bit():
    # recorded from furniture.py before cell objects were added to its tables
    assert (
        _digest(PAPER_KINDS, (0.15, 0.25, 0.35, 0.7, 0.8, 0.9))
        == "f544e805f1d9287d0ff292b7890f0c2478431b1ee43feb6da415c9509d79b3f2"
    )


def test_a_cell_object_is_pooled_posed_and_rendered_like_furniture():
    drum = PlacedObject(0, "drum", 2, 0.85, 0.5, -0.4, 0.0, 0.3)  # open-head: a flat lid
    scene = Scene("modeled", "industrial_workspace", (-2.3, -1.8), (2.3, 1.8), 0.3, 0.3, [drum])
    with Synthesizer(SynthesisConfig(noise="none"), warm=False) as s:
        f = s.render_scene(scene)
    k = PAPER_MOUNT.intrinsics
    z = 3.5 - 0.85
    u = round(0.5 / z * k.fx + k.cx)
    v = round(0.4 / z * k.fy + k.cy)  # world y = -0.4 is below the image centre
    assert f.labels[v, u] == labels.OBJECT and f.depth[v, u] == 2650
    lid = (f.labels == labels.OBJECT) & (f.depth == 2650)
    r = 0.28 - 0.005  # the lid's radius (the clamp ring below it is 0.28)
    assert lid.sum() == pytest.approx(np.pi * (r * k.fx / z) ** 2, rel=0.03)
    assert f.scene["objects"][0]["class"] == "object"


def test_warming_up_skips_a_class_given_no_height_range():
    import pybullet as p

    client = p.connect(p.DIRECT)
    try:
        builder = SceneBuilder(client)
        paper = {c: (0.8, 0.8) for c in ("chair", "table", "storage")} | {"plant": (0.2, 0.2)}
        builder.warm(paper, (1.7, 1.7))
        pooled = {kind for kind, _, _ in builder._furniture}
        assert pooled == set(PAPER_KINDS)
    finally:
        p.disconnect(client)


def test_the_pooled_pybullet_bodies_carry_every_part_of_every_kind():
    """What the renderer reads back from pybullet is the model, part for part."""
    import pybullet as p

    client = p.connect(p.DIRECT)
    try:
        builder = SceneBuilder(client)
        for kind in cell_objects.KINDS:
            for m in _models(kind):
                variant = m.variant
                o = PlacedObject(0, kind, variant, m.height, 0, 0)
                body = builder.build(Scene("modeled", "industrial_workspace", (-9, -9), (9, 9), 0, 0, [o]))[-1]  # fmt: skip
                read = builder.primitives([body])
                want = _primitives(m)
                assert len(read) == len(m.parts), (kind, variant)
                assert np.array_equal(read.kind, want.kind[1:]) and np.all(
                    read.label == labels.OBJECT
                )
                np.testing.assert_allclose(read.size, want.size[1:], atol=1e-6)
                np.testing.assert_allclose(read.center, want.center[1:], atol=1e-6)
                np.testing.assert_allclose(read.rot, want.rot[1:], atol=1e-6)
    finally:
        p.disconnect(client)


def test_an_item_with_more_parts_than_pybullet_keeps_is_refused():
    import pybullet as p

    client = p.connect(p.DIRECT)
    try:
        cubes = [Part(BOX, (0.05, 0.05, 0.05), (0.2 * i, 0.0, 0.05)) for i in range(MAX_PARTS + 1)]
        assert len(_create_compound(client, cubes[:MAX_PARTS], labels.OBJECT).kind) == MAX_PARTS
        with pytest.raises(ValueError, match=f"at most {MAX_PARTS} parts"):
            _create_compound(client, cubes, labels.OBJECT)
    finally:
        p.disconnect(client)
