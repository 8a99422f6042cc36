"""The model file (DESIGN section 4): a forest's flat arrays and a JSON header, no pickle.

Layout: a deflate-compressed numpy `.npz` zip archive holding

- `header`: uint8 bytes of a UTF-8 JSON object with `magic` ("topseg-model"),
  `format_version`, `labels` (the label table the forest predicts), `forest` (its shape and
  `background_mm`), and whatever the caller adds (camera, feature and training config,
  dataset fingerprint, validation metrics...);
- one `.npy` member per array of `Forest.arrays()`.

Compressed because a forest's posteriors and unused leaf fields are mostly zeros: the bundled
2-tree depth-19 model is 4.7 MB instead of 25.7 MB, and loads in 70 ms instead of 22 ms.
Every member is covered by the zip's CRC-32, so flipped bytes are caught on reading; the
arrays are then checked for dtype, shape and index bounds (`tree.validate_arrays`) so a
damaged file can never make inference read out of bounds. Writes are atomic: a temporary
file in the same directory is renamed over the target.
"""

from __future__ import annotations

import json
import os
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from topseg.core import labels
from topseg.core.atomic import atomic_write
from topseg.core.errors import TopsegError
from topseg.core.forest.tree import ARRAY_DTYPES, Forest

MAGIC = "topseg-model"
FORMAT_VERSION = 1
ARRAY_NAMES = (*ARRAY_DTYPES, "roots")
_RESERVED = ("magic", "format_version", "labels", "forest")


class ModelFileError(TopsegError):
    """A model file that cannot be used: missing, damaged, foreign or of another version."""


def _forest_header(forest: Forest) -> dict[str, Any]:
    return {
        "n_trees": forest.n_trees,
        "n_nodes": forest.n_nodes,
        "n_leaves": int(forest.posteriors.shape[0]),
        "features_per_node": forest.features_per_node,
        "max_depth": forest.depth,
        "background_mm": int(forest.background_mm),
    }


def save_model(
    path: str | os.PathLike, forest: Forest, header: dict[str, Any] | None = None
) -> None:
    """Write `forest` and `header` to `path` atomically (see the module docstring)."""
    path = Path(path)
    extra = dict(header or {})
    clash = [k for k in _RESERVED if k in extra]
    if clash:
        raise ModelFileError(f"header keys {clash} are reserved for the model file itself")
    full = {
        "magic": MAGIC,
        "format_version": FORMAT_VERSION,
        "labels": labels.as_json(),
        "forest": _forest_header(forest),
        **extra,
    }
    try:
        blob = json.dumps(full, sort_keys=True, allow_nan=False).encode("utf-8")
    except (TypeError, ValueError) as exc:
        raise ModelFileError(f"model header is not plain JSON: {exc}") from None
    arrays = {"header": np.frombuffer(blob, np.uint8), **forest.arrays()}
    with atomic_write(path) as f:
        np.savez_compressed(f, **arrays)


def _read_header(npz: Any, path: Path) -> dict[str, Any]:
    if "header" not in npz.files:
        raise ModelFileError(f"{path} is not a topseg model file (no header)")
    raw = npz["header"]
    if raw.dtype != np.uint8 or raw.ndim != 1:
        raise ModelFileError(f"{path}: the header is not a byte string")
    try:
        header = json.loads(raw.tobytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ModelFileError(f"{path}: the header is not valid JSON ({exc})") from None
    if not isinstance(header, dict) or header.get("magic") != MAGIC:
        raise ModelFileError(f"{path} is not a topseg model file (wrong magic)")
    version = header.get("format_version")
    if version != FORMAT_VERSION:
        raise ModelFileError(
            f"{path} has model format version {version!r}; this topseg reads version "
            f"{FORMAT_VERSION} (retrain or convert the model)"
        )
    if header.get("labels") != labels.as_json():
        raise ModelFileError(f"{path} was trained for a different label table than this topseg's")
    forest = header.get("forest")
    if not isinstance(forest, dict) or not isinstance(forest.get("background_mm"), int):
        raise ModelFileError(f"{path}: the header does not describe the forest")
    return header


def load_model(path: str | os.PathLike) -> tuple[Forest, dict[str, Any]]:
    """Read a model file: (forest, header). Raises ModelFileError saying what is wrong."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            start = f.read(4)
    except FileNotFoundError:
        raise ModelFileError(f"no model file at {path}") from None
    except OSError as exc:
        raise ModelFileError(f"cannot read model file {path}: {exc}") from None
    if start != b"PK\x03\x04":
        raise ModelFileError(f"{path} is not a topseg model file (not a zip archive)")
    try:
        with np.load(path, allow_pickle=False) as npz:
            header = _read_header(npz, path)
            missing = [name for name in ARRAY_NAMES if name not in npz.files]
            if missing:
                raise ModelFileError(f"{path} lacks the arrays {missing}")
            arrays = {name: npz[name] for name in ARRAY_NAMES}
    except ModelFileError:
        raise
    except (zipfile.BadZipFile, zlib.error, ValueError, OSError, EOFError, KeyError) as exc:
        raise ModelFileError(f"{path} is damaged or truncated ({exc})") from None
    try:
        forest = Forest(**arrays, background_mm=header["forest"]["background_mm"])
    except ValueError as exc:
        raise ModelFileError(f"{path} holds an inconsistent forest: {exc}") from None
    if forest.n_trees != header["forest"].get("n_trees") or forest.n_nodes != header["forest"].get(
        "n_nodes"
    ):
        raise ModelFileError(f"{path}: the arrays do not match the header's forest description")
    return forest, header
