"""The humanoid: numpy kinematics against pybullet's, poses from the clips and presets, reaching
and sitting checked on the pybullet body itself."""

from __future__ import annotations

import numpy as np
import pybullet as p
import pytest

from topseg.core import labels
from topseg.core.synth import humanoid, relations
from topseg.core.synth.density import DensityFunction
from topseg.core.synth.geometry import CAPSULE, quat_to_matrix
from topseg.core.synth.scene_builder import SceneBuilder


@pytest.fixture(scope="module")
def world():
    client = p.connect(p.DIRECT)
    yield client, SceneBuilder(client)
    p.disconnect(client)


def _pose_body(world, pose, height, base_pos, base_q):
    client, builder = world
    body = builder._human_body(height)
    p.resetBasePositionAndOrientation(
        body.uid, list(base_pos), list(base_q), physicsClientId=client
    )
    for i, link in enumerate(humanoid.load_model().links):
        if link.joint_type == "spherical":
            p.resetJointStateMultiDof(body.uid, i, pose.joints[link.name], physicsClientId=client)
        elif link.joint_type == "revolute":
            p.resetJointState(body.uid, i, pose.joints[link.name][0], physicsClientId=client)
    states = p.getLinkStates(
        body.uid, list(range(15)), computeForwardKinematics=1, physicsClientId=client
    )
    return body, np.array([s[4] for s in states]), np.array([quat_to_matrix(s[5]) for s in states])


def test_forward_kinematics_matches_pybullet(world):
    rng = np.random.default_rng(3)
    for name in ("walking", "dancing", "bending", "tilting", "sitting", "kicking"):
        pose, _ = humanoid.sample_pose(name, rng)
        height = humanoid.quantize_height(rng.uniform(1.6, 1.9))
        base = (rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0.5, 1.2))
        bq = humanoid.base_quat(pose.tilt, rng.uniform(0, 2 * np.pi))
        _, pos, rot = _pose_body(world, pose, height, base, bq)
        mine_pos, mine_rot = humanoid.link_frames(pose, humanoid.scale_for_height(height), base, bq)
        np.testing.assert_allclose(mine_pos, pos, atol=1e-6)
        np.testing.assert_allclose(mine_rot, rot, atol=1e-5)


def test_reaching_lands_the_wrist_on_the_target_in_pybullet(world):
    rng = np.random.default_rng(4)
    hits = 0
    for _ in range(8):
        pose, _ = humanoid.sample_pose("standing", rng)
        height = humanoid.quantize_height(rng.uniform(1.6, 1.9))
        scale = humanoid.scale_for_height(height)
        z0 = relations.stand_z(pose, scale)
        bq = humanoid.base_quat(pose.tilt, 0.0)
        side = str(rng.choice(["right", "left"]))
        sh = humanoid.link_frames(pose, scale, (0, 0, z0), bq)[0][
            humanoid.load_model().index[f"{side}_shoulder"]
        ]
        target = sh + rng.uniform([0.1, -0.2, -0.45], [0.35, 0.2, -0.1])
        if not humanoid.reach(pose, scale, (0, 0, z0), bq, side, target):
            continue
        _, pos, _ = _pose_body(world, pose, height, (0, 0, z0), bq)
        wrist = pos[humanoid.load_model().index[f"{side}_wrist"]]
        np.testing.assert_allclose(wrist, target, atol=1e-5)
        hits += 1
    assert hits >= 6
    pose = humanoid.identity_pose()
    far = (5.0, 0.0, 1.0)
    assert not humanoid.reach(pose, 0.25, (0, 0, 1), humanoid.base_quat(pose.tilt, 0), "right", far)
    assert pose.joints["right_elbow"] == [0.0]  # left unchanged


def test_sitting_humans_hips_are_at_seat_height_in_pybullet(world):
    client, builder = world
    d = DensityFunction()
    rng = np.random.default_rng(11)
    seen = 0
    while seen < 3:
        s = d.sample(rng)
        rel = next((r for r in s.relations if r.kind == "sitting_on_chair"), None)
        if rel is None:
            continue
        builder.build(s)
        chair = s.object(rel.object)
        body = builder._human_body(s.human.height)
        idx = humanoid.load_model().index
        for side in ("right", "left"):
            hip = p.getLinkState(
                body.uid, idx[f"{side}_hip"], computeForwardKinematics=1, physicsClientId=client
            )[4]
            radius = humanoid.limb_lengths(s.human.scale)["thigh_radius"]
            assert hip[2] == pytest.approx(chair.model().features["seat_z"] + radius, abs=1e-4)
        seen += 1


def test_heights_and_labels_of_the_humanoid():
    # pybullet_data's humanoid is ~1.62 m at its scaling; the smaller head takes ~2 cm off
    assert humanoid.reference_height() == pytest.approx(1.60, abs=0.01)
    for h in (1.60, 1.75, 1.90):
        pose = humanoid.identity_pose()
        prims = humanoid.posed_primitives(
            pose, humanoid.scale_for_height(h), (0, 0, 0), humanoid.base_quat(pose.tilt, 0)
        )
        lo, hi = humanoid.prims_z_range(prims)
        assert hi - lo == pytest.approx(h, abs=1e-9)
        head = prims.center[prims.label == labels.HEAD]
        assert (
            head[0, 2] > prims.center[prims.label == labels.BODY][:, 2].max()
        )  # the head is on top
    assert set(humanoid.LINK_LABELS.values()) == set(labels.HUMAN_IDS)
    assert len(humanoid.load_model().links) == 15


def test_clip_poses_interpolate_and_skip_tumbling_moments():
    frames = humanoid.load_clip("walk")
    a = humanoid.clip_pose("walk", 0.0)
    # phase 0 is the first key frame exactly (w, x, y, z in the file)
    w, x, y, z = frames[0][8:12]
    np.testing.assert_allclose(
        np.abs(a.joints["chest"]),
        np.abs(np.array([x, y, z, w]) / np.linalg.norm([x, y, z, w])),
        atol=1e-9,
    )
    rng = np.random.default_rng(0)
    for _ in range(20):
        pose, src = humanoid.sample_pose("kicking", rng)
        assert src["source"] == "mocap" and src["clip"] in humanoid.CLIPS["kicking"]
        assert humanoid.trunk_uprightness(pose) >= humanoid.MIN_UPRIGHT
    with pytest.raises(ValueError, match="unknown pose"):
        humanoid.sample_pose("moonwalking", rng)


#: ANSUR II (2012) means and SDs, mm (docs/research/sensor-noise-sources.md section 4):
#: dimension -> ((women mean, sd), (men mean, sd)); circumferences / pi for limb thickness
ANSUR = {
    "head_breadth": ((147.8, 5.2), (154.3, 5.5)),
    "head_length": ((189.8, 7.4), (199.5, 7.0)),
    "bideltoid_breadth": ((450.3, 28.7), (510.4, 32.5)),
    "chest_breadth": ((269.3, 18.6), (289.4, 18.3)),
    "chest_depth": ((247.4, 27.3), (253.8, 26.2)),
    "hip_breadth": ((353.8, 26.7), (345.7, 24.2)),
    "upper_arm_thickness": ((305.6 / np.pi, 30.8 / np.pi), (358.1 / np.pi, 34.6 / np.pi)),
    "forearm_thickness": ((264.1 / np.pi, 18.5 / np.pi), (310.1 / np.pi, 22.0 / np.pi)),
    "hand_breadth": ((78.2, 3.8), (88.3, 4.4)),
}
#: mean statures (m): women (ANSUR II data), men (ANSUR II, approximately)
STATURE = (1.6285, 1.756)


def test_the_body_seen_from_above_is_within_two_sd_of_ansur():
    """At each sex's mean stature the humanoid's top-view dimensions lie within 2 SD of that
    sex's ANSUR II mean (the table in docs/explanation/method.md)."""
    for stature, which in ((STATURE[0], 0), (STATURE[1], 1)):
        dims = humanoid.top_view_dimensions(stature)
        for name, pair in ANSUR.items():
            mean, sd = pair[which]
            z = (dims[name] - mean) / sd
            assert abs(z) <= 2.0, f"{name} at {stature} m: {dims[name]:.0f} mm is {z:+.1f} SD"


def test_fixed_proportions_reach_pybullet(world):
    """The URDF pybullet loads carries the same head, chest and pelvis as the numpy model."""
    _client, builder = world
    body = builder._human_body(1.75)
    model = humanoid.load_model()
    for name in humanoid.PROPORTION_FIXES:
        i = model.index[name]
        rows = body.link == i
        assert body.kind[rows].tolist() == [CAPSULE]
        scale = humanoid.scale_for_height(1.75)
        np.testing.assert_allclose(
            body.size[rows][0, :2], np.array(model.links[i].shape_size[:2]) * scale, atol=1e-6
        )
