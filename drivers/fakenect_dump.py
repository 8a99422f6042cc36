"""libfreenect fakenect dumps, and Kinect v1 raw disparity <-> millimetres.

A dump is a folder with `INDEX.txt` (one file name per line, in play order) and depth files
`d-<host seconds>-<device timestamp>.pgm`: the header line `P5 640 480 65535` then 640x480
little-endian 11-bit raw disparity, 2047 = no measurement. libfreenect's `fakenect` library
plays such a folder as if it were a Kinect, pacing by the host seconds.

The Kinect reports disparity, not depth. libfreenect turns it into millimetres through its
zero-plane model (`freenect_raw_to_mm` in its `src/registration.c`): with the reference
distance 120 mm, reference pixel size 0.1042 mm, emitter-to-camera distance 7.5 cm, shift
offset 200 and coefficient 4. `RAW_TO_MM` is that table (truncated to whole mm like
libfreenect's), valid where it rises to at most 10 m; `mm_to_raw` inverts it by picking the
nearest entry, so a round trip is exact up to the disparity step (about 35 mm at 3.5 m).
"""

from __future__ import annotations

import os
import re
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from topseg.core.atomic import atomic_write
from topseg.drivers.base import SourceError

WIDTH, HEIGHT = 640, 480
NO_DISPARITY = 2047
MAX_MM = 10_000
PGM_HEADER = b"P5 640 480 65535\n"
FRAME_BYTES = WIDTH * HEIGHT * 2
#: freenect_raw_tilt_state: accelerometer x, y, z (819 counts = 1 g), tilt angle, status
_LEVEL_ACCELEROMETER = struct.pack("<hhhbxi", 0, 819, 0, 0, 0)
_NAME = re.compile(r"d-(\d+(?:\.\d*)?)-(\d+)\.pgm")

# libfreenect's default zero-plane calibration and shift constants
_REFERENCE_DISTANCE_MM = 120.0
_REFERENCE_PIXEL_SIZE_MM = 0.1042
_EMITTER_DISTANCE_CM = 7.5
_CONST_SHIFT = 200.0
_PARAM_COEFF = 4.0
_SHIFT_SCALE = 10.0
_S2D_OFFSET = 0.375


def _raw_to_mm_table() -> np.ndarray:
    raw = np.arange(2048, dtype=np.float64)
    ref_x = (raw - _PARAM_COEFF * _CONST_SHIFT) / _PARAM_COEFF - _S2D_OFFSET
    metric = ref_x * _REFERENCE_PIXEL_SIZE_MM
    with np.errstate(divide="ignore", invalid="ignore"):
        mm = _SHIFT_SCALE * (
            metric * _REFERENCE_DISTANCE_MM / (_EMITTER_DISTANCE_CM - metric)
            + _REFERENCE_DISTANCE_MM
        )
    mm = np.floor(mm)
    # valid: the rising branch below the pole, within the sensor's range
    rising = np.concatenate([[True], np.diff(mm) >= 0])
    valid = np.logical_and.accumulate(rising & (mm > 0) & (mm <= MAX_MM))
    table = np.where(valid, mm, 0).astype(np.uint16)
    table[NO_DISPARITY] = 0
    return table


#: raw disparity (0..2047) -> millimetres, 0 where the Kinect reports nothing
RAW_TO_MM: np.ndarray = _raw_to_mm_table()
RAW_TO_MM.flags.writeable = False
_VALID_RAW = np.flatnonzero(RAW_TO_MM)
_VALID_MM = RAW_TO_MM[_VALID_RAW].astype(np.int64)
MIN_MM, MAX_VALID_MM = int(_VALID_MM[0]), int(_VALID_MM[-1])


def raw_to_mm(raw: np.ndarray) -> np.ndarray:
    """11-bit disparity -> uint16 millimetres (0 = no depth); values above 2047 read as none."""
    raw = np.asarray(raw)
    return RAW_TO_MM[np.minimum(raw, NO_DISPARITY).astype(np.intp)]


def _mm_to_raw_table() -> np.ndarray:
    mm = np.arange(65536, dtype=np.int64)
    hi = np.clip(np.searchsorted(_VALID_MM, mm), 1, len(_VALID_MM) - 1)
    lo = hi - 1
    nearer_lo = (mm - _VALID_MM[lo]) <= (_VALID_MM[hi] - mm)
    raw = np.where(nearer_lo, _VALID_RAW[lo], _VALID_RAW[hi]).astype(np.uint16)
    raw[(mm < MIN_MM) | (mm > MAX_VALID_MM)] = NO_DISPARITY
    return raw


_MM_TO_RAW = _mm_to_raw_table()


def mm_to_raw(mm: np.ndarray) -> np.ndarray:
    """uint16 millimetres -> 11-bit disparity whose depth is nearest; 2047 outside the range."""
    mm = np.asarray(mm)
    if mm.dtype != np.uint16:
        raise SourceError(f"depth must be uint16 millimetres, got {mm.dtype}")
    return _MM_TO_RAW[mm]


def quantisation_step_mm(mm: np.ndarray) -> np.ndarray:
    """The gap between the representable depths around each value (what a round trip may lose)."""
    raw = mm_to_raw(mm).astype(np.intp)
    inside = raw != NO_DISPARITY
    r = np.clip(raw, 1, len(RAW_TO_MM) - 2)
    table = RAW_TO_MM.astype(np.int64)
    step = np.maximum(table[r + 1] - table[r], table[r] - table[r - 1])
    return np.where(inside, step, 0)


# ---------------------------------------------------------------------------- dumps


@dataclass(frozen=True)
class DumpFrame:
    """One depth record: host seconds (fakenect paces by them), device timestamp, raw disparity."""

    host_s: float
    device_ts: int
    raw: np.ndarray  # (480, 640) uint16 disparity


def _atomic_write(path: Path, chunks: Iterable[bytes]) -> None:
    with atomic_write(path) as f:
        for chunk in chunks:
            f.write(chunk)


def write_dump(
    directory: str | os.PathLike,
    depth_frames: Iterable[np.ndarray],
    fps: float = 30.0,
    start_s: float = 1_000_000.0,
    tail_s: float = 0.5,
) -> list[str]:
    """Write 640x480 uint16 mm frames as a fakenect dump; returns the depth file names.

    Frames are `1/fps` apart in host time; the device timestamps count frames. An
    accelerometer record `tail_s` after the last frame ends the dump: fakenect 0.5.3 dies as
    soon as it finds no next record, racing the reader for the last frame, and the record
    makes it sleep first. INDEX.txt is written last, so a dump is playable only once complete.
    """
    folder = Path(directory)
    folder.mkdir(parents=True, exist_ok=True)
    if (folder / "INDEX.txt").exists():
        raise SourceError(f"{folder} already holds a fakenect dump (INDEX.txt)")
    names = []
    for i, depth in enumerate(depth_frames):
        depth = np.asarray(depth)
        if depth.shape != (HEIGHT, WIDTH):
            raise SourceError(f"fakenect dumps hold 640x480 frames, got {depth.shape}")
        raw = mm_to_raw(depth).astype("<u2")
        name = f"d-{start_s + i / fps:f}-{(i * 2_000_000) % 2**32}.pgm"
        _atomic_write(folder / name, (PGM_HEADER, raw.tobytes()))
        names.append(name)
    if not names:
        raise SourceError("a fakenect dump needs at least one frame")
    tail = (
        f"a-{start_s + (len(names) - 1) / fps + tail_s:f}-{(len(names) * 2_000_000) % 2**32}.dump"
    )
    _atomic_write(folder / tail, [_LEVEL_ACCELEROMETER])
    index = "".join(f"{n}\n" for n in [*names, tail])
    _atomic_write(folder / "INDEX.txt", [index.encode()])
    return names


def is_dump(path: str | os.PathLike) -> bool:
    """True when `path` is a folder holding a complete dump (INDEX.txt is written last)."""
    return (Path(path) / "INDEX.txt").is_file()


def read_dump(directory: str | os.PathLike) -> Iterator[DumpFrame]:
    """Depth frames of a fakenect dump in INDEX order (other records are skipped)."""
    folder = Path(directory)
    try:
        lines = (folder / "INDEX.txt").read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise SourceError(f"cannot read the fakenect index {folder / 'INDEX.txt'}: {exc}") from exc
    for line in lines:
        name = line.strip()
        if not name.startswith("d-"):
            continue  # rgb and accelerometer records
        match = _NAME.fullmatch(name)
        if not match or "/" in name:
            raise SourceError(f"{folder / 'INDEX.txt'}: {name[:80]!r} is not a depth file name")
        try:
            blob = (folder / name).read_bytes()
        except OSError as exc:
            raise SourceError(f"fakenect dump {folder}: {exc}") from exc
        if not blob.startswith(PGM_HEADER) or len(blob) != len(PGM_HEADER) + FRAME_BYTES:
            raise SourceError(
                f"{folder / name} is not a 640x480 16-bit PGM of {len(PGM_HEADER) + FRAME_BYTES} "
                f"bytes (header {blob[:20]!r}, {len(blob)} bytes)"
            )
        raw = np.frombuffer(blob, "<u2", offset=len(PGM_HEADER)).reshape(HEIGHT, WIDTH)
        yield DumpFrame(float(match.group(1)), int(match.group(2)), raw.astype(np.uint16))
