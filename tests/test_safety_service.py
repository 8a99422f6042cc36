"""`topseg safety` as a real process on loopback Zenoh: the test publishes rendered depth,
exact labels and the robot's joint states, and reads the states the service publishes."""

import threading
import time
from pathlib import Path

import pytest
import zenoh
from netutil import free_port, wait_for

from tests.safety_scenes import person, render
from topseg.core import labels
from topseg.core.formats import joint_states, safety_wire, wire
from topseg.core.formats.rmw_zenoh import topic_key
from topseg.core.safety.cell import load_cell
from topseg.core.safety.monitor import CellMonitor
from topseg.core.safety.robot import CellRobot
from topseg.services.live.safety import SafetyService
from topseg.services.runtime.zenoh_session import open_session

CELL_TOML = """
cell = "{cell}"
deadline_ms = 100
[robot]
name = "arm"
urdf = "panda"
base_xyz_m = [0.5, 0.0, 0.0]
[[camera]]
name = "cam0"
[[zone]]
name = "guard"
kind = "protective"
polygon_m = [[-1.4, -1.0], [-0.8, -1.0], [-0.8, -0.4], [-1.4, -0.4]]
"""


class CellPeer:
    """The test's session: publishes depth, labels and joints, keeps the safety states."""

    def __init__(self, port: int, cell: str) -> None:
        self.session = open_session(port=port)
        self.cell = cell
        self.states: list[tuple[float, safety_wire.SafetyState]] = []
        self.lock = threading.Lock()
        block = zenoh.CongestionControl.BLOCK
        self.depth = self.session.declare_publisher(wire.depth_key(cell), congestion_control=block)
        self.labels = self.session.declare_publisher(
            wire.labels_key(cell), congestion_control=block
        )
        self.joints = self.session.declare_publisher(joint_states.joints_key(cell, "arm"))
        self.session.declare_subscriber(safety_wire.safety_key(cell), self._on_state)

    def _on_state(self, sample) -> None:
        state = safety_wire.decode_safety(sample.payload.to_bytes())
        with self.lock:
            self.states.append((time.monotonic(), state))

    def since(self, t: float) -> list[safety_wire.SafetyState]:
        with self.lock:
            return [s for when, s in self.states if when >= t]

    def send(self, placement, robot, joints, people, seq: int, labels: bool = True) -> None:
        now = time.time_ns()
        self.joints.put(joint_states.encode_joint_state(
            joint_states.JointState(now, tuple(joints), tuple(joints.values()))))  # fmt: skip
        depth, lab = render(placement, robot, joints, people, seq=seq, stamp_ns=now)
        self.depth.put(wire.encode_depth(depth))
        if labels:
            self.labels.put(wire.encode_labels(lab))

    def close(self) -> None:
        self.session.close()


@pytest.fixture(scope="module")
def cell_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("cell") / "cell.toml"
    path.write_text(CELL_TOML.format(cell="safetytest"))
    return path


def test_the_service_decides_from_frames_and_stops_when_they_stop(run, cell_file):
    cell = load_cell(cell_file)
    robot = CellRobot(cell.robot, Path(cell_file).parent)
    port = free_port()
    svc = run("safety", "--cell", cell_file, "--zenoh-port", port)
    peer = CellPeer(port, "safetytest")
    try:
        svc.wait_line("deciding for cell safetytest")
        t0 = time.monotonic()
        wait_for(lambda: len(peer.since(t0)) >= 3, 30, "states before any frame")
        first = peer.since(t0)
        assert all(s.state == "stop" for s in first)
        assert "no labelled frame" in first[0].reasons[0]
        assert [s.seq for s in first] == sorted({s.seq for s in first})  # its own, in order

        joints = {n: 0.0 for n in robot.joint_names}
        joints["panda_joint4"] = -1.5
        seq = 0

        def send_until(people, state, what, parts=None):
            nonlocal seq
            t = time.monotonic()

            def said(s):
                return s.state == state and s.frame is not None and (not parts or s.part in parts)

            def got():
                nonlocal seq
                seq += 1
                peer.send(cell.cameras[0], robot, joints, people, seq)
                return any(said(s) for s in peer.since(t))

            wait_for(got, 30, what)
            return [s for s in peer.since(t) if said(s)][-1]

        clear = send_until([], "clear", "clear with nobody in view")
        # with the camera's mount from its first frame: how much of the robot's space it sees
        svc.wait_line("of the floor within")
        svc.wait_line("cam0: its labels are made without a recorded static background")
        assert clear.speed_scale == 1.0 and clear.min_distance_m is None
        assert clear.reaction_ms is not None and clear.reaction_ms < 5000
        near = send_until([person(0.9, 0.6)], "stop", "stop with a person at the robot")
        assert near.min_distance_m is not None and near.min_distance_m < 0.5
        # decided on before its labels came, the person is one of unknown part
        assert near.link.startswith("panda_")
        assert near.part in ("head", "body", "legs", "unidentified")
        named = send_until([person(0.9, 0.6)], "stop", "the nearest part named by the labels",
                           parts=("head", "body", "legs"))  # fmt: skip
        assert named.min_distance_m is not None and named.min_distance_m < 0.5
        assert near.nearest_m is not None and near.zones == {"guard": "clear"}
        send_until([], "clear", "clear again once the person left")

        # a driver's token that goes away (a killed driver) stops the cell before any deadline
        token = peer.session.liveliness().declare_token(
            wire.alive_key("safetytest", "cam0", "driver", "d1")
        )
        send_until([], "clear", "clear with the driver's token there")
        gone = time.monotonic()
        token.undeclare()
        wait_for(lambda: any("its driver went away" in " ".join(s.reasons) for s in peer.since(gone)),
                 10, "stop once the driver went away")  # fmt: skip
        token = peer.session.liveliness().declare_token(
            wire.alive_key("safetytest", "cam0", "driver", "d2")
        )
        send_until([], "clear", "clear once a driver is back")

        # the frames stop: `stop` once the deadline passed (how soon: `topseg bench safety`)
        quiet = time.monotonic()
        wait_for(lambda: any("no labelled frame for" in " ".join(s.reasons)
                             for s in peer.since(quiet)), 10, "stop after the frames stopped")  # fmt: skip
        stale = next(s for s in peer.since(quiet) if "no labelled frame for" in " ".join(s.reasons))
        assert stale.state == "stop" and stale.speed_scale == 0.0

        # garbage on its keys is dropped and counted; the service goes on
        peer.labels.put(b"\x93garbage")
        peer.joints.put(b"not msgpack at all")
        svc.wait_line("dropped a message on topseg/safetytest/cam0/labels")
        send_until([], "clear", "clear after the garbage")

        # the worker goes quiet while the driver goes on: every depth frame is still decided
        # on (the newest labels carried onto it) until those are older than the deadline
        labelled_seq, quiet = seq, time.monotonic()

        def depth_only():
            nonlocal seq
            seq += 1
            peer.send(cell.cameras[0], robot, joints, [], seq, labels=False)
            return any("no labelled frame for" in " ".join(s.reasons) for s in peer.since(quiet))

        wait_for(depth_only, 10, "stop once the labels are older than the deadline")
        carried = {s.frame[1] for s in peer.since(quiet) if s.frame is not None}
        assert carried & set(range(labelled_seq + 1, seq + 1))  # frames without labels decided
        stale = [s for s in peer.since(quiet) if "no labelled" in " ".join(s.reasons)]
        assert stale and all(s.state == "stop" and s.speed_scale == 0.0 for s in stale)
        assert svc.alive()
    finally:
        peer.close()
    assert svc.stop() == 0


def test_a_bad_cell_file_is_one_line_and_exit_2(run, tmp_path):
    bad = tmp_path / "cell.toml"
    bad.write_text(
        'cell = "x"\n[[zone]]\nname = "z"\nkind = "protective"\npolygon_m = [[0, 0], [1, 1]]\n'
    )
    svc = run("safety", "--cell", bad, "--zenoh-port", free_port())
    assert svc.proc.wait(60) == 2
    assert "zone" in svc.err and "Traceback" not in svc.err


def test_joint_states_from_ros2_give_the_robot_its_own_pixels(run, tmp_path):
    """The model read the whole arm as a person: with no joint state the service stops (a
    person, and a robot nowhere known); with the robot's ROS 2 /joint_states the arm's
    pixels are the robot's and the cell is clear."""
    path = tmp_path / "cell.toml"
    path.write_text(CELL_TOML.format(cell="rostest").replace(
        'base_xyz_m = [0.5, 0.0, 0.0]', 'base_xyz_m = [0.5, 0.0, 0.0]\njoints_source = "ros2"'))  # fmt: skip
    cell = load_cell(path)
    robot = CellRobot(cell.robot, tmp_path)
    joints = {n: 0.0 for n in robot.joint_names}
    joints["panda_joint4"] = -1.5
    port = free_port()
    svc = run("safety", "--cell", path, "--zenoh-port", port)
    peer = CellPeer(port, "rostest")
    ros = peer.session.declare_publisher(
        topic_key(0, "/joint_states", "sensor_msgs/msg/JointState")
    )
    seq = 0

    def send(with_joints: bool):
        nonlocal seq
        seq += 1
        now = time.time_ns()
        if with_joints:
            js = joint_states.JointState(now, tuple(joints), tuple(joints.values()))
            ros.put(joint_states.encode_ros2_joint_state(js))
        depth, lab = render(cell.cameras[0], robot, joints, [], seq=seq, stamp_ns=now)
        wrong = lab.labels.copy()
        wrong[wrong == labels.ROBOT] = labels.BODY
        peer.depth.put(wire.encode_depth(depth))
        peer.labels.put(wire.encode_labels(wire.LabelFrame(wrong, seq, now, "cam0")))

    def until(with_joints, predicate, what):
        t = time.monotonic()

        def got():
            send(with_joints)
            return any(predicate(s) for s in peer.since(t) if s.frame is not None)

        wait_for(got, 30, what)

    try:
        svc.wait_line("robot arm's joints (ros2)")
        until(False, lambda s: s.state == "stop" and "nowhere known" in " ".join(s.reasons),
              "stop without a joint state")  # fmt: skip
        until(True, lambda s: s.state == "clear", "clear with the ROS 2 joint states")
    finally:
        peer.close()
    assert svc.stop() == 0


def test_a_frame_is_not_decided_again_when_the_next_one_is_due_first(tmp_path):
    """In process: a frame decided with carried labels is decided again when its own labels
    come, unless the camera's next frame is due before that decision would be done."""
    path = tmp_path / "cell.toml"
    path.write_text('cell = "again"\n[[camera]]\nname = "cam0"\n')
    cell = load_cell(path)
    published = []
    service = SafetyService(cell, CellMonitor(cell, None), published.append, 0)
    depth_key, labels_key = wire.depth_key("again", "cam0"), wire.labels_key("again", "cam0")
    step_ns = 33_000_000

    def frame(seq, stamp_ns, received_ns):
        """Depth, decided on with the labels before it carried; then its own labels: whether
        they were decided on."""
        depth, lab = render(cell.cameras[0], people=[person(0.3, 0.2)], seq=seq,
                            stamp_ns=stamp_ns)  # fmt: skip
        service.handle(depth_key, wire.encode_depth(depth), received_ns)
        assert service.decide() == (seq > 1)  # the first has no labels to carry
        service.handle(labels_key, wire.encode_labels(lab), received_ns)
        return service.decide()

    now = time.time_ns()
    assert frame(1, now - 3 * step_ns, now - 3 * step_ns)
    # came 40 ms ago, frames 33 ms apart: the next is due, its own labels are not decided on
    assert not frame(2, now - 2 * step_ns, now - 40_000_000)
    assert service.counts["not_again"] == 1 and service.counts["carried"] == 1
    assert not service.decide()  # nor later
    # a second between frames: the next is far off, the frame is decided on again
    assert frame(3, now + 10**9, time.time_ns())
    assert service.counts["not_again"] == 1 and service.counts["frames"] == 4
