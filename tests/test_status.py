"""`topseg status` against a real driver (synthetic source) and worker on loopback Zenoh."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
from netutil import free_port, wait_for

from topseg.services.live import status

MODEL = Path(__file__).resolve().parent.parent / "models" / "default.npz"


def topseg_status(port, *args, timeout=3.0):
    """Run `topseg status` as a process; (exit status, stdout)."""
    cmd = [sys.executable, "-m", "topseg.services.cli", "status", "--zenoh-port", str(port)]
    cmd += ["--timeout", str(timeout), *args]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert done.returncode in (0, 1), done.stderr
    return done.returncode, done.stdout


@pytest.mark.slow
def test_status_shows_driver_and_worker_alive_then_the_killed_worker_down(run):
    port, cell = free_port(), "st1"
    worker = run("worker", "--model", MODEL, "--cameras", f"{cell}/cam0", "--zenoh-port", port)
    driver = run(
        "driver", "--cell", cell, "--source", "synthetic", "--fps", "5", "--zenoh-port", port
    )
    worker.wait_line("worker ready", 120)
    driver.wait_line("publishing", 120)

    tap = run.tap(port, cell)  # the test's own look at the stats, to start when labels flow
    wait_for(lambda: len(tap.stats) >= 2, 120, "two stats messages from the worker")

    for window in (3, 6, 12, 24):  # on a loaded machine a frame can take longer than 3 s
        rc, out = topseg_status(port, "--json", "--cell", cell, timeout=window)
        rep = json.loads(out)
        cams = rep["cameras"]
        if cams and cams[0]["worker"]["stats_messages"] >= 1:
            break
    assert rc == 0 and rep["ok"], out
    cam = cams[0]
    assert (cam["cell"], cam["camera"], cam["problems"]) == (cell, "cam0", [])
    assert len(cams) == 1, out
    assert cam["driver"]["alive"] and cam["driver"]["source"] == "synthetic"
    assert cam["driver"]["reconnects"] == 0 and cam["driver"]["frames"] > 0
    w = cam["worker"]
    assert w["alive"] and w["fps"] > 0 and w["model"] == "default.npz"
    assert 0 < w["latency_ms"]["p50"] <= w["latency_ms"]["p99"]
    assert w["processed"] > 0 and w["rejected"] == 0

    worker.kill()  # kill -9: no goodbye, its token goes with its link
    rc, out = topseg_status(port, "--cell", cell)
    assert rc == 1, out
    row = next(line for line in out.splitlines() if line.startswith(f"{cell}/cam0 "))
    assert row.split()[1] == "alive" and row.split().count("DOWN") == 1  # driver up, worker not
    assert f"{cell}/cam0: worker DOWN" in out and "PROBLEM" in out
    assert driver.alive()


def test_status_with_nothing_running_says_so_and_fails():
    rc, out = topseg_status(free_port(), timeout=0.5)
    assert rc == 1 and "no topseg service answered" in out


def test_expected_camera_with_nothing_up_is_down():
    rep = status.report(status.Observed(window_s=1.0), [("c", "cam9")])
    assert not rep["ok"] and rep["cameras"][0]["problems"] == ["driver DOWN", "worker DOWN"]
    assert "DOWN" in status.format_table(rep)


def test_report_from_stats_messages():
    seen = status.Observed(window_s=2.0)
    seen.alive = {("c", "k", "driver"), ("c", "k", "worker"), ("c", "k", "viewer")}
    seen.stats[("c", "k")] = [
        {
            "stamp_ns": i * 100_000_000,
            "model_id": "m",
            "fps": 9.0,
            "timings_ms": {"total": 5.0, "latency": float(10 + i)},
            "counts": {
                "processed": 10 + i,
                "dropped": 2 * i,
                "rejected": 0,
                "small_heads": 3 * i,
                "small_furniture": i,
                "restored_cell_px": 5 * i,
            },
        }
        for i in range(11)
    ]
    seen.info_start[("c", "k")] = (0.0, {"frames": 100, "source": "s", "reconnects": 1})
    seen.info_end[("c", "k")] = (2.0, {"frames": 140, "source": "s", "reconnects": 1})
    rep = status.report(seen)
    cam = rep["cameras"][0]
    assert rep["ok"] and cam["other_roles"] == ["viewer"] and not cam["idle"]
    assert cam["worker"]["fps"] == pytest.approx(10.0)  # 10 frames in 1 s of stamps
    assert cam["worker"]["latency_ms"] == {"p50": 15.0, "p99": 20.0}
    assert cam["worker"]["dropped"] == 20 and cam["worker"]["dropped_in_window"] == 20
    assert cam["worker"]["small_heads"] == 30 and cam["worker"]["small_heads_in_window"] == 30
    assert cam["worker"]["small_furniture"] == 10
    assert cam["worker"]["restored_cell_px"] == 50 and cam["worker"]["not_person_cells"] == 0
    assert cam["driver"]["fps"] == pytest.approx(20.0) and cam["driver"]["reconnects"] == 1


def test_the_one_percentile_is_numpys_inverted_cdf():
    """p50 / p99 of `status` and `pipeline`: nearest rank, always one of the values."""
    import numpy as np

    from topseg.core.metrics import percentile

    rng = np.random.default_rng(0)
    for _ in range(500):
        values = rng.normal(50, 20, size=int(rng.integers(1, 80)))
        if rng.random() < 0.3:
            values = np.round(values)  # ties
        for q in (0, 1, 25, 50, 90, 99, 99.9, 100, float(rng.uniform(0, 100))):
            expected = float(np.percentile(values, q, method="inverted_cdf"))
            assert percentile(list(values), q) == expected
    assert percentile([], 50) is None
    assert status.percentile is percentile


def test_report_and_table_show_floor_share_and_the_mount_in_use():
    seen = status.Observed(window_s=2.0)
    seen.alive = {("c", "k", "driver"), ("c", "k", "worker")}
    mount = {
        "height_mm": 3120.0, "pitch_deg": 3.0, "roll_deg": 4.0, "sensor": "kinect_v2",
        "source": "estimated", "moved": 1,
    }  # fmt: skip
    seen.stats[("c", "k")] = [
        {
            "stamp_ns": i * 100_000_000,
            "timings_ms": {},
            "floor_share": share,
            "mount": mount,
            "counts": {"processed": i, "dropped": 0, "rejected": 0},
        }
        for i, share in enumerate((0.6, 0.7))
    ]
    rep = status.report(seen)
    w = rep["cameras"][0]["worker"]
    assert w["floor_share"] == pytest.approx(0.65) and w["mount"] == mount
    json.dumps(rep)  # --json keeps working
    table = status.format_table(rep)
    head, row = table.splitlines()[:2]
    assert "FLOOR" in head and "MOUNT" in head
    assert "65%" in row and "3.12m 5.0deg est MOVED x1" in row  # tilt of pitch 3, roll 4
    assert status.mount_cell({**mount, "source": "frame", "moved": 0}) == "3.12m 5.0deg frame"


TOKENS = """
import sys, time
from topseg.services.runtime.zenoh_session import open_session
port, n = int(sys.argv[1]), int(sys.argv[2])
s = open_session(port=port)
toks = [s.liveliness().declare_token(f"topseg/flood/cam{i}/alive/worker") for i in range(n)]
print("ready", flush=True)
time.sleep(120)
"""


@pytest.mark.slow
def test_status_returns_within_its_timeout_and_lists_300_tokens():
    """More than 256 tokens fill a liveliness get's default reply channel inside the get call
    (answered from the session's own table), where a blocking channel would hang status for
    ever at 0 % CPU: status lists all 300 tokens and returns within its timeout."""
    import time

    port = free_port()
    holder = subprocess.Popen(
        [sys.executable, "-c", TOKENS, str(port), "300"], stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout.readline().strip() == "ready"
        cmd = [sys.executable, "-m", "topseg.services.cli", "status", "--zenoh-port", str(port)]
        t0 = time.monotonic()
        done = subprocess.run(
            [*cmd, "--timeout", "2", "--json", "--cell", "flood"],
            capture_output=True,
            text=True,
            timeout=30,
        )
        took = time.monotonic() - t0
    finally:
        holder.kill()
        holder.wait()
    assert done.returncode == 1, done.stderr  # no drivers: every camera is DOWN
    rep = json.loads(done.stdout)
    assert len(rep["cameras"]) == 300 and "incomplete" not in rep
    assert all(c["worker"]["alive"] and not c["driver"]["alive"] for c in rep["cameras"])
    assert took < 2 + 1 + 1.5 + 5, took  # window, final queries and grace, process start


def test_a_query_cut_off_at_its_deadline_is_said():
    seen = status.Observed(window_s=1.0, incomplete=["liveliness tokens"])
    seen.alive = {("c", "k", "driver"), ("c", "k", "worker")}
    rep = status.report(seen)
    assert rep["incomplete"] == ["liveliness tokens"]
    assert "query for liveliness tokens did not end in time" in status.format_table(rep)


def test_stats_of_two_workers_are_not_merged_into_one_row():
    seen = status.Observed(window_s=2.0)
    seen.alive = {("c", "k", "driver"), ("c", "k", "worker")}

    def message(instance, i, processed, latency):
        return {
            "stamp_ns": i * 100_000_000,
            "model_id": f"model-{instance}",
            "timings_ms": {"total": 5.0, "latency": latency},
            "counts": {"processed": processed, "dropped": 0, "rejected": 0},
            status.INSTANCE_FIELD: instance,
        }

    # interleaved: w1 labels 10 frames in 1 s, w2 (far behind in its counts) 2 in 0.5 s
    seen.stats[("c", "k")] = [message("w1", i, 100 + i, 10.0) for i in range(11)] + [
        message("w2", i, 5 + i // 2, 90.0) for i in range(5, 10, 2)
    ]
    rep = status.report(seen)
    row = rep["cameras"][0]
    worker = row["worker"]
    assert worker["model"] == "model-w1" and worker["fps"] == pytest.approx(10.0)
    assert worker["processed"] == 110 and worker["processed_in_window"] == 10
    assert worker["latency_ms"] == {"p50": 10.0, "p99": 10.0}  # none of w2's
    assert sorted(worker["instances"]) == ["w1", "w2"]
    assert worker["instances"]["w2"]["processed_in_window"] == 2
    assert not row["ok"] and status.exit_status(rep) == 1
    table = status.format_table(rep)
    assert "c/k: stats from 2 workers; the row shows w1's (others: w2: 2 frames, 5.0 fps)" in table


def test_two_workers_of_one_camera_and_a_waiting_wildcard_worker_are_shown():
    """Tokens name their process: two workers for one camera are a problem (exit 1); a worker
    for every camera with no camera yet is listed as waiting, and an expected camera without
    a worker of its own shows it waiting instead of DOWN."""
    tokens = {
        ("c", "k", "driver", "d1"),
        ("c", "k", "worker", "w1"),
        ("c", "k", "worker", "w2"),
        ("_any", "_any", "worker", "w3"),
    }
    seen = status.observed_tokens(tokens, went_down=set())
    seen.window_s = 2.0
    rep = status.report(seen, [("c", "other")])
    rows = {r["camera"]: r for r in rep["cameras"]}
    assert rows["k"]["duplicates"] == {"worker": ["w1", "w2"]} and not rows["k"]["ok"]
    assert rows["other"]["waiting"] and not rows["other"]["ok"]
    assert rep["any_camera_workers"] == [{"instance": "w3", "cameras": 0}]
    assert status.exit_status(rep) == 1
    table = status.format_table(rep)
    assert "c/k: 2 workers: w1, w2" in table
    assert "worker w3 serves every camera: waiting for a first depth frame" in table
    assert "c/other: no worker labels it yet" in table and "c/other: worker DOWN" not in table


def test_text_from_the_wire_is_printed_escaped_and_short():
    """A stats message's model id and a driver's info with escape codes, carriage returns
    and newlines, printed raw, would forge rows on the operator's terminal (and a `frames`
    that is not a number would crash status): every such text is printed escaped and cut
    short."""
    import threading
    import time

    from topseg.core.formats import wire
    from topseg.services.runtime.zenoh_session import open_session

    port, cell = free_port(), "esc"
    forged_row = f"\r\x1b[2K{cell}/cam0  alive  alive  30.0  1/1  9  0  0"
    model = f"m\x1b[31m{forged_row}\nall cameras up (window 3.0 s)\x1b]0;owned\x07"
    info = {
        "source": "synthetic\x1b[2J\x1b[H" + "x" * 5000,
        "frames": "many",
        "reconnects": "\x1b[1A",
        "last_error": "\r\n".join(["gone"] * 500),
        "instance": "d1",
    }
    session = open_session(port=port)
    stop = threading.Event()
    try:
        liveliness = session.liveliness()
        tokens = [  # held while status runs
            liveliness.declare_token(wire.alive_key(cell, "cam0", role, role[0] + "1"))
            for role in ("driver", "worker")
        ]
        session.declare_queryable(
            wire.info_key(cell, "cam0"),
            lambda q: q.reply(wire.info_key(cell, "cam0"), json.dumps(info).encode()),
        )
        stats = session.declare_publisher(wire.stats_key(cell, "cam0"))

        def publish():
            processed = 0
            while not stop.wait(0.05):
                processed += 1
                message = {
                    "stamp_ns": time.time_ns(),
                    "role": "worker",
                    "model_id": model,
                    "timings_ms": {"total": 1.0},
                    "counts": {"processed": processed, "dropped": 0, "rejected": 0},
                }
                stats.put(wire.encode_stats(message), attachment=b"w1")

        threading.Thread(target=publish, daemon=True).start()
        rc, out = topseg_status(port, "--cell", cell)
        for token in tokens:
            token.undeclare()
    finally:
        stop.set()
        session.close()
    assert rc == 0, out
    assert not {"\x1b", "\r", "\x07"} & set(out), repr(out)
    lines = out.splitlines()
    assert sum("all cameras up" in line for line in lines) == 1, out  # the verdict only
    assert all(len(line) < 400 for line in lines), out
    row = next(line for line in lines if line.startswith(f"{cell}/cam0 "))
    assert "m\\x1b[31m\\r\\x1b[2K" in row and "synthetic\\x1b[2J" in row, row
    error = next(line for line in lines if "driver's last error" in line)
    assert error.startswith(f"{cell}/cam0: driver's last error: gone\\r\\ngone"), error
    assert error.endswith("..."), error


def test_seq_resets_jumps_and_stamps_off_the_clock_are_shown_when_they_grew():
    seen = status.Observed(window_s=2.0)
    seen.alive = {("c", "k", "driver"), ("c", "k", "worker")}
    seen.stats[("c", "k")] = [
        {
            "stamp_ns": i * 100_000_000,
            "timings_ms": {"total": 5.0},
            "counts": {
                "processed": 10 + i, "dropped": 0, "rejected": 0,
                "seq_resets": 3, "seq_jumps": 4 + i, "stamps_out_of_window": 2 * i,
            },
        }
        for i in range(3)
    ]  # fmt: skip
    rep = status.report(seen)
    row = rep["cameras"][0]
    w = row["worker"]
    assert (w["seq_resets"], w["seq_jumps"], w["stamps_out_of_window"]) == (3, 6, 4)
    assert (w["seq_resets_in_window"], w["seq_jumps_in_window"]) == (0, 2)
    assert w["stamps_out_of_window_in_window"] == 4
    assert row["ok"] and status.exit_status(rep) == 0  # said, not a failure
    table = status.format_table(rep)
    assert "c/k: the depth's seq jumped ahead 2 times" in table
    assert (
        "c/k: 4 depth frames stamped over 1 s ahead of or 60 s behind the worker's clock" in table
    )
    assert "started again" not in table  # no reset in the window
