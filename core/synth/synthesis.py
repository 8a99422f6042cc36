"""Synthetic labelled depth frames: the one entry point datagen and the synthetic driver call.

    with Synthesizer(SynthesisConfig(mode="modeled", noise="gaussian:15")) as synth:
        frame = synth.render(frame_seed=42)   # frame.depth, frame.labels, frame.scene, frame.mount

`render(frame_seed)` draws the frame's camera mount, samples a scene from the density function
on the floor that mount sees, poses pooled pybullet bodies for it, ray-casts depth and exact
labels from the (possibly tilted) camera at the sensor's resolution and applies the noise
model. The same (config, frame_seed) gives the same frame in any process: all randomness flows
from `numpy.random.SeedSequence([config.seed, frame_seed])` (scene, noise and mount streams).
A Synthesizer owns one pybullet DIRECT client; use one per process (or thread) and close it.

Mounts: `SynthesisConfig.mounts` None keeps the one fixed `camera` (the paper's experiments:
PAPER_MOUNT); a `MountDistribution` draws height, pitch, roll and sensor per frame (training
data for any ceiling). Noise "sensor" uses each frame's sensor's own noise family
(`core.sensors`); any other spec applies to every frame.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from topseg.core import labels
from topseg.core.camera import PAPER_MOUNT, TopViewMount
from topseg.core.config import from_dict
from topseg.core.errors import TopsegError
from topseg.core.sensors import NAMES, get_sensor
from topseg.core.synth import rooms
from topseg.core.synth.density import MODES, DensityConfig, DensityFunction
from topseg.core.synth.humanoid import POSES
from topseg.core.synth.noise import parse_noise
from topseg.core.synth.render import Primitives, Triangles, raycast
from topseg.core.synth.scene import Scene
from topseg.core.synth.scene_builder import SceneBuilder

ROOMS: tuple[str, ...] = rooms.ROOMS
__all__ = [
    "POSES",
    "ROOMS",
    "SENSOR_NOISE",
    "MountDistribution",
    "SynthesisConfig",
    "Synthesizer",
    "SyntheticFrame",
    "mount_summary",
]

#: the noise spec meaning "each frame's sensor's own noise model"
SENSOR_NOISE = "sensor"


def _all_sensors() -> tuple[str, ...]:
    return tuple(NAMES)


@dataclass
class MountDistribution:
    """Camera mounts drawn per frame: height U[height_m], pitch and roll U[-tilt_deg, tilt_deg],
    a sensor uniformly from `sensors` (its intrinsics and noise family, `core.sensors`): a
    sensor listed N times is drawn N times as often."""

    height_m: tuple[float, float] = (2.4, 4.5)
    tilt_deg: float = 10.0
    sensors: tuple[str, ...] = field(default_factory=_all_sensors)

    def __post_init__(self) -> None:
        self.height_m = tuple(float(v) for v in self.height_m)
        self.sensors = tuple(str(v) for v in self.sensors)
        lo, hi = self.height_m
        if not 1.0 <= lo <= hi <= 10.0:
            raise TopsegError(
                f"mount heights must satisfy 1 <= low <= high <= 10 m, got {lo}, {hi}"
            )
        if not 0.0 <= float(self.tilt_deg) <= 20.0:
            raise TopsegError(f"mount tilt must be within 0..20 degrees, got {self.tilt_deg}")
        self.tilt_deg = float(self.tilt_deg)
        if not self.sensors:
            raise TopsegError("a mount distribution needs at least one sensor")
        for name in self.sensors:
            get_sensor(name)  # a one-line error naming the known sensors

    def draw(self, rng: np.random.Generator) -> TopViewMount:
        """One mount: sensor, height, pitch, roll, in that order from `rng`."""
        sensor = get_sensor(self.sensors[int(rng.integers(len(self.sensors)))])
        height = float(rng.uniform(*self.height_m))
        pitch, roll = (float(v) for v in rng.uniform(-self.tilt_deg, self.tilt_deg, 2))
        return TopViewMount(
            sensor.intrinsics, round(1000.0 * height, 1), round(pitch, 3), round(roll, 3),
            sensor.name,
        )  # fmt: skip

    def to_dict(self) -> dict:
        """Plain JSON/TOML data; see `from_dict`."""
        return {
            "height_m": list(self.height_m),
            "tilt_deg": self.tilt_deg,
            "sensors": list(self.sensors),
        }

    @classmethod
    def from_dict(cls, d: dict, source: str = "mount distribution") -> MountDistribution:
        """The distribution in `d` (`to_dict`'s form)."""
        return from_dict(cls, d, source)


def mount_summary(mounts: MountDistribution | None, camera: TopViewMount) -> dict:
    """What frames of this setting span, as a model header's `trained_for` records it:
    height_mm [lo, hi], tilt_deg (largest), sensors, resolutions [[w, h], ...]."""
    if mounts is None:
        k = camera.intrinsics
        return {
            "height_mm": [float(camera.height_mm)] * 2,
            "tilt_deg": round(camera.tilt_deg(), 6),
            "sensors": [camera.sensor],
            "resolutions": [[k.width, k.height]],
        }

    sizes = []
    for name in mounts.sensors:
        k = get_sensor(name).intrinsics
        if [k.width, k.height] not in sizes:
            sizes.append([k.width, k.height])
    tilt = float(np.degrees(np.arccos(np.cos(np.radians(mounts.tilt_deg)) ** 2)))
    return {
        "height_mm": [1000.0 * mounts.height_m[0], 1000.0 * mounts.height_m[1]],
        "tilt_deg": round(tilt, 6),
        "sensors": list(dict.fromkeys(mounts.sensors)),
        "resolutions": sizes,
    }


@dataclass
class SynthesisConfig:
    """What to synthesise. `theta_max`, when given, sets both of the density's theta' (H-O and
    O-O); `room` None draws one of ROOMS per frame; `noise` is a `parse_noise` spec or
    "sensor" (each frame's sensor's own model); `mounts` None renders every frame from the
    fixed `camera`, a MountDistribution draws each frame's mount."""

    mode: str = "modeled"
    noise: str = "gaussian:15"
    room: str | None = None
    theta_max: float | None = None
    density: DensityConfig = field(default_factory=DensityConfig)
    seed: int = 0
    camera: TopViewMount = PAPER_MOUNT
    mounts: MountDistribution | None = None

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise TopsegError(f"unknown mode {self.mode!r}; choose one of {', '.join(MODES)}")
        if self.room is not None and self.room not in ROOMS:
            raise TopsegError(f"unknown room {self.room!r}; choose one of {', '.join(ROOMS)}")
        if isinstance(self.mounts, dict):
            self.mounts = MountDistribution.from_dict(self.mounts)
        if self.noise != SENSOR_NOISE:
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
            "mounts": None if self.mounts is None else self.mounts.to_dict(),
        }

    def mount_summary(self) -> dict:
        """The mounts this config renders from, in a model header's `trained_for` form."""
        return mount_summary(self.mounts, self.camera)

    @classmethod
    def from_dict(cls, d: dict, source: str = "synthesis config") -> SynthesisConfig:
        """The config in `d` (`to_dict`'s form); ConfigError naming an unknown or mistyped key."""
        return from_dict(cls, d, source)


def scene_geometry(built: Primitives, scene: Scene) -> tuple[Primitives, Triangles | None]:
    """The scene's pybullet-built primitives with its robots' shapes added (robots are posed
    from their URDFs, not through pybullet) and its mesh objects' triangles; triangles None
    when the scene has neither robots nor mesh objects."""
    if not scene.robots and not scene.mesh_objects:
        return built, None
    prims, tris = [built], []
    for robot in scene.robots:
        p, t = robot.geometry()
        prims.append(p)
        tris.append(t)
    tris += [m.geometry() for m in scene.mesh_objects]
    return Primitives.concat(prims), Triangles.concat(tris)


@dataclass
class SyntheticFrame:
    """One frame: `depth` (H, W) uint16 mm (0 = no depth), `labels` (H, W) uint8 with NO_DEPTH
    where depth is 0 after noise, `scene` the JSON-able scene description (its "mount" key the
    camera's), `seed` its frame seed, `timings_ms` what each stage took, `mount` the camera
    it was seen from ((H, W) is its intrinsics' shape)."""

    depth: np.ndarray
    labels: np.ndarray
    scene: dict
    seed: int
    timings_ms: dict = field(default_factory=dict)
    mount: TopViewMount | None = None


class Synthesizer:
    """Owns one pybullet DIRECT client with its pooled bodies; renders frames by seed."""

    def __init__(self, config: SynthesisConfig | None = None, warm: bool = True) -> None:
        """`warm` creates every pooled pybullet body the config can draw up front (~1.5 s), so
        no frame waits for one; without it bodies are created when first needed."""
        import pybullet as p

        self.config = config or SynthesisConfig()
        self.density = DensityFunction(
            self.config.density, self.config.mode, self.config.room, self.config.camera
        )
        self._noise: dict[str, object] = {}
        self._p = p
        self.client = p.connect(p.DIRECT)
        self.builder = SceneBuilder(self.client, self.config.camera)
        if warm:
            d = self.config.density
            self.builder.warm(d.object_height_m, d.human_height_m)

    def noise_for(self, mount: TopViewMount):
        """The noise model of frames seen by `mount` (the config's, or its sensor's)."""
        key = mount.sensor if self.config.noise == SENSOR_NOISE else self.config.noise
        if key not in self._noise:
            if self.config.noise == SENSOR_NOISE:
                from topseg.core.sensors import get_sensor

                self._noise[key] = parse_noise(get_sensor(mount.sensor).noise_spec)
            else:
                self._noise[key] = parse_noise(self.config.noise)
        return self._noise[key]

    def mount_for(self, frame_seed: int) -> TopViewMount:
        """The camera mount of frame `frame_seed`: the fixed camera, or drawn from its seed."""
        if self.config.mounts is None:
            return self.config.camera
        return self.config.mounts.draw(self._streams(frame_seed)[2])

    def _streams(self, frame_seed: int) -> list[np.random.Generator]:
        if (
            isinstance(frame_seed, bool)
            or not isinstance(frame_seed, int | np.integer)
            or frame_seed < 0
        ):
            raise TopsegError(f"frame_seed must be a non-negative integer, got {frame_seed!r}")
        # spawn(3) starts with the same two children as spawn(2): a fixed-mount frame's scene
        # and noise streams are spawn(2)'s, untouched by the mount's third stream
        children = np.random.SeedSequence([self.config.seed, int(frame_seed)]).spawn(3)
        return [np.random.default_rng(c) for c in children]

    def rngs(self, frame_seed: int) -> tuple[np.random.Generator, np.random.Generator]:
        """The scene's and the noise's generators for `frame_seed`."""
        scene_rng, noise_rng, _ = self._streams(frame_seed)
        return scene_rng, noise_rng

    def render(self, frame_seed: int) -> SyntheticFrame:
        """Draw the mount, sample, build, ray-cast and add noise to frame `frame_seed`."""
        scene_rng, noise_rng = self.rngs(frame_seed)
        t0 = time.perf_counter()
        scene = self.density.sample(scene_rng, self.mount_for(frame_seed))
        t1 = time.perf_counter()
        frame = self.render_scene(scene, noise_rng)
        frame.seed = int(frame_seed)
        frame.timings_ms = {"sample": 1e3 * (t1 - t0), **frame.timings_ms}
        return frame

    def render_scene(
        self, scene: Scene, noise_rng: np.random.Generator | None = None
    ) -> SyntheticFrame:
        """Render a given scene description from its mount (the config's camera when it records
        none), noise drawn from `noise_rng`."""
        self._check_open()
        mount = scene.mount or self.config.camera
        if scene.mount is None:
            scene.mount = mount
        t0 = time.perf_counter()
        self.builder.build(scene)
        prims, triangles = scene_geometry(self.builder.primitives(), scene)
        t1 = time.perf_counter()
        clean, lab = raycast(prims, mount, triangles)
        t2 = time.perf_counter()
        depth = self.noise_for(mount).apply(
            clean, noise_rng if noise_rng is not None else np.random.default_rng(0), labels=lab
        )
        lab[depth == 0] = labels.NO_DEPTH
        t3 = time.perf_counter()
        timings = {"build": 1e3 * (t1 - t0), "raycast": 1e3 * (t2 - t1), "noise": 1e3 * (t3 - t2)}
        return SyntheticFrame(depth, lab, scene.to_dict(), -1, timings, mount)

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
