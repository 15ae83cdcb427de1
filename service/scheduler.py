"""The analysis scheduler: every interval, each loop's latest window is diagnosed.

Windows are cut from the rolling buffers and submitted to an executor (a
local process pool by default, or a Dask cluster: :mod:`service.executors`).
At most two analyses per worker are in flight, so each loop's result is
awaited with its own time limit counted from its submission, and one slow
or failing analysis never holds up the others; its run is stored as
``timeout`` or ``failed`` with the reason.  Results become analysis runs,
alarms and tickets in one transaction per loop.

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
loses an analysis nor runs one twice.  :meth:`AnalysisScheduler.run_once` is
the on-demand analysis outside the grid (``round_end`` NULL).
"""

from __future__ import annotations

import itertools
import logging
import math
import threading
import time
from collections.abc import Callable, Iterable
from concurrent.futures import FIRST_COMPLETED, Executor, Future, wait
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass
from operator import itemgetter
from typing import Any

import numpy as np
from sqlalchemy import delete, func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from service.alarms import expire_shelves, update_alarms_from_analysis
from service.analysis import analyse_window
from service.buffer import LoopBuffers
from service.config import LoopConfig, Settings
from service.executors import executor_slots
from service.ingest import purge_samples
from service.leader import Election, instance_name
from service.metrics import Metrics
from service.plant import PlantRegistry
from service.store.db import Store
from service.store.models import AnalysisRun, IngestLog, Sample
from service.tickets import evidence_from_run, update_ticket_from_analysis

__all__ = ["SYNC_OVERLAP_S", "AnalysisScheduler", "RunSummary"]

log = logging.getLogger(__name__)

PURGE_INTERVAL_S = 3600.0
"""How often samples past the retention period are deleted."""

SYNC_OVERLAP_S = 120.0
"""Each buffer sync looks again at the ingest transactions received this long before the
previous sync: one that committed up to two minutes after its time stamp is still read."""

IN_FLIGHT_PER_SLOT = 2
"""Analyses submitted per worker slot: one running, one queued, so no worker idles."""


@dataclass(frozen=True)
class RunSummary:
    """What one scheduled analysis of one loop produced."""

    loop_id: str
    run_id: int
    status: str
    verdict: str | None
    ticket_id: int | None


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
        executor: Executor,
        metrics: Metrics,
        clock: Callable[[], float] = time.time,
        on_ticket: Callable[[int], None] | None = None,
        election: Election | None = None,
        instance: str | None = None,
    ) -> None:
        self.store = store
        self.registry = registry
        self.buffers = buffers
        self.settings = settings
        self.executor = executor
        self.metrics = metrics
        self.clock = clock
        self.on_ticket = on_ticket
        self.election = election
        self.instance = instance or instance_name()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_purge = -float("inf")
        self._synced_until: float | None = None
        self._log_mark = -math.inf  # newest ingest_log.received_at read by a sync

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
        """Analyse every loop once on the window ending at ``now`` (on demand, off the grid)."""
        now = self.clock() if now is None else now
        self.maintain(now)
        return self._analyse(self.registry.plant.loops, now, round_end=None)

    def run_round(self, round_end: float) -> list[RunSummary]:
        """Run the scheduled round ending at ``round_end`` for the loops that have no run of it.

        A loop whose run of this round another scheduler stores first is left
        out of the summaries (the store refuses the second run).
        """
        loops = [loop for loop in self.registry.plant.loops if loop.id not in self._done(round_end)]
        return self._analyse(loops, round_end, round_end=round_end)

    def _done(self, round_end: float) -> set[str]:
        """The loops that have a run of the round ending at ``round_end``."""
        with self.store.session() as session:
            return set(session.scalars(
                select(AnalysisRun.loop_id).where(AnalysisRun.round_end == round_end)
            ))

    def due_rounds(self, now: float) -> list[float]:
        """The rounds to run at ``now``, oldest first (see the module docstring).

        Rounds older than the newest whose window has left the buffer horizon
        are dropped, counted and logged.
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
        return runnable

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

    def _submit(self, loop: LoopConfig, now: float) -> Future[dict[str, Any]] | None:
        """Submit the loop's window ending at ``now``; None when it holds no sample."""
        window = self.buffers.window(loop.id, self.settings.window_s, now)
        signals = {"op": window.op, "pv": window.pv, "sp": window.sp, "mv": window.mv}
        if window.t.size == 0 or all(x is None or not np.isfinite(x).any()
                                     for x in signals.values()):
            return None
        return self.executor.submit(
            analyse_window, loop.model_dump(mode="json"), window.ts, window.t, signals
        )

    def _analyse(self, loops: Iterable[LoopConfig], now: float,
                 round_end: float | None) -> list[RunSummary]:
        """Analyse ``loops`` on the windows ending at ``now``, a bounded number at a time."""
        queue = list(loops)
        order = {loop.id: i for i, loop in enumerate(queue)}
        queue.reverse()  # pop() takes the plant's first loop first
        limit = IN_FLIGHT_PER_SLOT * executor_slots(self.executor, self.settings.workers)
        in_flight: dict[Future[dict[str, Any]], tuple[LoopConfig, float]] = {}
        summaries: list[RunSummary] = []

        def finish(loop: LoopConfig, future: Future[dict[str, Any]] | None,
                   deadline: float) -> None:
            summary = self._finish(loop, now - self.settings.window_s, now, future, now,
                                   deadline, round_end)
            if summary is not None:
                summaries.append(summary)

        while queue or in_flight:
            if self._stop.is_set() or (round_end is not None and not self.leading):
                queue.clear()  # stopping or deposed: the next leader completes the round
            while queue and len(in_flight) < limit:
                loop = queue.pop()
                future = self._submit(loop, now)
                deadline = time.monotonic() + self.settings.analysis_timeout_s
                if future is None:
                    finish(loop, None, deadline)
                else:
                    in_flight[future] = (loop, deadline)
            if not in_flight:
                continue
            first_deadline = min(deadline for _, deadline in in_flight.values())
            done, _ = wait(in_flight, timeout=max(0.0, first_deadline - time.monotonic()),
                           return_when=FIRST_COMPLETED)
            expired = [f for f, (_, deadline) in in_flight.items()
                       if f not in done and deadline <= time.monotonic()]
            for future in [*done, *expired]:
                loop, deadline = in_flight.pop(future)
                finish(loop, future, deadline)
        return sorted(summaries, key=lambda s: order[s.loop_id])

    def _finish(self, loop: LoopConfig, start: float, end: float,
                future: Future[dict[str, Any]] | None, now: float,
                deadline: float, round_end: float | None) -> RunSummary | None:
        diagnosis: dict[str, Any] | None = None
        error = None
        if future is None:
            status, error = "no_data", "no samples in the analysis window"
        else:
            try:
                diagnosis = future.result(timeout=max(0.0, deadline - time.monotonic()))
                status = "ok"
            except FutureTimeout:
                future.cancel()
                status = "timeout"
                error = f"analysis took longer than {self.settings.analysis_timeout_s:g} s"
            except Exception as exc:  # a worker's failure must not stop the other loops
                status, error = "failed", f"{type(exc).__name__}: {exc}"
                log.warning("analysis of loop %s failed: %s", loop.id, error)
        if round_end is not None and not self.leading:
            log.warning("leadership lost: the result of loop %s for round %.0f is left to the "
                        "new leader", loop.id, round_end)
            return None
        self.metrics.inc("loopwatch_analyses_total", status=status)
        try:
            summary = self._store_run(loop, start, end, now, status, error, diagnosis,
                                      round_end)
        except IntegrityError:
            if round_end is None or not self._round_stored(loop.id, round_end):
                raise
            self.metrics.inc("loopwatch_analyses_duplicate_total")
            log.warning("loop %s, round %.0f: another scheduler stored its run first; "
                        "this result is dropped", loop.id, round_end)
            return None
        if summary.ticket_id is not None and self.on_ticket is not None:
            self.on_ticket(summary.ticket_id)
        return summary

    def _round_stored(self, loop_id: str, round_end: float) -> bool:
        with self.store.session() as session:
            return session.scalar(
                select(AnalysisRun.id)
                .where(AnalysisRun.loop_id == loop_id, AnalysisRun.round_end == round_end)
            ) is not None

    def _store_run(self, loop: LoopConfig, start: float, end: float, now: float, status: str,
                   error: str | None, diagnosis: dict[str, Any] | None,
                   round_end: float | None) -> RunSummary:
        """The run, its alarms and its ticket in one transaction."""
        with self.store.session() as session:
            run = AnalysisRun(
                loop_id=loop.id, started_at=now, finished_at=self.clock(),
                window_start=start, window_end=end, status=status, error=error,
                round_end=round_end, scheduled_by=None if round_end is None else self.instance,
            )
            if diagnosis is not None:
                q = diagnosis.get("quantification") or {}
                run.usable = diagnosis["quality"]["usable"]
                run.oscillating = diagnosis["oscillation"]["detected"]
                run.period_s = diagnosis["oscillation"]["period_s"]
                run.verdict = diagnosis["stiction"]["verdict"]
                run.confidence = diagnosis["stiction"]["confidence"]
                run.S, run.J = q.get("S"), q.get("J")
                run.health = diagnosis["health"]
                run.result = diagnosis
            session.add(run)
            session.flush()
            ticket_id = None
            if diagnosis is not None:
                update_alarms_from_analysis(
                    session, loop.id,
                    oscillating=bool(run.oscillating), usable=bool(run.usable),
                    importance=loop.importance, message=self._message(diagnosis), now=now,
                )
                ticket = update_ticket_from_analysis(
                    session, loop.id,
                    valve_asset=loop.valve_asset or loop.id, location=loop.location or loop.unit,
                    verdict=str(run.verdict), evidence=evidence_from_run(run),
                    importance=loop.importance,
                    confirmations_needed=self.settings.ticket_confirmations, now=now,
                )
                ticket_id = None if ticket is None else ticket.id
            return RunSummary(loop.id, run.id, status, run.verdict, ticket_id)

    @staticmethod
    def _message(diagnosis: dict[str, Any]) -> str:
        if not diagnosis["quality"]["usable"]:
            return "data unusable: " + diagnosis["stiction"]["reason"]
        osc = diagnosis["oscillation"]
        if not osc["detected"]:
            return "no oscillation"
        return (f"oscillation, period {osc['period_s']:.0f} s; "
                f"valve: {diagnosis['stiction']['verdict']}")

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
