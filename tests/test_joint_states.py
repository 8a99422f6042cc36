"""Joint states (core/formats/joint_states.py): topseg's msgpack message and ROS 2's
sensor_msgs/JointState CDR, the latter checked against Foxglove's independent CDR encoder and
decoder (mcap_ros2)."""

from __future__ import annotations

import math
import re

import msgpack
import numpy as np
import pytest
from mcap.records import Schema
from mcap_ros2._dynamic import serialize_dynamic
from mcap_ros2.decoder import DecoderFactory

from topseg.core.formats import joint_states as js
from topseg.core.formats.joint_states import JointState, WireError
from topseg.core.formats.ros2_messages import schema_text

STATE = JointState(1_700_000_000_123_456_789, ("joint1", "joint2", "joint3"), (0.5, -1.25, 2.0))


def _pack(**fields) -> bytes:
    msg = {"v": 1, "stamp_ns": 5, "name": ["a", "b"], "position": [0.0, 1.0]}
    msg.update(fields)
    msg = {k: v for k, v in msg.items() if v is not _DROP}
    return msgpack.packb(msg, use_bin_type=True)


_DROP = object()


def test_msgpack_round_trip():
    assert js.decode_joint_state(js.encode_joint_state(STATE)) == STATE
    assert js.decode_joint_state(js.encode_joint_state(STATE)).as_dict() == {
        "joint1": 0.5, "joint2": -1.25, "joint3": 2.0,
    }  # fmt: skip


def test_integer_positions_read_as_floats():
    state = js.decode_joint_state(_pack(position=[0, 1]))
    assert state.position == (0.0, 1.0) and all(type(p) is float for p in state.position)


@pytest.mark.parametrize(
    "fields, message",
    [
        ({"v": 2}, "schema version 2 is not 1"),
        ({"v": "1"}, "schema version '1' is not 1"),
        ({"stamp_ns": _DROP}, "missing ['stamp_ns']"),
        ({"extra": 1}, "unknown ["),
        ({"stamp_ns": -1}, "stamp_ns -1"),
        ({"stamp_ns": 2**63}, "stamp_ns"),
        ({"stamp_ns": 1.5}, "stamp_ns 1.5"),
        ({"name": "ab"}, "name must be a list"),
        ({"name": [], "position": []}, "0 joints"),
        ({"name": ["a", 3]}, "joint name 3"),
        ({"name": ["a", ""]}, "joint name ''"),
        ({"name": ["a", "x" * 65]}, "1..64 characters"),
        ({"name": ["a", "a"]}, "joint 'a' twice"),
        ({"position": [0.0]}, "2 names but 1 positions"),
        ({"position": [0.0, math.nan]}, "position[1] = nan"),
        ({"position": [math.inf, 0.0]}, "position[0] = inf"),
        ({"position": [0.0, "1"]}, "position[1] = '1'"),
        ({"position": [0.0, True]}, "position[1] = True"),
        ({"position": 3.0}, "position must be a list"),
    ],
)
def test_bad_fields_are_one_wire_error(fields, message):
    with pytest.raises(WireError) as err:
        js.decode_joint_state(_pack(**fields))
    assert message in str(err.value)


def test_at_most_64_joints():
    names = [f"j{i}" for i in range(64)]
    assert len(js.decode_joint_state(_pack(name=names, position=[0.0] * 64)).name) == 64
    with pytest.raises(WireError):
        js.decode_joint_state(_pack(name=[*names, "j64"], position=[0.0] * 65))


@pytest.mark.parametrize(
    "data",
    [b"", b"\xc1", b"\x93\x01\x02\x03", msgpack.packb([1, 2]), b"\xff" * 40, "text", None,
     b"\xdf\xff\xff\xff\xff", msgpack.packb({"v": 1}) + b"\x00" * 20000],
)  # fmt: skip
def test_garbage_is_one_wire_error(data):
    with pytest.raises(WireError):
        js.decode_joint_state(data)


def test_truncated_messages_are_wire_errors():
    data = js.encode_joint_state(STATE)
    for n in range(len(data)):
        with pytest.raises(WireError):
            js.decode_joint_state(data[:n])


def test_encode_refuses_an_invalid_state():
    with pytest.raises(ValueError, match="2 names but 1 positions"):
        js.encode_joint_state(JointState(0, ("a", "b"), (1.0,)))


def test_joints_key():
    assert js.joints_key("cell1", "ur10") == "topseg/cell1/robot/ur10/joints"
    with pytest.raises(WireError, match="robot name"):
        js.joints_key("cell1", "a/b")


# --- ROS 2 ----------------------------------------------------------------------------------


def _independent_encode(sec, nanosec, names, position, velocity=()) -> bytes:
    """sensor_msgs/JointState CDR written by mcap_ros2's own encoder, not rosbags'."""
    encoders = serialize_dynamic(js.ROS2_JOINT_STATE, schema_text(js.ROS2_JOINT_STATE))
    return encoders[js.ROS2_JOINT_STATE](
        {
            "header": {"stamp": {"sec": sec, "nanosec": nanosec}, "frame_id": "base"},
            "name": list(names), "position": list(position),
            "velocity": list(velocity), "effort": [],
        }
    )  # fmt: skip


def test_ros2_decode_reads_an_independent_encoders_bytes():
    data = _independent_encode(1_700_000_000, 123_456_789, STATE.name, STATE.position, (1, 2, 3))
    assert js.decode_ros2_joint_state(data) == STATE


def test_ros2_encode_is_read_by_an_independent_decoder():
    text = schema_text(js.ROS2_JOINT_STATE).encode()
    schema = Schema(id=1, name=js.ROS2_JOINT_STATE, encoding="ros2msg", data=text)
    msg = DecoderFactory().decoder_for("cdr", schema)(js.encode_ros2_joint_state(STATE, "base"))
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    assert tuple(msg.name) == STATE.name
    np.testing.assert_array_equal(msg.position, STATE.position)
    assert js.decode_ros2_joint_state(js.encode_ros2_joint_state(STATE)) == STATE


@pytest.mark.parametrize(
    "names, position, message",
    [
        (["a", "b"], [0.0], "2 names but 1 positions"),
        (["a", "b"], [], "2 names but 0 positions"),  # a driver sending velocities only
        (["a"], [math.nan], "position[0] = nan"),
        ([], [], "0 joints"),
        (["a", "a"], [0.0, 1.0], "twice"),
    ],
)
def test_ros2_decode_checks_names_and_positions(names, position, message):
    with pytest.raises(WireError, match=re.escape(message)):
        js.decode_ros2_joint_state(_independent_encode(1, 0, names, position))


def test_ros2_decode_refuses_a_negative_stamp():
    with pytest.raises(WireError, match="not a time since 1970"):
        js.decode_ros2_joint_state(_independent_encode(-5, 0, ["a"], [0.0]))


def test_ros2_garbage_and_truncated_payloads_are_wire_errors():
    data = _independent_encode(1, 2, STATE.name, STATE.position)
    for n in range(len(data)):
        with pytest.raises(WireError):
            js.decode_ros2_joint_state(data[:n])
    rng = np.random.default_rng(0)
    for _ in range(200):
        with pytest.raises(WireError):
            js.decode_ros2_joint_state(
                rng.integers(0, 256, rng.integers(0, 200), np.uint8).tobytes()
            )
    with pytest.raises(WireError, match="exceeds"):
        js.decode_ros2_joint_state(data + b"\x00" * js.MAX_JOINT_STATE_BYTES)
    with pytest.raises(WireError, match="must be bytes"):
        js.decode_ros2_joint_state("text")
