"""The analysis scheduler: every interval, each loop's latest window is diagnosed.

Windows are cut from the rolling buffers and submitted to an executor (a
local process pool by default, or a Dask cluster: :mod:`service.executors`).
At most two analyses per worker are in flight, so each loop's result is
awaited with its own time limit counted from its submission, and one slow
or failing analysis never holds up the others.  An analysis that raises is
stored as ``failed`` with the reason.  One whose worker process dies or that
outlives its time limit is tried once more with the same limit (issue 10):
a dead worker leaves a local pool broken, and a hung one holds its process,
so the scheduler kills the pool's workers, builds a new pool with its
executor factory and submits again what the old pool held.  When a worker
died, every job the pool held has lost a try (the pool does not say which
one killed it); after a hang only the hung job has.  A second loss stores
the run as ``failed`` or ``timeout`` with the reason.  Results become
analysis runs, alarms and tickets in one transaction per loop.

After each round's loop analyses every unit with two or more complete loop
windows is diagnosed as a whole (:func:`analytics.plantwide.diagnose_unit`,
thesis chapter 2) on the same executor and stored as a unit analysis run.
Tickets of the loops of a unit of two or more loops are decided only then,
so that the unit's diagnosis can withhold the tickets of valves it clears
(:mod:`service.tickets`).

Scheduled rounds sit on a fixed grid: round ``k`` analyses the windows
ending at ``k * analysis_interval_s`` (UNIX s).  Only the process holding
the scheduler leadership (:mod:`service.leader`) runs rounds, and the store
keeps at most one run per loop and round (``analysis_runs.round_end``).
Before each round the leader reads into its buffers the samples other
processes stored (:meth:`AnalysisScheduler.sync_buffers`).  It then completes
the newest round in the store (a leader that died mid-round leaves loops
without a run) and runs every later round, oldest first; a round whose window
has already left the buffer horizon can no longer be run and is counted in
``loopwatch_rounds_missed_total`` with a warning.  So a failover neither
loses an analysis nor runs one twice; the same holds for unit analyses
(``unit_analysis_runs.round_end``).  :meth:`AnalysisScheduler.run_once` is
the on-demand analysis outside the grid (``round_end`` NULL).
"""

from __future__ import annotations

import itertools
import logging
import math
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, BrokenExecutor, Executor, Future, wait
from dataclasses import dataclass, replace
from functools import partial
from operator import itemgetter
from typing import Any, Literal

import numpy as np
from sqlalchemy import delete, func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from service.alarms import alarm_payload, expire_shelves, update_alarms_from_analysis
from service.analysis import (
    UnitWindows,
    UnitWindowsError,
    analyse_unit,
    analyse_window,
    stiction_pattern_text,
    unit_model_spec,
    unit_windows,
    valve_decisions,
)
from service.buffer import LoopBuffers
from service.config import LoopConfig, PlantConfig, Settings
from service.executors import end_executor, executor_slots, kills_workers
from service.ingest import purge_samples
from service.leader import Election, instance_name
from service.metrics import Metrics
from service.notifications import Outbox
from service.plant import PlantRegistry
from service.store.db import Store
from service.store.models import AnalysisRun, IngestLog, Sample, UnitAnalysisRun
from service.tickets import evidence_from_run, ticket_payload, update_ticket_from_analysis
from service.verdicts import latest_unit_decision, previous_size_windows, settle_run

__all__ = ["MAX_TRIES", "SYNC_OVERLAP_S", "AnalysisScheduler", "RunSummary"]

log = logging.getLogger(__name__)

PURGE_INTERVAL_S = 3600.0
"""How often samples past the retention period are deleted."""

SYNC_OVERLAP_S = 120.0
"""Each buffer sync looks again at the ingest transactions received this long before the
previous sync: one that committed up to two minutes after its time stamp is still read."""

IN_FLIGHT_PER_SLOT = 2
"""Analyses submitted per worker slot: one running, one queued, so no worker idles."""

MAX_TRIES = 2
"""Tries of an analysis whose worker died or hung: the first and one retry (issue 10)."""

HISTORY_ROUNDS_PER_WINDOW = 4
"""History rounds per window length (:meth:`AnalysisScheduler.due_rounds`): the runs
between two confirmations on separate windows must find stiction too."""

HISTORY_WINDOW_COVERED = 0.9
"""Share of a window the buffers must hold before a new installation analyses it as
history (:meth:`AnalysisScheduler.due_rounds`); the data quality screen judges the rest."""


@dataclass(frozen=True)
class RunSummary:
    """What one scheduled analysis of one loop produced."""

    loop_id: str
    run_id: int
    status: str
    verdict: str | None
    ticket_id: int | None


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


def grid_rounds(last: float | None, now: float, interval_s: float) -> list[float]:
    """The round ends due at ``now``: ``last`` (to complete it) and every grid time after it.

    With no ``last`` only the newest grid time ``floor(now / interval_s) * interval_s``.

    >>> grid_rounds(None, 125.0, 60.0), grid_rounds(60.0, 185.0, 60.0)
    ([120.0], [60.0, 120.0, 180.0])
    """
    newest = math.floor(now / interval_s)
    if last is None:
        return [newest * interval_s]
    return [last] + [k * interval_s for k in range(math.floor(last / interval_s) + 1, newest + 1)]


class AnalysisScheduler:
    """Runs the pipeline on every loop each ``settings.analysis_interval_s``.

    ``executor_factory`` builds the executor, and a new one whenever a dead or
    hung worker has cost the current one (:func:`service.executors.make_executor`);
    ``election`` None means this process always leads (a single process);
    ``instance`` names the process in ``analysis_runs.scheduled_by``.
    """

    def __init__(
        self,
        *,
        store: Store,
        registry: PlantRegistry,
        buffers: LoopBuffers,
        settings: Settings,
        executor_factory: Callable[[], Executor],
        metrics: Metrics,
        clock: Callable[[], float] = time.time,
        outbox: Outbox | None = None,
        election: Election | None = None,
        instance: str | None = None,
    ) -> None:
        self.store = store
        self.registry = registry
        self.buffers = buffers
        self.settings = settings
        self.executor_factory = executor_factory
        self.executor = executor_factory()
        self.metrics = metrics
        self.clock = clock
        self.outbox = outbox
        self.election = election
        self.instance = instance or instance_name()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_purge = -float("inf")
        self._synced_until: float | None = None
        self._log_mark = -math.inf  # newest ingest_log.received_at read by a sync
        # the units of the plant object they were read from (the registry replaces it on
        # change): every stored run asks for its unit's loops
        self._units_of: tuple[PlantConfig | None, dict[str, list[LoopConfig]]] = (None, {})

    @property
    def leading(self) -> bool:
        """True while this process is the scheduler that runs rounds."""
        return self.election is None or self.election.is_leader

    def maintain(self, now: float) -> None:
        """Housekeeping before each round: end shelves that ran out, and purge samples
        older than the retention period (at most once an hour)."""
        with self.store.session() as session:
            expired = expire_shelves(session, now=now)
            if now - self._last_purge >= PURGE_INTERVAL_S:
                retention_s = self.settings.sample_retention_days * 86400.0
                purged = purge_samples(session, now - retention_s)
                session.execute(  # log rows older than the horizon have been read
                    delete(IngestLog).where(IngestLog.received_at < now - self.buffers.horizon_s)
                )
                self._last_purge = now
                self.metrics.inc("loopwatch_samples_purged_total", purged)
        if expired:
            log.info("%d shelved alarm(s) returned after their shelve ran out", len(expired))

    def sync_buffers(self, now: float) -> int:
        """Read into the rolling buffers what other processes stored since the last sync.

        Ingest logs every transaction in ``ingest_log``: when it was received
        and the time span of the samples it stored.  A sync takes the log rows
        received since the previous sync (less :data:`SYNC_OVERLAP_S`, for
        transactions that committed late) and reads every sample stamped from
        their earliest first time on (at most a horizon back), so late samples
        and historian backfills reach the analyses too.  The first time, or
        after a pause longer than the horizon (a standby taking over), the
        buffers are rebuilt from the store over the whole horizon.  Returns
        the number of samples read.
        """
        with self.store.session() as session:
            newest_log = session.scalar(select(func.max(IngestLog.received_at)))
            if self._synced_until is None or now - self._synced_until >= self.buffers.horizon_s:
                read = self.buffers.rebuild_from_store(session, now)
            else:
                since = session.scalar(
                    select(func.min(IngestLog.first_time))
                    .where(IngestLog.received_at > self._log_mark - SYNC_OVERLAP_S)
                )
                read = 0 if since is None else self._read_samples_since(
                    session, max(since, now - self.buffers.horizon_s)
                )
        self._synced_until = now
        if newest_log is not None:
            self._log_mark = max(self._log_mark, newest_log)
        return read

    def _read_samples_since(self, session: Session, since: float) -> int:
        rows = session.execute(
            select(Sample.tag, Sample.time, Sample.value, Sample.good)
            .where(Sample.time >= since).order_by(Sample.tag, Sample.time)
        )
        tags = self.buffers.tags
        read = 0
        for tag, group in itertools.groupby(rows, key=itemgetter(0)):
            if tag in tags:
                _, times, values, good = zip(*group, strict=True)
                self.buffers.append(tag, times, values, good)
                read += len(times)
        return read

    def run_once(self, now: float | None = None) -> list[RunSummary]:
        """Analyse every loop and unit once on the windows ending at ``now`` (on demand, off
        the grid)."""
        now = self.clock() if now is None else now
        self.maintain(now)
        summaries = self._analyse(self.registry.plant.loops, now, round_end=None)
        return self._analyse_units(summaries, now, round_end=None)

    def run_round(self, round_end: float) -> list[RunSummary]:
        """Run the scheduled round ending at ``round_end`` for the loops and units that have no
        run of it, then decide the tickets of the units' loops.

        A loop whose run of this round another scheduler stores first is left
        out of the summaries (the store refuses the second run).
        """
        loops = [loop for loop in self.registry.plant.loops if loop.id not in self._done(round_end)]
        summaries = self._analyse(loops, round_end, round_end=round_end)
        return self._analyse_units(summaries, round_end, round_end=round_end)

    def _done(self, round_end: float) -> set[str]:
        """The loops that have a run of the round ending at ``round_end``."""
        with self.store.session() as session:
            return set(session.scalars(
                select(AnalysisRun.loop_id).where(AnalysisRun.round_end == round_end)
            ))

    def due_rounds(self, now: float) -> list[float]:
        """The rounds to run at ``now``, oldest first (see the module docstring).

        Rounds older than the newest whose window has left the buffer horizon
        are dropped, counted and logged.  A new installation (no scheduled run
        stored) also runs the history it holds (:meth:`_history_rounds`).
        """
        newest = math.floor(now / self.settings.analysis_interval_s)
        with self.store.session() as session:
            last = session.scalar(
                select(func.max(AnalysisRun.round_end))
                .where(AnalysisRun.round_end <= newest * self.settings.analysis_interval_s)
            )
        rounds = grid_rounds(last, now, self.settings.analysis_interval_s)
        oldest_in_buffer = now - (self.buffers.horizon_s - self.settings.window_s)
        runnable = [r for r in rounds[:-1] if r >= oldest_in_buffer] + rounds[-1:]
        missed = len(rounds) - len(runnable)
        if rounds[0] == last and last not in runnable and (
            {loop.id for loop in self.registry.plant.loops} <= self._done(last)
        ):
            missed -= 1  # the newest round in the store was complete: nothing of it is lost
        if missed:
            self.metrics.inc("loopwatch_rounds_missed_total", missed)
            log.warning("%d analysis round(s) between %.0f and %.0f can no longer be run: "
                        "their windows have left the buffer horizon", missed, rounds[0],
                        runnable[0])
        if last is None:
            return self._history_rounds(runnable[0]) + runnable
        return runnable

    def _history_rounds(self, first: float) -> list[float]:
        """Grid rounds before the first round of a new installation whose windows the
        buffers hold (at least :data:`HISTORY_WINDOW_COVERED` of each), oldest first:
        :data:`HISTORY_ROUNDS_PER_WINDOW` per window, back to ``ticket_confirmations - 1``
        windows before ``first``.

        The ticket rule needs stiction found on windows that do not overlap, and
        on every window between them (:mod:`service.tickets`): with these, a
        sticky valve in the history a historian or the demo back-fills gets its
        ticket at start instead of after ``ticket_confirmations`` windows of
        waiting, and a loop whose findings come and go does not.
        """
        start = self.buffers.history_start()
        window, interval = self.settings.window_s, self.settings.analysis_interval_s
        step = math.ceil(window / HISTORY_ROUNDS_PER_WINDOW / interval) * interval
        rounds: list[float] = []
        for k in range(1, (self.settings.ticket_confirmations - 1) * HISTORY_ROUNDS_PER_WINDOW + 1):
            round_end = first - k * step
            if start is None or start > round_end - HISTORY_WINDOW_COVERED * window:
                break
            rounds.insert(0, round_end)
        return rounds

    def run_due(self) -> list[RunSummary]:
        """One turn of the leader: housekeeping, buffer sync, then every due round."""
        now = self.clock()
        self.maintain(now)
        self.sync_buffers(now)
        summaries: list[RunSummary] = []
        for round_end in self.due_rounds(now):
            if self._stop.is_set() or not self.leading:
                break
            summaries += self.run_round(round_end)
        return summaries

    def _window_args(self, loop: LoopConfig, now: float) -> tuple[Any, ...] | None:
        """The arguments of :func:`analyse_window` for the loop's window ending at ``now``,
        less the samples not yet arrived (:meth:`LoopBuffers.arrived_end`); None when the
        window holds no sample."""
        end = self.buffers.arrived_end([loop.id], now, self.settings.analysis_interval_s)
        window = self.buffers.window(loop.id, self.settings.window_s, end)
        signals = {"op": window.op, "pv": window.pv, "sp": window.sp, "mv": window.mv}
        if window.t.size == 0 or all(x is None or not np.isfinite(x).any()
                                     for x in signals.values()):
            return None
        return loop.model_dump(mode="json"), window.ts, window.t, {**signals, "mode": window.mode}

    def _units(self) -> dict[str, list[LoopConfig]]:
        """The plant's units of two or more loops, each with its loops in plant order."""
        plant = self.registry.plant
        if self._units_of[0] is not plant:
            units: dict[str, list[LoopConfig]] = {}
            for loop in plant.loops:
                if loop.unit is not None:
                    units.setdefault(loop.unit, []).append(loop)
            self._units_of = (plant, {unit: loops for unit, loops in units.items()
                                      if len(loops) >= 2})
        return self._units_of[1]

    def _analyse(self, loops: Iterable[LoopConfig], now: float,
                 round_end: float | None) -> list[RunSummary]:
        """Analyse ``loops`` on the windows ending at ``now``; the final verdict, alarms and
        tickets of loops in units of two or more loops wait for their unit's diagnosis
        (:meth:`_analyse_units`)."""
        loops = list(loops)
        order = {loop.id: i for i, loop in enumerate(loops)}
        in_units = {loop.id for members in self._units().values() for loop in members}
        summaries: list[RunSummary] = []

        def finish(loop: LoopConfig, outcome: JobOutcome) -> None:
            summary = self._finish_loop(loop, now, round_end, outcome,
                                        decided=loop.id not in in_units)
            if summary is not None:
                summaries.append(summary)

        def jobs() -> Iterator[AnalysisJob]:
            for loop in loops:
                args = self._window_args(loop, now)
                if args is None:
                    finish(loop, JobOutcome("no_data", error="no samples in the analysis window"))
                    continue
                yield AnalysisJob(f"loop {loop.id}", analyse_window, args, partial(finish, loop))

        self._run_jobs(jobs(), scheduled=round_end is not None)
        return sorted(summaries, key=lambda s: order[s.loop_id])

    def _run_jobs(self, jobs: Iterator[AnalysisJob], *, scheduled: bool) -> None:
        """Run ``jobs`` on the executor, at most :data:`IN_FLIGHT_PER_SLOT` per worker slot at
        a time, each with the time limit from its submission; a job whose worker died or hung
        is tried once more (see the module docstring).  ``jobs`` is drawn as room frees up,
        so only the windows in flight are held in memory."""
        limit = IN_FLIGHT_PER_SLOT * executor_slots(self.executor, self.settings.workers)
        again: list[AnalysisJob] = []  # retried or restarted: submitted before new jobs
        in_flight: dict[Future[dict[str, Any]], AnalysisJob] = {}
        drawing = True
        began = time.monotonic()
        while True:
            if self._stop.is_set() or (scheduled and not self.leading):
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

    def _finish_loop(self, loop: LoopConfig, now: float, round_end: float | None,
                outcome: JobOutcome, *, decided: bool) -> RunSummary | None:
        """Store the loop's run (and, if ``decided``, its alarms and ticket); None when it is
        dropped."""
        if round_end is not None and not self.leading:
            log.warning("leadership lost: the result of loop %s for round %.0f is left to the "
                        "new leader", loop.id, round_end)
            return None
        self.metrics.inc("loopwatch_analyses_total", status=outcome.status)
        try:
            summary = self._store_run(loop, now, outcome, round_end, decided=decided)
        except IntegrityError:
            if round_end is None or not self._round_stored(loop.id, round_end):
                raise
            self.metrics.inc("loopwatch_analyses_duplicate_total")
            log.warning("loop %s, round %.0f: another scheduler stored its run first; "
                        "this result is dropped", loop.id, round_end)
            return None
        return summary

    def _round_stored(self, loop_id: str, round_end: float) -> bool:
        with self.store.session() as session:
            return session.scalar(
                select(AnalysisRun.id)
                .where(AnalysisRun.loop_id == loop_id, AnalysisRun.round_end == round_end)
            ) is not None

    def _store_run(self, loop: LoopConfig, now: float, outcome: JobOutcome,
                   round_end: float | None, *, decided: bool) -> RunSummary:
        """The run with the final verdict on its valve (:func:`settle_run`: the loop's own,
        or its unit's latest decision) and, if ``decided`` (a loop in no unit), its alarms
        and ticket in one transaction."""
        diagnosis = outcome.result
        with self.store.session() as session:
            run = AnalysisRun(
                loop_id=loop.id, started_at=now, finished_at=self.clock(),
                window_start=now - self.settings.window_s, window_end=now,
                status=outcome.status, error=outcome.error,
                round_end=round_end, scheduled_by=None if round_end is None else self.instance,
            )
            if diagnosis is not None:
                run.usable = diagnosis["quality"]["usable"]
                run.oscillating = diagnosis["oscillation"]["detected"]
                run.period_s = diagnosis["oscillation"]["period_s"]
                run.result = diagnosis
                # A unit's latest decision keeps the last word until its diagnosis of this
                # round: the pages never show a cleared valve's own finding in between.
                unit_loops = self._units().get(loop.unit or "", [])
                unit = None if not unit_loops else latest_unit_decision(
                    session, str(loop.unit), {x.id: x.valve_asset or x.id for x in unit_loops})
                settle_run(run, unit, previous_size_windows(session, run))
            session.add(run)
            session.flush()
            ticket_id = None
            if diagnosis is not None and decided:
                ticket_id = self._decide(session, loop, run, now)
            return RunSummary(loop.id, run.id, outcome.status, run.verdict, ticket_id)

    def _decide(self, session: Session, loop: LoopConfig, run: AnalysisRun,
                now: float) -> int | None:
        """The alarms and the ticket rule (:func:`service.tickets.update_ticket_from_analysis`)
        for ``run`` with its final verdict; the id of the ticket opened or updated.  Alarm
        changes and the ticket's event go into the outbox."""
        assert run.result is not None
        changed = update_alarms_from_analysis(
            session, loop.id, oscillating=bool(run.oscillating), usable=bool(run.usable),
            importance=loop.importance, message=self._message(run.result), now=now,
            out_of_service="manual" in run.result and not run.usable,
        )
        if self.outbox is not None:
            for alarm in changed:
                self.outbox.add(session, "alarm.changed", alarm_payload(alarm), now)
        ticket = update_ticket_from_analysis(
            session, loop.id,
            valve_asset=loop.valve_asset or loop.id, location=loop.location or loop.unit,
            verdict=str(run.verdict), evidence=evidence_from_run(run),
            importance=loop.importance,
            confirmations_needed=self.settings.ticket_confirmations, now=now,
        )
        if ticket is None:
            return None
        if self.outbox is not None:
            session.flush()
            self.outbox.add(session, "ticket.changed",
                            ticket_payload(ticket, self.registry.plant.cmms_of(loop.id)), now)
        return ticket.id

    def _analyse_units(self, summaries: list[RunSummary], now: float,
                       round_end: float | None) -> list[RunSummary]:
        """Diagnose each unit of two or more loops (thesis chapter 2) on the windows ending at
        ``now``, unless this round's diagnosis is stored already, then decide the tickets of
        the units' loops; ``summaries`` with the final verdicts and ticket ids filled in.

        Each loop run of a unit gets its final verdict from the unit's latest ``ok``
        diagnosis (:func:`service.verdicts.valve_verdict`), then its alarms and its ticket.
        They are decided for the units that have a loop run or a diagnosis stored by
        this call (once per round, so a ticket closed since is not opened again from the
        same run): a scheduler completing a round whose unit diagnosis its predecessor
        left undone decides them on the round's stored loop runs.
        """
        units = self._units()
        scheduled = round_end is not None
        if not units or (scheduled and not self.leading):
            return summaries
        done = set() if round_end is None else self._units_done(round_end)
        self._run_jobs(self._unit_jobs(units, done, now, round_end), scheduled=scheduled)
        if self._stop.is_set() or (scheduled and not self.leading):
            return summaries  # the next leader decides the tickets of this round
        analysed = {s.loop_id for s in summaries}
        fresh = {unit for unit, loops in units.items() if any(x.id in analysed for x in loops)}
        if round_end is not None:
            fresh |= self._units_done(round_end) - done
        decided: dict[str, tuple[str | None, int | None]] = {}
        runs = self._runs_of_units(units, summaries, round_end)
        for unit_id, loops in units.items():
            if unit_id not in fresh:
                continue
            valves = {loop.id: loop.valve_asset or loop.id for loop in loops}
            for loop in loops:
                if loop.id not in runs:
                    continue
                with self.store.session() as session:
                    run = session.get(AnalysisRun, runs[loop.id])
                    if run is None or run.result is None:
                        continue
                    settle_run(run, latest_unit_decision(session, unit_id, valves),
                               previous_size_windows(session, run))
                    ticket_id = self._decide(session, loop, run, now)
                    decided[loop.id] = run.verdict, ticket_id
        return [replace(s, verdict=decided[s.loop_id][0], ticket_id=decided[s.loop_id][1])
                if s.loop_id in decided else s for s in summaries]

    def _units_done(self, round_end: float) -> set[str]:
        """The units that have a diagnosis of the round ending at ``round_end``."""
        with self.store.session() as session:
            return set(session.scalars(
                select(UnitAnalysisRun.unit_id).where(UnitAnalysisRun.round_end == round_end)
            ))

    def _runs_of_units(self, units: dict[str, list[LoopConfig]], summaries: list[RunSummary],
                       round_end: float | None) -> dict[str, int]:
        """The run of each unit loop to decide its ticket on: the scheduled round's, stored by
        whichever scheduler ran it, or the on-demand run just made."""
        if round_end is None:
            return {s.loop_id: s.run_id for s in summaries}
        loop_ids = [loop.id for loops in units.values() for loop in loops]
        with self.store.session() as session:
            rows = session.execute(
                select(AnalysisRun.loop_id, AnalysisRun.id)
                .where(AnalysisRun.round_end == round_end, AnalysisRun.loop_id.in_(loop_ids))
            )
            return {loop_id: run_id for loop_id, run_id in rows}

    def _unit_jobs(self, units: dict[str, list[LoopConfig]], done: set[str], now: float,
                   round_end: float | None) -> Iterator[AnalysisJob]:
        """A diagnosis job for each unit not in ``done`` with two or more complete windows;
        a unit whose windows cannot go together is stored as failed at once."""
        for unit_id, loops in units.items():
            if unit_id in done:
                continue
            end = self.buffers.arrived_end([loop.id for loop in loops], now,
                                           self.settings.analysis_interval_s)
            windows = unit_windows(self.buffers, loops, self.settings.window_s, end)
            if len(windows.signals) < 2:
                continue
            try:
                ts = windows.ts
            except UnitWindowsError as exc:
                self._finish_unit(unit_id, windows, now, round_end,
                                  JobOutcome("failed", error=str(exc)))
                continue
            config = next((u for u in self.registry.plant.units if u.id == unit_id), None)
            model = unit_model_spec(config, loops, windows)
            yield AnalysisJob(f"unit {unit_id}", analyse_unit, (windows.signals, ts, model),
                              partial(self._finish_unit, unit_id, windows, now, round_end))

    def _finish_unit(self, unit_id: str, windows: UnitWindows, now: float,
                     round_end: float | None, outcome: JobOutcome) -> None:
        """Store the unit's diagnosis (dropped if another scheduler stored it first)."""
        if round_end is not None and not self.leading:
            return
        self.metrics.inc("loopwatch_unit_analyses_total", status=outcome.status)
        sticky, cleared = ([], []) if outcome.result is None else valve_decisions(outcome.result)
        try:
            with self.store.session() as session:
                session.add(UnitAnalysisRun(
                    unit_id=unit_id, started_at=now, finished_at=self.clock(),
                    window_start=now - self.settings.window_s, window_end=now,
                    status=outcome.status, loops=list(windows.signals),
                    incomplete_loops=list(windows.incomplete), sticky_loops=sticky,
                    cleared_loops=cleared, result=outcome.result, error=outcome.error,
                    round_end=round_end,
                    scheduled_by=None if round_end is None else self.instance,
                ))
        except IntegrityError:
            if round_end is None or unit_id not in self._units_done(round_end):
                raise
            self.metrics.inc("loopwatch_analyses_duplicate_total")
            log.warning("unit %s, round %.0f: another scheduler stored its diagnosis first; "
                        "this result is dropped", unit_id, round_end)
            return
        if outcome.status != "ok":
            log.info("diagnosis of unit %s: %s (%s)", unit_id, outcome.status, outcome.error)

    @staticmethod
    def _message(diagnosis: dict[str, Any]) -> str:
        """The alarm message of an analysis, with the final verdict on the valve
        (:func:`service.verdicts.valve_verdict`); a stiction finding names its pattern (a
        stuck valve freezes PV, so it comes with unusable data), a valve the unit's
        diagnosis clears its reason ("cycles because FV-502 sticks")."""
        stiction = diagnosis["stiction"]
        final = diagnosis.get("valve") or stiction
        if final.get("decided_by") == "unit" and final["verdict"] != "stiction":
            pattern = final["reason"]
        else:
            pattern = stiction_pattern_text(stiction["pattern"], stiction["op_travel"])
        valve = f"valve: {final['verdict']}" + ("" if pattern is None else f" ({pattern})")
        if not diagnosis["quality"]["usable"]:
            if final["verdict"] == "stiction":
                return f"data unusable, {valve}"
            return stiction["reason"]  # "data unusable: ..." or why a loop in manual is not judged
        osc = diagnosis["oscillation"]
        if not osc["detected"]:
            return "no oscillation" + ("" if pattern is None else f"; {valve}")
        return f"oscillation, period {osc['period_s']:.0f} s; {valve}"

    def start(self) -> None:
        """Run the due rounds at every grid time in a background thread, while leading.

        The election (if any) is started here and stopped by :meth:`stop`.
        """
        if self.election is not None:
            self.election.start()

        def loop() -> None:
            interval = self.settings.analysis_interval_s
            while not self._stop.is_set():
                if not self.leading:
                    assert self.election is not None
                    self._stop.wait(self.election.period_s)
                    continue
                try:
                    self.run_due()
                except Exception:  # keep scheduling; the next round may succeed
                    log.exception("analysis round failed")
                now = self.clock()
                next_round = (math.floor(now / interval) + 1) * interval
                self._stop.wait(max(0.0, next_round - now))

        self._stop.clear()
        self._thread = threading.Thread(target=loop, name="loopwatch-scheduler", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the background thread (the round in progress finishes) and step down."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=self.settings.analysis_timeout_s + 5)
        if self.election is not None:
            self.election.stop()
