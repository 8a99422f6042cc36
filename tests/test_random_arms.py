"""Random robot arms: every seed gives a URDF that parses, poses within its limits and is an
arm's size; a seed always gives the same arm and the same depth; cells hold them, labelled
robot, and a cell's scene record alone renders them again; bad names are one clear error."""

from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from test_robots import FLOOR, TWO_LINK, write

from topseg.core import labels
from topseg.core.camera import PAPER_MOUNT
from topseg.core.errors import TopsegError
from topseg.core.synth import cell_relations, random_arms, render, robots
from topseg.core.synth.cell_scenes import CellConfig, CellSampler
from topseg.core.synth.density import DensityConfig
from topseg.core.synth.scene import Scene
from topseg.core.synth.synthesis import SynthesisConfig, Synthesizer

SEEDS = range(60)
RANDOM_CELLS = DensityConfig(cell=CellConfig(paper_share=0.0, random_robot_share=1.0))


def _fresh_model(name: str) -> robots.RobotModel:
    """The model built again from its name, not taken from the cache."""
    robots._RANDOM_MODELS.pop(name, None)
    return robots.robot_model(name)


def test_every_link_has_primitive_geometry_and_the_joints_are_an_arms():
    styles = set()
    for seed in SEEDS:
        root = ET.fromstring(random_arms.random_arm_urdf(seed))
        styles.add(root.get("name").split("_")[1])
        for link in root.iter("link"):
            shapes = [g[0].tag for g in link.iter("geometry")]
            assert shapes and set(shapes) <= {"box", "cylinder", "sphere"}, link.get("name")
        kinds = [j.get("type") for j in root.iter("joint") if j.get("type") != "fixed"]
        if "prismatic" in kinds:  # a SCARA: three turning axes and a quill
            assert sorted(kinds) == ["prismatic"] + ["revolute"] * 3
        else:
            assert set(kinds) == {"revolute"} and 4 <= len(kinds) <= 7
    assert styles == set(random_arms.STYLES)


@pytest.mark.parametrize("seed", SEEDS)
def test_a_random_arm_parses_poses_within_its_limits_and_is_an_arms_size(seed):
    name = robots.random_arm_name(seed)
    model = robots.robot_model(name)
    assert model.name == name and model.tool_link == random_arms.TOOL_LINK
    assert robots.robot_model(name) is model  # cached
    assert 0.4 <= model.reach_m <= 4.0
    assert np.all(model.lower < model.upper)
    rng = np.random.default_rng(seed)
    for mount in ("floor", "gantry"):
        joints = model.random_joints(rng)
        q = np.array(list(joints.values()))
        assert np.all(q >= model.lower) and np.all(q <= model.upper)
        placed = robots.PlacedRobot(3, name, 0.5, -0.5, 1.0, mount,
                                    2.6 if mount == "gantry" else 0.0, joints)  # fmt: skip
        prims, tris = model.link_geometry(joints, placed.base_pos(), placed.base_quat())
        assert len(tris) == 0 and len(prims) > 5
        assert np.all(prims.label == labels.ROBOT) and np.all(np.isfinite(prims.center))
        assert np.all(prims.size[:, 0] > 0) and prims.size.max() < 1.0
        tool = placed.tool_position()
        assert np.linalg.norm(tool - placed.base_pos()) <= model.reach_m + 1e-9
    rest = robots.PlacedRobot(3, name, 0.0, 0.0, 0.0, "floor", 0.0, {})
    extent = np.ptp(rest.footprint(), axis=0)
    assert 0.1 <= extent.min() and extent.max() <= 3.2  # a desk cobot to a large industrial arm
    low, high = rest.z_range()
    assert -1e-3 < low and 0.2 < high < 3.0


def test_the_same_seed_gives_the_same_urdf_and_the_same_depth():
    assert random_arms.random_arm_urdf(17) == random_arms.random_arm_urdf(17)
    assert random_arms.random_arm_urdf(17) != random_arms.random_arm_urdf(18)
    frames = []
    for _ in range(2):
        model = _fresh_model("random:17")
        joints = model.random_joints(np.random.default_rng(4))
        prims, tris = model.link_geometry(joints, (0.2, 0.1, 0.3), (0.0, 0.0, 0.0, 1.0))
        frames.append(render.raycast(render.Primitives.concat([FLOOR, prims]), PAPER_MOUNT, tris))
    (depth_a, lab_a), (depth_b, lab_b) = frames
    assert np.array_equal(depth_a, depth_b) and np.array_equal(lab_a, lab_b)
    assert (lab_a == labels.ROBOT).sum() > 100


@pytest.mark.parametrize("bad", ["random:x", "random:-3", "random:", "random:1.5", "random: 2"])
def test_a_malformed_random_name_is_one_clear_error_naming_it(bad):
    with pytest.raises(TopsegError) as err:
        robots.robot_model(bad)
    assert repr(bad) in str(err.value) and "\n" not in str(err.value)


def test_the_random_arm_cache_is_bounded():
    for seed in range(1000, 1000 + robots.RANDOM_CACHE + 5):
        robots.robot_model(robots.random_arm_name(seed))
    assert len(robots._RANDOM_MODELS) == robots.RANDOM_CACHE
    assert "random:1000" not in robots._RANDOM_MODELS  # the least recently used went first


def test_a_cylinder_standing_on_the_floor_is_clear_of_it(tmp_path):
    wide_base = TWO_LINK.replace(
        '<origin xyz="0 0 0.05"/><geometry><box size="0.2 0.2 0.1"/></geometry>',
        '<origin xyz="0 0 0.05"/><geometry><cylinder radius="0.3" length="0.1"/></geometry>',
    )
    path = write(tmp_path / "wide_base.urdf", wide_base)
    robot = robots.PlacedRobot(1, path, 0.0, 0.0, 0.0, "floor", 0.0, {})
    assert cell_relations.arm_clear_of(robot, [])
    assert cell_relations.robot_points(robot)[:, 2].min() == pytest.approx(0.0, abs=1e-9)


def _sampler(**cell) -> tuple[CellSampler, np.random.Generator]:
    return CellSampler(None, CellConfig(**cell)), np.random.default_rng(0)


def test_user_robot_names_mean_only_these_unless_they_list_random():
    sampler, rng = _sampler(robot_names=("panda", "kuka_kr6"), random_robot_share=1.0)
    assert {sampler._robot_name(rng) for _ in range(50)} == {"panda", "kuka_kr6"}
    sampler, rng = _sampler(robot_names=(robots.RANDOM,), random_robot_share=0.0)
    assert all(sampler._robot_name(rng).startswith("random:") for _ in range(20))
    sampler, rng = _sampler(robot_names=("panda", robots.RANDOM), random_robot_share=0.5)
    names = [sampler._robot_name(rng) for _ in range(200)]
    assert 50 < sum(n.startswith("random:") for n in names) < 150
    assert set(names) - {n for n in names if n.startswith("random:")} == {"panda"}
    sampler, rng = _sampler()  # the whole catalogue and random arms, 0.3 of them
    names = [sampler._robot_name(rng) for _ in range(400)]
    assert 80 < sum(n.startswith("random:") for n in names) < 160


@pytest.mark.parametrize("share", [-0.1, 1.5])
def test_a_random_robot_share_outside_0_1_is_refused(share):
    with pytest.raises(TopsegError, match="random_robot_share"):
        CellConfig.from_dict({"random_robot_share": share})


def test_cells_of_random_arms_render_robot_pixels_and_their_record_renders_them_again():
    cfg = SynthesisConfig(mode="cell", noise="none", seed=3, density=RANDOM_CELLS)
    with Synthesizer(cfg, warm=False) as synth:
        frames = [synth.render(i) for i in range(4)]
        with_robots = [f for f in frames if f.scene.get("robots")]
        assert with_robots
        for f in with_robots:
            assert all(r["name"].startswith("random:") for r in f.scene["robots"])
            assert (f.labels == labels.ROBOT).any()
        f = with_robots[0]
        for r in f.scene["robots"]:
            robots._RANDOM_MODELS.pop(r["name"], None)  # the record alone rebuilds the arm
        again = synth.render_scene(Scene.from_dict(json.loads(json.dumps(f.scene))))
    assert np.array_equal(again.depth, f.depth) and np.array_equal(again.labels, f.labels)
    assert math.isfinite(float(again.depth.sum()))
