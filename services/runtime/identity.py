"""Who a running service is: its instance id (the Zenoh session id), pid and host.

Every driver and worker puts its instance id in its liveliness token keys
(`wire.alive_key(..., instance)`) and, as a Zenoh attachment, on the messages it publishes
(`wire.instance_attachment`), so that two processes in one role for one camera are seen as
two, not merged into one: `topseg status` lists both, the worker notices depth from two
drivers interleaving, a second driver refuses to start.
"""

from __future__ import annotations

import os
import socket
from dataclasses import dataclass
from typing import Any

from topseg.core.formats import wire

#: How long a service waits, at start, for a first peer before asking who else is there.
CONNECT_WAIT_S = 1.0
#: How long it waits for the answers (liveliness tokens, info replies).
QUERY_S = 1.0


@dataclass(frozen=True)
class Identity:
    """One process's identity: `instance` (hex Zenoh id), `pid` and `host`."""

    instance: str
    pid: int
    host: str

    @classmethod
    def of(cls, session: Any) -> Identity:
        """The identity of this process, named by its open Zenoh session."""
        return cls(str(session.info.zid()), os.getpid(), socket.gethostname())

    def describe(self) -> str:
        """'<instance> (pid P on HOST)' for log lines."""
        return f"{self.instance} (pid {self.pid} on {self.host})"

    def to_dict(self) -> dict:
        """The fields for an `info` reply."""
        return {"instance": self.instance, "pid": self.pid, "host": self.host}


def other_instances(session: Any, key: str, me: str, timeout: float = QUERY_S) -> set[str]:
    """The instance ids, other than `me`, holding a liveliness token under `key`/* now."""
    found = set()
    for reply in session.liveliness().get(f"{key}/*", timeout=timeout):
        if reply.ok is None:
            continue
        try:
            parts = wire.parse_key(str(reply.ok.key_expr))
        except wire.WireError:
            continue
        if parts.instance is not None and parts.instance != me:
            found.add(parts.instance)
    return found
