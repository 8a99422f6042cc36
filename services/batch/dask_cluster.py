"""The one way topseg gets a Dask client: `datagen`, `train` and `experiment` all use it.

    with dask_client(scheduler=None, workers=4) as client:   # a local cluster
        client.submit(...)
    with dask_client("tcp://host:8786") as client:          # a running scheduler
        ...

A local cluster is one single-threaded worker process per `workers` (pybullet and the
numba kernels are not shared between threads: processes keep them apart), each allowed
`memory_limit` (Dask's "auto" shares the machine's memory out evenly) and the numba and
BLAS thread pools of cores / workers threads. Leaving the `with` block closes the client
and the cluster it started. A scheduler that cannot be reached within `timeout` seconds is
one TopsegError line. Dask's own log chatter is silenced unless topseg logs at DEBUG
(`-vv`): the caller reports what went wrong itself.

Ctrl-C reaches the whole process group: the local worker processes ignore SIGINT (`dask_setup`,
preloaded into each), so only the client stops (its caller says how far it got) and closes
them; before, each worker printed a 30-line KeyboardInterrupt traceback.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import os
import signal
import threading
from collections.abc import Iterator
from typing import Any

from topseg.core.errors import TopsegError

#: the thread pools each local worker process is limited to (cores / workers threads)
THREAD_ENV = ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def default_workers() -> int:
    """Cores this process may run on: the default number of local worker processes."""
    return max(1, len(os.sched_getaffinity(0)))


@contextlib.contextmanager
def dask_client(
    scheduler: str | None = None,
    workers: int | None = None,
    *,
    memory_limit: str | float | int | None = "auto",
    timeout: float = 10.0,
) -> Iterator[Any]:
    """A `distributed.Client`: on the scheduler at `scheduler`, or on a local cluster of
    `workers` processes (default: one per core), closed (cluster too) when the block ends."""
    import distributed

    quiet = logging.getLogger("topseg").getEffectiveLevel() > logging.DEBUG
    if quiet:
        logging.getLogger("distributed").setLevel(logging.ERROR)
    if scheduler:
        refused = None
        try:
            client = distributed.Client(scheduler, timeout=f"{timeout}s")
        except (OSError, TimeoutError, ValueError) as exc:
            refused = f"cannot reach the Dask scheduler at {scheduler}: {_one_line(exc)}"
        if refused is not None:
            # finalise the half-built Client now, its error and traceback gone: left to the
            # collector, its __del__ ran inside a later cluster's start-up and waited on that
            # cluster's event loop forever
            gc.collect()
            raise TopsegError(refused)
        with client:
            yield client
        return
    if workers is not None and workers < 1:
        raise TopsegError(f"a local Dask cluster needs at least 1 worker, got {workers}")
    n = workers or default_workers()
    threads = str(max(1, default_workers() // n))
    with (
        distributed.LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            memory_limit=memory_limit,
            # no dashboard; the scheduler's HTTP endpoint on a free port, never a fixed one
            dashboard_address=None,
            scheduler_kwargs={"dashboard_address": ":0"},
            # task errors reach the client, which reports them as one line; -vv shows all
            silence_logs=logging.CRITICAL if quiet else logging.DEBUG,
            env=dict.fromkeys(THREAD_ENV, threads),
            preload=[__name__],  # dask_setup below, in each worker process
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        yield client


def dask_setup(worker: Any) -> None:
    """Dask's preload hook, run in each local worker process: ignore SIGINT, which the
    terminal sends to the whole process group; the client closes the workers itself."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def _one_line(exc: BaseException) -> str:
    """An exception's message on one line (Dask's timeouts span several)."""
    text = " ".join(str(exc).split())
    return text or type(exc).__name__
