"""Pinhole depth camera and its top-view mount, as data.

Depth is uint16 millimetres, 0 = no measurement. The camera frame is x right, y down,
z forward (RDF). The mount places the camera at `height_mm` above the floor, looking
down with a small pitch and roll; `TopViewMount.height_map_mm` turns depth into height above
the floor, which is what the model reads.
"""

from __future__ import annotations

import functools
from dataclasses import asdict, dataclass

import numba
import numpy as np

from topseg.core.config import from_dict

#: the widest or tallest frame a camera may have, px (a sanity bound on intrinsics read from files)
MAX_CAMERA_SIDE = 16384


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics; the defaults are Kinect v1's depth camera."""

    width: int = 640
    height: int = 480
    fx: float = 570.3
    fy: float = 570.3
    cx: float = 319.5
    cy: float = 239.5

    def __post_init__(self) -> None:
        if not (0 < self.width <= MAX_CAMERA_SIDE and 0 < self.height <= MAX_CAMERA_SIDE):
            raise ValueError(
                f"camera size must be positive and at most {MAX_CAMERA_SIDE} px a side, "
                f"got {self.width}x{self.height}"
            )
        if not all(np.isfinite(v) and v > 0 for v in (self.fx, self.fy)):
            raise ValueError(f"focal lengths must be positive, got fx={self.fx} fy={self.fy}")
        if not (np.isfinite(self.cx) and np.isfinite(self.cy)):
            raise ValueError(f"the principal point must be finite, got ({self.cx}, {self.cy})")

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of a frame, numpy order."""
        return (self.height, self.width)

    def to_dict(self) -> dict:
        """The intrinsics as a plain dict (`from_dict` reads it back)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict, source: str = "camera intrinsics") -> Intrinsics:
        """The intrinsics in `d`; all six keys are required (no silent Kinect fallback)."""
        return from_dict(cls, d, source, required=("width", "height", "fx", "fy", "cx", "cy"))

    def scaled_to(self, width: int, height: int) -> Intrinsics:
        """The same optics resampled to another resolution."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(
            width,
            height,
            self.fx * sx,
            self.fy * sy,
            (self.cx + 0.5) * sx - 0.5,
            (self.cy + 0.5) * sy - 0.5,
        )

    def field_of_view_deg(self) -> tuple[float, float]:
        """Horizontal and vertical field of view in degrees."""
        fov_x = 2 * np.degrees(np.arctan2(self.width / 2, self.fx))
        fov_y = 2 * np.degrees(np.arctan2(self.height / 2, self.fy))
        return float(fov_x), float(fov_y)


KINECT_V1 = Intrinsics()


def check_depth(depth: np.ndarray, user: str = "depth") -> np.ndarray:
    """`depth` as a C-contiguous (H, W) uint16 frame in mm; ValueError naming `user` if not."""
    depth = np.asarray(depth)
    if depth.ndim != 2 or depth.dtype != np.uint16:
        raise ValueError(
            f"{user} needs a (H, W) uint16 depth frame in mm, got {depth.dtype} {depth.shape}"
        )
    return np.ascontiguousarray(depth)


#: the reading several cameras send for "no measurement" instead of 0
NO_READING_MM = 65535


def without_no_reading(depth: np.ndarray) -> np.ndarray:
    """`depth` with readings of `NO_READING_MM` (how several cameras say "no reading") set to
    0, no depth, as calibration reads them: the frame itself when it has none (no copy), a
    copy otherwise. Anything but a (H, W) uint16 frame is returned as it is, for the caller's
    own check to refuse."""
    if not isinstance(depth, np.ndarray) or depth.dtype != np.uint16 or depth.ndim != 2:
        return depth
    no_reading = depth == NO_READING_MM
    if not no_reading.any():
        return depth
    out = depth.copy()
    out[no_reading] = 0
    return out


def backproject(depth_mm: np.ndarray, k: Intrinsics) -> np.ndarray:
    """(H, W) depth in mm -> (H, W, 3) float32 points in metres in the camera frame.

    Pixels without depth come out as NaN so callers can mask them.
    """
    depth_mm = np.asarray(depth_mm)
    if depth_mm.shape != k.shape:
        raise ValueError(f"depth shape {depth_mm.shape} does not match camera {k.shape}")
    z = depth_mm.astype(np.float32) / 1000.0
    z[depth_mm == 0] = np.nan
    v, u = np.indices(k.shape, dtype=np.float32)
    return _rays(u, v, z, k)


def backproject_pixels(
    depth_mm: np.ndarray, rows: np.ndarray, cols: np.ndarray, k: Intrinsics
) -> np.ndarray:
    """(N, 3) float32 points in metres in the camera frame of the pixels (rows, cols) of a
    depth frame (`backproject` at those pixels only; without depth, NaN)."""
    depth_mm = np.asarray(depth_mm)
    if depth_mm.shape != k.shape:
        raise ValueError(f"depth shape {depth_mm.shape} does not match camera {k.shape}")
    d = depth_mm[rows, cols]
    z = d.astype(np.float32) / 1000.0
    z[d == 0] = np.nan
    return _rays(np.asarray(cols, np.float32), np.asarray(rows, np.float32), z, k)


def _rays(u: np.ndarray, v: np.ndarray, z: np.ndarray, k: Intrinsics) -> np.ndarray:
    """Pixel coordinates (u right, v down) at depth z (m) -> camera-frame points, last axis."""
    x = (u - k.cx) * z / k.fx
    y = (v - k.cy) * z / k.fy
    return np.stack([x, y, z], axis=-1)


def project(points_m: np.ndarray, k: Intrinsics) -> np.ndarray:
    """(..., 3) camera-frame points in metres -> (..., 2) pixel coordinates (u, v)."""
    p = np.asarray(points_m, np.float64)
    z = p[..., 2]
    return np.stack([k.fx * p[..., 0] / z + k.cx, k.fy * p[..., 1] / z + k.cy], axis=-1)


@functools.lru_cache(maxsize=64)
def _ray_coefficients(k: Intrinsics, normal: tuple[float, float, float]) -> np.ndarray:
    """(H, W) float32 `n . (x/z, y/z, 1)` of each pixel's ray: height = height + depth * it."""
    v, u = np.indices(k.shape, dtype=np.float64)
    a = normal[0] * (u - k.cx) / k.fx + normal[1] * (v - k.cy) / k.fy + normal[2]
    a = a.astype(np.float32)
    a.flags.writeable = False
    return a


@functools.lru_cache(maxsize=16)
def _ray_lengths(k: Intrinsics) -> np.ndarray:
    """(H, W) float64 |(x/z, y/z, 1)| of each pixel's ray: range over depth along the axis."""
    v, u = np.indices(k.shape, dtype=np.float64)
    n = np.sqrt(1.0 + ((u - k.cx) / k.fx) ** 2 + ((v - k.cy) / k.fy) ** 2)
    n.flags.writeable = False
    return n


def range_to_depth(range_mm: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """A range image (uint16 mm along each pixel's ray, what some time-of-flight cameras
    send) as depth along the optical axis: z = range / |(x/z, y/z, 1)|, rounded; 0 stays 0."""
    r = check_depth(range_mm, "range image")
    if r.shape != intrinsics.shape:
        raise ValueError(
            f"range image is {r.shape[1]}x{r.shape[0]} but the camera is "
            f"{intrinsics.width}x{intrinsics.height}"
        )
    return np.rint(r / _ray_lengths(intrinsics)).astype(np.uint16)


def depth_to_range(depth_mm: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """`range_to_depth`'s inverse: the range image a radial-distance camera would send for
    this depth frame (0 stays 0, clipped to the uint16 range)."""
    d = check_depth(depth_mm, "depth frame")
    r = np.rint(d * _ray_lengths(intrinsics))
    return np.minimum(r, MAX_DEPTH_MM).astype(np.uint16)


def axis_depth(depth: np.ndarray, mount: TopViewMount | None) -> np.ndarray:
    """A frame as depth along the optical axis, what REP 118 depth images and pinhole
    viewers expect: `mount.z_depth` of it, or the frame itself without a mount."""
    return depth if mount is None else mount.z_depth(depth)


def range_text(mount: TopViewMount) -> str:
    """', radial distance read as depth' for a camera that sends range (`TopViewMount.radial`),
    '' otherwise: what logs and printed mounts add."""
    return ", radial distance read as depth" if mount.radial else ""


def _rotation(pitch_deg: float, roll_deg: float) -> np.ndarray:
    """Rx(pitch) @ Ry(roll) @ diag(1, -1, -1): world -> camera for a tilted top-view camera."""
    p, r = np.radians(pitch_deg), np.radians(roll_deg)
    cp, sp, cr, sr = np.cos(p), np.sin(p), np.cos(r), np.sin(r)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]])
    ry = np.array([[cr, 0.0, sr], [0.0, 1.0, 0.0], [-sr, 0.0, cr]])
    return rx @ ry @ np.diag([1.0, -1.0, -1.0])


#: the largest tilt (degrees) a mount may have: a top-view camera, not a wall camera
MAX_MOUNT_TILT_DEG = 60.0
#: the measured-over-modelled depth noise a mount may have (`TopViewMount.noise_scale`): a
#: camera more than five times noisier than its sensor model needs a model of its own
NOISE_SCALE_RANGE = (0.05, 5.0)
#: how high above the floor a mount may hang, mm (0.3 to 20 m; calibration reads no farther)
MOUNT_HEIGHT_RANGE_MM = (300.0, 20_000.0)
#: the field of view a mount's camera may have across its width and its height, degrees: the
#: focal lengths a frame of its size can have (a fisheye is no pinhole camera)
FIELD_OF_VIEW_RANGE_DEG = (5.0, 160.0)


def _check_range(name: str, value: float, bounds: tuple[float, float], unit: str = "") -> None:
    """ValueError (one line, `value` as %.3g) unless `value` is finite and within `bounds`."""
    lo, hi = bounds
    if not (np.isfinite(value) and lo <= value <= hi):
        raise ValueError(f"{name} {value:.3g}{unit} is outside {lo:g}..{hi:g}{unit}")


def check_mount(mount: TopViewMount) -> TopViewMount:
    """`mount` when a camera can have it, else ValueError naming the first bad field in one
    line: the one validation of a mount read from a file or received from the wire. Height
    within `MOUNT_HEIGHT_RANGE_MM`, pitch and roll within +-`MAX_MOUNT_TILT_DEG`, `noise_scale`
    within `NOISE_SCALE_RANGE`, focal lengths that give the frame size a field of view within
    `FIELD_OF_VIEW_RANGE_DEG`, the principal point inside the frame."""
    _check_range("height_mm", mount.height_mm, MOUNT_HEIGHT_RANGE_MM, " mm")
    tilt = (-MAX_MOUNT_TILT_DEG, MAX_MOUNT_TILT_DEG)
    _check_range("pitch_deg", mount.pitch_deg, tilt, " deg")
    _check_range("roll_deg", mount.roll_deg, tilt, " deg")
    _check_range("noise_scale", mount.noise_scale, NOISE_SCALE_RANGE)
    k = mount.intrinsics
    lo, hi = FIELD_OF_VIEW_RANGE_DEG
    for name, focal, side in (("fx", k.fx, k.width), ("fy", k.fy, k.height)):
        fov = float(2 * np.degrees(np.arctan2(side / 2, focal)))
        if not lo <= fov <= hi:
            raise ValueError(
                f"intrinsics {name} {focal:.3g} px gives {side} px a field of view of "
                f"{fov:.3g} deg, outside {lo:g}..{hi:g} deg: not this frame size's focal length"
            )
    for name, centre, side in (("cx", k.cx, k.width), ("cy", k.cy, k.height)):
        if not -0.5 <= centre <= side - 0.5:
            raise ValueError(
                f"intrinsics {name} {centre:.3g} px puts the principal point outside the "
                f"{k.width}x{k.height} frame"
            )
    return mount


@dataclass(frozen=True)
class TopViewMount:
    """A camera on the ceiling, `height_mm` above the floor, looking down, tilted a little.

    World frame: x, y on the floor, z up, origin on the floor below the camera centre.
    Camera frame: x right, y down, z forward (RDF). A point maps as
    `p_cam = R @ (p_world - centre)` with `R = Rx(pitch) @ Ry(roll) @ diag(1, -1, -1)`:
    straight down (pitch = roll = 0) camera x = world x, camera y = -world y, camera
    z = -world z. Positive pitch turns the optical axis towards the image's bottom rows
    (the floor there reads farther); positive roll towards its left columns. The floor
    fixes only pitch and roll; the heading about the vertical is taken as zero.

    `height_mm` has no default: a mount comes from calibration (`core/calibration.py`),
    from the frames' own metadata, or from a training distribution, never from a constant.
    `sensor` names a sensor model in `core/sensors.py` (its noise family and ranges).
    `noise_scale` is the depth noise measured on this camera's floor (the calibration's
    residual) over the sensor model's at those depths: it scales the floor gate's margin,
    so a quieter camera than its sensor model keeps more of the feet. 1 when not measured.
    `radial` says the camera sends range along each pixel's ray (radial distance, as some
    time-of-flight cameras do), not depth along the optical axis: `z_depth` turns its frames
    into depth before anything measures heights from them. Calibration finds it out.
    `edge_thinning` False says the camera's depth edges are not fattened even though its
    sensor is a stereo one (its own filters cleaned them): its frames are then not thinned
    (`core/fattening.py`). True thins them as its sensor model says, which does nothing for
    a sensor that does not fatten edges.
    """

    intrinsics: Intrinsics
    height_mm: float
    pitch_deg: float = 0.0
    roll_deg: float = 0.0
    sensor: str = "kinect_v1"
    noise_scale: float = 1.0
    radial: bool = False
    edge_thinning: bool = True

    def __post_init__(self) -> None:
        if not (np.isfinite(self.height_mm) and self.height_mm > 0):
            raise ValueError(
                f"mount height_mm must be a positive number of mm, got {self.height_mm:.3g}"
            )
        for name in ("pitch_deg", "roll_deg"):
            angle = getattr(self, name)
            if not (np.isfinite(angle) and abs(angle) <= MAX_MOUNT_TILT_DEG):
                raise ValueError(
                    f"mount {name} must be within +-{MAX_MOUNT_TILT_DEG:g} degrees, got {angle:.3g}"
                )
        if not self.sensor:
            raise ValueError("mount sensor must be a sensor name, got an empty string")
        lo, hi = NOISE_SCALE_RANGE
        if not (np.isfinite(self.noise_scale) and lo <= self.noise_scale <= hi):
            raise ValueError(
                f"mount noise_scale must be within {lo:g}..{hi:g}, got {self.noise_scale:.3g}"
            )

    # --- geometry ------------------------------------------------------------------------

    def rotation_world_to_camera(self) -> np.ndarray:
        """(3, 3) float64 R with `p_cam = R @ (p_world - centre)`; straight down diag(1,-1,-1)."""
        return _rotation(self.pitch_deg, self.roll_deg)

    def centre_world_m(self) -> np.ndarray:
        """The camera centre in world metres: (0, 0, height)."""
        return np.array([0.0, 0.0, self.height_mm / 1000.0])

    def world_to_camera(self, xyz_world_m: np.ndarray) -> np.ndarray:
        """World points (z up, floor at 0) in metres -> camera-frame points (float64)."""
        p = np.asarray(xyz_world_m, np.float64)
        return (p - self.centre_world_m()) @ self.rotation_world_to_camera().T

    def camera_to_world(self, xyz_cam_m: np.ndarray) -> np.ndarray:
        """Camera-frame points in metres -> world points (float64); `world_to_camera`'s inverse."""
        p = np.asarray(xyz_cam_m, np.float64)
        return p @ self.rotation_world_to_camera() + self.centre_world_m()

    def up_normal_camera(self) -> np.ndarray:
        """The floor's unit up-normal (towards the camera) in camera coordinates."""
        return self.rotation_world_to_camera()[:, 2].copy()

    def floor_pixel_mm(self) -> float:
        """How much floor (mm) a pixel spans straight below the camera: height / fx."""
        return self.height_mm / self.intrinsics.fx

    def tilt_deg(self) -> float:
        """Angle in degrees between the optical axis and straight down."""
        return float(np.degrees(np.arccos(np.clip(-self.up_normal_camera()[2], -1.0, 1.0))))

    def height_map_mm(self, depth_mm: np.ndarray) -> np.ndarray:
        """(H, W) float32 height above the floor (mm) of each pixel's point; NaN without depth.

        `height_mm + n . X` with n the floor's up-normal and X the back-projected point in mm
        (a `radial` camera's frame read as depth first, `z_depth`).
        """
        depth_mm = np.asarray(depth_mm)
        if depth_mm.shape != self.intrinsics.shape:
            raise ValueError(
                f"depth shape {depth_mm.shape} does not match camera {self.intrinsics.shape}"
            )
        depth_mm = self.z_depth(depth_mm)
        z = depth_mm.astype(np.float32)
        h = z * self.height_rays() + np.float32(self.height_mm)
        h[depth_mm == 0] = np.nan
        return h

    def z_depth(self, frame: np.ndarray) -> np.ndarray:
        """This camera's frame as depth along the optical axis: the frame itself, or for a
        `radial` camera `range_to_depth` of it."""
        return range_to_depth(frame, self.intrinsics) if self.radial else frame

    def height_rays(self) -> np.ndarray:
        """(H, W) float32 read-only `n . (x/z, y/z, 1)` of each pixel's ray (n the floor's
        up-normal): a point at depth z (mm) is `height_mm + z * it` mm above the floor.
        Cached per camera and normal."""
        return _ray_coefficients(self.intrinsics, tuple(float(x) for x in self.up_normal_camera()))

    @classmethod
    def from_floor_plane(
        cls,
        normal_cam: np.ndarray,
        offset_mm: float,
        intrinsics: Intrinsics,
        sensor: str = "kinect_v1",
    ) -> TopViewMount:
        """The mount whose floor is the plane `n . X + offset = 0` (X in camera mm).

        `n` is the floor's normal in camera coordinates, pointing up (towards the camera);
        it is normalised here (and flipped, with the offset, if it points down).
        """
        n = np.asarray(normal_cam, np.float64).reshape(3)
        norm = float(np.linalg.norm(n))
        if not np.isfinite(norm) or norm == 0.0:
            raise ValueError(f"floor normal must be a non-zero vector, got {n.tolist()}")
        n, d = n / norm, float(offset_mm) / norm
        if n[2] > 0:  # pointing away from the camera: the same plane, the other side
            n, d = -n, -d
        # n = Rx(p) Ry(r) (0, 0, -1) = (-sin r, sin p cos r, -cos p cos r)
        roll = np.degrees(np.arctan2(-n[0], np.hypot(n[1], n[2])))
        pitch = np.degrees(np.arctan2(n[1], -n[2]))
        return cls(intrinsics, d, float(pitch), float(roll), sensor)

    def floor_extent_m(self) -> tuple[float, float]:
        """Width and depth (metres) of the floor area a straight-down camera would see."""
        h = self.height_mm / 1000.0
        k = self.intrinsics
        return (k.width * h / k.fx, k.height * h / k.fy)

    def depth_of_height(self, z_world_m: float) -> float:
        """Depth in mm that a horizontal surface at height `z_world_m` reads on the optical axis."""
        cos_tilt = -float(self.up_normal_camera()[2])
        return (self.height_mm - 1000.0 * z_world_m) / cos_tilt

    # --- as data -------------------------------------------------------------------------

    def to_dict(self) -> dict:
        """The mount as a plain dict (`from_dict` reads it back)."""
        return {
            "intrinsics": self.intrinsics.to_dict(),
            "height_mm": float(self.height_mm),
            "pitch_deg": float(self.pitch_deg),
            "roll_deg": float(self.roll_deg),
            "sensor": self.sensor,
            "noise_scale": float(self.noise_scale),
        } | (
            ({"radial": True} if self.radial else {})  # absent for depth: older readers load it
            | ({} if self.edge_thinning else {"edge_thinning": False})  # likewise when on
        )

    @classmethod
    def from_dict(cls, d: dict, source: str = "camera mount") -> TopViewMount:
        """The mount in `d` (`to_dict`'s form). `intrinsics` and `height_mm` are required;
        the tilt, sensor, noise scale, `radial` and `edge_thinning` default (straight down,
        Kinect v1, as modelled, depth, thinned as the sensor model says), so a dict that
        lacks them still loads."""
        return from_dict(cls, d, source, required=("intrinsics", "height_mm"))


#: The paper's mount: a Kinect v1 3.5 m above the floor, looking straight down. For
#: reproducing the paper's experiments only; real cameras are calibrated (`topseg calibrate`).
PAPER_MOUNT = TopViewMount(KINECT_V1, 3.5 * 1000)  # the paper's setting, in mm

#: the largest depth a uint16 mm frame holds
MAX_DEPTH_MM = 65535


@numba.njit(cache=True, inline="always")
def metres_to_mm_scalar(z_m: float) -> int:
    """`metres_to_mm` of one value, for numba kernels: round half up, 0 when out of range."""
    mm = np.floor(z_m * 1000.0 + 0.5)
    if mm > 0.0 and mm <= 65535.0:  # False for NaN and +-inf too
        return int(mm)
    return 0


def metres_to_mm(depth_m: np.ndarray) -> np.ndarray:
    """Depth in metres -> uint16 mm, the one conversion: rounded half up (floor(1000 z + 0.5)),
    0 (no depth) where not finite, below 0.5 mm or beyond the uint16 range."""
    mm = np.floor(np.asarray(depth_m, np.float64) * 1000.0 + 0.5)
    ok = (mm > 0) & (mm <= MAX_DEPTH_MM)  # False for NaN and +-inf too
    out = np.zeros(mm.shape, np.uint16)
    out[ok] = mm[ok].astype(np.uint16)
    return out
