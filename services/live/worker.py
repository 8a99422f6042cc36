"""Label depth frames from Zenoh: for every camera it serves (all of `topseg/*/*/depth`, or
`--cameras`) it runs the forest and the CRF on the newest frame, through the camera's mount
(the one the frames carry, or one it estimates and re-checks), and publishes labels and
stats (ms per stage, fps, counts). A slow worker skips frames rather than queue them;
`--lossless` labels every frame.

For every camera it serves (all of `topseg/*/*/depth`, or the `--cameras` given) the worker
runs the forest and the CRF on the newest depth frame and publishes

- labels on `topseg/<cell>/<camera>/labels` (the depth frame's `seq`, `stamp_ns`, `frame_id`);
- stats on `.../stats`: ms per step (receive = copy + decode, mount = estimating or checking
  the mount, forest and crf = the Segmenter's two headline figures, `stage_<name>` = each of
  its stages, publish, total), latency (depth stamp to labels published), fps, the counts
  processed / dropped / rejected / seq_resets (a `seq` not above the last one: a restarted
  driver) / seq_jumps (a `seq` further ahead than the camera could have counted since,
  `MAX_SEQ_RATE`: not counted as dropped) / stamps_out_of_window (stamps over 1 s ahead of
  the worker's clock or 60 s behind it: no latency for those frames) and every counter the
  Segmenter's stages keep (`Segmenter.counter_names`), the share of pixels the floor gate
  skipped (`floor_share`) and the mount in use (`mount`: height, pitch, roll, sensor, source
  "frame" | "estimated", times the camera was seen to move).

Each frame is labelled with its camera's mount (`services/live/worker_mount.py`): the one the
frames carry (`topseg driver --mount`), or, when they carry none, one the worker estimates
from the camera's first frames (those frames wait for it, a second at most) and logs. The
mount is checked again every `--mount-check` seconds against an estimate from the newest
frames; a camera that moved is logged as a warning ("camera cell/cam0 moved: height 3.31 ->
3.12 m ..."), counted in the stats and labelled with the new estimate. A camera whose mount
lies outside what the model was trained for is warned about once.

With a recorded background (`--background FILE`, from `topseg calibrate --background`; one
camera's, so the worker then serves exactly one `--cameras` entry) pixels that match the
static cell go to background without the forest, and each labels message carries the
background's id. When the frames no longer match it (a share of its pixels, more than
`--background-mismatch`, read farther than it for several frames: a fixture or the camera
moved), the worker logs one warning, labels without it until it matches again (logged too)
and its stats say so (`background`: id, state, the share missing), which `topseg status`
shows (`services/live/worker_background.py`).

Only the newest frame is kept: one `zenoh.handlers.RingChannel(1)` per camera, so a slow
worker skips frames and its memory never grows. Skipped frames are counted from gaps in
`seq`. `--lossless` uses a FIFO instead (tests, offline labelling of a replay). Messages that
do not decode (or that the forest cannot take) are dropped, counted as `rejected` and logged;
they never stop the worker; nor does depth on a key that names no camera (`_any/_any`, the
chunks of the token below, or a name the wire format refuses): dropped, counted in the
status line and warned about at most every 10 s. Without `--cameras`, a camera is served
from its first depth message on (that message only announces it; the ring subscriber takes
the next one).

A flood of camera names is bounded: without `--cameras` at most `--max-cameras` discovered
cameras are served at once; names beyond it are ignored, counted (in the status line) and
warned about at most every 10 s. A discovered camera that sent no depth for `--forget-after`
seconds is released (its publishers, token and subscriber undeclared, its state dropped;
logged), so names that came once do not cost memory and threads forever; it is served
again from its next message. Cameras named with `--cameras` are never limited or forgotten.

It holds `topseg/<cell>/<camera>/alive/worker/<instance>` for each camera it serves (its
Zenoh id, `services/runtime/identity.py`, also the attachment of its labels and stats) and, without
`--cameras`, `topseg/_any/_any/alive/worker/<instance>`, so that `topseg status` shows it
while it waits for a first frame. It stops cleanly on SIGTERM/SIGINT. A missing or damaged
model file stops it before it joins Zenoh (exit 2).

One camera, one worker, one driver. A worker whose `--cameras` are already labelled by
another worker refuses to start (one line, exit 2); a discovered camera that another worker
labels is left to it (two discovering workers: the one with the smaller instance id keeps
it); a named camera another worker takes later is warned about. Depth from two drivers on
one key (their attachments name two instances) is not labelled alternately: the worker
follows one driver, drops the other's frames, counts them as `foreign` and warns; it turns
to another driver only when the one it follows is gone (its token deleted: a driver killed
and restarted) or was silent for `SOURCE_SWITCH_S`.
"""

from __future__ import annotations

import argparse
import logging
import math
import threading
import time
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import zenoh

from topseg.core.bundled_model import MODEL_HELP
from topseg.core.errors import TopsegError
from topseg.core.formats import wire
from topseg.core.printable import printable
from topseg.core.segmenter import Segmenter
from topseg.core.segmenter_config import SegmenterConfig
from topseg.services.cli.options import (
    add_segmenter_arguments,
    finite,
    int_range,
    parse_camera,
    segmenter_config,
)
from topseg.services.live.worker_background import MISMATCH, BackgroundWatch
from topseg.services.live.worker_mount import MountWatch, MountWatchConfig
from topseg.services.live.worker_mount import warm_up as mount_warm_up
from topseg.services.runtime import identity, zenoh_session
from topseg.services.runtime.lifecycle import ServiceLifecycle

if TYPE_CHECKING:
    from topseg.core.segmenter import Segmenter

log = logging.getLogger("topseg.worker")

#: FIFO depth in --lossless mode: a full FIFO holds Zenoh back (the publisher waits).
LOSSLESS_QUEUE = 64
#: At most one "camera limit reached" warning this often (s).
LIMIT_WARN_S = 10.0
#: Distinct ignored camera names remembered for counting (beyond it, messages still count).
MAX_IGNORED_NAMES = 4096
#: Smoothing of the fps estimate (weight of the newest interval).
FPS_ALPHA = 0.2
#: A camera's depth comes from another driver instance: taken as a restart only when the
#: followed one was silent this long (s); before, the newcomer's frames are foreign.
SOURCE_SWITCH_S = 1.0
#: At most one warning about another worker on a camera this often (s).
DUPLICATE_WARN_S = 10.0
#: A worker that keeps a camera another worker took too waits this long for the other one
#: to step back (two workers serving every camera settle on one) before it warns (s).
CONTEST_GRACE_S = 5.0
#: The most frames a second a camera is taken to send (a driver's --fps is 1000 at most):
#: a forward step in `seq` larger than this rate allows since the last labelled frame
#: (plus one second) is counted as a jump (`seq_jumps`), not as that many dropped frames.
MAX_SEQ_RATE = 10_000


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The worker's options: the model, the CRF, the cameras, --lossless and Zenoh."""
    parser.add_argument("--model", metavar="PATH", help=MODEL_HELP)
    add_segmenter_arguments(parser)
    parser.add_argument(
        "--threads",
        type=int_range(0, 256),
        default=0,
        metavar="N",
        help="threads of the forest's kernels (default 0: one per core); on a machine shared "
        "with a driver, 1 can hold latency better (docs/performance.md)",
    )
    parser.add_argument(
        "--cameras",
        nargs="+",
        metavar="CELL/CAMERA",
        help="serve only these cameras (default: every camera seen on topseg/*/*/depth)",
    )
    parser.add_argument(
        "--max-cameras",
        type=int_range(1, 100000),
        default=32,
        metavar="N",
        help="without --cameras, serve at most this many discovered cameras at once; names "
        "beyond it are ignored and counted (default: %(default)s)",
    )
    parser.add_argument(
        "--forget-after",
        type=finite(0, 1e9),
        default=60.0,
        metavar="S",
        help="release a discovered camera that sent no depth for this long; 0 = never "
        "(default: %(default)s s)",
    )
    parser.add_argument(
        "--mount-check",
        type=finite(0, 1e6),
        default=30.0,
        metavar="S",
        help="re-estimate each camera's mount from its newest frames this often, to catch a "
        "camera that was bumped; 0 = never (default: %(default)s s)",
    )
    parser.add_argument(
        "--sensor",
        metavar="NAME",
        help="sensor named in mounts the worker estimates (default: guessed from the frames' "
        "size and focal length)",
    )
    parser.add_argument(
        "--lossless",
        action="store_true",
        help="label every frame (FIFO) instead of only the newest one per camera",
    )
    zenoh_session.add_arguments(parser)


@dataclass
class CameraState:
    """Per-camera bookkeeping: publishers, token, counts, the last seq and the fps estimate."""

    cell: str
    camera: str
    labels_pub: Any = None
    stats_pub: Any = None
    token: Any = None
    subscriber: Any = None
    counts: dict = field(
        default_factory=lambda: {
            "processed": 0,
            "dropped": 0,
            "rejected": 0,
            "seq_resets": 0,
            "seq_jumps": 0,
            "stamps_out_of_window": 0,
        }
    )
    last_seq: int | None = None
    last_seq_time: float = 0.0  # when last_seq was labelled (monotonic)
    last_time: float | None = None
    fps: float = 0.0
    watch: MountWatch | None = None
    background: BackgroundWatch | None = None  # whether frames match the recorded background
    warned_outside: bool = False
    downsample: int = 0  # the factor its frames were last labelled at (0: none yet)
    discovered: bool = False  # served because its depth came (not named by --cameras)
    last_seen: float = field(default_factory=time.monotonic)  # last depth message taken
    source: str | None = None  # the driver instance whose depth this camera follows
    source_seen: float = 0.0  # when its last frame was taken (monotonic)
    last_duplicate_warning: float = -math.inf
    contested_since: float | None = None  # another worker took it too (monotonic); None: not
    contested_by: tuple[str, ...] = ()  # the workers that took it too
    stamp_sides_said: set = field(default_factory=set)  # "ahead", "behind": logged once each

    def follow(self, source: str | None, now: float, followed_gone: bool = False) -> bool:
        """Whether a depth message from driver instance `source` is this camera's: the one
        followed, a first one, or a new one once the followed one is gone (`followed_gone`:
        its token was deleted) or fell silent (a restart; logged). Another driver's frames
        meanwhile are counted as `foreign` and warned about; None (no attachment: an older
        topseg) is always taken."""
        if source is None:
            return True
        silent = now - self.source_seen > SOURCE_SWITCH_S
        if self.source is None or source == self.source or followed_gone or silent:
            if self.source not in (None, source):
                log.info(
                    "%s/%s: depth now from driver %s (driver %s %s)",
                    self.cell,
                    self.camera,
                    source,
                    self.source,
                    "gone" if followed_gone else f"silent {now - self.source_seen:.1f} s",
                )
                self.last_seq = None  # a new source's seq starts afresh
            self.source, self.source_seen = source, now
            return True
        n = self.counts["foreign"] = self.counts.get("foreign", 0) + 1
        if n == 1 or n % 100 == 0:
            log.warning(
                "TWO DRIVERS publish %s/%s: following %s, dropping the frames of %s "
                "(%d dropped); stop one of them",
                self.cell,
                self.camera,
                self.source,
                source,
                n,
            )
        return False

    def note_seq(self, seq: int, now: float) -> None:
        """Count the frames skipped between the last labelled seq and this one (`now`:
        monotonic s). A seq that is not larger (a restarted source) counts as a reset; a
        step larger than the camera could have sent since (MAX_SEQ_RATE) as a jump; neither
        as dropped frames, so one odd frame cannot spoil `dropped` for good."""
        last, self.last_seq = self.last_seq, seq
        then, self.last_seq_time = self.last_seq_time, now
        if last is None:
            return
        if seq <= last:
            self.counts["seq_resets"] += 1
        elif seq - last - 1 > MAX_SEQ_RATE * (now - then + 1.0):
            self.counts["seq_jumps"] += 1
        else:
            self.counts["dropped"] += seq - last - 1

    def latency_ms(self, stamp_ns: int, now_ns: int) -> float | None:
        """Depth stamp to `now_ns` in ms; None (and counted as `stamps_out_of_window`; the
        first ahead, the first behind and every hundredth logged) for a stamp outside the
        sane window (wire.STAMP_AHEAD_S, wire.STAMP_AGE_S): a clock skew is said, not hidden as 0."""
        age_s = (now_ns - stamp_ns) / 1e9
        if -wire.STAMP_AHEAD_S <= age_s <= wire.STAMP_AGE_S:
            return max(0.0, 1000 * age_s)
        n = self.counts["stamps_out_of_window"] = self.counts["stamps_out_of_window"] + 1
        side = "ahead" if age_s < 0 else "behind"
        if side not in self.stamp_sides_said or n % 100 == 0:
            self.stamp_sides_said.add(side)
            log.warning(
                "%s/%s: a depth frame stamped %s this host's clock: its latency is not "
                "measured; are the hosts' clocks in step? (%d such frames)",
                self.cell,
                self.camera,
                f"{-age_s:.3g} s ahead of" if age_s < 0 else f"{age_s:.3g} s behind",
                n,
            )
        return None

    def note_done(self, now: float) -> None:
        """Update the fps estimate with the time since the last labelled frame."""
        if self.last_time is not None and now > self.last_time:
            rate = 1.0 / (now - self.last_time)
            self.fps = rate if self.fps == 0.0 else (1 - FPS_ALPHA) * self.fps + FPS_ALPHA * rate
        self.last_time = now


class Worker:
    """The serving loop: subscribers, per-camera state and the publish side.

    Depth arrives in Zenoh's own handlers: a RingChannel(1) per camera, which keeps the
    newest frame without ever taking Python's GIL (the forest's kernels hold it for a whole
    frame), or a FIFO with --lossless. A callback subscriber on the same keys, the doorbell,
    only notes that something came (and which new cameras appeared) and notifies one
    Condition; the main thread waits on it, then takes one sample per camera from the
    handlers and labels it. Frames are never labelled on Zenoh's threads.
    """

    def __init__(self, args: argparse.Namespace, session, segmenter: Segmenter) -> None:
        self.args, self.session, self.segmenter = args, session, segmenter
        self.me = identity.Identity.of(session)
        self.attachment = wire.instance_attachment(self.me.instance)
        self.mount_config = mount_config(args)
        self.cameras: dict[tuple[str, str], CameraState] = {}
        self.depth_keys: dict[str, tuple[str, str]] = {}  # the doorbell's cache of served keys
        self.bell = threading.Condition()
        self.rung = False  # something arrived (or a stop) since the main loop last looked
        self.announced: set[tuple[str, str]] = set()  # new cameras, for the main loop to serve
        self.shared_sub = None  # --lossless without --cameras: one FIFO on the wildcard
        self.doorbells: list[Any] = []
        self.max_cameras = getattr(args, "max_cameras", 32)
        self.forget_after = getattr(args, "forget_after", 60.0)
        self.ignored: set[tuple[str, str]] = set()  # names beyond --max-cameras
        self.ignored_messages = 0
        self.last_limit_warning = -math.inf
        self.next_sweep = time.monotonic()
        self.forgotten = 0
        self.other_workers: dict[tuple[str, str], set[str]] = {}  # under self.bell
        self.contested: set[tuple[str, str]] = set()  # another worker appeared (self.bell)
        self.left_to_others: set[tuple[str, str]] = set()  # said once each
        self.bad_keys = 0  # depth messages on keys that name no camera (under self.bell)
        self.last_bad_key: tuple[str, str] | None = None  # (key, why) of the newest one
        self.bad_keys_said = 0  # how many the last warning counted
        self.last_bad_key_warning = -math.inf
        self.any_token = None
        self.congestion = (
            zenoh.CongestionControl.BLOCK if args.lossless else zenoh.CongestionControl.DROP
        )
        wanted = [parse_camera(c) for c in args.cameras or ()]
        # discovery: without --cameras a camera is served from its first depth message on
        self.discover = not wanted and not args.lossless
        self.gone_drivers: dict[str, None] = {}  # tokens deleted, newest last (bounded)
        self.token_watch = session.liveliness().declare_subscriber(
            "topseg/*/*/alive/*/*", self._on_token, history=True
        )
        for cell, camera in wanted:
            self.serve(cell, camera, own_subscriber=True)
        if not wanted:
            self.any_token = session.liveliness().declare_token(
                wire.any_alive_key("worker", self.me.instance)
            )
            if args.lossless:
                self.shared_sub = session.declare_subscriber(
                    "topseg/*/*/depth", zenoh.handlers.FifoChannel(LOSSLESS_QUEUE)
                )
            self.doorbells.append(session.declare_subscriber("topseg/*/*/depth", self._ring))

    def _ring(self, sample) -> None:
        """Zenoh's callback thread: note that depth came, and from which new camera; wake
        the main loop. Never decodes or labels (that is the main thread's job)."""
        key = str(sample.key_expr)
        new = None
        if self.discover and key not in self.depth_keys:
            try:
                parts = wire.parse_key(key)
            except wire.WireError as exc:
                self.note_bad_key(key, exc)
                return
            new = (parts.cell, parts.camera)
        with self.bell:
            self.rung = True
            if new is not None and len(self.announced) < self.max_cameras + MAX_IGNORED_NAMES:
                self.announced.add(new)  # bounded: the main loop refuses and counts the excess
            self.bell.notify()

    def note_bad_key(self, key: str, why: Exception) -> None:
        """Count a depth message on a key that names no camera (`_any/_any`, reserved for
        the tokens of workers like this one, or a name the wire format refuses); the main
        loop warns about them (`warn_bad_keys`). Such a message is dropped, never served."""
        with self.bell:
            self.bad_keys += 1
            self.last_bad_key = (key, str(why))
            self.rung = True
            self.bell.notify()

    def warn_bad_keys(self) -> None:
        """Warn about new depth messages on keys that name no camera, at most every
        LIMIT_WARN_S (the key shown escaped and cut short)."""
        now = time.monotonic()
        with self.bell:
            count, last = self.bad_keys, self.last_bad_key
        if count == self.bad_keys_said or now - self.last_bad_key_warning < LIMIT_WARN_S:
            return
        self.bad_keys_said, self.last_bad_key_warning = count, now
        log.warning(
            "dropped depth on %s: %s (%d messages on keys that name no camera so far)",
            printable(last[0]),
            printable(last[1]),
            count,
        )

    def _on_token(self, sample) -> None:
        """Zenoh's callback thread: note drivers that went away (a camera following one may
        take the next driver's frames at once) and other workers' tokens per camera (a new
        one on a camera is looked at by the main loop, `settle_contested`)."""
        try:
            parts = wire.parse_key(str(sample.key_expr))
        except wire.WireError:
            return
        if parts.instance in (None, self.me.instance) or parts.cell == wire.ANY:
            return
        if parts.role == "driver":
            with self.bell:
                if str(sample.kind).endswith("DELETE"):
                    self.gone_drivers[parts.instance] = None
                    while len(self.gone_drivers) > MAX_IGNORED_NAMES:
                        del self.gone_drivers[next(iter(self.gone_drivers))]
                else:
                    self.gone_drivers.pop(parts.instance, None)
            return
        if parts.role != "worker":
            return
        camera = (parts.cell, parts.camera)
        with self.bell:
            others = self.other_workers.setdefault(camera, set())
            if str(sample.kind).endswith("DELETE"):
                others.discard(parts.instance)
                if not others:
                    del self.other_workers[camera]
                    self.left_to_others.discard(camera)
            else:
                others.add(parts.instance)
                self.contested.add(camera)
            self.rung = True
            self.bell.notify()

    def labelled_elsewhere(self, camera: tuple[str, str]) -> set[str]:
        """The other workers holding a token for `camera` now."""
        with self.bell:
            return set(self.other_workers.get(camera, ()))

    def settle_contested(self) -> None:
        """Another worker took a token for a camera served here: a discovered camera goes to
        the worker with the smaller instance id; a named one stays. A worker that keeps the
        camera warns loudly only if the other one still labels it CONTEST_GRACE_S later
        (`check_duplicates`): two workers serving every camera settle before that."""
        with self.bell:
            contested, self.contested = self.contested, set()
        now = time.monotonic()
        for camera in sorted(contested):
            state, others = self.cameras.get(camera), self.labelled_elsewhere(camera)
            if state is None or not others:
                continue
            if state.discovered and min(others) < self.me.instance:
                self.release(state)
                self.left_to_others.add(camera)
                log.warning(
                    "worker %s labels %s/%s too; leaving that camera to it",
                    min(others),
                    *camera,
                )
            elif state.contested_since is None:  # the other may step back: wait and see
                state.contested_since = now
                log.info(
                    "worker %s took %s/%s too; this worker keeps it%s",
                    ", ".join(sorted(others)),
                    *camera,
                    " (the smaller instance id)" if state.discovered else " (--cameras)",
                )
            state.contested_by = tuple(sorted(others))
        self.check_duplicates(now)

    def check_duplicates(self, now: float) -> None:
        """For each camera kept here that another worker took too: once the other is gone
        (it stepped back, or stopped), say so; while it stays past CONTEST_GRACE_S, warn
        loudly, every DUPLICATE_WARN_S."""
        for state in list(self.cameras.values()):
            if state.contested_since is None:
                continue
            camera = (state.cell, state.camera)
            others = self.labelled_elsewhere(camera)
            if not others:
                log.info(
                    "worker %s no longer labels %s/%s: labelled by this worker only",
                    ", ".join(state.contested_by),
                    *camera,
                )
                state.contested_since, state.contested_by = None, ()
            elif (
                now - state.contested_since >= CONTEST_GRACE_S
                and now - state.last_duplicate_warning >= DUPLICATE_WARN_S
            ):
                state.last_duplicate_warning = now
                log.warning(
                    "ANOTHER WORKER labels %s/%s too: %s; both publish labels for it: stop "
                    "one, or take the camera out of its --cameras",
                    *camera,
                    ", ".join(sorted(others)),
                )

    def seconds_to_duplicate_check(self) -> float | None:
        """Until a contested camera's next check is due (`check_duplicates`); None: none."""
        due = [
            max(s.contested_since + CONTEST_GRACE_S, s.last_duplicate_warning + DUPLICATE_WARN_S)
            for s in self.cameras.values()
            if s.contested_since is not None
        ]
        return max(0.0, min(due) - time.monotonic()) if due else None

    def wake(self) -> None:
        """Wake the main loop now (a stopping signal)."""
        with self.bell:
            self.rung = True
            self.bell.notify()

    def wait(self, timeout: float) -> None:
        """Block until the doorbell rang since the last wait, or `timeout` s."""
        with self.bell:
            if not self.rung:
                self.bell.wait(timeout)
            self.rung = False

    def discovered_count(self) -> int:
        """How many cameras are served because their depth came."""
        return sum(1 for s in self.cameras.values() if s.discovered)

    def admissible(self, cell: str, camera: str) -> bool:
        """Whether a newly seen camera is served here: not while another worker labels it
        (said once), and within --max-cameras (`admit`)."""
        others = self.labelled_elsewhere((cell, camera))
        if others:
            if (cell, camera) not in self.left_to_others:
                self.left_to_others.add((cell, camera))
                log.info(
                    "%s/%s is labelled by worker %s; not serving it", cell, camera, min(others)
                )
            return False
        return self.admit(cell, camera)

    def admit(self, cell: str, camera: str) -> bool:
        """Whether a newly seen camera may be served (--max-cameras); counts and warns (at
        most every LIMIT_WARN_S) about the ones that may not."""
        if self.discovered_count() < self.max_cameras:
            return True
        self.ignored_messages += 1
        if len(self.ignored) < MAX_IGNORED_NAMES:
            self.ignored.add((cell, camera))
        now = time.monotonic()
        if now - self.last_limit_warning >= LIMIT_WARN_S:
            self.last_limit_warning = now
            log.warning(
                "camera limit reached (--max-cameras %d): ignoring %s/%s; %d camera names "
                "ignored so far",
                self.max_cameras,
                cell,
                camera,
                len(self.ignored),
            )
        return False

    def forget_idle(self) -> None:
        """Release the discovered cameras that sent no depth for --forget-after seconds
        (checked at most a few times a second)."""
        now = time.monotonic()
        if not self.forget_after > 0 or now < self.next_sweep:
            return
        self.next_sweep = now + min(1.0, self.forget_after / 4)
        for state in list(self.cameras.values()):
            idle = now - state.last_seen
            if state.discovered and idle > self.forget_after:
                self.release(state)
                self.forgotten += 1
                log.info(
                    "released %s/%s: no depth for %.0f s (counts %s)",
                    state.cell,
                    state.camera,
                    idle,
                    state.counts,
                )

    def release(self, state: CameraState) -> None:
        """Stop serving one camera: undeclare its token, subscriber and publishers."""
        self.cameras.pop((state.cell, state.camera), None)
        self.depth_keys.pop(wire.depth_key(state.cell, state.camera), None)
        for entity in (state.token, state.subscriber, state.labels_pub, state.stats_pub):
            if entity is not None:
                entity.undeclare()
        state.token = state.subscriber = state.labels_pub = state.stats_pub = None

    def serve(self, cell: str, camera: str, own_subscriber: bool) -> CameraState:
        """Start serving one camera: publishers, liveliness token, maybe its own subscriber."""
        state = CameraState(cell, camera, discovered=not self.args.cameras)
        state.counts.update(dict.fromkeys(self.segmenter.counter_names, 0))
        state.watch = MountWatch(f"{cell}/{camera}", self.mount_config)
        if self.segmenter.background is not None:
            state.background = BackgroundWatch(
                self.segmenter.background_id, self.segmenter.config.background
            )
        publish = dict(congestion_control=self.congestion, express=True)
        state.labels_pub = self.session.declare_publisher(wire.labels_key(cell, camera), **publish)
        state.stats_pub = self.session.declare_publisher(wire.stats_key(cell, camera), **publish)
        key = wire.depth_key(cell, camera)
        if own_subscriber:
            handler = (
                zenoh.handlers.FifoChannel(LOSSLESS_QUEUE)
                if self.args.lossless
                else zenoh.handlers.RingChannel(1)
            )
            state.subscriber = self.session.declare_subscriber(key, handler)
            if self.args.cameras:  # without, the wildcard doorbell covers discovered cameras
                self.doorbells.append(self.session.declare_subscriber(key, self._ring))
        state.token = self.session.liveliness().declare_token(
            wire.alive_key(cell, camera, "worker", self.me.instance)
        )
        self.cameras[(cell, camera)] = state
        self.depth_keys[key] = (cell, camera)
        background = self.segmenter.background_id
        log.info(
            "serving %s/%s (crf %s%s)",
            cell,
            camera,
            self.segmenter.crf_mode,
            f", background {background[:12]}" if background else "",
        )
        return state

    def handle_ready(self) -> bool:
        """Serve new cameras, then label one sample of each handler that has one; False when
        none had."""
        with self.bell:
            new, self.announced = self.announced, set()
        self.warn_bad_keys()
        self.settle_contested()
        for cell, camera in sorted(new):
            if (cell, camera) not in self.cameras and self.admissible(cell, camera):
                self.serve(cell, camera, own_subscriber=True)
        self.forget_idle()
        busy = self.handle_due()
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

    def serve_until_stopped(self, svc: ServiceLifecycle) -> None:
        """The main loop: label what is ready, else block until the doorbell rings (or the
        heartbeat is due, or a stopping signal comes)."""
        svc.on_stop(self.wake)
        while not svc.stopping:
            svc.beat()  # watchdog ping from the serving loop, STATUS= every few s
            if not self.handle_ready():
                due = [s.watch.seconds_to_due() for s in self.cameras.values()]
                due = [d for d in (*due, self.seconds_to_duplicate_check()) if d is not None]
                if self.forget_after > 0 and self.discovered_count():
                    due.append(max(0.0, self.next_sweep - time.monotonic()))
                self.wait(min([svc.tick, *due]))

    def handle_due(self) -> bool:
        """Label the frames that waited for a first mount estimate whose time is up."""
        busy = False
        for state in list(self.cameras.values()):
            if state.watch.due():
                t0 = time.perf_counter()
                self.label_all(state, state.watch.flush(), t0, t0)
                busy = True
        return busy

    def handle(self, sample, state: CameraState | None) -> None:
        """Decode, label and publish one depth message; count and drop what is not one."""
        t0 = time.perf_counter()
        if state is None:  # the shared FIFO: the key says which camera
            try:
                parts = wire.parse_key(str(sample.key_expr))
            except wire.WireError as exc:
                self.note_bad_key(str(sample.key_expr), exc)
                return
            state = self.cameras.get((parts.cell, parts.camera))
            if state is None:
                if not self.admissible(parts.cell, parts.camera):
                    return
                state = self.serve(parts.cell, parts.camera, own_subscriber=False)
        state.last_seen = time.monotonic()
        with self.bell:
            gone = state.source in self.gone_drivers
        if not state.follow(wire.instance_of(sample.attachment), state.last_seen, gone):
            self.publish_stats(state, {})  # a second driver on this key: counted, dropped
            return
        try:
            frame = wire.decode_depth(sample.payload.to_bytes())
        except wire.WireError as exc:
            self.reject(state, f"bad depth message: {exc}")
            return
        t1 = time.perf_counter()
        released = state.watch.take(frame)  # may estimate or re-check the mount
        self.label_all(state, released, t0, t1)

    def label_all(self, state: CameraState, frames: list, t0: float, t1: float) -> None:
        """Label what the camera's mount watch released (`t0`: the message was taken, `t1`:
        decoded; now the mount is settled): all of it with --lossless, else only the newest
        (the others count as dropped)."""
        if frames and not self.args.lossless:
            frames = frames[-1:]
        for frame in frames:
            self.label_one(state, frame, t0, t1, time.perf_counter())
            t0 = t1 = time.perf_counter()

    def label_one(self, state: CameraState, frame, t0: float, t1: float, tm: float) -> None:
        """Label one decoded frame with the camera's mount and publish labels and stats
        (`t0` taken, `t1` decoded, `tm` mount settled: perf_counter seconds)."""
        mount = state.watch.mount
        if mount is not None and not state.warned_outside:
            why = self.segmenter.outside_trained_for(mount)
            if why:
                state.warned_outside = True
                log.warning(
                    "camera %s/%s lies outside what model %s was trained for: %s; its labels "
                    "may be poor",
                    state.cell,
                    state.camera,
                    self.segmenter.model_id,
                    why,
                )
        gate = state.background is None or state.background.gate
        try:
            result = self.segmenter.label(
                frame.depth, frame.intrinsics, f"frame {frame.seq}", mount, gate
            )
        except Exception as exc:  # a well-formed frame the forest or CRF cannot take
            self.reject(state, f"cannot label frame {frame.seq}: {type(exc).__name__}: {exc}")
            return
        t3 = time.perf_counter()
        if state.background is not None:
            self.note_background(state, result.background_missing_share)
        if result.downsample != state.downsample:  # said when it is known, or changes
            state.downsample = f = result.downsample
            h, w = result.labels.shape
            log.info(
                "camera %s/%s: %dx%d frames labelled at %s",
                state.cell,
                state.camera,
                w,
                h,
                "their own resolution"
                if f == 1
                else f"{-(-w // f)}x{-(-h // f)}, the labels brought back to {w}x{h} by depth",
            )
        background = self.segmenter.background_id if result.background_gated else None
        out = wire.LabelFrame(result.labels, frame.seq, frame.stamp_ns, frame.frame_id, background)
        state.labels_pub.put(wire.encode_labels(out), attachment=self.attachment)
        t4 = time.perf_counter()
        state.note_seq(frame.seq, time.monotonic())
        state.counts["processed"] += 1
        for name, n in result.counts.items():  # every stage's counters, whatever they are
            state.counts[name] = state.counts.get(name, 0) + n
        state.note_done(t4)
        timings = {
            "receive": 1000 * (t1 - t0),
            "mount": 1000 * (tm - t1),
            "forest": result.timings.forest_ms,
            "crf": result.timings.crf_ms,
            **{f"stage_{name}": ms for name, ms in result.timings.stages_ms.items()},
            "publish": 1000 * (t4 - t3),
            "total": 1000 * (t4 - t0),
        }
        if frame.stamp_ns:  # end to end: capture (driver host clock) -> labels published
            latency = state.latency_ms(frame.stamp_ns, time.time_ns())
            if latency is not None:
                timings["latency"] = latency
        self.publish_stats(
            state,
            timings,
            seq=frame.seq,
            frame_id=frame.frame_id,
            floor_share=min(1.0, max(0.0, float(result.floor_share))),
        )

    def note_background(self, state: CameraState, missing_share: float) -> None:
        """Take a frame's share of the background seen farther than it; say once when the
        background stops matching (and the worker labels without it) and when it matches
        again."""
        watch = state.background
        change = watch.note(missing_share)
        if change == MISMATCH:
            log.warning(
                "BACKGROUND MISMATCH on %s/%s: %.0f %% of background %s read farther than it "
                "(over %.0f %%): a fixture or the camera moved; labelling without the "
                "background until it matches again (record it again: topseg calibrate "
                "--background)",
                state.cell,
                state.camera,
                100 * watch.worst_share,
                watch.background_id[:12],
                100 * watch.config.mismatch_share,
            )
        elif change is not None:
            log.warning(
                "background %s matches %s/%s again (%.1f %% farther than it): gating with it",
                watch.background_id[:12],
                state.cell,
                state.camera,
                100 * missing_share,
            )

    def reject(self, state: CameraState, why: str) -> None:
        """Count a message that could not be labelled, log it (sparingly), publish the counts."""
        state.counts["rejected"] += 1
        n = state.counts["rejected"]
        if n <= 10 or n % 100 == 0:  # a stream of garbage does not flood the log
            log.warning("%s/%s: %s (%d rejected)", state.cell, state.camera, why, n)
        self.publish_stats(state, {})

    def publish_stats(self, state: CameraState, timings: dict, **extra) -> None:
        """One stats message: ms per stage, fps, counts and `extra` (seq, frame_id)."""
        stats = {
            "stamp_ns": time.time_ns(),
            "role": "worker",
            "model_id": self.segmenter.model_id[: wire.MAX_FRAME_ID],
            "fps": state.fps,
            "timings_ms": timings,
            "counts": dict(state.counts),
            **extra,
        }
        mount = state.watch.stats() if state.watch is not None else None
        if mount is not None:
            stats["mount"] = mount
        if state.background is not None:
            stats["background"] = state.background.stats()
        state.stats_pub.put(wire.encode_stats(stats), attachment=self.attachment)

    def close(self) -> None:
        """Undeclare the doorbells, subscribers and liveliness tokens."""
        for bell in self.doorbells:
            bell.undeclare()
        self.token_watch.undeclare()
        if self.any_token is not None:
            self.any_token.undeclare()
        for state in list(self.cameras.values()):
            self.release(state)
        if self.shared_sub is not None:
            self.shared_sub.undeclare()


def status_line(worker: Worker) -> str:
    """One line for `systemctl status`: each camera's fps and counts."""
    dropped = (
        [f"{worker.bad_keys} depth messages on keys that name no camera dropped"]
        if worker.bad_keys
        else []
    )
    if not worker.cameras:
        return "; ".join([f"model {worker.segmenter.model_id}: waiting for depth frames", *dropped])
    now, parts = time.perf_counter(), []
    for s in list(worker.cameras.values()):  # another thread asks; the dict may change
        c = s.counts
        idle = s.last_time is None or now - s.last_time > 2.0
        rate = "idle" if idle else f"{s.fps:.1f} fps"
        mismatch = s.background is not None and not s.background.gate
        parts.append(
            f"{s.cell}/{s.camera}: {rate}, {c['processed']} labelled, "
            f"{c['dropped']} dropped, {c['rejected']} rejected"
            + (", BACKGROUND MISMATCH" if mismatch else "")
        )
    if worker.ignored:
        parts.append(
            f"{len(worker.ignored)} camera names ignored (--max-cameras {worker.max_cameras})"
        )
    return "serving " + "; ".join([*parts, *dropped])


def mount_config(args: argparse.Namespace) -> MountWatchConfig:
    """The mount estimate's settings from the worker's options; TopsegError when bad."""
    check = getattr(args, "mount_check", 30.0)
    if not check >= 0:
        raise TopsegError(f"--mount-check must be >= 0 s, got {check}")
    sensor = getattr(args, "sensor", None)
    if sensor is not None:
        from topseg.core.sensors import get_sensor

        get_sensor(sensor)  # an unknown name fails here, in one line
    return MountWatchConfig(recheck_s=check, sensor=sensor)


def check_background_cameras(config: SegmenterConfig, cameras: list[str] | None) -> None:
    """TopsegError unless a recorded background, being one camera's, comes with exactly one
    `--cameras` entry."""
    if config.background.path is not None and len(cameras or ()) != 1:
        raise TopsegError(
            f"--background {config.background.path} is one camera's background: give the "
            "worker exactly one --cameras CELL/CAMERA"
        )


def load_segmenter(model: str | None, config: SegmenterConfig | None = None) -> Segmenter:
    """The worker's Segmenter: `model` (None = the bundled one) with `config` (None: the
    defaults). Frames are not checked against the model's camera: the worker labels
    whatever size a camera sends, through its mount."""
    config = replace(config or SegmenterConfig(), check_camera=False)
    return Segmenter.from_file(model, config)


def refuse_if_labelled(session, cameras: list[tuple[str, str]], me: identity.Identity) -> None:
    """TopsegError (one line) when another worker already labels one of `cameras` (its
    token is there; a crashed worker's token goes with its connection)."""
    if not cameras:
        return
    if zenoh_session.wait_connected(session, identity.CONNECT_WAIT_S):
        zenoh_session.wait_settled(session)  # gossip brings the peers after the first one
    for cell, camera in cameras:
        others = identity.other_instances(
            session, wire.alive_key(cell, camera, "worker"), me.instance
        )
        if others:
            raise TopsegError(
                f"camera {cell}/{camera} is already labelled by worker {min(others)}; stop it "
                "or leave the camera out of --cameras"
            )


def run(args: argparse.Namespace) -> int:
    """Serve until SIGTERM/SIGINT; a bad camera name, Zenoh config or model fails first (2)."""
    for text in args.cameras or ():
        parse_camera(text)  # bad names fail before anything is loaded
    mount_config(args)  # so do a bad --mount-check or --sensor
    config = segmenter_config(args)
    check_background_cameras(config, args.cameras)  # and a background without one camera
    svc = ServiceLifecycle("worker", args)  # so does a bad Zenoh config
    if args.threads:
        import numba

        numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    # ModelFileError, BackgroundFileError: one line, exit 2
    segmenter = load_segmenter(args.model, config)
    t0 = time.perf_counter()
    segmenter.warm_up()
    mount_warm_up()
    log.info("model %s loaded and compiled in %.1f s", segmenter.model_id, time.perf_counter() - t0)

    with svc:
        wanted = [parse_camera(c) for c in args.cameras or ()]
        refuse_if_labelled(svc.session, wanted, identity.Identity.of(svc.session))
        worker = Worker(args, svc.session, segmenter)
        svc.defer(worker.close)
        log.info("worker ready")
        svc.ready(status=lambda: status_line(worker))
        worker.serve_until_stopped(svc)
        for state in worker.cameras.values():
            log.info("%s/%s: %s", state.cell, state.camera, state.counts)
        if worker.ignored:
            log.warning(
                "%d camera names were ignored (--max-cameras %d; %d depth messages); %d idle "
                "cameras released",
                len(worker.ignored),
                worker.max_cameras,
                worker.ignored_messages,
                worker.forgotten,
            )
        if worker.bad_keys:
            log.warning(
                "%d depth messages on keys that name no camera were dropped", worker.bad_keys
            )
    return 0
