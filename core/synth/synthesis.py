"""Synthetic labelled depth frames: the one entry point datagen and the synthetic driver call.

    with Synthesizer(SynthesisConfig(mode="modeled", noise="gaussian:15")) as synth:
        frame = synth.render(frame_seed=42)   # frame.depth, frame.labels, frame.scene

`render(frame_seed)` samples a scene from the density function, poses pooled pybullet bodies
for it, ray-casts depth and exact labels from the ceiling camera and applies the noise model.
The same (config, frame_seed) gives the same frame in any process: all randomness flows from
`numpy.random.SeedSequence([config.seed, frame_seed])`. A Synthesizer owns one pybullet
DIRECT client; use one per process (or thread) and close it when done.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from topseg.core import labels
from topseg.core.camera import TOP_VIEW, TopViewMount
from topseg.core.errors import TopsegError
from topseg.core.synth import rooms
from topseg.core.synth.density import MODES, DensityConfig, DensityFunction
from topseg.core.synth.humanoid import POSES
from topseg.core.synth.noise import parse_noise
from topseg.core.synth.scene import Scene

ROOMS: tuple[str, ...] = rooms.ROOMS
__all__ = ["POSES", "ROOMS", "SynthesisConfig", "Synthesizer", "SyntheticFrame"]


@dataclass
class SynthesisConfig:
    """What to synthesise. `theta_max`, when given, sets both of the density's theta' (H-O and
    O-O); `room` None draws one of ROOMS per frame; `noise` is a `parse_noise` spec."""

    mode: str = "modeled"
    noise: str = "gaussian:15"
    room: str | None = None
    theta_max: float | None = None
    density: DensityConfig = field(default_factory=DensityConfig)
    seed: int = 0
    camera: TopViewMount = TOP_VIEW

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise TopsegError(f"unknown mode {self.mode!r}; choose one of {', '.join(MODES)}")
        if self.room is not None and self.room not in ROOMS:
            raise TopsegError(f"unknown room {self.room!r}; choose one of {', '.join(ROOMS)}")
        self.noise = parse_noise(self.noise).spec  # validated and normalised
        if isinstance(self.density, dict):
            self.density = DensityConfig.from_dict(self.density)
        if self.theta_max is not None:
            if not 0.0 <= float(self.theta_max) <= 1.0:
                raise TopsegError(f"theta_max is a fraction in [0, 1], got {self.theta_max}")
            self.theta_max = float(self.theta_max)
            self.density = replace(
                self.density, theta_max_ho=self.theta_max, theta_max_oo=self.theta_max
            )
        if not isinstance(self.seed, int) or self.seed < 0:
            raise TopsegError(f"seed must be a non-negative integer, got {self.seed!r}")

    def to_dict(self) -> dict:
        """Plain JSON/TOML data (datasets record it as the generator's config); see `from_dict`."""
        return {
            "mode": self.mode,
            "noise": self.noise,
            "room": self.room,
            "theta_max": self.theta_max,
            "density": self.density.to_dict(),
            "seed": self.seed,
            "camera": self.camera.to_dict(),
        }

    @classmethod
    def from_dict(cls, d: dict, source: str = "synthesis config") -> SynthesisConfig:
        """The config in `d` (`to_dict`'s form); ConfigError naming an unknown or mistyped key."""
        from topseg.core.config import from_dict

        return from_dict(cls, d, source)


@dataclass
class SyntheticFrame:
    """One frame: `depth` (H, W) uint16 mm (0 = no depth), `labels` (H, W) uint8 with NO_DEPTH
    where depth is 0 after noise, `scene` the JSON-able scene description, `seed` its frame
    seed, `timings_ms` what each stage took."""

    depth: np.ndarray
    labels: np.ndarray
    scene: dict
    seed: int
    timings_ms: dict = field(default_factory=dict)


class Synthesizer:
    """Owns one pybullet DIRECT client with its pooled bodies; renders frames by seed."""

    def __init__(self, config: SynthesisConfig | None = None, warm: bool = True) -> None:
        """`warm` creates every pooled pybullet body the config can draw up front (~1.5 s), so
        no frame waits for one; without it bodies are created when first needed."""
        import pybullet as p

        from topseg.core.synth.scene_builder import SceneBuilder

        self.config = config or SynthesisConfig()
        self.density = DensityFunction(
            self.config.density, self.config.mode, self.config.room, self.config.camera
        )
        self.noise = parse_noise(self.config.noise)
        self._p = p
        self.client = p.connect(p.DIRECT)
        self.builder = SceneBuilder(self.client, self.config.camera)
        if warm:
            d = self.config.density
            self.builder.warm(d.object_height_m, d.human_height_m)

    def rngs(self, frame_seed: int) -> tuple[np.random.Generator, np.random.Generator]:
        """The scene's and the noise's generators for `frame_seed`."""
        if (
            isinstance(frame_seed, bool)
            or not isinstance(frame_seed, int | np.integer)
            or frame_seed < 0
        ):
            raise TopsegError(f"frame_seed must be a non-negative integer, got {frame_seed!r}")
        scene_ss, noise_ss = np.random.SeedSequence([self.config.seed, int(frame_seed)]).spawn(2)
        return np.random.default_rng(scene_ss), np.random.default_rng(noise_ss)

    def render(self, frame_seed: int) -> SyntheticFrame:
        """Sample, build, ray-cast and add noise to frame `frame_seed`."""
        scene_rng, noise_rng = self.rngs(frame_seed)
        t0 = time.perf_counter()
        scene = self.density.sample(scene_rng)
        t1 = time.perf_counter()
        frame = self.render_scene(scene, noise_rng)
        frame.seed = int(frame_seed)
        frame.timings_ms = {"sample": 1e3 * (t1 - t0), **frame.timings_ms}
        return frame

    def render_scene(
        self, scene: Scene, noise_rng: np.random.Generator | None = None
    ) -> SyntheticFrame:
        """Render a given scene description (noise drawn from `noise_rng`)."""
        from topseg.core.synth.render import raycast

        self._check_open()
        t0 = time.perf_counter()
        self.builder.build(scene)
        prims = self.builder.primitives()
        t1 = time.perf_counter()
        clean, lab = raycast(prims, self.config.camera)
        t2 = time.perf_counter()
        depth = self.noise.apply(
            clean, noise_rng if noise_rng is not None else np.random.default_rng(0)
        )
        lab[depth == 0] = labels.NO_DEPTH
        t3 = time.perf_counter()
        timings = {"build": 1e3 * (t1 - t0), "raycast": 1e3 * (t2 - t1), "noise": 1e3 * (t3 - t2)}
        return SyntheticFrame(depth, lab, scene.to_dict(), -1, timings)

    def _check_open(self) -> None:
        if self.client is None:
            raise TopsegError("this Synthesizer is closed")

    def close(self) -> None:
        """Disconnect the pybullet client (its bodies go with it); safe to call twice."""
        if self.client is not None:
            try:
                self._p.disconnect(self.client)
            finally:
                self.client = None

    def __enter__(self) -> Synthesizer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
