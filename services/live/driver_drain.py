"""The end of a finite replay: the driver waits for its last frame's labels before it leaves.

Closing a Zenoh session drops what its queues still hold for slower links: a lossless replay
(`--congestion block`, what `--as-fast-as-possible` and the lossless pipeline use) lost the
last frame of 8 to its worker under load while another subscriber had it (docs/reliability.md,
12e). So a
driver in block mode follows the labels of its camera (`LabelsSeen`) and, when its source
ends, keeps its session open until a worker has labelled the last frame it sent, for as long
as labels keep coming (`--drain-idle` seconds at most between two). It does not wait when no
worker serves the camera (a recorder alone), nor in drop mode, where frames may be dropped
by design.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from topseg.core.formats import wire

log = logging.getLogger("topseg.driver")

#: seconds the driver waits, at most, for a worker's liveliness token to answer
WORKER_QUERY_S = 1.0


class LabelsSeen:
    """The highest label seq published for one camera since the driver started."""

    def __init__(self, session, cell: str, camera: str) -> None:
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self.highest = -1
        self.last_s: float | None = None  # monotonic time of the last labels message
        self.rejected = 0
        self._session, self._cell, self._camera = session, cell, camera
        self._sub = session.declare_subscriber(wire.labels_key(cell, camera), self._on_labels)

    def _on_labels(self, sample) -> None:
        try:
            seq = wire.decode_labels(sample.payload.to_bytes()).seq
        except wire.WireError:
            with self._lock:
                self.rejected += 1
            return
        with self._changed:
            self.highest = max(self.highest, seq)
            self.last_s = time.monotonic()
            self._changed.notify_all()

    def worker_serves(self) -> bool:
        """Whether a worker holds a liveliness token for this camera (or for every camera)."""
        keys = (
            f"{wire.alive_key(self._cell, self._camera, 'worker')}/**",
            f"{wire.ROOT}/{wire.ANY}/{wire.ANY}/alive/worker/**",
        )
        for key in keys:
            for reply in self._session.liveliness().get(key, timeout=WORKER_QUERY_S):
                if reply.ok is not None:
                    return True
        return False

    def wait_for(self, last_seq: int, idle_s: float, stopping: Callable[[], bool]) -> bool:
        """Wait until labels for `last_seq` (or later) came; False when none came for
        `idle_s` seconds or `stopping()` says so."""
        start = time.monotonic()
        with self._changed:
            while self.highest < last_seq:
                if stopping():
                    return False
                quiet_since = start if self.last_s is None else max(start, self.last_s)
                if time.monotonic() - quiet_since >= idle_s:
                    return False
                self._changed.wait(0.1)
        return True

    def close(self) -> None:
        """Stop following the labels."""
        self._sub.undeclare()


def drain(seen: LabelsSeen, last_seq: int, idle_s: float, stopping: Callable[[], bool]) -> None:
    """After a finite source's last frame (`last_seq`): wait for its labels when a worker
    serves the camera, logging what happened."""
    if last_seq < 0 or not seen.worker_serves():
        return
    t0 = time.monotonic()
    if seen.wait_for(last_seq, idle_s, stopping):
        log.info(
            "frame %d labelled; %.1f s after the source ended", last_seq, time.monotonic() - t0
        )
    elif not stopping():
        log.warning(
            "no labels for frame %d after %.0f s without progress (highest labelled: %d); leaving",
            last_seq,
            idle_s,
            seen.highest,
        )
