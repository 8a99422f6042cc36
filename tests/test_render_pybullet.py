"""The ray caster over pybullet's geometry against pybullet's own TinyRenderer, and the scene
builder's pooled bodies."""

from __future__ import annotations

import numpy as np
import pybullet as p
import pytest
import reference
from scipy import ndimage

from topseg.core import labels
from topseg.core.camera import PAPER_MOUNT, Intrinsics, TopViewMount
from topseg.core.synth import humanoid, render, rooms
from topseg.core.synth.density import DensityFunction
from topseg.core.synth.geometry import BOX
from topseg.core.synth.scene import PlacedObject, Scene
from topseg.core.synth.scene_builder import SceneBuilder


@pytest.fixture(scope="module")
def world():
    client = p.connect(p.DIRECT)
    yield client, SceneBuilder(client)
    p.disconnect(client)


def _both(world, scene):
    client, builder = world
    builder.build(scene)
    ray = render.raycast(builder.primitives(), PAPER_MOUNT)
    tiny = reference.render_tiny(client, builder.label_of)
    return ray, tiny


def _kinds(world) -> np.ndarray:
    """Which primitive kind each pixel sees (its geometry.* id), from the ray caster."""
    prims = world[1].primitives()
    prims.label = prims.kind.astype(np.uint8)
    return render.raycast(prims, PAPER_MOUNT)[1]


def _edges(lab: np.ndarray, width: int) -> np.ndarray:
    e = np.zeros(lab.shape, bool)
    e[1:] |= lab[1:] != lab[:-1]
    e[:-1] |= lab[1:] != lab[:-1]
    e[:, 1:] |= lab[:, 1:] != lab[:, :-1]
    e[:, :-1] |= lab[:, 1:] != lab[:, :-1]
    return ndimage.binary_dilation(e, iterations=width) if width else e


def test_box_furniture_renders_the_same_in_both_renderers(world):
    # tables, wardrobes, shelves and four-legged chairs are all boxes: nothing to tessellate
    objects = [
        PlacedObject(0, "table_rect", 0, 0.74, -0.6, 0.3, 0.0, 0.3),
        PlacedObject(1, "storage_wardrobe", 1, 0.88, 1.1, -0.5, 0.0, 2.0),
        PlacedObject(2, "storage_shelf", 2, 0.81, 0.9, 0.8, 0.0, 4.1),
        PlacedObject(3, "chair_plain", 0, 0.86, -1.2, -0.8, 0.0, 5.5),
        PlacedObject(4, "table_rect", 3, 0.70, 0.1, -1.0, 0.0, 0.0),
    ]
    scene = Scene("modeled", "meeting_room", (-2, -2), (2, 2), 0.3, 0.3, objects)
    (d1, l1), (d2, l2) = _both(world, scene)
    assert np.array_equal(l1, l2)
    assert np.abs(d1.astype(int) - d2.astype(int)).max() <= 1
    assert {labels.TABLE, labels.STORAGE, labels.CHAIR, labels.BACKGROUND} <= set(
        np.unique(l1).tolist()
    )


def test_sampled_scenes_agree_up_to_tessellation(world):
    """TinyRenderer draws spheres, capsules and cylinders as meshes: silhouettes of curved
    shapes may move by the mesh's sag (up to ~2 px on a 1.2 m round table top) and so may their
    depth. Everything else is equal."""
    d = DensityFunction()
    rng = np.random.default_rng(8)
    for _ in range(3):
        scene = d.sample(rng)
        (d1, l1), (d2, l2) = _both(world, scene)
        human = np.isin(l1, labels.HUMAN_IDS) | np.isin(l2, labels.HUMAN_IDS)
        near_edge = _edges(l1, 3)
        # TinyRenderer drops the triangles of a curved mesh cut by the image border (a round
        # table top half out of view loses a band of its top): leave furniture the border cuts
        parts, _ = ndimage.label((l1 != labels.BACKGROUND) & ~human)
        rim = np.concatenate([parts[0], parts[-1], parts[:, 0], parts[:, -1]])
        cut = np.isin(parts, rim[rim > 0])
        differ = (l1 != l2) & ~cut
        assert (differ & ~human).mean() < 0.005
        # outside the human, labels differ only along silhouettes
        assert not np.any(differ & ~near_edge & ~human)
        # on the human, TinyRenderer's capsule meshes are coarse: their sag grows with the
        # radius (the head and chest capsules lose up to ~9 px of rim at 1.8 m, the mesh
        # inscribed in the capsule), so more of the human's rim differs than of the furniture
        assert (differ & human).sum() <= 0.3 * human.sum()
        # boxes (floor, walls, table tops, seats, panels) need no mesh: away from silhouettes
        # their depth agrees to the millimetre
        boxes = (_kinds(world) == BOX) & ~_edges(l1, 2) & ~human & (l1 == l2)
        assert boxes.mean() > 0.5
        assert np.abs(d1[boxes].astype(int) - d2[boxes].astype(int)).max() <= 1


def test_primitives_read_from_pybullet_match_the_numpy_humanoid(world):
    _client, builder = world
    d = DensityFunction(mode="non-modeled", config=None)
    rng = np.random.default_rng(1)
    scene = next(s for s in (d.sample(rng) for _ in range(50)) if s.human is not None)
    builder.build(scene)
    prims = builder.primitives()
    mine = scene.human.primitives()
    is_human = np.isin(prims.label, labels.HUMAN_IDS)
    assert is_human.sum() == len(mine.kind)
    np.testing.assert_allclose(prims.center[is_human], mine.center, atol=1e-6)
    np.testing.assert_allclose(prims.size[is_human], mine.size, atol=1e-9)
    np.testing.assert_array_equal(prims.label[is_human], mine.label)
    np.testing.assert_array_equal(prims.kind[is_human], mine.kind)


def test_builder_pools_bodies_and_parks_the_unused(world):
    client, builder = world
    d = DensityFunction()
    rng = np.random.default_rng(3)
    scenes = [d.sample(rng) for _ in range(6)]
    for s in scenes:
        builder.build(s)
    n = builder.n_bodies
    images = []
    for s in scenes[:3]:  # the same scenes again: no new bodies, the same pictures
        builder.build(s)
        images.append(render.raycast(builder.primitives(), PAPER_MOUNT))
    assert builder.n_bodies == n
    builder.build(scenes[0])
    again = render.raycast(builder.primitives(), PAPER_MOUNT)
    assert np.array_equal(again[0], images[0][0]) and np.array_equal(again[1], images[0][1])
    # every body but the active ones waits below the floor, out of the camera's view
    active = {b.uid for b in builder.active}
    for uid in range(p.getNumBodies(physicsClientId=client)):
        uid = p.getBodyUniqueId(uid, physicsClientId=client)
        if uid not in active:
            assert p.getBasePositionAndOrientation(uid, physicsClientId=client)[0][2] < -50
    assert humanoid.load_model()  # loaded once, shared


def test_walls_follow_each_scenes_mount_from_a_small_pool(world):
    """The same room under two mounts: its walls stand where `wall_boxes` of that mount puts
    them, built from the same pooled slabs, and a tilted render of it matches the reference."""
    _client, builder = world
    d = DensityFunction(room="meeting_room")
    rng = np.random.default_rng(4)
    tilted = TopViewMount(
        Intrinsics(128, 100, 88.25, 88.25, 63.5, 49.5), 2600.0, 8.0, -6.0, "oak_d"
    )
    for mount in (PAPER_MOUNT, tilted):
        scene = d.sample(rng, mount)
        assert scene.mount == mount
        builder.build(scene)
        prims = builder.primitives()
        is_wall = (prims.kind == BOX) & (prims.size[:, 2] == rooms.WALL_HEIGHT_M / 2)
        walls = prims.center[is_wall & (prims.size.max(1) == rooms.WALL_HALF_LENGTH_M)]
        want = np.array([c for c, _ in rooms.get("meeting_room").wall_boxes(mount)])
        np.testing.assert_allclose(np.sort(walls, 0), np.sort(want, 0), atol=1e-9)
    n = builder.n_bodies
    builder.build(d.sample(rng, PAPER_MOUNT))
    assert builder.n_bodies >= n
    assert set(builder._walls) <= {("x", 0), ("x", 1), ("y", 0), ("y", 1)}  # pooled, reused
    depth, lab = render.raycast_m(prims, tilted)
    ref_depth, ref_lab = reference.raycast_world_reference(prims, tilted)
    assert np.array_equal(np.isfinite(depth), np.isfinite(ref_depth))
    assert np.mean(lab != ref_lab) < 1e-3
