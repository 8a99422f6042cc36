"""Publish topseg's cameras to ROS 2 over rmw_zenoh (`topseg bridge ros2`), as a node
`/topseg_bridge`: `/topseg/<cell>/<camera>/depth`, `.../labels`, `.../camera_info`, and the
cameras' mounts on `/tf_static`. Needs a Zenoh router that both sides reach; no ROS install.

For every camera seen on `topseg/<cell>/<camera>/{depth,labels}` (or the `--cameras` given)
it publishes, as a ROS 2 node `/topseg_bridge` would under `rmw_zenoh_cpp`:

- `/topseg/<cell>/<camera>/depth`: `sensor_msgs/msg/Image`, `16UC1` millimetres (0 = none);
- `/topseg/<cell>/<camera>/labels`: `sensor_msgs/msg/Image`, `mono8` label ids;
- `/topseg/<cell>/<camera>/camera_info`: `sensor_msgs/msg/CameraInfo`, with every depth frame;
- `/tf_static`: `tf2_msgs/msg/TFMessage`, `<cell>_<camera>_floor` -> `<cell>_<camera>_optical_frame` for every
  camera whose frames carry a mount, kept for late joiners (transient local, depth 1).

For every cell seen on `topseg/<cell>/safety` (the safety service's state):

- `/topseg/<cell>/safety/state`: `std_msgs/msg/String`, `clear`, `warning` or `stop`;
- `/topseg/<cell>/safety/speed_scale`: `std_msgs/msg/Float64`, 0..1;
- with `--cell CELL.toml` naming that cell, `/topseg/<cell>/safety/markers`:
  `visualization_msgs/msg/MarkerArray` in `<cell>_floor` (the cell file's frame), the zones
  and the nearest pair coloured by state (`safety_view.safety_markers`), and `/tf_static`
  gains `<cell>_floor` -> `<cell>_<camera>_floor` for every camera of the file.

A cell heard of that sends no valid state for `--safety-timeout` seconds is published as
`stop` with speed scale 0 (every timeout, until states come again).

Images carry the topseg frame's stamp and `<cell>_<camera>_optical_frame`. The bytes are
`core/formats/ros2_messages.py`'s CDR (the same as in recordings); keys, liveliness tokens,
GIDs and attachments are `core/formats/rmw_zenoh.py`'s. Each topic is a Zenoh
AdvancedPublisher declared as rmw_zenoh declares one for its QoS (`rmw_publisher_data.cpp`):
reliable with congestion control DROP, and for `/tf_static` a cache of its last message,
publisher detection and sporadic heartbeats, so that a transient-local reader that joins
later still gets the mounts. The node and each publisher hold the liveliness tokens ROS 2
graph tools (`ros2 topic list`, `ros2 node list`) discover.

Zenoh callbacks only queue the messages; the main thread decodes, converts and publishes.
A queue longer than `--queue` drops new messages (counted). Messages that do not decode are
dropped, counted and logged (rate-limited); they never stop the bridge. Without `--cameras`
at most `--max-cameras` cameras are served; further names, and names ROS 2 cannot spell
(a digit first, `.` or `-`), are ignored and counted. A camera seen without `--cameras` that
sent nothing for `--forget-after` seconds leaves the ROS graph (its publishers' tokens go,
its mount leaves `/tf_static`) and frees its place. Under systemd it says READY=1 once
subscribed and pings the watchdog; SIGTERM/SIGINT stop it cleanly.
"""

from __future__ import annotations

import argparse
import logging
import os
import time
from typing import Any

import zenoh
from zenoh import ext

from topseg.core.camera import axis_depth
from topseg.core.errors import TopsegError
from topseg.core.formats import rmw_zenoh as rz
from topseg.core.formats import ros2_messages as ros2
from topseg.core.formats import safety_wire, wire
from topseg.core.printable import printable
from topseg.core.safety.cell import CellConfig, load_cell
from topseg.services.cli.options import finite, int_range, parse_camera
from topseg.services.live import safety_view
from topseg.services.runtime import zenoh_session
from topseg.services.runtime.inbox import Inbox
from topseg.services.runtime.lifecycle import ServiceLifecycle

log = logging.getLogger("topseg.bridge")

NODE_NAME = "topseg_bridge"
DOMAIN_ENV = "ROS_DOMAIN_ID"
#: the largest ROS_DOMAIN_ID ROS 2 documents
MAX_DOMAIN = 232
#: Period (s) of the sporadic heartbeat of a reliable transient-local publisher (rmw_zenoh's
#: SAMPLE_MISS_DETECTION_HEARTBEAT_PERIOD, 500 ms)
HEARTBEAT_S = 0.5
#: A camera's ROS 2 topics: /topseg/<cell>/<camera>/<stream> and their message types
CAMERA_STREAMS = {
    "depth": "sensor_msgs/msg/Image",
    "labels": "sensor_msgs/msg/Image",
    "camera_info": "sensor_msgs/msg/CameraInfo",
}
#: Distinct refused camera names remembered (beyond it, messages still count)
MAX_REFUSED_NAMES = 4096
#: A cell's safety topics: /topseg/<cell>/safety/<stream> and their message types; markers
#: only for the cell of --cell
SAFETY_STREAMS = {
    "state": ros2.STRING,
    "speed_scale": ros2.FLOAT64,
    "markers": ros2.MARKER_ARRAY,
}
#: At most one "ignoring" warning this often (s)
WARN_EVERY_S = 10.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The bridge's options: the target, the ROS domain, the cameras, the queue and Zenoh."""
    parser.add_argument("target", choices=("ros2",), help="what to bridge to: ros2 (rmw_zenoh)")
    parser.add_argument(
        "--domain",
        type=int_range(0, MAX_DOMAIN),
        metavar="N",
        help=f"ROS 2 domain id (default ${DOMAIN_ENV}, else 0)",
    )
    parser.add_argument(
        "--cameras",
        nargs="+",
        metavar="CELL/CAMERA",
        help="bridge only these cameras (default: every camera seen on topseg/*/*/depth|labels)",
    )
    parser.add_argument(
        "--max-cameras",
        type=int_range(1, 100000),
        default=32,
        metavar="N",
        help="without --cameras, bridge at most this many cameras; names beyond it are "
        "ignored and counted (default: %(default)s)",
    )
    parser.add_argument(
        "--forget-after",
        type=finite(0, 1e9),
        default=60.0,
        metavar="S",
        help="without --cameras, release a camera that sent nothing for this long: its topics "
        "leave the ROS graph; 0 = never (default: %(default)s s)",
    )
    parser.add_argument(
        "--cell",
        metavar="CELL.toml",
        help="a cell file: also publish its zones and nearest pair as markers in the "
        "<cell>_floor frame, and where its cameras hang on /tf_static (default: each "
        "cell's safety state and speed scale only)",
    )
    parser.add_argument(
        "--safety-timeout",
        type=finite(0.001, 1e6),
        default=0.5,
        metavar="S",
        help="a cell whose safety state was heard of and then sent no valid state for this "
        "long is published as stop with speed scale 0 (default: %(default)s s)",
    )
    parser.add_argument(
        "--queue",
        type=int_range(1, 100000),
        default=16,
        metavar="N",
        help="messages waiting to be converted, at most; newer ones are dropped and counted "
        "(default: %(default)s)",
    )
    zenoh_session.add_arguments(parser)


def ros_domain(value: int | None) -> int:
    """The domain: --domain, else $ROS_DOMAIN_ID, else 0; TopsegError for a bad variable."""
    if value is not None:
        return value
    text = os.environ.get(DOMAIN_ENV, "").strip()
    if not text:
        return 0
    if not text.isdigit() or int(text) > MAX_DOMAIN:
        raise TopsegError(f"${DOMAIN_ENV}={text!r} is not a ROS 2 domain id (0..{MAX_DOMAIN})")
    return int(text)


class Ros2Publisher:
    """One ROS 2 publisher on rmw_zenoh: its Zenoh publisher, liveliness token, GID and
    sequence numbers."""

    def __init__(self, session: Any, node, entity_id: int, topic: str, typename: str, qos) -> None:
        self.topic = topic
        self.key = rz.topic_key(node.domain, topic, typename)
        self.token_key = node.publisher_token(entity_id, topic, typename, qos)
        self.gid = rz.entity_gid(self.token_key)
        self.sequence_number = 0
        self.publisher = declare_publisher(session, self.key, qos)
        self.token = session.liveliness().declare_token(self.token_key)

    def put(self, payload: bytes) -> None:
        """Publish one CDR message with rmw_zenoh's attachment (sequence numbers from 1)."""
        self.sequence_number += 1
        meta = rz.attachment(self.sequence_number, time.time_ns(), self.gid)
        self.publisher.put(payload, attachment=meta)

    def undeclare(self) -> None:
        """Leave the ROS graph (token first), then drop the publisher."""
        self.token.undeclare()
        self.publisher.undeclare()


def declare_publisher(session: Any, key: str, qos) -> Any:
    """A Zenoh AdvancedPublisher with the options rmw_zenoh gives a publisher of this QoS."""
    reliable = qos.reliability == rz.RELIABLE
    options: dict[str, Any] = {
        "reliability": zenoh.Reliability.RELIABLE if reliable else zenoh.Reliability.BEST_EFFORT,
        "congestion_control": zenoh.CongestionControl.BLOCK
        if reliable and qos.history == rz.KEEP_ALL
        else zenoh.CongestionControl.DROP,
    }
    if qos.durability == rz.TRANSIENT_LOCAL:
        options["publisher_detection"] = True
        options["cache"] = ext.CacheConfig(qos.depth)
        if reliable:
            options["sample_miss_detection"] = ext.MissDetectionConfig(
                sporadic_heartbeat=HEARTBEAT_S
            )
    return ext.declare_advanced_publisher(session, key, **options)


class Bridge:
    """The ROS 2 node `/topseg_bridge`: converts topseg messages and publishes them."""

    def __init__(
        self,
        session: Any,
        domain: int,
        max_cameras: int,
        wanted=None,
        forget_after: float = 0.0,
        cell: CellConfig | None = None,
        safety_timeout: float = 0.5,
    ) -> None:

        self.session, self.max_cameras = session, max_cameras
        self.cell, self.safety_timeout = cell, safety_timeout
        self.safety: dict[str, dict[str, Ros2Publisher]] = {}  # cell -> its safety topics
        self.safety_heard: dict[str, float] = {}  # cell -> monotonic s of its last valid state
        self.stale: set[str] = set()
        self.forget_after = forget_after
        self.last_seen: dict[tuple[str, str], float] = {}  # monotonic s of the last message
        self.next_sweep = 0.0
        self.forgotten = 0
        self.wanted: set[tuple[str, str]] | None = wanted
        self.node = rz.Node(domain, str(session.info.zid()), 0, NODE_NAME)
        self.node_token = session.liveliness().declare_token(self.node.token())
        self.next_entity_id = 1
        self.cameras: dict[tuple[str, str], dict[str, Ros2Publisher]] = {}
        self.mounts: dict[tuple[str, str], Any] = {}  # (cell, camera) -> its TopViewMount
        self.tf_static: Ros2Publisher | None = None
        self.refused: set[tuple[str, str]] = set()
        self.published = self.rejected = self.ignored = 0
        self._last_warning: dict[str, float] = {}

    def _publisher(self, topic: str, typename: str, qos) -> Ros2Publisher:
        entity_id, self.next_entity_id = self.next_entity_id, self.next_entity_id + 1
        return Ros2Publisher(self.session, self.node, entity_id, topic, typename, qos)

    def _warn(self, what: str, message: str, *args: Any) -> None:
        """Log a warning of kind `what` at most every WARN_EVERY_S seconds."""
        now = time.monotonic()
        if now - self._last_warning.get(what, -WARN_EVERY_S) >= WARN_EVERY_S:
            self._last_warning[what] = now
            log.warning(message, *args)

    def topics(self, cell: str, camera: str) -> dict[str, Ros2Publisher] | None:
        """The camera's publishers by stream, declared on its first message; None for a camera
        that is not bridged (not in --cameras, over --max-cameras, or a name ROS 2 refuses)."""
        name = (cell, camera)
        found = self.cameras.get(name)
        if found is not None:
            return found
        if self.wanted is not None and name not in self.wanted:
            return None
        if name in self.refused:
            self.ignored += 1
            return None
        if self.wanted is None and len(self.cameras) >= self.max_cameras:
            return self._refuse(
                name, "limit", f"camera limit reached (--max-cameras {self.max_cameras})"
            )
        try:
            rz.check_topic_name(ros2.ros2_topic(cell, camera, "depth"))
        except rz.Ros2NameError as exc:
            return self._refuse(name, "name", str(exc))
        found = {
            stream: self._publisher(ros2.ros2_topic(cell, camera, stream), typename, rz.DEFAULT_QOS)
            for stream, typename in CAMERA_STREAMS.items()
        }
        self.cameras[name] = found
        log.info(
            "publishing %s on ROS 2 domain %d",
            ", ".join(p.topic for p in found.values()),
            self.node.domain,
        )
        return found

    def _refuse(self, name: tuple[str, str], why: str, reason: str) -> None:
        """Count a camera that is not bridged; warn (per `why`, rate-limited) and remember it."""
        self.ignored += 1
        if len(self.refused) < MAX_REFUSED_NAMES:
            self.refused.add(name)
        self._warn(
            why, "ignoring camera %s/%s: %s (%d messages ignored)", *name, reason, self.ignored
        )
        return None

    def placements(self) -> dict[tuple[str, str], tuple[Any, float]]:
        """Where the cell file hangs its cameras: {(cell, camera): (offset, yaw_deg)}."""
        if self.cell is None:
            return {}
        return {(self.cell.cell, c.name): (c.offset(), c.yaw_deg) for c in self.cell.cameras}

    def safety_topics(self, cell: str) -> dict[str, Ros2Publisher] | None:
        """A cell's safety publishers, declared on its first state; None for a cell that is
        not bridged (not among --cameras' cells, over --max-cameras cells, or a name ROS 2
        refuses)."""
        found = self.safety.get(cell)
        if found is not None:
            return found
        name = (cell, "safety")
        if self.wanted is not None and cell not in {c for c, _ in self.wanted}:
            return None
        if name in self.refused:
            self.ignored += 1
            return None
        if len(self.safety) >= self.max_cameras:
            return self._refuse(name, "limit", f"cell limit reached ({self.max_cameras})")
        try:
            rz.check_topic_name(ros2.safety_topic(cell, "speed_scale"))
        except rz.Ros2NameError as exc:
            return self._refuse(name, "name", str(exc))
        streams = dict(SAFETY_STREAMS)
        if self.cell is None or self.cell.cell != cell:
            del streams["markers"]
        found = {
            stream: self._publisher(ros2.safety_topic(cell, stream), typename, rz.DEFAULT_QOS)
            for stream, typename in streams.items()
        }
        self.safety[cell] = found
        log.info("publishing %s", ", ".join(p.topic for p in found.values()))
        return found

    def handle_safety(self, key: str, cell: str, payload: bytes) -> None:
        """A cell's safety state: its state, speed scale and (with its cell file) markers."""
        try:
            state = safety_wire.decode_safety(payload)
        except wire.WireError as exc:
            self.rejected += 1
            self._warn(
                "rejected", "%s: %s (%d rejected)", printable(key), printable(exc), self.rejected
            )
            return
        topics = self.safety_topics(cell)
        if topics is None:
            return
        self.safety_heard[cell] = time.monotonic()
        if cell in self.stale:
            self.stale.discard(cell)
            log.info("cell %s: safety states again", cell)
        topics["state"].put(ros2.string_message(state.state))
        topics["speed_scale"].put(ros2.float64_message(state.speed_scale))
        self.published += 2
        if "markers" in topics:
            markers = safety_view.safety_markers(self.cell.zones, state)
            topics["markers"].put(
                ros2.marker_array_message(markers, state.stamp_ns, ros2.cell_floor_frame(cell))
            )
            self.published += 1

    def stop_stale(self) -> None:
        """Publish stop and speed scale 0 for every cell whose states stopped coming (no
        valid one for --safety-timeout): a reader never keeps a clear that is no longer
        being said; repeated every --safety-timeout until states come again."""
        now = time.monotonic()
        for cell, heard in self.safety_heard.items():
            if now - heard < self.safety_timeout:
                continue
            if cell not in self.stale:
                self.stale.add(cell)
                log.warning(
                    "cell %s: no valid safety state for %.1f s: publishing stop",
                    cell, self.safety_timeout,
                )  # fmt: skip
            topics = self.safety[cell]
            topics["state"].put(ros2.string_message("stop"))
            topics["speed_scale"].put(ros2.float64_message(0.0))
            self.published += 2
            self.safety_heard[cell] = now  # again after another timeout

    def handle(self, key: str, payload: bytes) -> None:
        """Decode one topseg message by its key and publish its ROS 2 messages."""
        chunks = key.split("/")
        if len(chunks) == 3 and chunks[0] == wire.ROOT and chunks[2] == safety_wire.SAFETY:
            self.handle_safety(key, chunks[1], payload)
            return
        try:
            parts = wire.parse_key(key)
            if parts.kind == "depth":
                message = wire.decode_depth(payload)
            elif parts.kind == "labels":
                message = wire.decode_labels(payload)
            else:
                raise wire.WireError(f"{key!r} carries nothing the bridge publishes")
        except wire.WireError as exc:
            self.rejected += 1
            self._warn(
                "rejected", "%s: %s (%d rejected)", printable(key), printable(exc), self.rejected
            )
            return
        topics = self.topics(parts.cell, parts.camera)
        if topics is None:
            return
        cam = (parts.cell, parts.camera)
        self.last_seen[cam] = time.monotonic()
        if parts.kind == "depth":
            self.publish_depth(cam, topics, message)
        else:
            self.publish_labels(cam, topics, message)

    def publish_depth(self, cam: tuple[str, str], topics: dict[str, Ros2Publisher], frame) -> None:
        """The depth image, its camera info, and /tf_static when the mount is new."""
        frame_id = ros2.optical_frame(*cam)
        depth = axis_depth(frame.depth, frame.mount)  # REP 118: z, also from a range camera
        topics["depth"].put(ros2.image_message(depth, frame.stamp_ns, frame_id))
        info = ros2.camera_info_message(frame.intrinsics, frame.stamp_ns, frame_id)
        topics["camera_info"].put(info)
        self.published += 2
        if frame.mount is not None and self.mounts.get(cam) != frame.mount:
            self.mounts[cam] = frame.mount
            self.publish_mounts(frame.stamp_ns)

    def publish_labels(self, cam: tuple[str, str], topics: dict[str, Ros2Publisher], frame) -> None:
        """The label image (mono8), stamped like the depth frame it came from."""
        topics["labels"].put(
            ros2.image_message(frame.labels, frame.stamp_ns, ros2.optical_frame(*cam))
        )
        self.published += 1

    def publish_mounts(self, stamp_ns: int) -> None:
        """Every known mount in one /tf_static message (its publisher keeps the last one)."""
        if self.tf_static is None:
            self.tf_static = self._publisher("/tf_static", ros2.TF_MESSAGE, rz.STATIC_TF_QOS)
        self.tf_static.put(ros2.mount_transforms_message(self.mounts, stamp_ns, self.placements()))
        self.published += 1
        frames = ", ".join(
            [ros2.floor_frame(*cam) for cam in self.placements()]
            + [ros2.optical_frame(*cam) for cam in self.mounts]
        )
        log.info("published /tf_static: %s", frames)

    def forget_idle(self) -> None:
        """Release the cameras seen without --cameras that sent nothing for --forget-after
        seconds (checked a few times a second at most): their publishers leave the ROS graph,
        their mounts leave /tf_static, their places under --max-cameras are free again."""
        now = time.monotonic()
        if self.wanted is not None or not self.forget_after > 0 or now < self.next_sweep:
            return
        self.next_sweep = now + min(1.0, self.forget_after / 4)
        idle = [c for c in self.cameras if now - self.last_seen.get(c, now) > self.forget_after]
        for cam in idle:
            for pub in self.cameras.pop(cam).values():
                pub.undeclare()
            self.last_seen.pop(cam, None)
            self.forgotten += 1
            log.info("released %s/%s: nothing for %.0f s", *cam, self.forget_after)
            if self.mounts.pop(cam, None) is not None:  # late joiners get the rest only
                self.publish_mounts(time.time_ns())

    def close(self) -> None:
        """Leave the ROS graph: every publisher, then the node."""
        for topics in self.cameras.values():
            for pub in topics.values():
                pub.undeclare()
        for topics in self.safety.values():
            for pub in topics.values():
                pub.undeclare()
        if self.tf_static is not None:
            self.tf_static.undeclare()
        self.node_token.undeclare()


def wanted_cameras(entries: list[str] | None) -> set[tuple[str, str]] | None:
    """The --cameras entries as (cell, camera), each one ROS 2 can name; None for all."""
    if not entries:
        return None
    wanted = set()
    for entry in entries:
        cell, camera = parse_camera(entry)
        try:
            rz.check_topic_name(ros2.ros2_topic(cell, camera, "depth"))
        except rz.Ros2NameError as exc:
            raise TopsegError(f"--cameras entry {entry!r}: {exc}") from None
        wanted.add((cell, camera))
    return wanted


def run(args: argparse.Namespace) -> int:
    """Bridge until SIGTERM/SIGINT; bad options or Zenoh config fail first (exit 2)."""
    domain = ros_domain(args.domain)
    wanted = wanted_cameras(args.cameras)
    cell = None if args.cell is None else load_cell(args.cell)  # bad file: one line, exit 2
    svc = ServiceLifecycle("bridge", args)
    inbox = Inbox(args.queue)

    if wanted is None:
        keys = ["topseg/*/*/depth", "topseg/*/*/labels", f"topseg/*/{safety_wire.SAFETY}"]
    else:
        keys = [k for c in sorted(wanted) for k in (wire.depth_key(*c), wire.labels_key(*c))]
        keys += [safety_wire.safety_key(c) for c in sorted({c for c, _ in wanted})]

    with svc:
        bridge = Bridge(
            svc.session, domain, args.max_cameras, wanted, args.forget_after, cell,
            args.safety_timeout,
        )  # fmt: skip
        if cell is not None:
            bridge.publish_mounts(time.time_ns())  # where the cell's cameras hang
        svc.defer(bridge.close)
        for key in keys:
            svc.declare(svc.session.declare_subscriber(key, inbox.on_sample))
        svc.on_stop(inbox.wake)

        def status() -> str:
            return (
                f"bridging {len(bridge.cameras)} camera(s) to ROS 2 domain {domain}: "
                f"{bridge.published} messages, {bridge.rejected} rejected, {inbox.dropped} dropped, "
                f"{bridge.ignored} ignored, {bridge.forgotten} released"
            )

        log.info(
            "bridge ready: node /%s on ROS 2 domain %d (zid %s)", NODE_NAME, domain, bridge.node.zid
        )
        svc.ready(status=status)
        while not svc.stopping:
            svc.beat()
            wait = svc.tick if not bridge.safety else min(svc.tick, args.safety_timeout / 4)
            item = inbox.get(wait)
            if item is not None:
                bridge.handle(*item)
            bridge.stop_stale()
            bridge.forget_idle()
        log.info("bridge done: %s", status())
    return 0
