"""Analyses on the executor: at most two per worker slot in flight, each with its time
limit, and one retry for a try lost to a dead or hung worker (issue 10; see
:mod:`service.scheduler`)."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, BrokenExecutor, Executor, Future, wait
from dataclasses import dataclass
from typing import Any, Literal

from service.config import Settings
from service.executors import end_executor, executor_slots, kills_workers
from service.metrics import Metrics

__all__ = ["MAX_TRIES", "AnalysisJob", "JobOutcome", "JobRunner"]

log = logging.getLogger(__name__)

IN_FLIGHT_PER_SLOT = 2
"""Analyses submitted per worker slot: one running, one queued, so no worker idles."""

MAX_TRIES = 2
"""Tries of an analysis whose worker died or hung: the first and one retry (issue 10)."""


@dataclass(frozen=True)
class JobOutcome:
    """How one analysis ended: ``ok`` with its result, or ``failed``/``timeout`` with why."""

    status: str
    result: dict[str, Any] | None = None
    error: str | None = None


@dataclass(eq=False)
class AnalysisJob:
    """One analysis for the executor, its tries lost to a dead or hung worker, and where
    its outcome goes."""

    label: str
    fn: Callable[..., dict[str, Any]]
    args: tuple[Any, ...]
    finish: Callable[[JobOutcome], None]
    lost_tries: int = 0
    deadline: float = math.inf
    submitted: float = math.inf  # time.monotonic() of the last submission

    @property
    def kind(self) -> str:
        """``loop`` or ``unit``: the first word of the label (the metrics' label)."""
        return self.label.split(" ", 1)[0]


class JobRunner:
    """Runs analysis jobs on an executor built by ``executor_factory``, and on a new one
    whenever a dead or hung worker has cost the current one
    (:func:`service.executors.make_executor`)."""

    def __init__(self, *, executor_factory: Callable[[], Executor], settings: Settings,
                 metrics: Metrics) -> None:
        self.executor_factory = executor_factory
        self.executor = executor_factory()
        self.settings = settings
        self.metrics = metrics

    def run(self, jobs: Iterator[AnalysisJob], halted: Callable[[], bool]) -> None:
        """Run ``jobs`` on the executor, at most :data:`IN_FLIGHT_PER_SLOT` per worker slot at
        a time, each with the time limit from its submission; a job whose worker died or hung
        is tried once more.  ``jobs`` is drawn as room frees up, so only the windows in
        flight are held in memory; once ``halted()`` no job is submitted any more."""
        limit = IN_FLIGHT_PER_SLOT * executor_slots(self.executor, self.settings.workers)
        again: list[AnalysisJob] = []  # retried or restarted: submitted before new jobs
        in_flight: dict[Future[dict[str, Any]], AnalysisJob] = {}
        drawing = True
        began = time.monotonic()
        while True:
            if halted():
                drawing = False  # stopping or deposed: the next leader completes the round
                again.clear()
            while len(in_flight) < limit and (again or drawing):
                job = again.pop(0) if again else next(jobs, None)
                if job is None:
                    drawing = False
                    break
                job.submitted = time.monotonic()
                job.deadline = job.submitted + self.settings.analysis_timeout_s
                if not job.lost_tries:
                    self.metrics.observe("loopwatch_analysis_queue_seconds",
                                         job.submitted - began, kind=job.kind)
                in_flight[self.executor.submit(job.fn, *job.args)] = job
            if not in_flight:
                return
            first_deadline = min(job.deadline for job in in_flight.values())
            done, _ = wait(in_flight, timeout=max(0.0, first_deadline - time.monotonic()),
                           return_when=FIRST_COMPLETED)
            broken = [job for future in done
                      if (job := self._collect(future, in_flight.pop(future))) is not None]
            if broken:  # the pool is broken for good: whatever else it held is lost too
                broken += self._take_unfinished(in_flight)
                self._replace_executor("a worker process died")
                for job in broken:
                    self._lose(job, "worker_died", "its worker process died", again)
                continue
            hung = [future for future, job in in_flight.items()
                    if job.deadline <= time.monotonic()]
            if not hung:
                continue
            timed_out = [in_flight.pop(future) for future in hung]
            for future in hung:
                future.cancel()
            if kills_workers(self.executor):  # end the hung worker with its pool
                again += self._take_unfinished(in_flight)  # not their fault: no try lost
                self._replace_executor(f"{', '.join(job.label for job in timed_out)} hung")
            for job in timed_out:
                self._lose(job, "timeout", "analysis took longer than "
                                           f"{self.settings.analysis_timeout_s:g} s", again)

    def _collect(self, future: Future[dict[str, Any]], job: AnalysisJob) -> AnalysisJob | None:
        """Pass a finished job's outcome on (its duration to the histogram); the job back if
        its worker process died."""
        try:
            result = future.result(timeout=0)
        except BrokenExecutor:
            return job
        except Exception as exc:  # a failing analysis must not stop the others
            error = f"{type(exc).__name__}: {exc}"
            log.warning("analysis of %s failed: %s", job.label, error)
            outcome = JobOutcome("failed", error=error)
        else:
            outcome = JobOutcome("ok", result)
        self.metrics.observe("loopwatch_analysis_duration_seconds",
                             time.monotonic() - job.submitted, kind=job.kind)
        job.finish(outcome)
        return None

    def _take_unfinished(self, in_flight: dict[Future[dict[str, Any]], AnalysisJob]
                         ) -> list[AnalysisJob]:
        """Empty ``in_flight`` of a pool about to be replaced: jobs that have finished pass
        their outcome on, the others are returned to be submitted again."""
        unfinished = [job for future, job in in_flight.items()
                      if not future.done() or self._collect(future, job) is not None]
        in_flight.clear()
        return unfinished

    def _replace_executor(self, why: str) -> None:
        """Kill the executor's workers and build a new executor with the factory."""
        end_executor(self.executor)
        self.executor = self.executor_factory()
        self.metrics.inc("loopwatch_executor_replacements_total")
        log.warning("analysis executor replaced: %s", why)

    def _lose(self, job: AnalysisJob, cause: Literal["worker_died", "timeout"], reason: str,
              again: list[AnalysisJob]) -> None:
        """A try of ``job`` lost to a dead or hung worker: try once more, or store why not."""
        job.lost_tries += 1
        if job.lost_tries < MAX_TRIES:
            self.metrics.inc("loopwatch_analysis_retries_total", cause=cause)
            log.warning("%s: %s; trying it once more", job.label, reason)
            again.append(job)
            return
        status = "timeout" if cause == "timeout" else "failed"
        log.warning("%s: %s, on its retry too", job.label, reason)
        job.finish(JobOutcome(status, error=f"{reason}, on its retry too"))
