"""The cell's safety service: from its cameras' labelled frames and the robot's joint states
to a state (`clear`, `warning`, `stop`) and a speed scale, published on
`topseg/<cell>/safety` at least every `publish_period_ms` of the cell file (33 ms).

    topseg safety --cell /etc/topseg/cell1.toml

The cell file (`core/safety/cell.py`, `docs/howto/safety.md`) names the cell, its cameras and
where each hangs over the cell, the robot (URDF, base pose, where its joint states come from,
stopping time and distance, speeds), the zones and the standard's parameters. For every
camera in it the service takes the depth (`topseg/<cell>/<camera>/depth`) and the worker's
labels (`.../labels`) and pairs them by `seq`; the robot's joint states come from
`topseg/<cell>/robot/<name>/joints` (msgpack) or ROS 2 `/joint_states` over rmw_zenoh.

Every depth frame is decided on as it arrives (`core/safety/monitor.py`) and published: with
the robot posed by a fresh joint state (or in a cell without a robot), the newest labels the
worker sent are carried onto it (`core/safety/carry.py`: what appeared since they were made
is a person of unknown part), so the decision waits for no worker; when a frame's own labels
come while it is still the newest, it is decided on again with them, unless the camera's next
frame is due before that decision would be done (that frame is decided on with these labels
carried onto it; deciding twice only delays it). Without a fresh joint
state each labelled frame is decided on as its labels come. Between frames the last decision
is published again, re-decided with the reaction time measured then (depth stamp to now). No
labels from a camera within `deadline_ms` (100 ms), a blinded camera, one that moved, or a
camera that never sent anything gives `stop` with the reason. The robot's joint state may
be missing or stale: then the model's `robot` class stands for the robot.

Messages that do not decode are dropped, counted and logged at most every 10 s; a queue of
`--queue` messages bounds what waits. A monitoring aid, not a certified safety device.
"""

from __future__ import annotations

import argparse
import logging
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numba

from topseg.core.errors import TopsegError
from topseg.core.formats import joint_states as joint_wire
from topseg.core.formats import safety_wire, wire
from topseg.core.formats.rmw_zenoh import topic_key
from topseg.core.formats.wire import WireError
from topseg.core.printable import printable
from topseg.core.safety.cell import CellConfig, load_cell
from topseg.core.safety.coverage import coverage
from topseg.core.safety.monitor import CellDecision, CellMonitor
from topseg.core.safety.robot import CellRobot
from topseg.services.cli.options import positive_int
from topseg.services.runtime import identity, zenoh_session
from topseg.services.runtime.inbox import Inbox
from topseg.services.runtime.lifecycle import ServiceLifecycle

log = logging.getLogger("topseg.safety")

#: Depth frames kept per camera while their labels are on the way (by seq).
PENDING_DEPTH = 8
#: A repeated warning (bad messages, unpaired labels) is logged at most this often (s).
WARN_EVERY_S = 10.0
#: Token changes kept between two turns of the main loop, at most (a flood of tokens costs
#: changes, never memory).
MAX_TOKEN_CHANGES = 1024
#: numba threads of the service's kernels: one. Its frames are small (160 pixels across) and
#: the worker's parallel kernels share the same cores: a second process entering parallel
#: regions stalls them (reaction p50 / p99 over two runs each on the cell recording: 47 / 87
#: and 37 / 79 ms with one thread, 51 / 88 and 59 / 101 ms with two).
THREADS = 1
#: Weight of the newest decision's duration in the running estimate of how long one takes.
DECISION_TIME_WEIGHT = 0.1
#: ROS 2 joint states: the type on the wire.
JOINT_STATE_TYPE = "sensor_msgs/msg/JointState"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The cell file, the queue and Zenoh."""
    parser.add_argument("--cell", required=True, metavar="CELL.toml", help="the cell file")
    parser.add_argument(
        "--ros-domain",
        type=int,
        default=0,
        metavar="N",
        help="the ROS 2 domain of /joint_states when the cell file takes them from ROS 2 "
        "(default: %(default)s)",
    )
    parser.add_argument(
        "--queue",
        type=positive_int,
        default=64,
        metavar="N",
        help="messages waiting to be decided on, at most (default: %(default)s)",
    )
    zenoh_session.add_arguments(parser)


@dataclass(frozen=True)
class Labelled:
    """A camera's newest labels, the depth frame they were made on and when they came."""

    labels: wire.LabelFrame
    depth: wire.DepthFrame
    received_ns: int


class SafetyService:
    """The service's state between messages: the monitor, depth frames waiting for their
    labels, the counts, and the publisher of the decisions."""

    def __init__(self, cell: CellConfig, monitor: CellMonitor, publish, ros_domain: int) -> None:
        self.cell = cell
        self.monitor = monitor
        self.publish_bytes = publish
        self.pending: dict[str, OrderedDict[int, wire.DepthFrame]] = {
            c.name: OrderedDict() for c in cell.cameras
        }
        # per camera: its newest labels, its newest depth frame (and when it came), and the
        # frame last decided on (seq, stamp, whether with its own labels)
        self.labelled: dict[str, Labelled] = {}
        self.newest_depth: dict[str, tuple[wire.DepthFrame, int]] = {}
        self.decided: dict[str, tuple[int, int, bool]] = {}
        # per camera: the stamp step between its last two depth frames (ns); and how long one
        # frame's decision takes (ns, a running mean): together, whether its next frame is due
        # before a second decision on the newest one would be done
        self.frame_step_ns: dict[str, int] = {}
        self.decision_ns = 0.0
        self.seq = 0
        self.last_publish = 0.0
        self.counts = {"decisions": 0, "frames": 0, "carried": 0, "not_again": 0, "skipped": 0,
                       "rejected": 0, "unpaired": 0}  # fmt: skip
        self.max_batch = PENDING_DEPTH * len(cell.cameras) * 4
        self.last_state = ""
        self._warned: dict[str, float] = {}
        self.keys = self._keys(ros_domain)
        # each camera's mount, from the cell file or its first frame, until the view of the
        # space around the robot was said once (`say_coverage`)
        self.mounts = {c.name: c.mount for c in cell.cameras if c.mount is not None}
        self.coverage_said = False
        # cameras whose labels came without a recorded background, said once each
        self.no_background_said: set[str] = set()

    def _keys(self, ros_domain: int) -> dict[str, tuple[str, str]]:
        """Key expression -> (what, camera) for every subscription."""
        keys = {}
        for camera in self.cell.cameras:
            keys[wire.depth_key(self.cell.cell, camera.name)] = ("depth", camera.name)
            keys[wire.labels_key(self.cell.cell, camera.name)] = ("labels", camera.name)
        robot = self.cell.robot
        if robot is not None:
            if robot.joints_source == "ros2":
                keys[topic_key(ros_domain, robot.ros2_topic, JOINT_STATE_TYPE)] = ("ros2", "")
            else:
                keys[joint_wire.joints_key(self.cell.cell, robot.name)] = ("joints", "")
        return keys

    def warn(self, what: str, message: str, *args) -> None:
        """Log `message` at most every WARN_EVERY_S per `what`."""
        now = time.monotonic()
        if now - self._warned.get(what, -WARN_EVERY_S) >= WARN_EVERY_S:
            self._warned[what] = now
            log.warning(message, *args)

    def handle(self, key: str, data: bytes, received_ns: int) -> None:
        """Take one message: keep a depth frame or labels for `decide`, pass joint states on."""
        what, camera = self.keys.get(key, ("", ""))
        try:
            if what == "depth":
                frame = wire.decode_depth(data)
                pending = self.pending[camera]
                pending[frame.seq] = frame
                while len(pending) > PENDING_DEPTH:
                    pending.popitem(last=False)
                before = self.newest_depth.get(camera)
                if before is not None and frame.stamp_ns > before[0].stamp_ns:
                    self.frame_step_ns[camera] = frame.stamp_ns - before[0].stamp_ns
                self.newest_depth[camera] = (frame, received_ns)
            elif what == "labels":
                self._labels(camera, wire.decode_labels(data), received_ns)
            elif what in ("joints", "ros2"):
                decode = joint_wire.decode_joint_state if what == "joints" else (
                    joint_wire.decode_ros2_joint_state)  # fmt: skip
                self.monitor.joint_state(decode(data), received_ns)
        except (WireError, ValueError) as exc:
            self.counts["rejected"] += 1
            self.warn(
                f"rejected {what}", "dropped a message on %s: %s (%d dropped so far)",
                printable(key), printable(exc), self.counts["rejected"],
            )  # fmt: skip

    def decide(self) -> bool:
        """Judge each camera's newest depth frame not judged yet: with its own labels when
        they came, else (`CellMonitor.decides_on_depth`) with the newest labels carried onto
        it; and judge it again once its own labels come. True when any frame was judged."""
        judged = False
        for camera, (depth, received_ns) in self.newest_depth.items():
            pair = self.labelled.get(camera)
            if pair is None:
                continue
            frame_id = (depth.seq, depth.stamp_ns)
            last = self.decided.get(camera)
            own = (pair.depth.seq, pair.depth.stamp_ns) == frame_id
            started = time.perf_counter_ns()
            if own:
                if last == (*frame_id, True):
                    continue
                if last == (*frame_id, False) and self.next_frame_due(camera, received_ns):
                    self.counts["not_again"] += 1
                    self.decided[camera] = (*frame_id, True)
                    continue
                self.monitor.frame(camera, depth, pair.labels, pair.received_ns)
            elif (
                (last is None or last[:2] != frame_id)
                and pair.depth.stamp_ns < depth.stamp_ns
                and self.monitor.decides_on_depth(received_ns)
            ):
                self.monitor.frame(
                    camera, depth, pair.labels, received_ns,
                    labels_depth=pair.depth, labels_received_ns=pair.received_ns,
                )  # fmt: skip
                self.counts["carried"] += 1
            else:
                continue
            took = time.perf_counter_ns() - started
            self.decision_ns += DECISION_TIME_WEIGHT * (took - self.decision_ns)
            self.decided[camera] = (*frame_id, own)
            self.counts["frames"] += 1
            judged = True
        return judged

    def next_frame_due(self, camera: str, received_ns: int) -> bool:
        """Whether `camera`'s next depth frame (its newest came at `received_ns`) is due
        before a decision started now would be done: one stamp step after the newest came."""
        step = self.frame_step_ns.get(camera)
        if step is None:
            return False
        return time.time_ns() + self.decision_ns >= received_ns + step

    def newest(self, first: tuple, inbox: Inbox) -> list[tuple]:
        """`first` and what else waits in `inbox` now, in order, with only the newest labels of
        each camera: a service that fell behind decides on the newest frame, never on a
        backlog (the older labels are counted as skipped)."""
        batch = [first]
        for _ in range(self.max_batch):
            got = inbox.get(0.0)
            if got is None:
                break
            batch.append(got)
        last = {}
        for i, (key, _, _) in enumerate(batch):
            what, camera = self.keys.get(key, ("", ""))
            if what == "labels":
                last[camera] = i
        keep = set(last.values())
        out = []
        for i, item in enumerate(batch):
            what, _ = self.keys.get(item[0], ("", ""))
            if what == "labels" and i not in keep:
                self.counts["skipped"] += 1
                continue
            out.append(item)
        return out

    def _labels(self, camera: str, labels: wire.LabelFrame, received_ns: int) -> None:
        """Pair labels with their depth frame and keep them as the camera's newest."""
        depth = self.pending[camera].pop(labels.seq, None)
        if depth is None:
            self.counts["unpaired"] += 1
            self.warn(
                f"unpaired {camera}", "labels of %s seq %d came without their depth frame "
                "(%d so far): is the worker labelling another driver's frames?",
                camera, labels.seq, self.counts["unpaired"],
            )  # fmt: skip
            return
        if labels.labels.shape != depth.depth.shape:
            raise ValueError(
                f"labels of {camera} seq {labels.seq} are {labels.labels.shape}, their depth "
                f"frame {depth.depth.shape}"
            )
        self.labelled[camera] = Labelled(labels, depth, received_ns)
        if labels.background is None and camera not in self.no_background_said:
            self.no_background_said.add(camera)
            log.warning(
                "%s: its labels are made without a recorded static background, so a table "
                "with parts on it can read as a person beside the robot: record one "
                "(topseg calibrate --background) and give it to the camera's worker", camera,
            )  # fmt: skip
        if not self.coverage_said and depth.mount is not None:
            self.mounts.setdefault(camera, depth.mount)
            self.say_coverage()

    def say_coverage(self) -> None:
        """Once every camera's mount is known: log how much of the space around the robot
        the cameras see (`core.safety.coverage`), a warning when not all of it."""
        if self.coverage_said or self.monitor.robot is None:
            return
        if any(c.name not in self.mounts for c in self.cell.cameras):
            return
        self.coverage_said = True
        seen = coverage(self.cell, self.monitor.robot.model.reach_m, self.mounts)
        (log.info if seen.worst() >= 1.0 else log.warning)("%s", seen.sentence())

    def publish(self, now_ns: int) -> CellDecision:
        """Decide now and publish the state."""
        decided = self.monitor.decision(now_ns)
        d = decided.decision
        nearest = decided.nearest
        pair = None
        if nearest is not None:
            pair = (tuple(map(float, nearest.point_m)), tuple(map(float, nearest.link_point_m)))
        state = safety_wire.SafetyState(
            seq=self.seq,
            stamp_ns=now_ns,
            state=d.state,
            speed_scale=float(d.speed_scale) if d.state != "stop" else 0.0,
            min_distance_m=None if nearest is None else float(nearest.distance_m),
            part=d.part,
            link=d.link[:256],
            reaction_ms=decided.reaction_ms,
            reasons=tuple(safety_wire.cut_reason(r) for r in d.reasons[: safety_wire.MAX_REASONS]),
            zones=decided.zones,
            nearest_m=pair,
            frame=decided.frame,
        )
        self.publish_bytes(safety_wire.encode_safety(state))
        self.seq += 1
        self.counts["decisions"] += 1
        self.last_publish = time.monotonic()
        if d.state != self.last_state:
            log.info("%s: %s%s", d.state, "; ".join(d.reasons[:3]), "" if d.reasons else "-")
            self.last_state = d.state
        return decided

    def status(self) -> str:
        """One line for systemd and the log."""
        c = self.counts
        return (
            f"cell {self.cell.cell}: {self.last_state or 'starting'}, {c['frames']} frames "
            f"({c['carried']} before their labels, {c['not_again']} not again with them: the "
            f"next was due), {c['decisions']} decisions, "
            f"{c['skipped']} skipped (behind), {c['rejected']} rejected, {c['unpaired']} unpaired, "
            f"{self.monitor.counts['joint_states']} joint states"
        )


class TokenWatch:
    """The liveliness tokens of the cell's drivers and workers, handed from Zenoh's threads to
    the main loop (`take`); a change wakes the loop, so a killed driver stops the cell at once."""

    def __init__(self, wake) -> None:
        self._lock = threading.Lock()
        self._changes: list[tuple[str, str, str, bool]] = []
        self._wake = wake

    def on_sample(self, sample) -> None:
        """A liveliness subscriber's callback: note the token's camera, role and instance."""
        try:
            parts = wire.parse_key(str(sample.key_expr))
        except WireError:
            return
        if parts.kind != "alive" or parts.role is None:
            return
        present = not str(sample.kind).endswith("DELETE")
        with self._lock:
            if len(self._changes) < MAX_TOKEN_CHANGES:
                self._changes.append((parts.camera, parts.role, parts.instance or "?", present))
        self._wake()

    def take(self, monitor: CellMonitor) -> bool:
        """Give the changes since the last call to `monitor`; True when there were any."""
        with self._lock:
            changes, self._changes = self._changes, []
        for camera, role, instance, present in changes:
            monitor.token(camera, role, instance, present)
            if not present:
                log.warning("%s's %s %s went away", camera, role, instance)
        return bool(changes)


def load(args: argparse.Namespace) -> tuple[CellConfig, CellRobot | None]:
    """The cell file and its robot, before Zenoh: a bad file is one line and exit 2."""
    cell = load_cell(args.cell)
    robot = None
    if cell.robot is not None:
        robot = CellRobot(cell.robot, Path(args.cell).resolve().parent)
    return cell, robot


def run(args: argparse.Namespace) -> int:
    """Publish the cell's state until SIGTERM/SIGINT."""
    cell, robot = load(args)
    if not cell.cameras:
        raise TopsegError(f"cell file {args.cell}: no [[camera]]: the service has nothing to watch")
    monitor = CellMonitor(cell, robot)
    numba.set_num_threads(min(THREADS, numba.config.NUMBA_NUM_THREADS))
    t0 = time.monotonic()
    monitor.warm_up()
    log.info("kernels ready in %.1f s", time.monotonic() - t0)
    svc = ServiceLifecycle("safety", args)
    inbox = Inbox(args.queue, stamp=True)
    period_s = cell.publish_period_ms / 1000.0
    with svc:
        session = svc.session
        me = identity.Identity.of(session)
        publisher = svc.declare(session.declare_publisher(safety_wire.safety_key(cell.cell)))
        service = SafetyService(cell, monitor, publisher.put, args.ros_domain)
        service.say_coverage()  # now when the cell file gives every camera's mount
        for key in service.keys:
            svc.declare(session.declare_subscriber(key, inbox.on_sample))
        svc.declare(
            session.liveliness().declare_token(safety_wire.safety_alive_key(cell.cell, me.instance))
        )
        tokens = TokenWatch(inbox.wake)
        for camera in cell.cameras:
            key = f"{wire.camera_prefix(cell.cell, camera.name)}/alive/**"
            svc.declare(
                session.liveliness().declare_subscriber(key, tokens.on_sample, history=True)
            )
        svc.on_stop(inbox.wake)
        log.info(
            "deciding for cell %s from %s%s; publishing on %s",
            cell.cell,
            ", ".join(c.name for c in cell.cameras),
            f" and robot {cell.robot.name}'s joints ({cell.robot.joints_source})"
            if cell.robot
            else "",
            safety_wire.safety_key(cell.cell),
        )
        service.publish(time.time_ns())  # `stop`: no frame yet
        svc.ready(status=service.status)
        log.info("safety ready: %s", service.status())
        while not svc.stopping:
            svc.beat()
            wait = period_s - (time.monotonic() - service.last_publish)
            item = inbox.get(max(0.0, wait))
            decided = tokens.take(monitor)
            if item is not None:
                for key, data, received_ns in service.newest(item, inbox):
                    service.handle(key, data, received_ns)
                decided = service.decide() or decided
            if decided or time.monotonic() - service.last_publish >= period_s:
                service.publish(time.time_ns())
    log.info("stopped: %s (%d dropped while the queue was full)", service.status(), inbox.dropped)
    return 0
