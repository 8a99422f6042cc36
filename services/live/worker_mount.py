"""The worker's view of where each camera hangs: the frames' mount, or its own estimate.

A camera whose frames carry a mount (`topseg driver --mount FILE`) is labelled with it, once
it agrees with their depth (`core.calibration.check_floor` on the first frames until one has
depth enough to tell): a carried mount whose floor is not where the depth shows it (a wrong
mount file, a recording made with one) is refused with one warning, counted in `refused`, and
the camera is treated as one whose frames carry none, until the frames carry another. One
whose frames carry none gets a mount estimated from its first frames
(`core.calibration.estimate_mount` over `first_frames` of them, or what came in `first_wait_s`):
those frames wait, unlabelled, for the estimate (labels under a guessed mount would be
wrong, and a second is short), then are labelled with it. Either way the mount is checked
again every `recheck_s` against an estimate from the newest frames: a camera whose floor
moved by more than `moved_height_mm` or tilted by more than `moved_tilt_deg` was bumped; that
is logged as a warning, counted in `moved` (the worker's stats) and the estimate is used from
then on (until the frames' own mount changes). A failed estimate (floor covered, camera
moving) is logged and tried again after `retry_s` on the newest frames; meanwhile frames
are labelled at once with the mount in use, or with none when there is none yet (the
Segmenter then says whether its model can do without: a height model refuses, and those
frames are counted as rejected).

Pure bookkeeping over frames and a clock: `MountWatch` does no I/O but logging, so the
worker's main thread drives it and tests drive it with their own clock and estimator.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from topseg.core.calibration import check_floor, estimate_mount
from topseg.core.calibration import mount_difference as difference
from topseg.core.camera import Intrinsics, TopViewMount, range_text
from topseg.core.denoise import smoothing_text
from topseg.core.errors import TopsegError
from topseg.core.fattening import thinning_text
from topseg.core.sensors import nearest_sensor

log = logging.getLogger("topseg.worker")


@dataclass(frozen=True)
class MountWatchConfig:
    """When and how the worker estimates and re-checks a camera's mount.

    first_frames, first_wait_s: the first estimate uses this many frames, or those that came
        in this many seconds after the first one.
    recheck_s: re-estimate from the newest `recheck_frames` frames this often (0: never).
    retry_s: after a failed estimate, try again this much later (at most recheck_s).
    moved_height_mm, moved_tilt_deg: a re-estimate this far from the mount in use means the
        camera moved.
    sensor: the sensor named in estimated mounts (None: guessed from the frames' intrinsics).
    """

    first_frames: int = 10
    first_wait_s: float = 1.0
    recheck_s: float = 30.0
    recheck_frames: int = 3
    retry_s: float = 5.0
    moved_height_mm: float = 50.0
    moved_tilt_deg: float = 2.0
    sensor: str | None = None

    def __post_init__(self) -> None:
        if self.first_frames < 1 or self.recheck_frames < 1:
            raise TopsegError("the mount estimate needs at least one frame")
        if min(self.first_wait_s, self.recheck_s, self.retry_s) < 0:
            raise TopsegError("mount check intervals must be >= 0 s")


def mount_text(m: TopViewMount) -> str:
    """'height 3.31 m, pitch +1.2, roll -0.4 deg, kinect_v1 (noise x0.35)' for logs, and
    for a radial camera ', radial distance read as depth', and when the frames are smoothed
    (`core.denoise`) ', depth smoothed (noise 85 mm at the floor)', and when a stereo
    camera's edges are thinned (`core.fattening`) ', edges thinned 1 px (stereo fattening)'."""
    return (
        f"height {m.height_mm / 1000:.2f} m, pitch {m.pitch_deg:+.1f}, "
        f"roll {m.roll_deg:+.1f} deg, {m.sensor} (noise x{m.noise_scale:.2f})"
        f"{range_text(m)}{thinning_text(m)}{smoothing_text(m)}"
    )


def _estimate(frames: Sequence[np.ndarray], k: Intrinsics, sensor: str) -> Any:
    return estimate_mount(frames, k, sensor)


def _check_floor(depth: np.ndarray, mount: TopViewMount) -> Any:
    return check_floor(depth, mount)


def warm_up() -> None:
    """Import the estimator (scikit-learn takes seconds) before the first frame needs it."""
    import sklearn.linear_model  # noqa: F401


def mount_difference(a: TopViewMount, b: TopViewMount) -> tuple[float, float]:
    """(height difference mm, angle between the floors' normals deg) of two mounts."""
    return difference(a, b)


@dataclass
class MountWatch:
    """One camera's mount: which is in use, where it came from, and when to look again.

    `take(frame, now)` hands in each decoded frame and returns the frames to label now with
    the mount to label them with; `due(now)` says whether frames wait on a deadline that
    passed (`flush(now)` then returns them).
    """

    name: str
    config: MountWatchConfig = field(default_factory=MountWatchConfig)
    estimate: Callable[[Sequence[np.ndarray], Intrinsics, str], Any] = _estimate
    check: Callable[[np.ndarray, TopViewMount], Any] = _check_floor
    mount: TopViewMount | None = None
    source: str | None = None  # "frame" | "estimated" | None
    moved: int = 0
    estimates: int = 0  # successful estimates
    failures: int = 0
    frame_mount: TopViewMount | None = None  # the last mount the frames carried
    frame_verdict: bool | None = None  # whether it agrees with their depth (None: not known)
    refused: int = 0  # mounts the frames carried that disagreed with their depth
    waiting: list = field(default_factory=list)  # frames held for the first estimate
    first_at: float | None = None
    tried: bool = False  # the first estimate was tried (later ones are re-checks)
    next_check: float | None = None
    recent: deque = field(default_factory=deque)

    # -- frames in

    def take(self, frame, now: float | None = None) -> list:
        """Note `frame` (a wire.DepthFrame); the frames to label now (maybe none, maybe the
        held ones). Label them with `self.mount`."""
        now = time.monotonic() if now is None else now
        self.recent.append(frame)
        while len(self.recent) > self.config.recheck_frames:
            self.recent.popleft()
        if frame.mount is not None:
            self._frame_mount(frame, now)
        elif self.source == "frame" or self.frame_mount is not None:
            # the frames stopped carrying a mount: keep the last one, re-check sooner
            self.frame_mount, self.source = None, "estimated" if self.mount else None
            log.warning("camera %s: frames no longer carry a mount; estimating one", self.name)
            self.next_check = now
        carried = frame.mount is not None and self.frame_verdict is not False
        if self.mount is None and not carried and not self.tried:
            self.waiting.append(frame)
            self.first_at = now if self.first_at is None else self.first_at
            if len(self.waiting) < self.config.first_frames and not self._waited(now):
                return []
            return self.flush(now)
        if self.next_check is not None and now >= self.next_check:
            self.recheck(now)
        return [frame]

    def _waited(self, now: float) -> bool:
        return self.first_at is not None and now - self.first_at >= self.config.first_wait_s

    def due(self, now: float | None = None) -> bool:
        """True when frames wait for a first estimate whose time is up."""
        now = time.monotonic() if now is None else now
        return bool(self.waiting) and self._waited(now)

    def seconds_to_due(self, now: float | None = None) -> float | None:
        """Seconds until held frames are due (None: none held)."""
        if not self.waiting or self.first_at is None:
            return None
        now = time.monotonic() if now is None else now
        return max(0.0, self.first_at + self.config.first_wait_s - now)

    def flush(self, now: float | None = None) -> list:
        """Estimate from the held frames; return them all to be labelled (with the estimate,
        or with no mount when it failed)."""
        now = time.monotonic() if now is None else now
        held, self.waiting, self.first_at = self.waiting, [], None
        if not held:
            return []
        self.tried = True
        est = self._try_estimate([f.depth for f in held], held[-1].intrinsics, "first")
        if est is not None:
            self.mount, self.source = est.mount, "estimated"
            log.info(
                "camera %s: estimated mount from %d frames: %s (floor %.0f %% of the view, "
                "residual %.1f mm)",
                self.name,
                len(held),
                mount_text(est.mount),
                100 * est.inlier_share,
                est.residual_mm,
            )
        self._schedule(now, est is not None)
        return held

    # -- the frames' own mount

    def _frame_mount(self, frame, now: float) -> None:
        mount = frame.mount
        if mount == self.frame_mount:
            if self.frame_verdict is None and self._judge(frame, now) is False:
                return
            if self.source is None and self.frame_verdict is not False:
                self.mount, self.source = mount, "frame"
            return
        previous = self.frame_mount
        self.frame_mount, self.frame_verdict = mount, None
        if previous is None:
            log.info("camera %s: mount from the frames: %s", self.name, mount_text(mount))
        else:
            dh, da = mount_difference(previous, mount)
            log.warning(
                "camera %s: the frames' mount changed: height %.2f -> %.2f m (tilt changed "
                "%.1f deg)",
                self.name,
                previous.height_mm / 1000,
                mount.height_mm / 1000,
                da,
            )
            if self._is_move(dh, da):
                self.moved += 1
        if self._judge(frame, now) is False:
            return
        self.mount, self.source = mount, "frame"
        self.waiting, self.first_at = [], None
        if self.next_check is None:
            self._schedule(now, True)

    def _judge(self, frame, now: float) -> bool | None:
        """Check the frames' mount against this frame's depth (`core.calibration.check_floor`)
        and note the verdict. A mount that disagrees is refused: said in one warning, counted
        in `refused`, and the mount estimated from the frames as for frames that carry none
        (the estimate in use is kept meanwhile, re-checked at once). None: no verdict yet
        (too little depth), the mount is used and checked again on the next frame."""
        mount = frame.mount
        if frame.intrinsics is not None and frame.intrinsics != mount.intrinsics:
            mount = replace(mount, intrinsics=frame.intrinsics)  # as the Segmenter reads it
        try:
            result = self.check(frame.depth, mount)
        except ValueError:  # not this camera's size: the Segmenter refuses the frame itself
            return None
        self.frame_verdict = result.agrees
        if result.agrees is not False:
            return result.agrees
        self.refused += 1
        log.warning(
            "camera %s: the frames' mount disagrees with their depth: %s; estimating the mount "
            "from the frames instead (calibrate the camera again: topseg calibrate)",
            self.name,
            result.reason(),
        )
        if self.source == "frame":  # a mount in use from earlier frames: not any more
            self.mount, self.source = None, None
        if self.mount is None:
            self.tried = False  # the frames wait for a first estimate, as without a mount
        else:
            self.next_check = now
        return False

    # -- re-checks

    def _is_move(self, dh: float, da: float) -> bool:
        return dh > self.config.moved_height_mm or da > self.config.moved_tilt_deg

    def recheck(self, now: float | None = None) -> bool:
        """Estimate from the newest frames and compare with the mount in use; True when the
        camera moved (logged as a warning, counted, and the estimate used from now on). A
        mount that reads range as depth, or depth as range, is replaced by the estimate the
        same way, with its own warning, and is not counted as a move."""
        now = time.monotonic() if now is None else now
        frames = list(self.recent)
        if not frames:
            return False
        est = self._try_estimate([f.depth for f in frames], frames[-1].intrinsics, "re-check")
        self._schedule(now, est is not None)
        if est is None:
            return False
        if self.mount is None:
            self.mount, self.source = est.mount, "estimated"
            log.info("camera %s: estimated mount: %s", self.name, mount_text(est.mount))
            return False
        if est.mount.radial != self.mount.radial:  # range read as depth, or depth as range
            sends = "range along each ray" if est.mount.radial else "depth"
            log.warning(
                "camera %s sends %s, but %s mount says otherwise (%s); labelling with the new "
                "estimate%s",
                self.name,
                sends,
                "the frames'" if self.source == "frame" else "the estimated",
                mount_text(self.mount),
                "; calibrate it again (topseg calibrate)" if self.source == "frame" else "",
            )
            self.mount, self.source = self._kept(est.mount), "estimated"
            return False
        dh, da = mount_difference(self.mount, est.mount)
        if not self._is_move(dh, da):
            log.debug("camera %s: mount checked: %.0f mm, %.2f deg off", self.name, dh, da)
            return False
        self.moved += 1
        log.warning(
            "camera %s moved: height %.2f -> %.2f m, tilt %.1f -> %.1f deg (%s mount was %s); "
            "labelling with the new estimate%s",
            self.name,
            self.mount.height_mm / 1000,
            est.mount.height_mm / 1000,
            self.mount.tilt_deg(),
            est.mount.tilt_deg(),
            "the frames'" if self.source == "frame" else "the estimated",
            mount_text(self.mount),
            "; calibrate it again (topseg calibrate)" if self.source == "frame" else "",
        )
        self.mount, self.source = self._kept(est.mount), "estimated"
        return True

    def _kept(self, estimate: TopViewMount) -> TopViewMount:
        """`estimate` with what the frames cannot show kept from the mount in use: whether
        the camera's edges are thinned (its own filters, not its pose)."""
        return replace(estimate, edge_thinning=self.mount.edge_thinning)

    def _schedule(self, now: float, ok: bool) -> None:
        if not ok:  # tried again soon, even with re-checks off
            retry = self.config.retry_s
            if self.config.recheck_s > 0:
                retry = min(retry, self.config.recheck_s)
            self.next_check = now + retry
        else:
            every = self.config.recheck_s
            self.next_check = None if every <= 0 else now + every

    def _try_estimate(self, depths: list, k: Intrinsics, what: str):
        guessed = nearest_sensor(k.width, k.height, k.fx).name
        sensor = self.config.sensor or (self.mount.sensor if self.mount else guessed)
        t0 = time.perf_counter()
        try:
            est = self.estimate(depths, k, sensor)
        except TopsegError as exc:
            self.failures += 1
            if self.failures <= 3 or self.failures % 20 == 0:
                using = mount_text(self.mount) if self.mount else "no mount"
                log.warning(
                    "camera %s: no mount estimate (%s, %d frames): %s; labelling with %s",
                    self.name,
                    what,
                    len(depths),
                    exc,
                    using,
                )
            return None
        self.estimates += 1
        log.debug(
            "camera %s: %s estimate in %.0f ms", self.name, what, 1000 * (time.perf_counter() - t0)
        )
        return est

    # -- stats

    def stats(self) -> dict | None:
        """The mount in use for the worker's stats (`wire` stats `mount`), None without one."""
        if self.mount is None:
            return None
        m = self.mount
        return {
            "height_mm": float(m.height_mm),
            "pitch_deg": float(m.pitch_deg),
            "roll_deg": float(m.roll_deg),
            "sensor": m.sensor,
            "source": self.source,
            "moved": self.moved,
        }
