"""ROS 2 MCAP recordings (core/formats/ros2_recording.py), checked with independent readers.

Foxglove's `mcap_ros2` decoder (its own `ros2msg` parser and CDR decoder) and `rosbags`' rosbag2
reader (which refuses files outside the ROS 2 profile) read what the writer wrote; our
own reader must give back the exact wire messages that went in.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader

from topseg.core import labels as label_table
from topseg.core.camera import KINECT_V1, TopViewMount
from topseg.core.formats import recording, wire
from topseg.core.formats import ros2_messages as ros2
from topseg.core.formats.ros2_recording_writer import Ros2RecordingWriter, qos_profiles
from topseg.core.formats.wire import DepthFrame, LabelFrame, WireError

K = KINECT_V1.scaled_to(160, 120)
STAMP = 1_763_000_000_000_000_000
MOUNT_A = TopViewMount(K, 2800.0, 5.0, -3.0, "kinect_v1")
MOUNT_B = TopViewMount(K, 3100.0, 0.0, 2.0, "oak_d")


def wire_messages(cell="c1", camera="cam0", n=6):
    """Depth (mount A, then B, then none), truth, labels and stats: the frame ids are the
    camera name, as the live driver sends them, so the round trip is byte for byte."""
    rng = np.random.default_rng(1)
    mounts = [MOUNT_A, MOUNT_A, MOUNT_B, MOUNT_B, None, MOUNT_A][:n]
    out = []
    for i, mount in enumerate(mounts):
        stamp = STAMP + i * 33_000_000
        depth = rng.integers(0, 65536, K.shape, dtype=np.uint16)
        truth = rng.integers(0, label_table.NUM_CLASSES, K.shape, dtype=np.uint8)
        truth[0, :3] = label_table.NO_DEPTH
        out.append(
            (
                wire.depth_key(cell, camera),
                wire.encode_depth(DepthFrame(depth, K, i, stamp, camera, mount)),
            )
        )
        out.append(
            (
                wire.truth_key(cell, camera),
                wire.encode_labels(LabelFrame(truth, i, stamp, camera)),
            )
        )
        out.append(
            (
                wire.labels_key(cell, camera),
                wire.encode_labels(LabelFrame(truth[::-1].copy(), i, stamp, camera)),
            )
        )
        stats = {"stamp_ns": stamp, "seq": i, "timings_ms": {"crf": 1.5}, "counts": {"n": i}}
        out.append((wire.stats_key(cell, camera), wire.encode_stats(stats)))
    return out


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    path = tmp_path_factory.mktemp("ros2") / "rec.mcap"
    sent = wire_messages()
    with Ros2RecordingWriter(path, metadata={"note": "test"}) as w:
        for i, (key, data) in enumerate(sent):
            w.write(key, data, log_time_ns=STAMP + i)
    return path, sent


def test_our_reader_gives_back_the_exact_wire_messages(written):
    path, sent = written
    info = recording.RecordingInfo()
    back = [(m.key, m.data) for m in recording.read_messages(path, info=info)]
    assert back == sent
    assert info.profile == "ros2" and info.rejected == 0 and not info.truncated
    assert info.metadata["topseg"]["format"] == "ros2"
    assert info.metadata["topseg"]["wire_version"] == str(wire.SCHEMA_VERSION)
    assert info.metadata["topseg"]["note"] == "test"
    depth_only = list(recording.read_messages(path, keys=[wire.depth_key("c1")]))
    assert [m.data for m in depth_only] == [d for k, d in sent if k.endswith("/depth")]
    assert [m.sequence for m in depth_only] == list(range(6))


def test_the_file_follows_the_mcap_ros2_profile(written):
    path, _ = written
    with open(path, "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary.chunk_indexes and all(c.compression == "zstd" for c in summary.chunk_indexes)
        for channel in summary.channels.values():
            schema = summary.schemas[channel.schema_id]
            assert channel.message_encoding == "cdr"
            assert schema.encoding == "ros2msg"
            assert schema.data.decode() == ros2.schema_text(schema.name)
            assert channel.metadata["topic_type_hash"] == ros2.type_hash(schema.name)
            latched = channel.topic in ("/tf_static", "/topseg/c1/cam0/mount")
            assert channel.metadata["offered_qos_profiles"] == qos_profiles(latched)
        topics = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        assert topics == {
            "/tf_static": "tf2_msgs/msg/TFMessage",
            "/topseg/c1/cam0/mount": "std_msgs/msg/String",
            "/topseg/c1/cam0/camera_info": "sensor_msgs/msg/CameraInfo",
            "/topseg/c1/cam0/depth": "sensor_msgs/msg/Image",
            "/topseg/c1/cam0/truth": "sensor_msgs/msg/Image",
            "/topseg/c1/cam0/labels": "sensor_msgs/msg/Image",
            "/topseg/c1/cam0/stats": "std_msgs/msg/String",
        }
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    table = {int(k): json.loads(v) for k, v in metadata["topseg.labels"].items()}
    assert table[11]["name"] == "robot" and table[12]["name"] == "object"
    assert table == {
        lab.id: {"name": lab.name, "color": list(lab.color)}
        for lab in (*label_table.LABELS, label_table.NO_DEPTH_LABEL)
    }
    assert "transient_local" in qos_profiles(True) and "volatile" in qos_profiles(False)


def test_foxglove_decodes_images_camera_info_stats_and_the_mount_transform(written):
    path, sent = written
    by_topic: dict[str, list] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
            by_topic.setdefault(channel.topic, []).append((message.sequence, decoded))
    depth_sent = [wire.decode_depth(d) for k, d in sent if k.endswith("/depth")]
    truth_sent = [wire.decode_labels(d) for k, d in sent if k.endswith("/truth")]
    for (sequence, msg), frame in zip(by_topic["/topseg/c1/cam0/depth"], depth_sent, strict=True):
        assert (msg.encoding, msg.height, msg.width, msg.step) == ("16UC1", 120, 160, 320)
        assert msg.header.frame_id == "c1_cam0_optical_frame"
        assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == frame.stamp_ns
        assert sequence == frame.seq
        got = np.frombuffer(bytes(msg.data), "<u2").reshape(120, 160)
        np.testing.assert_array_equal(got, frame.depth)  # bit-exact millimetres
    for (_, msg), frame in zip(by_topic["/topseg/c1/cam0/truth"], truth_sent, strict=True):
        assert msg.encoding == "mono8"
        got = np.frombuffer(bytes(msg.data), np.uint8).reshape(120, 160)
        np.testing.assert_array_equal(got, frame.labels)
    infos = by_topic["/topseg/c1/cam0/camera_info"]
    assert len(infos) == 6
    assert list(infos[0][1].k) == [K.fx, 0.0, K.cx, 0.0, K.fy, K.cy, 0.0, 0.0, 1.0]
    stats = [json.loads(msg.data) for _, msg in by_topic["/topseg/c1/cam0/stats"]]
    assert [s["counts"]["n"] for s in stats] == list(range(6))
    # the mount went A, A, B, B, none, A: three transforms, four mount messages
    tfs = [msg.transforms[0] for _, msg in by_topic["/tf_static"]]
    assert [t.header.frame_id for t in tfs] == ["c1_cam0_floor"] * 3
    assert [t.child_frame_id for t in tfs] == ["c1_cam0_optical_frame"] * 3
    for t, mount in zip(tfs, (MOUNT_A, MOUNT_B, MOUNT_A), strict=True):
        (x, y, z), quat = ros2.mount_pose(mount)
        got = t.transform
        assert (got.translation.x, got.translation.y, got.translation.z) == (x, y, z)
        rot = got.rotation
        np.testing.assert_allclose((rot.x, rot.y, rot.z, rot.w), quat)
    mounts = [json.loads(msg.data) for _, msg in by_topic["/topseg/c1/cam0/mount"]]
    assert mounts == [MOUNT_A.to_dict(), MOUNT_B.to_dict(), None, MOUNT_A.to_dict()]


def test_rosbags_reads_the_file_as_a_rosbag2_mcap(written):
    path, _ = written
    with AnyReader([path]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        decoded = [reader.deserialize(data, c.msgtype) for c, _, data in reader.messages()]
    assert counts["/topseg/c1/cam0/depth"] == 6 and counts["/tf_static"] == 3
    assert len(decoded) == sum(counts.values()) == 6 * 5 + 3 + 4


def test_a_radial_cameras_frames_are_written_as_depth(tmp_path):
    """REP 118: a depth image holds z. A range camera's frames go in as depth, its mount as a
    depth camera's, so rosbags and our reader both read depth, and nothing converts twice."""
    from dataclasses import replace

    from topseg.core.camera import depth_to_range, range_to_depth

    depth = np.random.default_rng(3).integers(2000, 3000, K.shape).astype(np.uint16)
    ranges = depth_to_range(depth, K)
    radial = replace(MOUNT_A, radial=True)
    path = tmp_path / "range.mcap"
    with Ros2RecordingWriter(path) as w:
        w.write(
            wire.depth_key("c1", "tof"),
            wire.encode_depth(DepthFrame(ranges, K, 0, STAMP, "tof", radial)),
        )
    with AnyReader([path]) as reader:
        by_topic = {c.topic: reader.deserialize(d, c.msgtype) for c, _, d in reader.messages()}
    got = np.frombuffer(bytes(by_topic["/topseg/c1/tof/depth"].data), "<u2").reshape(K.shape)
    np.testing.assert_array_equal(got, range_to_depth(ranges, K))
    assert json.loads(by_topic["/topseg/c1/tof/mount"].data) == MOUNT_A.to_dict()
    (back,) = [wire.decode_depth(m.data) for m in recording.read_messages(path)]
    np.testing.assert_array_equal(back.depth, got)
    assert back.mount == MOUNT_A


def test_garbage_is_refused_before_anything_is_written(tmp_path):
    path = tmp_path / "g.mcap"
    with Ros2RecordingWriter(path) as w:
        for key, data in [
            (wire.depth_key(), b"\xc1 not msgpack"),
            (wire.info_key(), b"{}"),
            ("elsewhere/x", wire.encode_stats({"stamp_ns": 1, "timings_ms": {}, "counts": {}})),
        ]:
            with pytest.raises(WireError):
                w.write(key, data)
        late = DepthFrame(np.zeros(K.shape, np.uint16), K, 0, 2**62, "cam0")  # past int32 s
        with pytest.raises(WireError, match="no ROS 2 form"):
            w.write(wire.depth_key(), wire.encode_depth(late))
        assert w.messages == 0
    assert recording.inspect(path).counts == {}


def test_damaged_or_foreign_messages_are_skipped_and_counted(tmp_path):
    """A hand-made ROS 2 file: a torn depth image, depth before any camera info, a foreign
    type on a depth topic, and a good frame, which alone comes back."""
    path = tmp_path / "hand.mcap"
    depth = np.arange(K.width * K.height, dtype=np.uint16).reshape(K.shape)
    image = ros2.image_message(depth, STAMP, "cam0_optical_frame")
    info = ros2.camera_info_message(K, STAMP, "cam0_optical_frame")
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="test")
        ids = {}
        for t in (ros2.IMAGE, ros2.CAMERA_INFO, "std_msgs/msg/String"):
            ids[t] = w.register_schema(t, "ros2msg", ros2.schema_text(t).encode())
        qos = {"offered_qos_profiles": ""}
        depth_ch = w.register_channel("/topseg/a/cam0/depth", "cdr", ids[ros2.IMAGE], qos)
        info_ch = w.register_channel(
            "/topseg/a/cam0/camera_info", "cdr", ids[ros2.CAMERA_INFO], qos
        )
        foreign = w.register_channel("/topseg/b/cam0/depth", "cdr", ids["std_msgs/msg/String"], qos)
        w.add_message(depth_ch, log_time=1, publish_time=1, data=image, sequence=0)  # no info yet
        w.add_message(info_ch, log_time=2, publish_time=2, data=info, sequence=1)
        w.add_message(depth_ch, log_time=3, publish_time=3, data=image[:-7], sequence=1)
        w.add_message(foreign, log_time=4, publish_time=4, data=b"\x00\x01\x00\x00", sequence=1)
        w.add_message(depth_ch, log_time=5, publish_time=5, data=image, sequence=1)
        w.finish()
    got = recording.RecordingInfo()
    back = list(recording.read_messages(path, info=got))
    assert got.rejected == 2
    assert [m.key for m in back] == ["topseg/a/cam0/depth"]
    frame = wire.decode_depth(back[0].data)
    np.testing.assert_array_equal(frame.depth, depth)
    assert (frame.seq, frame.stamp_ns, frame.intrinsics, frame.mount) == (1, STAMP, K, None)


def test_a_write_after_close_and_a_deleted_folder_are_refused(tmp_path):
    folder = tmp_path / "out"
    folder.mkdir()
    w = Ros2RecordingWriter(folder / "x.mcap")
    w.write(wire.stats_key(), wire.encode_stats({"stamp_ns": 1, "timings_ms": {}, "counts": {}}))
    for p in folder.iterdir():
        p.unlink()
    folder.rmdir()
    with pytest.raises(recording.RecordingError, match=r"deleted while recording.*lost"):
        w.close()
    with pytest.raises(recording.RecordingError, match="already closed"):
        w.write(
            wire.stats_key(), wire.encode_stats({"stamp_ns": 2, "timings_ms": {}, "counts": {}})
        )


def test_rerun_maps_depth_camera_info_and_the_mount_to_its_archetypes(written, tmp_path):
    """Rerun's own MCAP import (the viewer's CLI) sees the file as ROS 2 data."""
    path, _ = written
    rerun = Path(sys.executable).parent / "rerun"
    check = subprocess.run(
        [rerun, "mcap", "check", path], capture_output=True, text=True, timeout=120
    )
    assert check.returncode == 0, check.stderr
    rrd = tmp_path / "r.rrd"
    subprocess.run([rerun, "mcap", "convert", path, "-o", rrd], check=True, timeout=120)
    printed = subprocess.run(
        [rerun, "rrd", "print", rrd], capture_output=True, text=True, check=True, timeout=120
    ).stdout
    columns = {line.split(" - ")[1]: line for line in printed.splitlines() if " - /" in line}
    assert "Transform3D:translation" in columns["/tf_static"]
    assert "Pinhole:image_from_camera" in columns["/topseg/c1/cam0/camera_info"]
    assert "DepthImage:buffer" in columns["/topseg/c1/cam0/depth"]


def test_segment_and_replay_read_a_two_camera_ros2_recording(tmp_path):
    """`input_frames` (what `topseg segment` reads) and the replay source, on ROS 2 files."""
    from topseg.drivers.base import SourceOptions
    from topseg.drivers.replay import input_frames
    from topseg.drivers.replay import open as open_replay

    path = tmp_path / "two.mcap"
    sent = {cam: wire_messages("c2", cam, n=3) for cam in ("top", "side")}
    with Ros2RecordingWriter(path) as w:
        for pair in zip(sent["top"], sent["side"], strict=True):
            for key, data in pair:
                w.write(key, data)
    frames = list(input_frames(path))
    assert [f.name for f in frames] == [
        f"two_c2-{cam}_{i:06d}" for cam in ("top", "side") for i in range(3)
    ]
    for f in frames:
        cam = f.key.split("/")[2]
        depth = [wire.decode_depth(d) for k, d in sent[cam] if k.endswith("/depth")][f.seq]
        np.testing.assert_array_equal(f.depth, depth.depth)
        assert (f.intrinsics, f.mount) == (K, depth.mount)
        assert f.truth is not None
    with open_replay(f"{path}#topseg/c2/side/depth", SourceOptions(realtime=False)) as src:
        replayed = [frame.depth.depth for frame in src.frames()]
    assert len(replayed) == 3 and src.rejected == 0
