"""The mount file `topseg calibrate` writes and `topseg driver --mount FILE` reads.

A small JSON document, versioned:

    {"topseg_mount": 1,
     "mount": {"intrinsics": {...}, "height_mm": ..., "pitch_deg": ..., "roll_deg": ...,
               "sensor": "..."},
     "fit": {"residual_mm": ..., "inlier_share": ..., "frames_used": ..., "made_at": "..."}}

Written atomically; read back with one `ConfigError` line for anything wrong (missing,
unreadable, not JSON, another kind of file, a newer version, a bad mount: one a camera cannot
have, `camera.check_mount`, the same validation as a mount received on the wire).
"""

from __future__ import annotations

import json
import os
from typing import Protocol

from topseg.core.atomic import atomic_write
from topseg.core.camera import TopViewMount, check_mount
from topseg.core.errors import ConfigError


class MountEstimate(Protocol):
    """A fitted mount as a mount file stores it (`calibration.MountEstimate` is one)."""

    mount: TopViewMount
    made_at: str

    def fit_dict(self) -> dict:
        """The fit's figures as a plain dict (the file's `fit` section)."""
        ...


#: the mount file format this code writes and the newest it reads
MOUNT_FILE_VERSION = 1
MAGIC = "topseg_mount"


def mount_document(estimate: MountEstimate) -> dict:
    """The mount file's content for `estimate`, as a plain dict."""
    return {
        MAGIC: MOUNT_FILE_VERSION,
        "mount": estimate.mount.to_dict(),
        "fit": estimate.fit_dict(),
    }


def write_mount_file(path: str | os.PathLike, estimate: MountEstimate) -> None:
    """Write `estimate` to `path` as a mount file, atomically (old file or whole new one)."""
    text = json.dumps(mount_document(estimate), indent=2) + "\n"
    with atomic_write(path) as f:
        f.write(text.encode())


def read_mount_document(path: str | os.PathLike) -> dict:
    """The checked JSON document of the mount file at `path` (`mount` and `fit` sections)."""
    where = f"mount file {os.fspath(path)}"
    try:
        with open(path, "rb") as f:
            data = json.loads(f.read().decode("utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{where}: no such file (make one with `topseg calibrate`)") from None
    except OSError as exc:
        raise ConfigError(f"{where}: cannot be read: {exc.strerror or exc}") from exc
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{where}: not a mount file (not JSON: {exc})") from exc
    if not isinstance(data, dict) or MAGIC not in data:
        raise ConfigError(f"{where}: not a mount file (no {MAGIC!r} key)")
    version = data[MAGIC]
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise ConfigError(f"{where}: bad {MAGIC} version {version!r}")
    if version > MOUNT_FILE_VERSION:
        raise ConfigError(
            f"{where}: version {version} is newer than this topseg reads "
            f"({MOUNT_FILE_VERSION}); upgrade topseg"
        )
    if "mount" not in data:
        raise ConfigError(f"{where}: no 'mount' section")
    fit = data.get("fit", {})
    if not isinstance(fit, dict):
        raise ConfigError(f"{where}: 'fit' must be a table")
    mount = TopViewMount.from_dict(data["mount"], source=f"{where} [mount]")
    try:
        check_mount(mount)
    except ValueError as exc:
        raise ConfigError(f"{where} [mount]: {exc}") from None
    return {"mount": mount, "fit": fit}


def read_mount_file(path: str | os.PathLike) -> TopViewMount:
    """The mount in the mount file at `path`; ConfigError (one line) on anything wrong."""
    return read_mount_document(path)["mount"]
