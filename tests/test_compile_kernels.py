"""`topseg compile`: numba's kernels compiled into its cache before their first use."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from topseg.services.cli import main


def first_use(jobs: str) -> str:
    """A script for a fresh process: it runs `jobs` (an expression giving job functions of
    `compile_kernels`) and prints how many of topseg's cached kernels numba had to compile
    for them (cache misses), then their names. One kernel is never cached:
    `crf.exact._gco_label_setter`'s holds a C function's address."""
    return f"""
from numba.core import event
from numba.core.caching import NullCache

misses = []

class Misses(event.Listener):
    def on_start(self, ev):
        pass

    def on_end(self, ev):
        dispatcher = ev.data["dispatcher"]
        func = dispatcher.py_func
        if func.__module__.startswith("topseg") and not isinstance(dispatcher._cache, NullCache):
            misses.append(func.__qualname__)

event.register("numba:compile", Misses())
from topseg.services.cli import compile_kernels

for job in {jobs}:
    job()
print(len(misses), sorted(set(misses)))
"""


#: what the worker, `segment`, `datagen` and `train` run: every job
EVERY_JOB = "(*compile_kernels.JOBS.values(), *compile_kernels.LAST.values())"


def test_an_unknown_job_is_one_line_naming_the_jobs(capsys):
    assert main(["compile", "everything"]) == 2
    err = capsys.readouterr().err
    assert "unknown job 'everything'" in err and "synthesis" in err and "labelling" in err


def test_a_job_reports_what_it_compiled_and_its_time():
    """With the cache `make install` filled: the job runs in its own process and reports."""
    cli = [sys.executable, "-m", "topseg.services.cli", "compile", "crf", "--processes", "1"]
    done = subprocess.run(cli, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "compiling numba kernels (crf)" in done.stdout
    assert "compiled crf kernels in" in done.stdout and "done in" in done.stdout


@pytest.mark.slow  # the synthesis job into an empty cache: ~40 s on 2 cores
def test_a_job_leaves_its_kernels_cached(tmp_path):
    """Afterwards a fresh process renders every sensor's frame without compiling one of
    topseg's kernels."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    cli = [sys.executable, "-m", "topseg.services.cli", "compile", "synthesis"]
    done = subprocess.run(cli, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert any((tmp_path / "numba").rglob("*.nbi")), "nothing was cached"
    script = first_use("(compile_kernels.compile_synthesis,)")
    used = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=600
    )
    assert used.returncode == 0, used.stderr[-2000:]
    assert used.stdout.startswith("0 "), used.stdout


@pytest.mark.slow  # compiles every kernel into an empty cache: ~2 min on 2 cores
def test_after_compile_nothing_is_compiled_on_first_use(tmp_path):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    cli = [sys.executable, "-m", "topseg.services.cli", "compile"]
    done = subprocess.run(cli, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-2000:]
    for job in ("forest", "crf", "training", "synthesis", "labelling"):
        assert f"compiled {job} kernels in" in done.stdout
    used = subprocess.run(
        [sys.executable, "-c", first_use(EVERY_JOB)],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert used.returncode == 0, used.stderr[-2000:]
    assert used.stdout.startswith("0 "), used.stdout
