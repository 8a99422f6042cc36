"""Writing ROS 2 MCAP recordings (`Ros2RecordingWriter`): the form and its topics are
described in `ros2_recording`, which reads them back."""

from __future__ import annotations

import json
import logging
import os
import struct
from dataclasses import replace
from io import StringIO
from pathlib import Path

from topseg.core import labels as label_table
from topseg.core.camera import axis_depth
from topseg.core.formats import joint_states, wire
from topseg.core.formats.recording import CHUNK_SIZE, RecordingWriter
from topseg.core.formats.ros2_messages import (
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
from topseg.core.formats.ros2_recording import (
    LABELS_METADATA,
    LATCHED,
    MESSAGE_ENCODING,
    PROFILE,
    SCHEMA_ENCODING,
    STREAM_TYPES,
    STRING,
    TF_STATIC,
    cell_topic,
    parse_cell_topic,
    parse_topic,
    safety_json,
)
from topseg.core.formats.wire import DepthFrame, LabelFrame, WireError

log = logging.getLogger(__name__)


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


def _string_message(text: str) -> bytes:
    types = typestore().types
    return bytes(typestore().serialize_cdr(types[STRING](data=text), STRING))


class Ros2RecordingWriter:
    """Write wire messages to `path` as a ROS 2 MCAP recording (see the module), atomically.

    `write(key, data)` takes a wire message as it crossed Zenoh and raises WireError,
    writing nothing, when it is not a depth, labels, truth, stats, safety or joint state
    message; the file's
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
        self._backgrounds: dict[tuple[str, str], str | None] = {}

    @property
    def messages(self) -> int:
        """MCAP messages written so far (camera info, tf and mount included)."""
        return self._out.messages

    def write(self, key: str, data: bytes, log_time_ns: int | None = None) -> None:
        """Convert one wire message on `key` and append its ROS 2 messages."""
        topic = cell_topic(key)
        if topic is not None:
            self._write(topic, _cell_message(topic, data), log_time_ns, None)
            return
        parts = wire.parse_key(key)
        message = wire.decode_for_key(key, data)
        cell, camera = parts.cell, parts.camera
        try:  # everything is serialised before anything is written
            if isinstance(message, DepthFrame):
                out = self._depth(cell, camera, message)
            elif isinstance(message, LabelFrame):
                out = self._labels(cell, camera, parts.kind, message)
            else:
                text = _string_message(json.dumps(message))
                out = [(ros2_topic(cell, camera, "stats"), text, None)]
        except (ValueError, OverflowError, struct.error) as exc:  # seconds past ROS's int32
            raise WireError(f"a {parts.kind} message with no ROS 2 form: {exc}") from None
        for topic, cdr, seq in out:
            self._write(topic, cdr, log_time_ns, seq)
        if isinstance(message, DepthFrame):
            self._mounts[cell, camera] = _mount_state(message)
        elif parts.kind == "labels":
            self._backgrounds[cell, camera] = message.background

    def _labels(self, cell: str, camera: str, kind: str, frame: LabelFrame) -> list:
        """A labels (or truth) frame's messages: labels made with another background than
        the camera's last ones (none before its first) get `/background` first."""
        out = []
        if kind == "labels" and frame.background != self._backgrounds.get((cell, camera)):
            state = json.dumps({"id": frame.background})
            out.append((ros2_topic(cell, camera, "background"), _string_message(state), None))
        cdr = image_message(frame.labels, frame.stamp_ns, optical_frame(cell, camera))
        out.append((ros2_topic(cell, camera, kind), cdr, frame.seq))
        return out

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
        parsed, cell = parse_topic(topic), parse_cell_topic(topic)
        if cell is not None:
            typename, latched = cell[1], False
        else:
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


def _cell_message(topic: str, data: bytes) -> bytes:
    """A cell topic's CDR message of a wire safety or joint state (WireError when it is
    not one): the safety state's map as JSON in a String, the joints as a JointState."""
    if topic.endswith("/joints"):
        js = joint_states.decode_joint_state(data)
        try:
            return joint_states.encode_ros2_joint_state(js)
        except (ValueError, OverflowError, struct.error) as exc:  # past ROS's int32 seconds
            raise WireError(f"a joint state with no ROS 2 form: {exc}") from None
    return _string_message(safety_json(data))


def _mount_state(frame: DepthFrame) -> dict | None:
    """The mount map `/mount` holds: the wire's, but a radial camera's says depth, since its
    frames are written as depth (REP 118)."""
    if frame.mount is None:
        return None
    return wire.mount_map(replace(frame.mount, radial=False))
