"""The Zenoh wire format (DESIGN section 4): msgpack messages and key expressions.

A depth or label message is one msgpack map::

    v         schema version (SCHEMA_VERSION)
    seq       frame number, 0 <= seq < 2**63
    stamp_ns  capture time, ns since the Unix epoch, 0 <= stamp_ns < 2**63
    frame_id  camera name, at most 256 characters
    width, height   1..MAX_SIDE pixels
    encoding  "16UC1" (depth, millimetres, 0 = no depth) or "8UC1" (labels)
    data      raw little-endian pixels, row-major, exactly width*height*bytes-per-pixel bytes
    fx, fy, cx, cy  pinhole intrinsics in pixels (depth only)
    mount     optional (depth only, version 2 on): where the camera hangs, as
              `TopViewMount.to_dict()`: {intrinsics: {width, height, fx, fy, cx, cy},
              height_mm, pitch_deg, roll_deg, sensor, noise_scale (version 3 on),
              radial (version 4 on, only when true), edge_thinning (version 5 on, only
              when false)}; its size is the frame's
    background  optional (labels only, version 6 on): the sha256 id (64 hex digits) of the
              static cell's recorded background the labels were gated with; absent: none

Version 2 added `mount` and the worker's `floor_share` and `mount` stats; version 3 the
mount's measured `noise_scale` (the floor gate's scale); version 4 the mount's `radial` (a
camera that sends range along each ray, read as depth by whoever back-projects it); version 5
the mount's `edge_thinning` (false: a stereo camera whose edges are not fattened, so not
thinned before labelling); version 6 the labels' `background` and the worker's `background`
stats. A reader
accepts every version in `READABLE_VERSIONS` and refuses a newer one with a line that says
to upgrade; a version-1 reader refuses version-2 messages ("schema version 2 is not 1"), a
version-5 reader version-6 ones.

Labels carry the `seq` and `stamp_ns` of the depth frame they were computed from, and only
valid label ids (`topseg.core.labels`). A stats message (`encode_stats`) is a small
JSON-able map the worker publishes on `.../stats`.

Decoding trusts nothing from the sender: the buffer, every field's type and range and the
data length are checked before any array is made, and any failure is one `WireError`
(services count and drop those). Decoded arrays are read-only views of the message bytes.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

from topseg.core import labels as label_table
from topseg.core.camera import (
    KINECT_V1,
    MAX_MOUNT_TILT_DEG,
    MOUNT_HEIGHT_RANGE_MM,
    Intrinsics,
    TopViewMount,
    check_mount,
)
from topseg.core.config import from_dict
from topseg.core.errors import TopsegError

#: The version every message is written with.
SCHEMA_VERSION = 6
#: The versions this reader decodes (1: no mount, no mount stats; 2: no mount noise scale;
#: 3: no radial mounts; 4: no edge_thinning; 5: no background on labels and stats).
READABLE_VERSIONS = (1, 2, 3, 4, 5, 6)
MAX_SIDE = 4096
MAX_FRAME_ID = 256
DEPTH_ENCODING = "16UC1"
LABELS_ENCODING = "8UC1"
BYTES_PER_PIXEL = {DEPTH_ENCODING: 2, LABELS_ENCODING: 1}
#: No valid message is larger than the largest depth image plus a small header.
MAX_MESSAGE_BYTES = MAX_SIDE * MAX_SIDE * 2 + 4096
_MAX_STAMP = 2**63 - 1

DEFAULT_CELL = "default"
DEFAULT_CAMERA = "cam0"
ROOT = "topseg"
#: The message kinds that live under `topseg/<cell>/<camera>/`.
KINDS = ("depth", "labels", "truth", "stats", "info")
_NAME = re.compile(r"[A-Za-z0-9_.-]{1,64}")

_FRAME_FIELDS = ("v", "seq", "stamp_ns", "frame_id", "width", "height", "encoding", "data")
_DEPTH_FIELDS = frozenset((*_FRAME_FIELDS, "fx", "fy", "cx", "cy"))
_DEPTH_OPTIONAL = frozenset(("mount",))
_LABEL_FIELDS = frozenset(_FRAME_FIELDS)
#: Labels' optional fields and the version they came with.
_LABEL_OPTIONAL = frozenset(("background",))
_LABEL_OPTIONAL_SINCE = 6
#: A background id: a sha256 in lowercase hex (`core.background.background_id`).
_BACKGROUND_ID = re.compile(r"[0-9a-f]{64}")
#: The fields of a mount map (`TopViewMount.to_dict()`); all but the first two default.
#: `radial` is sent only when true and `edge_thinning` only when false, so a depth camera's
#: mount with its edges thinned as modelled reads as before.
_MOUNT_FIELDS = frozenset(
    (
        "intrinsics",
        "height_mm",
        "pitch_deg",
        "roll_deg",
        "sensor",
        "noise_scale",
        "radial",
        "edge_thinning",
    )
)
_MOUNT_REQUIRED = frozenset(("intrinsics", "height_mm"))
_INTRINSICS_FIELDS = frozenset(("width", "height", "fx", "fy", "cx", "cy"))
#: Bounds of a mount's height on the wire: a mount file's (`camera.check_mount`), not what a
#: model supports (the worker judges that).
MOUNT_HEIGHT_MM = MOUNT_HEIGHT_RANGE_MM

_VALID_LABEL = np.zeros(256, bool)
_VALID_LABEL[[lab.id for lab in label_table.LABELS]] = True
_VALID_LABEL[label_table.NO_DEPTH] = True
#: the label ids are 0 .. _MAX_LABEL without a gap: two comparisons check a frame
_MAX_LABEL = max(lab.id for lab in label_table.LABELS)
_IDS_CONTIGUOUS = bool(_VALID_LABEL[: _MAX_LABEL + 1].all())


class WireError(TopsegError):
    """A message (or key) that does not follow the wire format; receivers drop and count it."""


# ---------------------------------------------------------------------------- frames


@dataclass(frozen=True, eq=False)
class DepthFrame:
    """A depth image in millimetres (uint16, 0 = no depth) with its camera and time, and
    where the camera hangs when the sender knows it (`mount`, None when it does not)."""

    depth: np.ndarray
    intrinsics: Intrinsics = KINECT_V1
    seq: int = 0
    stamp_ns: int = 0
    frame_id: str = ""
    mount: TopViewMount | None = None

    def __post_init__(self) -> None:
        _check_image(self.depth, np.uint16, "depth")
        if self.depth.shape != self.intrinsics.shape:
            raise WireError(
                f"depth shape {self.depth.shape} does not match the camera's "
                f"{self.intrinsics.shape} (height, width)"
            )
        _check_header(self.seq, self.stamp_ns, self.frame_id)
        if self.mount is not None:
            if not isinstance(self.mount, TopViewMount):
                raise WireError(f"mount must be a TopViewMount, got {type(self.mount).__name__}")
            check_mount_size(self.mount, self.depth.shape)


def check_mount_size(mount: TopViewMount, shape: tuple[int, int]) -> None:
    """WireError unless `mount`'s intrinsics describe frames of `shape` (rows, cols)."""
    k = mount.intrinsics
    if k.shape != tuple(shape):
        raise WireError(
            f"the mount is for {k.width}x{k.height} frames, this frame is {shape[1]}x{shape[0]}"
        )


@dataclass(frozen=True, eq=False)
class LabelFrame:
    """A label image (uint8 label ids, 255 = no depth) for the depth frame `seq`/`stamp_ns`,
    and the id of the recorded background it was gated with (`background`, None: none)."""

    labels: np.ndarray
    seq: int = 0
    stamp_ns: int = 0
    frame_id: str = ""
    background: str | None = None

    def __post_init__(self) -> None:
        _check_image(self.labels, np.uint8, "labels")
        _check_header(self.seq, self.stamp_ns, self.frame_id)
        if self.background is not None:
            check_background_id(self.background)


def check_background_id(value: Any, name: str = "background") -> str:
    """A background id (64 lowercase hex digits), else WireError naming `name`."""
    if not isinstance(value, str) or not _BACKGROUND_ID.fullmatch(value):
        raise WireError(f"{name} {_short(value)} is not a background id (64 hex digits)")
    return value


def _check_image(arr: Any, dtype: type, what: str) -> None:
    if not isinstance(arr, np.ndarray) or arr.dtype != dtype or arr.ndim != 2:
        got = f"{arr.dtype} {arr.shape}" if isinstance(arr, np.ndarray) else type(arr).__name__
        raise WireError(f"{what} must be a 2-D {np.dtype(dtype).name} array, got {got}")
    h, w = arr.shape
    if not (1 <= h <= MAX_SIDE and 1 <= w <= MAX_SIDE):
        raise WireError(f"{what} is {w}x{h}; each side must be 1..{MAX_SIDE}")


def _check_header(seq: Any, stamp_ns: Any, frame_id: Any) -> None:
    _int_in("seq", seq, 0, _MAX_STAMP)
    _int_in("stamp_ns", stamp_ns, 0, _MAX_STAMP)
    if not isinstance(frame_id, str) or len(frame_id) > MAX_FRAME_ID:
        raise WireError(f"frame_id must be a string of at most {MAX_FRAME_ID} characters")


def _short(value: Any, limit: int = 60) -> str:
    """repr() cut to `limit` characters: error messages never echo a whole payload."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _int_in(name: str, value: Any, lo: int, hi: int) -> int:
    if type(value) is not int and not isinstance(value, np.integer):
        raise WireError(f"{name} must be an integer, got {type(value).__name__}")
    if not lo <= int(value) <= hi:
        raise WireError(f"{name}={_short(value)} is outside {lo}..{hi}")
    return int(value)


def _float(name: str, value: Any) -> float:
    if type(value) not in (int, float):
        raise WireError(f"{name} must be a number, got {type(value).__name__}")
    value = float(value)
    if not math.isfinite(value):
        raise WireError(f"{name} must be finite, got {value}")
    return value


# ---------------------------------------------------------------------------- encode


def _pack(obj: dict) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def _frame_map(seq: int, stamp_ns: int, frame_id: str, img: np.ndarray, encoding: str) -> dict:
    h, w = img.shape
    little = img.astype(img.dtype.newbyteorder("<"), copy=False)
    return {
        "v": SCHEMA_VERSION,
        "seq": int(seq),
        "stamp_ns": int(stamp_ns),
        "frame_id": frame_id,
        "width": w,
        "height": h,
        "encoding": encoding,
        "data": np.ascontiguousarray(little).tobytes(),
    }


def encode_depth(frame: DepthFrame) -> bytes:
    """A depth frame as one msgpack message (with its mount when it has one)."""
    if not isinstance(frame, DepthFrame):
        raise WireError(f"encode_depth takes a DepthFrame, got {type(frame).__name__}")
    msg = _frame_map(frame.seq, frame.stamp_ns, frame.frame_id, frame.depth, DEPTH_ENCODING)
    k = frame.intrinsics
    msg.update(fx=float(k.fx), fy=float(k.fy), cx=float(k.cx), cy=float(k.cy))
    if frame.mount is not None:
        msg["mount"] = mount_map(frame.mount)
    return _pack(msg)


def mount_map(mount: TopViewMount) -> dict:
    """`mount.to_dict()` checked and with plain Python numbers: what goes on the wire (and
    into stats and the driver's `info`). WireError when a value is out of bounds."""
    return check_mount_map(mount.to_dict())


def encode_labels(frame: LabelFrame) -> bytes:
    """A label frame as one msgpack message; refuses ids outside the label table."""
    if not isinstance(frame, LabelFrame):
        raise WireError(f"encode_labels takes a LabelFrame, got {type(frame).__name__}")
    _check_label_values(frame.labels)
    msg = _frame_map(frame.seq, frame.stamp_ns, frame.frame_id, frame.labels, LABELS_ENCODING)
    if frame.background is not None:
        msg["background"] = frame.background
    return _pack(msg)


def _check_label_values(img: np.ndarray) -> None:
    if _IDS_CONTIGUOUS and not np.any((img > _MAX_LABEL) & (img != label_table.NO_DEPTH)):
        return  # the common case, ~20x faster than counting every id
    counts = np.bincount(img.ravel(), minlength=256)
    bad = np.flatnonzero((counts > 0) & ~_VALID_LABEL)
    if bad.size:
        raise WireError(f"labels hold ids that are not in the label table: {bad[:8].tolist()}")


# ---------------------------------------------------------------------------- decode


def _unpack(data: Any) -> dict:
    if not isinstance(data, bytes | bytearray | memoryview):
        raise WireError(f"a message must be bytes, got {type(data).__name__}")
    if len(data) > MAX_MESSAGE_BYTES:
        raise WireError(f"message of {len(data)} bytes exceeds the {MAX_MESSAGE_BYTES}-byte limit")
    try:
        obj = msgpack.unpackb(
            data,
            raw=False,
            strict_map_key=True,
            use_list=False,
            max_bin_len=MAX_SIDE * MAX_SIDE * 2,
            max_str_len=4096,
            max_array_len=64,
            max_map_len=128,
            max_ext_len=0,
        )
    except Exception as exc:  # msgpack raises a zoo of types for bad input
        raise WireError(f"not a msgpack message ({type(exc).__name__}: {exc})") from None
    if not isinstance(obj, dict):
        raise WireError(f"a message must be a msgpack map, got {type(obj).__name__}")
    return obj


def _check_version(v: Any) -> int:
    """The message's schema version, if this reader reads it; WireError saying what to do."""
    if type(v) is not int:
        raise WireError(f"schema version {_short(v)} is not an integer")
    if v not in READABLE_VERSIONS:
        newest = max(READABLE_VERSIONS)
        if v > newest:
            raise WireError(
                f"schema version {v} is newer than this topseg reads "
                f"({', '.join(map(str, READABLE_VERSIONS))}): upgrade topseg on this host"
            )
        raise WireError(f"schema version {v} is not one this topseg reads ({newest})")
    return v


def _check_fields(
    msg: dict,
    expected: frozenset[str],
    what: str,
    optional: frozenset[str] = frozenset(),
    optional_since: int = 2,
) -> int:
    keys, v = set(msg), 0
    if "v" in keys:  # the version first: a newer message's new fields are not "unknown"
        v = _check_version(msg["v"])
        if v < optional_since:
            optional = frozenset()
    if not expected <= keys or not keys <= expected | optional:
        missing = sorted(expected - keys)
        extra = sorted(map(_short, keys - expected - optional))
        parts = [f"missing {missing}" if missing else "", f"unknown {extra}" if extra else ""]
        raise WireError(f"{what} message fields: " + "; ".join(p for p in parts if p))
    return v


def _fields(table: Any, what: str, allowed: frozenset[str], required: frozenset[str]) -> dict:
    if not isinstance(table, Mapping):
        raise WireError(f"{what} must be a map, got {type(table).__name__}")
    keys = set(table)
    if not required <= keys or not keys <= allowed:
        missing = sorted(required - keys)
        extra = sorted(map(_short, keys - allowed))
        raise WireError(f"{what} fields: missing {missing}, unknown {extra}")
    return dict(table)


def _intrinsics_in(name: str, msg: Mapping, w: int, h: int, bounded: bool = True) -> Intrinsics:
    """A frame's intrinsics (or, not `bounded`, a mount's: `check_mount` bounds those)."""
    fx, fy = _float(f"{name}fx", msg["fx"]), _float(f"{name}fy", msg["fy"])
    cx, cy = _float(f"{name}cx", msg["cx"]), _float(f"{name}cy", msg["cy"])
    if not bounded:
        if not (fx > 0 and fy > 0):
            raise WireError(f"focal lengths {name}fx={fx:.3g} fy={fy:.3g} must be positive")
        return Intrinsics(w, h, fx, fy, cx, cy)
    if not (0 < fx <= 100 * MAX_SIDE and 0 < fy <= 100 * MAX_SIDE):
        raise WireError(f"focal lengths {name}fx={fx} fy={fy} must be in (0, {100 * MAX_SIDE}]")
    if not (-w <= cx <= 2 * w and -h <= cy <= 2 * h):
        raise WireError(f"principal point {name}({cx}, {cy}) is far outside the {w}x{h} image")
    return Intrinsics(w, h, fx, fy, cx, cy)


def check_mount_map(d: Any) -> dict:
    """A mount map (`TopViewMount.to_dict()`'s form) checked field by field and returned with
    plain Python values; WireError naming the first bad field."""
    d = _fields(d, "mount", _MOUNT_FIELDS, _MOUNT_REQUIRED)
    kd = _fields(d["intrinsics"], "mount.intrinsics", _INTRINSICS_FIELDS, _INTRINSICS_FIELDS)
    w = _int_in("mount.intrinsics.width", kd["width"], 1, MAX_SIDE)
    h = _int_in("mount.intrinsics.height", kd["height"], 1, MAX_SIDE)
    k = _intrinsics_in("mount.intrinsics.", kd, w, h, bounded=False)
    height = _float("mount.height_mm", d["height_mm"])
    out: dict[str, Any] = {"intrinsics": k.to_dict(), "height_mm": height}
    for name in ("pitch_deg", "roll_deg"):
        if name in d:
            out[name] = _float(f"mount.{name}", d[name])
    if "sensor" in d:
        if not isinstance(d["sensor"], str) or not _NAME.fullmatch(d["sensor"]):
            raise WireError(
                f"mount.sensor {_short(d['sensor'])} must be 1-64 letters, digits, '_', '.', '-'"
            )
        out["sensor"] = d["sensor"]
    if "noise_scale" in d:
        out["noise_scale"] = _float("mount.noise_scale", d["noise_scale"])
    if "radial" in d:
        if not isinstance(d["radial"], bool):
            raise WireError(f"mount.radial {_short(d['radial'])} must be true or false")
        if d["radial"]:
            out["radial"] = True
    if "edge_thinning" in d:
        if not isinstance(d["edge_thinning"], bool):
            raise WireError(
                f"mount.edge_thinning {_short(d['edge_thinning'])} must be true or false"
            )
        if not d["edge_thinning"]:
            out["edge_thinning"] = False
    _mount_of(out)  # the bounds: the one validation of a mount, a mount file's too
    return out


def _mount_of(d: dict) -> TopViewMount:
    """The TopViewMount of a mount map whose fields were type-checked, after `check_mount`
    (the same bounds as a mount file's); WireError naming the first bad field."""
    try:
        mount = from_dict(TopViewMount, d, "mount", required=("intrinsics", "height_mm"))
        return check_mount(mount)
    except (TopsegError, ValueError, TypeError) as exc:
        raise WireError(f"mount: {exc}") from None


def mount_from_map(d: Any) -> TopViewMount:
    """A checked mount map -> TopViewMount; WireError when it is not one."""
    return _mount_of(check_mount_map(d))


def _frame_from_map(msg: dict, encoding: str, dtype: type) -> tuple[np.ndarray, int, int, str]:
    if msg["encoding"] != encoding:
        raise WireError(f"encoding {_short(msg['encoding'])}, expected {encoding!r}")
    width = _int_in("width", msg["width"], 1, MAX_SIDE)
    height = _int_in("height", msg["height"], 1, MAX_SIDE)
    data = msg["data"]
    if not isinstance(data, bytes):
        raise WireError(f"data must be binary, got {type(data).__name__}")
    expected = width * height * BYTES_PER_PIXEL[encoding]
    if len(data) != expected:
        raise WireError(
            f"data holds {len(data)} bytes; {width}x{height} {encoding} needs {expected}"
        )
    _check_header(msg["seq"], msg["stamp_ns"], msg["frame_id"])
    img = np.frombuffer(data, np.dtype(dtype).newbyteorder("<")).reshape(height, width)
    if img.dtype != dtype:  # big-endian host
        img = img.astype(dtype)
    return img, msg["seq"], msg["stamp_ns"], msg["frame_id"]


def decode_depth(data: bytes) -> DepthFrame:
    """Bytes -> DepthFrame (versions 1-6; `mount` None when the message has none), or
    WireError naming what is wrong."""
    msg = _unpack(data)
    _check_fields(msg, _DEPTH_FIELDS, "depth", _DEPTH_OPTIONAL)
    depth, seq, stamp, frame_id = _frame_from_map(msg, DEPTH_ENCODING, np.uint16)
    h, w = depth.shape
    k = _intrinsics_in("", msg, w, h)
    mount = None
    if "mount" in msg:
        mount = mount_from_map(msg["mount"])
        check_mount_size(mount, depth.shape)
    return DepthFrame(depth, k, seq, stamp, frame_id, mount)


def decode_labels(data: bytes) -> LabelFrame:
    """Bytes -> LabelFrame, or WireError naming what is wrong."""
    msg = _unpack(data)
    _check_fields(msg, _LABEL_FIELDS, "labels", _LABEL_OPTIONAL, _LABEL_OPTIONAL_SINCE)
    img, seq, stamp, frame_id = _frame_from_map(msg, LABELS_ENCODING, np.uint8)
    _check_label_values(img)
    background = msg.get("background")
    if background is not None:
        check_background_id(background)
    return LabelFrame(img, seq, stamp, frame_id, background)


# ---------------------------------------------------------------------------- stats

_STATS_REQUIRED = frozenset(("v", "stamp_ns", "timings_ms", "counts"))
_STATS_OPTIONAL = frozenset(("seq", "role", "model_id", "fps", "frame_id"))
#: Stats fields from version 2 on: the share of pixels skipped as floor, the mount in use.
_STATS_OPTIONAL_V2 = frozenset(("floor_share", "mount"))
#: Stats fields from version 6 on: the recorded background in use and whether it matches.
_STATS_OPTIONAL_V6 = frozenset(("background",))
#: Whether the frames still match the recorded background (`worker_background`).
BACKGROUND_STATES = ("match", "mismatch")
_STATS_BACKGROUND_FIELDS = frozenset(
    ("id", "state", "missing_share", "mismatch_share", "sigmas", "margin_mm", "mismatches")
)
#: Where the mount in use came from: the frames, or the worker's own estimate.
MOUNT_SOURCES = ("frame", "estimated")
_STATS_MOUNT_FIELDS = frozenset(("height_mm", "pitch_deg", "roll_deg", "sensor", "source", "moved"))
_MAX_ENTRIES = 64


def _check_stats(msg: Mapping) -> dict:
    keys = set(msg)
    optional = _STATS_OPTIONAL
    version = _check_version(msg["v"]) if "v" in keys else 0
    if version >= 2:
        optional = optional | _STATS_OPTIONAL_V2
    if version >= 6:
        optional = optional | _STATS_OPTIONAL_V6
    if not _STATS_REQUIRED <= keys or not keys <= _STATS_REQUIRED | optional:
        missing = sorted(_STATS_REQUIRED - keys)
        extra = sorted(map(_short, keys - _STATS_REQUIRED - optional))
        raise WireError(f"stats message fields: missing {missing}, unknown {extra}")
    out: dict[str, Any] = {"v": msg["v"]}
    out["stamp_ns"] = _int_in("stamp_ns", msg["stamp_ns"], 0, _MAX_STAMP)
    if "seq" in msg:
        out["seq"] = _int_in("seq", msg["seq"], 0, _MAX_STAMP)
    for name in ("role", "model_id", "frame_id"):
        if name in msg:
            if not isinstance(msg[name], str) or len(msg[name]) > MAX_FRAME_ID:
                raise WireError(f"{name} must be a string of at most {MAX_FRAME_ID} characters")
            out[name] = msg[name]
    if "fps" in msg:
        out["fps"] = _float("fps", msg["fps"])
        if out["fps"] < 0:
            raise WireError(f"fps must be >= 0, got {out['fps']}")
    out["timings_ms"] = _named_numbers(msg["timings_ms"], "timings_ms", _nonneg_float)
    out["counts"] = _named_numbers(msg["counts"], "counts", _count)
    if "floor_share" in msg:
        out["floor_share"] = _float("floor_share", msg["floor_share"])
        if not 0.0 <= out["floor_share"] <= 1.0:
            raise WireError(f"floor_share must be in 0..1, got {out['floor_share']}")
    if "mount" in msg:
        out["mount"] = _check_stats_mount(msg["mount"])
    if "background" in msg:
        out["background"] = _check_stats_background(msg["background"])
    return out


def _check_stats_background(table: Any) -> dict:
    """The worker's recorded background: its id, whether the frames match it, the share of
    its pixels they saw farther than it, its settings and how often it stopped matching."""
    d = _fields(table, "stats background", _STATS_BACKGROUND_FIELDS, _STATS_BACKGROUND_FIELDS)
    out: dict[str, Any] = {"id": check_background_id(d["id"], "background.id")}
    if d["state"] not in BACKGROUND_STATES:
        raise WireError(f"background.state {_short(d['state'])} is not one of {BACKGROUND_STATES}")
    out["state"] = d["state"]
    for name in ("missing_share", "mismatch_share"):
        out[name] = _float(f"background.{name}", d[name])
        if not 0.0 <= out[name] <= 1.0:
            raise WireError(f"background.{name} must be in 0..1, got {out[name]}")
    for name in ("sigmas", "margin_mm"):
        out[name] = _nonneg_float(f"background.{name}", d[name])
    out["mismatches"] = _count("background.mismatches", d["mismatches"])
    return out


def _check_stats_mount(table: Any) -> dict:
    """The worker's mount in use: height, tilt, sensor, where it came from, moves seen."""
    d = _fields(table, "stats mount", _STATS_MOUNT_FIELDS, _STATS_MOUNT_FIELDS)
    out: dict[str, Any] = {}
    lo, hi = MOUNT_HEIGHT_MM
    out["height_mm"] = _float("mount.height_mm", d["height_mm"])
    if not lo <= out["height_mm"] <= hi:
        raise WireError(f"mount.height_mm={out['height_mm']} is outside {lo:g}..{hi:g} mm")
    for name in ("pitch_deg", "roll_deg"):
        out[name] = _float(f"mount.{name}", d[name])
        if abs(out[name]) > MAX_MOUNT_TILT_DEG:
            raise WireError(f"mount.{name}={out[name]} is outside +-{MAX_MOUNT_TILT_DEG:g} degrees")
    if not isinstance(d["sensor"], str) or not _NAME.fullmatch(d["sensor"]):
        raise WireError(f"mount.sensor {_short(d['sensor'])} is not a sensor name")
    out["sensor"] = d["sensor"]
    if d["source"] not in MOUNT_SOURCES:
        raise WireError(f"mount.source {_short(d['source'])} is not one of {MOUNT_SOURCES}")
    out["source"] = d["source"]
    out["moved"] = _count("mount.moved", d["moved"])
    return out


def _nonneg_float(name: str, value: Any) -> float:
    value = _float(name, value)
    if value < 0:
        raise WireError(f"{name} must be >= 0, got {value}")
    return value


def _count(name: str, value: Any) -> int:
    return _int_in(name, value, 0, _MAX_STAMP)


def _named_numbers(table: Any, what: str, check) -> dict:
    if not isinstance(table, Mapping) or len(table) > _MAX_ENTRIES:
        raise WireError(f"{what} must be a map of at most {_MAX_ENTRIES} entries")
    out = {}
    for name, value in table.items():
        if not isinstance(name, str) or not _NAME.fullmatch(name):
            raise WireError(f"{what} has a bad entry name {_short(name)}")
        out[name] = check(f"{what}.{name}", value)
    return out


def encode_stats(stats: Mapping[str, Any]) -> bytes:
    """A stats map -> msgpack bytes.

    Required: `stamp_ns`, `timings_ms` ({stage: ms}), `counts` ({name: int}, e.g. processed,
    dropped, rejected). Optional: `seq`, `role`, `model_id`, `fps`, `frame_id`, `floor_share`
    (share of the frame's pixels skipped as floor, 0..1), `mount` (the mount in use:
    height_mm, pitch_deg, roll_deg, sensor, source "frame" | "estimated", and `moved`: how
    often the camera was seen to move) and `background` (the recorded background: id, state
    "match" | "mismatch", missing_share, mismatch_share, sigmas, margin_mm, mismatches).
    `v` is added.
    """
    return _pack(_check_stats({"v": SCHEMA_VERSION, **stats}))


def decode_stats(data: bytes) -> dict:
    """Bytes -> a validated, JSON-able stats dict (versions 1-6), or WireError."""
    return _check_stats(_unpack(data))


# ---------------------------------------------------------------------------- keys


def _check_name(what: str, name: Any) -> str:
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise WireError(
            f"{what} name {_short(name)} must be 1-64 characters of letters, digits, '_', '.', '-'"
        )
    return name


def camera_prefix(cell: str, camera: str) -> str:
    """`topseg/<cell>/<camera>`, after checking both names are plain key chunks (and not
    `_any/_any`, the chunks of `any_alive_key`)."""
    if (cell, camera) == (ANY, ANY):
        raise WireError(f"{ANY}/{ANY} is reserved for services that serve every camera")
    return f"{ROOT}/{_check_name('cell', cell)}/{_check_name('camera', camera)}"


def depth_key(cell: str = DEFAULT_CELL, camera: str = DEFAULT_CAMERA) -> str:
    """Where a camera's driver publishes its depth frames (`encode_depth` messages)."""
    return f"{camera_prefix(cell, camera)}/depth"


def labels_key(cell: str = DEFAULT_CELL, camera: str = DEFAULT_CAMERA) -> str:
    """Where the worker publishes the label image computed from each depth frame."""
    return f"{camera_prefix(cell, camera)}/labels"


def truth_key(cell: str = DEFAULT_CELL, camera: str = DEFAULT_CAMERA) -> str:
    """Ground-truth labels, when the source knows them (synthetic scenes, recordings)."""
    return f"{camera_prefix(cell, camera)}/truth"


def stats_key(cell: str = DEFAULT_CELL, camera: str = DEFAULT_CAMERA) -> str:
    """Where the worker publishes its per-camera stats (`encode_stats` maps)."""
    return f"{camera_prefix(cell, camera)}/stats"


def info_key(cell: str = DEFAULT_CELL, camera: str = DEFAULT_CAMERA) -> str:
    """The driver's queryable: its source, intrinsics, fps and health as JSON."""
    return f"{camera_prefix(cell, camera)}/info"


#: The cell/camera chunks of the token a worker serving every camera holds (`any_alive_key`).
ANY = "_any"


def alive_key(cell: str, camera: str, role: str, instance: str | None = None) -> str:
    """Liveliness token of one service (`driver`, `worker`, ...) for one camera; with
    `instance` (the process's Zenoh id) `.../alive/<role>/<instance>`, so that two processes
    in one role for one camera hold two tokens (Zenoh merges equal token keys into one)."""
    key = f"{camera_prefix(cell, camera)}/alive/{_check_name('role', role)}"
    return key if instance is None else f"{key}/{_check_name('instance', instance)}"


def any_alive_key(role: str, instance: str) -> str:
    """Token of a process that serves every camera (a worker without --cameras), held also
    while it waits for its first frame: `topseg/_any/_any/alive/<role>/<instance>`."""
    role, instance = _check_name("role", role), _check_name("instance", instance)
    return f"{ROOT}/{ANY}/{ANY}/alive/{role}/{instance}"


@dataclass(frozen=True)
class KeyParts:
    """A parsed key: cell, camera, kind (one of KINDS or `alive`) and, for `alive`, the role
    and the instance (None in a token of a topseg before instances; cell and camera are
    `ANY` in `any_alive_key`)."""

    cell: str
    camera: str
    kind: str
    role: str | None = None
    instance: str | None = None


def parse_key(key: str) -> KeyParts:
    """Split a concrete topseg key expression; WireError if it is not one. `ANY/ANY` is a
    token's only (`any_alive_key`): a message key that names it names no camera."""
    parts = key.split("/") if isinstance(key, str) else []
    if len(parts) in (5, 6) and parts[0] == ROOT and parts[3] == "alive":
        _check_name("cell", parts[1]), _check_name("camera", parts[2])
        instance = _check_name("instance", parts[5]) if len(parts) == 6 else None
        return KeyParts(parts[1], parts[2], "alive", _check_name("role", parts[4]), instance)
    if len(parts) != 4 or parts[0] != ROOT or parts[3] not in KINDS:
        raise WireError(
            f"{_short(key)} is not a topseg key (topseg/<cell>/<camera>/<{'|'.join(KINDS)}>)"
        )
    camera_prefix(parts[1], parts[2])  # plain names, and not the reserved pair
    return KeyParts(parts[1], parts[2], parts[3])


_PLAIN_KEY = re.compile(r"[A-Za-z0-9_.*/-]{1,300}")


def shown_key(key: Any) -> str:
    """A key as logs and messages print it: itself when it holds only letters, digits and
    '_', '.', '-', '/', '*'; else escaped (repr) and cut short, so that a key read from a file
    or the wire never writes control characters or escape codes to a terminal."""
    if isinstance(key, str) and _PLAIN_KEY.fullmatch(key):
        return key
    return _short(key, 80)


def depth_key_problem(key: Any) -> str | None:
    """Why `key` is no camera's depth key, in one line (the checks of `parse_key`, the key
    escaped), or None when it is one: what keys read from a recording are held to."""
    try:
        parts = parse_key(key)
    except WireError as exc:
        return str(exc)
    return None if parts.kind == "depth" else f"{shown_key(key)} is not a depth key"


def instance_attachment(instance: str) -> bytes:
    """The Zenoh attachment a service puts on its messages: its instance id, so a reader
    tells two publishers on one key apart (the msgpack message itself is unchanged, so
    older readers and recordings are unaffected)."""
    return _check_name("instance", instance).encode()


def instance_of(attachment: Any) -> str | None:
    """The instance id in a message's attachment (`instance_attachment`); None when there is
    none or it is not one (an older topseg, another tool)."""
    if attachment is None:
        return None
    try:
        raw = attachment if isinstance(attachment, bytes) else attachment.to_bytes()
        text = raw.decode("ascii") if len(raw) <= 64 else ""
    except (UnicodeDecodeError, AttributeError):
        return None
    return text if _NAME.fullmatch(text) else None


def decode_for_key(key: str, data: bytes) -> DepthFrame | LabelFrame | dict:
    """Decode a message by the kind its key names (depth, labels, truth or stats)."""
    kind = parse_key(key).kind
    if kind == "depth":
        return decode_depth(data)
    if kind in ("labels", "truth"):
        return decode_labels(data)
    if kind == "stats":
        return decode_stats(data)
    raise WireError(f"{key!r} does not carry a msgpack frame message")


#: A depth stamp's sane window against a receiver's clock (the worker's, `topseg status`'s): at most STAMP_AHEAD_S ahead
#: (more is clock skew between hosts) and STAMP_AGE_S old (more is a clock far behind, or
#: a stamp that is no time at all). Frames outside it get no latency and are counted as
#: `stamps_out_of_window`.
STAMP_AHEAD_S = 1.0
STAMP_AGE_S = 60.0
