"""Publish one camera's depth frames on Zenoh (`topseg/<cell>/<camera>/depth`) from a
source: a Kinect v1 (`freenect`), an OpenNI2 device, an OAK-D (`oak`), a recording or a PNG
folder (`replay:PATH`) or rendered scenes (`synthetic`). `--mount FILE` sends the camera's
mount with every frame. A sensor that drops out is reopened with backoff; a second driver
for a camera that already has one refuses to start.

Reads frames from a source (`replay:PATH`, `freenect[:index]`, `openni2[:uri]`,
`oak[:device-id]`, `synthetic`) and publishes them as wire messages on
`topseg/<cell>/<camera>/depth`, with ground truth on `.../truth` when the source has it.
A replay also publishes the recording's joint states and safety truth with the depth frame
they follow (`topseg/<cell>/robot/<name>/joints`, `topseg/<cell>/safety/separation`, moved to
`--cell`), restamped like the frame: as far from its new stamp as they were recorded, the
safety truth's `seq` the frame's, so a safety service downstream sees a consistent robot.
It holds the liveliness token `.../alive/driver/<instance>` while running (its Zenoh id,
`services/runtime/identity.py`; also the attachment of every message it publishes) and answers
`.../info` queries with JSON (source, camera intrinsics, mount, fps, frames published,
reconnects, instance, pid and host).

One camera, one driver (`OneDriverPerCamera`): a driver that finds another live driver of
its cell/camera (a token whose process answers `info`) refuses to start (one line, exit 2),
since their frames would interleave on one key; two started at once, each too early to see
the other, find each other later and the younger one stops the same way. A crashed driver's
token goes with its connection, so a restart is not refused; a token whose process does not
answer (a host gone, until Zenoh's lease ends) is only warned about. The worker and
`topseg status` report two drivers on one key too.

`--mount FILE` (a mount file from `topseg calibrate`) puts the camera's mount on every
depth message and in `info`. Before the driver joins Zenoh, the file is read and validated
(`camera.check_mount`) and the source's first frame is read and checked against it: its
size must be the mount's, and its depth must show the floor where the mount puts it
(`core.calibration.check_floor`); when not, one line and exit 2. A source not there yet is
checked at its first frame the same way. Without it, a mount the source knows (a recording made with one) is passed on, and
the worker estimates one itself from frames that carry none.

When the source fails, drops out or stalls, the driver closes it and opens it again with
exponential backoff, logging each attempt. A finite source (a replay without `--loop`)
ends the driver with status 0; so do SIGTERM and SIGINT, at once, even mid-wait.

Depth (and truth) is published with `express=True` (no batching delay). Congestion
control is DROP for live and real-time sources: measured with `topseg bench transport`
(640x480 frames, 30 fps, loopback), DROP lost no frame to a healthy subscriber, paced or
flat out (~2900 frames/s), while under BLOCK one frozen subscriber held every `put` for
5 s, starving all the others; under DROP the longest `put` was 31 ms. With
`--as-fast-as-possible` it is BLOCK, and the driver waits for a first subscriber, so that
a replay goes exactly as fast as its subscribers take it. `--congestion` overrides either.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import threading
import time

import zenoh

from topseg import __version__
from topseg.core.calibration import check_floor
from topseg.core.errors import TopsegError
from topseg.core.formats import cell_truth, wire
from topseg.core.formats.mount_file import read_mount_file
from topseg.core.formats.wire import DEFAULT_CAMERA, DEFAULT_CELL
from topseg.drivers import Reconnecting, SourceOptions, SourceUnavailable, open_source, parse_spec
from topseg.services.cli.options import finite
from topseg.services.live.driver_drain import LabelsSeen, drain
from topseg.services.runtime import identity, zenoh_session
from topseg.services.runtime.lifecycle import ServiceLifecycle

log = logging.getLogger("topseg.driver")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The driver's options: the source, the camera's names, pacing and Zenoh."""
    parser.add_argument(
        "--source",
        required=True,
        metavar="SPEC",
        help="replay:PATH | freenect[:index] | openni2[:uri] | oak[:device-id] | synthetic",
    )
    parser.add_argument(
        "--cell", default=DEFAULT_CELL, help="work cell name (default: %(default)s)"
    )
    parser.add_argument(
        "--camera", default=DEFAULT_CAMERA, help="camera name (default: %(default)s)"
    )
    parser.add_argument(
        "--mount",
        metavar="FILE",
        help="the camera's mount file from `topseg calibrate`: sent with every frame "
        "(default: none; a recording's own mount is passed on, else the worker estimates one)",
    )
    parser.add_argument(
        "--fps",
        type=finite(0.1, 1000),
        help="replay pace (default: as recorded) or cap for a live sensor",
    )
    parser.add_argument("--loop", action="store_true", help="replay: start again at the end")
    parser.add_argument(
        "--as-fast-as-possible",
        dest="realtime",
        action="store_false",
        help="replay: no pacing, publish as fast as the subscribers take it",
    )
    parser.add_argument(
        "--congestion",
        choices=("auto", "block", "drop"),
        default="auto",
        help="Zenoh congestion control for depth: auto = drop, or block with "
        "--as-fast-as-possible (default: %(default)s)",
    )
    parser.add_argument(
        "--drain-idle",
        type=finite(0.1, 3600),
        default=10.0,
        metavar="S",
        help="with block congestion, a finite source's end waits for the worker to label the "
        "last frame, while labels come at most S s apart (default: %(default)s)",
    )
    parser.add_argument(
        "--frame-timeout",
        type=finite(0.01, 3600),
        default=2.0,
        metavar="S",
        help="a live sensor silent this long is reopened (default: %(default)s s)",
    )
    zenoh_session.add_arguments(parser)


#: the most companion keys (joint states, safety truth) one driver publishes on
MAX_COMPANION_KEYS = 16


class CompanionPublisher:
    """Publishes a replay's companion messages on their keys (moved to the driver's cell),
    restamped like their depth frame; publishers are declared on first use, at most
    MAX_COMPANION_KEYS of them, and messages that cannot be restamped are dropped and
    counted."""

    def __init__(self, session, cell: str, publish: dict, attachment: bytes) -> None:
        self.session, self.cell, self.publish, self.attachment = session, cell, publish, attachment
        self.publishers: dict[str, object] = {}
        self.sent = 0
        self.dropped = 0

    def put(self, companions, stamp_ns: int, seq: int) -> None:
        """Publish the companions of the depth frame stamped `stamp_ns`, numbered `seq`."""
        for c in companions:
            key = cell_truth.in_cell(c.key, self.cell)
            publisher = self.publishers.get(key)
            if publisher is None:
                if len(self.publishers) >= MAX_COMPANION_KEYS:
                    self.dropped += 1
                    continue
                publisher = self.session.declare_publisher(key, **self.publish)
                self.publishers[key] = publisher
            try:
                data = cell_truth.restamped(c.data, stamp_ns + c.offset_ns, seq)
            except wire.WireError as exc:
                self.dropped += 1
                log.warning("a recorded message on %s not published: %s", wire.shown_key(key), exc)
                continue
            publisher.put(data, attachment=self.attachment)
            self.sent += 1

    def undeclare(self) -> None:
        """Undeclare the publishers."""
        for publisher in self.publishers.values():
            publisher.undeclare()


class DriverState:
    """What the `info` queryable reports; updated by the publishing loop."""

    def __init__(self, args: argparse.Namespace, keys: dict[str, str]) -> None:
        self.lock = threading.Lock()
        self.info = {
            "role": "driver",
            "cell": args.cell,
            "camera": args.camera,
            "source": args.source,
            "fps": args.fps,
            "intrinsics": None,
            "mount": None,
            "mount_file": getattr(args, "mount", None),
            "frames": 0,
            "truth_frames": 0,
            "companions": 0,
            "reconnects": 0,
            "last_error": None,
            "started_ns": time.time_ns(),
            "keys": keys,
            "congestion": args.congestion,
            "version": __version__,
            "duplicates": [],
        }

    def update(self, **fields) -> None:
        """Set some fields (from the publishing loop; the queryable reads them)."""
        with self.lock:
            self.info.update(fields)

    def note_duplicate(self, instance: str) -> None:
        """Remember another driver seen serving this camera (shown in `info`)."""
        with self.lock:
            if instance not in self.info["duplicates"]:
                self.info["duplicates"].append(instance)

    def to_json(self) -> bytes:
        """The info reply: all fields as JSON."""
        with self.lock:
            return json.dumps(self.info).encode()


def _wait_for_subscriber(publisher, key: str, svc: ServiceLifecycle) -> None:
    """Block until `publisher` has a subscriber (or a stopping signal), saying so every 5 s."""
    next_note = 0.0
    while not publisher.matching_status.matching and not svc.stopping:
        if time.monotonic() >= next_note:
            log.info("waiting for a subscriber on %s", key)
            next_note = time.monotonic() + 5.0
        svc.wait(0.05)


def read_mount(path: str):
    """The mount in a mount file (`topseg calibrate --out`); ConfigError (one line) when the
    file is missing or is not one."""
    return read_mount_file(path)


def check_mount_fits(mount, intrinsics, path: str) -> None:
    """TopsegError (one line) unless the mount file is for frames of the source's size; a
    warning when the focal lengths differ by more than 1 %."""

    m = mount.intrinsics
    if m.shape != intrinsics.shape:
        raise TopsegError(
            f"mount file {path} is for {m.width}x{m.height} frames but the source sends "
            f"{intrinsics.width}x{intrinsics.height}; calibrate this source "
            "(topseg calibrate --source ...)"
        )
    if abs(m.fx - intrinsics.fx) > 0.01 * intrinsics.fx:
        log.warning(
            "mount file %s was made with focal length %.4g px, the source says %.4g px",
            path,
            m.fx,
            intrinsics.fx,
        )


def check_mount_floor(mount, depth, path: str, source: str) -> bool | None:
    """Whether the mount file's floor agrees with a frame's depth (`check_floor`): True, or
    None when the frame has too little depth to tell; TopsegError (one line) when they
    disagree: the worker would label through a floor that is not there."""
    result = check_floor(depth, mount)
    if result.agrees is False:
        raise TopsegError(
            f"mount file {path} disagrees with the frames of {source}: {result.reason()}; "
            "calibrate this camera again (topseg calibrate --source ...), or start without "
            "--mount and the worker estimates the mount from the frames"
        )
    return result.agrees


class PeekedSource:
    """A source opened before the driver joins Zenoh, whose first frame was read to check
    the mount file against it: the same source, with that frame first."""

    def __init__(self, source, first, rest) -> None:
        self._source, self._first, self._rest = source, first, rest

    def __getattr__(self, name: str):
        return getattr(self._source, name)

    def frames(self):
        """The frame read first, then the source's others."""
        if self._first is not None:
            first, self._first = self._first, None
            yield first
        if self._rest is not None:
            yield from self._rest

    def close(self) -> None:
        """Close the frames and the source (once, however often called)."""
        if self._rest is not None:
            rest, self._rest = self._rest, None
            rest.close()
            self._source.close()


def open_checked(spec, options, mount, path: str):
    """The source opened and its first frame read, before the driver joins Zenoh, with the
    mount file checked against them (frame size, then floor): TopsegError (one line) when
    it does not fit. Returns (a PeekedSource or None, whether the floor check had a verdict);
    None when the source is not there yet: the checks then come with its first frame."""
    try:
        source = open_source(spec, options)
    except SourceUnavailable as exc:
        log.info("mount file %s is checked at the first frame: %s", path, exc)
        return None, False
    try:
        if source.intrinsics is not None:
            check_mount_fits(mount, source.intrinsics, path)
        rest = source.frames()
        first = next(rest, None)
        if first is None:
            return PeekedSource(source, None, rest), False
        check_mount_fits(mount, first.depth.intrinsics, path)
        verdict = check_mount_floor(mount, first.depth.depth, path, str(spec))
        return PeekedSource(source, first, rest), verdict is not None
    except SourceUnavailable as exc:
        source.close()
        log.info("mount file %s is checked at the first frame: %s", path, exc)
        return None, False
    except BaseException:
        source.close()
        raise


class OneDriverPerCamera:
    """One camera, one driver. A liveliness subscriber notes every other driver token of this
    cell/camera (warned about loudly: their frames interleave on one key); `check` asks those
    drivers' `info`, and when one that answers started before this one (or at the same ns
    with a smaller instance id) it raises TopsegError (one line, exit 2): at start, after
    the peers settled, and again whenever a new token appears (two drivers started at once,
    each too early to see the other: the younger one stops). A token nobody answers for (a
    host gone, until Zenoh's lease ends; a crashed process's token goes with its connection,
    so restarts start) is only warned about, and asked again after `RECHECK_S`, then after
    twice as long each time up to `RECHECK_MAX_S`, while its token lives: an answer lost
    under load does not leave two drivers running for good."""

    #: First wait before a driver whose token lives but who did not answer is asked again.
    RECHECK_S = 2.0
    #: The longest wait between two such questions (each can hold the loop `QUERY_S`).
    RECHECK_MAX_S = 30.0

    def __init__(self, session, args: argparse.Namespace, me, state: DriverState) -> None:
        self.session, self.args, self.me, self.state = session, args, me, state
        self.token = wire.alive_key(args.cell, args.camera, "driver")
        self.lock = threading.Lock()
        self.others: set[str] = set()
        self.appeared = threading.Event()
        self.said: set[str] = set()
        self.recheck_s = self.RECHECK_S
        self.recheck_at: float | None = None  # monotonic time to ask silent drivers again
        self.subscriber = session.liveliness().declare_subscriber(
            f"{self.token}/*", self._on_token, history=True
        )

    def _on_token(self, sample) -> None:
        try:
            parts = wire.parse_key(str(sample.key_expr))
        except wire.WireError:
            return
        if parts.instance in (None, self.me.instance):
            return
        with self.lock:
            if str(sample.kind).endswith("DELETE"):
                self.others.discard(parts.instance)
                return
            self.others.add(parts.instance)
        self.state.note_duplicate(parts.instance)
        self.appeared.set()
        log.warning(
            "ANOTHER DRIVER serves %s/%s: %s; the frames of both interleave on %s: stop one",
            self.args.cell,
            self.args.camera,
            parts.instance,
            wire.depth_key(self.args.cell, self.args.camera),
        )

    def at_start(self) -> None:
        """Wait for the peers (1 s at most when nobody is there) and their gossip to settle,
        then `check`."""
        if zenoh_session.wait_connected(self.session, identity.CONNECT_WAIT_S):
            zenoh_session.wait_settled(self.session)
        self.appeared.clear()
        self.check(identity.other_instances(self.session, self.token, self.me.instance))

    def poll(self) -> None:
        """From the publishing loop: `check` again once a new driver token appeared, or when
        it is time to ask a silent one again."""
        due = self.recheck_at is not None and time.monotonic() >= self.recheck_at
        if self.appeared.is_set() or due:
            self.appeared.clear()
            self.check(set())

    def check(self, found: set[str]) -> None:
        """TopsegError when a live driver that started first serves this camera."""
        with self.lock:
            others = found | self.others
        if not others:
            self.recheck_at, self.recheck_s = None, self.RECHECK_S
            return
        answering = {}
        replies = self.session.get(
            wire.info_key(self.args.cell, self.args.camera),
            timeout=identity.QUERY_S,
            consolidation=zenoh.ConsolidationMode.NONE,  # one reply per driver, not per key
        )
        for reply in replies:
            try:
                info = json.loads(reply.ok.payload.to_bytes()) if reply.ok is not None else None
            except ValueError:
                continue
            if isinstance(info, dict) and info.get("instance") in others:
                answering[info["instance"]] = info
        mine = (self.state.info["started_ns"], self.me.instance)
        first = sorted(
            (int(info.get("started_ns") or 0), inst, info) for inst, info in answering.items()
        )
        if first and first[0][:2] < mine:
            _, inst, info = first[0]
            raise TopsegError(
                f"camera {self.args.cell}/{self.args.camera} is already served by driver "
                f"{inst} (pid {info.get('pid')} on {info.get('host')}, source "
                f"{info.get('source')}); stop it or give this one another --camera"
            )
        unanswered = others - set(answering)
        if unanswered:
            self.recheck_at = time.monotonic() + self.recheck_s
            self.recheck_s = min(2 * self.recheck_s, self.RECHECK_MAX_S)
        else:
            self.recheck_at, self.recheck_s = None, self.RECHECK_S
        silent = sorted(unanswered - self.said)
        if silent:
            self.said.update(silent)
            log.warning(
                "a liveliness token of driver %s for %s/%s is there but that driver does not "
                "answer (gone, until Zenoh's lease ends, or slow); going on, asking again",
                ", ".join(silent),
                self.args.cell,
                self.args.camera,
            )

    def undeclare(self) -> None:
        """Undeclare the liveliness subscriber."""
        self.subscriber.undeclare()


def run(args: argparse.Namespace) -> int:
    """Publish the source's frames until it ends or a signal comes; 0 either way. A mount
    file is read, validated and checked against the source's first frame before the driver
    joins Zenoh (TopsegError, one line, when it does not fit)."""
    spec = parse_spec(args.source)
    mount = None if args.mount is None else read_mount(args.mount)  # fails before Zenoh
    if args.congestion == "auto":
        args.congestion = "drop" if args.realtime else "block"
    options = SourceOptions(
        loop=args.loop, realtime=args.realtime, fps=args.fps, frame_timeout_s=args.frame_timeout
    )
    opened, judged = None, False
    if mount is not None:  # the mount against the source's frames, before Zenoh too
        opened, judged = open_checked(spec, options, mount, args.mount)
    try:
        return _serve(args, spec, options, mount, opened, judged)
    finally:
        if opened is not None:
            opened.close()


def _serve(args, spec, options, mount, opened, judged: bool) -> int:
    """`run` once the mount file (if any) was checked: join Zenoh and publish; `opened` is
    the source opened for that check (its first frame not yet sent), or None."""
    keys = {
        "depth": wire.depth_key(args.cell, args.camera),
        "truth": wire.truth_key(args.cell, args.camera),
        "info": wire.info_key(args.cell, args.camera),
    }
    state = DriverState(args, keys)
    last = {"t": time.monotonic(), "n": 0}

    def status_text() -> str:
        now, n = time.monotonic(), state.info["frames"]
        fps = (n - last["n"]) / max(now - last["t"], 1e-9)
        last.update(t=now, n=n)
        return (
            f"publishing {args.cell}/{args.camera} from {args.source}: {fps:.1f} fps, "
            f"{n} frames, {state.info['reconnects']} reconnects"
        )

    congestion = {"block": zenoh.CongestionControl.BLOCK, "drop": zenoh.CongestionControl.DROP}
    if mount is not None:
        log.info(
            "mount from %s: %.0f mm above the floor, pitch %.1f, roll %.1f deg, %s",
            args.mount,
            mount.height_mm,
            mount.pitch_deg,
            mount.roll_deg,
            mount.sensor,
        )
    fitted = None  # the frame size the mount was last checked against
    with ServiceLifecycle("driver", args, status=status_text) as svc:
        session = svc.session
        me = identity.Identity.of(session)
        one_driver = svc.declare(OneDriverPerCamera(session, args, me, state))
        one_driver.at_start()  # another live driver of this camera: refused, exit 2
        keys["alive"] = wire.alive_key(args.cell, args.camera, "driver", me.instance)
        state.update(keys=keys, **me.to_dict())
        attachment = wire.instance_attachment(me.instance)
        publish = dict(congestion_control=congestion[args.congestion], express=True)
        depth_pub = session.declare_publisher(keys["depth"], **publish)
        truth_pub = session.declare_publisher(keys["truth"], **publish)
        companions = svc.declare(CompanionPublisher(session, args.cell, publish, attachment))
        svc.declare(  # before the token: a driver that sees the token can ask at once
            session.declare_queryable(
                keys["info"], lambda query: query.reply(keys["info"], state.to_json())
            )
        )
        svc.declare(session.liveliness().declare_token(keys["alive"]))

        def on_open(source) -> None:
            fields = source.info()
            fields["fps"] = args.fps or fields["fps"]
            fields["reconnects"] = max(0, reconnecting.opens - 1)
            fields["last_error"] = reconnecting.last_error
            fields.pop("finite", None)
            if mount is not None:
                if source.intrinsics is not None:
                    check_mount_fits(mount, source.intrinsics, args.mount)
                fields["mount"] = mount.to_dict()
            state.update(**fields)
            log.info("publishing %s on %s", source.description, keys["depth"])
            svc.ready(f"publishing {args.cell}/{args.camera} from {args.source}")

        def open_fn():
            nonlocal opened
            if opened is not None:  # the source the mount was checked against, once
                source, opened = opened, None
                return source
            try:
                return open_source(spec, options)
            except SourceUnavailable as exc:  # up and retrying: ready, and say what is missing
                svc.ready(f"waiting for {args.source}: {exc}")
                svc.beat()
                raise

        reconnecting = Reconnecting(
            open_fn,
            name=f"driver {args.cell}/{args.camera} ({spec})",
            stop=svc.stop,
            on_open=on_open,
        )
        if not args.realtime:  # as fast as consumed: there has to be a consumer
            _wait_for_subscriber(depth_pub, keys["depth"], svc)
        labels_seen = None
        if args.congestion == "block":  # lossless: the end waits for the last frame's labels
            labels_seen = LabelsSeen(session, args.cell, args.camera)
            svc.defer(labels_seen.close)
        frames = reconnecting.frames()
        svc.defer(frames.close)  # closes the source (and its reader process)
        seq = truth_count = 0
        while not svc.stopping:
            try:
                with svc.interruptible():  # a signal cuts a wait on the source short
                    frame = next(frames)
            except StopIteration:
                log.info("%s ended after %d frames", spec, seq)
                if labels_seen is not None:
                    drain(labels_seen, seq - 1, args.drain_idle, lambda: svc.stopping)
                break
            if mount is not None and frame.depth.depth.shape != fitted:
                check_mount_fits(mount, frame.depth.intrinsics, args.mount)
                fitted = frame.depth.depth.shape
            if mount is not None and not judged:  # no verdict before Zenoh: exit 2 here
                judged = check_mount_floor(mount, frame.depth.depth, args.mount, args.source)
            frame_mount = mount if mount is not None else frame.depth.mount
            depth = dataclasses.replace(
                frame.depth, seq=seq, frame_id=args.camera, mount=frame_mount
            )
            state.update(frames=seq + 1)  # counted before it leaves: no reader is ahead of info
            depth_pub.put(wire.encode_depth(depth), attachment=attachment)
            if frame.truth is not None:
                truth = dataclasses.replace(frame.truth, seq=seq, frame_id=args.camera)
                truth_pub.put(wire.encode_labels(truth), attachment=attachment)
                truth_count += 1
            if frame.companions:
                companions.put(frame.companions, depth.stamp_ns, seq)
            seq += 1
            svc.beat()  # watchdog ping from the publishing loop, STATUS= every few s
            one_driver.poll()  # a driver that started first appeared: stop (exit 2)
            state.update(
                truth_frames=truth_count,
                companions=companions.sent,
                intrinsics=depth.intrinsics.to_dict(),
                mount=None if frame_mount is None else frame_mount.to_dict(),
                fps=args.fps or getattr(reconnecting.source, "nominal_fps", None),
            )
    return 0
