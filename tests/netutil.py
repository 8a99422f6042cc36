"""Helpers for tests that run services on loopback Zenoh (not a test module)."""

import socket
import time


def free_port() -> int:
    """A loopback TCP port nobody listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(predicate, timeout=20.0, what="condition"):
    """Poll `predicate` until true; fail the test naming `what` after `timeout` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what}")


class Service:
    """A `topseg` command as a subprocess; a thread keeps its stderr lines with arrival times.

    `wait_line` waits for a log line (e.g. "worker ready") and says when it came, so tests
    can time what follows it; `stop` sends a signal and reaps; `kill` is kill -9.
    """

    def __init__(self, *args, env=None, preexec_fn=None):
        import subprocess
        import sys
        import threading

        cmd = [sys.executable, "-m", "topseg.services.cli", "-v", *map(str, args)]
        self.proc = subprocess.Popen(
            cmd,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
            preexec_fn=preexec_fn,
        )
        self.lines: list[tuple[float, str]] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self):
        for line in self.proc.stderr:
            self.lines.append((time.monotonic(), line.rstrip("\n")))

    @property
    def err(self) -> str:
        return "\n".join(line for _, line in self.lines)

    def wait_line(self, text, timeout=60.0, after=0.0) -> float:
        """Monotonic time of the first stderr line containing `text` that came after `after`."""

        def seen():
            return next((t for t, line in list(self.lines) if t > after and text in line), None)

        try:
            wait_for(lambda: seen() is not None or self.proc.poll() is not None, timeout, text)
        except AssertionError:
            raise AssertionError(f"no {text!r} line in {timeout} s; stderr:\n{self.err}") from None
        if seen() is None:
            self._reader.join(5)
            if seen() is None:
                raise AssertionError(f"exited {self.proc.returncode} before {text!r}:\n{self.err}")
        return seen()

    def alive(self) -> bool:
        return self.proc.poll() is None

    def rss_mb(self) -> float:
        """Resident memory of the process now (Linux /proc)."""
        with open(f"/proc/{self.proc.pid}/status") as f:
            kb = next(int(line.split()[1]) for line in f if line.startswith("VmRSS:"))
        return kb / 1024

    def stop(self, sig=None, timeout=20.0) -> int:
        """Send `sig` (SIGTERM), wait for the exit; kill -9 and fail if it does not come."""
        import signal
        import subprocess

        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM if sig is None else sig)
        try:
            rc = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.kill()
            raise AssertionError(f"{self.proc.args[4]} did not stop:\n{self.err}") from None
        self._reader.join(5)
        return rc

    def kill(self) -> None:
        """kill -9, then reap."""
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()
        self._reader.join(5)


class Services:
    """Every Service and Tap a test starts; `close()` kills the services still running and
    closes the taps (pass or fail)."""

    def __init__(self):
        self.made: list[Service] = []
        self.taps: list[Tap] = []

    def __call__(self, *args, **kwargs) -> Service:
        self.made.append(Service(*args, **kwargs))
        return self.made[-1]

    def tap(self, port, cell, camera="cam0") -> "Tap":
        self.taps.append(Tap(port, cell, camera))
        return self.taps[-1]

    def close(self):
        for s in self.made:
            s.kill()
        for t in self.taps:
            t.close()


class Tap:
    """The test's Zenoh session on one camera: keeps (arrival time, header) of its depth and
    labels (seq, stamp_ns; no pixels, so long runs stay small), its stats, and can ask the
    driver's `info` or publish on the depth key itself."""

    def __init__(self, port, cell, camera="cam0"):
        import zenoh

        from topseg.core.formats import wire
        from topseg.services.runtime.zenoh_session import open_session

        self.cell, self.camera = cell, camera
        self.session = open_session(port=port)
        self.depth: list[tuple[float, int, int]] = []  # (monotonic, seq, stamp_ns)
        self.labels: list[tuple[float, int, int, int]] = []  # (monotonic, seq, stamp, now_ns)
        self.stats: list[dict] = []
        self._pub = None
        sub = self.session.declare_subscriber
        sub(wire.depth_key(cell, camera), lambda s: self.depth.append(self._head(s, "depth")))
        sub(wire.labels_key(cell, camera), lambda s: self.labels.append(self._head(s, "labels")))
        sub(
            wire.stats_key(cell, camera),
            lambda s: self.stats.append(wire.decode_stats(s.payload.to_bytes())),
        )
        self._zenoh = zenoh

    @staticmethod
    def _head(sample, kind):
        import msgpack

        msg = msgpack.unpackb(sample.payload.to_bytes(), raw=False)
        now = time.monotonic()
        if kind == "depth":
            return now, msg["seq"], msg["stamp_ns"]
        return now, msg["seq"], msg["stamp_ns"], time.time_ns()

    def labels_after(self, t0: float) -> list:
        return [x for x in list(self.labels) if x[0] > t0]

    def info(self) -> dict:
        import json

        from topseg.core.formats import wire

        replies = self.session.get(wire.info_key(self.cell, self.camera), timeout=5.0)
        got = [json.loads(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]
        assert len(got) == 1, f"{len(got)} info replies"
        return got[0]

    def publish(self, payload: bytes) -> None:
        """Put raw bytes on the camera's depth key (BLOCK: nothing is dropped on the way)."""
        from topseg.core.formats import wire

        if self._pub is None:
            self._pub = self.session.declare_publisher(
                wire.depth_key(self.cell, self.camera),
                congestion_control=self._zenoh.CongestionControl.BLOCK,
            )
        self._pub.put(payload)

    @property
    def matched(self) -> bool:
        return self._pub is not None and self._pub.matching_status.matching

    def close(self):
        self.session.close()
