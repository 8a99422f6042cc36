"""Signals an operator sends, to real processes: Ctrl-C (SIGINT to the process group, as a
terminal sends it) during `topseg segment`, and SIGTERM again and again while a worker
shuts down. (Ctrl-C during datagen and train: tests/test_reliability_resume.py.)"""

import os
import signal
import time
from pathlib import Path

import pytest
from netutil import Services, free_port, wait_for
from test_reliability_resume import group_reaped, start

from topseg.core.formats import wire

ROOT = Path(__file__).resolve().parent.parent
MODEL = ROOT / "models" / "default.npz"
DEMO = ROOT / "recordings" / "demo.mcap"


@pytest.mark.slow
def test_ctrl_c_during_segment_says_what_was_written_and_exits_130(tmp_path):
    """Not numba's `SystemError` (a KeyboardInterrupt raised inside compiled code) and
    exit 1: the frame at hand is finished and the run stops there."""
    out = tmp_path / "out"
    proc = start("segment", DEMO, "--out", out, "--crf", "exact")
    with group_reaped(proc):
        wait_for(lambda: len(list(out.glob("*_labels.png"))) >= 1 or proc.poll() is not None,
                 300, "a first frame written")  # fmt: skip
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C
        stdout, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, stdout + err
    assert "Traceback" not in err and "SystemError" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("topseg segment: interrupted; "), err
    n = int(lines[0].split("interrupted; ")[1].split(" of ")[0])
    assert lines[0].endswith(f"{n} of 300 frames written to {out} (each with its overlay)")
    assert 1 <= n < 300 and f"segmented {n} frames into {out}" in stdout
    # every frame written is whole (labels and overlay), nothing else is left
    labels = sorted(p.name[: -len("_labels.png")] for p in out.glob("*_labels.png"))
    overlays = sorted(p.name[: -len("_overlay.png")] for p in out.glob("*_overlay.png"))
    assert labels == overlays and len(labels) == n
    assert len(list(out.iterdir())) == 2 * n


def test_sigterm_again_and_again_while_the_worker_stops_still_undeclares_and_exits_0():
    """A second SIGTERM during the shut-down (an impatient operator, `docker stop` after
    systemd's stop) once killed the worker with 143 before its clean-up."""
    run = Services()
    try:
        port, cell = free_port(), "sig"
        tap = run.tap(port, cell)
        tokens: set = set()
        tap.session.liveliness().declare_subscriber(
            f"topseg/{cell}/*/alive/**",
            lambda s: (tokens.discard if str(s.kind).endswith("DELETE") else tokens.add)(
                str(s.key_expr)
            ),
            history=True,
        )
        cameras = [f"{cell}/cam{i}" for i in range(20)]  # more to undeclare on the way out
        wk = run("worker", "--model", MODEL, "--crf", "none", "--cameras", *cameras,
                 "--zenoh-port", port)  # fmt: skip
        wk.wait_line("worker ready", 120)
        wait_for(lambda: len(tokens) == 20, 30, "the worker's 20 tokens")
        sent = 0
        while wk.alive() and sent < 2000:  # SIGTERM every 5 ms until it is gone
            wk.proc.send_signal(signal.SIGTERM)
            sent += 1
            time.sleep(0.005)
        rc = wk.proc.wait(30)
        wk._reader.join(5)
        assert rc == 0, f"exit {rc} after {sent} SIGTERMs:\n{wk.err}"
        assert "Traceback" not in wk.err, wk.err
        wait_for(lambda: not tokens, 10, "every token undeclared")
        assert wire.alive_key(cell, "cam0", "worker") not in tokens
    finally:
        run.close()
