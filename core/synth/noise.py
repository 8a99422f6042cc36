"""Sensor noise for synthetic depth frames: none, the paper's Gaussian, or a Kinect v1 model.

`parse_noise(spec)` turns a spec string into a `NoiseModel` with `apply(depth_u16, rng)`:

- "none": the clean rendering.
- "gaussian:<sigma_mm>": the paper's additive white Gaussian noise on depth, sigma in
  millimetres (swept 0..100 in the paper, best at 15; see docs/explanation/noise.md on "15 cm").
- "kinect" (optionally "kinect:key=value,..."): a structured-light Kinect v1 model, each
  effect from how the sensor works (docs/explanation/noise.md compares it with real frames):
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
from statistics import NormalDist
from typing import Protocol

import numba
import numpy as np

from topseg.core.camera import MAX_DEPTH_MM, check_depth, metres_to_mm_scalar
from topseg.core.errors import TopsegError
from topseg.core.labels import HEAD


class NoiseModel(Protocol):
    """What datagen needs of a sensor model: a spec string and `apply`."""

    spec: str

    def apply(
        self, depth: np.ndarray, rng: np.random.Generator, labels: np.ndarray | None = None
    ) -> np.ndarray:
        """A noisy copy of uint16 mm `depth`; 0 (no depth) stays 0. `labels` (the renderer's
        per-pixel label ids), where given, tells models that care which surfaces are dark."""
        ...


@dataclass(frozen=True)
class NoNoise:
    """The clean rendering."""

    @property
    def spec(self) -> str:
        """The spec string `parse_noise` turns back into this model."""
        return "none"

    def apply(
        self, depth: np.ndarray, rng: np.random.Generator, labels: np.ndarray | None = None
    ) -> np.ndarray:
        """The clean frame, copied (`labels` is not used)."""
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

    def apply(
        self, depth: np.ndarray, rng: np.random.Generator, labels: np.ndarray | None = None
    ) -> np.ndarray:
        """`depth` plus rounded N(0, sigma) mm on every measured pixel (clipped to 1..65535);
        `labels` is not used."""
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

    def apply(
        self, depth: np.ndarray, rng: np.random.Generator, labels: np.ndarray | None = None
    ) -> np.ndarray:
        """The frame as this Kinect would measure it; the draws come from `rng` (`labels` is
        not used: the model has no surface-dependent effect)."""
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


# --- shared pieces of the time-of-flight and stereo models -------------------------------------


@numba.njit(cache=True, inline="always")
def _field_at(field, u, v, cell):
    """A coarse normal field, bilinear at pixel (v, u) and renormalised to unit variance."""
    x = u / cell
    i0 = int(x)
    tx = x - i0
    y = v / cell
    j0 = int(y)
    ty = y - j0
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
    return n / np.sqrt(w00 * w00 + w01 * w01 + w10 * w10 + w11 * w11)


def _coarse_field(shape: tuple[int, int], cell: int, rng: np.random.Generator) -> np.ndarray:
    """The coarse normal field `_field_at` interpolates, for a frame of `shape`."""
    h, w = shape
    return rng.standard_normal((h // cell + 2, w // cell + 2))


def _normal_quantile(p: float) -> float:
    """Phi^-1(p): thresholding a unit normal field there marks a share p of the pixels."""
    if p <= 0.0:
        return -np.inf
    if p >= 1.0:
        return np.inf
    return NormalDist().inv_cdf(p)


def _check_probabilities(model, family: str, names: tuple[str, ...]) -> None:
    for name in names:
        v = getattr(model, name)
        if not 0.0 <= v <= 1.0:
            raise TopsegError(f"{family} noise: {name} is a probability in [0, 1], got {v}")


def _check_range(model, family: str) -> None:
    if not 0 <= model.min_range_m < model.max_range_m <= MAX_DEPTH_MM / 1000.0:
        raise TopsegError(f"{family} noise: 0 <= min_range_m < max_range_m <= 65.535 (uint16 mm)")


def _spec_of(model, name: str) -> str:
    """`name` and the parameters that differ from the defaults, as `parse_noise` reads them."""
    changed = [
        f"{f.name}={getattr(model, f.name):g}"
        for f in fields(model)
        if getattr(model, f.name) != f.default
    ]
    return name + (":" + ",".join(changed) if changed else "")


def _check_labels(labels: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray | None:
    if labels is None:
        return None
    labels = np.asarray(labels)
    if labels.shape != shape:
        raise ValueError(f"noise: labels {labels.shape} do not match the depth frame {shape}")
    return np.ascontiguousarray(labels, dtype=np.uint8)


# --- time of flight (Kinect v2 / Azure Kinect) -------------------------------------------------


@numba.njit(cache=True, inline="always")
def _concavity(depth, v, u, s, jump_mm):
    """How sharply the surface bends away from the camera at (v, u), seen over `s` px:
    max over rows and columns of d0/d(-s) + d0/d(+s) - 2 (0 on any plane, since inverse
    depth is linear in the image there; > 0 in a concave corner). Segments that leave the
    frame, miss depth or cross a jump of more than `jump_mm` between neighbours count 0."""
    h, w = depth.shape
    d0 = np.float64(depth[v, u])
    best = 0.0
    for axis in range(2):
        dv = 1 if axis == 0 else 0
        du = 0 if axis == 0 else 1
        if v - s * dv < 0 or v + s * dv >= h or u - s * du < 0 or u + s * du >= w:
            continue
        ok = True
        for k in range(-s, s + 1):
            a = depth[v + k * dv, u + k * du]
            if a == 0:
                ok = False
                break
            if k < s:
                b = depth[v + (k + 1) * dv, u + (k + 1) * du]
                if abs(np.int64(a) - np.int64(b)) > jump_mm:
                    ok = False
                    break
        if not ok:
            continue
        c = d0 / depth[v - s * dv, u - s * du] + d0 / depth[v + s * dv, u + s * du] - 2.0
        if c > best:
            best = c
    return best


@numba.njit(parallel=True, cache=True)
def _tof_kernel(
    depth,
    dark,
    gauss,
    dark_field,
    dark_cell,
    seed,
    c0,
    c1,
    c2,
    corner_sigma,
    jump_mm,
    flying_px,
    flying,
    edge_invalid,
    multipath_mm,
    multipath_px,
    concave_min,
    concave_full,
    dark_thr,
    dark_sigma,
    border_px,
    fov_radius,
    speckle,
    zmin,
    zmax,
    out,
):
    h, w = depth.shape
    cx = (w - 1) / 2.0
    cy = (h - 1) / 2.0
    fov_px2 = fov_radius * fov_radius * (w * w + h * h) / 4.0  # a circle, in square pixels
    for v in numba.prange(h):
        for u in range(w):
            idx = (v * w + u) * 4
            out[v, u] = 0
            d0 = depth[v, u]
            if d0 == 0:
                continue
            if u < border_px or v < border_px or u >= w - border_px or v >= h - border_px:
                continue
            if (u - cx) * (u - cx) + (v - cy) * (v - cy) > fov_px2:
                continue
            # normalised radius: 1 at the image corners
            rx = (u - cx) / (w / 2.0)
            ry = (v - cy) / (h / 2.0)
            r2 = (rx * rx + ry * ry) / 2.0
            is_dark = dark[v, u] != 0
            if is_dark and _field_at(dark_field, u, v, dark_cell) < dark_thr:
                continue
            if speckle > 0 and _hash_uniform(seed, idx + 3) < speckle:
                continue
            z = d0 * 0.001
            # flying (mixed) pixels: a band of `flying_px` around every depth jump
            lo = np.int64(d0)
            hi = np.int64(d0)
            for vv in range(max(0, v - flying_px), min(h, v + flying_px + 1)):
                for uu in range(max(0, u - flying_px), min(w, u + flying_px + 1)):
                    n = np.int64(depth[vv, uu])
                    if n > 0:
                        if n < lo:
                            lo = n
                        if n > hi:
                            hi = n
            if hi - lo > jump_mm:
                if edge_invalid > 0 and _hash_uniform(seed, idx) < edge_invalid:
                    continue
                if _hash_uniform(seed, idx + 1) < flying:
                    a = 0.2 + 0.6 * _hash_uniform(seed, idx + 2)
                    z = (lo + a * (hi - lo)) * 0.001
            # multipath: over-estimated depth in concave corners
            if multipath_mm > 0:
                c = _concavity(depth, v, u, multipath_px, jump_mm)
                if c > concave_min:
                    f = min(1.0, (c - concave_min) / (concave_full - concave_min))
                    z += 0.001 * multipath_mm * f
            sigma = (c0 + c1 * z + c2 * z * z) * (1.0 + (corner_sigma - 1.0) * r2)
            if is_dark:
                sigma *= dark_sigma
            z += 0.001 * sigma * gauss[v, u]
            if z < zmin or z > zmax:
                continue
            out[v, u] = metres_to_mm_scalar(z)


@dataclass(frozen=True)
class ToFNoise:
    """A time-of-flight sensor model (Kinect v2 defaults; docs/reference/sensors.md gives the sources).

    Effects: range-dependent Gaussian noise sigma(z) = c0 + c1 z + c2 z^2 mm (Fankhauser et
    al. 2015), growing towards the image corners (less light there); flying pixels mixing
    foreground and background depth in a band of `flying_px` around depth jumps (or, with
    `edge_invalid`, dropped as the Azure depth engine does); multipath: depth over-estimated
    by up to `multipath_mm` within `multipath_px` of a concave corner (floor meets wall or
    furniture); patchy dropout and extra noise on dark hair (pixels labelled head, when
    `apply` gets the renderer's labels); an invalid border, a circular valid region (radius
    `fov_radius` of the half-diagonal; in a share `fov_cut` of frames a smaller one, drawn
    from [`fov_cut_min`, `fov_radius`]: wide-view masks, vignetting, views resampled from
    another camera), isolated speckle and the range limits.
    """

    sigma_c0_mm: float = 1.5  # sigma(z) = c0 + c1 z + c2 z^2 mm, z in m (Fankhauser 2015)
    sigma_c1_mm: float = -0.5
    sigma_c2_mm: float = 0.3
    corner_sigma: float = 2.0  # noise multiplier at the image corners (falls off as r^2)
    jump_m: float = 0.10  # neighbours further apart than this make a depth edge
    flying_px: int = 1  # half-width of the mixed-pixel band around an edge
    flying: float = 0.5  # chance a band pixel reads a mix of both sides
    edge_invalid: float = 0.0  # chance a band pixel is dropped instead (Azure: high)
    multipath_mm: float = 20.0  # bias in the sharpest concave corner
    multipath_px: int = 6  # how far from the corner line the bias reaches
    concave_min: float = 0.002  # bend (d0/d- + d0/d+ - 2) below which there is no bias
    concave_full: float = 0.02  # bend at which the bias is full
    dark_dropout: float = 0.3  # share of dark (hair) pixels without depth, in patches
    dark_sigma: float = 3.0  # noise multiplier on dark pixels that keep depth
    dark_cell_px: int = 3  # size of the dropout patches
    border_px: int = 1  # invalid rows / columns at the frame's edge
    fov_radius: float = 1.0  # no depth beyond this share of the half-diagonal (1: the corners)
    fov_cut: float = 0.0  # share of frames whose valid circle is smaller, drawn per frame
    fov_cut_min: float = 0.6  # the smallest such circle, as a share of the half-diagonal
    speckle: float = 0.0005  # isolated dropouts anywhere
    min_range_m: float = 0.5
    max_range_m: float = 6.0

    def __post_init__(self) -> None:
        _check_probabilities(
            self, "tof", ("flying", "edge_invalid", "dark_dropout", "speckle", "fov_cut")
        )
        if (
            self.flying_px < 1
            or self.multipath_px < 1
            or self.dark_cell_px < 1
            or self.border_px < 0
        ):
            raise TopsegError(
                "tof noise: flying_px, multipath_px, dark_cell_px >= 1 and border_px >= 0"
            )
        if (
            self.jump_m <= 0
            or self.multipath_mm < 0
            or self.corner_sigma < 0
            or self.dark_sigma < 0
        ):
            raise TopsegError(
                "tof noise: jump_m > 0 and multipath_mm, corner_sigma, dark_sigma >= 0"
            )
        if not 0 <= self.concave_min < self.concave_full:
            raise TopsegError("tof noise: 0 <= concave_min < concave_full")
        if self.fov_radius <= 0:
            raise TopsegError("tof noise: fov_radius > 0")
        if self.fov_cut > 0 and not 0 < self.fov_cut_min <= self.fov_radius:
            raise TopsegError("tof noise: with fov_cut, 0 < fov_cut_min <= fov_radius")
        z = np.linspace(self.min_range_m, min(self.max_range_m, 10.0), 50)
        if np.any(self.sigma_mm(z) < 0):
            raise TopsegError("tof noise: sigma(z) = c0 + c1 z + c2 z^2 must be >= 0 in range")
        _check_range(self, "tof")

    def sigma_mm(self, z_m):
        """Standard deviation of the depth noise at `z_m` (m) in the image centre, in mm."""
        return self.sigma_c0_mm + self.sigma_c1_mm * z_m + self.sigma_c2_mm * z_m * z_m

    @property
    def spec(self) -> str:
        """'tof' and the parameters that differ from the defaults, as `parse_noise` reads them."""
        return _spec_of(self, "tof")

    def draws(self, shape: tuple[int, int], rng: np.random.Generator):
        """The random inputs of one frame: per-pixel normals, the dark-patch field, a seed and
        the radius of the valid circle."""
        gauss = rng.standard_normal(shape)
        dark_field = _coarse_field(shape, self.dark_cell_px, rng)
        seed = int(rng.integers(0, 2**63))
        cut, where = rng.random(2)
        fov = self.fov_radius
        if cut < self.fov_cut:
            fov = self.fov_cut_min + (self.fov_radius - self.fov_cut_min) * float(where)
        return gauss, dark_field, seed, fov

    def dark_mask(self, labels: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray:
        """uint8 (H, W): 1 on dark surfaces (hair: pixels labelled head), 0 elsewhere."""
        labels = _check_labels(labels, shape)
        if labels is None:
            return np.zeros(shape, np.uint8)
        return (labels == HEAD).astype(np.uint8)

    def run(self, depth, dark, gauss, dark_field, seed, fov) -> np.ndarray:
        """The kernel on given draws (what `apply` does after drawing them)."""
        out = np.empty_like(depth)
        _tof_kernel(
            depth, dark, gauss, dark_field, float(self.dark_cell_px), np.uint64(seed),
            self.sigma_c0_mm, self.sigma_c1_mm, self.sigma_c2_mm, self.corner_sigma,
            1000.0 * self.jump_m, self.flying_px, self.flying, self.edge_invalid,
            self.multipath_mm, self.multipath_px, self.concave_min, self.concave_full,
            _normal_quantile(self.dark_dropout), self.dark_sigma, self.border_px, float(fov),
            self.speckle, self.min_range_m, self.max_range_m, out,
        )  # fmt: skip
        return out

    def apply(
        self, depth: np.ndarray, rng: np.random.Generator, labels: np.ndarray | None = None
    ) -> np.ndarray:
        """The frame as this time-of-flight camera would measure it; draws come from `rng`;
        `labels` (renderer label ids) mark the dark hair, none without them."""
        depth = check_depth(depth, "noise")
        dark = self.dark_mask(labels, depth.shape)
        return self.run(depth, dark, *self.draws(depth.shape, rng))

    def to_dict(self) -> dict:
        """The parameters by name."""
        return asdict(self)


# --- active stereo (RealSense D435, OAK-D) -----------------------------------------------------


@numba.njit(parallel=True, cache=True)
def _stereo_kernel(
    depth,
    flags,
    field,
    speckle_field,
    cell,
    speckle_cell,
    seed,
    fb,
    subpixel,
    sigma_px,
    jump_mm,
    fatten_px,
    fatten,
    speckle_thr,
    border_px,
    zmin,
    zmax,
    out,
):
    h, w = depth.shape
    for v in numba.prange(h):
        for u in range(w):
            idx = (v * w + u) * 4
            out[v, u] = 0
            d0 = depth[v, u]
            if d0 == 0:
                continue
            if u < border_px or v < border_px or u >= w - border_px or v >= h - border_px:
                continue
            # edge fattening: the nearest ring (Chebyshev distance r) holding a surface nearer
            # by more than a jump lends its depth with probability fatten^r
            src = np.int64(d0)
            fattened = False
            for r in range(1, fatten_px + 1):
                m = np.int64(0)
                for vv in range(max(0, v - r), min(h, v + r + 1)):
                    for uu in range(max(0, u - r), min(w, u + r + 1)):
                        if max(abs(vv - v), abs(uu - u)) != r:
                            continue
                        n = np.int64(depth[vv, uu])
                        if n > 0 and (m == 0 or n < m):
                            m = n
                if m > 0 and np.int64(d0) - m > jump_mm:
                    if _hash_uniform(seed, idx) < fatten**r:
                        src = m
                        fattened = True
                    break
            # occluded in the second imager: the left-right check leaves no depth
            if not fattened and (flags[v, u] & SHADOW) != 0:
                continue
            disp = fb / (src * 0.001)
            # the match would lie left of the second image: the invalid band at the left edge
            if u < disp:
                continue
            if _field_at(speckle_field, u, v, speckle_cell) < speckle_thr:
                continue
            disp += sigma_px * _field_at(field, u, v, cell)
            disp = np.floor(disp * subpixel + 0.5) / subpixel
            if disp <= 0:
                continue
            z = fb / disp
            if z < zmin or z > zmax:
                continue
            out[v, u] = metres_to_mm_scalar(z)


@dataclass(frozen=True)
class StereoNoise:
    """An active stereo sensor model (RealSense D435 defaults; docs/reference/sensors.md for sources).

    The left imager is the reference, the second sits `baseline_m` to its right. Effects:
    disparity d = f B / z with matching noise (`disparity_sigma_px`, the "subpixel RMS",
    spatially correlated over `noise_cell_px`) quantised to 1 / 2^subpixel_bits px, so depth
    error grows as z^2; no depth in the band at the left edge whose match falls off the
    second image (u < f B / z px wide) nor where the second imager is occluded; edge
    fattening (the foreground's depth bleeds 1-`fatten_px` px over the background at jumps);
    speckle holes (irregular blobs, a share `speckle` of the image); range limits.
    """

    focal_px: float = 385.0  # D435 at 640x480
    baseline_m: float = 0.05
    subpixel_bits: int = 5  # disparity step 1 / 2^bits px
    disparity_sigma_px: float = 0.08  # subpixel RMS (Intel: "about 0.08")
    noise_cell_px: int = 4  # correlation length of the matching noise
    jump_m: float = 0.10  # a nearer neighbour by more than this is foreground
    fatten_px: int = 2  # how far the foreground can bleed
    fatten: float = 0.7  # chance per px of distance (p = fatten^r at distance r)
    speckle: float = 0.003  # share of the image in speckle holes
    speckle_cell_px: int = 3  # size of the holes
    border_px: int = 0  # invalid rows / columns at the frame's edge (OAK-D: ~3)
    min_range_m: float = 0.3
    max_range_m: float = 10.0

    def __post_init__(self) -> None:
        _check_probabilities(self, "stereo", ("fatten", "speckle"))
        if self.focal_px <= 0 or self.baseline_m <= 0 or not 0 <= self.subpixel_bits <= 8:
            raise TopsegError("stereo noise: focal_px > 0, baseline_m > 0, 0 <= subpixel_bits <= 8")
        if self.noise_cell_px < 1 or self.speckle_cell_px < 1 or self.fatten_px < 0:
            raise TopsegError(
                "stereo noise: noise_cell_px, speckle_cell_px >= 1 and fatten_px >= 0"
            )
        if self.disparity_sigma_px < 0 or self.jump_m <= 0 or self.border_px < 0:
            raise TopsegError("stereo noise: disparity_sigma_px >= 0, jump_m > 0, border_px >= 0")
        _check_range(self, "stereo")

    @property
    def fb(self) -> float:
        """focal length x baseline (pixel metres): disparity = fb / z."""
        return self.focal_px * self.baseline_m

    @property
    def subpixel(self) -> int:
        """Disparity levels per pixel."""
        return 1 << self.subpixel_bits

    def depth_step_mm(self, z_m):
        """Spacing of the depth levels the sensor can report at depth `z_m`."""
        return 1000.0 * z_m * z_m / (self.subpixel * self.fb)

    def sigma_mm(self, z_m):
        """Standard deviation of the depth error at `z_m`: matching noise plus quantisation."""
        sd = np.hypot(self.disparity_sigma_px, (1.0 / self.subpixel) / np.sqrt(12.0))
        return 1000.0 * z_m * z_m * sd / self.fb

    def invalid_band_px(self, z_m):
        """Width of the left band without depth over a surface at depth `z_m`: f B / z."""
        return self.fb / z_m

    @property
    def spec(self) -> str:
        """'stereo' and the parameters that differ from the defaults, as `parse_noise` reads."""
        return _spec_of(self, "stereo")

    def draws(self, shape: tuple[int, int], rng: np.random.Generator):
        """The random inputs of one frame: the matching-noise and speckle fields, a seed."""
        field = _coarse_field(shape, self.noise_cell_px, rng)
        speckle_field = _coarse_field(shape, self.speckle_cell_px, rng)
        seed = int(rng.integers(0, 2**63))
        return field, speckle_field, seed

    def occluded(self, depth: np.ndarray) -> np.ndarray:
        """uint8 flags, SHADOW where the second imager cannot see the surface."""
        flags = np.empty(depth.shape, np.uint8)
        near_h = np.empty(depth.shape, np.uint8)
        _flags_kernel(depth, self.fb, self.jump_m, 0, flags, near_h)
        return flags

    def run(self, depth, field, speckle_field, seed) -> np.ndarray:
        """The kernel on given draws (what `apply` does after drawing them)."""
        out = np.empty_like(depth)
        _stereo_kernel(
            depth, self.occluded(depth), field, speckle_field, float(self.noise_cell_px),
            float(self.speckle_cell_px), np.uint64(seed), self.fb, float(self.subpixel),
            self.disparity_sigma_px, 1000.0 * self.jump_m, self.fatten_px, self.fatten,
            _normal_quantile(self.speckle), self.border_px, self.min_range_m, self.max_range_m,
            out,
        )  # fmt: skip
        return out

    def apply(
        self, depth: np.ndarray, rng: np.random.Generator, labels: np.ndarray | None = None
    ) -> np.ndarray:
        """The frame as this stereo camera would measure it; draws come from `rng` (`labels`
        is not used)."""
        depth = check_depth(depth, "noise")
        _check_labels(labels, depth.shape)
        return self.run(depth, *self.draws(depth.shape, rng))

    def to_dict(self) -> dict:
        """The parameters by name."""
        return asdict(self)


# --- specs -------------------------------------------------------------------------------------

_FAMILIES = {"kinect": KinectNoise, "tof": ToFNoise, "stereo": StereoNoise}


def _parse_params(cls, name: str, spec: str, arg: str):
    kwargs = {}
    known = {f.name: f.type for f in fields(cls)}
    for item in filter(None, (s.strip() for s in arg.split(","))):
        key, eq, value = item.partition("=")
        key = key.strip()
        if not eq or key not in known:
            raise TopsegError(
                f"noise {spec!r}: unknown {name} parameter {key!r}; known: {', '.join(known)}"
            )
        try:
            kwargs[key] = int(value) if known[key] in ("int", int) else float(value)
        except ValueError:
            raise TopsegError(f"noise {spec!r}: {key} needs a number, got {value!r}") from None
    return cls(**kwargs)


def parse_noise(spec: str) -> NoiseModel:
    """ "none", "gaussian:<sigma_mm>", "kinect[:key=value,...]", "tof[:...]" (time of flight)
    or "stereo[:...]" (active stereo) -> a noise model; one-line TopsegError if not."""
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
    if name in _FAMILIES:
        return _parse_params(_FAMILIES[name], name, spec, arg)
    raise TopsegError(
        f"unknown noise {spec!r}; use none, gaussian:<sigma_mm>, kinect, tof or stereo"
    )
