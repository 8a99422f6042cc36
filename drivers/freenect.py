"""Kinect v1 through libfreenect: `freenect[:index]`.

The PyPI `freenect` wrapper runs in a child process (see `child.py`): libfreenect's sync
API blocks in C, and its `fakenect` replay library blocks or crashes after a dump's last
frame. The child asks for raw 11-bit disparity (`DEPTH_11BIT`, the one mode every
libfreenect and fakenect serves), converts it to millimetres with topseg's own copy of
libfreenect's table (`fakenect_dump.RAW_TO_MM`) and pipes the frames up.

Debian's libfreenect 0.5.3 leaves `freenect_camera_to_world` undefined, so the wrapper
imports only with lazy symbol binding (`sys.setdlopenflags(os.RTLD_LAZY)`).

To test without a Kinect, point `LD_LIBRARY_PATH` at libfreenect's fakenect library
(`/usr/lib/x86_64-linux-gnu/fakenect`) and `FAKENECT_PATH` at a dump
(`fakenect_dump.write_dump`); the child inherits both.
"""

from __future__ import annotations

import os
import sys
import time

from topseg.core.camera import KINECT_V1
from topseg.core.extras import import_failure
from topseg.drivers.base import SourceError, SourceOptions, SourceUnavailable, Throttle
from topseg.drivers.child import ChildSource, child_argv, serve
from topseg.drivers.fakenect_dump import raw_to_mm

FAKENECT_LIBRARY_DIR = "/usr/lib/x86_64-linux-gnu/fakenect"


def parse_index(arg: str | None) -> int:
    """The Kinect index of `freenect[:index]` (0 when none is given), or SourceError."""
    try:
        index = int(arg) if arg else 0
    except ValueError:
        raise SourceError(f"freenect takes a device index (freenect:0), got {arg!r}") from None
    if index < 0:
        raise SourceError(f"freenect device index must be >= 0, got {index}")
    return index


def open(arg: str | None, options: SourceOptions) -> ChildSource:
    """`freenect[:index]` -> a ChildSource whose child reads that Kinect through libfreenect."""
    index = parse_index(arg)
    fps = "" if options.fps is None else str(options.fps)
    argv = child_argv("topseg.drivers.freenect", str(index), fps)
    return ChildSource(argv, f"freenect:{index}", options)


def _produce(index: int, fps: float | None):
    """Child side: header, then (stamp_ns, mm) frames from libfreenect."""
    sys.setdlopenflags(os.RTLD_LAZY)
    try:
        import freenect
    except ImportError as exc:
        line = import_failure("freenect", "freenect", "kinect", exc)
        raise SourceError(f"{line}; its wheel builds against libfreenect-dev") from exc

    got = freenect.sync_get_depth(index, freenect.DEPTH_11BIT)
    if got is None:
        raise SourceUnavailable(
            f"no Kinect v1 at index {index} (libfreenect cannot open it; run `topseg devices`)"
        )
    yield {
        "intrinsics": KINECT_V1.to_dict(),
        "fps": fps or 30.0,
        "description": f"freenect:{index}",
    }
    throttle = Throttle(fps)
    try:
        while True:
            raw, _device_ts = got
            stamp_ns = time.time_ns()
            if throttle.admit():
                yield stamp_ns, raw_to_mm(raw)
            got = freenect.sync_get_depth(index, freenect.DEPTH_11BIT)
            if got is None:
                raise SourceUnavailable(f"Kinect {index} stopped delivering depth")
    finally:
        freenect.sync_stop()


if __name__ == "__main__":
    serve(lambda: _produce(int(sys.argv[1]), float(sys.argv[2]) if sys.argv[2] else None))
