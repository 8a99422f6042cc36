"""The viewer's Foxglove sink: live through the Foxglove SDK's WebSocket server.

`topseg viewer --foxglove [--foxglove-host H --foxglove-port P]` serves, per camera, on the
topics `/topseg/<cell>/<camera>/<stream>` (`ros2_messages.ros2_topic`, the names recordings
and the ROS 2 bridge use), with Foxglove's own schemas (protobuf):

| stream         | schema                      | what                                              |
|----------------|-----------------------------|---------------------------------------------------|
| `depth`        | `foxglove.RawImage`         | `16UC1`, millimetres, 0 = no reading              |
| `labels`       | `foxglove.RawImage`         | `mono8`, the label ids of `core/labels.py`        |
| `labels_color` | `foxglove.RawImage`         | `rgb8`, the labels in the label table's colours   |
| `camera_info`  | `foxglove.CameraCalibration`| the pinhole of the depth frames                   |
| `points`       | `foxglove.PointCloud`       | the labelled cloud, x y z float32 + r g b a uint8 |
| `mount`        | `foxglove.FrameTransform`   | floor frame -> the camera's optical frame         |
| `stats`        | JSON (`STATS_SCHEMA`)       | the worker's and driver's stats messages          |

Images and the calibration are in the camera's optical frame (`<cell>_<camera>_optical_frame`);
the cloud is in the floor frame (`<cell>_<camera>_floor`) when the mount is known, else in the
optical frame, and `mount` is sent with every depth frame that has one (so a client that
connects late gets it). `stats` carries each stats message as it came (ms per stage, fps,
counts, floor share), for Foxglove's Plot panel (`/topseg/<cell>/<camera>/stats.timings_ms.total`).
Per cell (advertised with its first camera or safety state): `/topseg/<cell>/safety`, the
safety state as JSON (`SAFETY_SCHEMA`: state, `level` 0/1/2, speed scale, reasons, zones...);
`/topseg/<cell>/safety/scene`, a `foxglove.SceneUpdate` in `<cell>_floor` (the cell frame)
with the nearest pair (`nearest`: a line and its distance) and, with `--cell`, the zones
(`zone/<name>`: outlines coloured by their state); with `--cell`,
`/topseg/<cell>/safety/placements`, `foxglove.FrameTransforms` `<cell>_floor` ->
`<cell>_<camera>_floor` for the file's cameras, so the zones sit on the clouds.
With `--cell` and a robot in it (shown as the Rerun sink shows it), also
`/topseg/<cell>/safety/robot`, a `foxglove.SceneUpdate` in `<cell>_floor` on a channel of
its own (so it and the zones' scene do not replace each other's entities): one entity
`robot`, the robot's bounding capsules at its newest joint state, per capsule a cylinder
between its ends, 2 * radius across, and a sphere at each end (one when the ends meet),
grey-blue and half transparent; and, per camera of the file,
`/topseg/<cell>/<camera>/robot_silhouette`, a `foxglove.RawImage` (`mono8`, 255 where the
robot is, 0 elsewhere) in the camera's optical frame: the robot rendered as that camera sees
it at its newest joint state, stamped with the depth frame it was rendered for.
Both are advertised with their first message.
Images and clouds are converted only while a client subscribes to them; each client's queue holds `CLIENT_BACKLOG` messages, the oldest dropped first.
`docs/foxglove/topseg-layout.json` opens these topics laid out.
"""

from __future__ import annotations

import argparse
import logging

import numpy as np

from topseg.core import labels
from topseg.core.camera import axis_depth
from topseg.core.errors import TopsegError
from topseg.core.formats import ros2_messages
from topseg.services.live import safety_view

log = logging.getLogger("topseg.viewer")

#: the Foxglove SDK's own default port
FOXGLOVE_PORT = 8765
#: messages queued per client before the oldest is dropped (the SDK's default, 1024 frames
#: of 640x480 depth, would be 600 MB for one slow client)
CLIENT_BACKLOG = 32
#: the streams served per camera with Foxglove's schemas, in the order they are advertised
STREAMS = ("depth", "labels", "labels_color", "camera_info", "points", "mount")
#: the JSON stream of stats messages (`wire.decode_stats`), advertised after STREAMS
STATS_STREAM = "stats"
#: a camera's image of the robot's rendered silhouette, advertised with the first one
SILHOUETTE_STREAM = "robot_silhouette"
#: the robot's capsules (r, g, b, a in 0..1): a neutral grey-blue, half transparent
ROBOT_RGBA = (0.45, 0.55, 0.7, 0.5)
#: the JSON schema of the stats channel: what Foxglove's panels offer to plot
STATS_SCHEMA = {
    "type": "object",
    "title": "topseg.Stats",
    "properties": {
        "stamp_ns": {"type": "integer", "description": "when the stats were sent (ns)"},
        "role": {"type": "string", "description": "driver or worker"},
        "seq": {"type": "integer", "description": "the frame the timings are of"},
        "fps": {"type": "number", "description": "frames a second"},
        "timings_ms": {
            "type": "object",
            "description": "ms per stage: receive, mount, forest, crf, publish, total, latency",
            "additionalProperties": {"type": "number"},
        },
        "counts": {
            "type": "object",
            "description": "frames processed, dropped, rejected, ...",
            "additionalProperties": {"type": "integer"},
        },
        "floor_share": {"type": "number", "description": "share of depth pixels gated as floor"},
    },
}
#: one point of a PointCloud: x, y, z float32 then r, g, b, a uint8
POINT_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgba", "u1", (4,))])


#: the JSON schema of a cell's safety channel (`safety_wire`'s fields)
SAFETY_SCHEMA = {
    "type": "object",
    "title": "topseg.Safety",
    "properties": {
        "seq": {"type": "integer", "description": "the decision's number"},
        "stamp_ns": {"type": "integer", "description": "when it was decided (ns)"},
        "state": {"type": "string", "description": "clear, warning or stop"},
        "level": {"type": "number", "description": "the state as a number: 0, 1, 2"},
        "speed_scale": {"type": "number", "description": "share of full speed, 0..1"},
        "min_distance_m": {"type": ["number", "null"], "description": "nearest person (m)"},
        "part": {"type": "string", "description": "body part of the nearest pair"},
        "link": {"type": "string", "description": "robot link of the nearest pair"},
        "reaction_ms": {"type": ["number", "null"], "description": "depth stamp to decision"},
        "reasons": {"type": "array", "items": {"type": "string"}},
        "zones": {"type": "object", "additionalProperties": {"type": "string"}},
    },
}


def safety_topic(cell: str, stream: str | None = None) -> str:
    """A cell's Foxglove safety topic: `/topseg/<cell>/safety`, or `.../safety/<stream>`."""
    return f"/topseg/{cell}/safety" if stream is None else ros2_messages.safety_topic(cell, stream)


def safety_map(state) -> dict:
    """A safety state as the JSON the safety channel carries."""
    return {
        "seq": state.seq,
        "stamp_ns": state.stamp_ns,
        "state": state.state,
        "level": safety_view.STATE_LEVELS[state.state],
        "speed_scale": state.speed_scale,
        "min_distance_m": state.min_distance_m,
        "part": state.part,
        "link": state.link,
        "reaction_ms": state.reaction_ms,
        "reasons": list(state.reasons),
        "zones": dict(state.zones),
    }


def _colour(state: str | None):
    from foxglove.messages import Color

    r, g, b, a = safety_view.rgba(state)
    return Color(r=r, g=g, b=b, a=a)


def _points(points) -> list:
    from foxglove.messages import Point3

    return [Point3(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in points]


def scene_update(cell: str, zones, state):
    """The zones (`zone/<name>`: their outlines, by their states) and the nearest pair
    (`nearest`: a line and its distance; deleted when there is none) in `<cell>_floor`."""
    from foxglove.messages import (
        LinePrimitive,
        LinePrimitiveLineType,
        Pose,
        Quaternion,
        SceneEntity,
        SceneEntityDeletion,
        SceneEntityDeletionType,
        SceneUpdate,
        TextPrimitive,
        Vector3,
    )

    frame, stamp = ros2_messages.cell_floor_frame(cell), _timestamp(state.stamp_ns)
    entities = []
    for zone in zones:
        colour = _colour(state.zones.get(zone.name))
        lines = [
            LinePrimitive(
                type=LinePrimitiveLineType.LineStrip, thickness=0.02, points=_points(strip),
                color=colour,
            )
            for strip in safety_view.zone_strips(zone)
        ]  # fmt: skip
        entities.append(
            SceneEntity(timestamp=stamp, frame_id=frame, id=f"zone/{zone.name}", lines=lines)
        )
    if state.nearest_m is None:
        deletion = SceneEntityDeletion(
            timestamp=stamp, type=SceneEntityDeletionType.MatchingId, id="nearest"
        )
        return SceneUpdate(deletions=[deletion], entities=entities)
    person, robot = (np.asarray(p, np.float64) for p in state.nearest_m)
    middle = (person + robot) / 2
    text = "" if state.min_distance_m is None else f"{state.min_distance_m:.2f} m"
    label = TextPrimitive(
        pose=Pose(
            position=Vector3(x=float(middle[0]), y=float(middle[1]), z=float(middle[2]) + 0.1),
            orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
        ),
        billboard=True, font_size=14.0, scale_invariant=True, color=_colour(state.state),
        text=text,
    )  # fmt: skip
    line = LinePrimitive(
        type=LinePrimitiveLineType.LineStrip, thickness=0.03, points=_points([person, robot]),
        color=_colour(state.state),
    )  # fmt: skip
    entities.append(
        SceneEntity(timestamp=stamp, frame_id=frame, id="nearest", lines=[line], texts=[label])
    )
    return SceneUpdate(entities=entities)


def robot_scene(cell: str, capsules, stamp_ns: int):
    """The robot's capsules (`Capsules`, cell frame) as one entity `robot` in `<cell>_floor`:
    per capsule a cylinder from end a to end b, 2 * radius across, and a sphere at each end
    (one sphere when a == b); grey-blue, half transparent (`ROBOT_RGBA`)."""
    from foxglove.messages import (
        Color,
        CylinderPrimitive,
        Pose,
        Quaternion,
        SceneEntity,
        SceneUpdate,
        SpherePrimitive,
        Vector3,
    )

    r, g, b, a = ROBOT_RGBA
    colour, upright = Color(r=r, g=g, b=b, a=a), Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)
    posed = safety_view.posed_capsules(capsules)  # turned from +z onto b - a (`_z_to`)
    ends_b = np.asarray(capsules.b, np.float64).reshape(-1, 3)
    cylinders, spheres = [], []
    for start, end, q, length, radius in zip(
        posed.translation, ends_b, posed.quaternion, posed.length, posed.radius, strict=True
    ):
        width = 2.0 * float(radius)
        ends = (start,) if np.array_equal(start, end) else (start, end)
        spheres += [
            SpherePrimitive(
                pose=Pose(position=_vector(p), orientation=upright),
                size=Vector3(x=width, y=width, z=width), color=colour,
            )
            for p in ends
        ]  # fmt: skip
        if len(ends) == 2:
            turn = Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))
            cylinders.append(
                CylinderPrimitive(
                    pose=Pose(position=_vector((start + end) / 2), orientation=turn),
                    size=Vector3(x=width, y=width, z=float(length)),
                    bottom_scale=1.0, top_scale=1.0, color=colour,
                )
            )  # fmt: skip
    entity = SceneEntity(
        timestamp=_timestamp(stamp_ns), frame_id=ros2_messages.cell_floor_frame(cell),
        id="robot", spheres=spheres, cylinders=cylinders,
    )  # fmt: skip
    return SceneUpdate(entities=[entity])


def _vector(point):
    from foxglove.messages import Vector3

    return Vector3(x=float(point[0]), y=float(point[1]), z=float(point[2]))


def placements(config, stamp_ns: int):
    """`<cell>_floor` -> `<cell>_<camera>_floor` for every camera of a cell file."""
    from foxglove.messages import FrameTransform, FrameTransforms, Quaternion, Vector3

    out = []
    for camera in config.cameras:
        half = np.radians(camera.yaw_deg) / 2
        out.append(
            FrameTransform(
                timestamp=_timestamp(stamp_ns),
                parent_frame_id=ros2_messages.cell_floor_frame(config.cell),
                child_frame_id=ros2_messages.floor_frame(config.cell, camera.name),
                translation=Vector3(x=camera.x_m, y=camera.y_m, z=0.0),
                rotation=Quaternion(x=0.0, y=0.0, z=float(np.sin(half)), w=float(np.cos(half))),
            )
        )
    return FrameTransforms(transforms=out)


def add_foxglove_arguments(parser: argparse.ArgumentParser) -> None:
    """--foxglove, --foxglove-host and --foxglove-port."""
    parser.add_argument(
        "--foxglove",
        action="store_true",
        help="serve live to Foxglove (its SDK's WebSocket server); alone: Foxglove only",
    )
    parser.add_argument(
        "--foxglove-host",
        default="127.0.0.1",
        metavar="H",
        help="address the Foxglove server listens on (default: %(default)s; 0.0.0.0: all)",
    )
    parser.add_argument(
        "--foxglove-port",
        type=int,
        default=FOXGLOVE_PORT,
        metavar="P",
        help="port of the Foxglove server (default: %(default)s; 0: any free one)",
    )


def topic(cell: str, camera: str, stream: str) -> str:
    """The Foxglove topic of a camera's stream."""
    return ros2_messages.ros2_topic(cell, camera, stream)


def point_cloud_bytes(xyz: np.ndarray, rgba: np.ndarray) -> bytes:
    """The packed PointCloud data of (N, 3) float32 points and their (N, 4) uint8 colours."""
    packed = np.empty(len(xyz), POINT_DTYPE)
    packed["x"], packed["y"], packed["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    packed["rgba"] = rgba
    return packed.tobytes()


def _timestamp(stamp_ns: int):
    from foxglove.messages import Timestamp

    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    return Timestamp(sec, nsec)


def _raw_image(image: np.ndarray, encoding: str, stamp_ns: int, frame_id: str):
    from foxglove.messages import RawImage

    image = np.ascontiguousarray(image)
    return RawImage(
        timestamp=_timestamp(stamp_ns),
        frame_id=frame_id,
        width=image.shape[1],
        height=image.shape[0],
        encoding=encoding,
        step=image.shape[1] * image.itemsize * (image.shape[2] if image.ndim == 3 else 1),
        data=image.tobytes(),
    )


class FoxgloveSink:
    """Serves the viewer's cameras to Foxglove clients over the SDK's WebSocket server."""

    def __init__(self, server, context, cell=None) -> None:
        self.server, self.context, self.cell = server, context, cell
        self.channels: dict[tuple[str, str], dict] = {}
        self.cell_streams: dict[str, dict] = {}
        if cell is not None:  # advertised before any client connects, not with the first state
            self.cell_channels(cell.name)

    @classmethod
    def start(cls, host: str, port: int, cell=None) -> FoxgloveSink:
        """Start the WebSocket server on host:port; a TopsegError when it cannot."""
        import foxglove

        context = foxglove.Context()
        try:
            server = foxglove.start_server(
                name="topseg",
                host=host,
                port=port,
                context=context,
                message_backlog_size=CLIENT_BACKLOG,
            )
        except Exception as exc:
            raise TopsegError(f"cannot serve Foxglove on {host}:{port}: {exc}") from None
        log.info("Foxglove WebSocket server: ws://%s:%d", host, server.port)
        return cls(server, context, cell)

    def cameras_changed(self, cameras) -> None:
        """Advertise the channels of cameras not seen before."""
        from foxglove import channels as fc

        kinds = {
            "depth": fc.RawImageChannel,
            "labels": fc.RawImageChannel,
            "labels_color": fc.RawImageChannel,
            "camera_info": fc.CameraCalibrationChannel,
            "points": fc.PointCloudChannel,
            "mount": fc.FrameTransformChannel,
        }
        import foxglove

        for cam in cameras:
            self.cell_channels(cam[0])
            if cam not in self.channels:
                self.channels[cam] = {
                    stream: kinds[stream](topic(*cam, stream), context=self.context)
                    for stream in STREAMS
                }
                self.channels[cam][STATS_STREAM] = foxglove.Channel(
                    topic(*cam, STATS_STREAM), schema=STATS_SCHEMA, context=self.context
                )

    def depth(self, cam: tuple[str, str], frame) -> None:
        """The depth image, the camera's calibration and its mount (when known)."""
        from foxglove.messages import CameraCalibration, FrameTransform, Quaternion, Vector3

        channels, optical = self.channels[cam], ros2_messages.optical_frame(*cam)
        stamp = _timestamp(frame.stamp_ns)
        if channels["depth"].has_sinks():  # a client subscribed: worth the copy
            depth = axis_depth(frame.depth, frame.mount)  # z, also from a range camera
            channels["depth"].log(_raw_image(depth, "16UC1", frame.stamp_ns, optical))
        k = frame.intrinsics
        channels["camera_info"].log(
            CameraCalibration(
                timestamp=stamp,
                frame_id=optical,
                width=k.width,
                height=k.height,
                distortion_model="plumb_bob",
                D=[0.0] * 5,
                K=[k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0],
                R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                P=[k.fx, 0.0, k.cx, 0.0, 0.0, k.fy, k.cy, 0.0, 0.0, 0.0, 1.0, 0.0],
            )
        )
        if frame.mount is not None:
            (tx, ty, tz), (qx, qy, qz, qw) = ros2_messages.mount_pose(frame.mount)
            channels["mount"].log(
                FrameTransform(
                    timestamp=stamp,
                    parent_frame_id=ros2_messages.floor_frame(*cam),
                    child_frame_id=optical,
                    translation=Vector3(x=tx, y=ty, z=tz),
                    rotation=Quaternion(x=qx, y=qy, z=qz, w=qw),
                )
            )

    def labels(self, cam: tuple[str, str], frame, cloud) -> None:
        """The label ids, their colours, and the labelled cloud when there is one."""
        from foxglove.messages import PackedElementField, PackedElementFieldNumericType, PointCloud

        channels, optical = self.channels[cam], ros2_messages.optical_frame(*cam)
        if channels["labels"].has_sinks():
            channels["labels"].log(_raw_image(frame.labels, "mono8", frame.stamp_ns, optical))
        if channels["labels_color"].has_sinks():
            channels["labels_color"].log(
                _raw_image(labels.colorize(frame.labels), "rgb8", frame.stamp_ns, optical)
            )
        if cloud is None or not channels["points"].has_sinks():
            return
        f32, u8 = PackedElementFieldNumericType.Float32, PackedElementFieldNumericType.Uint8
        fields = [
            PackedElementField(name=name, offset=4 * i, type=f32) for i, name in enumerate("xyz")
        ] + [
            PackedElementField(name=name, offset=12 + i, type=u8)
            for i, name in enumerate(("red", "green", "blue", "alpha"))
        ]
        channels["points"].log(
            PointCloud(
                timestamp=_timestamp(frame.stamp_ns),
                frame_id=ros2_messages.floor_frame(*cam) if cloud.in_floor_frame else optical,
                point_stride=POINT_DTYPE.itemsize,
                fields=fields,
                data=point_cloud_bytes(cloud.xyz, cloud.rgba()),
            )
        )

    def stats(self, cam: tuple[str, str], stats: dict) -> None:
        """The stats message as JSON, logged at its own stamp."""
        channel = self.channels[cam][STATS_STREAM]
        if channel.has_sinks():
            channel.log(stats, log_time=int(stats["stamp_ns"]))

    def cell_channels(self, cell: str) -> dict:
        """A cell's safety channels: the state as JSON, its zones and nearest pair as a
        SceneUpdate and, with a cell file, where its cameras hang. The cell file's cell has
        them from the start; another cell with its first state."""
        import foxglove
        from foxglove import channels as fc

        found = self.cell_streams.get(cell)
        if found is None:
            found = self.cell_streams[cell] = {
                "state": foxglove.Channel(
                    safety_topic(cell), schema=SAFETY_SCHEMA, context=self.context
                ),
                "scene": fc.SceneUpdateChannel(safety_topic(cell, "scene"), context=self.context),
            }
            if self.cell is not None and self.cell.name == cell:
                found["placements"] = fc.FrameTransformsChannel(
                    safety_topic(cell, "placements"), context=self.context
                )
        return found

    def safety(self, cell: str, state) -> None:
        """A cell's state as JSON; its zones (with a cell file) and nearest pair as scene
        entities in `<cell>_floor`, coloured by state; the cameras' placements."""
        channels = self.cell_channels(cell)
        log_time = int(state.stamp_ns)
        channels["state"].log(safety_map(state), log_time=log_time)
        zones = self.cell.config.zones if self.cell is not None and self.cell.name == cell else ()
        channels["scene"].log(scene_update(cell, zones, state), log_time=log_time)
        if "placements" in channels:
            channels["placements"].log(
                placements(self.cell.config, state.stamp_ns), log_time=log_time
            )

    def silhouette(self, cam: tuple[str, str], frame, mask) -> None:
        """The robot's rendered silhouette as this camera sees it, on the camera's
        `robot_silhouette` channel (advertised with the first one): `mono8`, 255 where the
        robot is and 0 elsewhere, in the camera's optical frame at the depth frame's stamp."""
        from foxglove import channels as fc

        channels = self.channels[cam]
        channel = channels.get(SILHOUETTE_STREAM)
        if channel is None:
            channel = channels[SILHOUETTE_STREAM] = fc.RawImageChannel(
                topic(*cam, SILHOUETTE_STREAM), context=self.context
            )
        if channel.has_sinks():
            image = np.where(np.asarray(mask, bool), np.uint8(255), np.uint8(0))
            optical = ros2_messages.optical_frame(*cam)
            channel.log(_raw_image(image, "mono8", frame.stamp_ns, optical))  # as the depth

    def robot(self, cell: str, capsules, stamp_ns: int) -> None:
        """The robot's capsules at its newest joint state (measured at `stamp_ns`) as the
        entity `robot` (`robot_scene`) on the cell's `/topseg/<cell>/safety/robot`
        SceneUpdate channel, advertised with the first capsules; a channel of its own, so
        that the zones' scene and the robot's do not replace each other."""
        from foxglove import channels as fc

        channels = self.cell_channels(cell)
        if "robot" not in channels:
            channels["robot"] = fc.SceneUpdateChannel(
                safety_topic(cell, "robot"), context=self.context
            )
        channels["robot"].log(robot_scene(cell, capsules, stamp_ns), log_time=int(stamp_ns))

    def close(self) -> None:
        """Stop the server (clients see it go)."""
        self.server.stop()
