"""The one Dask cluster helper (services/batch/dask_cluster.py) that datagen, train and experiment use."""

from __future__ import annotations

import gc
import os
import time

import distributed
import pytest

from topseg.core.errors import TopsegError
from topseg.services.batch.dask_cluster import dask_client


def _worker_env() -> tuple[int, str | None]:
    return os.getpid(), os.environ.get("NUMBA_NUM_THREADS")


def test_a_local_cluster_starts_runs_and_closes():
    with dask_client(workers=2, memory_limit="1GB") as client:
        info = client.scheduler_info(n_workers=-1)["workers"]
        assert len(info) == 2
        assert {w["memory_limit"] for w in info.values()} == {10**9}
        pids = {client.submit(_worker_env, pure=False).result()[0] for _ in range(4)}
        assert os.getpid() not in pids  # processes, not threads of this one
        _, threads = client.submit(_worker_env, pure=False).result()
        assert threads is not None and int(threads) >= 1
        cluster = client.cluster
    assert client.status == "closed"
    assert cluster.status.name == "closed"


def test_an_unreachable_scheduler_is_one_clear_error():
    t0 = time.perf_counter()
    with (
        pytest.raises(
            TopsegError, match=r"^cannot reach the Dask scheduler at tcp://127\.0\.0\.1:9: "
        ) as err,
        dask_client("tcp://127.0.0.1:9", timeout=1),
    ):
        pass
    assert "\n" not in str(err.value)
    assert time.perf_counter() - t0 < 30
    with pytest.raises(TopsegError, match="cannot reach the Dask scheduler at nowhere://x"):
        with dask_client("nowhere://x", timeout=1):
            pass


def test_a_refused_client_is_finalised_at_once():
    """A Client whose connection failed is gone when the error is raised: left to the
    collector, its __del__ ran inside a later local cluster's start-up and hung it."""
    with pytest.raises(TopsegError, match="cannot reach"):
        with dask_client("tcp://127.0.0.1:9", timeout=1):
            pass
    alive = [o for o in gc.get_objects() if isinstance(o, distributed.Client)]
    assert not alive, f"{len(alive)} half-built Client(s) left for the collector"


def test_a_bad_worker_count_is_refused():
    with pytest.raises(TopsegError, match="at least 1 worker"), dask_client(workers=0):
        pass
