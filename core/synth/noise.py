"""Sensor noise for synthetic depth frames: none, the paper's Gaussian, or a Kinect v1 model.

`parse_noise(spec)` turns a spec string into a `NoiseModel` with `apply(depth_u16, rng)`:

- "none": the clean rendering.
- "gaussian:<sigma_mm>": the paper's additive white Gaussian noise on depth, sigma in
  millimetres (swept 0..100 in the paper, best at 15; see docs/noise.md on "15 cm").
- "kinect" (optionally "kinect:key=value,..."): a structured-light Kinect v1 model, each
  effect from how the sensor works (docs/noise.md compares it with real frames):
  * projector shadows: the IR projector sits `baseline_m` to the right of the camera, so
    surfaces it cannot light (left of anything nearer) read no depth;
  * edge dropouts: block matching fails in a band beside shadows (often, widening them as
    in real frames) and beside other depth jumps (seldom);
  * flying pixels: on a jump, some pixels take a depth between the two sides;
  * depth-dependent error: noise in disparity (spatially correlated, like the matcher's
    window) becomes error growing with z^2 in depth (Khoshelham and Elberink 2012:
    sigma ~ 1.4e-3 z^2 m);
  * disparity quantisation: disparity has 1/8 pixel steps, so depth has steps of
    z^2 / (8 f b) (~3 cm at 3.5 m);
  * range limits and isolated speckle dropouts.

Every model keeps 0 (no depth) at 0; the Kinect model also adds zeros. Randomness comes
only from the `numpy.random.Generator` passed in, so a frame seed reproduces a frame.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Protocol

import numba
import numpy as np

from topseg.core.camera import MAX_DEPTH_MM, check_depth, metres_to_mm_scalar
from topseg.core.errors import TopsegError


class NoiseModel(Protocol):
    """What datagen needs of a sensor model: a spec string and `apply`."""

    spec: str

    def apply(self, depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """A noisy copy of uint16 mm `depth`; 0 (no depth) stays 0."""
        ...


@dataclass(frozen=True)
class NoNoise:
    """The clean rendering."""

    @property
    def spec(self) -> str:
        """The spec string `parse_noise` turns back into this model."""
        return "none"

    def apply(self, depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The clean frame, copied."""
        return check_depth(depth, "noise").copy()


@dataclass(frozen=True)
class GaussianNoise:
    """Additive white Gaussian noise with standard deviation `sigma_mm` on every measured pixel."""

    sigma_mm: float

    def __post_init__(self) -> None:
        if not (np.isfinite(self.sigma_mm) and self.sigma_mm >= 0):
            raise TopsegError(f"gaussian noise sigma must be >= 0 mm, got {self.sigma_mm}")

    @property
    def spec(self) -> str:
        """The spec string `parse_noise` turns back into this model."""
        return f"gaussian:{self.sigma_mm:g}"

    def apply(self, depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """`depth` plus rounded N(0, sigma) mm on every measured pixel (clipped to 1..65535)."""
        depth = check_depth(depth, "noise")
        out = depth.copy()
        valid = depth > 0
        if self.sigma_mm == 0 or not valid.any():
            return out
        noisy = depth[valid] + self.sigma_mm * rng.standard_normal(
            int(valid.sum()), dtype=np.float32
        )
        # a measured pixel stays measured: clip to 1 mm rather than turning it into "no depth"
        out[valid] = np.clip(np.rint(noisy), 1, 65535).astype(np.uint16)
        return out


# --- the Kinect v1 model ---------------------------------------------------------------------

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)

# flags from the first pass
SHADOW = 1
JUMP = 2
NEAR_SHADOW = 1
NEAR_JUMP = 2


@numba.njit(cache=True, inline="always")
def _hash_uniform(seed, index):
    """Uniform [0, 1) from (seed, index): splitmix64, a counter-based generator."""
    z = seed + np.uint64(index) * _GOLDEN
    z = (z ^ (z >> np.uint64(30))) * _MIX1
    z = (z ^ (z >> np.uint64(27))) * _MIX2
    z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@numba.njit(cache=True, inline="always")
def _is_jump(depth, v, u, z, jump_m):
    if depth[v, u] == 0:
        return False
    return abs(depth[v, u] * 0.001 - z) > jump_m


@numba.njit(parallel=True, cache=True)
def _flags_kernel(depth, fb, jump_m, band, flags, near_h):
    """Per pixel: SHADOW when the projector cannot light it, JUMP beside a depth step;
    near_h: whether a flagged or empty pixel lies within `band` columns (same row)."""
    h, w = depth.shape
    for v in numba.prange(h):
        # projector column of each pixel is u - fb / z; scanning right to left, a pixel is
        # shadowed when something to its right reaches a smaller projector column
        run_min = np.inf
        for u in range(w - 1, -1, -1):
            f = 0
            d = depth[v, u]
            if d > 0:
                z = d * 0.001
                up = u - fb / z
                if up > run_min + 1e-9:
                    f |= SHADOW
                if up < run_min:
                    run_min = up
                if u > 0 and _is_jump(depth, v, u - 1, z, jump_m):
                    f |= JUMP
                elif u < w - 1 and _is_jump(depth, v, u + 1, z, jump_m):
                    f |= JUMP
                elif v > 0 and _is_jump(depth, v - 1, u, z, jump_m):
                    f |= JUMP
                elif v < h - 1 and _is_jump(depth, v + 1, u, z, jump_m):
                    f |= JUMP
            flags[v, u] = f
        # horizontal pass of the bands: NEAR_SHADOW within `band` columns of a shadow or a
        # pixel without depth, NEAR_JUMP within `band` columns of a jump
        last_s = -(1 << 30)
        last_j = -(1 << 30)
        for u in range(w):
            if (flags[v, u] & SHADOW) != 0 or depth[v, u] == 0:
                last_s = u
            if (flags[v, u] & JUMP) != 0:
                last_j = u
            near_h[v, u] = (NEAR_SHADOW if u - last_s <= band else 0) | (
                NEAR_JUMP if u - last_j <= band else 0
            )
        last_s = 1 << 30
        last_j = 1 << 30
        for u in range(w - 1, -1, -1):
            if (flags[v, u] & SHADOW) != 0 or depth[v, u] == 0:
                last_s = u
            if (flags[v, u] & JUMP) != 0:
                last_j = u
            if last_s - u <= band:
                near_h[v, u] |= NEAR_SHADOW
            if last_j - u <= band:
                near_h[v, u] |= NEAR_JUMP


@numba.njit(parallel=True, cache=True)
def _kinect_kernel(
    depth,
    flags,
    near_h,
    field,
    cell,
    seed,
    fb,
    subpixel,
    sigma_px,
    band,
    p_shadow,
    p_edge,
    p_fly,
    p_speckle,
    zmin,
    zmax,
    out,
):
    h, w = depth.shape
    for v in numba.prange(h):
        v0 = max(0, v - band)
        v1 = min(h, v + band + 1)
        y = v / cell
        j0 = int(y)
        ty = y - j0
        for u in range(w):
            idx = (v * w + u) * 4
            out[v, u] = 0
            d0 = depth[v, u]
            if d0 == 0 or (flags[v, u] & SHADOW) != 0:
                continue
            # bands beside shadows and jumps where block matching may fail
            near = 0
            for vv in range(v0, v1):
                near |= near_h[vv, u]
            p_drop = p_shadow if (near & NEAR_SHADOW) != 0 else (p_edge if near != 0 else 0.0)
            if p_drop > 0 and _hash_uniform(seed, idx) < p_drop:
                continue
            if p_speckle > 0 and _hash_uniform(seed, idx + 1) < p_speckle:
                continue
            disp = fb / (d0 * 0.001)
            if (flags[v, u] & JUMP) != 0 and _hash_uniform(seed, idx + 2) < p_fly:
                # a flying pixel: between this depth and the most different neighbour's
                other = np.int64(d0)
                for k in range(4):
                    vv = v + (0, 0, -1, 1)[k]
                    uu = u + (-1, 1, 0, 0)[k]
                    if 0 <= vv < h and 0 <= uu < w and depth[vv, uu] > 0:
                        n = np.int64(depth[vv, uu])
                        if abs(n - d0) > abs(other - d0):
                            other = n
                a = 0.2 + 0.6 * _hash_uniform(seed, idx + 3)
                disp = (1.0 - a) * disp + a * fb / (other * 0.001)
            # spatially correlated disparity noise: bilinear in a coarse normal field,
            # renormalised so its variance is 1 everywhere
            x = u / cell
            i0 = int(x)
            tx = x - i0
            w00 = (1 - tx) * (1 - ty)
            w01 = tx * (1 - ty)
            w10 = (1 - tx) * ty
            w11 = tx * ty
            n = (
                w00 * field[j0, i0]
                + w01 * field[j0, i0 + 1]
                + w10 * field[j0 + 1, i0]
                + w11 * field[j0 + 1, i0 + 1]
            )
            disp += sigma_px * n / np.sqrt(w00 * w00 + w01 * w01 + w10 * w10 + w11 * w11)
            disp = np.floor(disp * subpixel + 0.5) / subpixel
            if disp <= 0:
                continue
            z = fb / disp
            if z < zmin or z > zmax:
                continue
            out[v, u] = metres_to_mm_scalar(z)  # zmax <= 65.535 m: never clipped


@dataclass(frozen=True)
class KinectNoise:
    """A Kinect v1 (structured light) sensor model; see the module doc for each effect."""

    focal_px: float = 580.0  # IR camera focal length (disparity is measured there)
    baseline_m: float = 0.075  # projector to the right of the IR camera
    subpixel: int = 8  # disparity resolution: 1/8 pixel
    disparity_sigma_px: float = 0.04  # matching noise; with the 1/8 px steps ~1.25e-3 z^2 m
    noise_cell_px: int = 4  # correlation length of the matching noise
    jump_m: float = 0.10  # a depth step larger than this is an edge
    edge_band_px: int = 2  # band beside shadows and jumps where matching may fail
    shadow_dropout: float = 0.8  # chance a pixel in the band beside a shadow reads nothing
    edge_dropout: float = 0.05  # chance a pixel in the band beside a jump reads nothing
    flying: float = 0.2  # chance a pixel on a jump mixes the depths of both sides
    speckle: float = 0.001  # isolated dropouts anywhere
    min_range_m: float = 0.5
    max_range_m: float = 8.0

    def __post_init__(self) -> None:
        for name in ("shadow_dropout", "edge_dropout", "flying", "speckle"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise TopsegError(f"kinect noise: {name} is a probability in [0, 1], got {v}")
        if self.focal_px <= 0 or self.baseline_m < 0 or self.subpixel < 1 or self.noise_cell_px < 1:
            raise TopsegError(
                "kinect noise: focal_px > 0, baseline_m >= 0, subpixel >= 1, noise_cell_px >= 1"
            )
        if self.disparity_sigma_px < 0 or self.edge_band_px < 0 or self.jump_m <= 0:
            raise TopsegError(
                "kinect noise: disparity_sigma_px >= 0, edge_band_px >= 0, jump_m > 0"
            )
        if not 0 <= self.min_range_m < self.max_range_m <= MAX_DEPTH_MM / 1000.0:
            raise TopsegError("kinect noise: 0 <= min_range_m < max_range_m <= 65.535 (uint16 mm)")

    @property
    def fb(self) -> float:
        """focal length x baseline (pixel metres): disparity = fb / z."""
        return self.focal_px * self.baseline_m

    def depth_step_mm(self, z_m: float) -> float:
        """Spacing of the depth levels the sensor can report at depth `z_m`."""
        return 1000.0 * z_m * z_m / (self.subpixel * self.fb)

    def sigma_mm(self, z_m: float) -> float:
        """Standard deviation of the depth error at `z_m`: matching noise plus quantisation."""
        sd = np.hypot(self.disparity_sigma_px, (1.0 / self.subpixel) / np.sqrt(12.0))
        return 1000.0 * z_m * z_m * sd / self.fb

    @property
    def spec(self) -> str:
        """'kinect' and the parameters that differ from the defaults, as `parse_noise` reads them."""
        changed = [
            f"{f.name}={getattr(self, f.name):g}"
            for f in fields(self)
            if getattr(self, f.name) != f.default
        ]
        return "kinect" + (":" + ",".join(changed) if changed else "")

    def draws(self, shape: tuple[int, int], rng: np.random.Generator) -> tuple[np.ndarray, int]:
        """The random inputs of one frame: the coarse noise field and the hash seed."""
        h, w = shape
        c = self.noise_cell_px
        field = rng.standard_normal((h // c + 2, w // c + 2))
        seed = int(rng.integers(0, 2**63))
        return field, seed

    def flags(self, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """SHADOW / JUMP flags of each pixel, and the row-wise part of the edge band."""
        flags = np.empty(depth.shape, np.uint8)
        near_h = np.empty(depth.shape, np.uint8)
        _flags_kernel(depth, self.fb, self.jump_m, self.edge_band_px, flags, near_h)
        return flags, near_h

    def apply(self, depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The frame as this Kinect would measure it; the draws come from `rng`."""
        depth = check_depth(depth, "noise")
        field, seed = self.draws(depth.shape, rng)
        out = np.empty_like(depth)
        _kinect_kernel(
            depth, *self.flags(depth), field, float(self.noise_cell_px), np.uint64(seed), self.fb, float(self.subpixel),
            self.disparity_sigma_px, self.edge_band_px, self.shadow_dropout, self.edge_dropout, self.flying, self.speckle,
            self.min_range_m, self.max_range_m, out,
        )  # fmt: skip
        return out

    def to_dict(self) -> dict:
        """The parameters by name."""
        return asdict(self)


def parse_noise(spec: str) -> NoiseModel:
    """ "none", "gaussian:<sigma_mm>" or "kinect[:key=value,...]" -> a noise model."""
    if not isinstance(spec, str):
        raise TopsegError(f"noise spec must be a string, got {type(spec).__name__}")
    name, _, arg = spec.strip().partition(":")
    name = name.lower()
    if name == "none" and not arg:
        return NoNoise()
    if name == "gaussian":
        try:
            sigma = float(arg)
        except ValueError:
            raise TopsegError(
                f"noise {spec!r}: expected gaussian:<sigma_mm>, e.g. gaussian:15"
            ) from None
        return GaussianNoise(sigma)
    if name == "kinect":
        kwargs = {}
        known = {f.name: f.type for f in fields(KinectNoise)}
        for item in filter(None, (s.strip() for s in arg.split(","))):
            key, eq, value = item.partition("=")
            if not eq or key not in known:
                raise TopsegError(
                    f"noise {spec!r}: unknown kinect parameter {key!r}; known: {', '.join(known)}"
                )
            try:
                kwargs[key] = (
                    int(value)
                    if key in ("subpixel", "noise_cell_px", "edge_band_px")
                    else float(value)
                )
            except ValueError:
                raise TopsegError(f"noise {spec!r}: {key} needs a number, got {value!r}") from None
        return KinectNoise(**kwargs)
    raise TopsegError(f"unknown noise {spec!r}; use none, gaussian:<sigma_mm> or kinect")
