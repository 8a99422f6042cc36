"""The depth sensors topseg supports, as data: intrinsics, noise family and range.

A `SensorModel` says what a frame from that camera looks like: its resolution and focal
length (the synthesiser renders at these; features scale by the focal length), its noise
(a `core.synth.noise.parse_noise` spec of the sensor's family) and the range it measures.
`get_sensor(name)` looks one up; `SENSORS` lists them all. Values and their sources:
docs/research/sensor-noise-sources.md (codes R/S/K/D there), summarised in docs/reference/sensors.md.

- kinect_v1: structured light (PrimeSense), 640x480, fx 570.3; today's `kinect` noise.
- kinect_v2: time of flight, 512x424, fx ~365 (70.6 x 60 deg). The Azure Kinect's NFOV
  modes (640x576 unbinned / 320x288 binned, 75 x 65 deg, fx ~504 / ~252) are close in
  field of view and noise family; frames from one are labelled as a `kinect_v2`-family
  camera with their own intrinsics.
- oak_d: stereo (Luxonis OAK-D, OV9282 pair), 640x400, fx 441.25, baseline 75 mm.
- realsense_d435: active stereo (Intel D435), 640x480, fx ~385, baseline 50 mm.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from topseg.core.camera import Intrinsics
from topseg.core.errors import ConfigError, TopsegError
from topseg.core.synth.noise import parse_noise

STRUCTURED_LIGHT = "structured_light"
TIME_OF_FLIGHT = "time_of_flight"
ACTIVE_STEREO = "active_stereo"
FAMILIES = (STRUCTURED_LIGHT, TIME_OF_FLIGHT, ACTIVE_STEREO)


@dataclass(frozen=True)
class SensorModel:
    """One depth camera: its intrinsics, noise family and spec, and measured range.

    `noise_spec` parses with `core.synth.noise.parse_noise`; `baseline_m` is the
    triangulation baseline (projector or second imager; 0 for time of flight).
    """

    name: str
    family: str
    intrinsics: Intrinsics
    noise_spec: str
    min_range_m: float
    max_range_m: float
    baseline_m: float = 0.0
    note: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        if self.family not in FAMILIES:
            raise ConfigError(
                f"sensor {self.name!r}: family {self.family!r} is not one of {', '.join(FAMILIES)}"
            )
        if not 0 <= self.min_range_m < self.max_range_m:
            raise ConfigError(f"sensor {self.name!r}: needs 0 <= min_range_m < max_range_m")

    def noise(self):
        """The sensor's noise model (`parse_noise(noise_spec)`)."""
        return parse_noise(self.noise_spec)

    def sigma_mm(self, z_m):
        """Standard deviation (mm) of the sensor's random depth error at depth `z_m` (metres,
        scalar or array), at normal incidence away from edges: a noise-aware margin's unit."""
        return np.asarray(self.noise().sigma_mm(np.asarray(z_m, np.float64)))


KINECT_V1 = SensorModel(
    "kinect_v1",
    STRUCTURED_LIGHT,
    Intrinsics(640, 480, 570.3, 570.3, 319.5, 239.5),
    "kinect",
    0.5,
    8.0,
    baseline_m=0.075,
    note="PrimeSense PS1080; the noise model's own range (Microsoft SDK: 0.8-4 m default)",
)
KINECT_V2 = SensorModel(
    "kinect_v2",
    TIME_OF_FLIGHT,
    Intrinsics(512, 424, 365.0, 365.0, 255.5, 211.5),
    "tof:fov_cut=0.3",
    0.5,
    6.0,
    note=(
        "fx ~365 (K/D from 70.6 deg); libfreenect2 cuts at 4.5 m by default, depth is delivered "
        "beyond it; Azure Kinect NFOV (75 x 65 deg, fx ~504 at 640x576) is the same family"
    ),
)
OAK_D = SensorModel(
    "oak_d",
    ACTIVE_STEREO,
    Intrinsics(640, 400, 441.25, 441.25, 319.5, 199.5),
    "stereo:focal_px=441.25,baseline_m=0.075,subpixel_bits=3,disparity_sigma_px=0.1,"
    "min_range_m=0.35,border_px=3",
    0.35,
    10.0,
    baseline_m=0.075,
    note="Luxonis OAK-D at 400P; MinZ = f B / 95 px = 0.35 m; 3 subpixel bits (default)",
)
REALSENSE_D435 = SensorModel(
    "realsense_d435",
    ACTIVE_STEREO,
    Intrinsics(640, 480, 385.0, 385.0, 319.5, 239.5),
    "stereo",
    0.3,
    10.0,
    baseline_m=0.05,
    note="Intel D435 at 640x480 (HFOV ~90 deg); subpixel RMS 0.08 px (Intel's advice)",
)

SENSORS: tuple[SensorModel, ...] = (KINECT_V1, KINECT_V2, OAK_D, REALSENSE_D435)
_BY_NAME = {s.name: s for s in SENSORS}
NAMES: tuple[str, ...] = tuple(_BY_NAME)


def nearest_sensor(width: int, height: int, fx: float | None = None) -> SensorModel:
    """The supported sensor nearest to frames of `width` x `height` px: one of the same size
    first, then (when `fx` is known) the nearest field of view (focal length over width,
    which resampling keeps); without `fx`, the first of the same size in SENSORS order."""

    def distance(s: SensorModel) -> tuple:
        k = s.intrinsics
        fov = 0.0 if fx is None else abs(k.fx / k.width - fx / width)
        return ((k.width, k.height) != (width, height), fov)

    return min(SENSORS, key=distance)


def sensor_of_frames(shape: tuple[int, int], name: str | None = None) -> SensorModel | None:
    """The sensor that frames of this (rows, cols) size, which say no optics (PNGs), come
    from: the one called `name` (a one-line ConfigError when its frames are another size),
    else the first supported sensor of that size, else None."""
    rows, cols = shape
    if name is not None:
        sensor = get_sensor(name)
        k = sensor.intrinsics
        if k.shape != (rows, cols):
            raise ConfigError(
                f"{cols}x{rows} frames that say no intrinsics, but the {sensor.name}'s are "
                f"{k.width}x{k.height}; name the sensor they come from, or calibrate the "
                "camera from a source that says its optics"
            )
        return sensor
    sensor = nearest_sensor(cols, rows)
    return sensor if sensor.intrinsics.shape == (rows, cols) else None


def get_sensor(name: str) -> SensorModel:
    """The sensor called `name`; a one-line ConfigError listing the known names if none."""
    try:
        return _BY_NAME[name]
    except (KeyError, TypeError):
        raise ConfigError(f"unknown sensor {name!r}; known: {', '.join(NAMES)}") from None


#: Kinect-like axial noise, sigma_z = KINECT_SIGMA_COEFF * z^2 (z and sigma in metres;
#: Khoshelham & Elberink 2012, docs/research/sensor-noise-sources.md), for unknown sensors
KINECT_SIGMA_COEFF = 1.4e-3


def depth_sigma_mm(depth_mm: np.ndarray, sensor: str = "kinect_v1") -> np.ndarray:
    """The sensor's axial depth noise (1 sigma, mm) at each depth (mm), float32.

    The sensor model's (`SensorModel.sigma_mm`) when it knows the sensor; else the Kinect v1
    structured-light law 1.4e-3 z^2 (z in metres).
    """
    z = np.asarray(depth_mm, np.float32)
    try:
        return np.asarray(get_sensor(sensor).sigma_mm(z * np.float32(1e-3)), np.float32)
    except (ImportError, AttributeError, TopsegError):
        return np.float32(KINECT_SIGMA_COEFF * 1e-3) * z * z  # (1.4e-3 / m) * z_mm^2
