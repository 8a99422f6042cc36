"""ROS 2 messages of topseg's streams, serialised as CDR: depth, labels, camera info, the mount.

One place builds the ROS 2 view of a frame, so that MCAP recordings (`recording.py`) and the
live rmw_zenoh bridge publish the very same bytes. Serialisation and the message definitions
come from `rosbags` (a maintained, ROS-free implementation of ROS 2's type system and CDR):
its typestore holds the definitions of the ROS 2 releases, computes their REP-2016 RIHS01
type hashes and writes the concatenated `ros2msg` schema text that MCAP's ROS 2 profile uses.

Types follow ROS 2 Jazzy (the LTS with type hashes that rmw_zenoh ships for); the four types
used here have the same RIHS01 hash in Iron, Jazzy, Kilted and Lyrical (checked in tests).

Frames (REP 103 / REP 105 conventions), one pair per camera, named after cell and camera so
that every camera of every cell has its own:
- `<cell>_<camera>_floor` (`floor_frame`): x, y on the floor, z up, origin on the floor below
  that camera's centre, x along its image's x (`TopViewMount`'s world frame). A mount fixes
  height, pitch and roll only, so two cameras' floor frames are not related by topseg: a
  user with several cameras publishes each floor frame's pose in their own map frame.
- `<cell>_<camera>_optical_frame` (`optical_frame`): x right, y down, z forward.
The mount is the static transform floor frame -> optical frame.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cache

import numpy as np
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from topseg.core.camera import Intrinsics, TopViewMount

#: the ROS 2 release whose message definitions and type hashes topseg speaks
ROS_DISTRO = "jazzy"

IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
#: the types topseg publishes, in the order a reader is told about them
MESSAGE_TYPES = (IMAGE, CAMERA_INFO, TF_MESSAGE)

FLOAT64 = "std_msgs/msg/Float64"
STRING = "std_msgs/msg/String"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
#: visualization_msgs/Marker types and actions topseg uses
ARROW, LINE_STRIP, LINE_LIST, TEXT_VIEW_FACING = 0, 4, 5, 9
MARKER_ADD, MARKER_DELETE = 0, 2

DEPTH_ENCODING = "16UC1"  # millimetres, 0 = no reading (REP 118)
LABEL_ENCODING = "mono8"  # label ids of core/labels.py


@cache
def typestore():
    """The rosbags typestore of `ROS_DISTRO` (built once)."""
    return get_typestore(Stores.ROS2_JAZZY)


def type_hash(typename: str) -> str:
    """The REP-2016 type hash of a ROS 2 type, `RIHS01_<64 hex>`."""
    return typestore().hash_rihs01(typename)


def schema_text(typename: str) -> str:
    """The `ros2msg` schema of a type: its definition followed by its dependencies' (MCAP)."""
    return typestore().generate_msgdef(typename, ros_version=2)[0]


def dds_type_name(typename: str) -> str:
    """The DDS name of a ROS 2 type, `sensor_msgs::msg::dds_::Image_` (rmw_zenoh key parts)."""
    package, kind, name = typename.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def ros2_topic(cell: str, camera: str, stream: str) -> str:
    """The ROS 2 topic of a camera's stream: `/topseg/<cell>/<camera>/<stream>`.

    Recordings and the live bridge use the same names, mirroring the Zenoh keys
    `topseg/<cell>/<camera>/<stream>` (`core/formats/wire.py`).
    """
    return f"/topseg/{cell}/{camera}/{stream}"


def floor_frame(cell: str, camera: str) -> str:
    """The frame id of the floor below a camera: `<cell>_<camera>_floor` (z up)."""
    return f"{cell}_{camera}_floor"


def cell_floor_frame(cell: str) -> str:
    """The frame id of a cell's own floor frame (the cell file's frame): `<cell>_floor`."""
    return f"{cell}_floor"


def safety_topic(cell: str, stream: str) -> str:
    """The ROS 2 topic of a cell's safety stream: `/topseg/<cell>/safety/<stream>`."""
    return f"/topseg/{cell}/safety/{stream}"


def optical_frame(cell: str, camera: str) -> str:
    """The optical frame id of a camera's images: `<cell>_<camera>_optical_frame`."""
    return f"{cell}_{camera}_optical_frame"


def _types():
    return typestore().types


def _stamp(stamp_ns: int):
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return _types()["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)


def _header(stamp_ns: int, frame_id: str):
    return _types()["std_msgs/msg/Header"](stamp=_stamp(stamp_ns), frame_id=frame_id)


def _serialise(message, typename: str) -> bytes:
    return bytes(typestore().serialize_cdr(message, typename))


def image_message(image: np.ndarray, stamp_ns: int, frame_id: str) -> bytes:
    """A `sensor_msgs/Image` as CDR: uint16 -> `16UC1` (mm), uint8 -> `mono8` (label ids)."""
    if image.ndim != 2 or image.dtype.kind != "u" or image.itemsize not in (1, 2):
        raise ValueError(
            f"an image must be 2-D uint16 depth or uint8 labels, got {image.dtype} {image.shape}"
        )
    encoding = DEPTH_ENCODING if image.itemsize == 2 else LABEL_ENCODING
    image = np.ascontiguousarray(image, dtype=image.dtype.newbyteorder("<"))
    rows, cols = image.shape
    message = _types()[IMAGE](
        header=_header(stamp_ns, frame_id),
        height=rows,
        width=cols,
        encoding=encoding,
        is_bigendian=0,
        step=cols * image.itemsize,
        data=image.view(np.uint8).reshape(-1),
    )
    return _serialise(message, IMAGE)


def camera_info_message(k: Intrinsics, stamp_ns: int, frame_id: str) -> bytes:
    """A `sensor_msgs/CameraInfo` as CDR: the pinhole of `k`, no distortion (`plumb_bob`, 0s)."""
    types = _types()
    kmat = np.array([k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0])
    pmat = np.array([k.fx, 0.0, k.cx, 0.0, 0.0, k.fy, k.cy, 0.0, 0.0, 0.0, 1.0, 0.0])
    message = types[CAMERA_INFO](
        header=_header(stamp_ns, frame_id),
        height=k.height,
        width=k.width,
        distortion_model="plumb_bob",
        d=np.zeros(5),
        k=kmat,
        r=np.eye(3).reshape(-1),
        p=pmat,
        binning_x=0,
        binning_y=0,
        roi=types["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        ),
    )
    return _serialise(message, CAMERA_INFO)


def mount_pose(mount: TopViewMount) -> tuple[np.ndarray, np.ndarray]:
    """The camera's pose in the floor frame: translation (m) and quaternion (x, y, z, w)."""
    camera_axes_in_floor = mount.rotation_world_to_camera().T
    return mount.centre_world_m(), Rotation.from_matrix(camera_axes_in_floor).as_quat()


def mount_transform_message(mount: TopViewMount, stamp_ns: int, cell: str, camera: str) -> bytes:
    """A `tf2_msgs/TFMessage` as CDR: the static transform floor frame -> optical frame."""
    return mount_transforms_message({(cell, camera): mount}, stamp_ns)


def mount_transforms_message(
    mounts: Mapping[tuple[str, str], TopViewMount],
    stamp_ns: int,
    placements: Mapping[tuple[str, str], tuple[np.ndarray, float]] | None = None,
) -> bytes:
    """A `tf2_msgs/TFMessage` as CDR with one static transform floor frame -> optical frame
    per camera of `mounts` ({(cell, camera): mount}): `/tf_static` keeps only its last
    message, so that message names every camera (as tf2_ros' StaticTransformBroadcaster
    does). With `placements` (`placement_transforms`) it also names each camera's floor
    frame in its cell's."""
    types = _types()
    transforms = placement_transforms(placements or {}, stamp_ns)
    for (cell, camera), mount in mounts.items():
        (tx, ty, tz), (qx, qy, qz, qw) = mount_pose(mount)
        transforms.append(
            types["geometry_msgs/msg/TransformStamped"](
                header=_header(stamp_ns, floor_frame(cell, camera)),
                child_frame_id=optical_frame(cell, camera),
                transform=types["geometry_msgs/msg/Transform"](
                    translation=types["geometry_msgs/msg/Vector3"](x=tx, y=ty, z=tz),
                    rotation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
                ),
            )
        )
    return _serialise(types[TF_MESSAGE](transforms=transforms), TF_MESSAGE)


def float64_message(value: float) -> bytes:
    """A `std_msgs/Float64` as CDR."""
    return _serialise(_types()[FLOAT64](data=float(value)), FLOAT64)


def string_message(text: str) -> bytes:
    """A `std_msgs/String` as CDR."""
    return _serialise(_types()[STRING](data=str(text)), STRING)


@dataclass(frozen=True)
class MarkerSpec:
    """One `visualization_msgs/Marker`: `kind` (ARROW, LINE_STRIP, ...), its `points`
    ((n, 3) m, in the array's frame), colour (r, g, b, a in 0..1), line width or arrow shaft
    diameter (m), the text of a TEXT_VIEW_FACING marker at `position`; `delete` removes the
    marker of this ns and id."""

    ns: str
    id: int
    kind: int = LINE_STRIP
    points: Sequence = ()
    rgba: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)
    width_m: float = 0.02
    text: str = ""
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    delete: bool = False


def _marker(spec: MarkerSpec, header):
    types = _types()
    point, vector = types["geometry_msgs/msg/Point"], types["geometry_msgs/msg/Vector3"]
    r, g, b, a = (float(c) for c in spec.rgba)
    width = float(spec.width_m)
    # ARROW from two points: x the shaft's diameter, y the head's, z the head's length
    scale = {ARROW: (width, 2 * width, 3 * width), TEXT_VIEW_FACING: (0, 0, 0.15)}.get(
        spec.kind, (width, 0.0, 0.0)
    )
    x, y, z = (float(v) for v in spec.position)
    return types["visualization_msgs/msg/Marker"](
        header=header,
        ns=spec.ns,
        id=int(spec.id),
        type=int(spec.kind),
        action=MARKER_DELETE if spec.delete else MARKER_ADD,
        pose=types["geometry_msgs/msg/Pose"](
            position=point(x=x, y=y, z=z),
            orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        ),
        scale=vector(x=scale[0], y=scale[1], z=scale[2]),
        color=types["std_msgs/msg/ColorRGBA"](r=r, g=g, b=b, a=a),
        lifetime=types["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
        frame_locked=False,
        points=[point(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in spec.points],
        colors=[],
        texture_resource="",
        texture=types["sensor_msgs/msg/CompressedImage"](
            header=_header(0, ""), format="", data=np.zeros(0, np.uint8)
        ),
        uv_coordinates=[],
        text=spec.text,
        mesh_resource="",
        mesh_file=types["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, np.uint8)),
        mesh_use_embedded_materials=False,
    )


def marker_array_message(markers: Sequence[MarkerSpec], stamp_ns: int, frame_id: str) -> bytes:
    """A `visualization_msgs/MarkerArray` as CDR: every marker stamped in `frame_id`."""
    header = _header(stamp_ns, frame_id)
    message = _types()[MARKER_ARRAY](markers=[_marker(m, header) for m in markers])
    return _serialise(message, MARKER_ARRAY)


def placement_transforms(
    placements: Mapping[tuple[str, str], tuple[np.ndarray, float]], stamp_ns: int
) -> list:
    """`geometry_msgs/TransformStamped`s `<cell>_floor` -> `<cell>_<camera>_floor`, one per
    camera of `placements` ({(cell, camera): (offset (x, y, 0) m, yaw in degrees)}): where the
    cell file places each camera's floor frame in the cell's."""
    types = _types()
    out = []
    for (cell, camera), (offset, yaw_deg) in placements.items():
        qx, qy, qz, qw = Rotation.from_euler("z", float(yaw_deg), degrees=True).as_quat()
        tx, ty, tz = (float(v) for v in offset)
        out.append(
            types["geometry_msgs/msg/TransformStamped"](
                header=_header(stamp_ns, cell_floor_frame(cell)),
                child_frame_id=floor_frame(cell, camera),
                transform=types["geometry_msgs/msg/Transform"](
                    translation=types["geometry_msgs/msg/Vector3"](x=tx, y=ty, z=tz),
                    rotation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
                ),
            )
        )
    return out
