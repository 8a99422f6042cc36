"""The poses a robot cell sees (kneeling, crouching, lying, reaching): each drawn over many seeds
rests on the floor with the shape it is named for, pybullet poses the same body, the density
function can place it, and the paper's scenes still draw only the paper's poses."""

from __future__ import annotations

import math

import numpy as np
import pybullet as p
import pytest

from topseg.core.synth import humanoid, relations
from topseg.core.synth.density import DensityConfig, DensityFunction
from topseg.core.synth.geometry import half_extents, quat_to_matrix
from topseg.core.synth.scene import PlacedHuman
from topseg.core.synth.scene_builder import SceneBuilder

SEEDS = range(50)
INDEX = humanoid.load_model().index


def _placed(name: str, seed: int) -> PlacedHuman:
    """Pose `name` drawn with `seed`, a paper height, stood on the floor anywhere, any heading."""
    rng = np.random.default_rng(seed)
    pose, source = humanoid.sample_pose(name, rng)
    height = humanoid.quantize_height(rng.uniform(1.6, 1.9))
    z = relations.stand_z(pose, humanoid.scale_for_height(height))
    x, y, yaw = rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0, 2 * np.pi)
    return PlacedHuman(height, name, pose, source, x, y, z, yaw)


def _tops_and_bottoms(h: PlacedHuman) -> tuple[np.ndarray, np.ndarray]:
    prims = h.primitives()
    ext = half_extents(prims.kind, prims.size, prims.rot)[:, 2]
    return prims.center[:, 2] + ext, prims.center[:, 2] - ext


def _joints(h: PlacedHuman) -> np.ndarray:
    return humanoid.link_frames(h.pose, h.scale, h.base_pos, h.base_quat)[0]


def _ahead(h: PlacedHuman, point) -> float:
    """How far (m) `point` lies ahead of the pelvis along the way the human faces."""
    facing = np.array([math.cos(h.yaw), math.sin(h.yaw)])
    return float((np.asarray(point)[:2] - np.array([h.x, h.y])) @ facing)


@pytest.mark.parametrize("name", humanoid.CELL_POSES)
def test_cell_poses_are_finite_and_rest_on_the_floor(name):
    for seed in SEEDS:
        h = _placed(name, seed)
        assert all(np.all(np.isfinite(v)) for v in h.pose.joints.values()), (name, seed)
        assert np.all(np.isfinite(h.pose.tilt)), (name, seed)
        lo, _ = humanoid.prims_z_range(h.primitives())
        assert abs(lo) <= 1e-3, (name, seed, lo)
        assert 0.4 < math.dist(*h.footprint()[[0, 2]]) < 3.0, (name, seed)  # its diagonal


def test_kneeling_has_a_knee_on_the_floor_and_the_head_at_knee_height():
    shin_radius = humanoid.load_model().link("right_knee").shape_size[0]
    for seed in SEEDS:
        h = _placed("kneeling", seed)
        joints = _joints(h)
        knee_surface = min(joints[INDEX[f"{s}_knee"], 2] for s in ("right", "left"))
        assert knee_surface - shin_radius * h.scale <= 0.05, seed
        head_top = _tops_and_bottoms(h)[0][INDEX["neck"]]
        assert 0.55 <= head_top / h.height <= 0.8, (seed, head_top / h.height)


def test_crouching_keeps_the_head_low_on_both_feet():
    for seed in SEEDS:
        h = _placed("crouching", seed)
        tops, bottoms = _tops_and_bottoms(h)
        assert 0.45 <= tops[INDEX["neck"]] / h.height <= 0.7, seed
        feet = [bottoms[INDEX[f"{s}_ankle"]] for s in ("right", "left")]
        assert max(feet) <= 1e-3, (seed, feet)  # both feet down, not one leg in the air


def test_lying_is_long_and_low():
    for seed in SEEDS:
        h = _placed("lying", seed)
        prims = h.primitives()
        lo, hi = humanoid.prims_xy_bounds(prims, h.yaw, h.base_pos)
        assert max(hi - lo) > 1.2, seed
        assert humanoid.prims_z_range(prims)[1] < 0.5, seed


def test_reaching_puts_a_hand_ahead_at_machine_height_with_the_trunk_bent():
    for seed in SEEDS:
        h = _placed("reaching", seed)
        joints, rot = humanoid.link_frames(h.pose, h.scale, h.base_pos, h.base_quat)
        wrists = [joints[INDEX[f"{s}_wrist"]] for s in ("right", "left")]
        assert any(_ahead(h, w) >= 0.45 and 0.6 <= w[2] <= 1.6 for w in wrists), seed
        chest_up = rot[INDEX["chest"]] @ np.array([0.0, 1.0, 0.0])
        assert 9.5 <= math.degrees(math.acos(chest_up[2])) <= 60.5, seed
        feet = [_tops_and_bottoms(h)[1][INDEX[f"{s}_ankle"]] for s in ("right", "left")]
        assert max(feet) <= 1e-3, (seed, feet)


def test_a_seed_draws_the_same_cell_pose():
    for name in humanoid.CELL_POSES:
        a, _ = humanoid.sample_pose(name, np.random.default_rng(7))
        b, _ = humanoid.sample_pose(name, np.random.default_rng(7))
        assert a.to_dict() == b.to_dict()


def test_pybullet_poses_the_cell_poses_as_the_kinematics_do():
    client = p.connect(p.DIRECT)
    try:
        builder = SceneBuilder(client)
        for k, name in enumerate(humanoid.CELL_POSES * 2):
            h = _placed(name, 100 + k)
            body = builder._human_body(h.height)
            p.resetBasePositionAndOrientation(
                body.uid, list(h.base_pos), list(h.base_quat), physicsClientId=client
            )
            for i, link in enumerate(humanoid.load_model().links):
                if link.joint_type == "spherical":
                    p.resetJointStateMultiDof(
                        body.uid, i, h.pose.joints[link.name], physicsClientId=client
                    )
                elif link.joint_type == "revolute":
                    p.resetJointState(
                        body.uid, i, h.pose.joints[link.name][0], physicsClientId=client
                    )
            states = p.getLinkStates(
                body.uid, list(range(15)), computeForwardKinematics=1, physicsClientId=client
            )
            pos, rot = humanoid.link_frames(h.pose, h.scale, h.base_pos, h.base_quat)
            np.testing.assert_allclose(pos, [s[4] for s in states], atol=1e-6)
            np.testing.assert_allclose(rot, [quat_to_matrix(s[5]) for s in states], atol=1e-5)
    finally:
        p.disconnect(client)


def test_the_density_function_places_cell_poses_on_the_floor():
    d = DensityFunction(DensityConfig(pose_weights={n: 1.0 for n in humanoid.CELL_POSES}))
    rng = np.random.default_rng(11)
    seen = set()
    for _ in range(16):
        scene = d.sample(rng)
        if scene.human is not None:
            seen.add(scene.human.pose_name)
            assert math.isfinite(d.log_density(scene)), scene.human.pose_name
    assert len(seen) >= 2 and seen <= set(humanoid.CELL_POSES)


def test_the_papers_scenes_draw_only_the_papers_poses():
    paper = ("sitting", "standing", "stretching", "working", "bending", "bowing", "tilting",
             "swinging", "walking", "running", "dancing", "boxing", "kicking", "spinning",
             "jumping")  # fmt: skip
    assert humanoid.PAPER_POSES == paper
    assert humanoid.POSES == (*paper, *humanoid.CELL_POSES)
    weights = DensityConfig().pose_weights
    assert tuple(weights) == paper and len(set(weights.values())) == 1
    d = DensityFunction()
    assert d.pose.choices == paper
    rng = np.random.default_rng(2)
    assert all(d.pose.sample(rng) in paper for _ in range(500))
