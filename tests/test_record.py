"""`topseg record` as a real process: the MCAP it writes holds exactly the bytes published."""

import os
import re
import resource
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import zenoh
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from netutil import free_port, wait_for
from rosbags.highlevel import AnyReader
from test_systemd_notify import NotifySocket

from topseg.core.camera import KINECT_V1, TopViewMount
from topseg.core.formats import recording, wire
from topseg.core.formats import ros2_messages as ros2
from topseg.drivers.replay import RecordingFrames
from topseg.services.runtime.zenoh_session import open_session

K = KINECT_V1.scaled_to(160, 120)


def start_recorder(port, out, *extra, preexec_fn=None, notify=None):
    """The recorder as a process; with `notify` (a NotifySocket) as its systemd socket, whose
    STATUS= line counts what it recorded."""
    cmd = [sys.executable, "-m", "topseg.services.cli", "-v", "record", "--out", str(out)]
    cmd += ["--zenoh-port", str(port), *extra]
    env = None
    if notify is not None:
        env = dict(os.environ, NOTIFY_SOCKET=notify.address, WATCHDOG_USEC="200000")
        env.pop("WATCHDOG_PID", None)
    return subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=preexec_fn,
        env=env,
    )  # fmt: skip


class Publisher:
    """The test's own session, publishing wire messages under BLOCK (nothing lost)."""

    def __init__(self, port, cell):
        self.session = open_session(port=port)
        self.cell = cell
        self.pubs = {}

    def pub(self, key):
        if key not in self.pubs:
            self.pubs[key] = self.session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK
            )
        return self.pubs[key]

    def wait_matched(self, keys, timeout=20.0):
        deadline = time.monotonic() + timeout
        while not all(self.pub(k).matching_status.matching for k in keys):
            assert time.monotonic() < deadline, "the recorder never subscribed"
            time.sleep(0.02)

    def close(self):
        self.session.close()


@pytest.fixture
def publisher():
    made = []

    def make(port, cell):
        made.append(Publisher(port, cell))
        return made[-1]

    yield make
    for p in made:
        p.close()


def messages(cell, n=4, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        depth = rng.integers(0, 5000, K.shape, dtype=np.uint16)
        lab = rng.integers(0, 11, K.shape, dtype=np.uint8)
        out.append((wire.depth_key(cell), wire.encode_depth(wire.DepthFrame(depth, K, i, 10 + i))))
        out.append((wire.labels_key(cell), wire.encode_labels(wire.LabelFrame(lab, i, 10 + i))))
        out.append((wire.truth_key(cell), wire.encode_labels(wire.LabelFrame(lab, i, 10 + i))))
    return out


def test_msgpack_records_exact_bytes_of_default_keys_and_stops_on_sigterm(tmp_path, publisher):
    port, cell = free_port(), "rec1"
    out = tmp_path / "session.mcap"
    notify = NotifySocket(str(tmp_path / "notify.sock"))
    proc = start_recorder(port, out, "--format", "msgpack", notify=notify)
    pub = publisher(port, cell)
    msgs = messages(cell)
    stats = (
        wire.stats_key(cell),
        wire.encode_stats({"stamp_ns": 1, "timings_ms": {}, "counts": {}}),
    )
    junk = (wire.depth_key(cell), b"\xc1 not msgpack")  # recorded as is: a recording keeps the wire
    try:
        pub.wait_matched([k for k, _ in [*msgs, stats]])
        for key, data in [*msgs, stats, junk]:
            pub.pub(key).put(data)
        # every message arrived (the heartbeat's STATUS= counts them, every 5 s): still
        # recording, under a temporary name beside the final one
        recorded = f": {len(msgs) + 2} messages,"
        wait_for(lambda: any(recorded in v for v in notify.values("STATUS")), 30, recorded)
        assert not out.exists() and any(p.suffix == ".partial" for p in tmp_path.iterdir())
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=20)
    finally:
        notify.close()
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    info = recording.RecordingInfo()
    back = [(m.key, m.data) for m in recording.read_messages(out, info=info)]
    # bytes and each key's order are kept (zenoh does not order messages across keys)
    for key in {k for k, _ in msgs}:
        assert [d for k, d in back if k == key] == [d for k, d in [*msgs, junk] if k == key]
    assert len(back) == len(msgs) + 2
    assert not info.truncated
    assert sorted(info.counts) == sorted(
        {wire.depth_key(cell), wire.labels_key(cell), wire.truth_key(cell), wire.stats_key(cell)}
    )
    assert not list(tmp_path.glob(".*partial"))


def test_count_and_chosen_keys(tmp_path, publisher):
    port, cell = free_port(), "rec2"
    out = tmp_path / "stats.mcap"
    key = wire.stats_key(cell)
    proc = start_recorder(
        port, out, "--keys", f"topseg/{cell}/*/stats", "--count", "3", "--format", "msgpack"
    )
    pub = publisher(port, cell)
    sent = [
        wire.encode_stats({"stamp_ns": i, "timings_ms": {"crf": 1.5}, "counts": {}})
        for i in range(5)
    ]
    try:
        pub.wait_matched([key])
        for data in sent:
            pub.pub(key).put(data)
        rc = proc.wait(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert rc == 0, proc.stderr.read()
    assert [m.data for m in recording.read_messages(out)] == sent[:3]


def test_a_message_on_a_bad_key_is_dropped_and_logged_escaped(tmp_path, publisher):
    """A key is whatever its publisher chose: escape codes in it must not go raw to the log. The
    ROS 2 form drops it (and depth on the reserved `_any/_any`), counted, the key escaped."""
    port, cell = free_port(), "rec3"
    out = tmp_path / "ros.mcap"
    proc = start_recorder(port, out, "--count", "1")
    pub = publisher(port, cell)
    depth = np.zeros(K.shape, np.uint16)
    frame = wire.encode_depth(wire.DepthFrame(depth, K, 0, 10))
    bad = ["topseg/x\x1b[2J\r/cam0/depth", f"topseg/{wire.ANY}/{wire.ANY}/depth"]
    try:
        pub.wait_matched([*bad, wire.depth_key(cell)])
        for key in bad:
            pub.pub(key).put(frame)
        pub.pub(wire.depth_key(cell)).put(frame)  # the one message --count waits for
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert "recorded 1 messages" in err and "2 rejected" in err, err
    assert "topseg/x\\x1b[2J\\r/cam0/depth" in err and "\x1b" not in err, err
    assert f"topseg/{wire.ANY}/{wire.ANY}/depth that is not a topseg message" in err, err


def test_duration_ends_an_idle_recording(tmp_path):
    out = tmp_path / "idle.mcap"
    t0 = time.monotonic()
    proc = start_recorder(free_port(), out, "--duration", "0.5")
    rc = proc.wait(timeout=30)
    assert rc == 0, proc.stderr.read()
    assert time.monotonic() - t0 >= 0.5
    assert recording.inspect(out).counts == {}  # a valid, empty recording


def test_full_disk_stops_cleanly_and_keeps_what_was_written(tmp_path, publisher):
    def small_disk():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (2_500_000, resource.RLIM_INFINITY))

    port, cell = free_port(), "rec3"
    out = tmp_path / "full.mcap"
    proc = start_recorder(port, out, "--format", "msgpack", preexec_fn=small_disk)
    pub = publisher(port, cell)
    rng = np.random.default_rng(5)
    key = wire.depth_key(cell)
    sent = []
    try:
        pub.wait_matched([key])
        for i in range(12):  # 12 incompressible 600 KB frames: far past the 2.5 MB limit
            depth = rng.integers(0, 65536, KINECT_V1.shape, dtype=np.uint16)
            sent.append(wire.encode_depth(wire.DepthFrame(depth, KINECT_V1, i, i)))
            pub.pub(key).put(sent[-1])
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 2, err
    assert "topseg record: error:" in err and "stays readable" in err and "Traceback" not in err
    info = recording.RecordingInfo()
    back = [m.data for m in recording.read_messages(out, info=info)]
    assert 0 < len(back) < len(sent)
    assert back == sent[: len(back)]
    assert info.truncated


def test_bad_arguments(tmp_path):
    proc = start_recorder(free_port(), tmp_path / "no" / "dir" / "x.mcap")
    assert proc.wait(timeout=30) == 2
    assert "does not exist" in proc.stderr.read()
    proc = start_recorder(free_port(), tmp_path / "x.mcap", "--keys", "topseg//depth")
    assert proc.wait(timeout=30) == 2
    assert "key expression" in proc.stderr.read()
    assert not os.path.exists(tmp_path / "x.mcap")


def test_a_deleted_output_folder_stops_the_recorder_saying_what_was_lost(tmp_path, publisher):
    port, cell = free_port(), "rec6"
    folder = tmp_path / "out"
    folder.mkdir()
    proc = start_recorder(port, folder / "x.mcap")
    pub = publisher(port, cell)
    msgs = messages(cell)
    try:
        pub.wait_matched([k for k, _ in msgs])
        for key, data in msgs:
            pub.pub(key).put(data)
        shutil.rmtree(folder)
        _, err = proc.communicate(timeout=30)  # it notices on its own, no signal needed
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 2, err
    lines = [line for line in err.splitlines() if "topseg record: error:" in line]
    assert len(lines) == 1 and "Traceback" not in err
    assert re.search(
        r"was deleted while recording x\.mcap: the \d+ messages recorded are lost", lines[0]
    )
    assert "recorded 12 messages" not in err and "kept" not in err


def _old_recording(path, n):
    """A msgpack recording (today's form) of n frames with truth; the mount changes halfway."""
    rng = np.random.default_rng(3)
    mounts = [TopViewMount(K, 2800.0 if i < n // 2 else 3200.0, 2.0, -1.0) for i in range(n)]
    frames = []
    with recording.RecordingWriter(path) as w:
        for i, mount in enumerate(mounts):
            t = 1_763_000_000_000_000_000 + i * 20_000_000  # 50 fps
            depth = rng.integers(0, 5000, K.shape, dtype=np.uint16)
            truth = rng.integers(0, 11, K.shape, dtype=np.uint8)
            frames.append((depth, truth, mount))
            w.write(
                wire.depth_key(), wire.encode_depth(wire.DepthFrame(depth, K, i, t, "", mount)), t
            )
            w.write(wire.truth_key(), wire.encode_labels(wire.LabelFrame(truth, i, t)), t)
    return frames


def test_ros2_recording_of_a_live_driver_reads_back_in_ros_tools_and_replays_the_same(
    tmp_path, publisher
):
    """driver (replaying an old msgpack recording, looped) -> Zenoh -> `topseg record` (the
    default ROS 2 form) -> Foxglove's decoder, rosbags, and our replay: same frames."""
    n, port, cell = 6, free_port(), "rec7"
    old = tmp_path / "old.mcap"
    frames = _old_recording(old, n)
    out = tmp_path / "ros2.mcap"
    recorder = start_recorder(port, out, "--count", str(4 * n))  # 2n frames: depth + truth
    probe = publisher(port, cell)
    probe.wait_matched([wire.depth_key(cell), wire.truth_key(cell)])  # the recorder listens
    cmd = [sys.executable, "-m", "topseg.services.cli", "driver", "--cell", cell]
    cmd += ["--zenoh-port", str(port), "--source", f"replay:{old}", "--loop"]
    driver = subprocess.Popen(
        cmd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        _, err = recorder.communicate(timeout=60)
    finally:
        for proc in (recorder, driver):
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        driver.communicate(timeout=20)
    assert recorder.returncode == 0, err

    # Foxglove's decoder: the profile, every message, depth bit-exact, the mounts as tf
    decoded: dict[str, list] = {}
    with open(out, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        for schema, channel, message, msg in reader.iter_decoded_messages(log_time_order=False):
            assert (schema.encoding, channel.message_encoding) == ("ros2msg", "cdr")
            assert "offered_qos_profiles" in channel.metadata
            decoded.setdefault(channel.topic, []).append((message.sequence, schema.name, msg))
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    base = f"/topseg/{cell}/cam0"
    assert set(decoded) == {f"{base}/{s}" for s in ("depth", "truth", "camera_info", "mount")} | {
        "/tf_static"
    }
    assert len(decoded[f"{base}/depth"]) + len(decoded[f"{base}/truth"]) == 4 * n
    for seq, typename, msg in decoded[f"{base}/depth"]:
        assert (typename, msg.encoding, msg.header.frame_id) == (
            "sensor_msgs/msg/Image",
            "16UC1",
            f"{cell}_cam0_optical_frame",
        )
        depth = np.frombuffer(bytes(msg.data), "<u2").reshape(K.shape)
        np.testing.assert_array_equal(depth, frames[seq % n][0])
    for seq, _, msg in decoded[f"{base}/truth"]:
        assert msg.encoding == "mono8"
        truth = np.frombuffer(bytes(msg.data), np.uint8).reshape(K.shape)
        np.testing.assert_array_equal(truth, frames[seq % n][1])
    assert all(
        list(m.k) == [K.fx, 0, K.cx, 0, K.fy, K.cy, 0, 0, 1]
        for *_, m in decoded[f"{base}/camera_info"]
    )
    poses = {2800.0: ros2.mount_pose(frames[0][2]), 3200.0: ros2.mount_pose(frames[-1][2])}
    for *_, msg in decoded["/tf_static"]:
        (t,) = msg.transforms
        assert (t.header.frame_id, t.child_frame_id) == (
            f"{cell}_cam0_floor",
            f"{cell}_cam0_optical_frame",
        )
        moved = t.transform.translation
        centre, quat = poses[round(moved.z * 1000, 6)]
        assert (moved.x, moved.y, moved.z) == tuple(centre)
        r = t.transform.rotation
        np.testing.assert_allclose((r.x, r.y, r.z, r.w), quat)
    assert len(decoded["/tf_static"]) == len(decoded[f"{base}/mount"]) >= 2  # it changed
    assert metadata["topseg"]["format"] == "ros2" and "topseg.labels" in metadata

    # rosbags' rosbag2 reader takes the file as a ROS 2 bag
    with AnyReader([out]) as bag:
        types = {c.topic: c.msgtype for c in bag.connections}
        assert sum(1 for c, _, d in bag.messages() if bag.deserialize(d, c.msgtype)) > 4 * n
    assert types[f"{base}/depth"] == "sensor_msgs/msg/Image"
    assert types["/tf_static"] == "tf2_msgs/msg/TFMessage"

    # replay reads it back as the frames the driver sent: depth, camera, mount and truth
    # (each truth with its depth frame; Zenoh does not order the two keys)
    truth_seqs = {seq for seq, *_ in decoded[f"{base}/truth"]}
    replayed = list(RecordingFrames(out))
    assert [item.seq for item in replayed] == [seq for seq, *_ in decoded[f"{base}/depth"]]
    for item in replayed:
        depth, truth, mount = frames[item.seq % n]
        np.testing.assert_array_equal(item.depth, depth)
        assert (item.intrinsics, item.mount) == (K, mount)
        assert (item.truth is not None) == (item.seq in truth_seqs)
        if item.truth is not None:
            np.testing.assert_array_equal(item.truth, truth)
