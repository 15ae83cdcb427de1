"""The round grid: which scheduled rounds are due, and the housekeeping before them
(buffer sync from the store, shelve expiry, purge); see :mod:`service.scheduler`."""

from __future__ import annotations

import itertools
import logging
import math
from operator import itemgetter

from sqlalchemy import delete, func, select
from sqlalchemy.orm import Session

from service.alarms import expire_shelves
from service.buffer import LoopBuffers
from service.config import Settings
from service.ingest import purge_samples
from service.metrics import Metrics
from service.plant import PlantRegistry
from service.store.db import Store
from service.store.models import AnalysisRun, IngestLog, Sample

__all__ = ["SYNC_OVERLAP_S", "RoundGrid", "grid_rounds"]

log = logging.getLogger(__name__)

PURGE_INTERVAL_S = 3600.0
"""How often samples past the retention period are deleted."""

SYNC_OVERLAP_S = 120.0
"""Each buffer sync looks again at the ingest transactions received this long before the
previous sync: one that committed up to two minutes after its time stamp is still read."""

HISTORY_ROUNDS_PER_WINDOW = 4
"""History rounds per window length (:meth:`RoundGrid.due_rounds`): the runs
between two confirmations on separate windows must find stiction too."""

HISTORY_WINDOW_COVERED = 0.9
"""Share of a window the buffers must hold before a new installation analyses it as
history (:meth:`RoundGrid.due_rounds`); the data quality screen judges the rest."""


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


class RoundGrid:
    """The rounds due and the rolling buffers kept in step with the store."""

    def __init__(self, *, store: Store, registry: PlantRegistry, buffers: LoopBuffers,
                 settings: Settings, metrics: Metrics) -> None:
        self.store = store
        self.registry = registry
        self.buffers = buffers
        self.settings = settings
        self.metrics = metrics
        self._last_purge = -math.inf
        self._synced_until: float | None = None
        self._log_mark = -math.inf  # newest ingest_log.received_at read by a sync

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

    def done(self, round_end: float) -> set[str]:
        """The loops that have a run of the round ending at ``round_end``."""
        with self.store.session() as session:
            return set(session.scalars(
                select(AnalysisRun.loop_id).where(AnalysisRun.round_end == round_end)
            ))

    def due_rounds(self, now: float) -> list[float]:
        """The rounds to run at ``now``, oldest first (see :mod:`service.scheduler`).

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
            {loop.id for loop in self.registry.plant.loops} <= self.done(last)
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
