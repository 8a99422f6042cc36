"""Show what flows on Zenoh: every camera's depth, labels, labelled point cloud and the
worker's timings, in Rerun (`--spawn`, `--web`, or `--save FILE.rrd`) and/or Foxglove
(`--foxglove`).

    topseg viewer [--spawn | --web | --save FILE.rrd] [--foxglove] [...]

Rerun: `--spawn` (the default when `--foxglove` is not given) opens the native viewer,
`--web` serves Rerun's web viewer (`--web-port`) and its gRPC data (`--grpc-port`), `--save`
writes an `.rrd`. Foxglove: `--foxglove` serves live through the Foxglove SDK's WebSocket
server (`--foxglove-host`, `--foxglove-port`; see `services/live/viewer_foxglove.py`). Given
alone, `--foxglove` drives Foxglove only; with a Rerun option, both.

For every camera seen on `topseg/*/*/{depth,labels,stats}` the Rerun sink logs under the
entity paths of `services/live/viewer_layout.py`: the camera's mount as a Transform3D in the
floor frame `world` (z up), its Pinhole with the depth (`rr.DepthImage`, metres = mm / 1000)
and label (`rr.SegmentationImage`) images, the label-coloured point cloud (every
`--stride`-th pixel of every `--stride`-th row of a labels message and the depth frame with
the same `seq`, `core/labelled_cloud.py`) in floor coordinates, and the worker's stats
(`ms/<stage>`, `fps`, `count/<name>`) as scalars over time. The label table is the static
AnnotationContext at the root and a legend view; a blueprint lays the views out at start
and again when a camera appears. Each message is logged on the `frame` timeline (its `seq`)
and `sensor_time` (its stamp). Undecodable messages are counted and skipped; Zenoh's
thread only queues (bounded), the logging loop drops and counts what it cannot take.
`--save` flushes the `.rrd` on SIGTERM, SIGINT or after `--duration` seconds.

Every cell's safety state (`topseg/<cell>/safety`) is logged too: the state (clear 0,
warning 1, stop 2), speed scale, reaction time and nearest distance as scalars, each change
of state or reasons as a text log line, and the nearest person-robot pair as a line labelled
with its distance. With `--cell CELL.toml` (optional) the viewer also draws the cell's
zones coloured by their newest state (clear green, warning amber, stop red, grey before the
first) and the robot's bounding capsules at its joint states (`topseg/<cell>/robot/<name>/
joints`, at most 30 a second), each in every camera's world frame of the cell file, where
that camera's cloud is (`services/live/safety_view.py`), and the robot rendered as each
camera sees it at its newest joint state over that camera's image (`robot_silhouette`, at
most five times a second).
"""

from __future__ import annotations

import argparse
import logging
import os
import time
import urllib.parse
from collections import OrderedDict
from typing import Any

import numpy as np

from topseg.core import labels
from topseg.core.camera import axis_depth
from topseg.core.errors import TopsegError
from topseg.core.formats import joint_states as joint_wire
from topseg.core.formats import safety_wire, wire
from topseg.core.formats.ros2_messages import mount_pose
from topseg.core.labelled_cloud import labelled_cloud
from topseg.core.printable import printable
from topseg.services.cli.options import finite, int_range
from topseg.services.live import safety_view, viewer_layout
from topseg.services.live.safety_view import CellView
from topseg.services.live.viewer_foxglove import FoxgloveSink, add_foxglove_arguments
from topseg.services.runtime import zenoh_session
from topseg.services.runtime.inbox import Inbox
from topseg.services.runtime.lifecycle import ServiceLifecycle

log = logging.getLogger("topseg.viewer")

#: depth frames kept per camera while their labels are on the way
PAIR_WINDOW = 16
#: messages queued between Zenoh's thread and the logging loop (older ones are dropped)
QUEUE_SIZE = 64
#: joint states are shown at most this often (s)
JOINT_PERIOD_S = 1 / 30
#: the robot's rendered silhouette is drawn over a camera's image at most this often (s): a
#: ray cast of the robot a frame would cost the viewer as much as it costs the safety service
SILHOUETTE_PERIOD_S = 0.2
#: Rerun's own default ports of its web viewer and its gRPC server
WEB_PORT, GRPC_PORT = 9090, 9876
#: how much the viewer lowers its CPU priority by default (nice): a view may lag, a decision not
VIEWER_NICE = 10


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The viewer's options: the sinks, --duration, --stride and Zenoh."""
    sink = parser.add_mutually_exclusive_group()
    sink.add_argument(
        "--spawn",
        action="store_true",
        help="open a native Rerun viewer (default without --foxglove)",
    )
    sink.add_argument("--web", action="store_true", help="serve Rerun's web viewer (HTTP + gRPC)")
    sink.add_argument("--save", metavar="FILE.rrd", help="write a Rerun recording instead")
    parser.add_argument(
        "--web-port", type=int, default=WEB_PORT, metavar="P",
        help="--web: HTTP port of the web viewer (default: %(default)s)",
    )  # fmt: skip
    parser.add_argument(
        "--grpc-port", type=int, default=GRPC_PORT, metavar="P",
        help="--web: gRPC port the web viewer reads the data from (default: %(default)s)",
    )  # fmt: skip
    add_foxglove_arguments(parser)
    parser.add_argument(
        "--duration",
        type=finite(0.001, 1e8),
        metavar="S",
        help="stop after this many seconds (default: never)",
    )
    parser.add_argument(
        "--cell",
        metavar="CELL.toml",
        help="a cell file: also show its zones coloured by their state and its robot at "
        "its joint states (default: states, speed scale and nearest pair only)",
    )
    parser.add_argument(
        "--stride",
        type=int,
        default=4,
        metavar="N",
        help="point cloud: every N-th pixel and row (default: %(default)s)",
    )
    parser.add_argument(
        "--nice",
        type=int_range(0, 19),
        default=VIEWER_NICE,
        metavar="N",
        help="lower the viewer's CPU priority by N (default: %(default)s), so that on a cell "
        "PC it never takes the cores from the driver, worker and safety service; 0 keeps it",
    )
    zenoh_session.add_arguments(parser)


def annotation_context():
    """The label table as a Rerun AnnotationContext (ids, names, colours)."""
    import rerun as rr

    return rr.AnnotationContext(
        [
            (lab.id, lab.name, tuple(int(c) for c in lab.color))
            for lab in (*labels.LABELS, labels.NO_DEPTH_LABEL)
        ]
    )


class RerunSink:
    """Logs the viewer's cameras to one Rerun RecordingStream, laid out by a blueprint."""

    def __init__(self, rec, cell: CellView | None = None) -> None:
        import rerun as rr

        self.rec, self.cell = rec, cell
        self.pinholes: dict[tuple[str, str], Any] = {}
        self.mounts: dict[tuple[str, str], Any] = {}
        self.cameras: list[tuple[str, str]] = []
        self.cells: set[str] = set()
        #: what was last drawn of each cell's state: (zones, nearest, reasons) by cell
        self.drawn: dict[str, tuple] = {}
        rec.log("/", annotation_context(), static=True)
        rec.log(viewer_layout.WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        rec.log(viewer_layout.LEGEND, viewer_layout.legend_points(), static=True)
        if cell is not None:
            self.cells.add(cell.name)
            self._zones(cell.name, {})  # grey until the first state
        rec.send_blueprint(viewer_layout.blueprint([], self.cells))

    def cameras_changed(self, cameras) -> None:
        """Lay the views out again for this set of (cell, camera)."""
        self.cameras = list(cameras)
        self.rec.send_blueprint(viewer_layout.blueprint(self.cameras, self.cells))

    def _frames(self, cell: str) -> list[tuple[str, Any]]:
        """Where a cell's safety shapes go: (entity, camera placement) per camera of the
        cell file, each in that camera's world frame (beside its cloud); without the cell's
        file one entity in the cell frame."""
        if self.cell is None or self.cell.name != cell:
            return [(viewer_layout.safety_shapes_entity(cell), None)]
        return [
            (viewer_layout.safety_shapes_entity(cell, c.name), c) for c in self.cell.config.cameras
        ]

    def _zones(self, cell: str, states: dict[str, str]) -> None:
        """The cell file's zones as line strips, coloured by their states."""
        import rerun as rr

        for zone in self.cell.config.zones:
            colour = safety_view.state_colour(states.get(zone.name))
            for entity, placement in self._frames(cell):
                self.rec.log(
                    f"{entity}/zones/{zone.name}",
                    rr.LineStrips3D(
                        safety_view.zone_strips(zone, placement), colors=colour, radii=0.01
                    ),
                )

    def safety(self, cell: str, state) -> None:
        """A cell's state: its scalars over time; its zones, nearest pair and reasons when
        they changed."""
        import rerun as rr

        self.rec.reset_time()
        if state.frame is not None:
            self.rec.set_time("frame", sequence=state.frame[1])
        self.rec.set_time("sensor_time", timestamp=state.stamp_ns * 1e-9)
        if cell not in self.cells:
            self.cells.add(cell)
            self.rec.send_blueprint(viewer_layout.blueprint(self.cameras, self.cells))
        base = viewer_layout.safety_entity(cell)
        self.rec.log(f"{base}/state", rr.Scalars(safety_view.STATE_LEVELS[state.state]))
        self.rec.log(f"{base}/speed_scale", rr.Scalars(state.speed_scale))
        if state.reaction_ms is not None:
            self.rec.log(f"{base}/reaction_ms", rr.Scalars(state.reaction_ms))
        if state.min_distance_m is not None:
            self.rec.log(f"{base}/min_distance_m", rr.Scalars(state.min_distance_m))
        zones, nearest, reasons = self.drawn.get(cell, (None, None, None))
        if (state.state, state.reasons) != reasons:
            level = {"clear": "INFO", "warning": "WARN", "stop": "ERROR"}[state.state]
            text = f"{state.state}: " + ("; ".join(state.reasons) or "-")
            self.rec.log(f"{base}/reasons", rr.TextLog(text, level=level))
        if self.cell is not None and self.cell.name == cell and state.zones != zones:
            self._zones(cell, state.zones)
        if state.nearest_m != nearest:
            self._nearest(cell, state)
        self.drawn[cell] = (state.zones, state.nearest_m, (state.state, state.reasons))

    def _nearest(self, cell: str, state) -> None:
        """The nearest pair as a line labelled with its distance (cleared when none)."""
        import rerun as rr

        for entity, placement in self._frames(cell):
            if state.nearest_m is None:
                self.rec.log(f"{entity}/nearest", rr.Clear(recursive=False))
                continue
            pair = safety_view.in_frame(np.array(state.nearest_m), placement)
            label = "" if state.min_distance_m is None else f"{state.min_distance_m:.2f} m"
            self.rec.log(
                f"{entity}/nearest",
                rr.LineStrips3D(
                    [pair], colors=safety_view.state_colour(state.state), radii=0.015,
                    labels=[label], show_labels=True,
                ),
            )  # fmt: skip

    def robot(self, cell: str, capsules, stamp_ns: int) -> None:
        """The robot's capsules at its newest joint state (measured at `stamp_ns`)."""
        import rerun as rr

        self.rec.reset_time()
        self.rec.set_time("sensor_time", timestamp=stamp_ns * 1e-9)
        for entity, placement in self._frames(cell):
            posed = safety_view.posed_capsules(capsules, placement)
            self.rec.log(
                f"{entity}/robot",
                rr.Capsules3D(
                    lengths=posed.length, radii=posed.radius, translations=posed.translation,
                    quaternions=posed.quaternion, labels=list(posed.link),
                    class_ids=[labels.ROBOT] * len(posed.link),
                ),
            )  # fmt: skip

    def silhouette(self, cam: tuple[str, str], frame, mask: np.ndarray) -> None:
        """The robot's rendered silhouette over the camera's image (robot where it is)."""
        import rerun as rr

        self._time(frame.seq, frame.stamp_ns)
        self.rec.log(
            f"{viewer_layout.image_entity(*cam)}/robot_silhouette",
            rr.SegmentationImage(mask.astype(np.uint8) * np.uint8(labels.ROBOT)),
        )

    def _time(self, seq: int, stamp_ns: int) -> None:
        self.rec.set_time("frame", sequence=seq)
        self.rec.set_time("sensor_time", timestamp=stamp_ns * 1e-9)

    def depth(self, cam: tuple[str, str], frame) -> None:
        """The camera's mount and Pinhole (when they changed) and the depth image."""
        import rerun as rr

        k = frame.intrinsics
        if self.mounts.get(cam, ...) != frame.mount:  # static: a mount changes rarely
            if frame.mount is None:  # unknown: the optical frame stands in for the floor
                transform = rr.Transform3D.cleared()
            else:
                translation, quaternion = mount_pose(frame.mount)
                transform = rr.Transform3D(
                    translation=translation, quaternion=rr.Quaternion(xyzw=quaternion)
                )
            self.rec.log(viewer_layout.camera_entity(*cam), transform, static=True)
            self.mounts[cam] = frame.mount
        if self.pinholes.get(cam) != k:  # static: the camera changes rarely, if ever
            self.rec.log(
                viewer_layout.image_entity(*cam),
                rr.Pinhole(
                    focal_length=[k.fx, k.fy],
                    principal_point=[k.cx, k.cy],
                    width=k.width,
                    height=k.height,
                    camera_xyz=rr.ViewCoordinates.RDF,
                ),
                static=True,
            )
            self.pinholes[cam] = k
        self._time(frame.seq, frame.stamp_ns)
        self.rec.log(
            f"{viewer_layout.image_entity(*cam)}/depth",
            rr.DepthImage(axis_depth(frame.depth, frame.mount), meter=1000.0),
        )

    def labels(self, cam: tuple[str, str], frame, cloud) -> None:
        """The label image, and the labelled cloud when there is one."""
        import rerun as rr

        self._time(frame.seq, frame.stamp_ns)
        self.rec.log(
            f"{viewer_layout.image_entity(*cam)}/labels", rr.SegmentationImage(frame.labels)
        )
        if cloud is not None:
            self.rec.log(
                viewer_layout.points_entity(*cam), rr.Points3D(cloud.xyz, class_ids=cloud.ids)
            )

    def stats(self, cam: tuple[str, str], stats: dict) -> None:
        """ms per stage, fps and counts as scalars over time."""
        import rerun as rr

        if "seq" in stats:
            self.rec.set_time("frame", sequence=stats["seq"])
        self.rec.set_time("sensor_time", timestamp=stats["stamp_ns"] * 1e-9)
        base = viewer_layout.stats_entity(*cam)
        for stage, ms in stats["timings_ms"].items():
            self.rec.log(f"{base}/ms/{stage}", rr.Scalars(ms))
        if "fps" in stats:
            self.rec.log(f"{base}/fps", rr.Scalars(stats["fps"]))
        for name, n in stats["counts"].items():
            self.rec.log(f"{base}/count/{name}", rr.Scalars(float(n)))

    def close(self) -> None:
        """Flush (the .rrd is complete) and disconnect."""
        self.rec.flush()
        self.rec.disconnect()


class Viewer:
    """Decodes topseg messages, pairs depth with labels and hands both to the sinks."""

    def __init__(self, sinks: list, stride: int, cell: CellView | None = None) -> None:
        self.sinks, self.stride, self.cell = sinks, stride, cell
        self.joints_key = None if cell is None else cell.joints_key()
        self.next_joints = 0.0  # monotonic s: joint states before it are skipped
        self.last_joints = None  # the newest joint state that fits the robot
        self.next_silhouette: dict[tuple[str, str], float] = {}  # camera -> monotonic s
        #: the kinds the viewer subscribes to, and their decoders
        self.decoders = {
            "depth": wire.decode_depth,
            "labels": wire.decode_labels,
            "stats": wire.decode_stats,
        }
        self.depth: dict[tuple[str, str], OrderedDict] = {}
        self.cameras: set[tuple[str, str]] = set()
        self.rejected = 0
        self.seen: set[str] = set()

    def _first(self, what: str) -> None:
        """Say once that `what` is logged (operators and tests see what is live)."""
        if what not in self.seen:
            self.seen.add(what)
            log.info("logging %s", what)

    def _reject(self, key: str, exc: Exception) -> None:
        """Count a message that does not decode; log the first ten, then every 100th."""
        self.rejected += 1
        if self.rejected <= 10 or self.rejected % 100 == 0:
            log.warning("%s: %s (%d rejected)", printable(key), printable(exc), self.rejected)

    def handle(self, key: str, payload: bytes) -> None:
        """Decode one message by the kind its key names (parsed once) and pass it on."""
        if self.on_cell_message(key, payload):
            return
        try:
            parts = wire.parse_key(key)
            decode = self.decoders.get(parts.kind)
            if decode is None:
                raise wire.WireError(f"{key!r} does not carry a message the viewer shows")
            msg = decode(payload)
        except wire.WireError as exc:
            self._reject(key, exc)
            return
        cam = (parts.cell, parts.camera)
        if cam not in self.cameras:
            self.cameras.add(cam)
            for sink in self.sinks:
                sink.cameras_changed(sorted(self.cameras))
        if parts.kind == "depth":
            self.on_depth(cam, msg)
        elif parts.kind == "labels":
            self.on_labels(cam, msg)
        else:
            for sink in self.sinks:
                sink.stats(cam, msg)
            self._first(f"{parts.cell}/{parts.camera}/stats")

    def on_cell_message(self, key: str, payload: bytes) -> bool:
        """Show a cell's safety state (`topseg/<cell>/safety`) or, with a cell file, its
        robot at a joint state (at most every JOINT_PERIOD_S); False for other keys."""
        parts = key.split("/")
        if len(parts) == 3 and parts[0] == wire.ROOT and parts[2] == safety_wire.SAFETY:
            try:
                state = safety_wire.decode_safety(payload)
            except wire.WireError as exc:
                self._reject(key, exc)
                return True
            for sink in self.sinks:
                sink.safety(parts[1], state)
            self._first(f"{parts[1]}/safety")
            return True
        if self.joints_key is None or key != self.joints_key:
            return False
        now = time.monotonic()
        if now < self.next_joints:  # a robot's joint states come faster than a view needs
            return True
        try:
            joints = joint_wire.decode_joint_state(payload)
            capsules, stamp_ns = self.cell.capsules(joints), joints.stamp_ns
        except (wire.WireError, ValueError) as exc:
            self._reject(key, exc)
            return True
        self.next_joints = now + JOINT_PERIOD_S
        self.last_joints = joints
        for sink in self.sinks:
            sink.robot(self.cell.name, capsules, stamp_ns)
        self._first(f"{self.cell.name}/robot")
        return True

    def on_depth(self, cam, frame) -> None:
        """Show the depth frame (and the robot's silhouette over it) and keep it for pairing
        with its labels."""
        for sink in self.sinks:
            sink.depth(cam, frame)
        self.robot_silhouette(cam, frame)
        frames = self.depth.setdefault(cam, OrderedDict())
        frames[frame.seq] = frame
        while len(frames) > PAIR_WINDOW:
            frames.popitem(last=False)

    def robot_silhouette(self, cam, frame) -> None:
        """With a cell file, its robot and a joint state, the robot rendered as this camera of
        the cell sees it at the newest joint state (at most every SILHOUETTE_PERIOD_S)."""
        if self.cell is None or self.cell.robot is None or self.last_joints is None:
            return
        placement = self.cell.config.camera(cam[1])
        if cam[0] != self.cell.name or placement is None or frame.mount is None:
            return
        now = time.monotonic()
        if now < self.next_silhouette.get(cam, 0.0):
            return
        self.next_silhouette[cam] = now + SILHOUETTE_PERIOD_S
        try:
            _, mask = self.cell.robot.silhouette(
                self.last_joints.as_dict(), frame.mount, placement, 0.0
            )
        except ValueError as exc:
            self._reject(f"{self.cell.name} robot", exc)
            return
        for sink in self.sinks:
            sink.silhouette(cam, frame, mask)
        self._first(f"{cam[0]}/{cam[1]}/robot silhouette")

    def on_labels(self, cam, frame) -> None:
        """Show the labels, with the labelled cloud when the depth frame of its seq is kept."""
        cloud = None
        depth = self.depth.get(cam, {}).get(frame.seq)
        if depth is not None and depth.depth.shape == frame.labels.shape:
            cloud = labelled_cloud(
                depth.depth, frame.labels, depth.intrinsics, depth.mount, self.stride
            )
        for sink in self.sinks:
            sink.labels(cam, frame, cloud)
        if cloud is not None:
            self._first(f"{cam[0]}/{cam[1]}/points")


def open_rerun(args: argparse.Namespace):
    """A RecordingStream sending to the chosen Rerun sink, or None when Rerun is not wanted."""
    import rerun as rr

    if not (args.save or args.web or args.spawn or not args.foxglove):
        return None
    rec = rr.RecordingStream("topseg")
    if args.save:
        try:
            rec.save(args.save)
        except Exception as exc:
            raise TopsegError(f"cannot write {args.save}: {exc}") from None
    elif args.web:
        try:
            uri = rec.serve_grpc(grpc_port=args.grpc_port)
            rr.serve_web_viewer(web_port=args.web_port, open_browser=False, connect_to=uri)
        except Exception as exc:
            raise TopsegError(
                f"cannot serve Rerun's web viewer on ports {args.web_port} and "
                f"{args.grpc_port}: {exc}"
            ) from None
        page = f"http://localhost:{args.web_port}/?url={urllib.parse.quote(uri, safe=':/')}"
        log.info("Rerun web viewer: %s", page)
    else:
        try:
            rec.spawn()
        except Exception as exc:
            raise TopsegError(
                f"cannot spawn the Rerun viewer ({exc}); try --web or --save"
            ) from None
    return rec


def run(args: argparse.Namespace) -> int:
    """Show what flows until SIGTERM/SIGINT or --duration; bad options fail first (exit 2)."""
    if args.stride < 1:
        raise TopsegError(f"--stride must be >= 1, got {args.stride}")
    if args.duration is not None and args.duration <= 0:
        raise TopsegError(f"--duration must be > 0, got {args.duration}")
    for name, lowest in (("web_port", 1), ("grpc_port", 1), ("foxglove_port", 0)):
        port = getattr(args, name)
        if not lowest <= port <= 65535:
            option = f"--{name.replace('_', '-')}"
            raise TopsegError(f"{option} must be a port {lowest}-65535, got {port}")
    cell = safety_view.load_cell_view(args.cell)  # a bad cell file: one line, exit 2
    if args.nice:
        os.nice(args.nice)  # before Rerun starts its threads (and a spawned viewer)
    svc = ServiceLifecycle("viewer", args)
    sinks: list = []
    inbox = Inbox(QUEUE_SIZE)

    rec = open_rerun(args)  # a sink that cannot open fails before Zenoh does (exit 2)
    if rec is not None:
        sinks.append(RerunSink(rec, cell))
        svc.defer(sinks[-1].close)  # the .rrd is complete on SIGTERM too
    if args.foxglove:
        sinks.append(FoxgloveSink.start(args.foxglove_host, args.foxglove_port, cell))
        svc.defer(sinks[-1].close)
    viewer = Viewer(sinks, args.stride, cell)
    rerun = args.save or ("the web viewer" if args.web else "the Rerun viewer")
    sink_names = ([rerun] if rec is not None else []) + (["Foxglove"] if args.foxglove else [])
    where = " and ".join(sink_names)

    def status_text() -> str:
        n = len(viewer.cameras)
        return (
            f"logging {n} camera(s) to {where}; {viewer.rejected} rejected, {inbox.dropped} dropped"
        )

    with svc:
        keys = [f"topseg/*/*/{kind}" for kind in ("depth", "labels", "stats")]
        keys.append(f"topseg/*/{safety_wire.SAFETY}")
        if viewer.joints_key is not None:
            keys.append(viewer.joints_key)
        for key in keys:
            svc.declare(svc.session.declare_subscriber(key, inbox.on_sample))
        svc.on_stop(inbox.wake)
        log.info("viewer ready")
        svc.ready(status=status_text)
        end = None if args.duration is None else time.monotonic() + args.duration
        while not svc.stopping:
            svc.beat()  # watchdog ping from the logging loop, STATUS= every few s
            timeout = svc.tick if end is None else min(svc.tick, end - time.monotonic())
            if timeout <= 0:
                break
            item = inbox.get(timeout)
            if item is not None:
                viewer.handle(*item)
    log.info("viewer done (%d rejected, %d dropped while busy)", viewer.rejected, inbox.dropped)
    return 0
