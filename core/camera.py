"""Pinhole depth camera and its top-view mount, as data.

Depth is uint16 millimetres, 0 = no measurement. The camera frame is x right, y down,
z forward (RDF). The mount places the camera at `height_mm` above the floor, looking
straight down, so a pixel's depth is its distance from the camera plane.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numba
import numpy as np


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
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera size must be positive, got {self.width}x{self.height}")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"focal lengths must be positive, got fx={self.fx} fy={self.fy}")

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
        from topseg.core.config import from_dict

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
    x = (u - k.cx) * z / k.fx
    y = (v - k.cy) * z / k.fy
    return np.stack([x, y, z], axis=-1)


def project(points_m: np.ndarray, k: Intrinsics) -> np.ndarray:
    """(..., 3) camera-frame points in metres -> (..., 2) pixel coordinates (u, v)."""
    p = np.asarray(points_m, np.float64)
    z = p[..., 2]
    return np.stack([k.fx * p[..., 0] / z + k.cx, k.fy * p[..., 1] / z + k.cy], axis=-1)


@dataclass(frozen=True)
class TopViewMount:
    """A camera on the ceiling, `height_mm` above the floor, looking straight down.

    World frame: x, y on the floor, z up, origin on the floor below the camera.
    Camera x = world x, camera y = -world y, camera z = -world z (looking down).
    """

    intrinsics: Intrinsics = field(default_factory=Intrinsics)
    height_mm: float = 3500.0

    def floor_extent_m(self) -> tuple[float, float]:
        """Width and depth (metres) of the floor area the camera sees."""
        h = self.height_mm / 1000.0
        k = self.intrinsics
        return (k.width * h / k.fx, k.height * h / k.fy)

    def world_to_camera(self, xyz_world_m: np.ndarray) -> np.ndarray:
        """World points (z up, floor at 0) in metres -> camera-frame points."""
        p = np.asarray(xyz_world_m, np.float64)
        h = self.height_mm / 1000.0
        return np.stack([p[..., 0], -p[..., 1], h - p[..., 2]], axis=-1)

    def camera_to_world(self, xyz_cam_m: np.ndarray) -> np.ndarray:
        """Camera-frame points in metres -> world points (the same flip, its own inverse)."""
        p = np.asarray(xyz_cam_m, np.float64)
        h = self.height_mm / 1000.0
        return np.stack([p[..., 0], -p[..., 1], h - p[..., 2]], axis=-1)

    def depth_of_height(self, z_world_m: float) -> float:
        """Depth in mm that a horizontal surface at height `z_world_m` reads."""
        return self.height_mm - 1000.0 * z_world_m

    def to_dict(self) -> dict:
        """The mount as a plain dict (`from_dict` reads it back)."""
        return {"intrinsics": self.intrinsics.to_dict(), "height_mm": self.height_mm}

    @classmethod
    def from_dict(cls, d: dict, source: str = "camera mount") -> TopViewMount:
        """The mount in `d` (`to_dict`'s form); both keys are required."""
        from topseg.core.config import from_dict

        return from_dict(cls, d, source, required=("intrinsics", "height_mm"))


TOP_VIEW = TopViewMount()


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
