"""`topseg bridge ros2` as a real process on loopback Zenoh, read the way a ROS 2 node on
rmw_zenoh would: subscribers on rmw_zenoh's data keys, a liveliness query on `@ros2_lv`, a
transient-local late joiner for `/tf_static`.

The keys, hashes and token layout the test expects are written out here from rmw_zenoh's
design document (ros2/rmw_zenoh `docs/design.md` @ 99a6a2bd10b9), not taken from the code
under test; CDR is decoded by Foxglove's independent `mcap_ros2` decoder.
"""

from __future__ import annotations

import re
import struct
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory
from netutil import free_port, wait_for
from zenoh import ext

from topseg.core import labels as label_table
from topseg.core.camera import KINECT_V1, TopViewMount
from topseg.core.formats import ros2_messages as ros2
from topseg.core.formats import wire
from topseg.core.formats.rmw_zenoh import entity_gid
from topseg.services.runtime.zenoh_session import open_session

# RIHS01 hashes of the Jazzy messages (docs/research/ros2-interop-sources.md, section 2)
HASH = {
    "sensor_msgs/msg/Image": "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
    "sensor_msgs/msg/CameraInfo": "RIHS01_b3dfd68ff46c9d56c80fd3bd4ed22c7a4ddce8c8348f2f59c299e73118e7e275",
    "tf2_msgs/msg/TFMessage": "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
}  # fmt: skip
DDS = {
    "sensor_msgs/msg/Image": "sensor_msgs::msg::dds_::Image_",
    "sensor_msgs/msg/CameraInfo": "sensor_msgs::msg::dds_::CameraInfo_",
    "tf2_msgs/msg/TFMessage": "tf2_msgs::msg::dds_::TFMessage_",
}
#: rmw_zenoh's QoS text: reliable keep-last 10 volatile; reliable keep-last 1 transient local
QOS_DEFAULT, QOS_STATIC = "::,10:,:,:,,", ":1:,1:,:,:,,"
K = KINECT_V1.scaled_to(160, 120)
MODEL = Path(__file__).resolve().parent.parent / "models" / "default.npz"


def data_key(domain: int, topic: str, typename: str) -> str:
    """design.md: `<domain_id>/<fully_qualified_name>/<type_name>/<type_hash>`."""
    return f"{domain}/{topic.strip('/')}/{DDS[typename]}/{HASH[typename]}"


def decode(typename: str, payload: bytes):
    schema = Schema(
        id=1, name=typename, encoding="ros2msg", data=ros2.schema_text(typename).encode()
    )
    return DecoderFactory().decoder_for("cdr", schema)(payload)


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """design.md "Publishers": int64 LE sequence number, int64 LE source timestamp (ns),
    a 1-byte GID length (16) and the GID."""
    assert len(data) == 33, data.hex()
    seq, stamp, n = struct.unpack("<qqB", data[:17])
    assert n == 16
    return seq, stamp, data[17:]


class RosSide:
    """The test's Zenoh session as a ROS 2 reader: every sample on `<domain>/**`, decoded."""

    def __init__(self, port: int, domain: int):
        self.session = open_session(port=port)
        self.domain = domain
        self.samples: list[tuple[str, bytes, bytes | None]] = []
        self.lock = threading.Lock()
        self.session.declare_subscriber(f"{domain}/**", self._on_sample)

    def _on_sample(self, sample) -> None:
        att = sample.attachment.to_bytes() if sample.attachment is not None else None
        with self.lock:
            self.samples.append((str(sample.key_expr), sample.payload.to_bytes(), att))

    def on(self, topic: str, typename: str) -> list[tuple[bytes, bytes | None]]:
        key = data_key(self.domain, topic, typename)
        with self.lock:
            return [(p, a) for k, p, a in self.samples if k == key]

    def keys(self) -> set[str]:
        with self.lock:
            return {k for k, _, _ in self.samples}

    def tokens(self) -> list[str]:
        replies = self.session.liveliness().get(f"@ros2_lv/{self.domain}/**", timeout=5.0)
        return sorted(str(r.ok.key_expr) for r in replies if r.ok is not None)

    def close(self) -> None:
        self.session.close()


@pytest.fixture
def sessions():
    made = []
    yield made
    for s in made:
        s.close()


def check_tokens(tokens: list[str], domain: int, expected_topics: dict[str, tuple[str, str]]):
    """Every token against design.md's "Graph Cache" layout; {topic: token} of the publishers.

    node:      @ros2_lv/<domain>/<zid>/<nid>/<nid>/NN/<enclave>/<namespace>/<node>
    publisher: ... /<nid>/<id>/MP/<enclave>/<namespace>/<node>/<topic>/<type>/<hash>/<qos>
    with `/` in names replaced by `%`, `%` for an unset enclave or namespace.
    """
    nodes = [t for t in tokens if t.split("/")[5] == "NN"]
    pubs = [t for t in tokens if t.split("/")[5] == "MP"]
    assert len(nodes) == 1 and len(pubs) == len(tokens) - 1, tokens
    node = nodes[0].split("/")
    assert len(node) == 9
    admin, dom, zid, nid, eid, _, enclave, namespace, name = node
    assert (admin, dom, nid, eid) == ("@ros2_lv", str(domain), "0", "0")
    assert re.fullmatch(r"[0-9a-f]{1,32}", zid)
    assert (enclave, namespace, name) == ("%", "%", "topseg_bridge")
    found, ids = {}, set()
    for token in pubs:
        parts = token.split("/")
        assert len(parts) == 13 and all(parts), token
        assert parts[:4] == ["@ros2_lv", str(domain), zid, "0"]
        assert parts[6:9] == ["%", "%", "topseg_bridge"]
        assert parts[4].isdigit() and parts[4] not in ids | {"0"}
        ids.add(parts[4])
        topic = parts[9].replace("%", "/")
        typename, qos = expected_topics[topic]
        assert parts[10:] == [DDS[typename], HASH[typename], qos], token
        found[topic] = token
    assert sorted(found) == sorted(expected_topics)
    return found


def test_driver_frames_reach_a_ros2_reader_bit_exact_with_camera_info_tf_and_tokens(run, sessions):
    port, cell, camera = free_port(), "rb1", "cam0"
    ros = RosSide(port, 0)
    sessions.append(ros)
    wire_depth: dict[int, wire.DepthFrame] = {}  # the driver's frames by stamp

    def on_wire_depth(sample):
        frame = wire.decode_depth(sample.payload.to_bytes())
        wire_depth[frame.stamp_ns] = frame

    ros.session.declare_subscriber(wire.depth_key(cell, camera), on_wire_depth)
    bridge = run("bridge", "ros2", "--zenoh-port", port)
    bridge.wait_line("bridge ready", 60)
    driver = run(
        "driver", "--cell", cell, "--camera", camera, "--source", "synthetic", "--fps", "5",
        "--zenoh-port", port,
    )  # fmt: skip
    driver.wait_line("publishing", 120)
    topic = {s: ros2.ros2_topic(cell, camera, s) for s in ("depth", "labels", "camera_info")}
    wait_for(lambda: len(ros.on(topic["depth"], ros2.IMAGE)) >= 4, 120, "4 ROS depth images")
    driver.stop()

    # depth: the very pixels of the wire frame with the same stamp, 16UC1, the optical frame
    depth_msgs = ros.on(topic["depth"], ros2.IMAGE)
    matched = 0
    for payload, _ in depth_msgs:
        msg = decode(ros2.IMAGE, payload)
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        frame = wire_depth.get(stamp)
        if frame is None:  # a wire frame the test's own subscriber missed
            continue
        assert (msg.encoding, msg.is_bigendian, msg.header.frame_id) == (
            "16UC1", 0, ros2.optical_frame(cell, camera),
        )  # fmt: skip
        assert (msg.height, msg.width, msg.step) == (*frame.depth.shape, 2 * frame.depth.shape[1])
        got = np.frombuffer(bytes(msg.data), "<u2").reshape(frame.depth.shape)
        np.testing.assert_array_equal(got, frame.depth)
        matched += 1
    assert matched >= 3, f"{matched} of {len(depth_msgs)} ROS images matched a wire frame"
    any_frame = next(iter(wire_depth.values()))

    # camera info: the intrinsics of the wire frames, with every depth image
    infos = [decode(ros2.CAMERA_INFO, p) for p, _ in ros.on(topic["camera_info"], ros2.CAMERA_INFO)]
    assert len(infos) >= len(depth_msgs) - 1
    k = any_frame.intrinsics
    assert (infos[0].width, infos[0].height) == (k.width, k.height)
    np.testing.assert_allclose(infos[0].k, [k.fx, 0, k.cx, 0, k.fy, k.cy, 0, 0, 1])
    assert infos[0].header.frame_id == ros2.optical_frame(cell, camera)

    # labels: the test plays the worker for one frame; mono8, bit-exact, same stamp; every
    # class id, robot and object included
    ids = np.arange(k.height * k.width) % label_table.NUM_CLASSES
    labels = ids.astype(np.uint8).reshape(k.height, k.width)
    pub = ros.session.declare_publisher(
        wire.labels_key(cell, camera), congestion_control=zenoh.CongestionControl.BLOCK
    )
    pub.put(wire.encode_labels(wire.LabelFrame(labels, any_frame.seq, any_frame.stamp_ns, "")))
    wait_for(lambda: ros.on(topic["labels"], ros2.IMAGE), 60, "the ROS labels image")
    lab = decode(ros2.IMAGE, ros.on(topic["labels"], ros2.IMAGE)[0][0])
    assert (lab.encoding, lab.header.frame_id) == ("mono8", ros2.optical_frame(cell, camera))
    assert lab.header.stamp.sec * 10**9 + lab.header.stamp.nanosec == any_frame.stamp_ns
    np.testing.assert_array_equal(
        np.frombuffer(bytes(lab.data), np.uint8).reshape(labels.shape), labels
    )

    # liveliness tokens: one node, one publisher per topic, in rmw_zenoh's format
    tokens = ros.tokens()
    publishers = check_tokens(
        tokens,
        0,
        {
            topic["depth"]: (ros2.IMAGE, QOS_DEFAULT),
            topic["labels"]: (ros2.IMAGE, QOS_DEFAULT),
            topic["camera_info"]: (ros2.CAMERA_INFO, QOS_DEFAULT),
            "/tf_static": (ros2.TF_MESSAGE, QOS_STATIC),
        },
    )

    # attachments: increasing sequence numbers per publisher, the source time, the GID of the
    # publisher's token (XXH3-128, as rmw_zenoh derives it)
    t_end = time.time_ns()
    for name, typename in ((topic["depth"], ros2.IMAGE), (topic["camera_info"], ros2.CAMERA_INFO)):
        atts = [parse_attachment(a) for _, a in ros.on(name, typename)]
        seqs = [s for s, _, _ in atts]
        assert seqs[0] >= 1 and seqs == sorted(set(seqs))  # increasing; DROP may skip one
        assert all(0 < t_end - ts < 600e9 for _, ts, _ in atts)
        assert {g for _, _, g in atts} == {entity_gid(publishers[name])}

    # /tf_static to a late joiner, subscribed as rmw_zenoh subscribes a reliable
    # transient-local reader (history of late publishers, heartbeat recovery)
    got = []
    late = ext.declare_advanced_subscriber(
        ros.session,
        data_key(0, "/tf_static", ros2.TF_MESSAGE),
        lambda s: got.append((s.payload.to_bytes(), s.attachment.to_bytes())),
        history=ext.HistoryConfig(detect_late_publishers=True, max_samples=1),
        recovery=ext.RecoveryConfig(heartbeat=True),
        subscriber_detection=True,
    )
    try:
        wait_for(lambda: got, 60, "/tf_static from the bridge's cache")
    finally:
        late.undeclare()
    (tf,) = decode(ros2.TF_MESSAGE, got[0][0]).transforms
    assert (tf.header.frame_id, tf.child_frame_id) == (
        ros2.floor_frame(cell, camera),
        ros2.optical_frame(cell, camera),
    )
    assert any_frame.mount is not None  # the synthetic camera sends its mount
    t, q = ros2.mount_pose(any_frame.mount)
    tr, rot = tf.transform.translation, tf.transform.rotation
    np.testing.assert_allclose([tr.x, tr.y, tr.z], t, atol=1e-9)
    np.testing.assert_allclose([rot.x, rot.y, rot.z, rot.w], q, atol=1e-9)
    assert parse_attachment(got[0][1])[2] == entity_gid(publishers["/tf_static"])

    assert bridge.stop() == 0
    assert "0 rejected" in bridge.err
    wait_for(lambda: not ros.tokens(), 30, "the bridge's tokens to go")


@pytest.mark.slow  # the worker compiles and loads its model: ~40 s on 2 busy cores
def test_worker_labels_reach_a_ros2_reader_bit_exact(run, sessions):
    """driver -> worker -> bridge: the worker's label images, unchanged, as mono8 Images."""
    port, cell = free_port(), "rb3"
    ros = RosSide(port, 0)
    sessions.append(ros)
    wire_labels: dict[int, np.ndarray] = {}  # the worker's label images by stamp

    def on_wire_labels(sample):
        frame = wire.decode_labels(sample.payload.to_bytes())
        wire_labels[frame.stamp_ns] = frame.labels

    ros.session.declare_subscriber(wire.labels_key(cell, "cam0"), on_wire_labels)
    bridge = run("bridge", "ros2", "--cameras", f"{cell}/cam0", "--zenoh-port", port)
    worker = run("worker", "--model", MODEL, "--cameras", f"{cell}/cam0", "--zenoh-port", port)
    bridge.wait_line("bridge ready", 60)
    worker.wait_line("worker ready", 120)
    driver = run(
        "driver", "--cell", cell, "--source", "synthetic", "--fps", "5", "--zenoh-port", port
    )
    driver.wait_line("publishing", 120)
    topic = ros2.ros2_topic(cell, "cam0", "labels")

    def matched():
        found = 0
        for payload, _ in ros.on(topic, ros2.IMAGE):
            msg = decode(ros2.IMAGE, payload)
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            labels = wire_labels.get(stamp)
            if labels is not None:
                assert (msg.encoding, msg.header.frame_id) == (
                    "mono8",
                    ros2.optical_frame(cell, "cam0"),
                )
                got = np.frombuffer(bytes(msg.data), np.uint8).reshape(labels.shape)
                np.testing.assert_array_equal(got, labels)
                found += 1
        return found >= 3

    wait_for(matched, 120, "3 ROS label images equal to the worker's")
    for service in (driver, worker, bridge):
        assert service.stop() == 0


def test_other_domain_garbage_and_camera_limits(run, sessions):
    port, cell, domain = free_port(), "rb2", 7
    ros = RosSide(port, domain)
    other = RosSide(port, 0)
    sessions.extend([ros, other])
    bridge = run("bridge", "ros2", "--domain", domain, "--max-cameras", 2, "--zenoh-port", port)
    bridge.wait_line("bridge ready", 60)
    pubs = {}

    def put(camera, payload):
        key = wire.depth_key(cell, camera)
        if key not in pubs:
            pubs[key] = ros.session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK
            )
            wait_for(lambda: pubs[key].matching_status.matching, 30, "the bridge's subscriber")
        pubs[key].put(payload)

    def frame(seq):
        depth = np.full(K.shape, 1000 + seq, np.uint16)
        return wire.encode_depth(wire.DepthFrame(depth, K, seq, 10**18 + seq, ""))

    def images(camera):
        return ros.on(ros2.ros2_topic(cell, camera, "depth"), ros2.IMAGE)

    put("a", frame(1))
    wait_for(lambda: images("a"), 60, "camera a on domain 7")
    put("a", b"\xc1 not msgpack")  # garbage: dropped and counted
    put("a", frame(9)[:-3])  # a truncated message: dropped and counted
    put("9lives", frame(2))  # ROS 2 cannot spell it: ignored
    put("b", frame(3))
    wait_for(lambda: images("b"), 60, "camera b")
    put("c", frame(4))  # a third camera, over --max-cameras 2: ignored
    put("a", frame(5))
    wait_for(lambda: len(images("a")) == 2, 60, "camera a after the garbage")

    assert bridge.alive()
    assert [parse_attachment(att)[0] for _, att in images("a")] == [1, 2]  # one per message
    seen = decode(ros2.IMAGE, images("a")[1][0])
    assert np.all(np.frombuffer(bytes(seen.data), "<u2") == 1005)
    assert all(k.startswith(f"{domain}/topseg/{cell}/") for k in ros.keys())
    assert not images("c") and not images("9lives")
    assert not other.keys() and not other.tokens()  # nothing on domain 0
    topics = {
        ros2.ros2_topic(cell, cam, s): (ros2.CAMERA_INFO if s == "camera_info" else ros2.IMAGE,
                                        QOS_DEFAULT)
        for cam in ("a", "b") for s in ("depth", "labels", "camera_info")
    }  # fmt: skip
    check_tokens(ros.tokens(), domain, topics)

    assert bridge.stop() == 0
    err = bridge.err
    assert "2 rejected" in err.splitlines()[-1], err
    assert "2 ignored" in err.splitlines()[-1], err
    assert "9lives" in err and "not a ROS 2 topic name" in err
    assert "camera limit reached (--max-cameras 2)" in err


def test_a_silent_camera_leaves_the_ros_graph_and_frees_its_place(run, sessions):
    port, cell, domain = free_port(), "rb3", 5
    ros = RosSide(port, domain)
    sessions.append(ros)
    bridge = run(
        "bridge", "ros2", "--domain", domain, "--max-cameras", 1, "--forget-after", 1,
        "--zenoh-port", port,
    )  # fmt: skip
    bridge.wait_line("bridge ready", 60)

    def put(camera, seq):
        key = wire.depth_key(cell, camera)
        pub = ros.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        wait_for(lambda: pub.matching_status.matching, 30, "the bridge's subscriber")
        depth = np.full(K.shape, 1000 + seq, np.uint16)
        mount = TopViewMount(K, 3000.0 + seq)
        pub.put(wire.encode_depth(wire.DepthFrame(depth, K, seq, 10**18 + seq, "", mount)))
        pub.undeclare()

    def topics():
        return {t.split("/")[9].replace("%", "/") for t in ros.tokens() if t.split("/")[5] == "MP"}

    put("a", 1)
    wait_for(lambda: ros2.ros2_topic(cell, "a", "depth") in topics(), 60, "camera a's topics")
    # silent for over a second: its publishers' tokens go; /tf_static stays, now empty
    wait_for(lambda: topics() == {"/tf_static"}, 30, "camera a released")
    put("b", 2)  # the one place under --max-cameras 1 is free again
    wait_for(lambda: ros2.ros2_topic(cell, "b", "depth") in topics(), 60, "camera b's topics")
    # its transform comes on /tf_static, which may arrive after its topics' tokens
    wait_for(lambda: len(ros.on("/tf_static", ros2.TF_MESSAGE)) >= 3, 30, "b's transform")
    tf = [decode(ros2.TF_MESSAGE, p) for p, _ in ros.on("/tf_static", ros2.TF_MESSAGE)]
    assert [[t.child_frame_id for t in m.transforms] for m in tf[:3]] == [
        [ros2.optical_frame(cell, "a")],
        [],
        [ros2.optical_frame(cell, "b")],
    ]
    assert bridge.stop() == 0
    last = bridge.err.splitlines()[-1]
    assert "0 ignored" in last and "released" in last, bridge.err
    assert f"released {cell}/a: nothing for 1 s" in bridge.err


def test_depth_on_the_reserved_any_pair_or_a_bad_key_is_rejected_not_bridged(run, sessions):
    """`topseg/_any/_any/depth` (where a worker serving every camera holds its token) is
    not bridged as a camera `_any/_any`, nor a key with escape codes logged raw: both are
    rejected and counted, the key logged escaped; a real camera is bridged on."""
    port, cell, domain = free_port(), "rb4", 9
    ros = RosSide(port, domain)
    sessions.append(ros)
    bridge = run("bridge", "ros2", "--domain", domain, "--zenoh-port", port)
    bridge.wait_line("bridge ready", 60)
    depth = np.full(K.shape, 1500, np.uint16)
    frame = wire.encode_depth(wire.DepthFrame(depth, K, 1, 10**18, ""))
    # the first rejection is logged (then one line per 10 s): the one with escape codes
    for key in ("topseg/x\x1b[2J\r/cam0/depth", f"topseg/{wire.ANY}/{wire.ANY}/depth"):
        pub = ros.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        wait_for(lambda pub=pub: pub.matching_status.matching, 30, "the bridge's subscriber")
        pub.put(frame)
    real = ros.session.declare_publisher(
        wire.depth_key(cell, "cam0"), congestion_control=zenoh.CongestionControl.BLOCK
    )
    wait_for(lambda: real.matching_status.matching, 30, "the bridge's subscriber")
    real.put(frame)
    wait_for(lambda: ros.on(ros2.ros2_topic(cell, "cam0", "depth"), ros2.IMAGE), 60, "cam0")
    assert all(k.startswith(f"{domain}/topseg/{cell}/") for k in ros.keys()), ros.keys()
    assert bridge.stop() == 0
    err = bridge.err
    assert "2 rejected" in err.splitlines()[-1], err  # the reserved pair too
    assert "topseg/x\\x1b[2J\\r/cam0/depth" in err and "\x1b" not in err, err


@pytest.mark.parametrize(
    "args, error",
    [
        (["--domain", "300"], "--domain must be"),
        (
            ["--cameras", "c1/9lives"],
            "--cameras entry 'c1/9lives': '/topseg/c1/9lives/depth' is not",
        ),
    ],
)
def test_bad_options_are_one_line(run, args, error):
    bad = run("bridge", "ros2", *args, "--zenoh-port", free_port())
    assert bad.proc.wait(60) == 2
    bad._reader.join(5)
    assert bad.err.strip().splitlines()[-1].startswith(f"topseg bridge: error: {error}"), bad.err


def test_domain_comes_from_the_option_then_ros_domain_id(monkeypatch):
    from topseg.core.errors import TopsegError
    from topseg.services.live.bridge_ros2 import ros_domain

    monkeypatch.setenv("ROS_DOMAIN_ID", "5")
    assert (ros_domain(9), ros_domain(None)) == (9, 5)
    monkeypatch.setenv("ROS_DOMAIN_ID", "")
    assert ros_domain(None) == 0
    for bad in ("-1", "233", "five"):
        monkeypatch.setenv("ROS_DOMAIN_ID", bad)
        with pytest.raises(TopsegError, match="is not a ROS 2 domain id"):
            ros_domain(None)
