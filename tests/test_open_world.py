"""`topseg experiment open-world`'s figures on hand-made frames, and one small real run."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from topseg.core import labels as L
from topseg.core.camera import project
from topseg.core.sensors import get_sensor
from topseg.services.batch.experiment import open_world as ow
from topseg.services.batch.experiment.mounts import cell_mount

MOUNT = cell_mount("kinect_v1", 3.0, 0.0)


def frame(h=480, w=640):
    return np.zeros((h, w), np.uint8), np.full((h, w), 3000, np.uint16)


def person(x=0.0, y=0.0, pose="standing"):
    return {"x": x, "y": y, "z": 1.0, "pose": pose}


def test_robot_and_object_pixels_called_human_are_counted():
    truth, depth = frame()
    truth[100:200, 100:200] = L.ROBOT
    truth[300:320, 300:400] = L.OBJECT
    pred = truth.copy()
    pred[100:150, 100:200] = L.BODY  # half the robot called a body
    pred[300:302, 300:400] = L.HEAD  # a tenth of the object called a head
    t = ow.OpenWorldTally()
    t.add(truth, pred, depth, MOUNT, {"human": None})
    f = t.figures()
    assert f["robot_as_human"] == 0.5 and f["robot_as_robot"] == 0.5
    assert math.isclose(f["object_as_human"], 0.1)


def test_a_phantom_person_needs_150_cm2_in_a_frame_without_people():
    truth, depth = frame()
    area_px = ow.pixel_area_cm2(depth, MOUNT)[0, 0]
    side = math.ceil(math.sqrt(ow.PHANTOM_CM2 / area_px))
    small, big = truth.copy(), truth.copy()
    small[: side - 2, : side - 2] = L.BODY
    big[:side, :side] = L.BODY
    t = ow.OpenWorldTally()
    t.add(truth, small, depth, MOUNT, {"human": None})
    t.add(truth, big, depth, MOUNT, {"human": None})
    f = t.figures()
    assert f["empty_frames"] == 2 and f["phantom_frames"] == 0.5


def test_two_people_are_told_apart_by_their_projected_trunks():
    truth, depth = frame()
    left, right = person(-0.5, 0.0, "kneeling"), person(0.5, 0.0, "lying")
    uv = project(MOUNT.world_to_camera(np.array([[-0.5, 0.0, 1.0], [0.5, 0.0, 1.0]])),
                    MOUNT.intrinsics)  # fmt: skip
    for u, v in uv.round().astype(int):
        truth[v - 20 : v + 20, u - 20 : u + 20] = L.BODY
    pred = truth.copy()
    (u, v) = uv[1].round().astype(int)
    pred[v - 20 : v + 20, u - 20 : u + 20] = L.ROBOT  # the lying person is missed
    t = ow.OpenWorldTally()
    t.add(truth, pred, depth, MOUNT, {"human": left, "extra_humans": [right]})
    poses = t.figures()["poses"]
    assert poses["kneeling"] == {"found": 1, "visible": 1, "share": 1.0}
    assert poses["lying"] == {"found": 0, "visible": 1, "share": 0.0}


def test_a_small_run_writes_its_report(tmp_path, monkeypatch):
    monkeypatch.setattr(ow, "MOUNTS", ((3.0, 0.0),))
    report = ow.run_open_world(None, ["kinect_v1"], 2, tmp_path, progress=lambda _: None,
                               background=True)  # fmt: skip
    saved = json.loads((tmp_path / "open-world.json").read_text())
    assert saved["all"]["frames"] == 2 and "with_background" in saved
    assert set(report["verdict"]) == set(ow.TARGETS)
    text = (tmp_path / "open-world.md").read_text()
    assert "robot as human" in text and "with background" in text
    assert get_sensor("kinect_v1").name in text


@pytest.mark.slow
def test_every_sensor_and_mount_sees_its_own_cells():
    """600 frames are 600 scenes: no two (sensor, mount) pairs draw the same cells."""
    seeds = {ow.cells_seed(s, m) for s in range(4) for m in range(len(ow.MOUNTS))}
    assert len(seeds) == 4 * len(ow.MOUNTS)
    mount = cell_mount("kinect_v1", 3.0, 0.0)
    ((_, _, _, first, _),) = ow.render_cells(mount, 1, ow.cells_seed(0, 0))
    ((_, _, _, second, _),) = ow.render_cells(mount, 1, ow.cells_seed(0, 1))
    assert first != second


@pytest.mark.slow
def test_generated_cells_hold_only_random_arms_and_mesh_objects(tmp_path, monkeypatch):
    """`--cells generated`: robots and objects drawn from generators, not the catalogues."""
    mount = cell_mount("kinect_v1", 3.0, 0.0)
    scenes = [s for *_, s, _ in ow.render_cells(mount, 3, ow.GENERATED_SEED, cells="generated")]
    robots = [r["name"] for s in scenes for r in s.get("robots", [])]
    assert robots and all(name.startswith("random:") for name in robots)
    assert sum(len(s.get("mesh_objects", [])) for s in scenes) > 0
    monkeypatch.setattr(ow, "MOUNTS", ((3.0, 0.0),))
    report = ow.run_open_world(None, ["kinect_v1"], 1, tmp_path, progress=lambda _: None,
                               cells="generated")  # fmt: skip
    assert report["cells"] == "generated" and report["test_seed"] == ow.GENERATED_SEED
    assert "generated cells" in (tmp_path / "open-world.md").read_text()
    with pytest.raises(ValueError, match="cells must be one of"):
        ow.run_open_world(None, ["kinect_v1"], 1, tmp_path, cells="imagined")
