"""The executors: the local process pool by default, a Dask cluster by configuration.

The Dask tests run a real ``LocalCluster`` with two worker processes and
ship the per-loop pipeline to them; its diagnoses must equal the ones
computed in this process.
"""

import importlib.util
import os
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import pytest
from pydantic import ValidationError

from analytics.synthetic_cases import synthetic_library
from service.analysis import analyse_window
from service.config import Settings
from service.executors import (
    DaskExecutor,
    ExecutorError,
    executor_slots,
    kills_workers,
    make_executor,
)
from tests.servers import free_port, require

pytestmark = pytest.mark.serial  # timing-sensitive: run alone, after the parallel tests

HAS_DASK = importlib.util.find_spec("distributed") is not None


def window_args(case_name: str, samples: int = 3600) -> tuple[Any, ...]:
    case = next(c for c in synthetic_library(samples) if c.name == case_name)
    r = case.simulate()
    loop = {"id": case.name, "process_type": case.process_type}
    return loop, case.ts, r.t, {"op": r.op[0], "pv": r.pv[0], "sp": r.sp[0], "mv": None}


@pytest.fixture(scope="module")
def cluster() -> Iterator[Any]:
    """A LocalCluster of two single-threaded worker processes on loopback."""
    require(HAS_DASK, "dask.distributed is not installed (pip install 'dask[distributed]')")
    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      host="127.0.0.1", dashboard_address=None) as local:
        yield local


def test_the_default_is_a_local_process_pool_of_the_configured_size() -> None:
    executor = make_executor(Settings(workers=3))
    try:
        assert isinstance(executor, ProcessPoolExecutor)
        assert executor_slots(executor, 3) == 3
        assert kills_workers(executor)  # the scheduler replaces it after a dead or hung worker
        assert executor.submit(os.getpid).result(timeout=60) != os.getpid()
    finally:
        executor.shutdown()


def test_dask_needs_the_scheduler_address() -> None:
    with pytest.raises(ValidationError, match="LOOPWATCH_EXECUTOR=dask needs "
                                              "LOOPWATCH_DASK_SCHEDULER"):
        Settings(executor="dask")


def test_an_unreachable_scheduler_is_named_in_the_error() -> None:
    require(HAS_DASK, "dask.distributed is not installed (pip install 'dask[distributed]')")
    address = f"tcp://127.0.0.1:{free_port()}"
    with pytest.raises(ExecutorError, match=f"cannot reach the Dask scheduler at {address}"):
        DaskExecutor(address, connect_timeout_s=2)


def test_the_pipeline_runs_on_the_cluster_workers_with_the_same_result(cluster: Any) -> None:
    settings = Settings(executor="dask", dask_scheduler=cluster.scheduler_address)
    executor = make_executor(settings)
    try:
        assert isinstance(executor, DaskExecutor)
        assert executor_slots(executor, default=99) == 2  # the cluster's threads, not 99
        worker_pids = set(executor.client.run(os.getpid).values())
        assert len(worker_pids) == 2 and os.getpid() not in worker_pids
        assert executor.submit(os.getpid).result(timeout=60) in worker_pids
        cases = ("flow-kano-S4-J2-ts1", "flow-noise-ts1")
        futures = [executor.submit(analyse_window, *window_args(c)) for c in cases]
        remote = [f.result(timeout=120) for f in futures]
    finally:
        executor.shutdown()
    local = [analyse_window(*window_args(c)) for c in cases]
    assert remote == local
    # the healthy loop hardly moves its valve: too little to judge (issue 17)
    assert [d["stiction"]["verdict"] for d in remote] == ["stiction", "undecided"]


def test_shutdown_cancels_what_is_queued_and_leaves_the_cluster_running(cluster: Any) -> None:
    executor = DaskExecutor(cluster.scheduler_address)
    futures = [executor.submit(time.sleep, 5) for _ in range(6)]  # 2 run, 4 wait
    executor.shutdown(wait=False, cancel_futures=True)
    assert sum(f.cancelled() for f in futures) >= 4
    again = DaskExecutor(cluster.scheduler_address)
    try:
        assert again.submit(sum, [1, 2, 3]).result(timeout=60) == 6
    finally:
        again.shutdown()


def die_once(marker: str) -> int:
    """Kill the worker process that runs it the first time; later, its process id."""
    if not os.path.exists(marker):
        Path(marker).touch()
        os._exit(1)
    return os.getpid()


def test_a_task_whose_dask_worker_dies_is_run_again_by_dask(cluster: Any, tmp_path: Path
                                                           ) -> None:
    """Why the scheduler leaves a Dask cluster alone: its nanny restarts the dead worker and
    the cluster's scheduler runs the task again (``allowed-failures``)."""
    executor = DaskExecutor(cluster.scheduler_address)
    try:
        assert not kills_workers(executor)
        marker = tmp_path / "died"
        assert executor.submit(die_once, str(marker)).result(timeout=120) > 0
        assert marker.exists()  # it did die once
        executor.client.wait_for_workers(2, timeout=60)
    finally:
        executor.shutdown()
