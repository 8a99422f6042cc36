"""systemd notifications: a real AF_UNIX datagram socket as $NOTIFY_SOCKET, real services."""

import os
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from netutil import free_port, wait_for

from topseg.core import forest
from topseg.core.camera import KINECT_V1, PAPER_MOUNT, TopViewMount
from topseg.core.synth.procedural import procedural_frame
from topseg.services.runtime import systemd_notify as sd


class NotifySocket:
    """A datagram socket standing in for systemd: keeps (arrival time, fields) per message."""

    def __init__(self, address):
        self.address = address
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(address)
        self.sock.settimeout(0.1)
        self.messages: list[tuple[float, dict[str, str]]] = []
        self.running = True
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self):
        while self.running:
            try:
                data = self.sock.recv(65536)  # passed fds (BARRIER=1) are closed by the kernel
            except TimeoutError:
                continue
            except OSError:
                return
            fields = dict(line.split("=", 1) for line in data.decode().splitlines())
            self.messages.append((time.monotonic(), fields))

    def times(self, key, value=None):
        return [t for t, f in self.messages if key in f and (value is None or f[key] == value)]

    def values(self, key):
        return [f[key] for _, f in self.messages if key in f]

    def close(self):
        self.running = False
        self.thread.join()
        self.sock.close()


@pytest.fixture
def notify_socket(tmp_path):
    listener = NotifySocket(str(tmp_path / "notify.sock"))
    yield listener
    listener.close()


@pytest.fixture(scope="module")
def model_path(tmp_path_factory):
    """A tiny forest, saved as a model file."""
    rng = np.random.default_rng(0)
    mount = TopViewMount(KINECT_V1.scaled_to(160, 120), PAPER_MOUNT.height_mm)
    pairs = [procedural_frame(rng, mount) for _ in range(6)]
    depth = np.stack([d for d, _ in pairs])
    truth = np.stack([t for _, t in pairs])
    config = forest.TrainConfig(
        n_trees=1, max_depth=6, frames_per_tree=6, pixels_per_frame=200,
        n_candidates=10, n_thresholds=10,
    )  # fmt: skip
    path = tmp_path_factory.mktemp("model") / "tiny.npz"
    forest.save_model(path, forest.train_forest(depth, truth, config, seed=0))
    return path


def service(notify, *args, watchdog_usec=200_000):
    env = dict(os.environ, NOTIFY_SOCKET=notify.address, WATCHDOG_USEC=str(watchdog_usec))
    env.pop("WATCHDOG_PID", None)
    cmd = [sys.executable, "-m", "topseg.services.cli", "-v", *map(str, args)]
    return subprocess.Popen(
        cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env
    )


def finish(proc, timeout=60):
    """Wait for a process that should exit by itself."""
    try:
        _, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
        raise AssertionError(f"did not exit:\n{err}") from None
    return proc.returncode, err


def stop(proc, timeout=20):
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        _, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
        raise AssertionError(f"did not stop on SIGTERM:\n{err}") from None
    return proc.returncode, err


def assert_ready_then_watchdog(notify, proc, what):
    try:
        wait_for(
            lambda: notify.times("READY", "1") or proc.poll() is not None, 120, f"{what} READY=1"
        )
        assert proc.poll() is None, proc.communicate()[1]
        ready = notify.times("READY", "1")[0]
        wait_for(lambda: len([t for t in notify.times("WATCHDOG") if t >= ready]) >= 4, 20, "pings")
    finally:
        rc, err = stop(proc)
    assert rc == 0, err
    assert len(notify.times("READY")) == 1
    pings = [t for t in notify.times("WATCHDOG", "1") if t >= ready]
    gaps = np.diff(pings)
    assert gaps.min() > 0.05, gaps  # rate-limited to half of WATCHDOG_USEC (0.1 s), not per loop
    return err


def test_socket_address_and_watchdog_interval():
    assert sd.socket_address("/run/systemd/notify") == "/run/systemd/notify"
    assert sd.socket_address("@abstract/name") == b"\0abstract/name"
    assert sd.socket_address("") is None and sd.socket_address("relative") is None
    me = str(os.getpid())
    assert sd.watchdog_interval({"WATCHDOG_USEC": "30000000"}) == 15.0
    assert sd.watchdog_interval({"WATCHDOG_USEC": "30000000", "WATCHDOG_PID": me}) == 15.0
    assert sd.watchdog_interval({"WATCHDOG_USEC": "30000000", "WATCHDOG_PID": "1"}) is None
    assert sd.watchdog_interval({"WATCHDOG_USEC": "0"}) is None
    assert sd.watchdog_interval({"WATCHDOG_USEC": "x"}) is None and sd.watchdog_interval({}) is None
    assert sd.format_message({"READY": 1, "STATUS": "two\nlines"}) == b"READY=1\nSTATUS=two lines"


def test_without_notify_socket_everything_is_a_no_op():
    n = sd.Notifier({"WATCHDOG_USEC": "1000"})
    assert not n.enabled
    assert not n.ready("x") and not n.watchdog() and not n.status("x") and not n.failed("x")
    sd.Heartbeat(lambda: "never asked", notifier=n)()


def test_notifier_sends_fields_rate_limits_the_watchdog_and_waits_at_the_barrier(notify_socket):
    n = sd.Notifier({"NOTIFY_SOCKET": notify_socket.address, "WATCHDOG_USEC": "2000000"})
    assert n.watchdog_s == 1.0
    assert n.ready("serving x")  # READY=1 and a first ping
    assert not n.watchdog(time.monotonic() + 0.5)  # within the half interval: not sent
    assert n.watchdog(time.monotonic() + 1.01)
    assert n.failed("topseg worker: error: bad model", errno=2)
    wait_for(lambda: len(notify_socket.messages) == 5, 5, "five messages")
    fields = [f for _, f in notify_socket.messages]
    assert fields[0] == {"READY": "1", "STATUS": "serving x"}
    assert fields[1] == fields[2] == {"WATCHDOG": "1"}
    assert fields[3] == {"STATUS": "topseg worker: error: bad model", "ERRNO": "2"}
    assert fields[4] == {"BARRIER": "1"}


def test_abstract_socket_and_heartbeat_status():
    name = f"topseg-test-{os.getpid()}-{time.monotonic_ns()}"
    listener = NotifySocket("\0" + name)
    try:
        n = sd.Notifier({"NOTIFY_SOCKET": "@" + name, "WATCHDOG_USEC": "100000"})
        beat = sd.Heartbeat(lambda: "serving cell/cam0: 30.0 fps", every_s=0.05, notifier=n)
        deadline = time.monotonic() + 0.5
        while time.monotonic() < deadline:
            beat()
            time.sleep(0.005)
        wait_for(lambda: len(listener.values("STATUS")) >= 3, 5, "status lines")
        assert set(listener.values("STATUS")) == {"serving cell/cam0: 30.0 fps"}
        assert 3 <= len(listener.values("WATCHDOG")) <= 12  # every 0.05 s, not every 5 ms
    finally:
        listener.close()


@pytest.mark.slow
def test_driver_sends_ready_status_and_repeated_watchdog_pings(notify_socket):
    port = free_port()
    proc = service(notify_socket, "driver", "--source", "synthetic", "--cell", "sd1",
                   "--fps", "30", "--zenoh-port", port)  # fmt: skip
    assert_ready_then_watchdog(notify_socket, proc, "the driver's")
    first = notify_socket.values("STATUS")[0]
    assert first.startswith("publishing sd1/cam0 from synthetic"), first
    assert notify_socket.values("STOPPING") == ["1"]


def test_worker_sends_ready_after_the_model_is_compiled_and_pings_from_its_loop(
    notify_socket, model_path
):
    port = free_port()
    proc = service(notify_socket, "worker", "--model", model_path, "--zenoh-port", port)
    err = assert_ready_then_watchdog(notify_socket, proc, "the worker's")
    assert "loaded and compiled" in err
    assert notify_socket.values("STATUS")[0] == "model tiny.npz: waiting for depth frames"


def test_worker_with_a_damaged_model_says_why_in_status_and_exits_2(notify_socket, tmp_path):
    bad = tmp_path / "damaged.npz"
    bad.write_bytes(b"PK\x03\x04 this is not a model")
    proc = service(notify_socket, "worker", "--model", bad, "--zenoh-port", free_port())
    rc, err = finish(proc)
    assert rc == 2
    assert err.strip().count("\n") == 0 and err.startswith("topseg worker: error:"), err
    wait_for(lambda: notify_socket.values("STATUS"), 5, "a STATUS line")
    assert notify_socket.values("STATUS") == [err.strip()]
    assert not notify_socket.times("READY")


def test_bad_config_file_reaches_systemd_too(notify_socket, tmp_path):
    config = tmp_path / "cam.toml"
    config.write_text('[driver]\nsource = "synthetic"\nfps = "fast"\n')
    proc = service(notify_socket, "driver", "--config", config)
    rc, err = finish(proc)
    assert rc == 2
    assert (
        err.strip()
        == f"topseg driver: error: {config}:3: fps: expected a number, got a string ('fast')"
    )
    wait_for(lambda: notify_socket.values("STATUS"), 5, "a STATUS line")
    assert notify_socket.values("STATUS") == [err.strip()]


def test_viewer_sends_ready_and_pings_while_idle(notify_socket, tmp_path):
    proc = service(
        notify_socket, "viewer", "--save", tmp_path / "v.rrd", "--zenoh-port", free_port()
    )
    assert_ready_then_watchdog(notify_socket, proc, "the viewer's")
    assert notify_socket.values("STATUS")[0].startswith("logging 0 camera(s) to ")
