"""Run a sensor library in a child process and read its frames through a pipe.

libfreenect (fakenect segfaults or blocks for ever after its last frame) and OpenNI2
(segfaults when it unloads) cannot be trusted inside the driver process, and a call that
blocks in C cannot be interrupted. So their drivers read the sensor in a child
(`python -m topseg.drivers.<name> ...`) that writes frames to its stdout; the parent reads
them under a timeout and kills the child when it stalls, crashes or is closed.

Protocol, child -> parent on the child's original stdout (its fd 1 is pointed at stderr so
that C libraries printing to stdout cannot corrupt it):
  one JSON line: {"intrinsics": {...}, "fps": F, "description": D}  or  {"error": msg,
  "retry": bool}; then per frame: FRAME_HEADER (magic, stamp_ns, width, height) and
  width*height little-endian uint16 millimetres.
"""

from __future__ import annotations

import collections
import json
import logging
import os
import select
import signal
import struct
import subprocess
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from topseg.core.camera import Intrinsics
from topseg.core.formats.wire import MAX_SIDE, DepthFrame, WireError
from topseg.drivers.base import Source, SourceError, SourceFrame, SourceOptions, SourceUnavailable

log = logging.getLogger(__name__)

FRAME_HEADER = struct.Struct("<4sQII")
MAGIC = b"TSF1"
_MAX_LINE = 64 * 1024


class ChildSource(Source):
    """A Source whose frames come from a child process speaking the protocol above."""

    def __init__(self, argv: list[str], description: str, options: SourceOptions) -> None:
        self.description = description
        self.options = options
        self._seq = 0
        self._stderr: collections.deque[str] = collections.deque(maxlen=20)
        try:
            self._proc = subprocess.Popen(
                argv,
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                start_new_session=True,  # a Ctrl-C meant for the driver does not hit the child
            )
        except OSError as exc:
            raise SourceError(f"cannot start the {description} reader: {exc}") from exc
        self._fd = self._proc.stdout.fileno()
        self._buf = bytearray()
        threading.Thread(target=self._drain_stderr, daemon=True).start()
        try:
            header = self._read_header()
        except BaseException:
            self.close()
            raise
        try:
            self.intrinsics = Intrinsics.from_dict(header["intrinsics"])
            self.nominal_fps = header.get("fps")
            self.description = header.get("description", description)
        except (KeyError, TypeError, ValueError) as exc:
            self.close()
            raise SourceError(f"{description} reader sent a bad header: {exc}") from exc

    # -- reading

    def _drain_stderr(self) -> None:
        for line in self._proc.stderr:
            text = line.decode(errors="replace").rstrip()
            if text:
                self._stderr.append(text)
                log.debug("%s: %s", self.description, text)

    def _exited(self) -> SourceUnavailable:
        try:
            rc = self._proc.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            rc = None
        time.sleep(0.05)  # let the stderr thread catch the last lines
        tail = " | ".join(list(self._stderr)[-3:])
        how = f"signal {-rc}" if rc is not None and rc < 0 else f"status {rc}"
        return SourceUnavailable(
            f"{self.description} reader exited ({how}){': ' + tail if tail else ''}"
        )

    def _fill(self, n: int, deadline: float) -> None:
        """Read until the buffer holds n bytes, or raise on timeout / end of stream."""
        while len(self._buf) < n:
            left = deadline - time.monotonic()
            if left <= 0:
                self._kill()
                raise SourceUnavailable(f"{self.description}: no data for {self._waited:.1f} s")
            ready, _, _ = select.select([self._fd], [], [], left)
            if not ready:
                continue
            chunk = os.read(self._fd, max(n - len(self._buf), 1 << 16))
            if not chunk:
                raise self._exited()
            self._buf += chunk

    def _take(self, n: int, timeout: float) -> bytes:
        self._waited = timeout
        self._fill(n, time.monotonic() + timeout)
        out = bytes(self._buf[:n])
        del self._buf[:n]
        return out

    def _read_header(self) -> dict:
        self._waited = self.options.open_timeout_s
        deadline = time.monotonic() + self.options.open_timeout_s
        while b"\n" not in self._buf:
            if len(self._buf) > _MAX_LINE:
                raise SourceError(f"{self.description} reader sent no header line")
            self._fill(len(self._buf) + 1, deadline)
        line, _, rest = bytes(self._buf).partition(b"\n")
        self._buf = bytearray(rest)
        try:
            header = json.loads(line)
        except ValueError as exc:
            raise SourceError(f"{self.description} reader sent a bad header: {exc}") from exc
        if "error" in header:
            cls = SourceUnavailable if header.get("retry") else SourceError
            raise cls(str(header["error"]))
        return header

    def frames(self) -> Iterator[SourceFrame]:
        """Frames as the child sends them; SourceUnavailable when it stalls or exits."""
        while True:
            magic, stamp_ns, width, height = FRAME_HEADER.unpack(
                self._take(FRAME_HEADER.size, self.options.frame_timeout_s)
            )
            if magic != MAGIC or not (0 < width <= MAX_SIDE and 0 < height <= MAX_SIDE):
                self._kill()
                raise SourceError(f"{self.description} reader broke the frame protocol")
            data = self._take(width * height * 2, self.options.frame_timeout_s)
            depth = np.frombuffer(data, "<u2").reshape(height, width).astype(np.uint16, copy=False)
            k = self.intrinsics
            if k is None or k.shape != depth.shape:
                raise SourceError(f"{self.description}: frame {width}x{height} does not match {k}")
            try:
                frame = DepthFrame(depth, k, self._seq, stamp_ns, "")
            except WireError as exc:
                raise SourceError(f"{self.description}: {exc}") from exc
            self._seq += 1
            yield SourceFrame(frame)

    # -- closing

    def _kill(self) -> None:
        if self._proc.poll() is None:
            self._proc.kill()
            self._proc.wait()

    def close(self) -> None:
        """SIGTERM the child so it closes its device, kill it after 1.5 s; safe to call twice."""
        proc = getattr(self, "_proc", None)
        if proc is None:
            return
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)  # the child closes its device, then exits
            try:
                proc.wait(timeout=1.5)
            except subprocess.TimeoutExpired:
                self._kill()
        proc.stdout.close()


# ---------------------------------------------------------------------------- child side


def child_argv(module: str, *args: str) -> list[str]:
    """The command line that runs `module` as a reader child under this same interpreter."""
    return [sys.executable, "-m", module, *args]


def _die_with_parent() -> None:
    """Ask Linux to SIGTERM this process when the parent dies (no orphaned readers)."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def serve(produce: Callable[[], Iterator[Any]]) -> None:
    """Child main loop. `produce()` is a generator: first a header dict (see the module
    docstring), then (stamp_ns, uint16 array) frames; its `finally` releases the device.
    Raising SourceError before the header reports it to the parent. Never returns.
    """
    out = os.fdopen(os.dup(1), "wb", buffering=0)
    os.dup2(2, 1)
    parent = os.getppid()
    _die_with_parent()
    stopping = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stopping.set())
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    code = 0
    gen = produce()
    try:
        try:
            header = next(gen)
        except SourceError as exc:
            retry = isinstance(exc, SourceUnavailable)
            out.write((json.dumps({"error": str(exc), "retry": retry}) + "\n").encode())
            code = 3
            return
        out.write((json.dumps(header) + "\n").encode())
        for stamp_ns, depth in gen:
            if stopping.is_set() or os.getppid() != parent:
                break
            h, w = depth.shape
            out.write(FRAME_HEADER.pack(MAGIC, stamp_ns, w, h))
            out.write(np.ascontiguousarray(depth, "<u2").tobytes())
    except BrokenPipeError:
        pass
    except SourceError as exc:
        print(f"error: {exc}", file=sys.stderr, flush=True)
        code = 3
    except Exception:
        traceback.print_exc()
        code = 4
    finally:
        try:
            gen.close()
        finally:
            sys.stderr.flush()
            os._exit(code)  # skip native libraries' exit handlers (OpenNI2 crashes in them)
