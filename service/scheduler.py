"""The analysis scheduler: every interval, each loop's latest window is diagnosed.

Windows are cut from the rolling buffers and submitted to an executor (a
local process pool by default; anything with the ``concurrent.futures``
``submit`` interface, such as a Dask ``distributed.Client``, fits).  Each
loop's result is awaited with its own time limit, so one slow or failing
analysis never holds up the others; its run is stored as ``timeout`` or
``failed`` with the reason.  Results become analysis runs, alarms and
tickets in one transaction per loop.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import Executor, Future
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass
from typing import Any

import numpy as np

from service.alarms import expire_shelves, update_alarms_from_analysis
from service.analysis import analyse_window
from service.buffer import LoopBuffers
from service.config import LoopConfig, Settings
from service.ingest import purge_samples
from service.metrics import Metrics
from service.plant import PlantRegistry
from service.store.db import Store
from service.store.models import AnalysisRun
from service.tickets import evidence_from_run, update_ticket_from_analysis

__all__ = ["AnalysisScheduler", "RunSummary"]

log = logging.getLogger(__name__)

PURGE_INTERVAL_S = 3600.0
"""How often samples past the retention period are deleted."""


@dataclass(frozen=True)
class RunSummary:
    """What one scheduled analysis of one loop produced."""

    loop_id: str
    run_id: int
    status: str
    verdict: str | None
    ticket_id: int | None


class AnalysisScheduler:
    """Runs the pipeline on every loop each ``settings.analysis_interval_s``."""

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
    ) -> None:
        self.store = store
        self.registry = registry
        self.buffers = buffers
        self.settings = settings
        self.executor = executor
        self.metrics = metrics
        self.clock = clock
        self.on_ticket = on_ticket
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_purge = -float("inf")

    def maintain(self, now: float) -> None:
        """Housekeeping before each round: end shelves that ran out, and purge samples
        older than the retention period (at most once an hour)."""
        with self.store.session() as session:
            expired = expire_shelves(session, now=now)
            if now - self._last_purge >= PURGE_INTERVAL_S:
                retention_s = self.settings.sample_retention_days * 86400.0
                purged = purge_samples(session, now - retention_s)
                self._last_purge = now
                self.metrics.inc("loopwatch_samples_purged_total", purged)
        if expired:
            log.info("%d shelved alarm(s) returned after their shelve ran out", len(expired))

    def run_once(self, now: float | None = None) -> list[RunSummary]:
        """Analyse every loop once on the window ending at ``now``."""
        now = self.clock() if now is None else now
        self.maintain(now)
        pending: list[tuple[LoopConfig, float, float, Future[dict[str, Any]] | None]] = []
        for loop in self.registry.plant.loops:
            window = self.buffers.window(loop.id, self.settings.window_s, now)
            start, end = now - self.settings.window_s, now
            if window.t.size == 0 or all(
                x is None or not np.isfinite(x).any()
                for x in (window.op, window.pv, window.sp, window.mv)
            ):
                pending.append((loop, start, end, None))
                continue
            signals = {"op": window.op, "pv": window.pv, "sp": window.sp, "mv": window.mv}
            future = self.executor.submit(
                analyse_window, loop.model_dump(mode="json"), window.ts, window.t, signals
            )
            pending.append((loop, start, end, future))
        deadline = time.monotonic() + self.settings.analysis_timeout_s
        return [self._finish(loop, start, end, future, now, deadline)
                for loop, start, end, future in pending]

    def _finish(self, loop: LoopConfig, start: float, end: float,
                future: Future[dict[str, Any]] | None, now: float,
                deadline: float) -> RunSummary:
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
        self.metrics.inc("loopwatch_analyses_total", status=status)
        with self.store.session() as session:
            run = AnalysisRun(
                loop_id=loop.id, started_at=now, finished_at=self.clock(),
                window_start=start, window_end=end, status=status, error=error,
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
            summary = RunSummary(loop.id, run.id, status, run.verdict, ticket_id)
        if ticket_id is not None and self.on_ticket is not None:
            self.on_ticket(ticket_id)
        return summary

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
        """Run :meth:`run_once` every interval in a background thread."""
        def loop() -> None:
            while not self._stop.is_set():
                try:
                    self.run_once()
                except Exception:  # keep scheduling; the next round may succeed
                    log.exception("analysis round failed")
                self._stop.wait(self.settings.analysis_interval_s)

        self._thread = threading.Thread(target=loop, name="loopwatch-scheduler", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the background thread (the round in progress finishes)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=self.settings.analysis_timeout_s + 5)
