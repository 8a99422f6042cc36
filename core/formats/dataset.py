"""The synthetic dataset on disk: a Zarr v3 store that datagen writes and training reads.

Layout (one directory, a Zarr v3 group; DESIGN section 4)::

    zarr.json           group attributes (below)
    depth/              (N, H, W) uint16 mm, 0 = no depth
    labels/             (N, H, W) uint8 label ids, 255 = no depth
    scene/              (N,) variable-length UTF-8: each frame's scene description as JSON
    complete/           (N,) uint8: 1 once all three of a frame's chunks are written

Frames may come from cameras of different resolutions (a mount drawn per frame): the arrays
are FRAME_SHAPE (480 x 640, the largest supported sensor's), and a smaller frame is stored
top-left with depth 0 and labels NO_DEPTH (255) outside it. Each frame's camera mount is in
its scene JSON under "mount" (`Dataset.mount(k)`; a dataset whose scenes hold no mount
falls back to the `camera` attribute); `mount(k).intrinsics.shape` says how much of the stored
frame is the frame, and `Dataset.frame(k)` returns it cropped.

`depth`, `labels` and `scene` have one frame per chunk. Image chunks are Blosc-zstd (level 1,
byte shuffle: ~2.5x on noisy depth at under a millisecond a frame) followed by a CRC32C
checksum, so a damaged chunk is reported instead of decoded into garbage. The scene JSON lives
in the store itself (not in side files) so that the dataset is one Zarr hierarchy that any
Zarr v3 reader can open.

Never a half-written frame: Zarr's local store writes every chunk to a temporary file and
renames it into place, and a frame's `complete` flag is set only after its three chunks are
written (by one client, the only writer of `complete`). Readers see complete frames only; a
resumed run rewrites every frame whose flag is not set. A SIGKILL can leave `*.partial` temp
files behind; `DatasetWriter.open` removes them. Data chunks are not fsynced: a killed process
loses nothing the kernel already holds, a power cut may need the run to be redone.

Root attributes: `topseg_dataset` (format name and version), `frames`, `height`, `width`,
`seed`, `mode`, `noise`, `room`, `generator` (the frame factory and its full config),
`frame_seed` (how a frame's seed derives from `seed`), `camera` (the fixed mount, or the
fallback of frames without their own), `mounts` (what the frames' mounts span: height_mm
[lo, hi], tilt_deg, sensors, resolutions; what a model header's `trained_for` records),
`labels` (the label table), `topseg_version`, `created`. The identity of a dataset (what must match to resume into it) is
everything but `frames`, `topseg_version` and `created`; `frames` may grow. A dataset made
before the label table grew holds a prefix of today's table: it resumes, and its frames
keep to the classes it names.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from topseg import __version__
from topseg.core import labels as label_table
from topseg.core.camera import PAPER_MOUNT, TopViewMount
from topseg.core.errors import TopsegError
from topseg.core.formats.zarr_chunks import ChunkWriter

FORMAT = "topseg-dataset"
FORMAT_VERSION = 1
FRAME_SHAPE = (480, 640)
ARRAYS = ("depth", "labels", "scene", "complete")
#: attributes that describe a run rather than the frames; they may differ on resume
RUN_ATTRS = ("frames", "topseg_version", "created")
#: `complete` flags per chunk (one client rewrites a flag chunk whenever frames finish)
COMPLETE_CHUNK = 4096
FRAME_SEED_RULE = (
    "numpy.random.SeedSequence([seed, index]).generate_state(2, uint32) read as one uint64"
)


class DatasetError(TopsegError):
    """A dataset that cannot be read or written as asked: missing, damaged, or a different run."""


def frame_seed(seed: int, index: int) -> int:
    """The seed of frame `index` of a dataset made with `seed`: a pure function of the two.

    It does not depend on which worker renders the frame or in what order, which is what
    makes a dataset the same whatever the number of workers.
    """
    if seed < 0 or index < 0:
        raise ValueError(f"seed and index must be >= 0, got seed={seed} index={index}")
    lo, hi = np.random.SeedSequence([seed, index]).generate_state(2, np.uint32)
    return int(lo) | (int(hi) << 32)


def _codecs():
    from zarr.codecs import BloscCodec, Crc32cCodec

    return (BloscCodec(cname="zstd", clevel=1, shuffle="shuffle"), Crc32cCodec())


def dataset_os_error(exc: OSError, path: Path, doing: str) -> TopsegError:
    """A full disk, a read-only place or a bad path as one line saying what to do."""
    where = exc.filename or path
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return DatasetError(
            f"no space left on the device while {doing} {where}; free some space and rerun "
            "the same command (complete frames are kept)"
        )
    if exc.errno == errno.EROFS:
        return DatasetError(f"{where} is on a read-only file system; choose a writable --out")
    if exc.errno in (errno.EACCES, errno.EPERM):
        return DatasetError(
            f"no permission to write {where} while {doing}; choose a writable --out"
        )
    return DatasetError(f"cannot {doing} {where}: {exc.strerror or exc}")


def _identity(attrs: dict) -> dict:
    return {k: v for k, v in attrs.items() if k not in RUN_ATTRS}


def _canonical(value: Any) -> Any:
    """JSON round trip, so that tuples/lists compare as stored. Key order is kept: a
    generator may draw from a config dict in its order (the synthesis pose weights do)."""
    return json.loads(json.dumps(value))


def make_attrs(
    *,
    seed: int,
    mode: str,
    noise: str,
    room: str | None,
    generator: dict,
    frames: int,
    shape: tuple[int, int] = FRAME_SHAPE,
    camera: dict | None = None,
    mounts: dict | None = None,
) -> dict:
    """The root attributes of a new dataset (see the module docstring); `mounts` None: every
    frame is seen from `camera` (the paper's mount when that is None too)."""
    camera = camera if camera is not None else PAPER_MOUNT.to_dict()
    if mounts is None:
        mounts = _fixed_summary(TopViewMount.from_dict(camera, "dataset camera"))
    return _canonical(
        {
            "topseg_dataset": {"format": FORMAT, "version": FORMAT_VERSION},
            "frames": int(frames),
            "height": int(shape[0]),
            "width": int(shape[1]),
            "seed": int(seed),
            "mode": mode,
            "noise": noise,
            "room": room,
            "generator": generator,
            "frame_seed": FRAME_SEED_RULE,
            "camera": camera,
            "mounts": mounts,
            "labels": label_table.as_json(),
            "topseg_version": __version__,
            "created": datetime.now(UTC).isoformat(timespec="seconds"),
        }
    )


def _fixed_summary(mount) -> dict:
    """`mounts` of a dataset whose frames all come from `mount`."""
    k = mount.intrinsics
    return {
        "height_mm": [float(mount.height_mm)] * 2,
        "tilt_deg": round(mount.tilt_deg(), 6),
        "sensors": [mount.sensor],
        "resolutions": [[k.width, k.height]],
    }


def _check_format(attrs: dict, path: Path) -> None:
    tag = attrs.get("topseg_dataset")
    if not isinstance(tag, dict) or tag.get("format") != FORMAT:
        raise DatasetError(f"{path} is a Zarr store but not a topseg dataset")
    if tag.get("version") != FORMAT_VERSION:
        raise DatasetError(
            f"{path} is a topseg dataset of format version {tag.get('version')}; "
            f"this topseg reads version {FORMAT_VERSION}"
        )


def _open_group(path: Path, mode: str):
    import zarr

    if not path.exists():
        raise DatasetError(f"no dataset at {path}")
    if not (path / "zarr.json").is_file():
        raise DatasetError(f"{path} is not a Zarr v3 store (no zarr.json)")
    try:
        group = zarr.open_group(str(path), mode=mode, zarr_format=3)
        attrs = dict(group.attrs)
    except OSError as exc:
        raise dataset_os_error(exc, path, "opening") from exc
    except Exception as exc:
        raise DatasetError(f"{path}: damaged Zarr metadata ({exc})") from exc
    _check_format(attrs, path)
    return group, attrs


def _open_arrays(group, path: Path, attrs: dict) -> dict:
    n, h, w = attrs["frames"], attrs["height"], attrs["width"]
    expected = {
        "depth": ((n, h, w), np.dtype(np.uint16)),
        "labels": ((n, h, w), np.dtype(np.uint8)),
        "scene": ((n,), None),
        "complete": ((n,), np.dtype(np.uint8)),
    }
    arrays = {}
    for name, (shape, dtype) in expected.items():
        try:
            arr = group[name]
        except KeyError:
            raise DatasetError(f"{path}: the '{name}' array is missing") from None
        except Exception as exc:
            raise DatasetError(f"{path}: the '{name}' array is damaged ({exc})") from exc
        if arr.shape != shape or (dtype is not None and arr.dtype != dtype):
            raise DatasetError(
                f"{path}: '{name}' is {arr.dtype}{list(arr.shape)}, expected "
                f"{dtype or 'string'}{list(shape)}"
            )
        arrays[name] = arr
    return arrays


def _chunk_present(path: Path, name: str, array) -> np.ndarray:
    """Frame indices whose chunk file of `array` (one frame per chunk) exists."""
    sep = array.metadata.chunk_key_encoding.separator
    rest = sep.join(["0"] * (array.ndim - 1))
    if sep == ".":  # the dataset's layout: every chunk a file `c.<i>.0.0` in the array's folder
        tail = f".{rest}" if rest else ""
        present = []
        for entry in os.scandir(path / name):
            parts = entry.name.split(".", 2)
            if len(parts) >= 2 and parts[0] == "c" and parts[1].isdigit():
                if entry.name == f"c.{parts[1]}{tail}":
                    present.append(int(parts[1]))
        return np.asarray(sorted(present), np.int64)
    base = path / name / "c"  # Zarr's default `c/<i>/0/0`
    if not base.is_dir():
        return np.zeros(0, np.int64)
    found = (int(e.name) for e in os.scandir(base) if e.name.isdigit())
    return np.asarray(sorted(i for i in found if (base / str(i) / rest).is_file()), np.int64)


class DatasetWriter:
    """The client side of writing: creates or resumes a store and owns its `complete` flags.

    Holds an exclusive lock on the store directory while open, so two runs never write the
    same store. Frames themselves are written by `FrameWriter`s (one per worker process).
    """

    def __init__(self, path: Path, group, arrays: dict, attrs: dict, lock_fd: int):
        self.path = path
        self._group = group
        self._arrays = arrays
        self.attrs = attrs
        self._lock_fd = lock_fd
        self.complete = np.asarray(arrays["complete"][:], np.uint8).astype(bool)

    @classmethod
    def open(cls, path: str | os.PathLike, attrs: dict) -> DatasetWriter:
        """Create the store at `path` from `attrs` (see `make_attrs`), or resume the one there.

        A resumed store must have the same identity (seed, mode, noise, generator and its
        config, shape, camera); it may grow to more frames, never shrink.
        """
        path = Path(path).absolute()
        attrs = _canonical(attrs)
        _check_format(attrs, path)
        if path.exists() and not path.is_dir():
            raise DatasetError(f"{path} exists and is not a directory")
        if not path.parent.is_dir():
            raise DatasetError(f"the folder {path.parent} does not exist; create it first")
        fresh = not (path / "zarr.json").exists()
        if fresh and path.exists() and any(path.iterdir()):
            raise DatasetError(
                f"{path} exists, is not empty and is not a dataset; refusing to write into it"
            )
        try:
            path.mkdir(exist_ok=True)
            lock_fd = _lock(path)
        except OSError as exc:
            raise dataset_os_error(exc, path, "creating") from exc
        try:
            if fresh:
                group, arrays = _create(path, attrs)
            else:
                group, arrays, attrs = _resume(path, attrs)
        except BaseException:
            os.close(lock_fd)
            raise
        return cls(path, group, arrays, attrs, lock_fd)

    @property
    def frames(self) -> int:
        """Frames the store holds room for (N), complete or not."""
        return len(self.complete)

    def todo(self) -> np.ndarray:
        """Frame indices still to write, ascending."""
        return np.flatnonzero(~self.complete)

    def mark_complete(self, indices: Sequence[int]) -> None:
        """Set the flags of frames whose chunks are all written (call only after the writes)."""
        idx = np.asarray(indices, np.int64)
        if idx.size == 0:
            return
        self.complete[idx] = True
        arr = self._arrays["complete"]
        for c in np.unique(idx // COMPLETE_CHUNK):
            lo, hi = c * COMPLETE_CHUNK, min((c + 1) * COMPLETE_CHUNK, self.frames)
            try:
                arr[lo:hi] = self.complete[lo:hi].astype(np.uint8)
            except OSError as exc:
                raise dataset_os_error(exc, self.path, "writing") from exc

    def close(self) -> None:
        """Release the store's lock so another run may open it; safe to call twice."""
        if self._lock_fd >= 0:
            os.close(self._lock_fd)
            self._lock_fd = -1

    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _lock(path: Path) -> int:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise DatasetError(f"another process is writing {path}; wait for it to end") from None
    return fd


def _create(path: Path, attrs: dict):
    """A new store: the group with its attributes in one write, then the arrays."""
    import zarr

    n, h, w = attrs["frames"], attrs["height"], attrs["width"]
    if n < 1 or h < 1 or w < 1:
        raise DatasetError(f"a dataset needs at least one frame of positive size, got {n}x{h}x{w}")
    try:
        group = zarr.create_group(str(path), zarr_format=3, attributes=attrs)
    except OSError as exc:
        raise dataset_os_error(exc, path, "creating") from exc
    return group, _ensure_arrays(group, path, attrs)


def _ensure_arrays(group, path: Path, attrs: dict) -> dict:
    """Create the arrays a creation did not get to (`complete` comes last, so its absence
    means no frame was ever flagged), then open and check all four."""
    n, h, w = attrs["frames"], attrs["height"], attrs["width"]
    flat = {"name": "default", "separator": "."}  # c.<i>.0.0: no folder per frame to create
    images = dict(chunks=(1, h, w), compressors=_codecs(), fill_value=0, chunk_key_encoding=flat)
    specs = {
        "depth": dict(shape=(n, h, w), dtype="uint16", **images),
        "labels": dict(shape=(n, h, w), dtype="uint8", **images),
        "scene": dict(shape=(n,), chunks=(1,), dtype=str, fill_value="", chunk_key_encoding=flat),
        "complete": dict(shape=(n,), chunks=(min(n, COMPLETE_CHUNK),), dtype="uint8", fill_value=0),
    }
    if "complete" not in group:
        try:
            for name, spec in specs.items():
                if name not in group:
                    group.create_array(name, **spec)
        except OSError as exc:
            raise dataset_os_error(exc, path, "creating") from exc
    return _open_arrays(group, path, attrs)


def _resume(path: Path, attrs: dict):
    group, stored = _open_group(path, "r+")
    old, new = _identity(stored), _identity(attrs)
    grown = new.get("labels") == label_table.as_json()
    if grown and label_table.table_classes(old.get("labels")) is not None:
        new["labels"] = old["labels"]  # made before the table grew: it keeps its classes
    if old != new:
        diffs = [
            f"{k}: stored {json.dumps(old.get(k))}, asked {json.dumps(new.get(k))}"
            for k in sorted(set(old) | set(new))
            if old.get(k) != new.get(k)
        ]
        raise DatasetError(
            f"{path} holds a dataset made with other settings ({'; '.join(diffs)}); "
            "rerun with the same settings to resume it, or choose another --out"
        )
    arrays = _ensure_arrays(group, path, stored)
    frames, had = attrs["frames"], stored["frames"]
    if frames < had:
        raise DatasetError(
            f"{path} holds {had} frames and this run asks {frames}; ask at least {had} "
            "(frames can be added, not removed)"
        )
    _remove_partials(path)
    try:
        if frames > had:
            h, w = stored["height"], stored["width"]
            for arr in arrays.values():
                arr.resize((frames, h, w) if arr.ndim == 3 else (frames,))
            group.attrs["frames"] = frames
        stored = dict(group.attrs)
    except OSError as exc:
        raise dataset_os_error(exc, path, "growing") from exc
    return group, arrays, stored


def _remove_partials(path: Path) -> None:
    """Temp files of chunk writes a killed run left behind (they were never visible)."""
    for root, _dirs, files in os.walk(path):
        for name in files:
            if name.endswith(".partial"):
                os.unlink(os.path.join(root, name))


class FrameWriter:
    """Writes whole frames into an existing store; one per worker process, no flags.

    A frame is visible to readers only once the client marks it complete. Chunks are encoded
    here and written straight to their files (`topseg.core.formats.zarr_chunks`: the bytes Zarr
    would write, at a fifth of the CPU); an array whose layout that module does not know is
    written through Zarr instead. Every chunk is written, even one equal to the fill value,
    so the reader can tell a complete frame from a damaged one.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        group, attrs = _open_group(self.path, "r+")
        arrays = _open_arrays(group, self.path, attrs)
        self._arrays = {k: a.with_config({"write_empty_chunks": True}) for k, a in arrays.items()}
        self._direct = {
            k: ChunkWriter.for_array(self.path / k) for k in ("depth", "labels", "scene")
        }
        self.shape = (attrs["height"], attrs["width"])
        self.frames = attrs["frames"]
        # the classes the dataset's own table names (fewer in one made before it grew)
        self.n_classes = label_table.table_classes(attrs.get("labels")) or label_table.NUM_CLASSES

    def write(self, index: int, depth: np.ndarray, labels: np.ndarray, scene: dict) -> None:
        """Validate one frame and write its depth, labels and scene chunks."""
        if not 0 <= index < self.frames:
            raise DatasetError(f"frame index {index} outside 0..{self.frames - 1}")
        depth, labels = check_frame(depth, labels, self.shape, index, self.n_classes)
        try:
            text = json.dumps(scene, separators=(",", ":"), allow_nan=False)
        except (TypeError, ValueError) as exc:
            raise DatasetError(f"frame {index}: scene is not plain JSON ({exc})") from exc
        parts = (
            ("depth", depth, (index, 0, 0)),
            ("labels", labels, (index, 0, 0)),
            ("scene", np.array([text], dtype=object), (index,)),
        )
        try:
            for name, value, coords in parts:
                direct = self._direct[name]
                if direct is not None:
                    direct.write(coords, value)
                else:
                    self._arrays[name][index] = value[0] if name == "scene" else value
        except OSError as exc:
            raise dataset_os_error(exc, self.path, "writing") from exc


def check_frame(
    depth: np.ndarray,
    labels: np.ndarray,
    shape: tuple[int, int],
    index: int = -1,
    n_classes: int = label_table.NUM_CLASSES,
) -> tuple[np.ndarray, np.ndarray]:
    """Refuse a frame that breaks the dataset's contract (shape, dtype, label ids below
    `n_classes` or NO_DEPTH, no-depth exactly where depth is 0).

    A frame smaller than `shape` (a sensor of lower resolution) is accepted and returned padded
    top-left to `shape` with depth 0 and NO_DEPTH labels; a larger one is refused.
    """
    what = f"frame {index}" if index >= 0 else "frame"
    depth, labels = np.asarray(depth), np.asarray(labels)
    if (
        depth.ndim == 2
        and depth.shape == labels.shape
        and depth.shape != tuple(shape)
        and depth.shape[0] <= shape[0]
        and depth.shape[1] <= shape[1]
    ):
        depth, labels = pad_frame(depth, labels, shape)
    if depth.dtype != np.uint16 or depth.shape != tuple(shape):
        raise DatasetError(f"{what}: depth is {depth.dtype}{depth.shape}, expected uint16{shape}")
    if labels.dtype != np.uint8 or labels.shape != tuple(shape):
        raise DatasetError(
            f"{what}: labels are {labels.dtype}{labels.shape}, expected uint8{shape}"
        )
    invalid = (labels >= n_classes) & (labels != label_table.NO_DEPTH)
    if invalid.any():
        raise DatasetError(f"{what}: unknown label ids {np.unique(labels[invalid]).tolist()}")
    if not np.array_equal(labels == label_table.NO_DEPTH, depth == 0):
        raise DatasetError(f"{what}: labels must be NO_DEPTH exactly where depth is 0")
    return depth, labels


def pad_frame(
    depth: np.ndarray, labels: np.ndarray, shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """`depth` and `labels` top-left in frames of `shape`: depth 0, labels NO_DEPTH around."""
    h, w = depth.shape
    out_d = np.zeros(shape, depth.dtype)
    out_l = np.full(shape, label_table.NO_DEPTH, labels.dtype)
    out_d[:h, :w] = depth
    out_l[:h, :w] = labels
    return out_d, out_l


class FrameArray:
    """(N, H, W) view of the complete frames of one array; int, slice or index-list access.

    Returns numpy arrays; a chunk that fails its checksum raises `DatasetError`.
    """

    def __init__(self, array, indices: np.ndarray, path: Path, name: str):
        self._array = array
        self._indices = indices
        self._path = path
        self.name = name
        self.dtype = array.dtype
        self.shape = (len(indices), *array.shape[1:])
        self.ndim = len(self.shape)

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, key):
        rest = ()
        if isinstance(key, tuple):
            key, rest = key[0], key[1:]
        if isinstance(key, (int, np.integer)):
            k = int(key)
            if not -len(self) <= k < len(self):
                raise IndexError(f"frame {k} out of range for {len(self)} frames")
            return self._read(int(self._indices[k]))[rest]
        picked = self._indices[key]
        out = np.empty((len(picked), *self.shape[1:]), self.dtype)
        for j, i in enumerate(picked):
            out[j] = self._read(int(i))
        return out[(slice(None), *rest)]

    def _read(self, i: int) -> np.ndarray:
        try:
            return self._array[i]
        except Exception as exc:
            raise DatasetError(
                f"{self._path}: frame {i} of '{self.name}' is damaged ({exc}); "
                "delete the store and regenerate it"
            ) from exc

    def __array__(self, dtype=None, copy=None):
        out = self[:]
        return out if dtype is None else out.astype(dtype)


class Dataset:
    """A dataset opened for reading: only frames flagged complete are visible.

    `depth[k]`, `labels[k]` and `scene(k)` address the k-th complete frame; `indices[k]` is
    its frame index in the store, `complete` the store's (N,) flag mask.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path).absolute()
        group, self.attrs = _open_group(self.path, "r")
        self._arrays = _open_arrays(group, self.path, self.attrs)
        try:
            self.complete = np.asarray(self._arrays["complete"][:], np.uint8).astype(bool)
        except Exception as exc:
            raise DatasetError(f"{self.path}: the 'complete' flags are damaged ({exc})") from exc
        self.indices = np.flatnonzero(self.complete)
        for name in ("depth", "labels", "scene"):
            have = _chunk_present(self.path, name, self._arrays[name])
            missing = np.setdiff1d(self.indices, have)
            if missing.size:
                shown = ", ".join(map(str, missing[:5])) + (" ..." if missing.size > 5 else "")
                raise DatasetError(
                    f"{self.path}: {missing.size} complete frame(s) lack their '{name}' chunk "
                    f"(frames {shown}); the store is damaged"
                )
        self.depth = FrameArray(self._arrays["depth"], self.indices, self.path, "depth")
        self.labels = FrameArray(self._arrays["labels"], self.indices, self.path, "labels")

    def __len__(self) -> int:
        return len(self.indices)

    def scene(self, k: int) -> dict:
        """The scene description of the k-th complete frame."""
        i = int(self.indices[k])
        try:
            return json.loads(str(self._arrays["scene"][i]))
        except Exception as exc:
            raise DatasetError(f"{self.path}: the scene of frame {i} is damaged ({exc})") from exc

    def mount(self, k: int):
        """The camera mount (`TopViewMount`) of the k-th complete frame: its scene's "mount",
        or the dataset's `camera` for frames that record none (datasets made before)."""
        m = self.scene(k).get("mount")
        if isinstance(m, dict):
            return TopViewMount.from_dict(m, f"{self.path}: mount of frame {int(self.indices[k])}")
        return TopViewMount.from_dict(self.attrs["camera"], f"{self.path}: dataset camera")

    def frame(self, k: int) -> tuple[np.ndarray, np.ndarray, Any]:
        """(depth, labels, mount) of the k-th complete frame, cropped to its camera's size."""
        mount = self.mount(k)
        h, w = mount.intrinsics.shape
        return self.depth[k][:h, :w], self.labels[k][:h, :w], mount

    def mount_summary(self) -> dict:
        """What the frames' mounts span (the `mounts` attribute; derived from `camera` for
        datasets made before it): height_mm [lo, hi], tilt_deg, sensors, resolutions."""
        if isinstance(self.attrs.get("mounts"), dict):
            return dict(self.attrs["mounts"])
        return _fixed_summary(TopViewMount.from_dict(self.attrs["camera"], "dataset camera"))

    def __repr__(self) -> str:
        a = self.attrs
        return (
            f"Dataset({str(self.path)!r}, {len(self)}/{a['frames']} frames, "
            f"mode={a['mode']}, noise={a['noise']}, seed={a['seed']})"
        )


def open_dataset(path: str | os.PathLike) -> Dataset:
    """Open a dataset for reading; a missing, foreign or damaged store raises `DatasetError`."""
    return Dataset(path)
