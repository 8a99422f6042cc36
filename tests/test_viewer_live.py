"""The viewer's live sinks as real processes: Rerun's web viewer fetched over HTTP, and the
Foxglove WebSocket server spoken to as a Foxglove client would (its subprotocol, the
advertised channels, messages decoded with the protobuf schemas the server sends)."""

import base64
import json
import signal
import struct
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import zenoh
from netutil import Service, free_port, wait_for

from topseg.core import labels
from topseg.core.camera import KINECT_V1, PAPER_MOUNT, TopViewMount
from topseg.core.formats import ros2_messages, wire
from topseg.core.labelled_cloud import labelled_cloud
from topseg.core.synth.procedural import procedural_frame
from topseg.services.live import foxglove_layout
from topseg.services.live.viewer_foxglove import POINT_DTYPE, STATS_STREAM, STREAMS, topic
from topseg.services.runtime.zenoh_session import open_session

K = KINECT_V1.scaled_to(160, 120)
MOUNT = TopViewMount(K, PAPER_MOUNT.height_mm, pitch_deg=8.0, roll_deg=-4.0)
LAYOUT_FILE = Path(__file__).parents[1] / "docs" / "foxglove" / "topseg-layout.json"
#: the Foxglove SDK's WebSocket subprotocol (the SDK 0.30 server speaks this one)
SUBPROTOCOL = "foxglove.sdk.v1"
#: what the viewer advertises per stream: schema name and encoding
SCHEMAS = {
    "depth": "foxglove.RawImage",
    "labels": "foxglove.RawImage",
    "labels_color": "foxglove.RawImage",
    "camera_info": "foxglove.CameraCalibration",
    "points": "foxglove.PointCloud",
    "mount": "foxglove.FrameTransform",
}


def fetch(url: str, limit: int | None = None) -> tuple[str, bytes]:
    with urllib.request.urlopen(url, timeout=30) as reply:
        return reply.headers.get("Content-Type", ""), reply.read(limit)


def stop(service: Service) -> int:
    service.proc.send_signal(signal.SIGTERM)
    return service.proc.wait(timeout=60)


def test_web_serves_rerun_web_viewer_page_and_its_wasm():
    web, grpc = free_port(), free_port()
    viewer = Service(
        "viewer", "--web", "--web-port", web, "--grpc-port", grpc, "--zenoh-port", free_port()
    )
    try:
        viewer.wait_line("viewer ready")
        # the log names the page with the gRPC address the browser reads the data from
        assert f"http://localhost:{web}/?url=rerun%2Bhttp://" in viewer.err
        assert f":{grpc}/proxy" in viewer.err
        kind, page = fetch(f"http://127.0.0.1:{web}/")
        html = page.decode()
        assert "text/html" in kind and "<title>Rerun Viewer</title>" in html
        assert 'src="re_viewer.js"' in html and "re_viewer_bg.wasm" in html
        kind, js = fetch(f"http://127.0.0.1:{web}/re_viewer.js")
        assert "javascript" in kind and b"wasm" in js
        kind, wasm = fetch(f"http://127.0.0.1:{web}/re_viewer_bg.wasm", limit=4)
        assert kind == "application/wasm" and wasm == b"\0asm"
        assert stop(viewer) == 0, viewer.err
    finally:
        if viewer.alive():
            viewer.proc.kill()


class Publisher:
    """Publishes depth (with MOUNT) and labels of one camera on loopback Zenoh in a thread
    until stopped, and remembers every frame by its stamp."""

    def __init__(self, port: int, cell: str, camera: str):
        self.session = open_session(port=port)
        block = dict(congestion_control=zenoh.CongestionControl.BLOCK)
        self.pubs = {
            kind: self.session.declare_publisher(
                f"{wire.camera_prefix(cell, camera)}/{kind}", **block
            )
            for kind in ("depth", "labels", "stats")
        }
        self.sent: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.done = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)

    def run(self):
        rng = np.random.default_rng(7)
        seq = 0
        while not self.done.is_set():
            depth, truth = procedural_frame(rng, MOUNT)
            stamp = 10**18 + seq * 10**8
            self.sent[stamp] = depth, truth
            self.pubs["depth"].put(
                wire.encode_depth(wire.DepthFrame(depth, K, seq, stamp, mount=MOUNT))
            )
            self.pubs["labels"].put(wire.encode_labels(wire.LabelFrame(truth, seq, stamp)))
            timings = {"forest": 10.0 + seq, "crf": 5.0, "total": 16.0 + seq}
            stats = {"stamp_ns": stamp, "role": "worker", "seq": seq, "timings_ms": timings}
            self.pubs["stats"].put(wire.encode_stats({**stats, "counts": {"processed": seq}}))
            seq += 1
            self.done.wait(0.2)

    def close(self):
        self.done.set()
        self.thread.join(10)
        self.session.close()


def decoder(channel: dict):
    """A protobuf message class from the schema (a FileDescriptorSet) the server advertised."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    assert channel["schemaEncoding"] == "protobuf"
    files = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for f in files.file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))


#: seconds a subscribed topic may stay silent before `FoxgloveClient` subscribes to it again
RESUBSCRIBE_S = 5.0


class FoxgloveClient:
    """What a Foxglove client does on an open WebSocket: collect the advertised channels,
    subscribe, and decode the first message of each subscription with its schema."""

    def __init__(self, ws):
        self.ws = ws
        self.channels: dict[str, dict] = {}

    def wait_for_topics(self, topics: set[str], timeout: float) -> None:
        while not topics <= set(self.channels):  # a camera's channels come with its first frame
            message = self.ws.recv(timeout=timeout)
            if isinstance(message, str) and json.loads(message)["op"] == "advertise":
                self.channels.update({c["topic"]: c for c in json.loads(message)["channels"]})

    def first_messages(self, topics: list[str], timeout: float) -> dict:
        """The first message of each topic. A topic still silent after RESUBSCRIBE_S is
        subscribed again under a new id, as a client does when a server drops a subscription
        (a subscription that reaches a loaded server as it advertises the channel can be)."""
        subs: dict[int, dict] = {}
        got, statuses = {}, []
        deadline = time.monotonic() + timeout
        asked = -RESUBSCRIBE_S
        while len(got) < len(topics):
            missing = [t for t in topics if t not in got]
            assert time.monotonic() < deadline, (
                f"no message in {timeout} s on {missing}; server status: {statuses[-3:]}"
            )
            if time.monotonic() - asked >= RESUBSCRIBE_S:
                asked = time.monotonic()
                fresh = {len(subs) + i: self.channels[t] for i, t in enumerate(missing)}
                ws_subs = [{"id": i, "channelId": c["id"]} for i, c in fresh.items()]
                self.ws.send(json.dumps({"op": "subscribe", "subscriptions": ws_subs}))
                subs.update(fresh)
            try:
                data = self.ws.recv(timeout=RESUBSCRIBE_S)
            except TimeoutError:
                continue
            if isinstance(data, str):
                message = json.loads(data)
                if message.get("op") == "status":
                    statuses.append(message.get("message"))
            else:
                op, sub = struct.unpack_from("<BI", data)
                assert op == 1  # MessageData: op, subscription id, log time, payload
                channel, payload = subs[sub], data[13:]
                if channel["encoding"] == "json":
                    got.setdefault(channel["topic"], json.loads(payload))
                else:
                    got.setdefault(channel["topic"], decoder(channel).FromString(payload))
        return got


def test_foxglove_server_advertises_every_stream_and_serves_decodable_messages():
    from websockets.sync.client import connect

    cell, camera = wire.DEFAULT_CELL, wire.DEFAULT_CAMERA  # the layout file's camera
    zport, fport = free_port(), free_port()
    viewer = Service("viewer", "--foxglove", "--foxglove-port", fport, "--zenoh-port", zport)
    publisher = None
    try:
        viewer.wait_line("viewer ready")
        assert f"ws://127.0.0.1:{fport}" in viewer.err
        publisher = Publisher(zport, cell, camera)
        publisher.thread.start()
        with connect(f"ws://127.0.0.1:{fport}", subprotocols=[SUBPROTOCOL]) as ws:
            assert ws.subprotocol == SUBPROTOCOL
            client = FoxgloveClient(ws)
            streams = (*STREAMS, STATS_STREAM)
            client.wait_for_topics({topic(cell, camera, stream) for stream in streams}, 90)
            for stream, schema in SCHEMAS.items():
                channel = client.channels[topic(cell, camera, stream)]
                assert (channel["schemaName"], channel["encoding"]) == (schema, "protobuf")
            stats_channel = client.channels[topic(cell, camera, STATS_STREAM)]
            assert (stats_channel["encoding"], stats_channel["schemaEncoding"]) == (
                "json",
                "jsonschema",
            )
            schema = json.loads(stats_channel["schema"])
            assert {"timings_ms", "counts", "fps"} <= set(schema["properties"])
            # the layout file reads only topics the viewer serves
            layout = json.loads(LAYOUT_FILE.read_text())
            assert layout == foxglove_layout.layout(cell, camera), "regenerate the layout file"
            assert foxglove_layout.layout_topics(layout) <= set(client.channels)
            streams = ("points", "labels_color", "mount", "depth", STATS_STREAM)
            first = client.first_messages([topic(cell, camera, s) for s in streams], 90)
            got = {stream: first[topic(cell, camera, stream)] for stream in streams}
    finally:
        if publisher is not None:
            publisher.close()
        code = stop(viewer) if viewer.alive() else viewer.proc.returncode
    assert code == 0, viewer.err

    optical = ros2_messages.optical_frame(cell, camera)
    points = got["points"]
    assert points.frame_id == ros2_messages.floor_frame(cell, camera)
    stamp = points.timestamp.seconds * 10**9 + points.timestamp.nanos
    depth, truth = publisher.sent[stamp]
    expected = labelled_cloud(depth, truth, K, MOUNT, 4)  # the viewer's default --stride
    assert points.point_stride == POINT_DTYPE.itemsize
    assert [f.name for f in points.fields] == ["x", "y", "z", "red", "green", "blue", "alpha"]
    cloud = np.frombuffer(points.data, POINT_DTYPE)
    np.testing.assert_allclose(np.stack([cloud["x"], cloud["y"], cloud["z"]], 1), expected.xyz)
    np.testing.assert_array_equal(cloud["rgba"], expected.rgba())

    colours = got["labels_color"]
    assert (colours.encoding, colours.width, colours.height) == ("rgb8", K.width, K.height)
    assert colours.frame_id == optical and colours.step == 3 * K.width
    stamp = colours.timestamp.seconds * 10**9 + colours.timestamp.nanos
    image = np.frombuffer(colours.data, np.uint8).reshape(K.height, K.width, 3)
    np.testing.assert_array_equal(image, labels.colorize(publisher.sent[stamp][1]))

    mount = got["mount"]
    assert (mount.parent_frame_id, mount.child_frame_id) == (
        ros2_messages.floor_frame(cell, camera),
        optical,
    )
    translation, quaternion = ros2_messages.mount_pose(MOUNT)
    t, q = mount.translation, mount.rotation
    np.testing.assert_allclose([t.x, t.y, t.z], translation)
    np.testing.assert_allclose([q.x, q.y, q.z, q.w], quaternion)

    stats = got[STATS_STREAM]  # the stats message as it came, as JSON
    seq = stats["seq"]
    assert stats["timings_ms"] == {"forest": 10.0 + seq, "crf": 5.0, "total": 16.0 + seq}
    assert stats["counts"] == {"processed": seq} and stats["role"] == "worker"

    depth_image = got["depth"]
    assert (depth_image.encoding, depth_image.step) == ("16UC1", 2 * K.width)
    stamp = depth_image.timestamp.seconds * 10**9 + depth_image.timestamp.nanos
    np.testing.assert_array_equal(
        np.frombuffer(depth_image.data, "<u2").reshape(K.shape), publisher.sent[stamp][0]
    )


def test_foxglove_port_in_use_is_one_clear_line():
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        viewer = Service(
            "viewer", "--foxglove", "--foxglove-port", port, "--zenoh-port", free_port()
        )
        viewer.proc.wait(timeout=60)
        wait_for(lambda: "error" in viewer.err, 10, "the error line")
    assert viewer.proc.returncode == 2
    assert f"cannot serve Foxglove on 127.0.0.1:{port}" in viewer.err


@pytest.mark.slow
def test_driver_worker_viewer_foxglove_shows_the_labelled_cloud_in_the_floor_frame():
    """The real path: a synthetic camera (its mount on every frame), the bundled model's
    worker, and the viewer serving Foxglove; the cloud arrives on the floor, labelled."""
    from websockets.sync.client import connect

    zport, fport = free_port(), free_port()
    cell, camera = "fx1", "top"
    services = [
        Service("viewer", "--foxglove", "--foxglove-port", fport, "--zenoh-port", zport),
        Service("worker", "--crf", "none", "--zenoh-port", zport),
        Service(
            "driver", "--source", "synthetic:mount=random,seed=5", "--cell", cell,
            "--camera", camera, "--fps", 2, "--zenoh-port", zport,
        ),
    ]  # fmt: skip
    try:
        for service, line in zip(
            services, ("viewer ready", "worker ready", "publishing"), strict=True
        ):
            service.wait_line(line, timeout=120)
        points_topic, mount_topic = topic(cell, camera, "points"), topic(cell, camera, "mount")
        with connect(f"ws://127.0.0.1:{fport}", subprotocols=[SUBPROTOCOL]) as ws:
            client = FoxgloveClient(ws)
            client.wait_for_topics({topic(cell, camera, s) for s in STREAMS}, 120)
            got = client.first_messages([points_topic, mount_topic], 120)
    finally:
        codes = [stop(s) if s.alive() else s.proc.returncode for s in services]
    assert codes == [0, 0, 0], "\n".join(s.err for s in services)
    points, mount = got[points_topic], got[mount_topic]
    assert points.frame_id == ros2_messages.floor_frame(cell, camera)
    assert mount.child_frame_id == ros2_messages.optical_frame(cell, camera)
    cloud = np.frombuffer(points.data, POINT_DTYPE)
    assert len(cloud) > 1000
    # the floor is at z = 0 in the floor frame: most points lie near it, none far below it
    assert abs(np.median(cloud["z"])) < 0.1 and cloud["z"].min() > -0.5
    assert 0 < mount.translation.z < 5  # the camera hangs metres above the floor
    palette = {tuple(c) for c in labels.palette()[[lab.id for lab in labels.LABELS]]}
    assert {tuple(c[:3]) for c in cloud["rgba"]} <= palette
