"""Interrupted datagen and training, with real signals to real processes: SIGINT (Ctrl-C:
the terminal signals the whole process group) and kill -9, then the same command again.
The rerun finishes what was left, the result equals an uninterrupted run with the same seed,
and no partial file (a torn tree part, a killed write's temp file, a half-written chunk) is
ever taken as whole."""

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from netutil import wait_for
from test_datagen_cli import assert_frames_whole, datagen_args, env, n_complete

from topseg.core import forest
from topseg.core.formats import dataset as D

TRAIN = ["--trees", "3", "--depth", "10", "--frames-per-tree", "10", "--pixels-per-frame", "400",
         "--features", "40", "--responses", "20", "--thresholds", "20", "--seed", "3"]  # fmt: skip


def topseg(*args, **kw) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "topseg.services.cli", *map(str, args)]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300, **kw)


def ctrl_c_default() -> None:
    """In the child before exec: SIGINT back to its default. A background job of a
    non-interactive shell (`make test &`, nohup, some CI runners) inherits SIGINT ignored,
    and Python then installs no KeyboardInterrupt handler: Ctrl-C would do nothing."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def start(*args, **kw) -> subprocess.Popen:
    """A command in its own process group (so the test can signal it as a terminal would)."""
    cmd = [sys.executable, "-m", "topseg.services.cli", *map(str, args)]
    return subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
        preexec_fn=ctrl_c_default, **kw,
    )  # fmt: skip


@contextlib.contextmanager
def group_reaped(proc: subprocess.Popen):
    """Kill whatever is left of the process group at the end, pass or fail."""
    try:
        yield proc
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(30)


@pytest.fixture(scope="module")
def whole_model(data, tmp_path_factory):
    """The model of an uninterrupted serial run."""
    out = tmp_path_factory.mktemp("whole") / "m.npz"
    r = topseg("train", "--data", data, "--out", out, "--serial", *TRAIN)
    assert r.returncode == 0, r.stderr
    return forest.load_model(out)[0]


def assert_same_forest(path: Path, whole) -> None:
    got, _ = forest.load_model(path)
    for name, arr in got.arrays().items():
        np.testing.assert_array_equal(arr, whole.arrays()[name], err_msg=name)


@pytest.mark.slow
def test_training_interrupted_by_ctrl_c_resumes_to_the_same_model(data, tmp_path, whole_model):
    out = tmp_path / "m.npz"
    parts = tmp_path / "m.npz.parts"
    with group_reaped(start("train", "--data", data, "--out", out, "--serial", *TRAIN)) as proc:
        wait_for(lambda: (parts / "tree-0.npz").exists() or proc.poll() is not None, 120, "tree 0")
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C, while tree 1 trains
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert err.strip().splitlines()[-1] == "topseg: interrupted" and "Traceback" not in err
    assert not out.exists()
    assert not (parts / "tree-2.npz").exists(), "finished before the interrupt: too fast a test"

    # what a kill -9 in the middle of writing tree 1's part would leave: a torn temp file,
    # and (had the write not been atomic) a torn part: neither may be taken as a tree
    whole_part = (parts / "tree-0.npz").read_bytes()
    (parts / ".tree-1.npz.x1y2z3.tmp").write_bytes(whole_part[: len(whole_part) // 2])
    (parts / "tree-1.npz").write_bytes(whole_part[: len(whole_part) // 3])

    r = topseg("-v", "train", "--data", data, "--out", out, "--serial", *TRAIN)
    assert r.returncode == 0, r.stderr
    assert "resuming: 1 of 3 trees already trained" in r.stderr
    assert "discarding damaged part" in r.stderr and "tree-1.npz" in r.stderr
    assert_same_forest(out, whole_model)
    assert not parts.exists(), list(parts.iterdir())


def _kill_after_first_tree(cmd, parts: Path) -> list[str]:
    with group_reaped(start(*cmd)) as proc:
        wait_for(lambda: (parts / "tree-0.npz").exists() or proc.poll() is not None, 180, "tree 0")
        os.killpg(proc.pid, signal.SIGKILL)  # the client (and any Dask workers), no cleanup
    assert proc.returncode == -signal.SIGKILL
    done = sorted(p.name for p in parts.glob("tree-*.npz"))
    assert "tree-0.npz" in done and len(done) < 3, done
    return done


@pytest.mark.parametrize(
    "where",
    [
        pytest.param(("--serial",), id="serial"),
        pytest.param(("--workers", "1"), marks=pytest.mark.slow, id="dask"),
    ],
)
def test_training_killed_with_9_resumes_to_the_same_model(where, data, tmp_path, whole_model):
    out = tmp_path / "m.npz"
    cmd = ("train", "--data", data, "--out", out, *where, *TRAIN)
    done = _kill_after_first_tree(cmd, tmp_path / "m.npz.parts")
    r = topseg("-v", *cmd)
    assert r.returncode == 0, r.stderr
    assert f"resuming: {len(done)} of 3 trees already trained" in r.stderr
    assert_same_forest(out, whole_model)
    assert not (tmp_path / "m.npz.parts").exists()


@pytest.mark.slow
def test_datagen_interrupted_by_ctrl_c_resumes_to_the_same_dataset(tmp_path):
    """The frames are compared with the toy generator's own, which an uninterrupted run
    writes whatever its workers (tests/test_datagen.py)."""
    out, frames = tmp_path / "ds.zarr", 16
    proc = subprocess.Popen(
        datagen_args(out, frames), env=env(TOY_FRAME_S="0.1"), start_new_session=True,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=ctrl_c_default,
    )  # fmt: skip
    with group_reaped(proc):
        deadline = time.monotonic() + 120
        while n_complete(out) < 4 and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C: the client and its Dask workers
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    line = [ln for ln in err.splitlines() if ln.startswith("topseg datagen: interrupted")]
    assert line and "rerun the same command to resume" in line[0], err
    # one line, not the Dask workers' KeyboardInterrupt tracebacks (~65 lines before)
    assert err.strip().splitlines() == line, err
    had = n_complete(out)
    assert 4 <= had < frames

    # a frame whose chunk a killed worker left half-written, never flagged complete
    todo = int(np.flatnonzero(~D.open_dataset(out).complete)[0])
    chunk = out / "depth" / f"c.{todo}.0.0"
    chunk.write_bytes(b"\x28\xb5\x2f\xfd torn")
    chunk.with_name(chunk.name + ".5e1f.partial").write_bytes(b"torn")

    r = subprocess.run(datagen_args(out, frames), env=env(TOY_FRAME_S="0"), capture_output=True,
                       text=True)  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert f"({had} were already complete)" in r.stdout
    assert_frames_whole(out, expect_all=frames)
    assert not list(out.rglob("*.partial"))
