"""Cell objects from meshes: every catalogue entry loads at its size, renders labelled object
where its footprint says, reproduces from its scene record, and cells place them."""

from __future__ import annotations

import math

import numpy as np
import pytest

from topseg.core import labels as L
from topseg.core.camera import PAPER_MOUNT
from topseg.core.errors import ConfigError, TopsegError
from topseg.core.synth import mesh_objects
from topseg.core.synth.cell_scenes import CellConfig
from topseg.core.synth.density import DensityConfig, DensityFunction
from topseg.core.synth.geometry import points_in_convex
from topseg.core.synth.mesh_objects import CATALOGUE, MESH_OBJECTS, PlacedMeshObject
from topseg.core.synth.render import camera_pose
from topseg.core.synth.scene import Scene
from topseg.core.synth.synthesis import SynthesisConfig, Synthesizer

MESH_CELLS = DensityConfig(cell=CellConfig(paper_share=0.0, mesh_share=1.0))


@pytest.mark.parametrize("name", MESH_OBJECTS)
def test_every_entry_loads_within_its_size_range(name):
    rng = np.random.default_rng(7)
    for on_table in (False, True):
        if (CATALOGUE[name].table_m if on_table else CATALOGUE[name].floor_m) is None:
            continue
        for _ in range(2):
            obj = _draw_entry(rng, name, on_table)
            tris = obj.geometry()
            assert 0 < len(tris) <= 8000
            assert np.all(tris.label == L.OBJECT)
            assert mesh_objects.size_ok(obj)
            lo, hi = obj.z_range()
            z = tris.vertices[:, :, 2]
            assert z.min() == pytest.approx(lo, abs=1e-9) and z.max() == pytest.approx(hi)


def _draw_entry(rng, name: str, on_table: bool) -> PlacedMeshObject:
    """`mesh_objects.draw` restricted to one entry."""
    pools = ("TABLE_ENTRIES", "FLOOR_ENTRIES")
    saved = {p: getattr(mesh_objects, p) for p in pools}
    try:
        for p in pools:
            setattr(mesh_objects, p, (name,))
        obj = mesh_objects.draw(rng, 0, on_table)
    finally:
        for p, v in saved.items():
            setattr(mesh_objects, p, v)
    if on_table:
        obj.support, obj.z = 99, 0.75
    return obj


def _one_object_scene(obj: PlacedMeshObject) -> Scene:
    return Scene("cell", "industrial_workspace", (-1.5, -1.5), (1.5, 1.5), 0.0, 0.0, mount=PAPER_MOUNT,
                 mesh_objects=[obj])  # fmt: skip


@pytest.fixture(scope="module")
def synth():
    with Synthesizer(SynthesisConfig(mode="cell", noise="none"), warm=False) as s:
        yield s


@pytest.mark.parametrize(("name", "params"), [("tank", {"seed": 3}), ("guard", {"seed": 5}),
                                              ("random_urdf", {"index": 42})])  # fmt: skip
def test_a_mesh_object_renders_labelled_object_inside_its_footprint(synth, name, params):
    unit = mesh_objects.mesh_model(name, params).size(CATALOGUE[name].measure)
    obj = PlacedMeshObject(0, name, params, 0.8 / unit, 0, 0.3, -0.2, 0.0, 0.7)
    frame = synth.render_scene(_one_object_scene(obj))
    mask = frame.labels == L.OBJECT
    assert mask.sum() > 200
    assert set(np.unique(frame.labels)) <= {L.BACKGROUND, L.OBJECT}
    points = _floor_points(frame, mask)
    height = PAPER_MOUNT.height_mm / 1000.0 - frame.depth[mask] / 1000.0
    assert height.max() == pytest.approx(obj.z_range()[1], abs=0.03)
    assert height.min() > -0.01
    inside = points_in_convex(points, obj.footprint(), margin=-0.01)  # a pixel's width
    assert inside.all()


def _floor_points(frame, mask) -> np.ndarray:
    """(n, 2) world floor points under the pixels of `mask` (the paper's camera looks straight
    down from its height, so a pixel's ray meets the surface at x, y below it)."""
    k = PAPER_MOUNT.intrinsics
    v, u = np.nonzero(mask)
    z = frame.depth[mask] / 1000.0
    xc, yc = (u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z
    rot, centre = camera_pose(PAPER_MOUNT)
    world = np.stack([xc, yc, z], 1) @ rot + centre  # p_world = R^T p_cam + c
    return world[:, :2]


def test_a_scene_record_reproduces_the_same_depth(synth):
    df = DensityFunction(MESH_CELLS, mode="cell")
    scene = next(
        s for s in (df.sample(np.random.default_rng(i)) for i in range(10)) if s.mesh_objects
    )
    first = synth.render_scene(scene)
    again = synth.render_scene(Scene.from_dict(first.scene))
    assert first.scene["mesh_objects"] == again.scene["mesh_objects"]
    np.testing.assert_array_equal(first.depth, again.depth)
    np.testing.assert_array_equal(first.labels, again.labels)


def test_scene_records_without_mesh_objects_still_load():
    scene = DensityFunction(MESH_CELLS, mode="cell").sample(np.random.default_rng(1))
    record = scene.to_dict()
    record.pop("mesh_objects", None)
    assert Scene.from_dict(record).mesh_objects == []
    paper = DensityFunction().sample(np.random.default_rng(0)).to_dict()
    assert "mesh_objects" not in paper


def test_cells_with_mesh_share_one_hold_mesh_objects_in_the_support():
    df = DensityFunction(MESH_CELLS, mode="cell")
    scenes = [df.sample(np.random.default_rng(s)) for s in range(8)]
    placed = [m for s in scenes for m in s.mesh_objects]
    assert len(placed) >= 8
    assert len({m.name for m in placed}) >= 4
    for s in scenes:
        f = df.log_factors(s)
        assert all(v > -math.inf for v in f.values()), f
        ids = [o.id for o in s.objects] + [m.id for m in s.mesh_objects] + [r.id for r in s.robots]
        assert len(ids) == len(set(ids))


def test_a_mesh_object_out_of_its_size_range_leaves_the_support():
    df = DensityFunction(MESH_CELLS, mode="cell")
    scene = next(
        s for s in (df.sample(np.random.default_rng(i)) for i in range(10)) if s.mesh_objects
    )
    broken = Scene.from_dict(scene.to_dict())
    broken.mesh_objects[0].scale *= 3.0
    assert df.log_density(broken) == -math.inf


def test_mesh_share_zero_leaves_cells_without_mesh_objects():
    df = DensityFunction(DensityConfig(cell=CellConfig(paper_share=0.0, mesh_share=0.0)), "cell")
    assert not any(df.sample(np.random.default_rng(s)).mesh_objects for s in range(4))


@pytest.mark.parametrize("value", [-0.1, 1.5])
def test_mesh_share_outside_zero_one_is_a_config_error(value):
    with pytest.raises(ConfigError, match="mesh_share"):
        CellConfig.from_dict({"mesh_share": value})


def test_an_unknown_entry_is_a_clear_error():
    obj = PlacedMeshObject(0, "no_such_mesh", {}, 1.0, 0, 0.0, 0.0)
    with pytest.raises(TopsegError, match="unknown mesh object 'no_such_mesh'"):
        obj.geometry()
