"""Atomic file writes: a reader sees the old file or the whole new one, never a part.

The data goes to a temporary file beside the target, is flushed and fsynced, gets the
permissions an ordinary `open()` would give (mode 0666 less the umask; `mkstemp` alone
would leave 0600 and lock a service user out of a model written by root), and is renamed
over the target. On any error the temporary file is removed and the old file stays.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import BinaryIO


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextmanager
def atomic_write(path: str | os.PathLike) -> Iterator[BinaryIO]:
    """`with atomic_write(path) as f: f.write(...)`: binary file replaced on success only."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_all(files: dict[Path, bytes]) -> None:
    """Write several files all or none: each to a temporary beside it (fsynced), then the
    renames; on any error every temporary and every file already renamed is removed. An
    OSError names the target it was writing (`filename`), not a temporary."""
    done: list[Path] = []
    tmps: list[tuple[str, Path]] = []
    target = next(iter(files), Path("."))
    try:
        for target, data in files.items():
            fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
            tmps.append((tmp, target))
            with os.fdopen(fd, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
            os.chmod(tmp, 0o666 & ~_umask())
        for tmp, target in tmps:
            os.replace(tmp, target)
            done.append(target)
    except BaseException as exc:
        for path in [*(Path(t) for t, _ in tmps), *done]:
            with suppress(OSError):
                path.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise OSError(exc.errno, exc.strerror or str(exc), str(target)) from exc
        raise
