"""A cell recording through the live path with the safety service: driver -> worker ->
safety, each its own process on loopback Zenoh, and the decisions scored against the
recording's truth (`core/safety/agreement.py`).

`run_cell_pipeline` starts `topseg worker` for the recording's camera, `topseg safety` with
the cell file (and `topseg viewer --save` when given an .rrd path), waits until they are
ready, then replays the recording with `topseg driver` (depth, exact labels, the robot's
joint states and the truth separations, restamped as they go). This process keeps the
safety states and, by frame, what the truth needs; when the replay ends it scores the
first decision taken on each frame against the truth's decision for that frame.
"""

from __future__ import annotations

import tempfile
import threading
import time
from collections import OrderedDict
from pathlib import Path

from topseg.core.bundled_model import bundled_model_path
from topseg.core.errors import TopsegError
from topseg.core.formats import cell_truth, safety_wire, wire
from topseg.core.formats.joint_states import decode_joint_state
from topseg.core.safety import WORKER_OPTIONS
from topseg.core.safety.agreement import (
    Compared,
    one_decision_per_frame,
    score,
    truth_decision,
    truth_nearest,
    truth_point_seen,
)
from topseg.core.safety.cell import CellConfig, load_cell
from topseg.core.safety.monitor import CellMonitor
from topseg.core.safety.robot import CellRobot
from topseg.services.batch.pipeline import START_TIMEOUT_S, Children, cli_argv, free_port
from topseg.services.runtime.zenoh_session import open_session

#: frames kept for scoring (depth and truth, ~0.3 MB a 320x240 frame)
MAX_FRAMES = 4000
#: what the static cell's background of a recording CELL.mcap is called, beside it
BACKGROUND_SUFFIX = ".background.npz"


def recording_background(recording: Path) -> Path | None:
    """The recorded static background beside a cell recording (`datagen cell-sequence`
    writes it), None without one."""
    path = Path(recording).with_suffix(BACKGROUND_SUFFIX)
    return path if path.is_file() else None


def worker_argv(model: Path, cell: str, camera: str, zenoh: list[str], background: Path | None):
    """The worker's command line for a cell recording's camera, gated by `background`, with
    the settings the safety decision's labels take (`core.safety.WORKER_OPTIONS`)."""
    gate = [] if background is None else ["--background", str(background)]
    return cli_argv("worker", "--model", str(model), "--cameras", f"{cell}/{camera}", *gate,
                    *WORKER_OPTIONS, *zenoh)  # fmt: skip


#: states kept
MAX_STATES = 100_000
DRAIN_S = 1.0


class _Collector:
    """What the pipeline published, by frame: safety states, depth, truth, joints, truth
    separations (each bounded)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.states: list[tuple[float, safety_wire.SafetyState]] = []
        self.depth: OrderedDict[int, bytes] = OrderedDict()
        self.truth: OrderedDict[int, bytes] = OrderedDict()
        self.separations: dict[int, list[dict]] = {}
        self.joints: list = []
        self.rejected = 0

    def _keep(self, table: OrderedDict, seq: int, data: bytes) -> None:
        with self.lock:
            table[seq] = data
            while len(table) > MAX_FRAMES:
                table.popitem(last=False)

    def on_state(self, sample) -> None:
        try:
            state = safety_wire.decode_safety(sample.payload.to_bytes())
        except wire.WireError:
            self.rejected += 1
            return
        with self.lock:
            if len(self.states) < MAX_STATES:
                self.states.append((time.monotonic(), state))

    def on_depth(self, sample) -> None:
        data = sample.payload.to_bytes()
        self._keep(self.depth, wire.decode_depth(data).seq, data)

    def on_truth(self, sample) -> None:
        data = sample.payload.to_bytes()
        self._keep(self.truth, wire.decode_labels(data).seq, data)

    def on_joints(self, sample) -> None:
        state = decode_joint_state(sample.payload.to_bytes())
        with self.lock:
            if len(self.joints) < MAX_STATES:
                self.joints.append(state)

    def on_separation(self, sample) -> None:
        msg = cell_truth.decode_safety_truth(sample.payload.to_bytes())
        with self.lock:
            if len(self.separations) < MAX_FRAMES:
                self.separations[int(msg["seq"])] = list(msg["persons"])


def compare(
    cell: CellConfig, robot: CellRobot | None, camera: str, col: _Collector
) -> list[Compared]:
    """Each first decision on a frame beside the truth's (frames the collector kept whole)."""
    with col.lock:
        states = [s for _, s in col.states]
        joints = sorted(col.joints, key=lambda j: j.stamp_ns)
        depth, truth, seps = dict(col.depth), dict(col.truth), dict(col.separations)
    monitor = CellMonitor(cell, robot)
    stamps = [j.stamp_ns for j in joints]
    out = []
    for state in one_decision_per_frame(states):
        cam, seq = state.frame
        if cam != camera or seq not in depth or seq not in truth or seq not in seps:
            continue
        frame = wire.decode_depth(depth[seq])
        if joints and robot is not None:
            i = min(range(len(stamps)), key=lambda k: abs(stamps[k] - frame.stamp_ns))
            monitor.set_joints(joints[i], frame.stamp_ns)
        reaction_s = (state.reaction_ms or 0.0) / 1000.0
        expected = truth_decision(monitor, [(camera, frame, wire.decode_labels(truth[seq]))],
                                  seps[seq], reaction_s)  # fmt: skip
        nearest, in_view = truth_nearest(seps[seq])
        out.append(
            Compared(
                state=state.state,
                truth_state=expected.state,
                distance_m=state.min_distance_m,
                truth_distance_m=None if nearest is None else nearest.distance_m,
                part=state.part,
                truth_part=expected.part,
                persons_in_view=in_view,
                reaction_ms=state.reaction_ms,
                truth_point_seen=truth_point_seen(nearest, [(frame, cell.camera(camera))]),
            )
        )
    return out


def run_cell_pipeline(
    recording: Path,
    cell_file: Path,
    model: Path | None = None,
    rrd: Path | None = None,
    *,
    port: int | None = None,
    logs_dir: Path | None = None,
    background: bool = True,
) -> dict:
    """Replay `recording` through driver, worker and safety (and a viewer when `rrd` is
    given) and return the scores (`agreement.score`) with the run's counts. The worker is
    gated by the recording's static background when one lies beside it and `background`."""
    recording, cell_file = Path(recording), Path(cell_file)
    for path, what in ((recording, "recording"), (cell_file, "cell file")):
        if not path.is_file():
            raise TopsegError(f"{what} {path} does not exist (make one: make cell-recording)")
    cell = load_cell(cell_file)
    background = recording_background(recording) if background else None
    robot = None if cell.robot is None else CellRobot(cell.robot, cell_file.resolve().parent)
    camera = cell.cameras[0].name
    model = bundled_model_path() if model is None else Path(model)
    port = port or free_port()
    logs = Path(logs_dir or tempfile.mkdtemp(prefix="topseg-cell-"))
    logs.mkdir(parents=True, exist_ok=True)
    zenoh = ["--zenoh-port", str(port)]
    session = open_session(port=port)
    col = _Collector()
    subs = [
        session.declare_subscriber(safety_wire.safety_key(cell.cell), col.on_state),
        session.declare_subscriber(wire.depth_key(cell.cell, camera), col.on_depth),
        session.declare_subscriber(wire.truth_key(cell.cell, camera), col.on_truth),
        session.declare_subscriber(cell_truth.safety_truth_key(cell.cell), col.on_separation),
    ]
    if cell.robot is not None:
        subs.append(session.declare_subscriber(
            cell_truth.joints_key(cell.cell, cell.robot.name), col.on_joints))  # fmt: skip
    kids = Children(logs)
    codes: dict[str, int | None] = {}
    try:
        kids.start("worker", worker_argv(model, cell.cell, camera, zenoh, background))
        kids.start("safety", cli_argv("safety", "--cell", str(cell_file), *zenoh))
        if rrd is not None:
            kids.start(
                "viewer", cli_argv("viewer", "--save", str(rrd), "--cell", str(cell_file), *zenoh)
            )
        kids.wait_ready("worker", "worker ready", START_TIMEOUT_S)
        kids.wait_ready("safety", "safety ready", START_TIMEOUT_S)
        if rrd is not None:
            kids.wait_ready("viewer", "viewer ready", START_TIMEOUT_S)
        kids.start("driver", cli_argv("driver", "--source", f"replay:{recording}", "--cell",
                                  cell.cell, "--camera", camera, *zenoh))  # fmt: skip
        driver = kids.procs["driver"]
        while driver.poll() is None:
            time.sleep(0.05)
        codes["driver"] = driver.returncode
        if driver.returncode != 0:
            raise TopsegError(f"driver exited ({driver.returncode}): {kids.tail('driver')}")
        time.sleep(DRAIN_S)
    finally:
        for name in kids.procs:
            if name not in codes:
                codes[name] = kids.stop(name)
        for sub in subs:
            sub.undeclare()
        session.close()
    figures = score(compare(cell, robot, camera, col))
    figures.update(states=len(col.states), exit_codes=codes, logs=str(logs),
                   background=None if background is None else str(background))  # fmt: skip
    return figures


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.1f} %"


def _cm(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.1f} cm"


def _ms(x: float | None) -> str:
    return "-" if x is None else f"{x:.0f} ms"


def cell_summary(figures: dict) -> str:
    """The scores as lines for people."""
    if not figures.get("frames"):
        return "no decision was taken on a frame the truth covers"
    moves = figures["states_truth_to_service"]
    return "\n".join(
        [
            f"{figures['frames']} frames decided on ({figures['states']} states published), "
            + (
                "labelled without a static background"
                if not figures.get("background")
                else f"labelled with the static background {Path(figures['background']).name}"
            ),
            f"state equal to the truth's: {_pct(figures['state_agreement'])}; clear when the "
            f"truth says stop: {figures['clear_when_truth_stop']} frames",
            "truth -> service: " + ", ".join(f"{k} {v}" for k, v in moves.items() if v),
            f"separation error p50 / p95: {_cm(figures['distance_error_p50_m'])} / "
            f"{_cm(figures['distance_error_p95_m'])} over {figures['distance_frames']} frames "
            f"(p95 {_cm(figures['distance_error_p95_seen_m'])} over the "
            f"{figures['distance_frames_seen']} whose nearest point the camera sees, "
            f"{_cm(figures['distance_error_p95_hidden_m'])} over the "
            f"{figures['distance_frames_hidden']} where it does not)",
            f"nearest part as the truth's (one person in view): {_pct(figures['part_agreement'])} "
            f"of {figures['part_frames']} frames",
            f"reaction time (depth stamp to decision) p50 / p99: {_ms(figures['reaction_p50_ms'])}"
            f" / {_ms(figures['reaction_p99_ms'])}",
        ]
    )
