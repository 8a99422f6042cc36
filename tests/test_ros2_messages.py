"""ROS 2 messages of core/formats/ros2_messages.py, decoded by an independent reader.

`mcap_ros2` (Foxglove's ROS 2 support for MCAP) parses the `ros2msg` schema text and decodes
CDR with its own code, so these tests check rosbags' bytes against a second implementation.
"""

from __future__ import annotations

import numpy as np
import pytest
from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory
from rosbags.typesys import Stores, get_typestore

from topseg.core.camera import Intrinsics, TopViewMount
from topseg.core.formats import ros2_messages as ros2


def _decode(typename: str, data: bytes):
    schema = Schema(
        id=1, name=typename, encoding="ros2msg", data=ros2.schema_text(typename).encode()
    )
    return DecoderFactory().decoder_for("cdr", schema)(data)


def test_depth_image_decodes_as_16uc1_millimetres():
    rng = np.random.default_rng(0)
    depth = rng.integers(0, 8000, (48, 64), dtype=np.uint16)
    msg = _decode(
        ros2.IMAGE, ros2.image_message(depth, 1_700_000_000_123_456_789, "cam_optical_frame")
    )
    assert (msg.height, msg.width, msg.encoding, msg.step) == (48, 64, "16UC1", 128)
    assert msg.is_bigendian == 0
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    assert msg.header.frame_id == "cam_optical_frame"
    np.testing.assert_array_equal(np.frombuffer(bytes(msg.data), "<u2").reshape(48, 64), depth)


def test_label_image_decodes_as_mono8():
    labels = np.arange(30, dtype=np.uint8).reshape(5, 6) % 11
    msg = _decode(ros2.IMAGE, ros2.image_message(labels, 5, "x"))
    assert (msg.encoding, msg.step) == ("mono8", 6)
    np.testing.assert_array_equal(np.frombuffer(bytes(msg.data), np.uint8).reshape(5, 6), labels)


@pytest.mark.parametrize(
    "bad",
    [np.zeros((4, 4), np.float32), np.zeros((2, 2, 2), np.uint8), np.zeros((3, 3), np.uint32)],
)
def test_image_message_refuses_what_is_not_depth_or_labels(bad):
    with pytest.raises(ValueError, match="2-D uint16 depth or uint8 labels"):
        ros2.image_message(bad, 0, "x")


def test_camera_info_carries_the_pinhole():
    k = Intrinsics(width=640, height=400, fx=400.0, fy=401.0, cx=320.5, cy=199.5)
    msg = _decode(ros2.CAMERA_INFO, ros2.camera_info_message(k, 7, "cam_optical_frame"))
    assert (msg.width, msg.height, msg.distortion_model) == (640, 400, "plumb_bob")
    np.testing.assert_allclose(msg.k, [400, 0, 320.5, 0, 401, 199.5, 0, 0, 1])
    np.testing.assert_allclose(np.reshape(msg.p, (3, 4))[:, :3], np.reshape(msg.k, (3, 3)))
    np.testing.assert_allclose(msg.d, 0.0)


@pytest.mark.parametrize("pitch, roll", [(0.0, 0.0), (12.0, -7.0), (-30.0, 20.0)])
def test_mount_transform_maps_camera_points_to_the_floor_frame(pitch, roll):
    mount = TopViewMount(Intrinsics(), 3100.0, pitch, roll, "kinect_v2")
    msg = _decode(ros2.TF_MESSAGE, ros2.mount_transform_message(mount, 9, "cell1", "cam"))
    (tf,) = msg.transforms
    assert (tf.header.frame_id, tf.child_frame_id) == ("cell1_cam_floor", "cell1_cam_optical_frame")
    t, q = tf.transform.translation, tf.transform.rotation
    # a tf consumer maps p_floor = R(q) p_cam + t: it must agree with the mount's own geometry
    rng = np.random.default_rng(1)
    p_cam = rng.uniform(-2, 4, (20, 3))
    rot = _quaternion_matrix(q.x, q.y, q.z, q.w)
    np.testing.assert_allclose(
        p_cam @ rot.T + [t.x, t.y, t.z], mount.camera_to_world(p_cam), atol=1e-9
    )


def test_mount_transforms_message_names_every_camera():
    mounts = {
        ("c", "cam0"): TopViewMount(Intrinsics(), 3100.0, 5.0, 0.0, "kinect_v2"),
        ("d", "cam0"): TopViewMount(Intrinsics(), 2800.0, 0.0, 3.0, "kinect_v2"),
    }
    msg = _decode(ros2.TF_MESSAGE, ros2.mount_transforms_message(mounts, 9))
    # two cells with a camera of the same name: two floors, two optical frames
    assert [(tf.header.frame_id, tf.child_frame_id) for tf in msg.transforms] == [
        ("c_cam0_floor", "c_cam0_optical_frame"),
        ("d_cam0_floor", "d_cam0_optical_frame"),
    ]
    heights = [tf.transform.translation.z for tf in msg.transforms]
    np.testing.assert_allclose(heights, [m.centre_world_m()[2] for m in mounts.values()])


def _quaternion_matrix(x, y, z, w):
    """Rotation matrix of a unit quaternion, written out (independent of scipy)."""
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def test_type_hashes_match_rep_2016_and_every_release_with_hashes():
    # the std_msgs/String hash quoted in rmw_zenoh's design document (docs/research/...)
    assert ros2.type_hash("std_msgs/msg/String") == (
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
    )
    for typename in ros2.MESSAGE_TYPES:
        hashes = {
            get_typestore(s).hash_rihs01(typename)
            for s in (Stores.ROS2_IRON, Stores.ROS2_JAZZY, Stores.ROS2_KILTED, Stores.ROS2_LYRICAL)
        }
        assert hashes == {ros2.type_hash(typename)}


def test_dds_type_names():
    assert ros2.dds_type_name(ros2.IMAGE) == "sensor_msgs::msg::dds_::Image_"
    assert ros2.dds_type_name(ros2.TF_MESSAGE) == "tf2_msgs::msg::dds_::TFMessage_"


def test_ros2_topic_mirrors_the_zenoh_key():
    assert ros2.ros2_topic("cell1", "cam0", "depth") == "/topseg/cell1/cam0/depth"
