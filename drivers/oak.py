"""Luxonis OAK-D stereo depth through depthai 3: `oak[:device-id]`.

On the device: the two mono cameras (CAM_B, CAM_C) feed StereoDepth, whose depth (uint16
mm) is aligned to the colour camera (CAM_A) at 640x400 unless asked otherwise; intrinsics
come from the device's calibration for CAM_A at that size. On the host, `OakSource` reads
an output queue of RAW16 `ImgFrame`s under a timeout, checks each frame and hands it on;
that host half runs for real in the tests on a host-only pipeline (`dai.Pipeline(False)`).

depthai's telemetry is switched off (`DEPTHAI_TELEMETRY=0`) before it is imported.
"""

from __future__ import annotations

import datetime
import os
import time
from collections.abc import Iterator
from typing import Any

import numpy as np

from topseg.core.camera import Intrinsics
from topseg.core.extras import import_failure
from topseg.core.formats.wire import MAX_SIDE, DepthFrame, WireError
from topseg.drivers.base import (
    Source,
    SourceError,
    SourceFrame,
    SourceOptions,
    SourceUnavailable,
    Throttle,
)

DEFAULT_SIZE = (640, 400)


def import_depthai() -> Any:
    """depthai, with its telemetry off."""
    os.environ["DEPTHAI_TELEMETRY"] = "0"
    try:
        import depthai
    except ImportError as exc:
        raise SourceError(import_failure("oak", "depthai", "oak", exc)) from exc
    return depthai


class OakSource(Source):
    """Depth frames from a running depthai pipeline's output queue of RAW16 frames.

    `pipeline` is started here and stopped by `close()`; `intrinsics` must match the
    frames' size.
    """

    def __init__(
        self,
        pipeline: Any,
        queue: Any,
        intrinsics: Intrinsics,
        options: SourceOptions,
        description: str = "oak",
        fps: float | None = None,
    ) -> None:
        self.dai = import_depthai()
        self.pipeline = pipeline
        self.queue = queue
        self.intrinsics = intrinsics
        self.options = options
        self.description = description
        self.nominal_fps = fps
        self._seq = 0
        self._closed = False
        try:
            pipeline.start()
        except RuntimeError as exc:
            raise SourceUnavailable(f"{description}: cannot start the pipeline: {exc}") from exc

    def _depth_of(self, msg: Any) -> np.ndarray:
        dai = self.dai
        if not isinstance(msg, dai.ImgFrame):
            raise SourceError(f"{self.description}: expected ImgFrame, got {type(msg).__name__}")
        if msg.getType() != dai.ImgFrame.Type.RAW16:
            raise SourceError(f"{self.description}: frame type {msg.getType()}, expected RAW16")
        w, h = msg.getWidth(), msg.getHeight()
        if not (0 < w <= MAX_SIDE and 0 < h <= MAX_SIDE) or (h, w) != self.intrinsics.shape:
            raise SourceError(
                f"{self.description}: frame is {w}x{h}, the camera is "
                f"{self.intrinsics.width}x{self.intrinsics.height}"
            )
        data = np.asarray(msg.getData(), dtype=np.uint8)
        if data.size != w * h * 2:
            raise SourceError(
                f"{self.description}: RAW16 frame holds {data.size} bytes, not {w * h * 2}"
            )
        return data.view("<u2").reshape(h, w).astype(np.uint16)

    def frames(self) -> Iterator[SourceFrame]:
        """Checked RAW16 frames, at most `options.fps` a second; SourceUnavailable on a stall."""
        timeout = datetime.timedelta(seconds=self.options.frame_timeout_s)
        throttle = Throttle(self.options.fps)
        while True:
            if not self.pipeline.isRunning():
                raise SourceUnavailable(f"{self.description}: the pipeline stopped")
            try:
                msg = self.queue.get(timeout=timeout)
            except RuntimeError as exc:  # the device went away
                raise SourceUnavailable(f"{self.description}: {exc}") from exc
            if msg is None:
                raise SourceUnavailable(
                    f"{self.description}: no frame for {self.options.frame_timeout_s:.1f} s"
                )
            stamp_ns = time.time_ns()
            if not throttle.admit():
                continue
            try:
                frame = DepthFrame(self._depth_of(msg), self.intrinsics, self._seq, stamp_ns, "")
            except WireError as exc:
                raise SourceError(f"{self.description}: {exc}") from exc
            self._seq += 1
            yield SourceFrame(frame)

    def close(self) -> None:
        """Stop the pipeline and wait for it (frees the device); safe to call twice."""
        if self._closed:
            return
        self._closed = True
        try:
            self.pipeline.stop()
            self.pipeline.wait()
        except RuntimeError:
            pass


def calibrated_intrinsics(device: Any, socket: Any, width: int, height: int) -> Intrinsics:
    """CAM intrinsics at a resolution from the device's calibration."""
    m = device.readCalibration().getCameraIntrinsics(socket, width, height)
    return Intrinsics(width, height, float(m[0][0]), float(m[1][1]), float(m[0][2]), float(m[1][2]))


def open(
    arg: str | None, options: SourceOptions, size: tuple[int, int] = DEFAULT_SIZE
) -> OakSource:
    """Build and start the on-device StereoDepth pipeline of the OAK `arg` (or the first)."""
    dai = import_depthai()
    name = f"oak:{arg}" if arg else "oak"
    try:
        device = dai.Device(dai.DeviceInfo(arg)) if arg else dai.Device()
    except RuntimeError as exc:
        raise SourceUnavailable(f"cannot open {name}: {exc} (see `topseg devices`)") from exc
    fps = options.fps or 30.0
    pipeline = dai.Pipeline(device)
    left = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_B)
    right = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_C)
    stereo = pipeline.create(dai.node.StereoDepth).build(
        left.requestOutput(size, fps=fps), right.requestOutput(size, fps=fps)
    )
    stereo.setDepthAlign(dai.CameraBoardSocket.CAM_A)
    stereo.setOutputSize(*size)
    queue = stereo.depth.createOutputQueue(maxSize=4, blocking=False)
    k = calibrated_intrinsics(device, dai.CameraBoardSocket.CAM_A, *size)
    return OakSource(pipeline, queue, k, options, name, fps)
