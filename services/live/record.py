"""Record what is on Zenoh to an MCAP file: every camera's depth, labels, ground truth and
stats, every cell's safety state and its robot's joint states by default, as ROS 2 messages (`--format ros2`, which ROS 2 tools and `replay:` read)
or as the raw wire bytes (`--format msgpack`). Stops after `--duration`, `--count` or
Ctrl-C, then moves the finished file into place.

Subscribes to `--keys` (default: every camera's depth, labels, ground truth and stats,
`topseg/*/safety` and `topseg/*/robot/*/joints`). `--format ros2` (the default) writes a ROS 2
recording (`core/formats/ros2_recording.py`: CDR images, camera info, the mount as
`/tf_static`, stats and safety states as JSON, joint states as `sensor_msgs/JointState`);
wire messages that are none of these are dropped and counted as rejected. `--format msgpack`
writes each message's exact bytes on a channel named after its key
(`core/formats/recording.py`), a raw capture of the wire, garbage included.
Stops after `--duration` seconds, `--count` messages, or SIGTERM/SIGINT, and only then
moves the finished file into place. If the disk fills up it stops, keeps what it wrote
(readable up to its last complete chunk) and exits with status 2. If the output folder is
deleted while recording it stops, says that what it recorded is lost, and exits with 2.

Zenoh callbacks only queue the messages; the main thread converts and writes them. If
writing falls behind by more than `--queue` messages, new ones are dropped and counted,
never buffered without bound. Under systemd it says READY=1 once subscribed and pings the
watchdog.
"""

from __future__ import annotations

import argparse
import logging
import time

import zenoh

from topseg.core.errors import TopsegError
from topseg.core.formats.recording import RecordingWriter
from topseg.core.formats.ros2_recording_writer import Ros2RecordingWriter
from topseg.core.formats.wire import WireError
from topseg.core.printable import printable
from topseg.services.cli.options import finite, positive_int
from topseg.services.runtime import zenoh_session
from topseg.services.runtime.inbox import Inbox
from topseg.services.runtime.lifecycle import ServiceLifecycle

log = logging.getLogger("topseg.record")

DEFAULT_KEYS = (
    "topseg/*/*/depth",
    "topseg/*/*/labels",
    "topseg/*/*/truth",
    "topseg/*/*/stats",
    "topseg/*/safety",
    "topseg/*/robot/*/joints",
)
FORMATS = ("ros2", "msgpack")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The recorder's options: the file, when to stop, the keys, the queue and Zenoh."""
    parser.add_argument("--out", required=True, metavar="FILE.mcap", help="the recording to write")
    parser.add_argument(
        "--duration", type=finite(0.001, 1e8), metavar="S", help="stop after S seconds"
    )
    parser.add_argument("--count", type=positive_int, metavar="N", help="stop after N messages")
    parser.add_argument(
        "--keys",
        nargs="+",
        metavar="KEYEXPR",
        default=list(DEFAULT_KEYS),
        help="Zenoh key expressions to record (default: %(default)s)",
    )
    parser.add_argument(
        "--format",
        choices=FORMATS,
        default="ros2",
        help="ros2: ROS 2 messages (CDR) for ROS tools and replay; msgpack: the exact wire "
        "bytes (default: %(default)s)",
    )
    parser.add_argument(
        "--queue",
        type=positive_int,
        default=256,
        metavar="N",
        help="messages waiting to be written, at most",
    )
    zenoh_session.add_arguments(parser)


def _check(args: argparse.Namespace) -> list[str]:
    if args.duration is not None and args.duration <= 0:
        raise TopsegError(f"--duration must be positive, got {args.duration}")
    if args.count is not None and args.count <= 0:
        raise TopsegError(f"--count must be positive, got {args.count}")
    if args.queue <= 0:
        raise TopsegError(f"--queue must be positive, got {args.queue}")
    keys = []
    for key in args.keys:
        try:
            keys.append(str(zenoh.KeyExpr(key)))
        except Exception as exc:  # zenoh raises ZError for malformed key expressions
            raise TopsegError(f"{key!r} is not a Zenoh key expression: {exc}") from None
    return keys


def open_writer(fmt: str, path: str, metadata: dict[str, str]):
    """The writer of a `--format`: both take `write(key, wire bytes, log_time_ns=...)`."""
    writer = Ros2RecordingWriter if fmt == "ros2" else RecordingWriter
    return writer(path, metadata=metadata)


def run(args: argparse.Namespace) -> int:
    """Record until --duration, --count or SIGTERM/SIGINT; 2 (and the part written) on a
    full disk, 2 when the output folder was deleted (what it held is lost)."""
    keys = _check(args)
    svc = ServiceLifecycle("record", args, signal_note="finishing the recording")
    inbox = Inbox(args.queue, stamp=True)
    rejected = written = 0

    def store(item) -> None:
        nonlocal written, rejected
        key, data, log_time = item
        try:
            writer.write(key, data, log_time_ns=log_time)
        except WireError as exc:  # only the ros2 form reads what it writes
            rejected += 1
            log.warning(
                "dropped a message on %s that is not a topseg message: %s",
                printable(key),
                printable(exc),
            )
            return
        written += 1

    with svc:
        writer = open_writer(args.format, args.out, {"keys": " ".join(keys)})
        svc.defer(writer.close)  # moves the file into place; after a write error it is there
        subscribers = [svc.session.declare_subscriber(k, inbox.on_sample) for k in keys]
        svc.on_stop(inbox.wake)
        log.info("recording %s to %s (%s)", ", ".join(keys), args.out, args.format)
        svc.ready(
            status=lambda: (
                f"recording to {args.out}: {written} messages, {inbox.dropped} dropped, "
                f"{rejected} rejected"
            )
        )
        deadline = None if args.duration is None else time.monotonic() + args.duration
        while not svc.stopping:
            writer.check_in_place()
            if args.count is not None and written >= args.count:
                break
            svc.beat()
            timeout = svc.tick if deadline is None else min(svc.tick, deadline - time.monotonic())
            if timeout <= 0:
                break
            item = inbox.get(timeout)
            if item is not None:
                store(item)
        for sub in subscribers:
            sub.undeclare()
        for item in inbox.drain():  # what arrived before the stop
            if args.count is not None and written >= args.count:
                break
            store(item)
    log.info(
        "recorded %d messages to %s (%d dropped, %d rejected)",
        written,
        args.out,
        inbox.dropped,
        rejected,
    )
    return 0
