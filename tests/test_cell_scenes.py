"""Robot cells from the density function's cell mode: robots, cell objects and people placed by
their relations, scored by log_density, rendered with exact robot and object labels."""

from __future__ import annotations

import math

import numpy as np
import pytest

from topseg.core import labels as L
from topseg.core.errors import TopsegError
from topseg.core.synth import cell_relations, humanoid
from topseg.core.synth.cell_scenes import CellConfig
from topseg.core.synth.density import DensityConfig, DensityFunction
from topseg.core.synth.scene import Scene, human_id
from topseg.core.synth.synthesis import SynthesisConfig, Synthesizer

CELLS_ONLY = DensityConfig(cell=CellConfig(paper_share=0.0))


@pytest.fixture(scope="module")
def cells():
    """Twenty cell scenes (no paper scenes) and the function that drew them."""
    df = DensityFunction(CELLS_ONLY, mode="cell")
    return df, [df.sample(np.random.default_rng(s)) for s in range(20)]


def test_cells_hold_robots_objects_and_people(cells):
    _, scenes = cells
    assert sum(len(s.robots) for s in scenes) >= 20
    assert sum(o.cls == "object" for s in scenes for o in s.objects) >= 20
    people = [len(s.humans) for s in scenes]
    assert min(people) == 0 and max(people) == 2
    kinds = {r.kind for s in scenes for r in s.relations}
    assert "works_at_robot" in kinds
    assert len(kinds & set(cell_relations.CELL_OO_RELATIONS)) >= 2
    mounts = {r.mount for s in scenes for r in s.robots}
    assert len(mounts) >= 2


def test_sampled_cells_lie_in_the_support(cells):
    df, scenes = cells
    for s in scenes:
        f = df.log_factors(s)
        assert all(v > -math.inf for v in f.values()), f
        ids = [o.id for o in s.objects] + [r.id for r in s.robots]
        assert len(ids) == len(set(ids))


def test_a_joint_past_its_limit_leaves_the_support(cells):
    df, scenes = cells
    s = next(s for s in scenes if s.robots)
    broken = Scene.from_dict(s.to_dict())
    r = broken.robots[0]
    name = r.model().joint_names[0]
    r.joints[name] = float(r.model().upper[0]) + 0.5
    assert df.log_density(broken) == -math.inf


def test_a_broken_relation_leaves_the_support(cells):
    df, scenes = cells
    s = next(s for s in scenes if any(r.kind == "works_at_robot" for r in s.relations))
    broken = Scene.from_dict(s.to_dict())
    rel = next(r for r in broken.relations if r.kind == "works_at_robot")
    person = broken.humans[[human_id(i) for i in range(len(broken.humans))].index(rel.subject)]
    person.x += 1.0  # the hands leave the tool
    assert df.log_density(broken) == -math.inf


def test_cell_scenes_round_trip_through_their_record(cells):
    _, scenes = cells
    for s in scenes:
        again = Scene.from_dict(s.to_dict())
        assert again.to_dict() == s.to_dict()


def test_paper_scene_records_have_no_cell_keys():
    s = DensityFunction().sample(np.random.default_rng(0))
    d = s.to_dict()
    assert "robots" not in d and "extra_humans" not in d


@pytest.mark.slow
def test_cells_render_robots_and_objects_with_their_labels():
    cfg = SynthesisConfig(mode="cell", noise="none", seed=5, density=CELLS_ONLY)
    seen = set()
    with Synthesizer(cfg) as synth:
        for i in range(6):
            f = synth.render(i)
            seen |= set(np.unique(f.labels).tolist())
            if f.scene.get("robots"):
                assert (f.labels == L.ROBOT).any()
    assert {L.ROBOT, L.OBJECT} <= seen


def test_the_paper_share_draws_the_paper_scenes():
    df = DensityFunction(DensityConfig(cell=CellConfig(paper_share=1.0)), mode="cell")
    for seed in range(5):
        s = df.sample(np.random.default_rng(seed))
        assert not s.robots and all(o.cls != "object" for o in s.objects)


def test_cell_poses_are_drawn():
    df = DensityFunction(CELLS_ONLY, mode="cell")
    poses = set()
    for seed in range(60):
        s = df.sample(np.random.default_rng(seed))
        poses |= {h.pose_name for h in s.humans}
    assert len(poses & set(humanoid.CELL_POSES)) >= 3


@pytest.mark.parametrize(
    "bad",
    [
        {"paper_share": 1.5},
        {"robots": [3, 1]},
        {"robot_names": ["no_such_robot"]},
        {"mount_weights": {"ceiling": 1.0}},
        {"pose_weights": {"flying": 1.0}},
        {"people_weights": [1, 1, 1, 1]},
    ],
)
def test_bad_cell_settings_name_the_setting(bad):
    with pytest.raises(TopsegError, match=next(iter(bad))):
        CellConfig.from_dict(bad)
