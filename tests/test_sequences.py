"""Rendered cell sequences: the truth separation on hand-made bodies, and a sequence's robot,
people, frames and determinism."""

from types import SimpleNamespace

import numpy as np
import pytest

from topseg.core import labels
from topseg.core.synth import body_distance
from topseg.core.synth.geometry import BOX, CAPSULE, SPHERE
from topseg.core.synth.humanoid import prims_z_range
from topseg.core.synth.render import Primitives, Triangles
from topseg.core.synth.sequences import (
    MAX_JOINT_SPEED,
    CellSequence,
    CellSequenceConfig,
    person_at,
)

pytest.importorskip("trimesh")


def box_robot(half=(0.1, 0.2, 0.3), centre=(0.0, 0.0, 1.0)):
    """A robot that is one box (link "link1"), tessellated like a robot's primitives."""
    prims = Primitives(
        np.array([BOX], np.int32), np.array([half], np.float64), np.array([centre], np.float64),
        np.eye(3)[None], np.array([labels.ROBOT], np.uint8),
    )  # fmt: skip
    return body_distance.robot_surface(
        prims, np.array([1]), Triangles.empty(), np.zeros(0, np.int64), ("link0", "link1")
    )


def body(kinds, sizes, centres, rots=None, parts=None):
    """A person-like set of primitives (humanoid.Primitives' fields)."""
    n = len(kinds)
    return SimpleNamespace(
        kind=np.array(kinds, np.int32),
        size=np.array(sizes, np.float64),
        center=np.array(centres, np.float64),
        rot=np.repeat(np.eye(3)[None], n, 0) if rots is None else np.array(rots, np.float64),
        label=np.array(parts or [labels.HAND] * n, np.uint8),
    )


def test_a_sphere_at_a_known_distance_from_a_box_link():
    surface = box_robot()
    # a hand ball of radius 5 cm, its centre 0.25 m beyond the box's +x face (x = 0.1)
    sep = body_distance.body_separation(
        surface, body([SPHERE], [(0.05, 0, 0)], [(0.35, 0.05, 1.1)])
    )
    assert sep.distance_m == pytest.approx(0.20, abs=1e-9)
    assert sep.link == "link1" and sep.part == labels.HAND
    np.testing.assert_allclose(sep.link_point_m, (0.1, 0.05, 1.1), atol=1e-9)
    np.testing.assert_allclose(sep.point_m, (0.30, 0.05, 1.1), atol=1e-9)


def test_a_slanted_capsule_and_a_box_face_are_measured_within_a_millimetre():
    surface = box_robot()
    # a forearm capsule (r 4 cm, half length 15 cm) tilted in the x-z plane beside the box:
    # its nearer end (x = 0.1 + 0.12 + 0.15 sin 30deg - ...) is what counts
    tilt = np.radians(60.0)
    rot = np.array([[np.cos(tilt), 0, np.sin(tilt)], [0, 1, 0], [-np.sin(tilt), 0, np.cos(tilt)]])
    centre = np.array([0.35, 0.0, 1.0])
    axis = rot[:, 2] * 0.15
    near_end_x = min((centre - axis)[0], (centre + axis)[0])
    sep = body_distance.body_separation(
        surface, body([CAPSULE], [(0.04, 0.15, 0)], [centre], [rot], [labels.LOWER_ARM])
    )
    assert sep.distance_m == pytest.approx(near_end_x - 0.04 - 0.1, abs=1e-3)
    assert sep.part == labels.LOWER_ARM
    # a foot box whose bottom face is 7 cm above the box's top (z = 1.3)
    sep = body_distance.body_separation(
        surface, body([BOX], [(0.12, 0.05, 0.03)], [(0.0, 0.1, 1.4)], parts=[labels.LEGS])
    )
    assert sep.distance_m == pytest.approx(0.07, abs=1e-3)
    assert sep.point_m[2] == pytest.approx(1.37, abs=1e-3)


def test_overlapping_bodies_read_zero():
    sep = body_distance.body_separation(box_robot(), body([SPHERE], [(0.1, 0, 0)], [(0.15, 0, 1)]))
    assert sep.distance_m == 0.0


@pytest.fixture(scope="module")
def sequence():
    return CellSequence(CellSequenceConfig(duration_s=20, fps=2, size=(160, 120)), seed=3)


def test_the_robot_loops_its_task_within_its_limits_and_speed(sequence):
    task, model = sequence.task, sequence.model
    t = np.linspace(0, 2 * task.period, 2001)
    q = np.array([task.at(v) for v in t])
    assert np.all(q >= model.lower - 1e-9) and np.all(q <= model.upper + 1e-9)
    speed = np.abs(np.diff(q, axis=0)) / np.diff(t)[:, None]
    assert speed.max() <= MAX_JOINT_SPEED * 1.01
    np.testing.assert_allclose(task.at(0.0), task.at(task.period), atol=1e-12)
    assert 3 <= len(task.waypoints) <= 5


@pytest.mark.slow
def test_people_walk_in_come_close_and_leave(sequence):
    times = np.arange(0, 20, 0.25)
    closest, farthest = np.inf, 0.0
    for t in times:
        for truth in sequence.truth_at(float(t)):
            closest = min(closest, truth.distance_m)
            farthest = max(farthest, truth.distance_m)
    assert closest < 0.5
    for i, visit in enumerate(sequence.visits):
        enter, arrive, *_, gone = visit.times
        assert person_at(visit, enter - 0.01) is None and person_at(visit, gone + 0.01) is None
        walking = [person_at(visit, enter + k * (arrive - enter) / 8) for k in range(8)]
        xy = np.array([(h.x, h.y) for h in walking])
        speed = np.linalg.norm(np.diff(xy, axis=0), axis=1) / ((arrive - enter) / 8)
        assert np.all((speed > 0.99) & (speed < 1.61))
        for h in walking:  # feet on the floor
            assert prims_z_range(h.primitives())[0] == pytest.approx(0.0, abs=1e-6)
        # each comes in from out of view
        assert not any(t.in_view for t in sequence.truth_at(enter + 0.01) if t.id == i)
    assert farthest > 2.0


def test_frames_carry_depth_labels_joints_and_truth_and_repeat_by_seed(sequence):
    frames = list(sequence.frames(8, 10))
    assert [f.index for f in frames] == [8, 9]
    f = frames[0]
    assert f.depth.dtype == np.uint16 and f.depth.shape == (120, 160)
    assert f.labels.shape == (120, 160)
    seen = set(np.unique(f.labels).tolist())
    assert {labels.ROBOT, labels.TABLE} <= seen
    assert np.all(f.labels[f.depth == 0] == labels.NO_DEPTH)
    assert f.joint_names == sequence.model.joint_names
    np.testing.assert_allclose(f.joint_positions, sequence.task.at(f.time_s))
    again = CellSequence(CellSequenceConfig(duration_s=20, fps=2, size=(160, 120)), seed=3)
    g = next(again.frames(8, 9))
    np.testing.assert_array_equal(g.depth, f.depth)
    np.testing.assert_array_equal(g.labels, f.labels)
    assert [p.to_dict() for p in g.persons] == [p.to_dict() for p in f.persons]


def test_the_recording_holds_depth_truth_joints_and_separations_and_its_cell_file(tmp_path):
    import tomllib

    import msgpack

    from topseg.core.formats import wire
    from topseg.core.formats.recording import read_messages
    from topseg.services.batch.datagen.cell_sequence import write_recording

    seq = CellSequence(CellSequenceConfig(duration_s=1.0, fps=4, size=(80, 60)), seed=3)
    out = tmp_path / "cell.mcap"
    done = write_recording(seq, out)
    assert done["frames"] == 4
    by_key = {}
    for msg in read_messages(out):
        by_key.setdefault(msg.key, []).append(msg)
    joints = "topseg/default/robot/panda/joints"
    assert sorted(by_key) == sorted(
        ["topseg/default/cam0/depth", "topseg/default/cam0/truth", joints,
         "topseg/default/safety/separation"]
    )  # fmt: skip
    depth = [wire.decode_depth(m.data) for m in by_key["topseg/default/cam0/depth"]]
    states = [msgpack.unpackb(m.data) for m in by_key[joints]]
    truths = [msgpack.unpackb(m.data) for m in by_key["topseg/default/safety/separation"]]
    assert [d.mount for d in depth] == [seq.mount] * 4
    for d, js, tr in zip(depth, states, truths, strict=True):
        assert js["v"] == 1 and js["stamp_ns"] == d.stamp_ns == tr["stamp_ns"]
        assert tuple(js["name"]) == seq.model.joint_names
        assert tr["seq"] == d.seq
    cell = tomllib.loads(out.with_suffix(".toml").read_text())
    assert cell["camera"][0] == {"name": "cam0", "x_m": 0.0, "y_m": 0.0, "yaw_deg": 0.0}
    r = cell["robot"]
    assert r["urdf"] == "panda" and r["joints_source"] == "zenoh"
    assert r["base_xyz_m"] == pytest.approx([seq.robot.x, seq.robot.y, 0.8], abs=1e-6)
    assert [z["kind"] for z in cell["zone"]] == ["protective", "warning"]


def test_two_cameras_see_the_same_cell_from_where_the_cell_file_hangs_them(tmp_path):
    """Each camera renders the cell moved by minus its position: the table's middle lies where
    each camera's placement projects it, the robot is in both, and the recording carries both
    cameras' depth and truth with a background each."""
    import tomllib

    from topseg.core.formats.recording import read_messages
    from topseg.core.safety.cell import cell_from_dict
    from topseg.core.safety.separation import camera_pixels
    from topseg.services.batch.datagen.cell_sequence import cell_toml, write_recording

    config = CellSequenceConfig(duration_s=1.0, fps=4, size=(160, 120), cameras=2)
    seq = CellSequence(config, seed=3)
    (x0, y0), (x1, y1) = seq.positions
    assert x0 == x1 == 0.0 and y0 == -y1 < 0
    # the views abut at head height: each camera's view there is as deep as they are apart
    k = config.mount().intrinsics
    assert y1 - y0 == pytest.approx((config.height_m - 1.8) * k.height / k.fy)
    cell = cell_from_dict(tomllib.loads(cell_toml(seq)), "sequence")
    assert [(c.name, c.x_m, c.y_m) for c in cell.cameras] == [
        ("cam0", 0.0, pytest.approx(y0)), ("cam0-2", 0.0, pytest.approx(y1))
    ]  # fmt: skip
    frame = next(seq.frames(0, 1))
    assert len(frame.views()) == 2
    top = np.array([[seq.table.x, seq.table.y, seq.table.height]])
    for (depth, lab), placement in zip(frame.views(), cell.cameras, strict=True):
        uv, _, inside = camera_pixels(top, seq.mount, placement)
        assert inside[0]
        assert lab[int(uv[0, 1]), int(uv[0, 0])] == labels.TABLE
        assert (lab == labels.ROBOT).any() and depth.shape == (120, 160)
    one = CellSequence(CellSequenceConfig(duration_s=1.0, fps=4, size=(160, 120)), seed=3)
    assert one.stage()[1][1] < seq.stage()[1][1]  # the two see more floor
    out = tmp_path / "cell.mcap"
    write_recording(seq, out)
    keys = {m.key for m in read_messages(out)}
    assert {"topseg/default/cam0/depth", "topseg/default/cam0-2/depth",
            "topseg/default/cam0-2/truth"} <= keys  # fmt: skip
    assert (tmp_path / "cell.background.npz").is_file()
    assert (tmp_path / "cell.cam0-2.background.npz").is_file()
