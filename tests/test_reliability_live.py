"""Faults of the live system, with real processes, real Zenoh on loopback and real signals:
a worker killed with -9 and restarted, sensors that drop out or stall, a driver restarted,
a worker slower than its sensor (and its 10-minute soak, `make test-all`)."""

import json
import os
import re
import signal
import statistics
import time
from pathlib import Path

import numpy as np
import pytest
from netutil import free_port, wait_for

from topseg.core.camera import KINECT_V1

ROOT = Path(__file__).resolve().parent.parent
MODEL = ROOT / "models" / "default.npz"
DEMO = ROOT / "recordings" / "demo.mcap"
K = KINECT_V1.scaled_to(160, 120)
FPS = 30


@pytest.fixture
def recording(small_recording):
    """One second of small procedural frames at 30 fps (conftest's `small_recording`)."""
    return small_recording


def worker(run, port, cell, *extra):
    return run(
        "worker", "--model", MODEL, "--cameras", f"{cell}/cam0", "--zenoh-port", port, *extra
    )


def driver(run, port, cell, source, *extra):
    return run("driver", "--cell", cell, "--source", source, "--zenoh-port", port, *extra)


@pytest.mark.slow
def test_worker_killed_mid_stream_labels_again_within_2s_and_the_driver_never_notices(
    run, recording
):
    port, cell = free_port(), "rel1"
    w1 = worker(run, port, cell)
    w1.wait_line("worker ready", 120)  # it holds the rendezvous port: the harder case
    drv = driver(run, port, cell, f"replay:{recording}", "--loop")
    tap = run.tap(port, cell)
    wait_for(lambda: len(tap.labels) >= 10, 60, "labels from the first worker")

    w1.kill()  # kill -9 mid-stream: no goodbye, the port holder is gone
    killed = time.monotonic()
    wait_for(lambda: len([d for d in tap.depth if d[0] > killed + 1.0]) >= 10, 20, "depth on")

    w2 = worker(run, port, cell)
    ready = w2.wait_line("worker ready", 120)
    wait_for(lambda: tap.labels_after(ready), 10, "labels from the restarted worker")
    first = tap.labels_after(ready)[0]
    print(f"first labels {first[0] - ready:.2f} s after the restarted worker's READY")
    assert first[0] - ready < 2.0, f"first labels {first[0] - ready:.2f} s after READY"
    wait_for(lambda: len(tap.labels_after(ready)) >= 10, 20, "labels flowing again")

    received = len(tap.depth)  # before asking: frames keep coming while the reply travels
    info = tap.info()
    assert drv.alive() and info["reconnects"] == 0 and info["last_error"] is None
    assert info["frames"] >= received > 0
    # the driver kept its pace: depth in order, and none lost but what DROP congestion
    # control sheds on a starved machine (at load 14 on 2 cores: up to 6 % in bursts of
    # 3-5 frames, with or without the kill; none on a quiet one), never a pause
    seqs = [d[1] for d in tap.depth]
    missing = sorted(set(range(seqs[0], seqs[-1] + 1)) - set(seqs))
    runs = np.split(np.array(missing), np.flatnonzero(np.diff(missing) != 1) + 1)
    longest = max((len(r) for r in runs), default=0)
    print(f"the tap missed {len(missing)} of {seqs[-1] - seqs[0] + 1} depth frames")
    assert seqs == sorted(seqs), "depth out of order"
    assert len(missing) <= len(seqs) // 10 and longest <= FPS // 2, f"missing {missing}"
    assert "WARNING" not in drv.err and "trying again" not in drv.err
    assert w2.stop() == 0 and drv.stop() == 0, w2.err + drv.err


def _delays(err: str) -> list[float]:
    return [float(x) for x in re.findall(r"trying again in ([0-9.]+) s", err)]


@pytest.mark.slow
def test_sensor_faults_back_off_and_a_restarted_driver_is_served_again(run, recording):
    port, cell = free_port(), "rel2"
    tap = run.tap(port, cell)  # holds the port; the worker and each driver come and go
    wk = worker(run, port, cell)
    wk.wait_line("worker ready", 120)

    # two failed opens (sensor missing), then two opens that drop out after 20 frames
    spec = f"faulty:fail_opens=2,fail_after=20,faults=2@replay:{recording}"
    d1 = driver(run, port, cell, spec, "--loop")
    wait_for(lambda: d1.err.count("open again") >= 2, 30, "the sensor back after four faults")
    back = [t for t, line in d1.lines if "open again" in line][1]
    wait_for(lambda: len(tap.labels_after(back)) >= 10, 30, "labels after the sensor is back")
    delays = _delays(d1.err)
    # exponential while opens fail (0.5, 1.0 s, ±10 %), reset by the frames of a good open
    assert 0.45 <= delays[0] <= 0.55 and 0.9 <= delays[1] <= 1.1, delays
    assert all(0.45 <= d <= 0.55 for d in delays[2:4]), delays
    assert "sensor not found" in d1.err and "sensor dropped out after 20 frames" in d1.err
    info = tap.info()
    assert info["reconnects"] == 2 and "dropped out" in info["last_error"]
    seqs = [d[1] for d in tap.depth]
    assert seqs == sorted(seqs)  # the driver numbers on across reopens

    d1.kill()  # the driver process dies; a new one (seq from 0 again) takes over
    t1 = time.monotonic()
    d2 = driver(run, port, cell, f"faulty:stall_after=15,faults=1@replay:{recording}", "--loop",
                "--frame-timeout", "0.5")  # fmt: skip
    d2.wait_line("stalled", 30)
    stalled = d2.wait_line("open again", 30)
    wait_for(lambda: len(tap.labels_after(stalled)) >= 10, 30, "labels after the stall")
    seqs = [x[1] for x in tap.labels_after(t1)]
    assert min(seqs) < 15, f"the restarted driver's first frames were not labelled: {seqs}"
    assert wk.alive() and d2.alive()
    wait_for(lambda: tap.stats and tap.stats[-1]["counts"]["rejected"] == 0, 5, "stats")
    assert wk.stop() == 0 and d2.stop() == 0, wk.err + d2.err
    assert "Traceback" not in wk.err + d1.err + d2.err


def watch_slow_worker(run, seconds: float, sample_s: float, cell: str) -> dict:
    """A 30 fps 640x480 replay into a worker with the exact CRF (~1-2 s a frame): the figures."""
    port = free_port()
    tap = run.tap(port, cell)
    wk = worker(run, port, cell, "--crf", "exact")
    wk.wait_line("worker ready", 120)
    drv = driver(run, port, cell, f"replay:{DEMO}", "--loop")
    wait_for(lambda: len(tap.labels) >= 2, 120, "the first labels")
    start = time.monotonic()
    rss = []  # (s since start, worker MB, driver MB)
    # at least `seconds`, and until 3 labels came (a loaded machine is slower), 120 s at most
    while time.monotonic() - start < seconds or (
        len(tap.labels_after(start)) < 3 and time.monotonic() - start < max(seconds, 120)
    ):
        assert wk.alive() and drv.alive(), wk.err + drv.err
        rss.append((time.monotonic() - start, wk.rss_mb(), drv.rss_mb()))
        time.sleep(sample_s)
    labels = tap.labels_after(start)
    elapsed = time.monotonic() - start

    def missing_stats() -> set:  # a frame's stats follow its labels on another key
        return {seq for _, seq, _, _ in labels} - {s["seq"] for s in tap.stats if "seq" in s}

    # the worker publishes with congestion control DROP (not --lossless): on a starved
    # machine one stats message may be dropped, two are a fault
    deadline = time.monotonic() + 10
    while missing_stats() and time.monotonic() < deadline:
        time.sleep(0.02)
    assert len(missing_stats()) <= 1, f"no stats for labelled frames {sorted(missing_stats())}"
    stats = [s for s in tap.stats if "seq" in s]
    assert wk.stop() == 0 and drv.stop() == 0, wk.err + drv.err

    took = {s["seq"]: s["timings_ms"]["total"] / 1000 for s in stats}
    newest = [(t, seq) for t, seq, _ in tap.depth]
    rows = []
    for t, seq, stamp, now_ns in (row for row in labels if row[1] in took):
        latency = (now_ns - stamp) / 1e9
        ahead = max((s for tt, s in newest if tt <= t), default=seq)
        # waited = how old the frame was when the worker took it: a backlog would grow it
        rows.append(
            {"seq": seq, "latency_s": latency, "work_s": took[seq], "waited_s": latency - took[seq],
             "behind": ahead - seq}
        )  # fmt: skip
    return {
        "rss": rss,
        "labels": rows,
        "depth_fps": len([d for d in tap.depth if start < d[0] <= start + elapsed]) / elapsed,
    }


def check_slow_worker(fig: dict) -> None:
    rows = fig["labels"]
    assert len(rows) >= 3, fig
    work = [r["work_s"] for r in rows]
    assert statistics.median(work) * fig["depth_fps"] > 3, (
        "the worker is not slower than the sensor"
    )
    for r in rows:  # newest frame: taken fresh, whatever the backlog could have been
        # a queue of even one frame would make a frame wait a whole work time; the slack
        # also covers scheduling stalls of a loaded machine (0.9 s seen on 2 busy cores)
        slack = max(0.5, r["work_s"] / 2)
        assert r["waited_s"] < slack, r
        assert r["behind"] <= (r["work_s"] + slack) * fig["depth_fps"], r
    rss = [w for t, w, _ in fig["rss"] if t >= 5.0]  # after the CRF's first allocations
    head, tail = max(rss[: len(rss) // 2]), max(rss[len(rss) // 2 :])
    assert tail - head < 30, f"worker RSS grows: {head:.0f} -> {tail:.0f} MB"


@pytest.mark.slow
def test_a_worker_slower_than_the_sensor_stays_on_the_newest_frame(run):
    check_slow_worker(watch_slow_worker(run, 15.0, 0.5, "rel3"))


@pytest.mark.slow
@pytest.mark.timeout(900)  # the default 600 s would cut the 600 s soak short
def test_soak_slow_worker_ten_minutes(run):
    """10 minutes of the above; writes its figures to $TOPSEG_SOAK_REPORT when set."""
    seconds = float(os.environ.get("TOPSEG_SOAK_S", 600))
    fig = watch_slow_worker(run, seconds, 5.0, "rel4")
    report = os.environ.get("TOPSEG_SOAK_REPORT")
    if report:
        Path(report).write_text(json.dumps(fig, indent=1))
    check_slow_worker(fig)


def test_sigterm_during_backoff_stops_the_driver_at_once(run, recording):
    port, cell = free_port(), "rel5"
    drv = driver(run, port, cell, f"faulty:fail_opens=100@replay:{recording}")
    wait_for(lambda: len(_delays(drv.err)) >= 4, 30, "a few failed opens")  # ~0.5+1+2+4 s
    t0 = time.monotonic()
    assert drv.stop(signal.SIGTERM) == 0, drv.err
    assert time.monotonic() - t0 < 3.0
