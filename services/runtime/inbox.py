"""The bounded hand-over from Zenoh's threads to a service's main loop.

A subscriber callback runs on one of Zenoh's threads and must never block it: `Inbox.on_sample`
copies the key and the payload and queues them; when the queue is full the message is
dropped and counted (`dropped`), so a slow consumer costs messages, never memory. The main
loop takes them with `get` (None on a timeout or a `wake`), and after its subscribers are
gone, what is left with `drain`. The recorder, the viewer and the ROS 2 bridge read their
messages through one.
"""

from __future__ import annotations

import contextlib
import queue
import threading
import time
from collections.abc import Iterator


class Inbox:
    """At most `maxsize` messages `(key, payload)` waiting, or `(key, payload, receive time
    in ns)` with `stamp`; newer ones are dropped and counted while it is full."""

    def __init__(self, maxsize: int, stamp: bool = False) -> None:
        if maxsize <= 0:
            raise ValueError(f"an inbox holds at least one message, got {maxsize}")
        self._queue: queue.Queue = queue.Queue(maxsize)
        self._stamp = stamp
        self._lock = threading.Lock()
        self.dropped = 0

    def on_sample(self, sample) -> None:
        """A Zenoh subscriber's callback: copy the message and queue it, never block."""
        item = (str(sample.key_expr), sample.payload.to_bytes())
        if self._stamp:
            item = (*item, time.time_ns())
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            with self._lock:  # several Zenoh threads may drop at once
                self.dropped += 1

    def wake(self) -> None:
        """End a `get` that is waiting (a stopping signal's handler); when the inbox is
        full the loop finds its stop flag at its next message instead."""
        with contextlib.suppress(queue.Full):
            self._queue.put_nowait(None)

    def get(self, timeout: float) -> tuple | None:
        """The oldest message, waiting up to `timeout` s; None on a timeout or a wake."""
        try:
            return self._queue.get(timeout=max(timeout, 0.0))
        except queue.Empty:
            return None

    def drain(self) -> Iterator[tuple]:
        """The messages still queued, oldest first, without waiting."""
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                return
            if item is not None:
                yield item
