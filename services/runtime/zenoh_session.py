"""Open the Zenoh session every topseg service uses, from topseg's default or a config file.

Default (no `--zenoh-config`): peer mode on loopback, multicast scouting off, and a
rendezvous port (`--zenoh-port`, `$TOPSEG_ZENOH_PORT`, else 7447). Every process

- listens on `tcp/127.0.0.1:<port>` if that port is free (the first one to start gets it),
  and on an ephemeral loopback port in any case;
- connects to `tcp/127.0.0.1:<port>`, retrying in the background while nobody holds it
  (every second at most: a restarted port holder is reached within about a second);
- learns the other peers' ephemeral endpoints by gossip scouting and connects to them.

So separate processes on one host find each other without multicast, in any start order,
and keep working when the process holding the port exits: the others stay connected to
each other, and the next process to start takes the port over (checked with eclipse-zenoh
1.10: four processes, the port holder killed, a newcomer reaches the rest). A zenohd or a
topseg process in router mode on that port serves the same purpose. Other hosts, TLS or
access control: pass a full Zenoh JSON5 config with `--zenoh-config` (see `deploy/`).

Key expressions live in `topseg.core.formats.wire` (`depth_key`, `labels_key`, ... `alive_key`).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import socket
import threading
import time
from typing import Any

import psutil
import zenoh

from topseg.core.errors import TopsegError

DEFAULT_PORT = 7447
PORT_ENV = "TOPSEG_ZENOH_PORT"
CONFIG_ENV = "TOPSEG_ZENOH_CONFIG"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The Zenoh options every service takes."""
    group = parser.add_argument_group("zenoh")
    group.add_argument(
        "--zenoh-config",
        metavar="FILE",
        default=os.environ.get(CONFIG_ENV),
        help=f"a Zenoh JSON5 config file used as is (default ${CONFIG_ENV}; "
        "otherwise peers on loopback, see the rendezvous port)",
    )
    group.add_argument(
        "--zenoh-port",
        type=int,
        metavar="PORT",
        default=None,
        help=f"loopback rendezvous port of the default config (default ${PORT_ENV} or {DEFAULT_PORT})",
    )


def rendezvous_port(port: int | None = None) -> int:
    """The port from the argument, else the environment, else 7447."""
    if port is None:
        text = os.environ.get(PORT_ENV, "")
        try:
            port = int(text) if text else DEFAULT_PORT
        except ValueError:
            raise TopsegError(f"${PORT_ENV}={text!r} is not a port number") from None
    if not 1 <= port <= 65535:
        raise TopsegError(f"Zenoh port {port} is not in 1..65535")
    return port


def default_config_json(port: int | None = None) -> dict[str, Any]:
    """topseg's default Zenoh settings as {path: JSON value}, for docs and tests."""
    endpoint = f"tcp/127.0.0.1:{rendezvous_port(port)}"
    return {
        "mode": "peer",
        "scouting/multicast/enabled": False,
        "scouting/gossip/enabled": True,
        "listen/endpoints": [endpoint, "tcp/127.0.0.1:0"],
        "listen/exit_on_failure": False,
        "connect/endpoints": [endpoint],
        "connect/exit_on_failure": False,
        "connect/timeout_ms": 0,
        # retry the rendezvous every second at most (Zenoh's default backs off to 4 s), so a
        # restarted port holder is reached within about a second, not up to four
        "connect/retry": {
            "period_init_ms": 250,
            "period_max_ms": 1000,
            "period_increase_factor": 2,
        },
        # no implicit shared memory: Zenoh would put every message over 3 KB (every depth
        # frame) in a 16 MB pool and take a buffer back from a reader that has not confirmed
        # it for ~0.2 s, so a paused worker (SIGSTOP, a debugger, a cgroup freeze) later
        # read other frames' bytes (docs/reliability.md); loopback TCP is fast enough
        "transport/shared_memory/transport_optimization/enabled": False,
    }


def error_line(exc: BaseException) -> str:
    """Zenoh's error text on one line, without its Rust source paths (for the one-line error
    on stderr and systemd's STATUS=): its config parse errors span several lines."""
    text = re.sub(r"\s*\(?(?:at\s+)?[\w./\\-]+\.rs:\d+(?::\d+)?\)?\.?", "", str(exc))
    m = re.search(r'msg: "(.*?)", location: Some\(Location \{ line: (\d+), column: (\d+)', text)
    if m:
        return f"line {m[2]}, column {m[3]}: {m[1]}"
    m = re.search(r"-->\s*(\d+):(\d+).*?=\s*(.+)", text, re.S)
    if m:
        return f"line {m[1]}, column {m[2]}: {' '.join(m[3].split())}"
    return " ".join(text.split()) or type(exc).__name__


def make_config(config_file: str | None = None, port: int | None = None) -> Any:
    """A zenoh.Config: the file as is, or topseg's loopback default."""
    if config_file:
        if not os.path.isfile(config_file):
            raise TopsegError(f"Zenoh config {config_file} does not exist")
        try:
            return zenoh.Config.from_file(config_file)
        except Exception as exc:  # zenoh reports parse errors as ZError
            raise TopsegError(f"bad Zenoh config {config_file}: {error_line(exc)}") from exc
    conf = zenoh.Config()
    for path, value in default_config_json(port).items():
        conf.insert_json5(path, json.dumps(value))
    return conf


def open_config(config: Any, what: str = "cannot open a Zenoh session") -> Any:
    """An open zenoh.Session for a zenoh.Config; TopsegError("<what>: <Zenoh's reason>")."""
    try:
        return zenoh.open(config)
    except Exception as exc:
        raise TopsegError(f"{what}: {error_line(exc)}") from exc


class OpenTimeout(TopsegError):
    """No Zenoh session by the deadline (`open_within`). The open still runs in a thread:
    leave with `os._exit` after saying so, since a normal exit would stop that thread inside
    Zenoh's Rust code, which aborts the process ("FATAL: exception not rethrown")."""


def open_within(config: Any, seconds: float, what: str = "cannot open a Zenoh session") -> Any:
    """`open_config`, but OpenTimeout once `seconds` passed without a session: Zenoh's open
    waits for the handshake with the rendezvous port's holder (10 s for a frozen one)."""
    box: list = []

    def opener() -> None:
        try:
            box.append(open_config(config, what))
        except BaseException as exc:
            box.append(exc)

    thread = threading.Thread(target=opener, name="zenoh-open", daemon=True)
    thread.start()
    thread.join(seconds)
    if not box:
        raise OpenTimeout(
            f"{what} within {seconds:g} s: whatever holds the rendezvous port (or the "
            "configured endpoints) accepts connections but does not answer as Zenoh (a "
            "frozen process, or another program)"
        )
    if isinstance(box[0], BaseException):
        raise box[0]
    return box[0]


def open_session(config_file: str | None = None, port: int | None = None) -> Any:
    """An open zenoh.Session (close it, or use it as a context manager)."""
    return open_config(make_config(config_file, port))


def config_from_args(args: argparse.Namespace) -> Any:
    """The zenoh.Config named by a service's --zenoh-config / --zenoh-port options."""
    return make_config(args.zenoh_config, args.zenoh_port)


def wait_connected(session: Any, timeout: float) -> bool:
    """Wait up to `timeout` s for a first peer or router, so that a first query reaches
    someone; False when none came."""
    deadline = time.monotonic() + timeout
    while True:
        if any(True for _ in session.info.peers_zid()) or any(
            True for _ in session.info.routers_zid()
        ):
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.02)


def wait_settled(session: Any, quiet_s: float = 0.3, timeout: float = 2.0) -> None:
    """Wait until the session's peers stayed the same for `quiet_s` (gossip brings the
    others after the first one), `timeout` s at most."""
    deadline = time.monotonic() + timeout
    peers, since = None, time.monotonic()
    while time.monotonic() < deadline:
        now_peers = {str(z) for z in session.info.peers_zid()}
        if now_peers != peers:
            peers, since = now_peers, time.monotonic()
        elif time.monotonic() - since >= quiet_s:
            return
        time.sleep(0.02)


def holds_port(port: int) -> bool:
    """Whether this process listens on loopback TCP `port` (its Zenoh session took it)."""
    return any(
        c.status == psutil.CONN_LISTEN and c.laddr and c.laddr.port == port
        for c in psutil.Process().net_connections("tcp")
    )


def has_peers(session: Any) -> bool:
    """Whether `session` is connected to a peer or a router now."""
    return any(True for _ in session.info.peers_zid()) or any(
        True for _ in session.info.routers_zid()
    )


def port_answers(port: int, timeout: float = 0.5) -> bool:
    """Whether something accepts TCP connections on loopback `port` now (the connection is
    closed at once)."""
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=timeout):
            return True
    except OSError:
        return False


def rendezvous_free(port: int) -> bool:
    """Whether nothing holds the rendezvous `port` now: not this process, not another one
    (nothing accepts a connection there)."""
    return not holds_port(port) and not port_answers(port)


def isolation_problem(session: Any, config: Any, port: int | None) -> str | None:
    """Why `session`, open for a while, has met nobody, when that is a fault; else None.

    Alone is normal for the process holding the rendezvous port (`port`, topseg's default
    config: it waits for the others), when nothing listens on that port (the others, its
    holder among them, stopped: the next service to start takes it) and for a config that
    connects nowhere. Otherwise the endpoint it connects to is held by something that does
    not answer as Zenoh: another program on the port, or a frozen process (Zenoh retries
    without a word)."""
    if has_peers(session):
        return None
    if port is not None:
        if holds_port(port) or rendezvous_free(port):
            return None
        where = f"tcp/127.0.0.1:{port}"
        return (
            f"no Zenoh peer reached: {where} (the rendezvous port) is held by something that "
            "does not answer as Zenoh (another program, or a frozen process), so topseg "
            "services cannot meet there; free the port or give every service another "
            "--zenoh-port"
        )
    endpoints = json.loads(config.get_json("connect/endpoints") or "[]")
    if isinstance(endpoints, dict):
        endpoints = [e for v in endpoints.values() for e in v or ()]
    if not endpoints:
        return None
    return (
        f"no Zenoh peer or router reached at {', '.join(map(str, endpoints))}: nothing "
        "there answers as Zenoh (down, another program, or a frozen process)"
    )


def session_from_args(args: argparse.Namespace) -> Any:
    """An open zenoh.Session from a service's --zenoh-config / --zenoh-port options."""
    return open_config(config_from_args(args))
