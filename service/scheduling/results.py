"""Analysis results into the store: a loop's run with its final verdict, a unit's
diagnosis, and the alarms and ticket of each run in the same transaction (see
:mod:`service.scheduler`)."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from analytics.plantwide import UnitDiagnosis
from service.alarms import alarm_payload, update_alarms_from_analysis
from service.analysis import UnitWindows, stiction_pattern_text
from service.config import LoopConfig, PlantConfig, Settings
from service.metrics import Metrics
from service.notifications import Outbox
from service.plant import PlantRegistry
from service.scheduling.jobs import JobOutcome
from service.store.db import Store
from service.store.models import AnalysisRun, UnitAnalysisRun
from service.stored import StoredDiagnosis
from service.tickets import evidence_from_run, ticket_payload, update_ticket_from_analysis
from service.verdicts import latest_unit_decision, previous_size_windows, settle_run

__all__ = ["ResultWriter", "RunSummary", "alarm_message"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunSummary:
    """What one scheduled analysis of one loop produced."""

    loop_id: str
    run_id: int
    status: str
    verdict: str | None
    ticket_id: int | None


def alarm_message(diagnosis: dict[str, Any]) -> str:
    """The alarm message of an analysis, with the final verdict on the valve
    (:func:`service.verdicts.valve_verdict`); a stiction finding names its pattern (a
    stuck valve freezes PV, so it comes with unusable data), a valve the unit's
    diagnosis clears its reason ("cycles because FV-502 sticks")."""
    stored = StoredDiagnosis.from_dict(diagnosis)
    analysis, final = stored.analysis, stored.final
    if stored.final_by_unit and final.verdict != "stiction":
        pattern: str | None = final.reason
    else:
        pattern = stiction_pattern_text(analysis.pattern, analysis.op_travel)
    # in words, as the dashboard's verdicts read ("no stiction", not "no_stiction")
    valve = (f"valve: {str(final.verdict).replace('_', ' ')}"
             + ("" if pattern is None else f" ({pattern})"))
    if not analysis.quality.usable:
        if final.verdict == "stiction":
            return f"data unusable, {valve}"
        # "data unusable: ..." or why a loop in manual is not judged
        return analysis.stiction.reason
    osc = stored.oscillation
    if not osc.detected:
        return "no oscillation" + ("" if pattern is None else f"; {valve}")
    return f"oscillation, period {osc.period_s:.0f} s; {valve}"


class ResultWriter:
    """Stores the outcomes of analyses as runs, alarms and tickets.

    A scheduled result (``round_end`` set) is dropped while ``leading()`` is
    false, or when another scheduler stored the round's run first;
    ``instance`` names this process in ``scheduled_by``.
    """

    def __init__(self, *, store: Store, registry: PlantRegistry, settings: Settings,
                 metrics: Metrics, clock: Callable[[], float], outbox: Outbox | None,
                 instance: str, leading: Callable[[], bool]) -> None:
        self.store = store
        self.registry = registry
        self.settings = settings
        self.metrics = metrics
        self.clock = clock
        self.outbox = outbox
        self.instance = instance
        self.leading = leading
        # the units of the plant object they were read from (the registry replaces it on
        # change): every stored run asks for its unit's loops
        self._units_of: tuple[PlantConfig | None, dict[str, list[LoopConfig]]] = (None, {})

    def units(self) -> dict[str, list[LoopConfig]]:
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

    def finish_loop(self, loop: LoopConfig, now: float, round_end: float | None,
                    outcome: JobOutcome, *, decided: bool) -> RunSummary | None:
        """Store the loop's run (and, if ``decided``, its alarms and ticket); None when it is
        dropped."""
        if round_end is not None and not self.leading():
            log.warning("leadership lost: the result of loop %s for round %.0f is left to the "
                        "new leader", loop.id, round_end)
            return None
        self.metrics.inc("loopwatch_analyses_total", status=outcome.status)
        try:
            summary = self.store_run(loop, now, outcome, round_end, decided=decided)
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

    def store_run(self, loop: LoopConfig, now: float, outcome: JobOutcome,
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
                stored = StoredDiagnosis.from_dict(diagnosis)
                run.usable = stored.analysis.quality.usable
                run.oscillating = stored.oscillation.detected
                run.period_s = stored.oscillation.period_s
                run.result = diagnosis
                # A unit's latest decision keeps the last word until its diagnosis of this
                # round: the pages never show a cleared valve's own finding in between.
                unit_loops = self.units().get(loop.unit or "", [])
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
            importance=loop.importance, message=alarm_message(run.result), now=now,
            out_of_service=StoredDiagnosis.from_dict(run.result).manual is not None
            and not run.usable,
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

    def finish_unit(self, unit_id: str, windows: UnitWindows, now: float,
                    round_end: float | None, outcome: JobOutcome) -> None:
        """Store the unit's diagnosis (dropped if another scheduler stored it first)."""
        if round_end is not None and not self.leading():
            return
        self.metrics.inc("loopwatch_unit_analyses_total", status=outcome.status)
        sticky, cleared = ([], []) if outcome.result is None else (
            UnitDiagnosis.from_dict(outcome.result, lenient=True).valve_decisions())
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
            if round_end is None or unit_id not in self.units_done(round_end):
                raise
            self.metrics.inc("loopwatch_analyses_duplicate_total")
            log.warning("unit %s, round %.0f: another scheduler stored its diagnosis first; "
                        "this result is dropped", unit_id, round_end)
            return
        if outcome.status != "ok":
            log.info("diagnosis of unit %s: %s (%s)", unit_id, outcome.status, outcome.error)

    def units_done(self, round_end: float) -> set[str]:
        """The units that have a diagnosis of the round ending at ``round_end``."""
        with self.store.session() as session:
            return set(session.scalars(
                select(UnitAnalysisRun.unit_id).where(UnitAnalysisRun.round_end == round_end)
            ))

    def decide_units(self, units: dict[str, list[LoopConfig]], summaries: list[RunSummary],
                     now: float, round_end: float | None, done: set[str]) -> list[RunSummary]:
        """Settle the loop runs of ``units`` and decide their alarms and tickets, after the
        units' diagnoses; ``summaries`` with the final verdicts and ticket ids filled in.

        Each loop run of a unit gets its final verdict from the unit's latest ``ok``
        diagnosis (:func:`service.verdicts.valve_verdict`), then its alarms and its ticket.
        They are decided for the units that have a loop run in ``summaries`` or a
        diagnosis of the round not in ``done`` (stored by this call; once per round, so a
        ticket closed since is not opened again from the same run): a scheduler
        completing a round whose unit diagnosis its predecessor left undone decides them
        on the round's stored loop runs.
        """
        analysed = {s.loop_id for s in summaries}
        fresh = {unit for unit, loops in units.items() if any(x.id in analysed for x in loops)}
        if round_end is not None:
            fresh |= self.units_done(round_end) - done
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
