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
    /topseg/<cell>/<camera>/background   std_msgs/msg/String         {"id": background id or null}
    /tf_static                           tf2_msgs/msg/TFMessage      <cell>_<camera>_floor -> optical frame
    /topseg/<cell>/safety                std_msgs/msg/String         the safety state's map as JSON
    /topseg/<cell>/robot/<robot>/joints  sensor_msgs/msg/JointState  the robot's joint states

The cell's topics mirror the Zenoh keys `topseg/<cell>/safety` (`safety_wire`) and
`topseg/<cell>/robot/<robot>/joints` (`joint_states`) and read back as those wire messages.

Depth images hold depth along the optical axis, as REP 118 says: a radial camera's frames
(range along each ray, `TopViewMount.radial`) are written as depth, and its `/mount` as a
depth camera's, so that a ROS tool and topseg's own reader both read depth.

Images and camera info carry the frame's capture stamp and `<cell>_<camera>_optical_frame`; the
MCAP `sequence` of depth, labels, truth and camera info is the wire `seq` (modulo 2**32),
which pairs a frame's depth, labels and truth; log time is when the recorder received it.
`/tf_static` and `/mount` (latched QoS: transient local, depth 1) are written before the
first depth frame of a camera and again whenever its mount changes; `/mount` holds `null`
when a camera stops sending one. `/background` (latched too) is written before the first labels a
camera's recorded background gated (the static cell's, `core/background.py`) and again
whenever that changes (`{"id": null}`: labels made without one); labels before any
`/background`, as in a recording made before it existed, read as made without one. JSON rides in `std_msgs/String` because the ROS 2 profile
allows only CDR channels: a `json` channel makes rosbags' reader refuse the whole file and
mcap-ros2-support's stop at it.

What ROS types cannot carry is in the file too: the sensor name and the mount exactly as
the wire sent it (height, tilt, sensor: `/mount`), the label table (metadata record
`topseg.labels`: `{"<id>": '{"name": ..., "color": [r, g, b]}'}`, no-depth 255 included)
and the versions (metadata record `topseg`: `format` `ros2`, `wire_version`,
`topseg_version`, `created_ns`, plus what the writer was given).

Writing is `ros2_recording_writer.Ros2RecordingWriter`'s. Reading (`recording.read_messages`, through `Ros2Channels`) rebuilds wire messages from
depth, labels, truth and stats with the latest camera info, mount and background of their
camera (wire `frame_id` = the camera name), so replay, segment and every other reader treat both forms
alike. A message that does not decode is skipped and counted (`RecordingInfo.rejected`).
"""

from __future__ import annotations

import json
import logging
import re
from dataclasses import dataclass
from functools import cache
from typing import Any

import msgpack
import numpy as np

from topseg.core.camera import Intrinsics, TopViewMount
from topseg.core.formats import joint_states, safety_wire, wire
from topseg.core.formats.ros2_messages import (
    CAMERA_INFO,
    DEPTH_ENCODING,
    IMAGE,
    LABEL_ENCODING,
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
    "background": STRING,
}
#: Streams with latched QoS (a late subscriber of a replay still gets them).
LATCHED = frozenset(("mount", "background"))
#: Streams that only update their camera's state (no wire message of their own).
STATE_STREAMS = ("camera_info", "mount", "background")
_TOPIC = re.compile(r"/topseg/([^/]+)/([^/]+)/([^/]+)")
_CELL_TOPIC = re.compile(r"/topseg/([^/]+)/(?:safety|robot/([^/]+)/joints)")
#: the largest JSON safety state read back (a wire state is far smaller)
MAX_SAFETY_JSON = 65536


@cache
def parse_cell_topic(topic: str) -> tuple[str, str] | None:
    """A cell's topic (`/topseg/<cell>/safety`, `/topseg/<cell>/robot/<robot>/joints`) ->
    (its wire key, its ROS 2 type); None for other topics."""
    m = _CELL_TOPIC.fullmatch(topic)
    if m is None:
        return None
    try:
        if m.group(2) is None:
            return safety_wire.safety_key(m.group(1)), STRING
        return joint_states.joints_key(m.group(1), m.group(2)), joint_states.ROS2_JOINT_STATE
    except (WireError, ValueError):
        return None


def cell_topic(key: str) -> str | None:
    """The ROS 2 topic of a cell's wire key (`topseg/<cell>/safety`,
    `topseg/<cell>/robot/<robot>/joints`): the key with a leading `/`; None for other keys."""
    topic = "/" + key
    return topic if parse_cell_topic(topic) is not None else None


def safety_json(data: bytes) -> str:
    """A wire safety state (checked: WireError) as the JSON of its map."""
    safety_wire.decode_safety(data)
    return json.dumps(msgpack.unpackb(data, raw=False))


def safety_from_json(text: str) -> bytes:
    """The wire safety state of a JSON map (`safety_json`), checked; WireError otherwise."""
    if len(text) > MAX_SAFETY_JSON:
        raise WireError(f"a safety state of {len(text)} characters is too long")
    state = _json(text)
    if not isinstance(state, dict):
        raise WireError("a safety state must be a JSON object")
    return safety_wire.encode_safety(safety_wire.decode_safety(msgpack.packb(state)))


@cache
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


# ---------------------------------------------------------------------------- reading


@dataclass
class _Camera:
    intrinsics: Intrinsics | None = None
    mount: TopViewMount | None = None
    background: str | None = None


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
        self._cell_channels: dict[int, tuple[str, str]] = {}  # id -> (wire key, type)

    def add(self, channel_id: int, topic: str, schema_name: str | None) -> bool:
        """Take a channel if it is one of topseg's topics of the expected type (False: skip
        it; `/tf_static` is skipped too, `/mount` says the same more exactly)."""
        parsed = parse_topic(topic)
        cell = parse_cell_topic(topic) if parsed is None else None
        if cell is not None:
            if schema_name != cell[1]:
                log.warning(
                    "%s: channel %s is %s, not %s: skipped", self.path, topic, schema_name, cell[1]
                )
                return False
            self._cell_channels[channel_id] = cell
            return True
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
        return channel_id in self._channels or channel_id in self._cell_channels

    def key(self, channel_id: int) -> str | None:
        """The wire key a channel's messages are rebuilt for; None for camera info, mount and
        background."""
        if channel_id in self._cell_channels:
            return self._cell_channels[channel_id][0]
        ch = self._channels.get(channel_id)
        return None if ch is None or ch.stream in STATE_STREAMS else ch.key

    def message(self, channel_id: int, data: bytes, sequence: int) -> bytes | None:
        """A wire message rebuilt from one CDR message (None for camera info, mount and
        background, which only update their camera); WireError when it does not decode."""
        if channel_id in self._cell_channels:
            return _cell_message(self._cell_channels[channel_id][1], data)
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
        if ch.stream == "background":
            cam.background = None
            cam.background = _background_id(_json(msg.data))
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
        background = cam.background if ch.stream == "labels" else None
        return wire.encode_labels(LabelFrame(labels, sequence, stamp, ch.camera, background))


def _cell_message(typename: str, data: bytes) -> bytes:
    """The wire message of a cell topic's CDR message: a safety state or a joint state."""
    if typename == joint_states.ROS2_JOINT_STATE:
        return joint_states.encode_joint_state(joint_states.decode_ros2_joint_state(data))
    try:
        text = typestore().deserialize_cdr(data, STRING).data
    except Exception as exc:  # rosbags raises many types for malformed CDR
        raise WireError(f"not a CDR {STRING} ({type(exc).__name__}: {exc})") from None
    return safety_from_json(text)


def _background_id(state: Any) -> str | None:
    """The id in a `/background` message ({"id": id or null}); WireError when it is not one."""
    if not isinstance(state, dict) or set(state) != {"id"}:
        raise WireError('a background message must be {"id": ...}')
    return None if state["id"] is None else wire.check_background_id(state["id"])


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
