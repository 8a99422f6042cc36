"""The static cell: a recorded background and the gate that sends pixels matching it to
background without the forest.

In a robot cell most of the view never changes: floor, fences, tables, cabinets, machine
housings. `topseg calibrate --background` records a few seconds of the empty cell and
`fit_background` turns them into a `BackgroundModel`: for every pixel the median depth of
what does not move and its noise (the MAD of its readings, never below the sensor's noise
model at that depth, `sensors.depth_sigma_mm`). Each pixel's own MAD
is a rough estimate (60 readings of a quantised sensor), so its noise is never taken above
the median of its neighbours' (`NOISE_WINDOW`): an odd pixel does not widen the gate. A
pixel is *not background* (never gated)
when it had a reading in too few frames, or when its readings were unstable: too many far
from the median (a robot moving through it while recording), or a spread far beyond the
camera's own noise (an edge flickering between two surfaces).

A frame's pixel whose depth lies within `sigmas` sigma plus `margin_mm` of the background
(at most `MAX_GATE_MM`) is background (`gate_background`): a person standing where the
background was floor or a table is nearer than it and stays foreground. A pixel *farther*
than the background by more than that tolerance saw something static go (a fixture moved,
or the camera): counted as missing, never gated.

The file (`save_background` / `load_background`) is a numpy `.npz` archive with no pickle:
a JSON header (`magic` "topseg-background", `format_version`, `id`, the camera's
intrinsics, the mount and sensor it was recorded with, frames, created, how it was fitted)
and three arrays of the camera's size: `depth_mm` and `sigma_mm` (float32) and `valid`
(bool). The `id` is the sha256 of the camera and the arrays: labels made with a background
carry it, and a file whose arrays do not hash to it is refused as damaged. Writes are
atomic (`core.atomic`); anything wrong on reading is one `BackgroundFileError` line naming
the file and what is wrong.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import warnings
import zipfile
import zlib
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numba
import numpy as np

from topseg.core.atomic import atomic_write
from topseg.core.camera import (
    NO_READING_MM,
    Intrinsics,
    TopViewMount,
    check_mount,
    range_to_depth,
)
from topseg.core.errors import TopsegError
from topseg.core.sensors import depth_sigma_mm

MAGIC = "topseg-background"
FORMAT_VERSION = 1
#: the arrays of a background file and their dtypes
ARRAYS = {
    "depth_mm": np.dtype(np.float32),
    "sigma_mm": np.dtype(np.float32),
    "valid": np.dtype(bool),
}
#: the largest JSON header a background file may hold
MAX_HEADER_BYTES = 1 << 20
#: a MAD scaled by this is a Gaussian's sigma
MAD_TO_SIGMA = 1.4826
#: the widest tolerance (mm) the gate allows: like the floor gate's largest margin, a noisy
#: camera far away must not gate away a hand on a table or a foot on the floor
MAX_GATE_MM = 150.0
#: rows of frames a fit reads at a time (bounds its memory: N frames x rows x width floats)
FIT_ROWS = 32
#: the side (px) of the neighbourhood whose median MAD noise caps a pixel's own
NOISE_WINDOW = 5
#: the smallest number of frames a background is fitted from (its noise needs several)
MIN_FRAMES = 5
#: relative difference of focal lengths, and of the principal point in share of the frame's
#: side, within which a frame's camera is the background's
CAMERA_TOLERANCE = 0.01


class BackgroundFileError(TopsegError):
    """A background file that cannot be used: missing, damaged, foreign or of another camera."""


@dataclass(frozen=True)
class BackgroundFitConfig:
    """How `fit_background` decides which pixels are background.

    min_valid_share   a pixel needs a reading in at least this share of the frames
    outlier_sigmas    a reading farther than this many sigma from the pixel's median is an
                      outlier (something passed through it)
    max_outlier_share a pixel with more outliers than this share of its readings is unstable
    max_sigma_ratio   a pixel whose MAD noise is more than this many times the camera's (the
                      sensor's noise model times the frames' median ratio to it) is unstable
    """

    min_valid_share: float = 0.8
    outlier_sigmas: float = 4.0
    max_outlier_share: float = 0.1
    max_sigma_ratio: float = 3.0

    def __post_init__(self) -> None:
        for name in ("min_valid_share", "max_outlier_share"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise TopsegError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        for name in ("outlier_sigmas", "max_sigma_ratio"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise TopsegError(f"{name} must be > 0, got {getattr(self, name)}")


@dataclass(frozen=True, eq=False)
class BackgroundModel:
    """The empty cell as one camera saw it (see the module).

    depth_mm   (H, W) float32 median depth (mm) as the camera sends it; 0 where not valid
    sigma_mm   (H, W) float32 noise (mm, 1 sigma); 0 where not valid
    valid      (H, W) bool: background pixels (enough stable readings)
    intrinsics the camera's optics; frames of another camera are refused
    mount      the mount the frames carried, when they carried one
    sensor     the sensor whose noise model floors the noise
    frames     frames it was fitted from
    created    when (ISO 8601, UTC)
    unstable_px pixels with enough readings that were too unstable to be background
    id         sha256 hex of the camera and the arrays (`background_id`)
    source     what the frames came from, as the operator named it
    """

    depth_mm: np.ndarray
    sigma_mm: np.ndarray
    valid: np.ndarray
    intrinsics: Intrinsics
    mount: TopViewMount | None
    sensor: str
    frames: int
    created: str
    unstable_px: int
    id: str
    source: str = ""

    @property
    def valid_share(self) -> float:
        """Share of the camera's pixels that are background."""
        return float(np.count_nonzero(self.valid)) / self.valid.size

    @property
    def unstable_share(self) -> float:
        """Share of the camera's pixels whose readings were too unstable to be background."""
        return self.unstable_px / self.valid.size

    @property
    def median_sigma_mm(self) -> float:
        """The median noise of the background pixels (mm; 0 with none)."""
        return float(np.median(self.sigma_mm[self.valid])) if self.valid.any() else 0.0

    def summary(self) -> str:
        """What the fit found, as `topseg calibrate --background` prints it."""
        k = self.intrinsics
        no_reading = 1.0 - self.valid_share - self.unstable_share
        return "\n".join(
            [
                f"background {100 * self.valid_share:6.1f} % of the pixels",
                f"unstable   {100 * self.unstable_share:6.1f} % (readings that moved: not "
                "background)",
                f"no reading {100 * max(0.0, no_reading):6.1f} % (too few readings: not "
                "background)",
                f"sigma      {self.median_sigma_mm:6.1f} mm median noise of the background pixels",
                f"frames     {self.frames}",
                f"camera     {k.width}x{k.height} fx {k.fx:.4g} fy {k.fy:.4g} cx {k.cx:.4g} "
                f"cy {k.cy:.4g}",
                f"sensor     {self.sensor}",
                f"id         {self.id}",
            ]
        )


def background_id(
    intrinsics: Intrinsics, depth_mm: np.ndarray, sigma_mm: np.ndarray, valid: np.ndarray
) -> str:
    """sha256 hex of the camera's optics and the background's arrays: what names it."""
    h = hashlib.sha256(MAGIC.encode())
    h.update(json.dumps(intrinsics.to_dict(), sort_keys=True).encode())
    for arr, dtype in ((depth_mm, "<f4"), (sigma_mm, "<f4"), (valid, "|b1")):
        h.update(np.ascontiguousarray(arr, dtype=dtype).tobytes())
    return h.hexdigest()


# ---------------------------------------------------------------------------- fit


def fit_background(
    frames: list[np.ndarray] | np.ndarray,
    intrinsics: Intrinsics,
    sensor: str = "unknown",
    mount: TopViewMount | None = None,
    config: BackgroundFitConfig | None = None,
    source: str = "",
) -> BackgroundModel:
    """The background of `frames` (uint16 mm, as the camera sends them: 0 and 65535 are no
    reading) of the empty cell seen by `intrinsics`; TopsegError for too few frames or
    frames of another size."""
    config = config or BackgroundFitConfig()
    stack = _stacked(frames, intrinsics)
    n = stack.shape[0]
    median, mad_sigma, count = _pixel_statistics(stack)
    enough = count >= max(1, math.ceil(config.min_valid_share * n))
    floor = depth_sigma_mm(median, sensor).astype(np.float32)
    scale = _noise_ratio(mad_sigma, floor, enough)
    sigma = np.maximum(np.minimum(mad_sigma, _local_median(mad_sigma, enough)), floor)
    outliers = _outlier_counts(stack, median, sigma, config.outlier_sigmas)
    stable = (outliers <= config.max_outlier_share * count) & (
        mad_sigma <= config.max_sigma_ratio * scale * floor
    )
    valid = enough & stable & (median > 0)
    depth_mm = np.where(valid, median, np.float32(0)).astype(np.float32)
    sigma_mm = np.where(valid, sigma, np.float32(0)).astype(np.float32)
    return BackgroundModel(
        depth_mm=depth_mm,
        sigma_mm=sigma_mm,
        valid=valid,
        intrinsics=intrinsics,
        mount=mount,
        sensor=sensor,
        frames=n,
        created=datetime.now(UTC).isoformat(timespec="seconds"),
        unstable_px=int(np.count_nonzero(enough & ~stable)),
        id=background_id(intrinsics, depth_mm, sigma_mm, valid),
        source=source,
    )


def _stacked(frames, intrinsics: Intrinsics) -> np.ndarray:
    """(N, H, W) uint16 of `frames`, each of the camera's size; TopsegError otherwise."""
    frames = list(frames)
    if len(frames) < MIN_FRAMES:
        raise TopsegError(
            f"a background needs at least {MIN_FRAMES} frames to measure its noise, got "
            f"{len(frames)}"
        )
    for i, f in enumerate(frames):
        f = np.asarray(f)
        if f.dtype != np.uint16 or f.shape != intrinsics.shape:
            raise TopsegError(
                f"frame {i + 1} is {f.dtype} {f.shape}; the camera's frames are uint16 "
                f"{intrinsics.shape}"
            )
    return np.stack(frames)


def _pixel_statistics(stack: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`_robust_rows` of (N, H, W) readings, FIT_ROWS rows at a time (bounded memory)."""
    shape = stack.shape[1:]
    median = np.zeros(shape, np.float32)
    mad_sigma = np.zeros(shape, np.float32)
    count = np.zeros(shape, np.int32)
    for r0 in range(0, shape[0], FIT_ROWS):
        rows = slice(r0, r0 + FIT_ROWS)
        median[rows], mad_sigma[rows], count[rows] = _robust_rows(stack[:, rows])
    return median, mad_sigma, count


def _robust_rows(block: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel of (N, rows, W) uint16 readings: the median, the MAD as a sigma, and how
    many readings there were (0 and 65535 are none)."""
    x = block.astype(np.float32)
    x[(block == 0) | (block == NO_READING_MM)] = np.nan
    count = np.count_nonzero(~np.isnan(x), axis=0).astype(np.int32)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN pixels: no reading at all
        median = np.nanmedian(x, axis=0)
        mad = np.nanmedian(np.abs(x - median), axis=0)
    median = np.nan_to_num(median, nan=0.0).astype(np.float32)
    return median, np.nan_to_num(MAD_TO_SIGMA * mad, nan=0.0).astype(np.float32), count


def _local_median(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Per pixel, the median of `values` over the valid pixels of its NOISE_WINDOW square
    (+inf where it has none)."""
    r = NOISE_WINDOW // 2
    padded = np.pad(np.where(valid, values, np.nan).astype(np.float32), r, constant_values=np.nan)
    h, w = values.shape
    shifted = [
        padded[i : i + h, j : j + w] for i in range(NOISE_WINDOW) for j in range(NOISE_WINDOW)
    ]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a window without a valid pixel
        median = np.nanmedian(np.stack(shifted), axis=0)
    return np.nan_to_num(median, nan=np.inf).astype(np.float32)


def _noise_ratio(mad_sigma: np.ndarray, floor: np.ndarray, enough: np.ndarray) -> float:
    """The camera's measured noise over its model's: the median ratio over the pixels with
    enough readings, never below 1 (a camera quieter than its model keeps the model's)."""
    ok = enough & (floor > 0)
    if not ok.any():
        return 1.0
    return max(1.0, float(np.median(mad_sigma[ok] / floor[ok])))


def _outlier_counts(
    stack: np.ndarray, median: np.ndarray, sigma: np.ndarray, sigmas: float
) -> np.ndarray:
    """Per pixel, its readings farther than `sigmas` sigma from its median."""
    out = np.zeros(median.shape, np.int32)
    reach = np.float32(sigmas) * sigma
    for frame in stack:
        seen = (frame != 0) & (frame != NO_READING_MM)
        out += seen & (np.abs(frame.astype(np.float32) - median) > reach)
    return out


# ---------------------------------------------------------------------------- file


def _header(bg: BackgroundModel, fit: BackgroundFitConfig | None) -> dict[str, Any]:
    return {
        "magic": MAGIC,
        "format_version": FORMAT_VERSION,
        "id": bg.id,
        "intrinsics": bg.intrinsics.to_dict(),
        "mount": None if bg.mount is None else bg.mount.to_dict(),
        "sensor": bg.sensor,
        "frames": bg.frames,
        "created": bg.created,
        "unstable_px": bg.unstable_px,
        "source": bg.source,
        "fit": asdict(fit or BackgroundFitConfig()),
    }


def save_background(
    path: str | os.PathLike, bg: BackgroundModel, fit: BackgroundFitConfig | None = None
) -> None:
    """Write `bg` to `path` atomically (see the module); `fit` is recorded in the header."""
    blob = json.dumps(_header(bg, fit), sort_keys=True, allow_nan=False).encode()
    arrays = {
        "header": np.frombuffer(blob, np.uint8),
        "depth_mm": np.ascontiguousarray(bg.depth_mm, np.float32),
        "sigma_mm": np.ascontiguousarray(bg.sigma_mm, np.float32),
        "valid": np.ascontiguousarray(bg.valid, bool),
    }
    with atomic_write(path) as f:
        np.savez_compressed(f, **arrays)


def load_background(
    path: str | os.PathLike, intrinsics: Intrinsics | None = None
) -> BackgroundModel:
    """Read a background file (and, given `intrinsics`, check it is that camera's);
    BackgroundFileError naming the file and what is wrong."""
    path = Path(path)
    where = f"background file {path}"
    try:
        with open(path, "rb") as f:
            start = f.read(4)
    except FileNotFoundError:
        raise BackgroundFileError(
            f"{where}: no such file (record one with `topseg calibrate --background`)"
        ) from None
    except OSError as exc:
        raise BackgroundFileError(f"{where}: cannot be read: {exc.strerror or exc}") from None
    if start != b"PK\x03\x04":
        raise BackgroundFileError(f"{where}: not a background file (not a zip archive)")
    try:
        header = _read_header(path, where)
        k = _header_intrinsics(header, where)
        _check_members(path, where, k.shape)
        with np.load(path, allow_pickle=False) as npz:
            arrays = {name: npz[name] for name in ARRAYS}
    except BackgroundFileError:
        raise
    except (zipfile.BadZipFile, zlib.error, ValueError, OSError, EOFError, KeyError) as exc:
        raise BackgroundFileError(f"{where}: damaged or truncated ({exc})") from None
    except (SyntaxError, TypeError) as exc:  # an array's .npy header that does not parse
        raise BackgroundFileError(f"{where}: damaged ({exc})") from None
    bg = _model(header, arrays, k, where)
    if intrinsics is not None:
        check_camera(bg, intrinsics, str(path))
    return bg


def _read_header(path: Path, where: str) -> dict[str, Any]:
    """The JSON header of a background file, its magic and version checked."""
    shape, dtype = _member_header(path, "header", where)
    if dtype != np.uint8 or len(shape) != 1 or shape[0] > MAX_HEADER_BYTES:
        raise BackgroundFileError(f"{where}: the header is not a small byte string")
    with np.load(path, allow_pickle=False) as npz:
        raw = npz["header"]
    try:
        header = json.loads(raw.tobytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise BackgroundFileError(f"{where}: the header is not JSON ({exc})") from None
    if not isinstance(header, dict) or header.get("magic") != MAGIC:
        raise BackgroundFileError(f"{where}: not a background file (wrong magic)")
    version = header.get("format_version")
    if version != FORMAT_VERSION:
        raise BackgroundFileError(
            f"{where}: format version {version!r}; this topseg reads version {FORMAT_VERSION} "
            "(record the background again)"
        )
    return header


def _header_intrinsics(header: dict, where: str) -> Intrinsics:
    try:
        return Intrinsics.from_dict(header.get("intrinsics"), source=f"{where} intrinsics")
    except (TopsegError, ValueError, TypeError) as exc:
        raise BackgroundFileError(f"{where}: bad intrinsics: {exc}") from None


def _member_header(path: Path, name: str, where: str) -> tuple[tuple[int, ...], np.dtype]:
    """(shape, dtype) a member's `.npy` header claims, read before numpy allocates anything;
    BackgroundFileError when the member is missing."""
    with zipfile.ZipFile(path) as zf:
        try:
            info = zf.getinfo(f"{name}.npy")
        except KeyError:
            raise BackgroundFileError(f"{where}: lacks the array {name!r}") from None
        with zf.open(info) as f:
            version = np.lib.format.read_magic(f)
            read = (
                np.lib.format.read_array_header_1_0
                if version == (1, 0)
                else np.lib.format.read_array_header_2_0
            )
            shape, _, dtype = read(f)
    return tuple(shape), dtype


def _check_members(path: Path, where: str, shape: tuple[int, int]) -> None:
    """Refuse an array that is missing or whose `.npy` header claims another dtype or shape
    than the camera's."""
    for name, dtype in ARRAYS.items():
        got_shape, got_dtype = _member_header(path, name, where)
        if got_dtype != dtype or got_shape != shape:
            raise BackgroundFileError(
                f"{where}: array {name!r} is {got_dtype} {got_shape}; its camera needs "
                f"{dtype} {shape}"
            )


def _model(header: dict, arrays: dict, k: Intrinsics, where: str) -> BackgroundModel:
    """The model of a checked header and arrays; BackgroundFileError for values that do
    not make one (or whose hash is not the header's id)."""
    depth, sigma, valid = arrays["depth_mm"], arrays["sigma_mm"], arrays["valid"]
    finite = np.isfinite(depth).all() and np.isfinite(sigma).all()
    if not finite or (depth < 0).any() or (sigma < 0).any() or (valid & (depth <= 0)).any():
        raise BackgroundFileError(f"{where}: holds depths or noise that are not background")
    if background_id(k, depth, sigma, valid) != header.get("id"):
        raise BackgroundFileError(f"{where}: damaged (its arrays do not match its id)")
    mount = header.get("mount")
    try:
        mount = None if mount is None else check_mount(TopViewMount.from_dict(mount))
    except (TopsegError, ValueError, TypeError) as exc:
        raise BackgroundFileError(f"{where}: bad mount: {exc}") from None
    frames, unstable = header.get("frames"), header.get("unstable_px", 0)
    if not (_count(frames) and frames >= 1 and _count(unstable)):
        raise BackgroundFileError(f"{where}: bad frame or pixel counts in the header")
    return BackgroundModel(
        depth_mm=depth,
        sigma_mm=sigma,
        valid=valid,
        intrinsics=k,
        mount=mount,
        sensor=str(header.get("sensor", "unknown")),
        frames=frames,
        created=str(header.get("created", "")),
        unstable_px=unstable,
        id=header["id"],
        source=str(header.get("source", "")),
    )


def _count(value: Any) -> bool:
    """A JSON integer >= 0 (not a bool)."""
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def camera_text(k: Intrinsics) -> str:
    """'640x480 fx 570.3': what tells one camera from another in a line."""
    return f"{k.width}x{k.height} fx {k.fx:.4g} fy {k.fy:.4g} cx {k.cx:.4g} cy {k.cy:.4g}"


def check_camera(bg: BackgroundModel, intrinsics: Intrinsics, name: str) -> None:
    """TopsegError naming `name` (the file) unless frames of `intrinsics` come from the
    camera the background was recorded with (same size; focal lengths and principal point
    within CAMERA_TOLERANCE)."""
    k = bg.intrinsics
    same = k.shape == intrinsics.shape and all(
        abs(a - b) <= CAMERA_TOLERANCE * scale
        for a, b, scale in (
            (k.fx, intrinsics.fx, k.fx),
            (k.fy, intrinsics.fy, k.fy),
            (k.cx, intrinsics.cx, k.width),
            (k.cy, intrinsics.cy, k.height),
        )
    )
    if not same:
        raise BackgroundFileError(
            f"background file {name} was recorded with another camera ({camera_text(k)}) than "
            f"these frames' ({camera_text(intrinsics)}): record this camera's background "
            "(topseg calibrate --background)"
        )


# ---------------------------------------------------------------------------- gate


@dataclass(frozen=True, eq=False)
class GateGrid:
    """A background at a frame's working grid, ready for `gate_background`.

    depth_mm   (h, w) float32 background depth along the optical axis
    tolerance  (h, w) float32 how far (mm) a reading may lie from it and be background;
               -1 where the background is not valid
    valid_px   the background's valid pixels on this grid
    """

    depth_mm: np.ndarray
    tolerance: np.ndarray
    valid_px: int


def gate_grid(
    bg: BackgroundModel,
    downsample: int,
    sigmas: float,
    margin_mm: float,
    radial: bool = False,
) -> GateGrid:
    """`bg` for frames labelled every `downsample`-th pixel of every `downsample`-th row
    (`resolution.decimate`), tolerance `sigmas` sigma plus `margin_mm` (at most
    MAX_GATE_MM); `radial`: the camera sends range along each ray, which the frame is read
    as depth from, and so is the background."""
    depth, sigma, valid = bg.depth_mm, bg.sigma_mm, bg.valid
    if radial:
        as_sent = np.rint(depth).astype(np.uint16)
        axis = range_to_depth(as_sent, bg.intrinsics).astype(np.float32)
        ratio = np.divide(axis, depth, out=np.ones_like(depth), where=depth > 0)
        depth, sigma = axis, sigma * ratio
    f = downsample
    depth = np.ascontiguousarray(depth[::f, ::f], np.float32)
    valid = valid[::f, ::f]
    tolerance = np.minimum(
        np.float32(sigmas) * sigma[::f, ::f] + np.float32(margin_mm), MAX_GATE_MM
    )
    tolerance = np.ascontiguousarray(np.where(valid, tolerance, -1.0), np.float32)
    return GateGrid(depth, tolerance, int(np.count_nonzero(valid)))


def gate_background(
    depth: np.ndarray, values: np.ndarray, grid: GateGrid, gate: np.ndarray, apply: bool = True
) -> tuple[int, int]:
    """Match a working frame's `depth` (uint16 mm) against the background `grid`: where the
    model input has a value (`values` > 0) and the depth lies within the tolerance, `gate`
    (the floor gate's mask, updated in place when `apply`) is set. Returns (pixels that
    match the background, pixels farther than it by more than the tolerance)."""
    if (
        depth.shape != grid.depth_mm.shape
        or values.shape != depth.shape
        or gate.shape != depth.shape
    ):
        raise ValueError(f"the background grid is {grid.depth_mm.shape}, the frame {depth.shape}")
    matched, missing = _gate(depth, values, grid.depth_mm, grid.tolerance, gate, apply)
    return int(matched), int(missing)


@numba.njit(cache=True, parallel=True)
def _gate(depth, values, background, tolerance, gate, apply):
    """`gate_background`'s kernel, rows in parallel: (matched, missing) counts."""
    rows = depth.shape[0]
    matched = np.zeros(rows, np.int64)
    missing = np.zeros(rows, np.int64)
    for r in numba.prange(rows):
        matched[r], missing[r] = _gate_row(
            depth[r], values[r], background[r], tolerance[r], gate[r], apply
        )
    return matched.sum(), missing.sum()


@numba.njit(cache=True)
def _gate_row(depth, values, background, tolerance, gate, apply):
    """One row of `_gate`: (matched, missing)."""
    hits = 0
    gone = 0
    for c in range(depth.shape[0]):
        t = tolerance[c]
        d = depth[c]
        if t >= 0 and d != 0 and values[c] != 0:
            diff = np.float32(d) - background[c]
            if abs(diff) <= t:
                hits += 1
                if apply:
                    gate[c] = True
            elif diff > t:
                gone += 1
    return hits, gone


def warm_up_gate(depth: np.ndarray) -> None:
    """Compile (or load from numba's cache) the gate's kernel for writable and read-only
    frames and model inputs (numba compiles a kernel apart for read-only arrays), on a
    uint16 frame like the ones to come."""
    writable = np.array(depth, np.uint16)
    read_only = writable.copy()
    read_only.flags.writeable = False
    grid = GateGrid(
        np.zeros(writable.shape, np.float32), np.full(writable.shape, -1.0, np.float32), 0
    )
    gate = np.zeros(writable.shape, bool)
    for d in (writable, read_only):
        for values in (writable, read_only):
            gate_background(d, values, grid, gate)
