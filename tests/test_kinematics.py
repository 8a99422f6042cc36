"""`synth.kinematics` against yourdfpy's own scene graph: every catalogue arm, random arms
and a URDF with prismatic and mimic joints, at random joint values."""

import io

import numpy as np
import pytest
import yourdfpy

from topseg.core.synth import robots
from topseg.core.synth.kinematics import Kinematics

MIMIC_URDF = """<robot name="slide">
  <link name="base"/><link name="a"/><link name="b"/><link name="c"/><link name="d"/>
  <joint name="turn" type="revolute"><parent link="base"/><child link="a"/>
    <origin xyz="0.1 0.2 0.3" rpy="0.3 -0.2 0.5"/><axis xyz="0 1 1"/>
    <limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="slide" type="prismatic"><parent link="a"/><child link="b"/>
    <origin xyz="0 0 0.4" rpy="0 0.7 0"/><axis xyz="0 0 2"/>
    <limit lower="0" upper="0.5" effort="1" velocity="1"/></joint>
  <joint name="follow" type="revolute"><parent link="b"/><child link="c"/>
    <origin xyz="0.2 0 0"/><axis xyz="1 0 0"/><mimic joint="turn" multiplier="-0.5" offset="0.2"/>
    <limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="tip" type="fixed"><parent link="c"/><child link="d"/>
    <origin xyz="0 0.1 0" rpy="0.1 0.2 0.3"/></joint>
</robot>"""


def library_poses(urdf, q, links):
    """Each link's pose from yourdfpy's scene graph (the reference)."""
    graph = yourdfpy.URDF(robot=urdf.robot, build_scene_graph=True, load_meshes=False)
    graph.update_cfg(np.asarray(q, np.float64))
    return np.array([graph.get_transform(link) for link in links])


def assert_like_the_library(urdf, lower, upper, seed):
    kin = Kinematics.of(urdf)
    assert sorted(kin.links) == sorted(link.name for link in urdf.robot.links)
    rng = np.random.default_rng(seed)
    for _ in range(3):
        q = rng.uniform(lower, upper)
        np.testing.assert_allclose(kin.poses(q), library_poses(urdf, q, kin.links), atol=1e-9)


@pytest.mark.parametrize("name", [*robots.ROBOTS, "random:3", "random:11"])
def test_every_arm_is_posed_as_yourdfpy_poses_it(name):
    model = robots.robot_model(name)
    assert_like_the_library(model._urdf, model.lower, model.upper, seed=len(name))


def test_prismatic_and_mimic_joints_follow_the_urdf():
    urdf = yourdfpy.URDF.load(io.StringIO(MIMIC_URDF), load_meshes=False)
    assert urdf.actuated_joint_names == ["turn", "slide"]
    assert_like_the_library(urdf, [-2.0, 0.0], [2.0, 0.5], seed=5)
    kin = Kinematics.of(urdf)
    poses = dict(zip(kin.links, kin.poses(np.array([0.0, 0.25])), strict=True))
    # the slide moves b 2 * 0.25 = 0.5 m along its (unnormalised) axis, z of its origin's
    # frame (pitched 0.7 rad), from 0.4 m up a's z
    expected = [0.5 * np.sin(0.7), 0.0, 0.4 + 0.5 * np.cos(0.7), 1.0]
    np.testing.assert_allclose(np.linalg.inv(poses["a"]) @ poses["b"][:, 3], expected, atol=1e-12)
