"""`topseg bridge ros2 --cell` as a real process: a cell's safety state reaches a ROS 2
reader on rmw_zenoh's keys as std_msgs String and Float64 and zone / nearest-pair markers;
a cell whose states stop is published as stop. CDR is decoded by Foxglove's independent
`mcap_ros2` decoder."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import zenoh
from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory
from netutil import free_port, wait_for
from zenoh import ext

from topseg.core.formats import ros2_messages as ros2
from topseg.core.formats import safety_wire
from topseg.services.runtime.zenoh_session import open_session

#: std_msgs/msg/String's RIHS01 hash (docs/research/ros2-interop-sources.md)
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
CELL_TOML = """
cell = "rbs"
[[camera]]
name = "cam0"
x_m = 1.0
yaw_deg = 90.0
[[zone]]
name = "guard"
kind = "protective"
polygon_m = [[-1.4, -1.0], [-0.8, -1.0], [-0.8, -0.4], [-1.4, -0.4]]
z_max_m = 2.0
"""
AMBER = (255 / 255, 170 / 255, 0.0)


def decode(typename: str, payload: bytes):
    schema = Schema(
        id=1, name=typename, encoding="ros2msg", data=ros2.schema_text(typename).encode()
    )
    return DecoderFactory().decoder_for("cdr", schema)(payload)


class RosReader:
    """Every sample on domain 0, by key; a topic's messages by its key's prefix."""

    def __init__(self, port: int):
        self.session = open_session(port=port)
        self.samples: list[tuple[str, bytes]] = []
        self.lock = threading.Lock()
        self.session.declare_subscriber("0/**", self._on)

    def _on(self, sample) -> None:
        with self.lock:
            self.samples.append((str(sample.key_expr), sample.payload.to_bytes()))

    def on(self, topic: str, dds: str) -> list[tuple[str, bytes]]:
        prefix = f"0/{topic.strip('/')}/{dds}/RIHS01_"
        with self.lock:
            return [(k, p) for k, p in self.samples if k.startswith(prefix)]

    def states(self, cell: str) -> list[str]:
        found = self.on(ros2.safety_topic(cell, "state"), "std_msgs::msg::dds_::String_")
        return [decode(ros2.STRING, p).data for _, p in found]


@pytest.fixture
def reader():
    made = []
    yield lambda port: made.append(RosReader(port)) or made[-1]
    for r in made:
        r.session.close()


def test_safety_states_markers_and_a_silent_cell_reach_ros2(run, reader, tmp_path):
    cell_file, port = tmp_path / "cell.toml", free_port()
    cell_file.write_text(CELL_TOML)
    ros = reader(port)
    bridge = run(
        "bridge", "ros2", "--cell", cell_file, "--safety-timeout", "0.5", "--zenoh-port", port
    )
    bridge.wait_line("bridge ready", 60)
    block = dict(congestion_control=zenoh.CongestionControl.BLOCK)
    pub = ros.session.declare_publisher(safety_wire.safety_key("rbs"), **block)
    other = ros.session.declare_publisher(safety_wire.safety_key("rbx"), **block)
    warning = safety_wire.SafetyState(
        seq=1, stamp_ns=10**18 + 5, state="warning", speed_scale=0.5, min_distance_m=0.75,
        zones={"guard": "warning"}, nearest_m=((0.0, 0.0, 1.0), (0.75, 0.0, 1.0)),
        reasons=("person near",),
    )  # fmt: skip
    clear = safety_wire.SafetyState(seq=1, stamp_ns=10**18, state="clear", speed_scale=1.0)
    deadline = time.monotonic() + 60
    while "warning" not in ros.states("rbs") or "clear" not in ros.states("rbx"):
        assert time.monotonic() < deadline, bridge.err
        pub.put(safety_wire.encode_safety(warning))
        other.put(safety_wire.encode_safety(clear))
        time.sleep(0.1)
    pub.put(b"\x93garbage")  # dropped and counted; the bridge goes on
    first_silent = len(ros.states("rbs"))
    # no more states: the bridge says stop, speed scale 0
    wait_for(lambda: "stop" in ros.states("rbs")[first_silent:], 30, "stop for a silent cell")

    (key, _), *_ = ros.on(ros2.safety_topic("rbs", "state"), "std_msgs::msg::dds_::String_")
    assert key.endswith(STRING_HASH)
    scales = [
        decode(ros2.FLOAT64, p).data
        for _, p in ros.on(ros2.safety_topic("rbs", "speed_scale"), "std_msgs::msg::dds_::Float64_")
    ]
    assert 0.5 in scales and scales[-1] == 0.0

    markers = ros.on(
        ros2.safety_topic("rbs", "markers"), "visualization_msgs::msg::dds_::MarkerArray_"
    )
    assert markers, "no markers"
    array = decode(ros2.MARKER_ARRAY, markers[0][1])
    by_id = {(m.ns, m.id): m for m in array.markers}
    assert {m.header.frame_id for m in array.markers} == {"rbs_floor"}
    bottom, top, edges = (by_id["zone/guard", i] for i in range(3))
    assert (bottom.type, top.type, edges.type) == (4, 4, 5)  # LINE_STRIP, LINE_STRIP, LINE_LIST
    ring = [(p.x, p.y, p.z) for p in bottom.points]
    assert ring[0] == ring[-1] == (-1.4, -1.0, 0.0) and len(ring) == 5
    assert {p.z for p in top.points} == {2.0} and len(edges.points) == 8
    np.testing.assert_allclose((bottom.color.r, bottom.color.g, bottom.color.b), AMBER, atol=1e-6)
    arrow = by_id["nearest", 0]
    assert arrow.type == 0 and [(p.x, p.y, p.z) for p in arrow.points] == [
        (0.0, 0.0, 1.0), (0.75, 0.0, 1.0),
    ]  # fmt: skip
    assert by_id["nearest", 1].text == "0.75 m"
    stamp = array.markers[0].header.stamp
    assert stamp.sec * 10**9 + stamp.nanosec == warning.stamp_ns
    # a cell without the cell file: state and speed scale, no markers
    assert not ros.on(
        ros2.safety_topic("rbx", "markers"), "visualization_msgs::msg::dds_::MarkerArray_"
    )

    # /tf_static names the cell file's camera floor frame in the cell's
    got = []
    late = ext.declare_advanced_subscriber(
        ros.session,
        f"0/tf_static/tf2_msgs::msg::dds_::TFMessage_/{ros2.type_hash(ros2.TF_MESSAGE)}",
        lambda s: got.append(s.payload.to_bytes()),
        history=ext.HistoryConfig(detect_late_publishers=True, max_samples=1),
        recovery=ext.RecoveryConfig(heartbeat=True),
        subscriber_detection=True,
    )
    try:
        wait_for(lambda: got, 60, "/tf_static from the bridge's cache")
    finally:
        late.undeclare()
    (tf,) = decode(ros2.TF_MESSAGE, got[0]).transforms
    assert (tf.header.frame_id, tf.child_frame_id) == ("rbs_floor", "rbs_cam0_floor")
    t, q = tf.transform.translation, tf.transform.rotation
    np.testing.assert_allclose([t.x, t.y, t.z], [1.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose([q.x, q.y, q.z, q.w], [0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-9)

    assert bridge.stop() == 0
    assert "no valid safety state" in bridge.err and "1 rejected" in bridge.err
