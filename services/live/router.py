"""Run a Zenoh router, for a cell whose services run on several machines. Without a config
it listens on loopback at the rendezvous port; with `--zenoh-config` (such as
`deploy/zenoh/router.json5`, or the TLS `secure-router.json5`) the file is used as is.
`--listen` replaces the listen endpoints.

zenohd is on neither PyPI nor Debian, so this opens a Zenoh session in `router` mode, which
runs Zenoh's own router: it routes between the peers and clients connected to it, on this
host or others (see `deploy/zenoh/` and docs/howto/deploy.md). With `--zenoh-config` the file
is used as is, except that a file without `mode` gets `"router"`; a file with another mode is
refused (it would not route). Without a file the router listens on loopback at the
rendezvous port (`--zenoh-port`, default 7447) with multicast scouting off, where topseg's
default peer config finds it. `--listen` replaces the listen endpoints of either.

It logs its endpoints, tells systemd READY=1 once open, pings the watchdog, shows in
STATUS= how many sessions it routes for, and stops cleanly on SIGTERM/SIGINT.
"""

from __future__ import annotations

import argparse
import json
import logging
import re
from collections import Counter
from typing import Any

import zenoh

from topseg.core.errors import TopsegError
from topseg.services.runtime import zenoh_session
from topseg.services.runtime.lifecycle import ServiceLifecycle

log = logging.getLogger("topseg.router")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The router's options: --listen and Zenoh."""
    parser.add_argument(
        "--listen",
        nargs="+",
        metavar="ENDPOINT",
        help="listen on these endpoints instead (e.g. tcp/0.0.0.0:7447 tls/0.0.0.0:7448)",
    )
    zenoh_session.add_arguments(parser)


def listen_endpoints(config: Any) -> list[str]:
    """The router's listen endpoints from a zenoh.Config (a list, or a per-mode table)."""
    value = json.loads(config.get_json("listen/endpoints"))
    if isinstance(value, dict):
        value = value.get("router", [])
    return [str(v) for v in value or []]


def router_config(config_file: str | None, port: int | None, listen: list[str] | None) -> Any:
    """The zenoh.Config to route with; TopsegError when the file asks for another mode."""
    if config_file:
        config = zenoh_session.make_config(config_file)
        mode = json.loads(config.get_json("mode"))
        if mode is None:  # unset: Zenoh's default would be peer
            config.insert_json5("mode", '"router"')
        elif mode != "router":
            raise TopsegError(
                f'{config_file}: mode is "{mode}"; topseg router needs "router" (or no mode)'
            )
    else:
        config = zenoh.Config()
        config.insert_json5("mode", '"router"')
        config.insert_json5("scouting/multicast/enabled", "false")
        endpoint = f"tcp/127.0.0.1:{zenoh_session.rendezvous_port(port)}"
        config.insert_json5("listen/endpoints", json.dumps([endpoint]))
    if listen:
        try:
            config.insert_json5("listen/endpoints", json.dumps(listen))
        except Exception as exc:  # zenoh reports a bad endpoint as ZError
            reason = re.sub(r"^line \d+, column \d+: ", "", zenoh_session.error_line(exc))
            raise TopsegError(f"--listen {' '.join(listen)}: {reason}") from None
    return config


def connections(session: Any) -> str:
    """'2 client(s), 1 peer(s)': the sessions this router is connected to, by kind."""
    kinds = Counter(str(t.whatami).rsplit(".", 1)[-1].lower() for t in session.info.transports())
    if not kinds:
        return "no sessions connected"
    return ", ".join(f"{n} {kind}(s)" for kind, n in sorted(kinds.items()))


def run(args: argparse.Namespace) -> int:
    """Route until SIGTERM/SIGINT; a config in another mode or a taken port fails (exit 2)."""
    config = router_config(args.zenoh_config, args.zenoh_port, args.listen)
    endpoints = listen_endpoints(config)
    where = ", ".join(endpoints) or "no endpoints"
    svc = ServiceLifecycle(
        "router", config=config, open_error=f"cannot start the router on {', '.join(endpoints)}"
    )
    with svc:
        log.info("router %s listening on %s", svc.session.info.zid(), where)
        svc.ready(
            f"routing on {where}", status=lambda: f"routing on {where}: {connections(svc.session)}"
        )
        svc.wait()  # until a stopping signal, pinging the watchdog
    log.info("router stopped")
    return 0
