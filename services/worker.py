"""Label depth frames from Zenoh: `topseg worker --model M [--crf MODE] [--cameras cell/cam ...]`.

For every camera it serves (all of `topseg/*/*/depth`, or the `--cameras` given) the worker
runs the forest and the CRF on the newest depth frame and publishes

- labels on `topseg/<cell>/<camera>/labels` (the depth frame's `seq`, `stamp_ns`, `frame_id`);
- stats on `.../stats`: ms per stage (receive = copy + decode, forest, crf, publish, total),
  latency (depth stamp to labels published), fps, and the counts processed / dropped / rejected.

Only the newest frame is kept: one `zenoh.handlers.RingChannel(1)` per camera, so a slow
worker skips frames and its memory never grows. Skipped frames are counted from gaps in
`seq`. `--lossless` uses a FIFO instead (tests, offline labelling of a replay). Messages that
do not decode (or that the forest cannot take) are dropped, counted as `rejected` and logged;
they never stop the worker. Without `--cameras`, a camera is served from its first depth
message on (that message only announces it; the ring subscriber takes the next one).

It holds `topseg/<cell>/<camera>/alive/worker` for each camera it serves and stops cleanly on
SIGTERM/SIGINT. A missing or damaged model file stops it before it joins Zenoh (exit 2).
"""

from __future__ import annotations

import argparse
import logging
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from topseg.services import systemd_notify, zenoh_session

log = logging.getLogger("topseg.worker")

#: FIFO depth in --lossless mode: a full FIFO holds Zenoh back (the publisher waits).
LOSSLESS_QUEUE = 64
#: Idle poll period of the subscriber handlers.
POLL_S = 0.002
#: Smoothing of the fps estimate (weight of the newest interval).
FPS_ALPHA = 0.2


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--model",
        required=True,
        metavar="PATH",
        help="model file from `topseg train` (required: there is no bundled model yet)",
    )
    parser.add_argument(
        "--crf",
        choices=("none", "exact", "realtime"),
        default="realtime",
        help="CRF smoothing after the forest (default: %(default)s)",
    )
    parser.add_argument(
        "--cameras",
        nargs="+",
        metavar="CELL/CAMERA",
        help="serve only these cameras (default: every camera seen on topseg/*/*/depth)",
    )
    parser.add_argument(
        "--lossless",
        action="store_true",
        help="label every frame (FIFO) instead of only the newest one per camera",
    )
    zenoh_session.add_arguments(parser)


def parse_camera(text: str) -> tuple[str, str]:
    """'cell/camera' -> (cell, camera); TopsegError naming the bad entry."""
    from topseg.core.errors import TopsegError
    from topseg.core.formats import wire

    parts = text.split("/")
    if len(parts) != 2:
        raise TopsegError(f"--cameras entry {text!r} must be CELL/CAMERA")
    try:
        wire.camera_prefix(*parts)
    except wire.WireError as exc:
        raise TopsegError(f"--cameras entry {text!r}: {exc}") from None
    return parts[0], parts[1]


@dataclass
class CameraState:
    """Per-camera bookkeeping: publishers, token, counts, the last seq and the fps estimate."""

    cell: str
    camera: str
    labels_pub: Any = None
    stats_pub: Any = None
    token: Any = None
    subscriber: Any = None
    counts: dict = field(default_factory=lambda: {"processed": 0, "dropped": 0, "rejected": 0})
    last_seq: int | None = None
    last_time: float | None = None
    fps: float = 0.0

    def note_seq(self, seq: int) -> None:
        """Count the frames skipped between the last labelled seq and this one."""
        if self.last_seq is not None and seq > self.last_seq + 1:
            self.counts["dropped"] += seq - self.last_seq - 1
        self.last_seq = seq  # a smaller seq: the source restarted, nothing to count

    def note_done(self, now: float) -> None:
        if self.last_time is not None and now > self.last_time:
            rate = 1.0 / (now - self.last_time)
            self.fps = rate if self.fps == 0.0 else (1 - FPS_ALPHA) * self.fps + FPS_ALPHA * rate
        self.last_time = now


class Labeller:
    """Forest + CRF on one depth image, reusing the posterior buffer across frames."""

    def __init__(self, model_path: str, crf_mode: str) -> None:
        from topseg.core import crf, forest

        self.forest, self.header = forest.load_model(model_path)
        self.model_id = str(self.header.get("model_id") or Path(model_path).name)
        self.config = crf.CRFConfig(mode=crf_mode)
        self._out: Any = None

    def warm_up(self) -> None:
        """Compile the numba kernels before the first frame (they are cached on disk)."""
        import numpy as np

        self.label(np.full((48, 64), 3000, np.uint16))

    def label(self, depth) -> tuple[Any, float, float]:
        """(labels, forest ms, crf ms) for one uint16 depth image."""
        import numpy as np

        from topseg.core import crf, forest
        from topseg.core.labels import NUM_CLASSES

        shape = (*depth.shape, NUM_CLASSES)
        if self._out is None or self._out.shape != shape:
            self._out = np.empty(shape, np.float32)
        t0 = time.perf_counter()
        proba = forest.predict_proba(self.forest, depth, out=self._out)
        t1 = time.perf_counter()
        labels = crf.segment_crf(proba, depth, self.config)
        t2 = time.perf_counter()
        return labels, 1000 * (t1 - t0), 1000 * (t2 - t1)


class Worker:
    """The serving loop: subscribers, per-camera state and the publish side."""

    def __init__(self, args: argparse.Namespace, session, labeller: Labeller) -> None:
        import zenoh

        self.args, self.session, self.labeller = args, session, labeller
        self.cameras: dict[tuple[str, str], CameraState] = {}
        self.pending: set[tuple[str, str]] = set()
        self.pending_lock = threading.Lock()
        self.shared_sub = None  # --lossless without --cameras: one FIFO on the wildcard
        self.discovery = None
        self.congestion = (
            zenoh.CongestionControl.BLOCK if args.lossless else zenoh.CongestionControl.DROP
        )
        wanted = [parse_camera(c) for c in args.cameras or ()]
        for cell, camera in wanted:
            self.serve(cell, camera, own_subscriber=True)
        if not wanted:
            if args.lossless:
                self.shared_sub = session.declare_subscriber(
                    "topseg/*/*/depth", zenoh.handlers.FifoChannel(LOSSLESS_QUEUE)
                )
            else:
                self.discovery = session.declare_subscriber("topseg/*/*/depth", self._discover)

    def _discover(self, sample) -> None:
        """Zenoh thread: note cameras not served yet (the main loop declares them)."""
        from topseg.core.formats import wire

        try:
            parts = wire.parse_key(str(sample.key_expr))
        except wire.WireError:
            return
        key = (parts.cell, parts.camera)
        if key not in self.cameras:
            with self.pending_lock:
                self.pending.add(key)

    def serve(self, cell: str, camera: str, own_subscriber: bool) -> CameraState:
        """Start serving one camera: publishers, liveliness token, maybe its own subscriber."""
        import zenoh

        from topseg.core.formats import wire

        state = CameraState(cell, camera)
        publish = dict(congestion_control=self.congestion, express=True)
        state.labels_pub = self.session.declare_publisher(wire.labels_key(cell, camera), **publish)
        state.stats_pub = self.session.declare_publisher(wire.stats_key(cell, camera), **publish)
        if own_subscriber:
            handler = (
                zenoh.handlers.FifoChannel(LOSSLESS_QUEUE)
                if self.args.lossless
                else zenoh.handlers.RingChannel(1)
            )
            state.subscriber = self.session.declare_subscriber(
                wire.depth_key(cell, camera), handler
            )
        state.token = self.session.liveliness().declare_token(
            wire.alive_key(cell, camera, "worker")
        )
        self.cameras[(cell, camera)] = state
        log.info("serving %s/%s (crf %s)", cell, camera, self.labeller.config.mode)
        return state

    def poll(self) -> bool:
        """Handle what has arrived; False when nothing had."""
        with self.pending_lock:
            new, self.pending = self.pending, set()
        for cell, camera in sorted(new):
            if (cell, camera) not in self.cameras:
                self.serve(cell, camera, own_subscriber=True)
        busy = False
        if self.shared_sub is not None:
            sample = self.shared_sub.handler.try_recv()
            if sample is not None:
                self.handle(sample, None)
                busy = True
        for state in list(self.cameras.values()):
            if state.subscriber is None:
                continue
            sample = state.subscriber.handler.try_recv()
            if sample is not None:
                self.handle(sample, state)
                busy = True
        return busy

    def handle(self, sample, state: CameraState | None) -> None:
        """Decode, label and publish one depth message; count and drop what is not one."""
        from topseg.core.formats import wire

        t0 = time.perf_counter()
        if state is None:  # the shared FIFO: the key says which camera
            try:
                parts = wire.parse_key(str(sample.key_expr))
            except wire.WireError:
                return
            state = self.cameras.get((parts.cell, parts.camera))
            if state is None:
                state = self.serve(parts.cell, parts.camera, own_subscriber=False)
        try:
            frame = wire.decode_depth(sample.payload.to_bytes())
        except wire.WireError as exc:
            self.reject(state, f"bad depth message: {exc}")
            return
        t1 = time.perf_counter()
        try:
            labels, forest_ms, crf_ms = self.labeller.label(frame.depth)
        except Exception as exc:  # a well-formed frame the forest or CRF cannot take
            self.reject(state, f"cannot label frame {frame.seq}: {type(exc).__name__}: {exc}")
            return
        t2 = time.perf_counter()
        out = wire.LabelFrame(labels, frame.seq, frame.stamp_ns, frame.frame_id)
        state.labels_pub.put(wire.encode_labels(out))
        t3 = time.perf_counter()
        state.note_seq(frame.seq)
        state.counts["processed"] += 1
        state.note_done(t3)
        timings = {
            "receive": 1000 * (t1 - t0),
            "forest": forest_ms,
            "crf": crf_ms,
            "publish": 1000 * (t3 - t2),
            "total": 1000 * (t3 - t0),
        }
        if frame.stamp_ns:  # end to end: capture (driver host clock) -> labels published
            timings["latency"] = max(0.0, (time.time_ns() - frame.stamp_ns) / 1e6)
        self.publish_stats(state, timings, seq=frame.seq, frame_id=frame.frame_id)

    def reject(self, state: CameraState, why: str) -> None:
        state.counts["rejected"] += 1
        n = state.counts["rejected"]
        if n <= 10 or n % 100 == 0:  # a stream of garbage does not flood the log
            log.warning("%s/%s: %s (%d rejected)", state.cell, state.camera, why, n)
        self.publish_stats(state, {})

    def publish_stats(self, state: CameraState, timings: dict, **extra) -> None:
        from topseg.core.formats import wire

        stats = {
            "stamp_ns": time.time_ns(),
            "role": "worker",
            "model_id": self.labeller.model_id[: wire.MAX_FRAME_ID],
            "fps": state.fps,
            "timings_ms": timings,
            "counts": dict(state.counts),
            **extra,
        }
        state.stats_pub.put(wire.encode_stats(stats))

    def close(self) -> None:
        for state in self.cameras.values():
            state.token.undeclare()
            if state.subscriber is not None:
                state.subscriber.undeclare()
        for sub in (self.shared_sub, self.discovery):
            if sub is not None:
                sub.undeclare()


def status_line(worker: Worker) -> str:
    """One line for `systemctl status`: each camera's fps and counts."""
    if not worker.cameras:
        return f"model {worker.labeller.model_id}: waiting for depth frames"
    now, parts = time.perf_counter(), []
    for s in worker.cameras.values():
        c = s.counts
        idle = s.last_time is None or now - s.last_time > 2.0
        rate = "idle" if idle else f"{s.fps:.1f} fps"
        parts.append(
            f"{s.cell}/{s.camera}: {rate}, {c['processed']} labelled, "
            f"{c['dropped']} dropped, {c['rejected']} rejected"
        )
    return "serving " + "; ".join(parts)


def run(args: argparse.Namespace) -> int:
    for text in args.cameras or ():
        parse_camera(text)  # bad names fail before anything is loaded
    zenoh_session.make_config(args.zenoh_config, args.zenoh_port)  # so does a bad config
    labeller = Labeller(args.model, args.crf)  # ModelFileError: one line, exit 2
    t0 = time.perf_counter()
    labeller.warm_up()
    log.info("model %s loaded and compiled in %.1f s", labeller.model_id, time.perf_counter() - t0)

    stop = threading.Event()

    def on_signal(signum, _frame):
        log.info("%s: stopping", signal.Signals(signum).name)
        stop.set()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
    session = zenoh_session.session_from_args(args)
    worker = None
    try:
        worker = Worker(args, session, labeller)
        log.info("worker ready")
        systemd_notify.ready(status_line(worker))
        beat = systemd_notify.Heartbeat(lambda: status_line(worker))
        while not stop.is_set():
            beat()  # watchdog ping from the serving loop, STATUS= every few s
            if not worker.poll():
                stop.wait(POLL_S)
        for state in worker.cameras.values():
            log.info("%s/%s: %s", state.cell, state.camera, state.counts)
    finally:
        for s, handler in old.items():
            signal.signal(s, handler)
        if worker is not None:
            worker.close()
        session.close()
    return 0
