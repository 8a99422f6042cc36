"""The service lifecycle helper in this process: real signals, a real Zenoh session on
loopback and a real AF_UNIX datagram socket as systemd's $NOTIFY_SOCKET."""

import argparse
import logging
import os
import signal
import socket
import threading
import time

import pytest
from netutil import free_port, wait_for
from test_systemd_notify import NotifySocket

from topseg.core.errors import TopsegError
from topseg.services.runtime import systemd_notify
from topseg.services.runtime.lifecycle import ServiceLifecycle, ServiceStopped


def args(port=None, config=None):
    return argparse.Namespace(zenoh_config=config, zenoh_port=port or free_port())


@pytest.fixture
def notify(tmp_path):
    listener = NotifySocket(str(tmp_path / "notify.sock"))
    yield listener
    listener.close()


def notifier(listener, watchdog_usec=200_000):
    env = {"NOTIFY_SOCKET": listener.address, "WATCHDOG_USEC": str(watchdog_usec)}
    return systemd_notify.Notifier(env)


def handlers():
    return {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}


def wakeup_fd():
    fd = signal.set_wakeup_fd(-1)
    signal.set_wakeup_fd(fd)
    return fd


def test_ready_beats_stopping_and_signals_restored(notify):
    before, fd_before = handlers(), wakeup_fd()
    svc = ServiceLifecycle("lc1", args(), notifier=notifier(notify))
    with svc:
        assert handlers() != before and wakeup_fd() != fd_before
        assert not svc.session.is_closed()
        svc.ready(status=lambda: "serving lc1")
        assert not svc.wait(0.35)  # times out, pinging the watchdog every 0.1 s meanwhile
    assert handlers() == before and wakeup_fd() == fd_before
    assert svc.session.is_closed() and svc.stopping
    wait_for(lambda: notify.values("STOPPING"), 5, "STOPPING=1")
    fields = [f for _, f in notify.messages]
    assert fields[0] == {"READY": "1", "STATUS": "serving lc1"}
    assert len(notify.times("WATCHDOG", "1")) >= 3
    assert fields[-1] == {"STOPPING": "1"}


def test_cleanups_run_in_reverse_order_on_error_and_the_body_error_wins(caplog):
    ran = []
    before = handlers()

    def failing():
        ran.append("failing")
        raise OSError("cannot clean up")

    svc = ServiceLifecycle("lc2", args(), notifier=systemd_notify.Notifier({}))
    with pytest.raises(RuntimeError, match="the body failed"), svc:
        token = svc.declare(svc.session.liveliness().declare_token("topseg/lc2/cam0/alive/x"))
        assert token is not None
        svc.defer(ran.append, "first")
        svc.defer(failing)
        svc.defer(ran.append, "last")
        raise RuntimeError("the body failed")
    assert ran == ["last", "failing", "first"]
    assert svc.session.is_closed() and handlers() == before
    assert "cannot clean up" in caplog.text


def test_a_cleanup_error_is_raised_when_the_body_succeeded():
    ran = []
    svc = ServiceLifecycle("lc3", args(), notifier=systemd_notify.Notifier({}))
    with pytest.raises(ValueError, match="bad close"), svc:
        svc.defer(ran.append, "still runs")
        svc.defer(lambda: (_ for _ in ()).throw(ValueError("bad close")))
    assert ran == ["still runs"] and svc.session.is_closed()


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_stops_wakes_and_is_logged(caplog, sig):
    caplog.set_level(logging.INFO, logger="topseg")
    woken = threading.Event()
    before = handlers()
    svc = ServiceLifecycle("lc4", args(), notifier=systemd_notify.Notifier({}))
    try:
        with svc:
            svc.on_stop(woken.set)
            threading.Timer(0.2, os.kill, (os.getpid(), sig)).start()
            t0 = time.monotonic()
            assert svc.wait()  # blocks until the signal
            assert time.monotonic() - t0 < 1.0
            assert woken.wait(1.0)
        # stopped by a signal, the process is on its way out: more signals are ignored
        assert handlers() == {signal.SIGTERM: signal.SIG_IGN, signal.SIGINT: signal.SIG_IGN}
    finally:
        for s, handler in before.items():
            signal.signal(s, handler)
    assert f"{signal.Signals(sig).name}: stopping" in caplog.text


def test_interruptible_cuts_a_blocking_call_short():
    svc = ServiceLifecycle("lc5", args(), notifier=systemd_notify.Notifier({}))
    t0 = time.monotonic()
    with svc:
        threading.Timer(0.2, os.kill, (os.getpid(), signal.SIGTERM)).start()
        with svc.interruptible():
            time.sleep(10)
        raise AssertionError("not reached: ServiceStopped leaves the block")
    assert time.monotonic() - t0 < 5.0 and svc.stopping
    with pytest.raises(ServiceStopped), svc.interruptible():
        pass  # already stopped: nothing blocks any more


def test_bad_config_fails_before_signals_or_zenoh(tmp_path):
    before = handlers()
    with pytest.raises(TopsegError, match="does not exist"):
        ServiceLifecycle("lc6", args(config=str(tmp_path / "missing.json5")))
    assert handlers() == before


def test_zenoh_open_error_is_one_line_and_restores_signals():
    import zenoh

    before = handlers()
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        config = zenoh.Config()
        config.insert_json5("mode", '"router"')
        config.insert_json5("scouting/multicast/enabled", "false")
        config.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{port}"]')
        svc = ServiceLifecycle("lc7", config=config, open_error="cannot start the router")
        with pytest.raises(TopsegError, match=r"^cannot start the router: ") as info, svc:
            pass
    assert "\n" not in str(info.value)
    assert handlers() == before


def test_ready_freezes_what_the_service_loaded_out_of_the_collector(notify):
    import gc

    gc.unfreeze()
    svc = ServiceLifecycle("lc-gc", args(), notifier=notifier(notify))
    try:
        with svc:
            loaded = [[i] for i in range(1000)]  # tracked objects the service holds
            svc.ready("serving lc-gc")
            assert gc.get_freeze_count() >= len(loaded)
            scanned = {id(o) for o in gc.get_objects()}  # every generation but the frozen
            assert not any(id(o) in scanned for o in loaded)
            more = [[i] for i in range(1000)]
            svc.ready("still serving")  # STATUS= only: nothing frozen again
            scanned = {id(o) for o in gc.get_objects()}
            assert all(id(o) in scanned for o in more)
    finally:
        gc.unfreeze()  # the test process's own objects back under the collector
