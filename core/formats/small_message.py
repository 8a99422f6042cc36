"""Checks shared by the small msgpack messages (the safety state, joint states): unpack a map
with tight limits and read its fields, each failure one `WireError` naming the field.

The frame messages (`wire.py`) carry images and have their own, larger limits; these carry a
few numbers and names, so a message of more than `max_bytes` is refused before it is parsed.
"""

from __future__ import annotations

import math
from typing import Any

import msgpack

from topseg.core.formats.wire import WireError

#: The largest small message read (bytes): a few dozen names and numbers fit many times over.
MAX_SMALL_BYTES = 64 * 1024


def short(value: Any, limit: int = 60) -> str:
    """repr() cut to `limit` characters: error messages never echo a whole payload."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def unpack_map(
    data: Any,
    what: str,
    max_bytes: int = MAX_SMALL_BYTES,
    max_items: int = 256,
    max_str_len: int = 4096,
    max_map_len: int | None = None,
) -> dict:
    """The msgpack map in `data`; WireError for anything else (not bytes, too long, not
    msgpack, not a map, arrays, maps (`max_map_len`, default `max_items`) or strings over
    the limits)."""
    if not isinstance(data, bytes | bytearray | memoryview):
        raise WireError(f"a {what} message must be bytes, got {type(data).__name__}")
    if len(data) > max_bytes:
        raise WireError(f"{what} message of {len(data)} bytes exceeds the {max_bytes}-byte limit")
    try:
        obj = msgpack.unpackb(
            data,
            raw=False,
            strict_map_key=True,
            use_list=True,
            max_bin_len=0,
            max_str_len=max_str_len,
            max_array_len=max_items,
            max_map_len=max_items if max_map_len is None else max_map_len,
            max_ext_len=0,
        )
    except Exception as exc:  # msgpack raises a zoo of types for bad input
        raise WireError(f"{what}: not a msgpack message ({type(exc).__name__}: {exc})") from None
    if not isinstance(obj, dict):
        raise WireError(f"a {what} message must be a msgpack map, got {type(obj).__name__}")
    return obj


def check_keys(msg: dict, what: str, required: frozenset[str], optional: frozenset[str]) -> None:
    """WireError naming the missing and unknown fields, if any."""
    keys = set(msg)
    missing = sorted(required - keys)
    extra = sorted(map(short, keys - required - optional))
    if missing or extra:
        parts = [f"missing {missing}" if missing else "", f"unknown {extra}" if extra else ""]
        raise WireError(f"{what} message fields: " + "; ".join(p for p in parts if p))


def int_in(name: str, value: Any, lo: int, hi: int) -> int:
    """An int (not a bool) within lo..hi, else WireError naming `name`."""
    if type(value) is not int:
        raise WireError(f"{name} must be an integer, got {type(value).__name__}")
    if not lo <= value <= hi:
        raise WireError(f"{name}={short(value)} is outside {lo}..{hi}")
    return value


def finite_float(name: str, value: Any, lo: float = -math.inf, hi: float = math.inf) -> float:
    """A finite number within lo..hi as a float, else WireError naming `name`."""
    if type(value) not in (int, float):
        raise WireError(f"{name} must be a number, got {type(value).__name__}")
    value = float(value)
    if not math.isfinite(value) or not lo <= value <= hi:
        raise WireError(f"{name}={short(value)} is not a finite number within {lo:g}..{hi:g}")
    return value


def text(name: str, value: Any, max_len: int) -> str:
    """A string of at most `max_len` characters, else WireError naming `name`."""
    if not isinstance(value, str) or len(value) > max_len:
        raise WireError(f"{name} must be a string of at most {max_len} characters")
    return value
