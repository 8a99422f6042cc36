"""ROS 2 MCAP recordings: topseg's wire messages as ROS 2 (CDR) messages, and back.

`topseg record` writes this form by default (`recording.py` keeps the raw msgpack form for
wire capture). The file follows MCAP's `ros2` profile: header profile `ros2`, every channel
message encoding `cdr` with a `ros2msg` schema (`ros2_messages.schema_text`) and channel
metadata `offered_qos_profiles` (rosbag2's version-9 YAML) and `topic_type_hash` (RIHS01,
rosbag2 practice), as rosbag2's MCAP storage writes them. Checked in tests: rosbags'
rosbag2 reader, Foxglove's mcap-ros2-support and Rerun's MCAP import read every message
(rosbag2 itself is not installable here). Topics (`ros2_messages.ros2_topic`, the live
bridge's names):

    /topseg/<cell>/<camera>/depth        sensor_msgs/msg/Image       16UC1, millimetres
    /topseg/<cell>/<camera>/labels       sensor_msgs/msg/Image       mono8 label ids (worker)
    /topseg/<cell>/<camera>/truth        sensor_msgs/msg/Image       mono8 ground truth
    /topseg/<cell>/<camera>/camera_info  sensor_msgs/msg/CameraInfo  one before each depth frame
    /topseg/<cell>/<camera>/stats        std_msgs/msg/String         the stats map as JSON
    /topseg/<cell>/<camera>/mount        std_msgs/msg/String         the wire's mount map as JSON
    /tf_static                           tf2_msgs/msg/TFMessage      <cell>_<camera>_floor -> optical frame

Depth images hold depth along the optical axis, as REP 118 says: a radial camera's frames
(range along each ray, `TopViewMount.radial`) are written as depth, and its `/mount` as a
depth camera's, so that a ROS tool and topseg's own reader both read depth.

Images and camera info carry the frame's capture stamp and `<cell>_<camera>_optical_frame`; the
MCAP `sequence` of depth, labels, truth and camera info is the wire `seq` (modulo 2**32),
which pairs a frame's depth, labels and truth; log time is when the recorder received it.
`/tf_static` and `/mount` (latched QoS: transient local, depth 1) are written before the
first depth frame of a camera and again whenever its mount changes; `/mount` holds `null`
when a camera stops sending one. JSON rides in `std_msgs/String` because the ROS 2 profile
allows only CDR channels: a `json` channel makes rosbags' reader refuse the whole file and
mcap-ros2-support's stop at it.

What ROS types cannot carry is in the file too: the sensor name and the mount exactly as
the wire sent it (height, tilt, sensor: `/mount`), the label table (metadata record
`topseg.labels`: `{"<id>": '{"name": ..., "color": [r, g, b]}'}`, no-depth 255 included)
and the versions (metadata record `topseg`: `format` `ros2`, `wire_version`,
`topseg_version`, `created_ns`, plus what the writer was given).

Reading (`recording.read_messages`, through `Ros2Channels`) rebuilds wire messages from
depth, labels, truth and stats with the latest camera info and mount of their camera (wire
`frame_id` = the camera name), so replay, segment and every other reader treat both forms
alike. A message that does not decode is skipped and counted (`RecordingInfo.rejected`).
"""

from __future__ import annotations

import json
import logging
import os
import re
import struct
from dataclasses import dataclass, replace
from functools import cache
from io import StringIO
from pathlib import Path
from typing import Any

import numpy as np

from topseg.core import labels as label_table
from topseg.core.camera import Intrinsics, TopViewMount, axis_depth
from topseg.core.formats import wire
from topseg.core.formats.recording import CHUNK_SIZE, RecordingWriter
from topseg.core.formats.ros2_messages import (
    CAMERA_INFO,
    DEPTH_ENCODING,
    IMAGE,
    LABEL_ENCODING,
    TF_MESSAGE,
    camera_info_message,
    image_message,
    mount_transform_message,
    optical_frame,
    ros2_topic,
    schema_text,
    type_hash,
    typestore,
)
from topseg.core.formats.wire import DepthFrame, LabelFrame, WireError

log = logging.getLogger(__name__)

PROFILE = "ros2"
MESSAGE_ENCODING = "cdr"
SCHEMA_ENCODING = "ros2msg"
STRING = "std_msgs/msg/String"
TF_STATIC = "/tf_static"
LABELS_METADATA = "topseg.labels"
#: The ROS type of each per-camera stream.
STREAM_TYPES = {
    "depth": IMAGE,
    "labels": IMAGE,
    "truth": IMAGE,
    "camera_info": CAMERA_INFO,
    "stats": STRING,
    "mount": STRING,
}
#: Streams with latched QoS (a late subscriber of a replay still gets them).
LATCHED = frozenset(("mount",))
_TOPIC = re.compile(r"/topseg/([^/]+)/([^/]+)/([^/]+)")


@cache
def qos_profiles(latched: bool) -> str:
    """`offered_qos_profiles` of a channel as rosbag2 (version 9) writes it: reliable,
    keep-last 10 volatile for streams, keep-last 1 transient-local when `latched`."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )
    from rosbags.rosbag2.metadata import dump_qos_v9
    from ruamel.yaml import YAML

    default = QosTime(0, 0)  # rclcpp's default deadline, lifespan and lease: none
    qos = Qos(
        QosHistory.KEEP_LAST,
        1 if latched else 10,
        QosReliability.RELIABLE,
        QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE,
        default,
        default,
        QosLiveliness.AUTOMATIC,
        default,
        False,
    )
    out = StringIO()
    yaml = YAML(typ="safe")
    yaml.default_flow_style = False
    yaml.dump(dump_qos_v9([qos]), out)
    return out.getvalue().strip()


def label_table_metadata() -> dict[str, str]:
    """The label table as an MCAP metadata map: id -> JSON {name, color}."""
    rows = (*label_table.LABELS, label_table.NO_DEPTH_LABEL)
    return {str(lab.id): json.dumps({"name": lab.name, "color": list(lab.color)}) for lab in rows}


def parse_topic(topic: str) -> tuple[str, str, str] | None:
    """`/topseg/<cell>/<camera>/<stream>` -> (cell, camera, stream), None for other topics."""
    m = _TOPIC.fullmatch(topic)
    if m is None or m.group(3) not in STREAM_TYPES:
        return None
    try:
        wire.camera_prefix(m.group(1), m.group(2))
    except WireError:
        return None
    return m.group(1), m.group(2), m.group(3)


def _string_message(text: str) -> bytes:
    types = typestore().types
    return bytes(typestore().serialize_cdr(types[STRING](data=text), STRING))


class Ros2RecordingWriter:
    """Write wire messages to `path` as a ROS 2 MCAP recording (see the module), atomically.

    `write(key, data)` takes a wire message as it crossed Zenoh and raises WireError,
    writing nothing, when it is not a depth, labels, truth or stats message; the file's
    atomic rename, small chunks and full-disk salvage are `RecordingWriter`'s.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        metadata: dict[str, str] | None = None,
        compression: str = "zstd",
        chunk_size: int = CHUNK_SIZE,
    ) -> None:
        info = {"format": PROFILE, "wire_version": str(wire.SCHEMA_VERSION), **(metadata or {})}
        self._out = RecordingWriter(
            path, metadata=info, compression=compression, chunk_size=chunk_size, profile=PROFILE
        )
        self.path = self._out.path
        self._out.add_metadata(LABELS_METADATA, label_table_metadata())
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._counts: dict[str, int] = {}
        self._mounts: dict[tuple[str, str], dict | None] = {}

    @property
    def messages(self) -> int:
        """MCAP messages written so far (camera info, tf and mount included)."""
        return self._out.messages

    def write(self, key: str, data: bytes, log_time_ns: int | None = None) -> None:
        """Convert one wire message on `key` and append its ROS 2 messages."""
        parts = wire.parse_key(key)
        message = wire.decode_for_key(key, data)
        cell, camera = parts.cell, parts.camera
        try:  # everything is serialised before anything is written
            if isinstance(message, DepthFrame):
                out = self._depth(cell, camera, message)
            elif isinstance(message, LabelFrame):
                frame = optical_frame(cell, camera)
                cdr = image_message(message.labels, message.stamp_ns, frame)
                out = [(ros2_topic(cell, camera, parts.kind), cdr, message.seq)]
            else:
                text = _string_message(json.dumps(message))
                out = [(ros2_topic(cell, camera, "stats"), text, None)]
        except (ValueError, OverflowError, struct.error) as exc:  # seconds past ROS's int32
            raise WireError(f"a {parts.kind} message with no ROS 2 form: {exc}") from None
        for topic, cdr, seq in out:
            self._write(topic, cdr, log_time_ns, seq)
        if isinstance(message, DepthFrame):
            self._mounts[cell, camera] = _mount_state(message)

    def _depth(self, cell: str, camera: str, frame: DepthFrame) -> list:
        """A depth frame's messages: tf and mount when the mount changed, camera info, depth."""
        out = []
        mount = _mount_state(frame)
        if mount != self._mounts.get((cell, camera)):  # a new camera without one: nothing to say
            if frame.mount is not None:
                tf = mount_transform_message(frame.mount, frame.stamp_ns, cell, camera)
                out.append((TF_STATIC, tf, None))
            out.append(
                (ros2_topic(cell, camera, "mount"), _string_message(json.dumps(mount)), None)
            )
        optical = optical_frame(cell, camera)
        info = camera_info_message(frame.intrinsics, frame.stamp_ns, optical)
        depth = image_message(axis_depth(frame.depth, frame.mount), frame.stamp_ns, optical)
        out.append((ros2_topic(cell, camera, "camera_info"), info, frame.seq))
        out.append((ros2_topic(cell, camera, "depth"), depth, frame.seq))
        return out

    def _write(self, topic: str, cdr: bytes, log_time_ns: int | None, seq: int | None) -> None:
        channel = self._channels.get(topic)
        if channel is None:
            channel = self._channels[topic] = self._add_channel(topic)
            self._counts[topic] = 0
        count = self._counts[topic]
        self._out.write_to(channel, cdr, log_time_ns, None, count if seq is None else seq)
        self._counts[topic] = count + 1

    def _add_channel(self, topic: str) -> int:
        parsed = parse_topic(topic)
        typename = TF_MESSAGE if parsed is None else STREAM_TYPES[parsed[2]]
        latched = parsed is None or parsed[2] in LATCHED
        schema = self._schemas.get(typename)
        if schema is None:
            text = schema_text(typename).encode()
            schema = self._schemas[typename] = self._out.add_schema(typename, SCHEMA_ENCODING, text)
        metadata = {
            "offered_qos_profiles": qos_profiles(latched),
            "topic_type_hash": type_hash(typename),
        }
        return self._out.add_channel(topic, MESSAGE_ENCODING, schema, metadata)

    def check_in_place(self) -> None:
        """RecordingError when the file being written was deleted (`RecordingWriter`)."""
        self._out.check_in_place()

    def close(self) -> Path:
        """Finish the file and move it into place (`RecordingWriter.close`)."""
        return self._out.close()

    def discard(self) -> None:
        """Drop an unfinished recording: nothing appears at `path`."""
        self._out.discard()

    def __enter__(self) -> Ros2RecordingWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self._out.__exit__(exc_type, exc, tb)


def _mount_state(frame: DepthFrame) -> dict | None:
    """The mount map `/mount` holds: the wire's, but a radial camera's says depth, since its
    frames are written as depth (REP 118)."""
    if frame.mount is None:
        return None
    return wire.mount_map(replace(frame.mount, radial=False))


# ---------------------------------------------------------------------------- reading


@dataclass
class _Camera:
    intrinsics: Intrinsics | None = None
    mount: TopViewMount | None = None


@dataclass(frozen=True)
class _Channel:
    cell: str
    camera: str
    stream: str
    typename: str

    @property
    def key(self) -> str:
        return f"{wire.ROOT}/{self.cell}/{self.camera}/{self.stream}"


class Ros2Channels:
    """The CDR channels of a recording, read in file order: wire messages rebuilt from
    depth, labels, truth and stats; camera info and mount kept per camera on the way."""

    def __init__(self, path: Any = "") -> None:
        self.path = path
        self._channels: dict[int, _Channel] = {}
        self._cameras: dict[tuple[str, str], _Camera] = {}

    def add(self, channel_id: int, topic: str, schema_name: str | None) -> bool:
        """Take a channel if it is one of topseg's topics of the expected type (False: skip
        it; `/tf_static` is skipped too, `/mount` says the same more exactly)."""
        parsed = parse_topic(topic)
        if parsed is None:
            if topic != TF_STATIC:
                log.info("%s: channel %s is not a topseg topic: skipped", self.path, topic)
            return False
        cell, camera, stream = parsed
        if schema_name != STREAM_TYPES[stream]:
            log.warning(
                "%s: channel %s is %s, not %s: skipped",
                self.path,
                topic,
                schema_name,
                STREAM_TYPES[stream],
            )
            return False
        self._channels[channel_id] = _Channel(cell, camera, stream, STREAM_TYPES[stream])
        self._cameras.setdefault((cell, camera), _Camera())
        return True

    def __contains__(self, channel_id: int) -> bool:
        return channel_id in self._channels

    def key(self, channel_id: int) -> str | None:
        """The wire key a channel's messages are rebuilt for; None for camera info and mount."""
        ch = self._channels.get(channel_id)
        return None if ch is None or ch.stream in ("camera_info", "mount") else ch.key

    def message(self, channel_id: int, data: bytes, sequence: int) -> bytes | None:
        """A wire message rebuilt from one CDR message (None for camera info and mount,
        which only update their camera); WireError when it does not decode."""
        ch = self._channels[channel_id]
        cam = self._cameras[ch.cell, ch.camera]
        try:
            msg = typestore().deserialize_cdr(data, ch.typename)
        except Exception as exc:  # rosbags raises many types for malformed CDR
            raise WireError(f"not a CDR {ch.typename} ({type(exc).__name__}: {exc})") from None
        if ch.stream == "camera_info":
            cam.intrinsics = None  # until this one checks out
            cam.intrinsics = _intrinsics(msg)
            return None
        if ch.stream == "mount":
            cam.mount = None
            state = _json(msg.data)
            cam.mount = None if state is None else wire.mount_from_map(state)
            return None
        if ch.stream == "stats":
            stats = _json(msg.data)
            if not isinstance(stats, dict):
                raise WireError("a stats message must be a JSON object")
            return wire.encode_stats(stats)
        stamp = _stamp_ns(msg.header.stamp)
        if ch.stream == "depth":
            depth = _image(msg, DEPTH_ENCODING, np.uint16)
            if cam.intrinsics is None:
                raise WireError(f"depth frame {sequence} has no camera_info before it")
            mount = cam.mount
            if mount is not None and mount.intrinsics.shape != depth.shape:
                mount = None
            frame = DepthFrame(depth, cam.intrinsics, sequence, stamp, ch.camera, mount)
            return wire.encode_depth(frame)
        labels = _image(msg, LABEL_ENCODING, np.uint8)
        return wire.encode_labels(LabelFrame(labels, sequence, stamp, ch.camera))


def _json(text: str) -> Any:
    try:
        return json.loads(text)
    except ValueError as exc:
        raise WireError(f"not JSON ({exc})") from None


def _stamp_ns(stamp) -> int:
    if stamp.sec < 0:
        raise WireError(f"stamp {stamp.sec} s is before 1970")
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _intrinsics(msg) -> Intrinsics:
    k = msg.k
    try:
        return Intrinsics(
            int(msg.width), int(msg.height), float(k[0]), float(k[4]), float(k[2]), float(k[5])
        )
    except (ValueError, TypeError) as exc:
        raise WireError(f"camera_info: {exc}") from None


def _image(msg, encoding: str, dtype: type) -> np.ndarray:
    """A checked `sensor_msgs/Image` -> a 2-D array (a copy, native byte order)."""
    if msg.encoding != encoding:
        raise WireError(f"image encoding {msg.encoding!r}, expected {encoding!r}")
    h, w = int(msg.height), int(msg.width)
    if not (1 <= h <= wire.MAX_SIDE and 1 <= w <= wire.MAX_SIDE):
        raise WireError(f"image is {w}x{h}; each side must be 1..{wire.MAX_SIDE}")
    size = np.dtype(dtype).itemsize
    data = np.asarray(msg.data, np.uint8)
    if msg.step < w * size or data.size != msg.step * h:
        raise WireError(f"image data of {data.size} bytes does not fit {w}x{h}, step {msg.step}")
    rows = data.reshape(h, msg.step)[:, : w * size]
    order = ">" if msg.is_bigendian else "<"
    return np.ascontiguousarray(rows).view(np.dtype(dtype).newbyteorder(order)).astype(dtype)
