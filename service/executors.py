"""Where analyses run: the local process pool (default) or a Dask distributed cluster.

The scheduler needs only the ``concurrent.futures`` interface: ``submit``
returning a future with ``result(timeout)`` and ``cancel()``, and
``shutdown``.  :class:`DaskExecutor` gives a ``distributed.Client`` exactly
that, so the same scheduler code ships :func:`service.analysis.analyse_window`
(a module-level function of plain arguments) to the workers of a cluster;
workers need the ``loopwatch`` package installed, as the Docker image has.

Faults (issue 10).  A local pool whose worker process dies is broken for
good (``BrokenProcessPool`` for every job in it), and a hung analysis holds
its worker until it ends; :func:`end_executor` kills the workers, and the
scheduler builds a new pool with :func:`make_executor`.  A Dask cluster
needs neither: the nanny restarts a worker that dies and the scheduler of the
cluster runs its tasks again elsewhere (``distributed.scheduler.allowed-failures``,
3 by default, after which the task fails with ``KilledWorker``); a hung task
cannot be killed from the client.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from typing import ParamSpec, TypeVar

from service.config import Settings

__all__ = [
    "ANALYSIS_NICENESS",
    "DaskExecutor",
    "ExecutorError",
    "end_executor",
    "executor_slots",
    "kills_workers",
    "make_executor",
]

P = ParamSpec("P")
T = TypeVar("T")


class ExecutorError(RuntimeError):
    """The configured executor cannot be used; the message says why and what to do."""


class DaskExecutor(Executor):
    """A ``concurrent.futures.Executor`` over the workers of a Dask cluster.

    Parameters
    ----------
    address : str
        The cluster's scheduler, ``tcp://host:8786`` (a ``LocalCluster``'s
        ``scheduler_address`` too).
    connect_timeout_s : float
        How long to wait for the scheduler before giving up.

    Tasks are submitted with ``pure=False``: every call runs (Dask would
    otherwise hash the window arrays to reuse an earlier result).

    Raises
    ------
    ExecutorError
        ``dask.distributed`` is not installed or the scheduler does not answer.
    """

    def __init__(self, address: str, *, connect_timeout_s: float = 30.0) -> None:
        try:
            from distributed import Client
        except ImportError:
            raise ExecutorError(
                "LOOPWATCH_EXECUTOR=dask needs dask.distributed: "
                "pip install 'dask[distributed]'"
            ) from None
        try:
            self.client = Client(address, timeout=connect_timeout_s, set_as_default=False)
        except (OSError, TimeoutError) as exc:
            raise ExecutorError(
                f"cannot reach the Dask scheduler at {address} "
                f"(LOOPWATCH_DASK_SCHEDULER): {exc}"
            ) from None
        self.address = address
        self._executor = self.client.get_executor(pure=False)

    def submit(self, fn: Callable[P, T], /, *args: P.args, **kwargs: P.kwargs) -> Future[T]:
        """Run ``fn(*args, **kwargs)`` on a worker of the cluster."""
        future: Future[T] = self._executor.submit(fn, *args, **kwargs)
        return future

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """Wait for (or cancel) the submitted tasks, then disconnect from the cluster.

        The cluster itself keeps running: it belongs to the deployment.
        """
        self._executor.shutdown(wait=wait and not cancel_futures)
        self.client.close()


ANALYSIS_NICENESS = 10
"""The analysis processes run at a lower CPU priority: on a busy machine the requests
(and ingest) of the API process go first, the analyses take longer."""


def make_executor(settings: Settings) -> Executor:
    """The executor ``settings`` select: ``process`` (``workers`` local processes, at
    :data:`ANALYSIS_NICENESS`) or ``dask`` (the cluster at ``dask_scheduler``).

    The scheduler's rounds ran at the API's priority: the first round of 2,000 loops
    took both cores from the requests for its first 10-30 s (issue 20's load benchmark).
    """
    if settings.executor == "dask":
        assert settings.dask_scheduler is not None  # checked by Settings
        return DaskExecutor(settings.dask_scheduler,
                            connect_timeout_s=settings.dask_connect_timeout_s)
    return ProcessPoolExecutor(max_workers=settings.workers, initializer=os.nice,
                               initargs=(ANALYSIS_NICENESS,))


def executor_slots(executor: Executor, default: int) -> int:
    """How many analyses ``executor`` runs at once: the worker threads of a Dask cluster
    now, otherwise ``default`` (the configured pool size)."""
    if isinstance(executor, DaskExecutor):
        return max(1, sum(executor.client.nthreads().values()))
    return default


def kills_workers(executor: Executor) -> bool:
    """True when :func:`end_executor` ends ``executor``'s running jobs: a local process pool.

    Threads cannot be killed, and a Dask cluster's workers are not ours to kill.
    """
    return isinstance(executor, ProcessPoolExecutor)


def end_executor(executor: Executor) -> None:
    """Shut ``executor`` down without waiting; a process pool's workers are killed first,
    so a hung analysis ends with them (its futures fail with ``BrokenProcessPool``)."""
    if isinstance(executor, ProcessPoolExecutor):
        # Python 3.14 has ProcessPoolExecutor.kill_workers(); 3.11 only the private map
        for process in list((executor._processes or {}).values()):
            process.kill()
    executor.shutdown(wait=False, cancel_futures=True)
