"""The live path end to end: driver -> Zenoh -> worker -> Zenoh (-> viewer), as separate processes.

`run_pipeline` starts `topseg worker` (and `topseg viewer --save` when given an .rrd path),
waits until they say they are ready, then starts `topseg driver`, all peers on a private
loopback Zenoh port under their own cell. This process subscribes to the camera's depth,
truth and labels and measures:

- `fps`: labelled frames a second over the time labels came;
- `latency_p50_ms` / `latency_p99_ms`: driver stamp (the moment the source handed the frame
  on) -> labels received here, over every labelled frame after the first `WARMUP_FRAMES`
  (nearest-rank percentiles, `core.metrics.percentile`, as `topseg status` reports them);
- `frames_sent` (depth messages seen, and at least the frames labelled), `frames_labelled`,
  `frames_scored`;
- `scores`: `ConfusionAccumulator.scores()` of the labels against the truth channel (frames
  paired by seq; scored after the run so that scoring takes no CPU from the pipeline).

It stops after `duration_s` seconds of labels, or, with no duration, when a finite source (a
replay) ends; then SIGTERM to the driver, a short wait for labels in flight, SIGTERM to the
worker and the viewer. The children's logs go to `logs_dir` (a temporary folder by default).
"""

from __future__ import annotations

import math
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from topseg.core.bundled_model import bundled_model_path
from topseg.core.errors import TopsegError
from topseg.core.formats import wire
from topseg.core.metrics import ConfusionAccumulator, percentile
from topseg.core.segmenter_config import SegmenterConfig
from topseg.drivers.spec import parse_spec
from topseg.services.cli.options import setting_argv
from topseg.services.runtime.zenoh_session import open_session

CELL = "pipeline"
CAMERA = "cam0"
WARMUP_FRAMES = 5
START_TIMEOUT_S = 180.0
MAX_SCORED = 3000  # frames kept for scoring (~0.6 MB each)
#: the worker's per-frame stage timings kept for percentiles
MAX_STAGE = 100_000
STAGES = ("receive", "mount", "forest", "crf", "publish", "total")
DRAIN_S = 1.0  # wait for labels still in flight after the driver stops
#: --lossless: after the driver stops, keep waiting while labels still come (at most this
#: long between two), until every frame sent is labelled; a loaded worker has a backlog
DRAIN_IDLE_S = 15.0


def free_port() -> int:
    """A TCP port on loopback that nothing listens on now (for a private Zenoh)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _drain(col: _Collector, lossless: bool, stop: threading.Event) -> None:
    """Wait for labels still in flight after the driver stopped.

    DRAIN_S at least; with `lossless`, also until every depth frame seen is labelled, for as
    long as labels keep coming (DRAIN_IDLE_S at most between two). A fixed wait loses the
    tail of a loaded worker's FIFO to the SIGTERM that follows.
    """
    t_end = time.monotonic() + DRAIN_S
    while not stop.is_set():
        now = time.monotonic()
        with col.lock:
            done = col.n_labels >= col.frames_sent
            last = col.last_label_s  # monotonic
        if now >= t_end and (not lossless or done):
            return
        if lossless and now >= t_end and last is not None and now - last > DRAIN_IDLE_S:
            return  # the worker stopped making progress: report what came
        stop.wait(0.05)


class _Collector:
    """Subscriber callbacks: count depth, keep truth and labels by seq, time the labels."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.frames_sent = 0
        self.truth: dict[tuple[str, int], np.ndarray] = {}  # by (camera, seq)
        self.labels: dict[tuple[str, int], np.ndarray] = {}
        self.latency_ms: list[float] = []
        self.first_label_s: float | None = None
        self.last_label_s: float | None = None
        self.n_labels = 0
        self.rejected = 0
        self.stage_ms: dict[str, list[float]] = {}  # the worker's own timings, per stage
        self.n_stats = 0

    def on_depth(self, _sample) -> None:
        with self.lock:
            self.frames_sent += 1

    def on_truth(self, sample) -> None:
        try:
            frame = wire.decode_labels(sample.payload.to_bytes())
        except wire.WireError:
            self.rejected += 1
            return
        with self.lock:
            if len(self.truth) < MAX_SCORED:
                self.truth[_camera_of(sample), frame.seq] = frame.labels

    def on_labels(self, sample) -> None:
        now_ns, now_s = time.time_ns(), time.monotonic()
        try:
            frame = wire.decode_labels(sample.payload.to_bytes())
        except wire.WireError:
            self.rejected += 1
            return
        with self.lock:
            self.n_labels += 1
            if self.first_label_s is None:
                self.first_label_s = now_s
            self.last_label_s = now_s
            if self.n_labels > WARMUP_FRAMES:
                self.latency_ms.append((now_ns - frame.stamp_ns) / 1e6)
            if len(self.labels) < MAX_SCORED:
                self.labels[_camera_of(sample), frame.seq] = frame.labels

    def on_stats(self, sample) -> None:
        try:
            stats = wire.decode_stats(sample.payload.to_bytes())
        except wire.WireError:
            self.rejected += 1
            return
        timings = stats.get("timings_ms") or {}
        with self.lock:
            if "total" not in timings:
                return  # a count update, not a labelled frame
            self.n_stats += 1
            if self.n_stats <= WARMUP_FRAMES or len(self.stage_ms.get("total", ())) >= MAX_STAGE:
                return
            for stage in STAGES:
                if stage in timings:
                    self.stage_ms.setdefault(stage, []).append(float(timings[stage]))


def _camera_of(sample) -> str:
    """The camera name in a sample's key `topseg/<cell>/<camera>/<stream>`."""
    return str(sample.key_expr).split("/")[2]


def camera_names(cameras: int) -> list[str]:
    """The cameras of a pipeline run: CAMERA alone, or cam0, cam1, ... for several."""
    return [CAMERA] if cameras == 1 else [f"cam{i}" for i in range(cameras)]


def cli_argv(*args: str) -> list[str]:
    """The command line of `topseg -v <args>` run by this Python."""
    return [sys.executable, "-m", "topseg.services.cli", "-v", *args]


class Children:
    """The started processes, their log files, and stopping them with SIGTERM."""

    def __init__(self, logs_dir: Path) -> None:
        self.logs_dir = logs_dir
        self.procs: dict[str, subprocess.Popen] = {}

    def start(self, name: str, cmd: list[str]) -> None:
        """Start `cmd` as `name`, its output to `name`.log."""
        log = (self.logs_dir / f"{name}.log").open("w")
        self.procs[name] = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT)
        log.close()

    def log_text(self, name: str) -> str:
        """What `name` has logged so far."""
        return (self.logs_dir / f"{name}.log").read_text(errors="replace")

    def wait_ready(self, name: str, marker: str, timeout_s: float) -> None:
        """Wait until `name` logs `marker`; TopsegError when it exits or `timeout_s` passes."""
        deadline = time.monotonic() + timeout_s
        proc = self.procs[name]
        while marker not in self.log_text(name):
            if proc.poll() is not None:
                raise TopsegError(f"{name} exited ({proc.returncode}): {self.tail(name)}")
            if time.monotonic() > deadline:
                raise TopsegError(f"{name} not ready after {timeout_s:.0f} s: {self.tail(name)}")
            time.sleep(0.05)

    def tail(self, name: str) -> str:
        """The last line `name` logged."""
        lines = self.log_text(name).strip().splitlines()
        return lines[-1] if lines else "(no output)"

    def stop(self, name: str, timeout_s: float = 20.0) -> int | None:
        """SIGTERM to `name`, then kill after `timeout_s`; its exit status (None: not started)."""
        proc = self.procs.get(name)
        if proc is None:
            return None
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        try:
            return proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            return -signal.SIGKILL


def run_pipeline(
    source: str,
    model: Path | None,
    duration_s: float | None,
    fps: float | None,
    config: SegmenterConfig | None = None,
    rrd: Path | None = None,
    lossless: bool = False,
    *,
    web: bool = False,
    port: int | None = None,
    logs_dir: Path | None = None,
    cameras: int = 1,
) -> dict:
    """Run driver, worker (and viewer when `rrd` is given) and return the figures.

    `model` None is the bundled model (`core.segmenter.bundled_model_path`).
    Returns {"fps", "latency_p50_ms", "latency_p99_ms", "worker_<stage>_p50_ms" and "_p99_ms"
    (the worker's own forest, crf and total: receive to publish, from its stats),
    "frames_sent", "frames_labelled", "frames_scored", "scores" (ConfusionAccumulator.scores(),
    None without truth), "confusion", "exit_codes", "logs"}. `config` is the worker's
    Segmenter configuration (None: the defaults), given to it as options
    (`options.setting_argv`). `cameras` > 1 runs that many
    drivers of the same source (cameras cam0, cam1, ...; each at `fps`) into the one
    worker; the figures are over all of them. `web` adds a second viewer serving Rerun's web
    viewer. `duration_s` None runs a finite source to its end (and a live one until
    SIGINT/SIGTERM reaches this process). `lossless` makes the whole path lossless:
    the driver publishes with BLOCK congestion control (a real-time replay uses DROP, which
    under load dropped a frame on the worker's link while this process's copy arrived), the
    worker labels every frame (FIFO), and the drain waits for every frame seen. Raises
    TopsegError when a child fails to start.
    """
    spec = parse_spec(source)
    model = bundled_model_path() if model is None else Path(model)
    if not model.is_file():
        raise TopsegError(
            f"model file {model} does not exist (make one with scripts/make_model.sh)"
        )
    if duration_s is not None and duration_s <= 0:
        raise TopsegError(f"duration must be > 0 seconds, got {duration_s}")
    port = port or free_port()
    logs = Path(logs_dir or tempfile.mkdtemp(prefix="topseg-pipeline-"))
    logs.mkdir(parents=True, exist_ok=True)
    zenoh = ["--zenoh-port", str(port)]

    stop = threading.Event()
    old = {}
    if threading.current_thread() is threading.main_thread():  # signals only reach main
        old = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGTERM, signal.SIGINT)}
    session = open_session(port=port)
    col = _Collector()
    if cameras < 1:
        raise TopsegError(f"cameras must be >= 1, got {cameras}")
    names = camera_names(cameras)
    subs = [
        session.declare_subscriber(f"{wire.ROOT}/{CELL}/*/depth", col.on_depth),
        session.declare_subscriber(f"{wire.ROOT}/{CELL}/*/truth", col.on_truth),
        session.declare_subscriber(f"{wire.ROOT}/{CELL}/*/labels", col.on_labels),
        session.declare_subscriber(f"{wire.ROOT}/{CELL}/*/stats", col.on_stats),
    ]
    kids = Children(logs)
    codes: dict[str, int | None] = {}
    try:
        worker = ["worker", "--model", str(model), *setting_argv(config or SegmenterConfig())]
        worker += ["--cameras", *(f"{CELL}/{name}" for name in names)]
        kids.start("worker", cli_argv(*worker, *(["--lossless"] if lossless else []), *zenoh))
        if rrd is not None:
            kids.start("viewer", cli_argv("viewer", "--save", str(rrd), *zenoh))
        if web:
            kids.start("web-viewer", cli_argv("viewer", "--web", *zenoh))
        kids.wait_ready("worker", "worker ready", START_TIMEOUT_S)
        if rrd is not None:
            kids.wait_ready("viewer", "viewer ready", START_TIMEOUT_S)
        if web:
            kids.wait_ready("web-viewer", "viewer ready", START_TIMEOUT_S)
        drivers = {}
        for name in names:
            driver = ["driver", "--source", str(spec), "--cell", CELL, "--camera", name]
            if fps is not None:
                driver += ["--fps", str(fps)]
            if duration_s is not None and spec.kind == "replay":
                driver.append("--loop")
            if lossless:  # lossless end to end: a real-time driver would DROP under load
                driver += ["--congestion", "block"]
            kid = "driver" if cameras == 1 else f"driver-{name}"
            kids.start(kid, cli_argv(*driver, *zenoh))
            drivers[kid] = kids.procs[kid]
        while col.first_label_s is None and not stop.is_set():
            for kid, drv in drivers.items():
                if drv.poll() is not None and drv.returncode != 0:
                    raise TopsegError(f"{kid} exited ({drv.returncode}): {kids.tail(kid)}")
                if drv.poll() is not None and col.frames_sent == 0:
                    raise TopsegError(f"{kid} ended without a frame: {kids.tail(kid)}")
            stop.wait(0.05)
        end = None if duration_s is None else time.monotonic() + duration_s
        while not stop.is_set() and any(d.poll() is None for d in drivers.values()):
            if end is not None and time.monotonic() >= end:
                break
            stop.wait(0.05)
        for kid in drivers:
            codes[kid] = kids.stop(kid)
        _drain(col, lossless, stop)
    finally:
        for name in kids.procs:
            if name not in codes:
                codes[name] = kids.stop(name)
        for sub in subs:
            sub.undeclare()
        session.close()
        for s, handler in old.items():
            signal.signal(s, handler)

    with col.lock:
        span = (col.last_label_s or 0.0) - (col.first_label_s or 0.0)
        acc = ConfusionAccumulator()
        scored = 0
        for key, pred in col.labels.items():
            truth = col.truth.get(key)
            if truth is not None and truth.shape == pred.shape:
                acc.add(truth, pred)
                scored += 1
        return {
            "source": str(spec),
            "cameras": cameras,
            "fps": (col.n_labels - 1) / span if span > 0 else 0.0,
            "latency_p50_ms": percentile(col.latency_ms, 50),
            "latency_p99_ms": percentile(col.latency_ms, 99),
            **{
                f"worker_{stage}_p{q}_ms": percentile(col.stage_ms.get(stage, []), q)
                for stage in STAGES
                for q in (50, 99)
            },
            # this process's own subscriber can miss a depth message under load (the driver
            # drops rather than block) that the worker got: sent is at least what was labelled
            "frames_sent": max(col.frames_sent, col.n_labels),
            "frames_labelled": col.n_labels,
            "frames_scored": scored,
            "scores": acc.scores() if scored else None,
            "confusion": acc.to_dict()["confusion"] if scored else None,
            "exit_codes": codes,
            "logs": str(logs),
        }


def summary(figures: dict) -> str:
    """Two lines for an operator: throughput and latency, then F1 against the truth."""

    def ms(x):
        return "-" if x is None else f"{x:.1f} ms"

    line = (
        f"{figures['frames_labelled']}/{figures['frames_sent']} frames labelled, "
        f"{figures['fps']:.1f} fps, latency p50 {ms(figures['latency_p50_ms'])}, "
        f"p99 {ms(figures['latency_p99_ms'])}; worker per frame p50 "
        f"{ms(figures.get('worker_total_p50_ms'))}, p99 {ms(figures.get('worker_total_p99_ms'))}"
    )
    s = figures.get("scores")
    if s is None:
        return line + "\nno ground truth on this source: no F1"
    ten = s.get("avg_f1_10", s["avg_f1"])
    text = f"\nF1 against ground truth (mean of classes 1-10): {ten:.3f}"
    if not math.isclose(ten, s["avg_f1"], abs_tol=5e-4) and not math.isnan(s["avg_f1"]):
        text += f", of classes 1-12 (with robot and object): {s['avg_f1']:.3f}"
    return line + text
