"""Control-plane faults an operator causes, with real processes, real Zenoh on loopback and
real signals: two drivers or two workers for one camera, a wildcard worker that waits or
meets a renamed camera, a foreign program or a frozen process on the rendezvous port."""

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from netutil import free_port, wait_for

from topseg.core.camera import KINECT_V1, PAPER_MOUNT, TopViewMount
from topseg.core.formats import wire
from topseg.core.synth.procedural import procedural_frame
from topseg.services.runtime.zenoh_session import open_session

ROOT = Path(__file__).resolve().parent.parent
MODEL = ROOT / "models" / "default.npz"
K = KINECT_V1.scaled_to(160, 120)
#: The instance id of the test's stand-in for a second driver (real ones are Zenoh ids).
IMPOSTOR = "0123456789abcdef"


@pytest.fixture
def recording(small_recording):
    """One second of small procedural frames at 30 fps (conftest's `small_recording`)."""
    return small_recording


def driver(run, port, cell, recording, camera="cam0"):
    source = f"replay:{recording}"
    return run("driver", "--cell", cell, "--camera", camera, "--source", source, "--loop",
               "--zenoh-port", port)  # fmt: skip


def worker(run, port, *cameras):
    named = ["--cameras", *cameras] if cameras else []
    return run("worker", "--model", MODEL, "--crf", "none", *named, "--zenoh-port", port)


def status(port, *args, timeout=2.0):
    """`topseg status` as a process: (exit status, stdout, stderr)."""
    cmd = [sys.executable, "-m", "topseg.services.cli", "status", "--zenoh-port", str(port)]
    done = subprocess.run([*cmd, "--timeout", str(timeout), *args], capture_output=True,
                          text=True, timeout=120)  # fmt: skip
    return done.returncode, done.stdout, done.stderr


def one_error_line(service) -> str:
    """The service's one error line (it exited 2 without a traceback)."""
    errors = [line for _, line in service.lines if "error:" in line]
    assert len(errors) == 1 and "Traceback" not in service.err, service.err
    return errors[0]


@pytest.mark.slow
def test_a_second_driver_for_a_served_camera_is_refused_and_a_restart_after_kill_9_is_not(
    run, recording
):
    port, cell = free_port(), "dup1"
    tap = run.tap(port, cell)  # holds the rendezvous port
    d1 = driver(run, port, cell, recording)
    wait_for(lambda: len(tap.depth) >= 5, 60, "depth from the first driver")
    first = tap.info()["instance"]

    d2 = driver(run, port, cell, recording)
    assert d2.proc.wait(60) == 2, d2.err
    line = one_error_line(d2)
    assert f"camera {cell}/cam0 is already served by driver {first} (pid {d1.proc.pid}" in line
    assert d1.alive()

    d1.kill()  # a crashed driver's token goes with its connection: a restart starts
    d3 = driver(run, port, cell, recording)
    d3.wait_line("publishing", 60)
    wait_for(lambda: tap.info()["instance"] != first, 20, "the restarted driver's info")
    assert d3.stop() == 0 and "already served" not in d3.err, d3.err


def test_two_drivers_started_at_once_end_with_one(run, recording):
    """Each starts too early to see the other; once their tokens meet, the younger stops."""
    port, cell = free_port(), "dup4"
    tap = run.tap(port, cell)
    pair = [driver(run, port, cell, recording) for _ in range(2)]
    wait_for(lambda: any(not d.alive() for d in pair), 60, "one of the two drivers to stop")
    n = len(tap.depth)
    wait_for(lambda: len(tap.depth) > n + 10, 30, "depth from the driver left")  # goes on
    stopped = [d for d in pair if not d.alive()]
    assert len(stopped) == 1 and stopped[0].proc.returncode == 2, pair[0].err + pair[1].err
    assert f"camera {cell}/cam0 is already served by driver" in one_error_line(stopped[0])
    (left,) = [d for d in pair if d.alive()]
    assert left.stop() == 0, left.err


def test_a_driver_that_did_not_answer_once_is_asked_again_and_the_younger_stops():
    """In process, real Zenoh on loopback: an older driver's token is there but its `info`
    answer to the first question is lost (as under load); the younger driver warns, goes on,
    asks again `RECHECK_S` later and then stops, instead of running beside it for good."""
    import argparse

    from topseg.core.errors import TopsegError
    from topseg.services.live.driver import DriverState, OneDriverPerCamera
    from topseg.services.runtime import identity

    port, cell = free_port(), "dup5"
    older, younger = open_session(port=port), open_session(port=port)
    asked = []

    def answer_all_but_the_first(query):
        asked.append(time.monotonic())
        if len(asked) > 1:
            info = {"instance": IMPOSTOR, "started_ns": 1, "pid": 1, "host": "h", "source": "s"}
            query.reply(wire.info_key(cell, "cam0"), json.dumps(info).encode())

    queryable = older.declare_queryable(wire.info_key(cell, "cam0"), answer_all_but_the_first)
    token = older.liveliness().declare_token(wire.alive_key(cell, "cam0", "driver", IMPOSTOR))
    args = argparse.Namespace(cell=cell, camera="cam0", source="s", fps=None, congestion="drop")
    state = DriverState(args, {})
    one = OneDriverPerCamera(younger, args, identity.Identity.of(younger), state)
    try:
        wait_for(lambda: IMPOSTOR in one.others, 20, "the older driver's token")
        one.at_start()  # the first question: no answer, a warning, no error
        assert len(asked) == 1 and one.recheck_at is not None
        with pytest.raises(TopsegError, match=f"already served by driver {IMPOSTOR}"):
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline:
                one.poll()
                time.sleep(0.05)
        assert len(asked) == 2
        assert asked[1] - asked[0] >= OneDriverPerCamera.RECHECK_S - 0.1
    finally:
        one.undeclare()
        token.undeclare(), queryable.undeclare()
        younger.close(), older.close()


def test_a_silent_driver_is_asked_less_often_and_not_at_all_once_its_token_goes():
    """The waits between questions to a driver that never answers double up to
    `RECHECK_MAX_S`; when its token goes (its lease ended) the questions stop."""
    import argparse

    from topseg.services.live.driver import DriverState, OneDriverPerCamera
    from topseg.services.runtime import identity

    port, cell = free_port(), "dup6"
    older, younger = open_session(port=port), open_session(port=port)
    token = older.liveliness().declare_token(wire.alive_key(cell, "cam0", "driver", IMPOSTOR))
    args = argparse.Namespace(cell=cell, camera="cam0", source="s", fps=None, congestion="drop")
    one = OneDriverPerCamera(younger, args, identity.Identity.of(younger), DriverState(args, {}))
    try:
        wait_for(lambda: IMPOSTOR in one.others, 20, "the silent driver's token")
        waits = []
        for _ in range(6):
            before = time.monotonic()
            one.check(set())
            waits.append(one.recheck_at - before)
        first, most = OneDriverPerCamera.RECHECK_S, OneDriverPerCamera.RECHECK_MAX_S
        expected = [min(first * 2**i, most) for i in range(6)]  # 2, 4, 8, 16, 30, 30 s
        slack = identity.QUERY_S + 1  # the question itself comes before the wait
        assert all(e <= w <= e + slack for e, w in zip(expected, waits, strict=True)), waits
        token.undeclare()
        wait_for(lambda: IMPOSTOR not in one.others, 20, "the token's deletion")
        one.check(set())
        assert one.recheck_at is None and one.recheck_s == OneDriverPerCamera.RECHECK_S
    finally:
        one.undeclare()
        younger.close(), older.close()


class Impostor:
    """A second publisher of one camera's depth as a second driver would be: its own token
    `.../alive/driver/IMPOSTOR` and frames (seq from 10000) with its attachment, 15 a second."""

    def __init__(self, port, cell):
        self.session = open_session(port=port)
        self.token = self.session.liveliness().declare_token(
            wire.alive_key(cell, "cam0", "driver", IMPOSTOR)
        )
        self.pub = self.session.declare_publisher(wire.depth_key(cell, "cam0"))
        rng = np.random.default_rng(3)
        self.depth, _ = procedural_frame(rng, TopViewMount(K, PAPER_MOUNT.height_mm))
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._publish, daemon=True)
        self.thread.start()

    def _publish(self):
        seq = 10000
        while not self.stop.wait(1 / 15):
            frame = wire.DepthFrame(self.depth, K, seq, time.time_ns())
            self.pub.put(wire.encode_depth(frame), attachment=wire.instance_attachment(IMPOSTOR))
            seq += 1

    def close(self):
        self.stop.set()
        self.thread.join(5)
        self.session.close()


@pytest.mark.slow
def test_depth_from_two_drivers_on_one_key_is_not_mixed_and_status_shows_both(run, recording):
    """Two drivers that started at once (neither saw the other) interleave on one key: the
    worker follows one, drops and counts the other's frames; status names both, exit 1."""
    port, cell = free_port(), "dup2"
    wk = worker(run, port, f"{cell}/cam0")
    wk.wait_line("worker ready", 120)
    drv = driver(run, port, cell, recording)
    tap = run.tap(port, cell)
    wait_for(lambda: len(tap.labels) >= 5, 60, "labels of the real driver's frames")
    impostor = Impostor(port, cell)
    try:
        started = time.monotonic()
        wait_for(lambda: "TWO DRIVERS publish" in wk.err, 60, "the worker's warning")
        wait_for(lambda: tap.stats and tap.stats[-1]["counts"].get("foreign", 0) >= 5, 60,
                 "foreign frames counted")  # fmt: skip
        drv.wait_line("ANOTHER DRIVER serves", 30)
        rc, out, err = status(port, "--cell", cell)
        rc_json, out_json, _ = status(port, "--cell", cell, "--json")
    finally:
        impostor.close()
    labelled = [x[1] for x in tap.labels_after(started)]
    assert labelled and max(labelled) < 10000, "the impostor's frames were labelled"
    assert rc == 1 and f"{cell}/cam0: 2 drivers: " in out and IMPOSTOR in out, out + err
    assert "depth from two drivers" in out, out
    row = json.loads(out_json)["cameras"][0]
    assert rc_json == 1 and not row["ok"] and len(row["duplicates"]["driver"]) == 2
    assert wk.stop() == 0 and drv.stop() == 0, wk.err + drv.err


@pytest.mark.slow
def test_a_second_worker_for_a_camera_is_refused_and_a_wildcard_worker_leaves_it(run, recording):
    port, cell = free_port(), "dup3"
    w1 = worker(run, port, f"{cell}/cam0")
    w1.wait_line("worker ready", 120)
    w2 = worker(run, port, f"{cell}/cam0", f"{cell}/cam1")
    assert w2.proc.wait(120) == 2, w2.err
    assert f"camera {cell}/cam0 is already labelled by worker " in one_error_line(w2)

    w3 = worker(run, port)  # serves every camera it sees, but not one another worker labels
    w3.wait_line("worker ready", 120)
    drv = driver(run, port, cell, recording)
    tap = run.tap(port, cell)
    wait_for(lambda: len(tap.labels) >= 5, 60, "labels")
    w3.wait_line(f"{cell}/cam0 is labelled by worker", 30)
    assert f"serving {cell}/cam0" not in w3.err, w3.err
    rc, out, err = status(port, "--cell", cell)
    assert rc == 0 and "2 workers" not in out, out + err
    assert w1.stop() == 0 and w3.stop() == 0 and drv.stop() == 0, w1.err + w3.err


@pytest.mark.slow
def test_two_wildcard_workers_end_with_one_labelling_the_camera(run, recording):
    """Two workers that serve every camera meet one: one of them leaves it to the other
    (whichever saw the other's token first, else the larger instance id), and the labels go
    on from the one left."""
    port, cell = free_port(), "two"
    w1, w2 = worker(run, port), worker(run, port)
    w1.wait_line("worker ready", 120)
    w2.wait_line("worker ready", 120)
    drv = driver(run, port, cell, recording)
    tap = run.tap(port, cell)
    wait_for(lambda: len(tap.labels) >= 5, 60, "labels")

    def one_worker() -> bool:
        rc, out, _ = status(port, "--cell", cell)
        return rc == 0 and "2 workers" not in out

    wait_for(one_worker, 90, "one worker for the camera")
    left = [
        w
        for w in (w1, w2)
        if "leaving that camera to it" in w.err or f"{cell}/cam0 is labelled by worker" in w.err
    ]
    assert len(left) == 1, w1.err + w2.err
    n = len(tap.labels)
    wait_for(lambda: len(tap.labels) >= n + 5, 60, "labels from the worker left")
    assert w1.stop() == 0 and w2.stop() == 0 and drv.stop() == 0, w1.err + w2.err


@pytest.mark.slow
def test_a_waiting_wildcard_worker_shows_in_status_and_serves_a_renamed_camera(run, recording):
    port, cell = free_port(), "ren"
    wk = worker(run, port)
    wk.wait_line("worker ready", 120)
    rc, out, err = status(port, "--cell", cell)
    assert rc == 1 and "serves every camera: waiting for a first depth frame" in out, out + err
    rc, out, err = status(port, "--expect", f"{cell}/old")
    assert rc == 1 and "waiting" in out and "worker DOWN" not in out, out + err

    d1 = driver(run, port, cell, recording, camera="old")
    old = run.tap(port, cell, "old")
    wait_for(lambda: len(old.labels) >= 5, 60, "labels of the camera 'old'")
    d1.kill()  # restarted under another name: the worker serves it, no restart needed
    d2 = driver(run, port, cell, recording, camera="new")
    new = run.tap(port, cell, "new")
    wait_for(lambda: len(new.labels) >= 5, 60, "labels of the renamed camera")
    assert wk.stop() == 0 and d2.stop() == 0, wk.err + d2.err


@pytest.mark.slow
def test_a_foreign_program_on_the_rendezvous_port_is_warned_about(run, recording):
    """Another program holds the port: the driver cannot meet anyone there and says so."""
    port = free_port()
    with socket.socket() as squatter:
        squatter.bind(("127.0.0.1", port))
        squatter.listen(16)
        drv = driver(run, port, "foreign", recording)
        line = drv.wait_line("no Zenoh peer reached", 60)
        assert f"tcp/127.0.0.1:{port} (the rendezvous port) is held by something" in drv.err
        assert drv.alive() and line > 0
        assert drv.stop() == 0, drv.err


@pytest.mark.slow
def test_status_ends_within_its_timeout_when_the_rendezvous_holder_is_frozen(run, recording):
    """A frozen port holder must not make status wait for Zenoh's 10 s handshake and then
    report no services while the driver publishes: one line and exit 2 once its time is up."""
    port, cell = free_port(), "frozen"
    router = run("router", "--zenoh-port", port)
    router.wait_line("listening on", 60)
    drv = driver(run, port, cell, recording)
    drv.wait_line("publishing", 60)
    rc, out, err = status(port, "--cell", cell)
    assert rc == 1 and f"{cell}/cam0" in out, out + err  # the driver, no worker
    os.kill(router.proc.pid, signal.SIGSTOP)
    try:
        rc, out, err = status(port, "--cell", cell)
    finally:
        os.kill(router.proc.pid, signal.SIGCONT)
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1 and "cannot open a Zenoh session within 3 s" in err, err
    assert "does not answer as Zenoh" in err and ".rs:" not in err
    assert drv.stop() == 0 and router.stop() == 0, drv.err + router.err


@pytest.mark.slow
def test_the_worker_that_keeps_a_camera_warns_only_about_a_worker_that_stays(run, recording):
    """Of two workers serving every camera that both took one, the one that kept it warned
    `ANOTHER WORKER labels ... too` after the other had stepped back. A stand-in second
    worker (its token; an instance id above any Zenoh id, so it is the one to step back)
    takes the real worker's camera and leaves it: the real one says so and warns not;
    taken again and kept past the grace, it is warned about."""
    port, cell = free_port(), "keep"
    wk = worker(run, port)
    wk.wait_line("worker ready", 120)
    driver(run, port, cell, recording)
    wk.wait_line(f"serving {cell}/cam0", 60)
    other = "f" * 32
    session = open_session(port=port)
    try:
        token = session.liveliness().declare_token(wire.alive_key(cell, "cam0", "worker", other))
        wk.wait_line(f"worker {other} took {cell}/cam0 too; this worker keeps it", 30)
        token.undeclare()  # what the other does once it has seen the smaller id
        wk.wait_line(f"worker {other} no longer labels {cell}/cam0", 30)
        assert "ANOTHER WORKER" not in wk.err, wk.err
        taken = time.monotonic()
        token = session.liveliness().declare_token(wire.alive_key(cell, "cam0", "worker", other))
        wk.wait_line(f"ANOTHER WORKER labels {cell}/cam0 too: {other}", 60, after=taken)
        token.undeclare()
    finally:
        session.close()
    assert wk.stop() == 0, wk.err


@pytest.mark.slow
def test_a_clean_driver_stop_raises_no_alarm_about_the_rendezvous_port(run, recording):
    """A worker that met the driver holding the rendezvous port does not warn, once the
    driver stops on SIGTERM, that the port "is held by something that does not answer as
    Zenoh" when nothing listens there: it says, once, that nothing holds the port."""
    port, cell = free_port(), "calm"
    drv = driver(run, port, cell, recording)
    drv.wait_line("publishing", 60)  # it holds the port: it started first
    wk = worker(run, port, f"{cell}/cam0")
    wk.wait_line("frames labelled at", 120)  # it met the driver
    stopped = time.monotonic()
    assert drv.stop() == 0, drv.err
    wk.wait_line(f"nothing holds the rendezvous port tcp/127.0.0.1:{port}", 30, after=stopped)
    assert "does not answer as Zenoh" not in wk.err, wk.err
    assert wk.stop() == 0, wk.err
