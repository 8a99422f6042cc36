"""Show what flows on Zenoh in Rerun: `topseg viewer [--spawn | --web | --save FILE.rrd]`.

For every camera seen on `topseg/*/*/{depth,labels,stats}` it logs, under `<cell>/<camera>/`:

- `image` the Pinhole from the depth message's intrinsics (RDF camera), with
  `image/depth` (`rr.DepthImage`, metres = mm / 1000) and `image/labels` (`rr.SegmentationImage`);
- `points` the label-coloured point cloud (every `--stride`-th pixel of every `--stride`-th row)
  of a labels message and the depth frame with the same `seq`;
- `stats/ms/<stage>`, `stats/fps` and `stats/count/<name>` as `rr.Scalars` over time.

The label table is the static AnnotationContext at the root, so ids show with their names and
colours. Each message is logged on the `frame` timeline (its `seq`) and `sensor_time` (its
stamp). Undecodable messages are counted and skipped. `--save` flushes the `.rrd` on SIGTERM,
SIGINT or after `--duration` seconds.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import queue
import time
from collections import OrderedDict
from typing import Any

from topseg.services import zenoh_session
from topseg.services.cli_types import finite
from topseg.services.lifecycle import ServiceLifecycle

log = logging.getLogger("topseg.viewer")

#: depth frames kept per camera while their labels are on the way
PAIR_WINDOW = 16
#: messages queued between Zenoh's thread and the logging loop (older ones are dropped)
QUEUE_SIZE = 64


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The viewer's options: the sink, --duration, --stride and Zenoh."""
    sink = parser.add_mutually_exclusive_group()
    sink.add_argument("--spawn", action="store_true", help="open a native Rerun viewer (default)")
    sink.add_argument("--web", action="store_true", help="serve the web viewer (gRPC + HTTP)")
    sink.add_argument("--save", metavar="FILE.rrd", help="write a Rerun recording instead")
    parser.add_argument(
        "--duration",
        type=finite(0.001, 1e8),
        metavar="S",
        help="stop after this many seconds (default: never)",
    )
    parser.add_argument(
        "--stride",
        type=int,
        default=4,
        metavar="N",
        help="point cloud: every N-th pixel and row (default: %(default)s)",
    )
    zenoh_session.add_arguments(parser)


def annotation_context():
    """The label table as a Rerun AnnotationContext (ids, names, colours)."""
    import rerun as rr

    from topseg.core import labels

    return rr.AnnotationContext(
        [(lab.id, lab.name, tuple(int(c) for c in lab.color)) for lab in labels.LABELS]
        + [(labels.NO_DEPTH, "no_depth", (0, 0, 0))]
    )


def point_cloud(depth_frame, label_img, stride: int) -> tuple[Any, Any]:
    """(N, 3) float32 metres in the camera frame and their (N,) class ids, subsampled."""
    from topseg.core.camera import backproject

    xyz = backproject(depth_frame.depth, depth_frame.intrinsics)[::stride, ::stride]
    ids = label_img[::stride, ::stride]
    keep = depth_frame.depth[::stride, ::stride] > 0
    return xyz[keep], ids[keep].astype("uint16")


class Viewer:
    """Decodes topseg messages and logs them to one Rerun recording stream."""

    def __init__(self, rec, stride: int) -> None:
        from topseg.core.formats import wire

        self.rec, self.stride = rec, stride
        #: the kinds the viewer subscribes to, and their decoders
        self.decoders = {
            "depth": wire.decode_depth,
            "labels": wire.decode_labels,
            "stats": wire.decode_stats,
        }
        self.depth: dict[tuple[str, str], OrderedDict] = {}
        self.pinholes: dict[tuple[str, str], Any] = {}
        self.rejected = 0
        self.seen: set[str] = set()
        rec.log("/", annotation_context(), static=True)

    def _first(self, entity: str) -> None:
        """Log an entity's first message once (operators and tests see what is live)."""
        if entity not in self.seen:
            self.seen.add(entity)
            log.info("logging %s", entity)

    def handle(self, key: str, payload: bytes) -> None:
        """Decode one message by the kind its key names (parsed once) and log it."""
        from topseg.core.formats import wire

        try:
            parts = wire.parse_key(key)
            decode = self.decoders.get(parts.kind)
            if decode is None:
                raise wire.WireError(f"{key!r} does not carry a message the viewer shows")
            msg = decode(payload)
        except wire.WireError as exc:
            self.rejected += 1
            if self.rejected <= 10 or self.rejected % 100 == 0:
                log.warning("%s: %s (%d rejected)", key, exc, self.rejected)
            return
        cam = (parts.cell, parts.camera)
        base = f"{parts.cell}/{parts.camera}"
        if parts.kind == "depth":
            self.log_depth(cam, base, msg)
        elif parts.kind == "labels":
            self.log_labels(cam, base, msg)
        else:
            self.log_stats(base, msg)

    def _time(self, seq: int, stamp_ns: int) -> None:
        self.rec.set_time("frame", sequence=seq)
        self.rec.set_time("sensor_time", timestamp=stamp_ns * 1e-9)

    def log_depth(self, cam, base: str, frame) -> None:
        """The camera's Pinhole (when it changed) and the depth image; keep it for pairing."""
        import rerun as rr

        k = frame.intrinsics
        if self.pinholes.get(cam) != k:  # static: the camera changes rarely, if ever
            self.rec.log(
                f"{base}/image",
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
        self.rec.log(f"{base}/image/depth", rr.DepthImage(frame.depth, meter=1000.0))
        frames = self.depth.setdefault(cam, OrderedDict())
        frames[frame.seq] = frame
        while len(frames) > PAIR_WINDOW:
            frames.popitem(last=False)

    def log_labels(self, cam, base: str, frame) -> None:
        """The label image, and the point cloud when the depth frame of its seq is kept."""
        import rerun as rr

        self._time(frame.seq, frame.stamp_ns)
        self.rec.log(f"{base}/image/labels", rr.SegmentationImage(frame.labels))
        depth = self.depth.get(cam, {}).get(frame.seq)
        if depth is not None and depth.depth.shape == frame.labels.shape:
            xyz, ids = point_cloud(depth, frame.labels, self.stride)
            self.rec.log(f"{base}/points", rr.Points3D(xyz, class_ids=ids))
            self._first(f"{base}/points")

    def log_stats(self, base: str, stats: dict) -> None:
        """ms per stage, fps and counts as scalars over time."""
        import rerun as rr

        if "seq" in stats:
            self.rec.set_time("frame", sequence=stats["seq"])
        self.rec.set_time("sensor_time", timestamp=stats["stamp_ns"] * 1e-9)
        for stage, ms in stats["timings_ms"].items():
            self.rec.log(f"{base}/stats/ms/{stage}", rr.Scalars(ms))
        if "fps" in stats:
            self.rec.log(f"{base}/stats/fps", rr.Scalars(stats["fps"]))
        for name, n in stats["counts"].items():
            self.rec.log(f"{base}/stats/count/{name}", rr.Scalars(float(n)))
        self._first(f"{base}/stats")


def open_recording(args: argparse.Namespace):
    """A RecordingStream sending to the chosen sink."""
    import rerun as rr

    from topseg.core.errors import TopsegError

    rec = rr.RecordingStream("topseg")
    if args.save:
        try:
            rec.save(args.save)
        except Exception as exc:
            raise TopsegError(f"cannot write {args.save}: {exc}") from None
    elif args.web:
        uri = rec.serve_grpc()
        rr.serve_web_viewer(connect_to=uri)
        log.info("web viewer serving %s", uri)
    else:
        try:
            rec.spawn()
        except Exception as exc:
            raise TopsegError(
                f"cannot spawn the Rerun viewer ({exc}); try --web or --save"
            ) from None
    return rec


def run(args: argparse.Namespace) -> int:
    """Log what flows until SIGTERM/SIGINT or --duration; bad options fail first (exit 2)."""
    from topseg.core.errors import TopsegError

    if args.stride < 1:
        raise TopsegError(f"--stride must be >= 1, got {args.stride}")
    if args.duration is not None and args.duration <= 0:
        raise TopsegError(f"--duration must be > 0, got {args.duration}")
    svc = ServiceLifecycle("viewer", args)
    rec = open_recording(args)
    viewer = Viewer(rec, args.stride)
    inbox: queue.Queue = queue.Queue(QUEUE_SIZE)
    dropped = 0

    def on_sample(sample) -> None:  # Zenoh thread: copy and hand over, never block
        nonlocal dropped
        try:
            inbox.put_nowait((str(sample.key_expr), sample.payload.to_bytes()))
        except queue.Full:
            dropped += 1

    def wake() -> None:  # a stopping signal: end the wait on the inbox at once
        with contextlib.suppress(queue.Full):
            inbox.put_nowait(None)

    sink = f" to {args.save}" if args.save else " to the web viewer" if args.web else ""

    def status_text() -> str:
        n = len(viewer.pinholes)
        return f"logging {n} camera(s){sink}; {viewer.rejected} rejected, {dropped} dropped"

    with svc:
        svc.defer(rec.disconnect)
        svc.defer(rec.flush)  # runs first: the .rrd is complete on SIGTERM too
        for kind in ("depth", "labels", "stats"):
            svc.declare(svc.session.declare_subscriber(f"topseg/*/*/{kind}", on_sample))
        svc.on_stop(wake)
        log.info("viewer ready")
        svc.ready(status=status_text)
        end = None if args.duration is None else time.monotonic() + args.duration
        while not svc.stopping:
            svc.beat()  # watchdog ping from the logging loop, STATUS= every few s
            timeout = svc.tick if end is None else min(svc.tick, end - time.monotonic())
            if timeout <= 0:
                break
            try:
                item = inbox.get(timeout=timeout)
            except queue.Empty:
                continue
            if item is not None:
                viewer.handle(*item)
    log.info("viewer done (%d rejected, %d dropped while busy)", viewer.rejected, dropped)
    return 0
