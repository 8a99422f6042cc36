"""The cell monitor on rendered frames: people near and far, the robot's own pixels from its
joint state, a hand over a link, zones, and every fault that must give `stop`."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from tests.safety_scenes import MOUNT, person, render
from topseg.core import labels
from topseg.core.camera import depth_to_range
from topseg.core.formats.joint_states import JointState
from topseg.core.formats.wire import DepthFrame, LabelFrame
from topseg.core.safety.cell import cell_from_dict
from topseg.core.safety.monitor import CellMonitor, working_factor
from topseg.core.safety.robot import CellRobot

T0 = 1_800_000_000_000_000_000
MS = 1_000_000

CELL = {
    "cell": "c1",
    "robot": {"name": "panda", "urdf": "panda", "base_xyz_m": [0.5, 0.0, 0.0]},
    "camera": [{"name": "cam0"}],
    "zone": [
        {"name": "guard", "kind": "protective",
         "polygon_m": [[-1.4, -1.0], [-0.8, -1.0], [-0.8, -0.4], [-1.4, -0.4]]},
        {"name": "aisle", "kind": "warning",
         "polygon_m": [[-1.4, 0.3], [-0.6, 0.3], [-0.6, 1.0], [-1.4, 1.0]]},
    ],
}  # fmt: skip


@pytest.fixture(scope="module")
def cell():
    return cell_from_dict(CELL, "test cell", Path("."))


@pytest.fixture(scope="module")
def robot(cell):
    return CellRobot(cell.robot, Path("."))


@pytest.fixture(scope="module")
def joints(robot):
    values = {n: 0.0 for n in robot.joint_names}
    values["panda_joint4"] = -1.5  # the elbow bent: the arm reaches out along +x
    return values


def monitor_with_joints(cell, robot, joints, stamp_ns=T0) -> CellMonitor:
    mon = CellMonitor(cell, robot)
    mon.joint_state(JointState(stamp_ns, tuple(joints), tuple(joints.values())), stamp_ns)
    return mon


def decide(mon, cell, robot, joints, people, now=T0, **kw):
    depth, lab = render(cell.cameras[0], robot, joints, people, stamp_ns=now, **kw)
    view = mon.frame("cam0", depth, lab, now)
    return view, mon.decision(now + 20 * MS)


def test_nobody_in_view_is_clear(cell, robot, joints):
    mon = monitor_with_joints(cell, robot, joints)
    view, d = decide(mon, cell, robot, joints, [])
    assert view.faults == () and view.robot_source == "joints"
    assert d.decision.state == "clear" and d.decision.speed_scale == 1.0
    assert d.nearest is None and d.reaction_ms == pytest.approx(20.0)
    assert d.zones == {"guard": "clear", "aisle": "clear"}


def test_a_person_walking_up_slows_then_stops_the_robot(cell, robot, joints):
    mon = monitor_with_joints(cell, robot, joints)
    scales, distances = [], []
    for x in (-1.2, -0.4, 0.2, 0.9):
        _, d = decide(mon, cell, robot, joints, [person(x, 0.6)])
        distances.append(d.nearest.distance_m)
        scales.append(d.decision.speed_scale)
    assert distances == sorted(distances, reverse=True)
    assert scales == sorted(scales, reverse=True)
    assert d.decision.state == "stop" and d.decision.link.startswith("panda_")
    assert d.decision.part in ("head", "body", "legs")


def _capsule_distance(points, caps) -> np.ndarray:
    ab = caps.b - caps.a
    ap = points[:, None, :] - caps.a[None]
    t = np.clip((ap * ab).sum(2) / np.maximum((ab * ab).sum(1), 1e-12), 0, 1)
    gap = np.linalg.norm(ap - t[..., None] * ab, axis=2) - caps.radius
    return np.maximum(gap, 0).min(axis=1)


def _box_surface(centre, half, step=0.01) -> np.ndarray:
    axes = [np.arange(-h, h + 1e-9, step) for h in half]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    on_face = (np.abs(np.abs(grid) - half) < step / 2).any(axis=1)
    return grid[on_face] + centre


def test_the_separation_is_that_of_the_persons_body(cell, robot, joints):
    """The measured distance (from the pixels the camera sees) lies within 5 cm above the
    distance of the person's whole body to the robot's capsules, never below it."""
    mon = monitor_with_joints(cell, robot, joints)
    _, d = decide(mon, cell, robot, joints, [person(-0.6, 0.0)])
    body = np.concatenate([
        _box_surface(np.array([-0.6, 0.0, 0.45]), np.array([0.15, 0.1, 0.45])),
        _box_surface(np.array([-0.6, 0.0, 1.2]), np.array([0.2, 0.12, 0.3])),
    ])  # fmt: skip
    truth = _capsule_distance(body, robot.capsules(joints)).min()
    assert truth - 0.01 <= d.nearest.distance_m <= truth + 0.05


def test_robot_pixels_read_as_human_are_the_robot_with_a_fresh_joint_state(cell, robot, joints):
    """The model labelled the arm as a person: the joint state's silhouette gives those
    pixels back to the robot, so nobody is there; without a joint state they stand."""
    depth, lab = render(cell.cameras[0], robot, joints, [], stamp_ns=T0)
    wrong = lab.labels.copy()
    wrong[wrong == labels.ROBOT] = labels.BODY
    mislabelled = LabelFrame(wrong, lab.seq, lab.stamp_ns, lab.frame_id)
    mon = monitor_with_joints(cell, robot, joints)
    mon.frame("cam0", depth, mislabelled, T0)
    assert mon.decision(T0).decision.state == "clear"
    blind = CellMonitor(cell, robot)
    blind.frame("cam0", depth, mislabelled, T0)
    assert blind.views["cam0"].robot_source == "none"  # no robot pixel left to place it
    # a person and a robot nobody can place: stop
    assert blind.decision(T0).decision.state == "stop"
    assert "nowhere known" in blind.decision(T0).decision.reasons[0]


def test_a_stale_joint_state_leaves_the_models_robot_class(cell, robot, joints):
    mon = monitor_with_joints(cell, robot, joints, stamp_ns=T0 - 5000 * MS)
    view, d = decide(mon, cell, robot, joints, [person(0.9, 0.6)])
    assert view.robot_source == "labels"  # the robot's labelled pixels stand for it
    assert d.nearest is not None and d.nearest.link == "robot pixels"
    assert d.decision.state == "stop"


def test_a_hand_over_a_link_keeps_its_label(cell, robot, joints):
    """A hand 15 cm above the arm is in front of the rendered robot: still a person's."""
    caps = robot.capsules(joints)
    top = int(np.argmax(np.maximum(caps.a[:, 2], caps.b[:, 2])))
    tip = caps.b[top] if caps.b[top, 2] >= caps.a[top, 2] else caps.a[top]
    hand = (tip[0], tip[1], tip[2] + caps.radius[top] + 0.15)
    mon = monitor_with_joints(cell, robot, joints)
    view, d = decide(mon, cell, robot, joints, [person(1.2, 0.9, hand_at=hand)])
    assert (view.labels == labels.HAND).sum() > 20
    assert d.decision.state == "stop" and d.decision.part in ("hand", "lower-arm")


def test_small_blobs_are_noise(cell, robot, joints):
    depth, lab = render(cell.cameras[0], robot, joints, [], stamp_ns=T0)
    speck = lab.labels.copy()
    speck[10:13, 10:13] = labels.HEAD  # 9 px of ~1.3 cm: far below a person's area
    mon = monitor_with_joints(cell, robot, joints)
    mon.frame("cam0", depth, LabelFrame(speck, 0, T0, "cam0"), T0)
    assert mon.decision(T0).nearest is None


def test_zones(cell, robot, joints):
    mon = monitor_with_joints(cell, robot, joints)
    _, d = decide(mon, cell, robot, joints, [person(-1.0, 0.6)])
    assert d.zones["aisle"] == "warning" and d.decision.state in ("warning", "stop")
    _, d = decide(mon, cell, robot, joints, [person(-1.1, -0.7)])
    assert d.zones["guard"] == "stop" and d.decision.state == "stop"
    assert any("guard" in r for r in d.decision.reasons)


def test_a_protective_zone_the_camera_cannot_see_stops_the_robot(cell, robot, joints):
    depth, lab = render(cell.cameras[0], robot, joints, [], stamp_ns=T0)
    holes = depth.depth.copy()  # the guard's pixels blanked: its floor has no depth
    mon = monitor_with_joints(cell, robot, joints)
    masks = mon._masks("cam0", MOUNT, cell.cameras[0])
    holes[masks.mask("guard")] = 0
    mon.frame("cam0", DepthFrame(holes, MOUNT.intrinsics, 0, T0, "cam0", MOUNT), lab, T0)
    d = mon.decision(T0)
    assert d.decision.state == "stop" and d.zones["guard"] == "stop"
    assert any("guard" in r and "unseen" in r for r in d.decision.reasons)


def test_the_robots_own_shadow_does_not_stop_it(cell, robot, joints):
    """No depth right beside the robot (a structured-light shadow) inside a protective zone
    around it is explained by the robot and passes."""
    table = dict(CELL, zone=[{"name": "robot", "kind": "protective",
                              "polygon_m": [[0.2, -0.5], [1.6, -0.5], [1.6, 0.5], [0.2, 0.5]]}])  # fmt: skip
    robot_cell = cell_from_dict(table, "test cell", Path("."))
    depth, lab = render(robot_cell.cameras[0], robot, joints, [], stamp_ns=T0)
    shadowed = depth.depth.copy()
    arm = lab.labels == labels.ROBOT
    beside = np.roll(arm, 3, axis=1) & ~arm
    shadowed[beside] = 0
    mon = monitor_with_joints(robot_cell, robot, joints)
    mon.frame("cam0", DepthFrame(shadowed, MOUNT.intrinsics, 0, T0, "cam0", MOUNT), lab, T0)
    assert mon.decision(T0).decision.state == "clear"


def test_no_frame_yet_and_stale_frames_stop(cell, robot, joints):
    mon = monitor_with_joints(cell, robot, joints)
    d = mon.decision(T0)
    assert d.decision.state == "stop" and "no labelled frame yet" in d.decision.reasons[0]
    decide(mon, cell, robot, joints, [])
    assert mon.decision(T0 + 90 * MS).decision.state == "clear"
    late = mon.decision(T0 + 150 * MS)
    assert late.decision.state == "stop" and "150 ms" in late.decision.reasons[0]


def test_a_blinded_camera_stops(cell, robot, joints):
    depth, lab = render(cell.cameras[0], robot, joints, [], stamp_ns=T0)
    mon = monitor_with_joints(cell, robot, joints)
    covered = np.zeros_like(depth.depth)
    covered[:20] = 400  # a hand over the lens: a few rows of very near depth, the rest none
    mon.frame("cam0", DepthFrame(covered, MOUNT.intrinsics, 0, T0, "cam0", MOUNT), lab, T0)
    d = mon.decision(T0)
    assert d.decision.state == "stop" and "blinded" in d.decision.reasons[0]
    lens = np.full_like(depth.depth, 300)
    mon.frame("cam0", DepthFrame(lens, MOUNT.intrinsics, 0, T0, "cam0", MOUNT), lab, T0)
    assert "blinded" in mon.decision(T0).decision.reasons[0]


def test_a_camera_that_moved_stops(cell, robot, joints):
    """Frames rendered 3.0 m up but sent with the mount of 3.4 m: the floor is off."""
    depth, lab = render(cell.cameras[0], robot, joints, [], stamp_ns=T0)
    told = replace(MOUNT, height_mm=3400.0)
    mon = monitor_with_joints(cell, robot, joints)
    mon.frame("cam0", DepthFrame(depth.depth, MOUNT.intrinsics, 0, T0, "cam0", told), lab, T0)
    d = mon.decision(T0)
    assert d.decision.state == "stop" and "moved" in d.decision.reasons[0]


def test_a_frame_without_a_mount_stops(cell, robot, joints):
    depth, lab = render(cell.cameras[0], robot, joints, [], stamp_ns=T0)
    mon = monitor_with_joints(cell, robot, joints)
    mon.frame("cam0", DepthFrame(depth.depth, MOUNT.intrinsics, 0, T0, "cam0"), lab, T0)
    assert "no mount" in mon.decision(T0).decision.reasons[0]


def test_two_cameras_see_more_than_one(robot, joints):
    """The person stands where only the second camera sees them: the cell still stops."""
    table = dict(CELL, camera=[{"name": "cam0"}, {"name": "cam1", "x_m": 2.5}], zone=[])
    two = cell_from_dict(table, "test cell", Path("."))
    mon = monitor_with_joints(two, robot, joints)
    for placement in two.cameras:
        depth, lab = render(placement, robot, joints, [person(2.2, 0.0)], stamp_ns=T0,
                            name=placement.name)  # fmt: skip
        mon.frame(placement.name, depth, lab, T0)
    assert mon.views["cam0"].nearest is None and mon.views["cam1"].nearest is not None
    d = mon.decision(T0)
    assert d.frame[0] == "cam1" and d.nearest is mon.views["cam1"].nearest


def test_a_joint_state_that_misses_joints_is_refused(cell, robot, joints):
    mon = CellMonitor(cell, robot)
    with pytest.raises(ValueError, match="panda_joint"):
        mon.joint_state(JointState(T0, ("panda_joint1",), (0.0,)), T0)
    assert mon.counts["joint_states_refused"] == 1 and mon.joints is None


def test_a_full_resolution_frame_is_read_at_the_working_resolution():
    big = replace(MOUNT, intrinsics=MOUNT.intrinsics.scaled_to(640, 480))
    small = replace(MOUNT, intrinsics=MOUNT.intrinsics.scaled_to(160, 120))
    assert working_factor(big) == 4 and working_factor(MOUNT) == 2 and working_factor(small) == 1


def test_a_driver_that_went_away_stops_the_cell_at_once(cell, robot, joints):
    mon = monitor_with_joints(cell, robot, joints)
    mon.token("cam0", "driver", "a1", True)
    mon.token("cam0", "viewer", "v1", True)  # not watched
    decide(mon, cell, robot, joints, [])
    assert mon.decision(T0).decision.state == "clear"
    mon.token("cam0", "viewer", "v1", False)
    assert mon.decision(T0).decision.state == "clear"
    mon.token("cam0", "driver", "a1", False)
    d = mon.decision(T0)  # the frame is fresh, but its driver is gone
    assert d.decision.state == "stop" and d.decision.reasons == ("cam0: its driver went away",)
    mon.token("cam0", "driver", "a2", True)  # a restarted driver
    assert mon.decision(T0).decision.state == "clear"


def test_a_pedestal_read_as_legs_is_the_robots(joints):
    """A robot on a 0.8 m column: the column's pixels read as legs are the robot's too."""
    table = dict(CELL, robot=dict(CELL["robot"], base_xyz_m=[0.5, 0.0, 0.8],
                                  pedestal="cylinder", pedestal_size_m=0.15), zone=[])  # fmt: skip
    raised = cell_from_dict(table, "test cell", Path("."))
    robot = CellRobot(raised.robot, Path("."))
    depth, lab = render(raised.cameras[0], robot, joints, [], stamp_ns=T0)
    column = (lab.labels == labels.ROBOT) & (depth.depth > 3000 - 900)  # below the arm's base
    assert column.sum() > 50
    wrong = lab.labels.copy()
    wrong[column] = labels.LEGS
    mon = monitor_with_joints(raised, robot, joints)
    mon.frame("cam0", depth, LabelFrame(wrong, 0, T0, "cam0"), T0)
    assert mon.decision(T0).decision.state == "clear"
    assert mon.views["cam0"].nearest is None


def test_a_person_read_as_robot_away_from_the_robot_is_a_person(cell, robot, joints):
    """The model read a whole person beside the robot as robot: with the robot placed by its
    joint state, robot pixels outside its silhouette are not the robot, so the person stands."""
    depth, lab = render(cell.cameras[0], robot, joints, [person(0.9, 0.6)], stamp_ns=T0)
    wrong = lab.labels.copy()
    wrong[np.isin(wrong, labels.HUMAN_IDS)] = labels.ROBOT
    mon = monitor_with_joints(cell, robot, joints)
    view = mon.frame("cam0", depth, LabelFrame(wrong, 0, T0, "cam0"), T0)
    d = mon.decision(T0)
    assert d.decision.state == "stop" and view.nearest is not None
    assert d.decision.part == "body"
    # a speck of stray robot pixels is not a person
    speck = lab.labels.copy()
    speck[np.isin(speck, labels.HUMAN_IDS)] = labels.BACKGROUND
    speck[5:8, 5:8] = labels.ROBOT
    mon.frame("cam0", depth, LabelFrame(speck, 1, T0, "cam0"), T0)
    assert mon.views["cam0"].nearest is None
    # nor is a flat table top in a corner, 0.7 m above the floor, read as robot
    table_depth = depth.depth.copy()
    table_depth[190:230, 10:70] = 2300
    table = speck.copy()
    table[190:230, 10:70] = labels.ROBOT
    flat = DepthFrame(table_depth, depth.intrinsics, 2, T0, "cam0", depth.mount)
    mon.frame("cam0", flat, LabelFrame(table, 2, T0, "cam0"), T0)
    assert mon.views["cam0"].nearest is None
    # but the same patch with the heights of a person (head 1.7 m, shoulders 1.4 m) is one
    person_depth = table_depth.copy()
    person_depth[200:215, 30:50] = 1300
    tall = DepthFrame(person_depth, depth.intrinsics, 3, T0, "cam0", depth.mount)
    mon.frame("cam0", tall, LabelFrame(table, 3, T0, "cam0"), T0)
    assert mon.views["cam0"].nearest is not None


def test_a_camera_that_sends_range_is_read_like_one_that_sends_depth(cell, robot, joints):
    """The same frame sent as range along each ray by a `radial` camera: the same person at
    the same distance (its frames are turned into depth once, not twice)."""
    depth, lab = render(cell.cameras[0], robot, joints, [person(0.9, 0.6)], stamp_ns=T0)
    plain = monitor_with_joints(cell, robot, joints)
    plain.frame("cam0", depth, lab, T0)
    radial = replace(MOUNT, radial=True)
    ranged = depth_to_range(depth.depth, MOUNT.intrinsics)
    mon = monitor_with_joints(cell, robot, joints)
    mon.frame("cam0", DepthFrame(ranged, MOUNT.intrinsics, 0, T0, "cam0", radial), lab, T0)
    assert mon.views["cam0"].faults == ()
    a, b = plain.views["cam0"].nearest, mon.views["cam0"].nearest
    assert b.distance_m == pytest.approx(a.distance_m, abs=0.005)


def test_set_joints_holds_an_older_state_that_joint_state_passes_over(cell, robot, joints):
    mon = monitor_with_joints(cell, robot, joints)
    older = JointState(T0 - 10**9, robot.joint_names, tuple(v + 0.1 for v in joints.values()))
    mon.joint_state(older, T0)  # a late state: the newer one stays
    assert mon.joints.stamp_ns == T0
    mon.set_joints(older, T0)
    assert mon.joints is older and mon.counts["joint_states"] == 2
    mon.set_joints(None)
    assert mon.joints is None and mon.fresh_joints(T0) is None


def test_a_sliver_of_a_person_at_the_image_edge_is_a_person_but_a_speck_inside_is_not(
    cell, robot, joints
):
    """A person stepping into view shows a few leg pixels at the edge: too small to pass as a
    person anywhere else, but the edge cuts them, so they stand; the same speck inside the
    image is noise."""
    depth, lab = render(cell.cameras[0], robot, joints, [], stamp_ns=T0)
    legs_depth = depth.depth.copy()
    mon = monitor_with_joints(cell, robot, joints)
    for seq, cols in ((1, slice(0, 3)), (2, slice(40, 43))):  # at the edge, then inside
        sliver = lab.labels.copy()
        sliver[20:26, cols] = labels.LEGS
        legs_depth[20:26, cols] = 2300
        frame = DepthFrame(legs_depth, depth.intrinsics, seq, T0, "cam0", depth.mount)
        mon.frame("cam0", frame, LabelFrame(sliver, seq, T0, "cam0"), T0)
        at_edge = mon.views["cam0"].nearest is not None
        assert at_edge == (seq == 1)


def _two_camera_cell(zones=()):
    cameras = [{"name": "cam0"}, {"name": "cam1", "x_m": 0.8}]
    return cell_from_dict(dict(CELL, camera=cameras, zone=list(zones)), "test cell", Path("."))


def test_what_another_camera_sees_otherwise_is_checked_point_by_point(robot, joints):
    """`seen_otherwise` against a camera that sees a person, the floor and a box."""
    from tests.safety_scenes import _prims
    from topseg.core.safety.monitor import seen_otherwise, sight
    from topseg.core.synth.geometry import BOX

    two = _two_camera_cell()
    other = two.cameras[1]
    box = _prims([BOX], [(0.2, 0.2, 0.4)], [(0.8, 0.9, 0.4)], [labels.STORAGE])
    depth, lab = render(other, None, None, [person(0.8, -0.6), box], name="cam1")
    seen = sight(depth.depth, lab.labels, MOUNT, other)
    points = np.array([
        [0.8, -0.6, 1.5],  # on the person's body: a person there
        [0.2, 0.0, 1.0],  # in the air over the open floor: it sees past it
        [0.8, 0.9, 0.8],  # on the box's top: a surface that is no person
        [0.8, 0.9, 0.3],  # inside the box, under its top: hidden from it
        [9.0, 9.0, 1.0],  # outside its image
    ])  # fmt: skip
    assert seen_otherwise(points, seen).tolist() == [False, True, True, False, False]


def test_a_second_camera_drops_a_phantom_the_first_read_on_open_floor(robot, joints, monkeypatch):
    """Camera 0's labels put legs on open floor beside the robot; camera 1 sees floor there:
    the nearest pair is the real person's and the zone around the robot is not held. One
    camera alone keeps the phantom, and so does the monitor with the check off."""
    from topseg.core.safety import monitor as monitor_module

    guard = {"name": "guard", "kind": "protective",
             "polygon_m": [[0.3, -0.7], [0.7, -0.7], [0.7, 0.7], [0.3, 0.7]]}  # fmt: skip
    two = _two_camera_cell([guard])
    people = [person(-0.9, 0.0)]
    frames = {c.name: render(c, robot, joints, people, stamp_ns=T0, name=c.name)
              for c in two.cameras}  # fmt: skip
    depth0, lab0 = frames["cam0"]
    phantom = lab0.labels.copy()
    k = MOUNT.intrinsics
    # 16 cm of floor 0.35-0.5 m beside the robot's base
    rows, cols = int(k.cy) + 30, int(k.cx) + int(0.5 * k.fx / 3.0)
    patch = (slice(rows, rows + 14), slice(cols - 7, cols + 7))
    phantom[patch] = labels.LEGS
    assert (lab0.labels[patch] == labels.BACKGROUND).all()
    frames["cam0"] = (depth0, LabelFrame(phantom, 0, T0, "cam0"))

    def seen_by(cameras):
        mon = monitor_with_joints(two, robot, joints)
        for name in cameras:
            mon.frame(name, *frames[name], T0)
        return mon.gathered(T0)

    real = seen_by(["cam1"])
    assert real.nearest is not None and real.nearest.distance_m > 1.0
    assert real.occupied == []
    alone = seen_by(["cam0"])  # the phantom, read alone
    assert alone.nearest.distance_m < 0.6 and alone.occupied == ["guard"]
    both = seen_by(["cam0", "cam1"])
    assert both.nearest.distance_m == pytest.approx(real.nearest.distance_m, abs=0.03)
    assert both.occupied == []
    monkeypatch.setattr(monitor_module, "CROSS_CHECK", False)
    unchecked = seen_by(["cam0", "cam1"])
    assert unchecked.nearest.distance_m < 0.6 and unchecked.occupied == ["guard"]


def test_a_person_both_cameras_see_keeps_their_nearest_point(robot, joints):
    two = _two_camera_cell()
    people = [person(0.0, -0.5, hand_at=(0.3, -0.25, 1.0))]
    mon = monitor_with_joints(two, robot, joints)
    for c in two.cameras:
        mon.frame(c.name, *render(c, robot, joints, people, stamp_ns=T0, name=c.name), T0)
    alone = min(v.nearest.distance_m for v in mon.views.values())
    assert mon.decision(T0).nearest.distance_m == pytest.approx(alone, abs=0.01)


def test_one_of_two_cameras_going_quiet_stops_the_cell(robot, joints):
    """The other camera's fresh view cannot stand in for a camera whose labels stopped, nor
    check another's points with a stale one."""
    two = _two_camera_cell()
    mon = monitor_with_joints(two, robot, joints)
    for c in two.cameras:
        mon.frame(c.name, *render(c, robot, joints, [], stamp_ns=T0, name=c.name), T0)
    assert mon.decision(T0 + 50 * MS).decision.state == "clear"
    later = T0 + 120 * MS
    c1 = two.cameras[1]
    mon.frame(c1.name, *render(c1, robot, joints, [], stamp_ns=later, name=c1.name), later)
    d = mon.decision(later + 10 * MS)
    assert d.decision.state == "stop"
    assert any(r.startswith("cam0: no labelled frame for") for r in d.decision.reasons)
    assert not any(r.startswith("cam1") for r in d.decision.reasons)


def test_a_decision_taken_again_between_frames_checks_nothing_again(robot, joints, monkeypatch):
    from topseg.core.safety import monitor as monitor_module

    calls = []
    real = monitor_module.cross_checked
    monkeypatch.setattr(monitor_module, "cross_checked", lambda *a: calls.append(1) or real(*a))
    two = _two_camera_cell()
    mon = monitor_with_joints(two, robot, joints)
    people = [person(0.0, -0.5)]
    for c in two.cameras:
        mon.frame(c.name, *render(c, robot, joints, people, stamp_ns=T0, name=c.name), T0)
    first = mon.decision(T0 + 10 * MS)
    assert len(calls) == 2  # each camera's view against the other's
    again = mon.decision(T0 + 40 * MS)
    assert len(calls) == 2 and again.nearest is first.nearest
    c0 = two.cameras[0]
    mon.frame(c0.name, *render(c0, robot, joints, people, stamp_ns=T0, name=c0.name), T0)
    mon.decision(T0 + 50 * MS)
    assert len(calls) == 4  # a new view: both checked again


def test_a_zone_part_only_the_second_camera_sees_going_dark_stops_the_cell(robot, joints):
    """Camera 0 sees its part of the zone clearly; the part only camera 1 looks at has no
    depth there: unknown space, so the cell stops, though camera 0 alone has nothing
    unseen."""
    guard = {"name": "far", "kind": "protective",
             "polygon_m": [[1.0, -0.3], [2.5, -0.3], [2.5, 0.3], [1.0, 0.3]]}  # fmt: skip
    two = _two_camera_cell([guard])
    k = MOUNT.intrinsics
    c0, c1 = two.cameras
    frames = {c.name: render(c, robot, joints, [], stamp_ns=T0, name=c.name) for c in two.cameras}

    def decided(dark: bool):
        mon = monitor_with_joints(two, robot, joints)
        for c in two.cameras:
            depth, lab = frames[c.name]
            if dark and c is c1:  # nothing beyond 1.9 m in the cell frame (1.1 m from it)
                d = depth.depth.copy()
                d[:, int(k.cx + 1.1 * k.fx / 3.0) :] = 0
                depth = DepthFrame(d, depth.intrinsics, 0, T0, c.name, depth.mount)
            view = mon.frame(c.name, depth, lab, T0)
            if c is c0:
                assert view.unseen["far"] == 0.0  # camera 0 sees all of the zone it looks at
        return mon.decision(T0 + 10 * MS).decision

    assert decided(False).state == "clear"
    dark = decided(True)
    assert dark.state == "stop"
    assert any(r.startswith("protective zone far") and "unseen" in r for r in dark.reasons)
