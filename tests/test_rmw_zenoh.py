"""core/formats/rmw_zenoh.py against rmw_zenoh's own examples and code.

The expected strings are copied from ros2/rmw_zenoh `docs/design.md` @ 99a6a2bd10b9 (section
"Graph Cache"); the GIDs were computed by rmw_zenoh's `simplified_xxhash3.cpp` @ 97aed4819677
compiled from source, so these tests hold our strings and hashes to rmw_zenoh's, not to ours.
"""

from __future__ import annotations

import struct

import pytest

from topseg.core.formats import rmw_zenoh as rz
from topseg.core.formats import ros2_messages as ros2

STRING = "std_msgs/msg/String"
# docs/design.md: the talker/listener example of domain 2
TALKER_PUB = (
    "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
    "std_msgs::msg::dds_::String_/"
    "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,7:,:,:,,"
)
LISTENER_NODE = "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"


def test_data_key_is_the_design_docs_example():
    assert rz.topic_key(0, "/chatter", STRING) == (
        "0/chatter/std_msgs::msg::dds_::String_/"
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
    )


def test_data_key_keeps_inner_slashes_as_key_chunks():
    key = rz.topic_key(7, ros2.ros2_topic("cell1", "cam0", "depth"), ros2.IMAGE)
    assert key == (
        "7/topseg/cell1/cam0/depth/sensor_msgs::msg::dds_::Image_/"
        "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47"
    )


def test_node_and_publisher_tokens_are_the_design_docs_examples():
    listener = rz.Node(domain=2, zid="aac3178e146ba6f1fc6e6a4085e77f21", node_id=0, name="listener")
    assert listener.token() == LISTENER_NODE
    talker = rz.Node(domain=2, zid="8b20917502ee955ac4476e0266340d5c", node_id=0, name="talker")
    assert talker.publisher_token(10, "/chatter", STRING, rz.Qos(depth=7)) == TALKER_PUB


def test_names_are_mangled_in_tokens():
    node = rz.Node(0, "ab", 3, "bridge", namespace="/topseg/x", enclave="/secure")
    token = node.publisher_token(4, "/topseg/c/cam0/labels", ros2.IMAGE, rz.DEFAULT_QOS)
    parts = token.split("/")
    assert parts[6:10] == ["%secure", "%topseg%x", "bridge", "%topseg%c%cam0%labels"]
    assert len(parts) == 13 and all(parts)


@pytest.mark.parametrize(
    "qos, text",
    [
        (rz.Qos(depth=42), "::,:,:,:,,"),  # rmw_zenoh's defaults: nothing written
        (rz.DEFAULT_QOS, "::,10:,:,:,,"),  # rclcpp::QoS(10), as the listener in design.md
        (rz.STATIC_TF_QOS, ":1:,1:,:,:,,"),  # transient local, keep last 1
        (rz.Qos(rz.BEST_EFFORT, rz.VOLATILE, rz.KEEP_LAST, 5), "2::,5:,:,:,,"),  # sensor data
        (rz.Qos(history=rz.KEEP_ALL, depth=42), "::2,:,:,:,,"),
    ],
)
def test_qos_keyexpr(qos, text):
    assert qos.keyexpr() == text


@pytest.mark.parametrize(
    "token, gid_hex",
    [
        (LISTENER_NODE, "49877999dacb858702d11ac823785912"),
        (TALKER_PUB, "ac170f31eadcd9ff0cd86d7a17907d1c"),
    ],
)
def test_gid_is_what_rmw_zenohs_xxhash3_computes(token, gid_hex):
    assert rz.entity_gid(token).hex() == gid_hex


def test_attachment_has_the_documented_layout():
    gid = bytes(range(0x00, 0x100, 0x11))
    data = rz.attachment(1, 1_700_000_000_123_456_789, gid)
    # design.md "Publishers": int64 LE sequence number, int64 LE timestamp, 1-byte GID length, GID
    assert len(data) == 33
    assert struct.unpack("<qqB", data[:17]) == (1, 1_700_000_000_123_456_789, 16)
    assert data[17:] == gid
    assert data.hex().startswith("010000000000000015cd853dfe9c9717")
    with pytest.raises(ValueError, match="16 bytes"):
        rz.attachment(1, 2, b"short")


@pytest.mark.parametrize(
    "bad", ["topseg/a", "/topseg/1cam/depth", "/topseg/cam-0/depth", "/topseg//x", "/a.b", "/"]
)
def test_topic_names_ros_refuses_are_refused(bad):
    with pytest.raises(rz.Ros2NameError, match="not a ROS 2 topic name"):
        rz.topic_key(0, bad, ros2.IMAGE)


def test_tokens_refuse_topics_ros_refuses():
    node = rz.Node(0, "ab", 0, "n")
    with pytest.raises(rz.Ros2NameError):
        node.publisher_token(1, "/topseg/c/cam.0/depth", ros2.IMAGE, rz.DEFAULT_QOS)
