"""Show each camera's health over a window of `--timeout` seconds: driver and worker alive
or DOWN, fps, latency p50/p99, dropped and rejected counts, the model and the mount. Exit
status 0 when every camera's driver and worker are alive, 1 when one is DOWN or no service
answered, 2 for bad arguments or no Zenoh session.

For every camera seen on Zenoh (a liveliness token, a stats message or a driver `info`
reply under `topseg/<cell>/<camera>/`, or named with `--expect`) it reports, over a window
of `--timeout` seconds:

- driver: alive (its token `.../alive/driver`), source, frames published, reconnects and
  last error (its `.../info` queryable, asked at the start and end of the window: the frame
  difference gives the driver's measured fps);
- worker: alive (`.../alive/worker`), fps, end-to-end latency p50/p99 (depth stamp to labels
  published, from the worker's stats messages in the window), processed / dropped / rejected
  counts since the worker started, the model in use, the share of pixels skipped as floor
  and the camera's mount (height, tilt, and whether it came from the frames or the worker's
  estimate; "MOVED" when the worker saw the camera move); and a line when, in the window,
  the depth's `seq` started again or jumped ahead or its stamps lay off the worker's clock
  (the worker's `seq_resets`, `seq_jumps`, `stamps_out_of_window`);
- each cell's safety service (`services/live/status_safety.py`): alive or DOWN, its state
  now, how often each state held in the window, reaction time p50/p99 and why it is not
  clear; a `stop` is the cell's state and does not change the exit status, a safety
  service that went down in the window does;
- the static cell's recorded background, when the worker has one (BG: `on`, or `MISMATCH`
  with a line saying how much of it read farther than recorded: a fixture or the camera
  moved, and the worker labels without it until it matches again).

Text from the wire (the model, the driver's source and last error) is printed escaped and
cut short (`topseg.core.printable`): escape codes, carriage returns and newlines in it cannot
forge a row or move the terminal's cursor.

Liveliness comes from a `get` at the end of the window plus a subscriber for the window, so
a service that goes away during the window shows as DOWN. A service killed outright is seen
as soon as its TCP link closes; one on a host that vanished, after Zenoh's lease (10 s).

Each process's token names its instance (`.../alive/<role>/<instance>`,
`services/runtime/identity.py`): two drivers or two workers for one camera are shown as a problem
("2 drivers: ...") with a non-zero exit, and so is depth from two drivers that a worker
dropped as `foreign`. Stats messages are told apart by the worker that sent them (its id
rides on each message): a camera's row shows one worker's figures, and stats from a second
worker are a problem line naming both, with each one's frames and fps. A worker serving every camera holds `topseg/_any/_any/alive/worker/...`
too, so one that waits for its first frame is listed as waiting, not missing.

The whole run is bounded by `--timeout` (plus up to 1 s for the final queries): a Zenoh
session that cannot open by then (the rendezvous port held by a frozen process makes Zenoh's
handshake wait 10 s) is one error line, exit 2.

Exit status: 0 when every camera has both its driver and its worker alive; 1 when any
camera's driver or worker is DOWN, its background no longer matches, or when no topseg
service was found at all; 2 for bad arguments or no Zenoh session. A camera whose services are alive but labelled no frame in
the window is shown as "idle" without changing the exit status.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import zenoh

from topseg.core.errors import TopsegError
from topseg.core.formats import wire
from topseg.core.formats.safety_wire import decode_safety
from topseg.core.metrics import percentile
from topseg.core.printable import printable
from topseg.services.cli.options import finite, parse_camera
from topseg.services.live.status_safety import (
    format_safety,
    is_safety_token,
    safety_ok,
    safety_rows,
)
from topseg.services.runtime import zenoh_session

log = logging.getLogger("topseg.status")

#: The most safety states kept per cell in one window (a cell publishes ~30 a second).
MAX_SAFETY_STATES = 100_000
#: The roles whose absence makes a camera DOWN.
REQUIRED_ROLES = ("driver", "worker")
#: the key under which a stats message keeps the id of the worker that sent it (from its
#: attachment; not a wire field)
INSTANCE_FIELD = "_instance"
#: The longest text kept from a driver's info reply (its source, its last error).
MAX_INFO_TEXT = 256
#: The widest a table cell of text from the wire (model, source) is printed, and the longest
#: such text on a line of its own (the driver's last error): escaped, then cut.
MAX_CELL = 40
MAX_LINE_TEXT = 200
#: The worker's counts of frames that did not fit the stream, and what a line says of them
#: (when they grew in the window): a restarted or foreign `seq`, stamps off the clock.
ODD_FRAME_COUNTS = ("seq_resets", "seq_jumps", "stamps_out_of_window")
ODD_FRAME_LINES = {
    "seq_resets": "the depth's seq started again {n} times (a driver restarted?)",
    "seq_jumps": "the depth's seq jumped ahead {n} times, further than the camera could count "
    "(another source on its key?); not counted as dropped",
    "stamps_out_of_window": "{n} depth frames stamped over {ahead:g} s ahead of or {age:g} s "
    "behind the worker's clock: no latency for them; are the hosts' clocks in step?",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The window, output format, watch mode, cell filter and expected cameras."""
    parser.add_argument(
        "--timeout",
        type=finite(0.1, 3600),
        default=3.0,
        metavar="S",
        help="listen this long for stats and tokens, plus up to 1 s for the final queries "
        "(default: %(default)s s)",
    )
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.add_argument(
        "--watch", action="store_true", help="report every window until interrupted"
    )
    parser.add_argument("--cell", default="*", help="only this cell (default: every cell)")
    parser.add_argument(
        "--expect",
        nargs="+",
        metavar="CELL/CAMERA",
        default=[],
        help="cameras that must be there: shown DOWN when nothing of theirs answers",
    )
    zenoh_session.add_arguments(parser)


# ---------------------------------------------------------------------------- pure part


@dataclass
class Observed:
    """What one window saw: tokens, stats messages and driver info replies, by camera."""

    alive: set = field(default_factory=set)  # (cell, camera, role) alive at the end
    instances: dict = field(default_factory=dict)  # (cell, camera, role) -> {instance ids}
    any_workers: dict = field(default_factory=dict)  # workers for every camera: id -> cameras
    went_down: set = field(default_factory=set)  # (cell, camera, role) deleted in the window
    stats: dict = field(default_factory=dict)  # (cell, camera) -> [stats dicts]
    info_start: dict = field(default_factory=dict)  # (cell, camera) -> (monotonic, info)
    info_end: dict = field(default_factory=dict)
    window_s: float = 0.0
    incomplete: list = field(default_factory=list)  # queries cut off at their deadline
    safety_alive: set = field(default_factory=set)  # cells whose safety service is alive
    safety_went_down: set = field(default_factory=set)
    safety: dict = field(default_factory=dict)  # cell -> [SafetyState] in the window


def _info_count(info: dict, name: str) -> int | None:
    """A count from a driver's info reply (whatever answered on the key): an int >= 0,
    else None."""
    value = info.get(name)
    return value if type(value) is int and value >= 0 else None


def _info_text(info: dict, name: str) -> str | None:
    """A text from a driver's info reply, cut to MAX_INFO_TEXT characters; None when it is
    not a string."""
    value = info.get(name)
    return value[:MAX_INFO_TEXT] if isinstance(value, str) else None


def _driver_report(alive: bool, start: tuple | None, end: tuple | None) -> dict:
    out: dict[str, Any] = {"alive": alive}
    info = (end or start or (None, None))[1]
    if info:
        for name in ("source", "last_error"):
            out[name] = _info_text(info, name)
        for name in ("frames", "reconnects"):
            out[name] = _info_count(info, name)
        fps = info.get("fps")
        out["nominal_fps"] = fps if type(fps) in (int, float) and math.isfinite(fps) else None
    if start and end and end[0] > start[0]:
        first, last = _info_count(start[1], "frames"), _info_count(end[1], "frames")
        if first is not None and last is not None:
            out["fps"] = max(0, last - first) / (end[0] - start[0])
    return out


def _worker_report(alive: bool, stats: list[dict]) -> dict:
    out: dict[str, Any] = {"alive": alive, "stats_messages": len(stats)}
    if not stats:
        return out
    stats = sorted(stats, key=lambda s: s["stamp_ns"])
    last = stats[-1]
    latency = [s["timings_ms"]["latency"] for s in stats if "latency" in s["timings_ms"]]
    total = [s["timings_ms"]["total"] for s in stats if "total" in s["timings_ms"]]
    out["model"] = last.get("model_id")
    out["fps"] = last.get("fps", 0.0)
    first = stats[0]
    span_s = (last["stamp_ns"] - first["stamp_ns"]) / 1e9
    done = last["counts"].get("processed", 0) - first["counts"].get("processed", 0)
    if span_s > 0 and done > 0:
        out["fps"] = done / span_s  # measured over the window, not the worker's own estimate
    out["latency_ms"] = {"p50": percentile(latency, 50), "p99": percentile(latency, 99)}
    out["processing_ms"] = {"p50": percentile(total, 50), "p99": percentile(total, 99)}
    shares = [s["floor_share"] for s in stats if "floor_share" in s]
    if shares:
        out["floor_share"] = sum(shares) / len(shares)
    if "mount" in last:
        out["mount"] = last["mount"]
    if "background" in last:
        out["background"] = last["background"]
    for name in (
        "processed",
        "dropped",
        "rejected",
        "foreign",
        "prior_cells",
        "prior_changed_px",
        "not_person_cells",
        "not_person_cell_px",
        "restored_cells",
        "restored_cell_px",
        "not_people_blobs",
        "not_people_px",
        "surface_votes_px",
        "small_heads",
        "small_furniture",
        "satellite_heads",
        "filled_holes",
        "background_px",
        "background_missing_px",
        *ODD_FRAME_COUNTS,
    ):
        out[name] = last["counts"].get(name, 0)
        out[f"{name}_in_window"] = max(0, out[name] - first["counts"].get(name, 0))
    return out


def _odd_frame_lines(worker: dict) -> list[str]:
    """A line for each count of odd frames (`ODD_FRAME_COUNTS`) that grew in the window."""

    return [
        ODD_FRAME_LINES[name].format(
            n=worker[f"{name}_in_window"], ahead=wire.STAMP_AHEAD_S, age=wire.STAMP_AGE_S
        )
        for name in ODD_FRAME_COUNTS
        if worker.get(f"{name}_in_window")
    ]


def _background_lines(worker: dict) -> list[str]:
    """A line when the worker's recorded background no longer matches its frames."""
    bg = worker.get("background")
    if not bg or bg["state"] != "mismatch":
        return []
    return [
        f"BACKGROUND MISMATCH: {100 * bg['missing_share']:.0f} % of background "
        f"{bg['id'][:12]} reads farther than recorded (over {100 * bg['mismatch_share']:.0f} "
        "%): a fixture or the camera moved; labelled without it until it matches again "
        "(record it again: topseg calibrate --background)"
    ]


def background_cell(bg: dict | None) -> str:
    """'-' without a recorded background, 'on' while it matches, 'MISMATCH' when not."""
    if not bg:
        return "-"
    return "on" if bg["state"] == "match" else "MISMATCH"


def _by_worker(stats: list[dict]) -> dict[str, list[dict]]:
    """A camera's stats messages by the worker that sent them (its instance id from the
    message's attachment; "?" for a sender without one)."""
    groups: dict[str, list[dict]] = {}
    for message in stats:
        groups.setdefault(message.get(INSTANCE_FIELD) or "?", []).append(message)
    return groups


def report(seen: Observed, expect: list[tuple[str, str]] = ()) -> dict:
    """The JSON-able status of every camera `seen` knows of (and every expected one)."""
    cameras = set(expect)
    cameras |= {(c, cam) for c, cam, _ in seen.alive | seen.went_down}
    cameras |= set(seen.stats) | set(seen.info_start) | set(seen.info_end)
    rows = []
    for cell, camera in sorted(cameras):
        roles = {r for c, cam, r in seen.alive if (c, cam) == (cell, camera)}
        driver = _driver_report(
            "driver" in roles,
            seen.info_start.get((cell, camera)),
            seen.info_end.get((cell, camera)),
        )
        # one worker's figures: counts and stamps of two workers do not mix
        senders = _by_worker(seen.stats.get((cell, camera), []))
        shown = max(senders, key=lambda i: (len(senders[i]), i)) if senders else None
        worker = _worker_report("worker" in roles, senders.get(shown, []))
        if len(senders) > 1:
            worker["instances"] = {i: _worker_report(True, g) for i, g in sorted(senders.items())}
        waiting = "worker" not in roles and bool(seen.any_workers)
        problems = [
            f"{r} DOWN"
            if not (r == "worker" and waiting)
            else f"no worker labels it yet ({len(seen.any_workers)} worker(s) serving every "
            "camera wait for its depth)"
            for r in REQUIRED_ROLES
            if r not in roles
        ]
        duplicates = {
            r: sorted(ids)
            for (c, cam, r), ids in seen.instances.items()
            if (c, cam) == (cell, camera) and len(ids) > 1
        }
        problems += [f"{len(ids)} {r}s: {', '.join(ids)}" for r, ids in sorted(duplicates.items())]
        if len(senders) > 1:
            others = ", ".join(
                f"{i}: {r['processed_in_window']} frames, {r['fps']:.1f} fps"
                for i, r in worker["instances"].items()
                if i != shown
            )
            problems.append(
                f"stats from {len(senders)} workers; the row shows {shown}'s (others: {others})"
            )
        if worker.get("foreign_in_window"):
            problems.append(
                f"depth from two drivers: the worker dropped {worker['foreign_in_window']} "
                "frames of the one it does not follow"
            )
        problems += _odd_frame_lines(worker)
        mismatch = _background_lines(worker)
        problems += mismatch
        problems += [
            f"{r} went down during the window"
            for c, cam, r in sorted(seen.went_down)
            if (c, cam) == (cell, camera) and r not in roles
        ]
        idle = not problems and worker["stats_messages"] == 0
        rows.append(
            {
                "cell": cell,
                "camera": camera,
                "ok": not any(r not in roles for r in REQUIRED_ROLES)
                and not duplicates
                and len(senders) <= 1
                and not worker.get("foreign_in_window")
                and not mismatch,
                "waiting": waiting,
                "duplicates": duplicates,
                "idle": idle,
                "driver": driver,
                "worker": worker,
                "other_roles": sorted(roles - set(REQUIRED_ROLES)),
                "problems": problems,
            }
        )
    safety = safety_rows(seen.safety_alive, seen.safety_went_down, seen.safety, seen.window_s)
    ok = bool(rows) and all(r["ok"] for r in rows) and safety_ok(safety)
    any_workers = [
        {"instance": inst, "cameras": len(cams)} for inst, cams in sorted(seen.any_workers.items())
    ]
    rep = {"window_s": round(seen.window_s, 3), "ok": ok, "cameras": rows}
    if safety:
        rep["safety"] = safety
    if any_workers:
        rep["any_camera_workers"] = any_workers
    if seen.incomplete:
        rep["incomplete"] = list(seen.incomplete)
    return rep


def observed_tokens(tokens: set, went_down: set) -> Observed:
    """Observed's token fields from (cell, camera, role, instance) entries: roles alive per
    camera, the instances of each, the workers for every camera (with how many cameras they
    hold tokens for), and the roles that went down and did not come back."""
    seen = Observed()
    any_ids = {inst for c, _, r, inst in tokens if c == wire.ANY and r == "worker" and inst}
    seen.any_workers = {inst: set() for inst in any_ids}
    for cell, camera, role, inst in tokens:
        if cell == wire.ANY:
            continue
        if is_safety_token(camera, role):
            seen.safety_alive.add(cell)
            continue
        seen.alive.add((cell, camera, role))
        seen.instances.setdefault((cell, camera, role), set()).add(inst or "?")
        if inst in seen.any_workers:
            seen.any_workers[inst].add((cell, camera))
    # a token deleted and never seen again is down; one that came back is alive
    seen.went_down = {
        (c, cam, r) for c, cam, r, _ in went_down if c != wire.ANY and not is_safety_token(cam, r)
    } - seen.alive
    seen.safety_went_down = {
        c for c, cam, r, _ in went_down if is_safety_token(cam, r)
    } - seen.safety_alive
    return seen


def exit_status(rep: dict) -> int:
    """0 when every camera is up, 1 otherwise (see the module docstring)."""
    return 0 if rep["ok"] else 1


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value:.0f}" if value >= 10 else f"{value:.1f}"


def mount_cell(mount: dict | None) -> str:
    """'3.31 m 2.1deg est' / '... frame', with ' MOVED' once the worker saw the camera move."""
    if not mount:
        return "-"
    tilt = math.degrees(
        math.acos(
            min(
                1.0,
                math.cos(math.radians(mount["pitch_deg"]))
                * math.cos(math.radians(mount["roll_deg"])),
            )
        )
    )
    source = "est" if mount["source"] == "estimated" else mount["source"]
    moved = f" MOVED x{mount['moved']}" if mount.get("moved") else ""
    return f"{mount['height_mm'] / 1000:.2f}m {tilt:.1f}deg {source}{moved}"


def format_table(rep: dict) -> str:
    """The report as a table for people: one row per camera, DOWN in capitals."""
    waiting = [
        f"worker {w['instance']} serves every camera: "
        + (f"{w['cameras']} now" if w["cameras"] else "waiting for a first depth frame")
        for w in rep.get("any_camera_workers", ())
    ]
    if not rep["cameras"]:
        if waiting:
            return "\n".join(
                [f"no camera seen in {rep['window_s']:.1f} s", *waiting, "PROBLEM: no camera"]
            )
        return f"no topseg service answered in {rep['window_s']:.1f} s (is Zenoh reachable?)"
    head = (
        "CAMERA", "DRIVER", "WORKER", "FPS", "LATENCY p50/p99 ms",
        "PROCESSED", "DROPPED", "REJECTED", "FLOOR", "MOUNT", "BG", "MODEL", "SOURCE",
        "RECONNECTS",
    )  # fmt: skip
    lines = [head]
    for row in rep["cameras"]:
        d, w = row["driver"], row["worker"]
        lat = w.get("latency_ms", {})
        fps = f"{w['fps']:.1f}" if "fps" in w else "-"
        if row["idle"]:
            fps = "idle"
        drv_fps = f" {d['fps']:.1f} fps" if d.get("fps") is not None and d["alive"] else ""
        lines.append(
            (
                f"{row['cell']}/{row['camera']}",
                ("alive" + drv_fps) if d["alive"] else "DOWN",
                "alive" if w["alive"] else "waiting" if row.get("waiting") else "DOWN",
                fps,
                f"{_ms(lat.get('p50'))}/{_ms(lat.get('p99'))}",
                str(w.get("processed", "-")),
                str(w.get("dropped", "-")),
                str(w.get("rejected", "-")),
                f"{100 * w['floor_share']:.0f}%" if "floor_share" in w else "-",
                mount_cell(w.get("mount")),
                background_cell(w.get("background")),
                printable(w.get("model") or "-", MAX_CELL),
                printable(d.get("source") or "-", MAX_CELL),
                str(d["reconnects"]) if d.get("reconnects") is not None else "-",
            )
        )
    widths = [max(len(line[i]) for line in lines) for i in range(len(head))]
    out = [
        "  ".join(c.ljust(n) for c, n in zip(line, widths, strict=True)).rstrip() for line in lines
    ]
    for row in rep["cameras"]:
        for p in row["problems"]:
            out.append(f"{row['cell']}/{row['camera']}: {p}")
        if row["driver"].get("last_error") and row["driver"]["alive"]:
            out.append(
                f"{row['cell']}/{row['camera']}: driver's last error: "
                + printable(row["driver"]["last_error"], MAX_LINE_TEXT)
            )
    out += waiting
    out += format_safety(rep.get("safety", []))
    for what in rep.get("incomplete", ()):
        out.append(f"warning: the query for {what} did not end in time; cameras may be missing")
    verdict = "all cameras up" if rep["ok"] else "PROBLEM: see the lines above"
    out.append(f"{verdict} (window {rep['window_s']:.1f} s)")
    return "\n".join(out)


# ---------------------------------------------------------------------------- Zenoh part


def _camera_of(key: str) -> tuple[str, str] | None:
    try:
        parts = wire.parse_key(key)
    except wire.WireError:
        return None
    return parts.cell, parts.camera


class Replies:
    """The replies to one `get`, gathered by a callback into a list.

    Not a channel: Zenoh's default reply channel holds 256 replies, and a liveliness `get`
    answered from the session's own table (every token it already knows of) fills it inside
    the `get` call itself, before anyone can read: with more than 256 tokens `status` would
    hang there for ever. A callback never blocks Zenoh, and `wait` gives up at its deadline.
    """

    #: How long past the query's own timeout `wait` waits for Zenoh to end the query.
    GRACE_S = 0.5

    def __init__(self, get, key: str, timeout: float) -> None:
        self.lock = threading.Lock()
        self.items: list = []  # (monotonic, reply) of the ok replies
        self.done = threading.Event()
        self.deadline = time.monotonic() + timeout + self.GRACE_S
        get(key, zenoh.handlers.Callback(self._on_reply, self.done.set), timeout=timeout)

    def _on_reply(self, reply) -> None:
        if reply.ok is None:
            return
        with self.lock:
            self.items.append((time.monotonic(), reply))

    @property
    def complete(self) -> bool:
        """Whether Zenoh ended the query (else `wait` gave up at its deadline)."""
        return self.done.is_set()

    def wait(self) -> list:
        """The replies once the query ended, or those in by the deadline."""
        self.done.wait(max(0.0, self.deadline - time.monotonic()))
        with self.lock:
            return list(self.items)


class Listener:
    """Subscribers for tokens and stats on one session; `window()` collects one Observed."""

    def __init__(self, session, cell: str) -> None:
        self.session, self.cell = session, cell
        self.lock = threading.Lock()
        self.tokens: set = set()
        self.went_down: set = set()
        self.stats: dict = {}
        self.incomplete: list[str] = []  # queries of this window cut off at their deadline
        # `alive/**`: a token of a topseg before instances (`.../alive/<role>`) counts too
        self.alive_keys = [f"topseg/{cell}/*/alive/**"]
        if cell != "*":
            self.alive_keys.append("topseg/_any/_any/alive/**")
        self._subs = [
            session.liveliness().declare_subscriber(key, self._on_token, history=True)
            for key in self.alive_keys
        ]
        self._subs.append(session.declare_subscriber(f"topseg/{cell}/*/stats", self._on_stats))
        self.safety: dict = {}
        self._subs.append(session.declare_subscriber(f"topseg/{cell}/safety", self._on_safety))

    def _on_token(self, sample) -> None:
        try:
            parts = wire.parse_key(str(sample.key_expr))
        except wire.WireError:
            return
        entry = (parts.cell, parts.camera, parts.role, parts.instance)
        with self.lock:
            if str(sample.kind).endswith("DELETE"):
                self.tokens.discard(entry)
                self.went_down.add(entry)
            else:
                self.tokens.add(entry)

    def _on_stats(self, sample) -> None:
        camera = _camera_of(str(sample.key_expr))
        if camera is None:
            return
        try:
            stats = wire.decode_stats(sample.payload.to_bytes())
        except wire.WireError:
            return  # not ours to judge: the worker counts its own rejects
        stats[INSTANCE_FIELD] = wire.instance_of(sample.attachment)
        with self.lock:
            self.stats.setdefault(camera, []).append(stats)

    def _on_safety(self, sample) -> None:
        try:
            state = decode_safety(sample.payload.to_bytes())
        except wire.WireError:
            return
        cell = str(sample.key_expr).split("/")[1]
        with self.lock:
            got = self.safety.setdefault(cell, [])
            if len(got) < MAX_SAFETY_STATES:
                got.append(state)

    def info(self, timeout: float):
        """Ask every driver's info queryable; the returned callable collects the replies as
        {(cell, camera): (monotonic, info dict)} (so other queries can go out meanwhile)."""

        def get(key, handler, timeout):  # every driver's reply, not one per key
            none = zenoh.ConsolidationMode.NONE
            self.session.get(key, handler, timeout=timeout, consolidation=none)

        got = Replies(get, f"topseg/{self.cell}/*/info", timeout)

        def collect() -> dict:
            out = {}
            for when, reply in got.wait():
                try:
                    info = json.loads(reply.ok.payload.to_bytes())
                except ValueError:
                    continue
                if not isinstance(info, dict):
                    continue
                # The driver replies on the query's key (a wildcard here): its payload names it.
                camera = _camera_of(str(reply.ok.key_expr))
                if camera is None:
                    camera = _camera_of(f"topseg/{info.get('cell')}/{info.get('camera')}/info")
                if camera is not None and (
                    camera not in out
                    or str(info.get("instance")) < str(out[camera][1].get("instance"))
                ):
                    out[camera] = (when, info)  # of two drivers, always the same one
            if not got.complete:
                self.incomplete.append("driver info")
            return out

        return collect

    def live_tokens(self, timeout: float):
        """Ask for the live tokens; the returned callable collects
        {(cell, camera, role, instance)}."""
        gets = [Replies(self.session.liveliness().get, key, timeout) for key in self.alive_keys]

        def collect() -> set:
            out = set()
            for got in gets:
                for _, reply in got.wait():
                    try:
                        parts = wire.parse_key(str(reply.ok.key_expr))
                    except wire.WireError:
                        continue
                    out.add((parts.cell, parts.camera, parts.role, parts.instance))
                if not got.complete:
                    self.incomplete.append("liveliness tokens")
            return out

        return collect

    def window(self, seconds: float, stop: threading.Event) -> Observed:
        """Listen for `seconds`; ask the drivers' info at both ends and the tokens at the end
        (those queries wait at most a third of the window, 1 s at most, for slow repliers)."""
        t0 = time.monotonic()
        with self.lock:
            self.stats, self.went_down, self.safety = {}, set(), {}
        self.incomplete = []
        query_s = max(0.2, min(1.0, seconds / 3))
        start = self.info(query_s)()
        stop.wait(max(0.0, seconds - (time.monotonic() - t0)))
        end_info, end_tokens = self.info(query_s), self.live_tokens(query_s)
        end, live = end_info(), end_tokens()
        with self.lock:
            tokens = self.tokens | live
            seen = observed_tokens(tokens, self.went_down)
            seen = Observed(
                alive=seen.alive,
                instances=seen.instances,
                any_workers=seen.any_workers,
                went_down=seen.went_down,
                stats={k: list(v) for k, v in self.stats.items()},
                info_start=start,
                info_end=end,
                incomplete=sorted(set(self.incomplete)),
                window_s=time.monotonic() - t0,
                safety_alive=seen.safety_alive,
                safety_went_down=seen.safety_went_down,
                safety={k: list(v) for k, v in self.safety.items()},
            )
        return seen

    def close(self) -> None:
        """Undeclare the subscribers."""
        for sub in self._subs:
            sub.undeclare()


def _expected(entries: list[str]) -> list[tuple[str, str]]:
    return [parse_camera(e) for e in entries]


def run(args: argparse.Namespace) -> int:
    """Watch the window(s) and print the report; the exit status says whether all is up."""
    if not args.timeout > 0:
        raise TopsegError(f"--timeout must be > 0, got {args.timeout}")
    if args.cell != "*":
        try:
            wire.camera_prefix(args.cell, "x")
        except wire.WireError as exc:
            raise TopsegError(str(exc)) from None
    expect = _expected(args.expect)
    stop = threading.Event()
    t0 = time.monotonic()
    config = zenoh_session.config_from_args(args)
    try:  # Zenoh's own handshake timeout is 10 s: open within the window (+ the query grace)
        session = zenoh_session.open_within(config, args.timeout + 1.0)
    except zenoh_session.OpenTimeout as exc:
        from topseg.services.cli import fail

        fail("status", exc)
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(2)  # see OpenTimeout: a normal exit would abort inside Zenoh
    try:
        listener = Listener(session, args.cell)
        zenoh_session.wait_connected(session, min(1.0, args.timeout / 3))
        rc = 1
        # the first window gives back what opening took, so the run stays within --timeout
        window = max(0.1, args.timeout - (time.monotonic() - t0))
        while True:
            try:
                rep = report(listener.window(window, stop), expect)
                window = args.timeout
            except KeyboardInterrupt:
                break
            rc = exit_status(rep)
            if args.json:
                print(json.dumps(rep), flush=True)
            else:
                if args.watch and sys.stdout.isatty():
                    print("\033[H\033[2J", end="")
                print(time.strftime("%H:%M:%S"), format_table(rep), sep="\n", flush=True)
            if not args.watch:
                break
        listener.close()
    finally:
        session.close()
    return rc
