"""A virtual camera: `synthetic[:OPTIONS]` renders scenes from the density function live, with
ground truth on every frame.

OPTIONS is a comma-separated list: a mode (`modeled`, the default, `non-modeled` or `cell`: robot
cells) and
`key=value` settings `seed=N` (default 0), `room=NAME`, `noise=SPEC` (a `parse_noise` spec,
or `sensor`: the camera's own noise family), `mount=paper|random` and `sensor=NAME`, e.g.
`synthetic:non-modeled,seed=3` or `synthetic:mount=random,sensor=oak_d`. A camera stays put,
so the stream has one mount: the paper's (default), or one drawn from the seed (height
2.4-4.5 m, pitch and roll up to 10 degrees, the named sensor or one of all four; its noise
family unless `noise` says otherwise). Every depth frame carries its mount. Frame `i` is `Synthesizer.render(i)`, so the same spec
gives the same frames in any process. Frames come at `options.fps` (default 30) or as fast as
they render without `realtime`; rendering one takes 15-40 ms on one core, so 30 fps is the
most this source sustains. The source never ends on its own.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from topseg.core.camera import PAPER_MOUNT
from topseg.core.errors import TopsegError
from topseg.core.extras import is_installed, needs_extra
from topseg.core.formats import wire
from topseg.core.formats.ros2_recording_writer import Ros2RecordingWriter
from topseg.core.formats.wire import DepthFrame, LabelFrame
from topseg.core.synth.density import MODES
from topseg.core.synth.synthesis import MountDistribution, SynthesisConfig, Synthesizer
from topseg.drivers.base import Pacer, Source, SourceError, SourceFrame, SourceOptions

DEFAULT_FPS = 30.0
_KEYS = ("seed", "room", "noise", "mount", "sensor")


def parse_options(arg: str | None) -> dict:
    """'non-modeled,seed=3' -> SynthesisConfig keyword arguments; SourceError on anything else."""
    kw: dict = {}
    for token in (arg or "").split(","):
        token = token.strip()
        if not token:
            continue
        key, sep, value = token.partition("=")
        if not sep:
            if token not in MODES:
                raise SourceError(f"synthetic: unknown mode {token!r}; use {' or '.join(MODES)}")
            kw["mode"] = token
        elif key not in _KEYS:
            raise SourceError(f"synthetic: unknown option {key!r}; use {', '.join(_KEYS)}")
        elif key == "seed":
            try:
                kw["seed"] = int(value)
            except ValueError:
                raise SourceError(f"synthetic: seed must be an integer, got {value!r}") from None
        elif key == "mount" and value not in ("paper", "random"):
            raise SourceError(f"synthetic: mount must be paper or random, got {value!r}")
        else:
            kw[key] = value
    return kw


def synthesis_config(kw: dict):
    """`parse_options`' result -> a SynthesisConfig with one fixed mount for the stream."""
    kw = dict(kw)
    mount_kind, sensor = kw.pop("mount", "paper"), kw.pop("sensor", None)
    if mount_kind == "paper" and sensor is None:
        return SynthesisConfig(**kw)
    d = MountDistribution() if sensor is None else MountDistribution(sensors=(sensor,))
    if mount_kind == "paper":  # a sensor at the paper's height, straight down
        h = PAPER_MOUNT.height_mm / 1000.0
        d = MountDistribution(height_m=(h, h), tilt_deg=0.0, sensors=(sensor,))
    seed = int(kw.get("seed", 0))
    camera = d.draw(np.random.default_rng(np.random.SeedSequence([seed, 0x6D6F756E74])))
    kw.setdefault("noise", "sensor")
    return SynthesisConfig(camera=camera, **kw)


class SyntheticSource(Source):
    """Frames `Synthesizer.render(0), render(1), ...` paced at fps, each with its truth."""

    finite = False

    def __init__(self, arg: str | None, options: SourceOptions) -> None:
        try:
            config = synthesis_config(parse_options(arg))
        except SourceError:
            raise
        except TopsegError as exc:
            raise SourceError(f"synthetic: {exc}") from exc
        self.options = options
        self.description = "synthetic" + (f":{arg}" if arg else "")
        self.intrinsics = config.camera.intrinsics
        self.mount = config.camera
        self.nominal_fps = options.fps or DEFAULT_FPS
        if not is_installed("pybullet"):
            raise SourceError(needs_extra("synthetic", "pybullet", "train"))
        self.synth = Synthesizer(config)
        self._stop = threading.Event()

    def frames(self) -> Iterator[SourceFrame]:
        """Frame i is `render(i)` stamped with host time, paced at nominal_fps until closed."""
        pacer = Pacer(self.options.realtime)
        seq = 0
        while not self._stop.is_set():
            pacer.wait(seq / self.nominal_fps, self._stop)
            frame = self.synth.render(seq)
            stamp = time.time_ns()
            depth = DepthFrame(frame.depth, self.intrinsics, seq, stamp, "", frame.mount)
            yield SourceFrame(depth, LabelFrame(frame.labels, seq, stamp, ""))
            seq += 1

    def close(self) -> None:
        """Stop `frames` (also mid-wait) and release the pybullet pools."""
        self._stop.set()
        self.synth.close()


def open(arg: str | None, options: SourceOptions) -> SyntheticSource:
    """`synthetic[:OPTIONS]` -> a SyntheticSource (warms its pybullet pools, ~1.5 s)."""
    return SyntheticSource(arg, options)


def record(
    path: str | Path, n_frames: int, arg: str | None = None, fps: float = DEFAULT_FPS
) -> Path:
    """Write `n_frames` synthetic frames (depth + truth, 1/fps apart) to a ROS 2 MCAP recording
    that `replay:PATH` plays back with its ground truth; atomic like every RecordingWriter."""
    if n_frames < 1:
        raise SourceError(f"a recording needs at least one frame, got {n_frames}")
    source = SyntheticSource(arg, SourceOptions(realtime=False))
    t0 = time.time_ns()
    try:
        with Ros2RecordingWriter(path, metadata={"source": source.description}) as w:
            for frame in source.frames():
                i = frame.depth.seq
                stamp = t0 + round(i * 1e9 / fps)
                depth = DepthFrame(
                    frame.depth.depth, source.intrinsics, i, stamp, "", frame.depth.mount
                )
                truth = LabelFrame(frame.truth.labels, i, stamp, "")
                w.write(wire.depth_key(), wire.encode_depth(depth), log_time_ns=stamp)
                w.write(wire.truth_key(), wire.encode_labels(truth), log_time_ns=stamp)
                if i + 1 == n_frames:
                    break
    finally:
        source.close()
    return Path(path)
