"""`topseg record` keeps the cells' safety states and the robots' joint states by default:
in the msgpack form as sent, in the ROS 2 form as JSON in std_msgs/String and as
sensor_msgs/JointState that ROS tools read; both read back as the wire messages, and replay
still reads the camera's frames."""

import json

import numpy as np
import pytest
from netutil import free_port
from rosbags.highlevel import AnyReader
from test_record import K, publisher, start_recorder

from topseg.core.formats import joint_states, recording, safety_wire, wire
from topseg.core.formats.ros2_recording_writer import Ros2RecordingWriter
from topseg.drivers.replay import RecordingFrames

assert publisher  # the fixture, imported for the tests below

CELL = "recsafe"


def cell_messages(n: int = 3) -> list[tuple[str, bytes]]:
    """A depth frame, a safety state and a joint state per step, as the wire sends them."""
    out = []
    for i in range(n):
        stamp = 10**18 + i * 10**8
        depth = np.full(K.shape, 1000 + i, np.uint16)
        out.append((wire.depth_key(CELL), wire.encode_depth(wire.DepthFrame(depth, K, i, stamp))))
        state = safety_wire.SafetyState(
            seq=i, stamp_ns=stamp, state=("clear", "warning", "stop")[i % 3],
            speed_scale=(1.0, 0.5, 0.0)[i % 3], min_distance_m=1.5 - 0.5 * i, part="hand",
            link="link7", reaction_ms=40.0 + i, reasons=(f"reason {i}",) if i else (),
            zones={"guard": "clear"}, nearest_m=((0.0, 0.0, 1.0), (1.0, 0.0, 1.0)),
            frame=("cam0", i),
        )  # fmt: skip
        out.append((safety_wire.safety_key(CELL), safety_wire.encode_safety(state)))
        joints = joint_states.JointState(stamp, ("j1", "j2"), (0.1 * i, -0.2 * i))
        out.append((joint_states.joints_key(CELL, "arm"), joint_states.encode_joint_state(joints)))
    return out


@pytest.mark.parametrize("form", ["msgpack", "ros2"])
def test_record_keeps_safety_and_joint_states_by_default(tmp_path, publisher, form):
    port, out = free_port(), tmp_path / f"{form}.mcap"
    msgs = cell_messages()
    proc = start_recorder(port, out, "--format", form, "--count", str(len(msgs)))
    pub = publisher(port, CELL)
    try:
        pub.wait_matched([k for k, _ in msgs])
        for key, data in msgs:
            pub.pub(key).put(data)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    back = [(m.key, m.data) for m in recording.read_messages(out)]
    # each key's messages, in order, as sent (the ROS 2 form rebuilds depth frames, with the
    # camera's name, which this test's frames leave out)
    keys = {k for k, _ in msgs} - ({wire.depth_key(CELL)} if form == "ros2" else set())
    assert keys >= {safety_wire.safety_key(CELL), joint_states.joints_key(CELL, "arm")}
    for key in keys:
        assert [d for k, d in back if k == key] == [d for k, d in msgs if k == key], key
    assert [f.seq for f in RecordingFrames(out)] == [0, 1, 2]  # replay reads the frames
    if form == "msgpack":
        return
    with AnyReader([out]) as bag:  # rosbags' rosbag2 reader: what ROS tools see
        types = {c.topic: c.msgtype for c in bag.connections}
        read = {}
        for conn, _, data in bag.messages():
            read.setdefault(conn.topic, []).append(bag.deserialize(data, conn.msgtype))
    assert types[f"/topseg/{CELL}/safety"] == "std_msgs/msg/String"
    assert types[f"/topseg/{CELL}/robot/arm/joints"] == "sensor_msgs/msg/JointState"
    states = [json.loads(m.data) for m in read[f"/topseg/{CELL}/safety"]]
    assert [s["state"] for s in states] == ["clear", "warning", "stop"]
    assert states[2]["speed_scale"] == 0.0 and states[1]["reasons"] == ["reason 1"]
    joints = read[f"/topseg/{CELL}/robot/arm/joints"]
    assert list(joints[2].name) == ["j1", "j2"]
    np.testing.assert_allclose(joints[2].position, [0.2, -0.4])
    assert joints[1].header.stamp.sec * 10**9 + joints[1].header.stamp.nanosec == 10**18 + 10**8


def test_the_ros2_form_refuses_a_bad_safety_state_and_reads_back_none_damaged(tmp_path):
    out = tmp_path / "bad.mcap"
    with Ros2RecordingWriter(out) as writer:
        with pytest.raises(wire.WireError):
            writer.write(safety_wire.safety_key(CELL), b"\x81\xa1v\x07")
        with pytest.raises(wire.WireError):
            writer.write(joint_states.joints_key(CELL, "arm"), b"not msgpack")
        key, data = cell_messages(1)[1]
        writer.write(key, data)
    assert [(m.key, m.data) for m in recording.read_messages(out)] == [(key, data)]
