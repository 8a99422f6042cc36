"""The safety path live: driver -> worker -> safety (with the viewer writing an .rrd), each its
own process on loopback Zenoh, fed the cell recording at 30 fps in a loop.

Measured, from the states this process receives:

- `reaction_p50_ms` / `reaction_p99_ms`: the service's own reaction time (the depth stamp of
  the frame decided on to the decision), over the first decision on each frame;
- `decisions_per_s` and `frames_decided_per_s`: how often it published, and on how many
  distinct frames;
- `killed_driver_stop_ms`: the driver killed (SIGKILL) at a moment this process notes, to
  the first `stop` stamped after it;
- `covered_camera_stop_ms`: a driver then replays frames with no depth (a covered lens), from
  the first such frame's stamp to the first `stop` that says the camera is blinded.

Targets: reaction p99 <= 50 ms at 30 fps on 2 cores with the viewer running; `stop` within
100 ms of a dead or covered camera.
"""

from __future__ import annotations

import argparse
import signal
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from topseg.core.bundled_model import MODEL_HELP, bundled_model_path
from topseg.core.errors import TopsegError
from topseg.core.formats import safety_wire, wire
from topseg.core.formats.recording import RecordingWriter, read_messages
from topseg.core.metrics import percentile
from topseg.core.safety.agreement import one_decision_per_frame
from topseg.core.safety.cell import load_cell
from topseg.services.batch.cell_pipeline import recording_background, worker_argv
from topseg.services.batch.demo import REPO
from topseg.services.batch.pipeline import START_TIMEOUT_S, Children, cli_argv, free_port
from topseg.services.cli.options import finite
from topseg.services.runtime.zenoh_session import open_session

#: how long the covered camera is replayed (s) and how long a stop may take to come (s)
COVERED_S = 2.0
WAIT_STOP_S = 5.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Duration, rate, recording and model."""
    parser.add_argument(
        "--duration", type=finite(1.0, 3600), default=20.0, metavar="S",
        help="seconds of the looped replay before the driver is killed (default: %(default)s)",
    )  # fmt: skip
    parser.add_argument(
        "--fps", type=finite(1.0, 120), default=30.0, help="replay rate (default: %(default)s)"
    )
    parser.add_argument(
        "--recording", type=Path, default=REPO / "recordings" / "cell.mcap", metavar="FILE",
        help="a cell recording with its cell file beside it (default: the bundled one)",
    )  # fmt: skip
    parser.add_argument("--model", type=Path, default=None, metavar="PATH", help=MODEL_HELP)
    parser.add_argument("--no-viewer", action="store_true", help="without the viewer")
    parser.add_argument(
        "--no-background", action="store_true",
        help="the worker without the recording's static background (CELL.background.npz "
        "beside it), which gates it by default",
    )  # fmt: skip


class _States:
    """The safety states received, with this process's clock at arrival."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.got: list[safety_wire.SafetyState] = []
        self.first_covered_ns: int | None = None
        # depth frames are decoded only once the covered camera's driver starts: decoding
        # every frame before would take this process's share of the cores being measured
        self.watch_depth = False

    def on_state(self, sample) -> None:
        try:
            state = safety_wire.decode_safety(sample.payload.to_bytes())
        except wire.WireError:
            return
        with self.lock:
            self.got.append(state)

    def on_depth(self, sample) -> None:
        if not self.watch_depth or self.first_covered_ns is not None:
            return
        frame = wire.decode_depth(sample.payload.to_bytes())
        if not frame.depth.any():
            with self.lock:
                self.first_covered_ns = frame.stamp_ns

    def first_stop_after(self, t_ns: int, words: str = "") -> int | None:
        with self.lock:
            for s in self.got:
                if s.stamp_ns >= t_ns and s.state == "stop" and words in " ".join(s.reasons):
                    return s.stamp_ns
        return None


def covered_recording(recording: Path, out: Path, seconds: float, fps: float) -> None:
    """A recording of the camera covered: the first depth frame of `recording`, mount kept,
    with no depth anywhere, `seconds` long at `fps`."""
    first = next(m for m in read_messages(recording) if wire.parse_key(m.key).kind == "depth")
    frame = wire.decode_depth(first.data)
    blank = np.zeros_like(frame.depth)
    with RecordingWriter(out) as writer:
        for i in range(max(1, round(seconds * fps))):
            stamp = frame.stamp_ns + round(i * 1e9 / fps)
            covered = wire.DepthFrame(
                blank, frame.intrinsics, i, stamp, frame.frame_id, frame.mount
            )
            writer.write(first.key, wire.encode_depth(covered), log_time_ns=stamp)


def _wait(predicate, timeout_s: float):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        got = predicate()
        if got is not None:
            return got
        time.sleep(0.005)
    return None


def measure(args: argparse.Namespace) -> dict:
    """Run the safety path, kill its driver, cover its camera; the figures of the module doc."""
    recording = Path(args.recording)
    cell_file = recording.with_suffix(".toml")
    if not recording.is_file() or not cell_file.is_file():
        raise TopsegError(f"no cell recording {recording} with {cell_file.name} beside it")
    cell = load_cell(cell_file)
    camera = cell.cameras[0].name
    model = bundled_model_path() if args.model is None else Path(args.model)
    port = free_port()
    zenoh = ["--zenoh-port", str(port)]
    logs = Path(tempfile.mkdtemp(prefix="topseg-bench-safety-"))
    covered = logs / "covered.mcap"
    covered_recording(recording, covered, COVERED_S, args.fps)
    session = open_session(port=port)
    states = _States()
    subs = [
        session.declare_subscriber(safety_wire.safety_key(cell.cell), states.on_state),
        session.declare_subscriber(wire.depth_key(cell.cell, camera), states.on_depth),
    ]
    kids = Children(logs)
    background = None if args.no_background else recording_background(recording)
    driver = ["--cell", cell.cell, "--camera", camera, "--fps", str(args.fps), *zenoh]
    try:
        kids.start("worker", worker_argv(model, cell.cell, camera, zenoh, background))
        kids.start("safety", cli_argv("safety", "--cell", str(cell_file), *zenoh))
        if not args.no_viewer:
            kids.start("viewer", cli_argv("viewer", "--save", str(logs / "bench.rrd"), "--cell",
                                      str(cell_file), *zenoh))  # fmt: skip
        for name, marker in (("worker", "worker ready"), ("safety", "safety ready")):
            kids.wait_ready(name, marker, START_TIMEOUT_S)
        if not args.no_viewer:
            kids.wait_ready("viewer", "viewer ready", START_TIMEOUT_S)
        kids.start(
            "driver", cli_argv("driver", "--source", f"replay:{recording}", "--loop", *driver)
        )
        time.sleep(args.duration)
        with states.lock:
            running = list(states.got)
        kids.procs["driver"].send_signal(signal.SIGKILL)
        killed_ns = time.time_ns()
        kids.procs["driver"].wait()
        killed_stop = _wait(lambda: states.first_stop_after(killed_ns), WAIT_STOP_S)
        time.sleep(0.5)  # the driver's token gone everywhere before the next one starts
        states.watch_depth = True
        kids.start("covered", cli_argv("driver", "--source", f"replay:{covered}", *driver))
        _wait(lambda: states.first_covered_ns, WAIT_STOP_S + COVERED_S)
        covered_stop = _wait(
            lambda: (
                states.first_covered_ns
                and states.first_stop_after(states.first_covered_ns, "blinded")
            ),
            WAIT_STOP_S,
        )
        kids.procs["covered"].wait(WAIT_STOP_S + COVERED_S)
    finally:
        for name in kids.procs:
            kids.stop(name)
        for sub in subs:
            sub.undeclare()
        session.close()
    running = [s for s in running if s.frame is not None]  # from the first frame on
    decided = one_decision_per_frame(running)
    reactions = [s.reaction_ms for s in decided if s.reaction_ms is not None]
    span_s = (running[-1].stamp_ns - running[0].stamp_ns) / 1e9 if len(running) > 1 else 0.0
    return {
        "fps": args.fps,
        "viewer": not args.no_viewer,
        "background": background is not None,
        "decisions_per_s": len(running) / span_s if span_s else 0.0,
        "frames_decided_per_s": len(decided) / span_s if span_s else 0.0,
        "reaction_p50_ms": percentile(reactions, 50) if reactions else None,
        "reaction_p99_ms": percentile(reactions, 99) if reactions else None,
        "killed_driver_stop_ms": None if killed_stop is None else (killed_stop - killed_ns) / 1e6,
        "covered_camera_stop_ms": (
            None if not covered_stop else (covered_stop - states.first_covered_ns) / 1e6
        ),
        "logs": str(logs),
    }
