"""`topseg router` as a real process: two client-mode sessions talk only through it."""

import json
import signal
import subprocess
import sys
import threading

import pytest
import zenoh
from netutil import free_port, wait_for


class Router:
    """`topseg router ...` as a subprocess; a thread keeps its stderr lines."""

    def __init__(self, *args):
        cmd = [sys.executable, "-m", "topseg.services.cli", "-v", "router", *map(str, args)]
        self.proc = subprocess.Popen(
            cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
        )
        self.lines: list[str] = []
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self):
        for line in self.proc.stderr:
            self.lines.append(line.rstrip("\n"))

    def log(self):
        return "\n".join(self.lines)

    def wait_line(self, text, timeout=30):
        wait_for(
            lambda: any(text in line for line in self.lines) or self.proc.poll() is not None,
            timeout,
            f"router log line {text!r}",
        )
        assert any(text in line for line in self.lines), self.log()

    def stop(self):
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            raise AssertionError(f"router did not stop on SIGTERM:\n{self.log()}") from None
        self.thread.join(5)
        return self.proc.returncode


def client(port):
    """A client-mode session that can reach others only through a router on `port`."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    return zenoh.open(conf)


def write_config(path, port, mode="router"):
    body = {
        "listen": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
        "scouting": {"multicast": {"enabled": False}},
    }
    if mode is not None:
        body["mode"] = mode
    path.write_text(json.dumps(body, indent=2))
    return path


def assert_message_passes(port):
    a, b = client(port), client(port)
    try:
        got = []
        b.declare_subscriber("topseg/rt/cam0/stats", lambda s: got.append(s.payload.to_bytes()))
        pub = a.declare_publisher("topseg/rt/cam0/stats")
        wait_for(lambda: pub.matching_status.matching, 10, "the subscriber through the router")
        pub.put(b"through the router")
        wait_for(lambda: got, 10, "the message")
        assert got == [b"through the router"]
    finally:
        a.close()
        b.close()


@pytest.mark.parametrize("mode", ["router", None])
def test_two_clients_talk_through_the_router_then_it_stops_on_sigterm(tmp_path, mode):
    port = free_port()
    router = Router("--zenoh-config", write_config(tmp_path / "router.json5", port, mode))
    try:
        router.wait_line(f"listening on tcp/127.0.0.1:{port}")
        assert_message_passes(port)
    finally:
        rc = router.stop()
    assert rc == 0, router.log()
    assert "router stopped" in router.log()


def test_default_router_listens_on_the_loopback_rendezvous_port():
    port = free_port()
    router = Router("--zenoh-port", port)
    try:
        router.wait_line(f"listening on tcp/127.0.0.1:{port}")
        assert_message_passes(port)
    finally:
        assert router.stop() == 0, router.log()


def test_a_config_in_another_mode_is_refused_in_one_line(tmp_path):
    config = write_config(tmp_path / "peer.json5", free_port(), mode="peer")
    proc = subprocess.run(
        [sys.executable, "-m", "topseg.services.cli", "router", "--zenoh-config", str(config)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip() == (
        f'topseg router: error: {config}: mode is "peer"; topseg router needs "router" (or no mode)'
    )


def test_a_port_in_use_is_one_line_too():
    port = free_port()
    first = Router("--zenoh-port", port)
    try:
        first.wait_line("listening on")
        proc = subprocess.run(
            [sys.executable, "-m", "topseg.services.cli", "router", "--zenoh-port", str(port)],
            capture_output=True,
            text=True,
            timeout=60,
        )
    finally:
        first.stop()
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert lines[-1].startswith(
        f"topseg router: error: cannot start the router on tcp/127.0.0.1:{port}"
    )
