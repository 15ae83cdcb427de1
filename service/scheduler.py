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

import logging
import math
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Executor
from functools import partial
from typing import Any

import numpy as np

from service.analysis import (
    UnitWindowsError,
    analyse_unit,
    analyse_window,
    independent_gains,
    to_percent_of_span,
    unit_model_spec,
    unit_windows,
)
from service.buffer import LoopBuffers
from service.config import LoopConfig, Settings
from service.leader import Election, instance_name
from service.metrics import Metrics
from service.notifications import Outbox
from service.plant import PlantRegistry
from service.scheduling.jobs import AnalysisJob, JobOutcome, JobRunner
from service.scheduling.results import ResultWriter, RunSummary
from service.scheduling.rounds import RoundGrid
from service.store.db import Store

__all__ = ["AnalysisScheduler"]

log = logging.getLogger(__name__)


class AnalysisScheduler:
    """Runs the pipeline on every loop each ``settings.analysis_interval_s``.

    The coordinator of :attr:`rounds` (:class:`~service.scheduling.rounds.RoundGrid`),
    :attr:`jobs` (:class:`~service.scheduling.jobs.JobRunner`) and :attr:`results`
    (:class:`~service.scheduling.results.ResultWriter`): it cuts each loop's and unit's
    window from the buffers into a job and hands its outcome to the results.
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
        self.metrics = metrics
        self.clock = clock
        self.election = election
        self.rounds = RoundGrid(store=store, registry=registry, buffers=buffers,
                                settings=settings, metrics=metrics)
        self.jobs = JobRunner(executor_factory=executor_factory, settings=settings,
                              metrics=metrics)
        self.results = ResultWriter(store=store, registry=registry, settings=settings,
                                    metrics=metrics, clock=clock, outbox=outbox,
                                    instance=instance or instance_name(),
                                    leading=lambda: self.leading)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def leading(self) -> bool:
        """True while this process is the scheduler that runs rounds."""
        return self.election is None or self.election.is_leader

    @property
    def executor(self) -> Executor:
        """The executor the analyses run on now."""
        return self.jobs.executor

    @property
    def outbox(self) -> Outbox | None:
        """Where alarm and ticket events go (None: not notified)."""
        return self.results.outbox

    @property
    def instance(self) -> str:
        """This process's name in ``scheduled_by``."""
        return self.results.instance

    def maintain(self, now: float) -> None:
        """Housekeeping before each round (:meth:`RoundGrid.maintain`)."""
        self.rounds.maintain(now)

    def sync_buffers(self, now: float) -> int:
        """Read into the buffers what other processes stored (:meth:`RoundGrid.sync_buffers`);
        the number of samples read."""
        return self.rounds.sync_buffers(now)

    def due_rounds(self, now: float) -> list[float]:
        """The rounds to run at ``now``, oldest first (:meth:`RoundGrid.due_rounds`)."""
        return self.rounds.due_rounds(now)

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
        done = self.rounds.done(round_end)
        loops = [loop for loop in self.registry.plant.loops if loop.id not in done]
        summaries = self._analyse(loops, round_end, round_end=round_end)
        return self._analyse_units(summaries, round_end, round_end=round_end)

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

    def _halted(self, scheduled: bool) -> bool:
        """True once stopping, or, for a scheduled round, deposed."""
        return self._stop.is_set() or (scheduled and not self.leading)

    def _window_args(self, loop: LoopConfig, now: float, gains: dict[str, dict[str, Any]]
                     ) -> tuple[Any, ...] | None:
        """The arguments of :func:`analyse_window` for the loop's window ending at ``now``,
        less the samples not yet arrived (:meth:`LoopBuffers.arrived_end`), with the loop's
        process gain in ``gains`` (:func:`independent_gains`); None when the window holds no
        sample."""
        end = self.buffers.arrived_end([loop.id], now, self.settings.analysis_interval_s)
        window = self.buffers.window(loop.id, self.settings.window_s, end)
        signals = {"op": window.op, "pv": window.pv, "sp": window.sp, "mv": window.mv}
        if window.t.size == 0 or all(x is None or not np.isfinite(x).any()
                                     for x in signals.values()):
            return None
        gain = gains.get(loop.id)
        if gain is not None and gain["couplings"]:
            gain = {**gain, "inputs": self._coupled_inputs(gain["couplings"], window.t, end)}
        return (loop.model_dump(mode="json"), window.ts, window.t,
                {**signals, "mode": window.mode}, gain)

    def _coupled_inputs(self, couplings: dict[str, Any], t: np.ndarray, end: float
                        ) -> dict[str, np.ndarray]:
        """The OP windows (% of span) of the coupled loops on the grid ``t`` ending at
        ``end``, for :func:`service.analysis.sizing_pv`; a loop without one on that grid
        is left out."""
        inputs = {}
        for other_id in couplings:
            try:
                other = self.registry.plant.loop(other_id)
                window = self.buffers.window(other_id, self.settings.window_s, end)
            except KeyError:
                continue
            op = to_percent_of_span(window.op, other.ranges.get("op"))
            if op is not None and window.t.shape == t.shape and np.allclose(window.t, t):
                inputs[other_id] = op
        return inputs

    def _analyse(self, loops: Iterable[LoopConfig], now: float,
                 round_end: float | None) -> list[RunSummary]:
        """Analyse ``loops`` on the windows ending at ``now``; the final verdict, alarms and
        tickets of loops in units of two or more loops wait for their unit's diagnosis
        (:meth:`_analyse_units`)."""
        loops = list(loops)
        order = {loop.id: i for i, loop in enumerate(loops)}
        in_units = {loop.id for members in self.results.units().values() for loop in members}
        summaries: list[RunSummary] = []

        def finish(loop: LoopConfig, outcome: JobOutcome) -> None:
            summary = self.results.finish_loop(loop, now, round_end, outcome,
                                               decided=loop.id not in in_units)
            if summary is not None:
                summaries.append(summary)

        def jobs() -> Iterator[AnalysisJob]:
            gains = independent_gains(self.registry.plant)
            for loop in loops:
                args = self._window_args(loop, now, gains)
                if args is None:
                    finish(loop, JobOutcome("no_data", error="no samples in the analysis window"))
                    continue
                yield AnalysisJob(f"loop {loop.id}", analyse_window, args, partial(finish, loop))

        self.jobs.run(jobs(), partial(self._halted, round_end is not None))
        return sorted(summaries, key=lambda s: order[s.loop_id])

    def _analyse_units(self, summaries: list[RunSummary], now: float,
                       round_end: float | None) -> list[RunSummary]:
        """Diagnose each unit of two or more loops (thesis chapter 2) on the windows ending at
        ``now``, unless this round's diagnosis is stored already, then decide the tickets of
        the units' loops (:meth:`ResultWriter.decide_units`)."""
        units = self.results.units()
        scheduled = round_end is not None
        if not units or (scheduled and not self.leading):
            return summaries
        done = set() if round_end is None else self.results.units_done(round_end)
        self.jobs.run(self._unit_jobs(units, done, now, round_end),
                      partial(self._halted, scheduled))
        if self._halted(scheduled):
            return summaries  # the next leader decides the tickets of this round
        return self.results.decide_units(units, summaries, now, round_end, done)

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
            finish = partial(self.results.finish_unit, unit_id, windows, now, round_end)
            try:
                ts = windows.ts
            except UnitWindowsError as exc:
                finish(JobOutcome("failed", error=str(exc)))
                continue
            config = next((u for u in self.registry.plant.units if u.id == unit_id), None)
            model = unit_model_spec(config, loops, windows)
            yield AnalysisJob(f"unit {unit_id}", analyse_unit, (windows.signals, ts, model),
                              finish)

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
