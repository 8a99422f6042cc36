"""The model file (DESIGN section 4): a forest's flat arrays and a JSON header, no pickle.

Layout: a deflate-compressed numpy `.npz` zip archive holding

- `header`: uint8 bytes of a UTF-8 JSON object with `magic` ("topseg-model"),
  `format_version`, `labels` (the classes the forest predicts: the first n_classes rows of
  the label table, then no-depth; a model trained before the table grew holds a shorter
  prefix of today's table and still loads), `forest` (its shape,
  `background_mm` and `off_image`), and whatever the caller adds (camera, feature and
  training config, dataset fingerprint, validation metrics...);
- one `.npy` member per array of `Forest.arrays()`.

Compressed because a forest's posteriors and unused leaf fields are mostly zeros: the bundled
2-tree depth-19 model is 4.7 MB instead of 25.7 MB, and loads in 70 ms instead of 22 ms.
Every member is covered by the zip's CRC-32, so flipped bytes are caught on reading; the
arrays are then checked for dtype, shape and index bounds (`tree.validate_arrays`) so a
damaged file can never make inference read out of bounds. A file that is intact but says
nonsense (a checksummed member altered and re-zipped) is refused too, before anything is
allocated for it: each `.npy` member's own header must describe an array of its expected
dtype that fits the member and `MAX_ARRAY_BYTES`; the JSON header must be small and not
nested deeper than `MAX_HEADER_NESTING`; its forest description (`background_mm`, tree,
node and leaf counts, features per node, depth) must agree with the arrays, and its camera
and feature config must be readable (`check_header`). Writes are atomic: a temporary file in
the same directory is renamed over the target.
"""

from __future__ import annotations

import json
import os
import re
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from topseg.core import labels
from topseg.core.atomic import atomic_write
from topseg.core.errors import TopsegError
from topseg.core.forest.feature_config import OFF_IMAGE_READS
from topseg.core.forest.model_header import model_camera, model_features
from topseg.core.forest.tree import ARRAY_DTYPES, Forest

MAGIC = "topseg-model"
FORMAT_VERSION = 1
ARRAY_NAMES = (*ARRAY_DTYPES, "roots")
_RESERVED = ("magic", "format_version", "labels", "forest")
#: the largest array a model file may hold (the bundled model's largest is ~26 MB)
MAX_ARRAY_BYTES = 4 << 30
#: the largest JSON header a model file may hold
MAX_HEADER_BYTES = 64 << 20
#: the deepest nesting of lists and objects a model header may have
MAX_HEADER_NESTING = 64
#: deflate expands at most ~1032:1; a member claiming more than this ratio is lying
_MAX_DEFLATE_RATIO = 1100
#: `background_mm` bounds (`FeatureConfig.background_mm`: clamped differences fit int16)
_BACKGROUND_MM = (1, 16000)


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
        "off_image": "nearest" if forest.nearest_off_image else "background",
    }


def caller_header(header: dict[str, Any]) -> dict[str, Any]:
    """A loaded header without the keys `save_model` writes itself: what to pass it back to
    write the same model again (with changes)."""
    return {k: v for k, v in header.items() if k not in _RESERVED}


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
        "labels": labels.as_json(forest.n_classes),
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


def _check_members(path: Path) -> None:
    """Refuse, before numpy allocates anything, a member whose `.npy` header claims an array
    of the wrong dtype, or larger than the member or `MAX_ARRAY_BYTES`."""
    expected = {**ARRAY_DTYPES, "roots": np.dtype(np.int32), "header": np.dtype(np.uint8)}
    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            name = info.filename.removesuffix(".npy")
            if name not in expected:
                continue
            limit = MAX_HEADER_BYTES if name == "header" else MAX_ARRAY_BYTES
            if info.file_size > limit + 4096 or (
                info.compress_type != zipfile.ZIP_STORED
                and info.file_size > _MAX_DEFLATE_RATIO * info.compress_size + 4096
            ):
                raise ModelFileError(
                    f"{path}: member {name!r} claims {info.file_size} bytes, more than a "
                    "model file holds"
                )
            with zf.open(info) as f:
                try:
                    version = np.lib.format.read_magic(f)
                    read = (
                        np.lib.format.read_array_header_1_0
                        if version == (1, 0)
                        else np.lib.format.read_array_header_2_0
                    )
                    shape, _, dtype = read(f)
                except (ValueError, OSError, EOFError, SyntaxError, TypeError) as exc:
                    raise ModelFileError(
                        f"{path}: member {name!r} is not an array ({exc})"
                    ) from None
                offset = f.tell()
            if dtype != expected[name]:
                raise ModelFileError(
                    f"{path}: array {name!r} has dtype {dtype}, expected {expected[name]}"
                )
            nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
            if nbytes > limit or offset + nbytes != info.file_size:
                raise ModelFileError(
                    f"{path}: array {name!r} claims shape {shape} ({nbytes} bytes), which its "
                    f"{info.file_size}-byte member does not hold"
                )


def _nesting(text: str) -> int:
    """The deepest nesting of `[` and `{` in JSON `text`, brackets inside strings ignored."""
    depth = deepest = 0
    for ch in re.findall(r"[\[\]{}]", re.sub(r'"(?:[^"\\]|\\.)*"', "", text)):
        depth += 1 if ch in "[{" else -1
        deepest = max(deepest, depth)
    return deepest


def _read_header(npz: Any, path: Path) -> dict[str, Any]:
    if "header" not in npz.files:
        raise ModelFileError(f"{path} is not a topseg model file (no header)")
    raw = npz["header"]
    if raw.dtype != np.uint8 or raw.ndim != 1:
        raise ModelFileError(f"{path}: the header is not a byte string")
    try:
        text = raw.tobytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ModelFileError(f"{path}: the header is not valid UTF-8 ({exc})") from None
    if _nesting(text) > MAX_HEADER_NESTING:
        raise ModelFileError(f"{path}: the header nests more than {MAX_HEADER_NESTING} levels deep")
    try:
        header = json.loads(text)
    except (json.JSONDecodeError, RecursionError) as exc:
        raise ModelFileError(f"{path}: the header is not valid JSON ({exc})") from None
    if not isinstance(header, dict) or header.get("magic") != MAGIC:
        raise ModelFileError(f"{path} is not a topseg model file (wrong magic)")
    version = header.get("format_version")
    if version != FORMAT_VERSION:
        raise ModelFileError(
            f"{path} has model format version {version!r}; this topseg reads version "
            f"{FORMAT_VERSION} (retrain or convert the model)"
        )
    if labels.table_classes(header.get("labels")) is None:
        raise ModelFileError(f"{path} was trained for a different label table than this topseg's")
    forest = header.get("forest")
    if not isinstance(forest, dict) or not _is_int(forest.get("background_mm")):
        raise ModelFileError(f"{path}: the header does not describe the forest")
    lo, hi = _BACKGROUND_MM
    if not lo <= forest["background_mm"] <= hi:
        raise ModelFileError(
            f"{path}: the header's background_mm {forest['background_mm']} is outside "
            f"[{lo}, {hi}] mm"
        )
    if forest.get("off_image", "background") not in OFF_IMAGE_READS:
        raise ModelFileError(
            f"{path}: the header's off_image {forest['off_image']!r} is not one of "
            f"{', '.join(OFF_IMAGE_READS)}"
        )
    return header


def _is_int(value: Any) -> bool:
    """A JSON integer (not a bool)."""
    return isinstance(value, int) and not isinstance(value, bool)


def check_header(forest: Forest, header: dict[str, Any], path: str | os.PathLike) -> None:
    """Refuse a header that disagrees with its forest or names an unreadable camera or
    feature config: ModelFileError naming `path` and the first thing wrong."""
    described = header.get("forest", {})
    actual = {
        "n_trees": forest.n_trees,
        "n_nodes": forest.n_nodes,
        "n_leaves": int(forest.posteriors.shape[0]),
        "features_per_node": forest.features_per_node,
        "max_depth": forest.depth,
    }
    for key, value in actual.items():
        if key in described and described[key] != value:
            raise ModelFileError(
                f"{path}: the header says {key} {described[key]!r} but the arrays hold {value}"
            )
    for key in ("n_trees", "n_nodes"):
        if key not in described:
            raise ModelFileError(f"{path}: the header's forest description lacks {key!r}")
    if labels.table_classes(header.get("labels")) != forest.n_classes:
        raise ModelFileError(
            f"{path}: the header names {len(header.get('labels', [])) - 1} classes but the "
            f"posteriors hold {forest.n_classes}"
        )
    try:
        model_camera(header)
        features = model_features(header, forest)
    except TopsegError as exc:
        raise ModelFileError(f"{path}: {exc}") from None
    if features is not None and features.nearest_off_image != forest.nearest_off_image:
        raise ModelFileError(
            f"{path}: the header's features and forest disagree on what probes off the image read"
        )


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
        _check_members(path)
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
        described = header["forest"]
        forest = Forest(
            **arrays,
            background_mm=described["background_mm"],
            # a header without `off_image`: the forest was trained with probes off the
            # image reading background_mm
            nearest_off_image=described.get("off_image", "background") == "nearest",
        )
    except ValueError as exc:
        raise ModelFileError(f"{path} holds an inconsistent forest: {exc}") from None
    check_header(forest, header, path)
    return forest, header
