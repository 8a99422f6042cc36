"""OpenNI2 depth cameras: `openni2[:uri]` (Asus Xtion, PrimeSense, Orbbec; `openni2:Dummy` is
OpenNI2's built-in test device).

The PyPI `openni` wrapper loads Debian's libOpenNI2 (`OPENNI2_REDIST` names another
folder). OpenNI2 crashes when it unloads, so it runs in a child process (see `child.py`)
that stops the stream, closes the device and leaves without running exit handlers.
Depth in 1 mm or 100 um units is delivered as millimetres; intrinsics come from the
stream's field of view, or Kinect-like optics scaled to the frame when the device does not
report one (the Dummy device).
"""

from __future__ import annotations

import math
import os
import sys
import time

import numpy as np

from topseg.core.camera import KINECT_V1, Intrinsics
from topseg.core.extras import import_failure
from topseg.drivers.base import SourceError, SourceOptions, SourceUnavailable, Throttle
from topseg.drivers.child import ChildSource, child_argv, serve

DEFAULT_REDIST = "/usr/lib/x86_64-linux-gnu"


def open(arg: str | None, options: SourceOptions) -> ChildSource:
    """`openni2[:uri]` -> a ChildSource whose child reads that device (the first when no uri)."""
    fps = "" if options.fps is None else str(options.fps)
    wait_ms = str(int(1000 * options.frame_timeout_s))
    argv = child_argv("topseg.drivers.openni2", arg or "", fps, wait_ms)
    return ChildSource(argv, f"openni2:{arg}" if arg else "openni2", options)


def intrinsics_from_fov(
    width: int, height: int, hfov: float | None, vfov: float | None
) -> Intrinsics:
    """Pinhole intrinsics from fields of view in radians (None: Kinect v1 optics, rescaled)."""
    if not hfov or not vfov:
        return KINECT_V1.scaled_to(width, height)
    fx = width / 2 / math.tan(hfov / 2)
    fy = height / 2 / math.tan(vfov / 2)
    return Intrinsics(width, height, fx, fy, (width - 1) / 2, (height - 1) / 2)


def _produce(uri: str, fps: float | None, wait_ms: int):
    """Child side: header, then (stamp_ns, mm) frames from one OpenNI2 depth stream."""
    try:
        from openni import openni2
        from openni.utils import OpenNIError
    except ImportError as exc:
        raise SourceError(import_failure("openni2", "openni", "openni2", exc)) from exc
    redist = os.environ.get("OPENNI2_REDIST", DEFAULT_REDIST)
    try:
        openni2.initialize(redist)
    except (OpenNIError, OSError) as exc:
        raise SourceError(
            f"cannot load OpenNI2 from {redist} ({exc}); apt install libopenni2-0"
        ) from exc
    name = f"openni2:{uri}" if uri else "openni2"
    try:
        dev = openni2.Device(uri.encode()) if uri else openni2.Device.open_any()
        stream = dev.create_depth_stream()
        mode = stream.get_video_mode()
        stream.start()
    except OpenNIError as exc:
        raise SourceUnavailable(f"cannot open {name}: {exc}") from exc
    fmt = mode.pixelFormat
    if fmt == openni2.PIXEL_FORMAT_DEPTH_1_MM:
        scale = None
    elif fmt == openni2.PIXEL_FORMAT_DEPTH_100_UM:
        scale = 0.1
    else:
        raise SourceError(f"{name} streams {fmt}, not depth in mm or 100 um")
    try:
        hfov, vfov = stream.get_horizontal_fov(), stream.get_vertical_fov()
    except OpenNIError:
        hfov = vfov = None
    k = intrinsics_from_fov(mode.resolutionX, mode.resolutionY, hfov, vfov)
    try:
        yield {"intrinsics": k.to_dict(), "fps": fps or float(mode.fps), "description": name}
        throttle = Throttle(fps)
        while True:
            if openni2.wait_for_any_stream([stream], wait_ms / 1000.0) is None:
                raise SourceUnavailable(f"{name}: no frame for {wait_ms} ms")
            frame = stream.read_frame()
            stamp_ns = time.time_ns()
            if not throttle.admit():
                continue
            depth = np.frombuffer(frame.get_buffer_as_uint16(), np.uint16)
            depth = depth.reshape(frame.height, frame.width)
            if scale is not None:
                depth = np.round(depth * scale).astype(np.uint16)
            yield stamp_ns, depth
    finally:
        stream.stop()
        dev.close()


if __name__ == "__main__":
    serve(
        lambda: _produce(sys.argv[1], float(sys.argv[2]) if sys.argv[2] else None, int(sys.argv[3]))
    )
