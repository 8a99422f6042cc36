"""Record topseg's Zenoh traffic to an MCAP file: `topseg record --out FILE.mcap`.

Subscribes to `--keys` (default: every camera's depth, labels and ground truth) and writes
each message's exact bytes on a channel named after its key (`topseg.core.formats.recording`).
Stops after `--duration` seconds, `--count` messages, or SIGTERM/SIGINT, and only then
moves the finished file into place. If the disk fills up it stops, keeps what it wrote
(readable up to its last complete chunk) and exits with status 2.

Zenoh callbacks only queue the messages; the main thread writes them. If writing falls
behind by more than `--queue` messages, new ones are dropped and counted, never buffered
without bound. Under systemd it says READY=1 once subscribed and pings the watchdog.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import queue
import time

from topseg.core.errors import TopsegError
from topseg.services import zenoh_session
from topseg.services.cli_types import finite, positive_int
from topseg.services.lifecycle import ServiceLifecycle

log = logging.getLogger("topseg.record")

DEFAULT_KEYS = ("topseg/*/*/depth", "topseg/*/*/labels", "topseg/*/*/truth")


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
        "--queue",
        type=positive_int,
        default=256,
        metavar="N",
        help="messages waiting to be written, at most",
    )
    zenoh_session.add_arguments(parser)


def _check(args: argparse.Namespace) -> list[str]:
    import zenoh

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


def run(args: argparse.Namespace) -> int:
    """Record until --duration, --count or SIGTERM/SIGINT; 2 (and the part written) on a
    full disk."""
    from topseg.core.formats.recording import RecordingWriter

    keys = _check(args)
    svc = ServiceLifecycle("record", args, signal_note="finishing the recording")
    inbox: queue.Queue = queue.Queue(maxsize=args.queue)
    dropped = 0

    def on_sample(sample) -> None:
        nonlocal dropped
        try:
            inbox.put_nowait((str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))
        except queue.Full:
            dropped += 1

    def wake() -> None:  # a stopping signal: end the wait on the inbox at once
        with contextlib.suppress(queue.Full):
            inbox.put_nowait(None)

    written = 0
    with svc:
        writer = RecordingWriter(args.out, metadata={"keys": " ".join(keys)})
        svc.defer(writer.close)  # moves the file into place; after a write error it is there
        subscribers = [svc.session.declare_subscriber(k, on_sample) for k in keys]
        svc.on_stop(wake)
        log.info("recording %s to %s", ", ".join(keys), args.out)
        svc.ready(status=lambda: f"recording to {args.out}: {written} messages, {dropped} dropped")
        deadline = None if args.duration is None else time.monotonic() + args.duration
        while not svc.stopping:
            if args.count is not None and written >= args.count:
                break
            svc.beat()
            timeout = svc.tick if deadline is None else min(svc.tick, deadline - time.monotonic())
            if timeout <= 0:
                break
            try:
                item = inbox.get(timeout=timeout)
            except queue.Empty:
                continue
            if item is not None:
                key, data, log_time = item
                writer.write(key, data, log_time_ns=log_time)
                written += 1
        for sub in subscribers:
            sub.undeclare()
        while args.count is None or written < args.count:  # what arrived before the stop
            try:
                item = inbox.get_nowait()
            except queue.Empty:
                break
            if item is not None:
                key, data, log_time = item
                writer.write(key, data, log_time_ns=log_time)
                written += 1
    log.info("recorded %d messages to %s (%d dropped)", written, args.out, dropped)
    return 0
