"""The final verdict on each valve: the loop's own diagnosis, overruled by its unit's.

In a unit of interacting loops one sticky valve makes its neighbours cycle,
and their own analyses then find stiction too (thesis chapter 2, section
2.3.5).  The unit diagnosis (:func:`analytics.plantwide.diagnose_unit`)
decides which valves stick.  :func:`valve_verdict` is the one place where
the two are combined; the scheduler stores its answer in the loop's
analysis run (:func:`settle_run`: the run's ``verdict``, ``confidence``,
``S``, ``J`` and ``health`` columns and ``result["valve"]``), so that the
loop list, the loop page, the overview, the alarms, the unit page, the
tickets and the bad-actor ranking all read the same decision.  The loop's
own findings stay in ``result["stiction"]`` and ``result["quantification"]``
as evidence.

Sizes.  One window's S and J jump with the window (issue 19: FV-101, a Kano
valve S = 4, J = 2, read 2.94/0.25 in one window and 4.01/1.92 in another).
The size every page shows is the valve's combined estimate
(:func:`analytics.quantification.combine_windows`) over the windows of its
current streak of stiction verdicts that do not overlap, each with its
interval (:func:`valve_size`): ``S`` and ``J`` of the final verdict, with
``S_interval``, ``J_interval``, the windows combined in ``size_windows`` and
``J_note``, which says whether J was sized with a configured process gain or is
known only through the product ``K J`` in some windows (a stiction limit cycle
pins the PV step of a slip better than the slip).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from analytics.plantwide import UnitDiagnosis, ValveFinding
from analytics.quantification import combine_windows
from service.analysis import health_score
from service.store.models import AnalysisRun, UnitAnalysisRun
from service.stored import (
    GainFlags,
    SizeWindow,
    StoredDiagnosis,
    StoredValve,
    ValveSize,
)
from service.tickets import latest_unit_run

__all__ = [
    "MAX_SIZE_WINDOWS",
    "UnitDecision",
    "combined_size",
    "j_note",
    "latest_unit_decision",
    "named_valves",
    "previous_size_windows",
    "settle_run",
    "unit_decision",
    "valve_decision",
    "valve_size",
    "valve_verdict",
]

MAX_SIZE_WINDOWS = 24
"""Windows a valve's combined size keeps, the latest (a day of hour-long windows)."""


@dataclass(frozen=True)
class UnitDecision:
    """What a unit's diagnosis decided on its valves.

    Attributes
    ----------
    unit_id, run_id : str, int
        The unit and its diagnosis (:class:`~service.store.models.UnitAnalysisRun`).
    sticky : dict
        ``loop id -> finding`` (:class:`~analytics.plantwide.ValveFinding`: ``confidence``,
        ``S``, ``J``, ``reason``) of each loop whose valve the diagnosis names sticky, most
        confident first; findings given in their stored (dict) form are read into it.
    cleared : tuple of str
        The loops whose valves it clears
        (:meth:`~analytics.plantwide.UnitDiagnosis.valve_decisions`).
    valves : dict
        ``loop id -> valve tag`` of the unit's loops (the loop id when no valve is
        configured).
    """

    unit_id: str
    run_id: int
    sticky: Mapping[str, ValveFinding]
    cleared: tuple[str, ...]
    valves: dict[str, str]

    def __post_init__(self) -> None:
        object.__setattr__(self, "sticky", {
            loop: f if isinstance(f, ValveFinding) else ValveFinding.from_dict(f, lenient=True)
            for loop, f in self.sticky.items()})


def unit_decision(run: UnitAnalysisRun | None, valves: Mapping[str, str]
                  ) -> UnitDecision | None:
    """The decision of a stored unit diagnosis; None when it is missing or not ``ok``."""
    if run is None or run.status != "ok" or run.result is None:
        return None
    diagnosis = UnitDiagnosis.from_dict(run.result, lenient=True)
    sticky, cleared = diagnosis.valve_decisions()
    findings = {f.loop: f for f in diagnosis.sticky_valves}
    return UnitDecision(run.unit_id, run.id, {loop: findings[loop] for loop in sticky},
                        tuple(cleared), dict(valves))


def _valve_list(tags: list[str]) -> str:
    """``"FV-1"``, ``"FV-1 and FV-2"``, ``"FV-1, FV-2 and FV-3"``."""
    return tags[0] if len(tags) == 1 else ", ".join(tags[:-1]) + " and " + tags[-1]


def _stored(diagnosis: StoredDiagnosis | Mapping[str, Any]) -> StoredDiagnosis:
    return (diagnosis if isinstance(diagnosis, StoredDiagnosis)
            else StoredDiagnosis.from_dict(diagnosis))


def valve_decision(loop_id: str, diagnosis: StoredDiagnosis | Mapping[str, Any],
                   unit: UnitDecision | None = None) -> StoredValve:
    """The final verdict on the valve of ``loop_id`` (:func:`valve_verdict`), typed."""
    stored = _stored(diagnosis)
    own = stored.analysis.stiction
    size = stored.analysis.quantification
    verdict = StoredValve(
        verdict=own.verdict, confidence=own.confidence,
        S=None if size is None else size.S, J=None if size is None else size.J,
        reason=own.reason, decided_by="loop", own_verdict=own.verdict)
    if unit is None or (loop_id not in unit.cleared and loop_id not in unit.sticky):
        return verdict
    tags = [unit.valves.get(loop, loop) for loop in unit.sticky]
    verdict = replace(verdict, decided_by="unit", unit_id=unit.unit_id, unit_run_id=unit.run_id,
                      sticky_valves=tuple(tags))
    if loop_id in unit.cleared:
        reason = (f"cycles because {_valve_list(tags)} {'sticks' if len(tags) == 1 else 'stick'}"
                  if tags else "its own valve is not needed to explain its cycle, and unit "
                               f"{unit.unit_id}'s diagnosis names no sticky valve")
        strongest = max((f.confidence for f in unit.sticky.values()), default=0.0)
        return replace(verdict, verdict="no_stiction", confidence=strongest, S=None, J=None,
                       reason=reason)
    finding = unit.sticky[loop_id]
    own_sticky = own.verdict == "stiction"
    verdict = replace(verdict, verdict="stiction",
                      confidence=max(finding.confidence, own.confidence if own_sticky else 0.0),
                      reason=finding.reason)
    if verdict.S is None:
        verdict = replace(verdict, S=finding.S, J=finding.J)
    return verdict


def valve_verdict(loop_id: str, diagnosis: StoredDiagnosis | Mapping[str, Any],
                  unit: UnitDecision | None = None) -> dict[str, Any]:
    """The final verdict on the valve of ``loop_id``: the one every page and rule reads.

    Without a unit decision on the loop's valve it is the loop's own
    (the diagnosis's ``stiction``, sizes from its ``quantification``).  A
    valve the unit diagnosis clears is ``no_stiction``, with the unit's reason
    ("cycles because FV-502 sticks") and no size; its confidence is that of
    the strongest valve named instead.  A valve the unit names is ``stiction``
    with the unit's reason; its size is the loop's own estimate when it has
    one, else the unit's.

    Returns
    -------
    dict
        ``verdict``, ``confidence``, ``S``, ``J``, ``reason``, ``decided_by``
        (``"loop"`` or ``"unit"``), ``own_verdict`` (the loop's own), ``unit_id``
        and ``unit_run_id`` (None when decided by the loop), ``sticky_valves`` (the
        valve tags the unit names; empty when decided by the loop): the stored form
        of :func:`valve_decision`.

    Examples
    --------
    >>> own = {"stiction": {"verdict": "stiction", "confidence": 0.8, "reason": "shape"},
    ...        "quantification": {"S": 34.0, "J": 31.0}}
    >>> unit = UnitDecision("column", 7, {"AIC-502": {"loop": "AIC-502", "confidence": 0.9,
    ...     "S": 4.0, "J": 2.0, "reason": "own valve needed"}}, ("TIC-503",),
    ...     {"AIC-502": "FV-502"})
    >>> v = valve_decision("TIC-503", own, unit)
    >>> v.verdict, v.reason, v.S, v.own_verdict, v.decided_by
    ('no_stiction', 'cycles because FV-502 sticks', None, 'stiction', 'unit')
    >>> valve_verdict("TIC-503", own)["verdict"]
    'stiction'
    """
    return valve_decision(loop_id, diagnosis, unit).decision_dict()


def combined_size(verdict: StoredValve, diagnosis: StoredDiagnosis,
                  window: tuple[float, float], previous: Sequence[SizeWindow]) -> ValveSize:
    """The valve's combined size after a run, typed (:func:`valve_size`).

    >>> own = {"S": 4.2, "J": 1.9, "S_interval": [4.0, 4.4], "J_interval": [1.5, 2.3]}
    >>> first = combined_size(StoredValve("stiction", S=4.2, J=1.9),
    ...                       StoredDiagnosis.from_dict({"quantification": own}), (0.0, 3600.0),
    ...                       [])
    >>> first.S, first.S_interval, len(first.size_windows)
    (4.2, (4.0, 4.4), 1)
    """
    size = ValveSize(verdict.S, verdict.J)
    if verdict.verdict != "stiction":
        return size
    windows = list(previous)
    own = diagnosis.analysis.quantification
    if (own is not None and own.S is not None and own.S == verdict.S and own.J is not None
            and own.S_interval and own.J_interval
            and (not windows or window[0] >= windows[-1].window_end)):
        windows.append(SizeWindow(window[0], window[1], own.S, own.S_interval, own.J,
                                  own.J_interval, gain_given=own.gain_given,
                                  gain_source=diagnosis.gain_source,
                                  J_product_only=own.J_product_only, fit_r2=own.fit_r2))
    windows = windows[-MAX_SIZE_WINDOWS:]
    if not windows:
        return size
    fits = [w.fit_r2 for w in windows]
    S = combine_windows([w.S for w in windows], [w.S_interval for w in windows], fits)
    J = combine_windows([w.J for w in windows], [w.J_interval for w in windows], fits)
    return ValveSize(S.value, J.value, S.interval, J.interval, tuple(windows),
                     j_note(windows))


def valve_size(verdict: Mapping[str, Any], diagnosis: StoredDiagnosis | Mapping[str, Any],
               window: tuple[float, float], previous: Sequence[SizeWindow | Mapping[str, Any]]
               ) -> dict[str, Any]:
    """The valve's combined size after a run: ``S``, ``J``, ``S_interval``, ``J_interval``,
    ``size_windows`` and ``J_note`` (:func:`j_note`): the stored form of
    :func:`combined_size`.

    ``previous`` are the windows combined after the loop's run before (its
    ``size_windows``; empty when that run did not find the valve sticky: the streak
    starts over).  A sticky valve adds its own estimate of this ``window``
    (``(start, end)``) when the estimate is the loop's own, with intervals
    (the diagnosis's ``quantification``), and the window starts no earlier than the
    last one combined ends: the windows do not share data.  The latest
    :data:`MAX_SIZE_WINDOWS` are combined.  Without windows the verdict's own
    sizes stand, without intervals.  Each window keeps whether its J was sized with a
    given process gain (``gain_given``, its ``gain_source``) or is known only through
    ``K J`` (``J_product_only``).

    >>> own = {"S": 4.2, "J": 1.9, "S_interval": [4.0, 4.4], "J_interval": [1.5, 2.3]}
    >>> first = valve_size({"verdict": "stiction", "S": 4.2, "J": 1.9},
    ...                    {"quantification": own}, (0.0, 3600.0), [])
    >>> first["S"], first["S_interval"], len(first["size_windows"])
    (4.2, [4.0, 4.4], 1)
    >>> later = valve_size({"verdict": "stiction", "S": 3.0, "J": 0.2},
    ...                    {"quantification": {**own, "S": 3.0, "J": 0.2,
    ...                     "S_interval": [2.9, 3.1], "J_interval": [0.1, 0.3]}},
    ...                    (60.0, 3660.0), first["size_windows"])  # overlaps: not combined
    >>> later["S"], later["J"]
    (4.2, 1.9)
    """
    return combined_size(
        StoredValve.from_dict(verdict), _stored(diagnosis), window,
        [w if isinstance(w, SizeWindow) else SizeWindow.from_dict(w) for w in previous],
    ).to_dict()


def j_note(windows: Sequence[SizeWindow | Mapping[str, Any]]) -> str | None:
    """What the combined J rests on, for the pages; None when every window fitted the
    process gain and told J from it (or the windows predate these flags).

    >>> j_note([{"J_product_only": True}, {"J_product_only": False}])[:45]
    'J is known only through K J in 1 of 2 windows'
    >>> j_note([{"gain_given": True, "gain_source": "the loop's process_model"}])
    "J sized with the process gain from the loop's process_model"
    """
    flags = [w.flags if isinstance(w, SizeWindow) else GainFlags.from_dict(w) for w in windows]
    vague = sum(1 for w in flags if w.J_product_only)
    if vague:
        return (f"J is known only through K J in {vague} of {len(flags)} windows (the "
                "PV step of a slip): a process gain in the plant file (the loop's "
                "process_model) fixes it")
    given = [w for w in flags if w.gain_given]
    if given and len(given) == len(flags):
        return ("J sized with the process gain from "
                f"{given[-1].gain_source or 'the plant file'}")
    return None


def previous_size_windows(session: Session, run: AnalysisRun) -> list[SizeWindow]:
    """The windows combined into the valve's size by the loop's run before ``run`` (by
    start time); empty when that run is not an ``ok`` stiction finding."""
    row = session.execute(
        select(AnalysisRun.status, AnalysisRun.verdict,
               AnalysisRun.result[("valve", "size_windows")])
        .where(AnalysisRun.loop_id == run.loop_id, AnalysisRun.started_at < run.started_at)
        .order_by(AnalysisRun.started_at.desc(), AnalysisRun.id.desc()).limit(1)
    ).first()
    if row is None or row[0] != "ok" or row[1] != "stiction":
        return []
    return [SizeWindow.from_dict(w) for w in row[2] or []]


def settle_run(run: AnalysisRun, unit: UnitDecision | None,
               previous: Sequence[SizeWindow] = ()) -> None:
    """Store the final verdict (:func:`valve_decision`) in an ``ok`` run: its columns and
    the result's ``valve``, and the health that follows from it; its ``S`` and ``J`` are
    the valve's combined size (:func:`combined_size`) after the windows ``previous``
    (:func:`previous_size_windows`).  Settling again with the same decision changes
    nothing."""
    if run.result is None:
        return
    diagnosis = StoredDiagnosis.from_dict(run.result)
    verdict = valve_decision(run.loop_id, diagnosis, unit)
    window = (run.started_at if run.window_start is None else run.window_start,
              run.started_at if run.window_end is None else run.window_end)
    size = combined_size(verdict, diagnosis, window, previous)
    result = {**run.result, "valve": {**verdict.decision_dict(), **size.to_dict()}}
    health = health_score(result)
    run.result = {**result, "health": health}
    run.verdict, run.confidence = verdict.verdict, verdict.confidence
    run.S, run.J = size.S, size.J
    run.health = health


def named_valves(result: Mapping[str, Any], valves: Mapping[str, str]) -> dict[str, Any]:
    """A unit diagnosis (:meth:`analytics.plantwide.UnitDiagnosis.to_dict`) as the API shows
    it: each oscillation group's ``sticky_valves`` names valve tags (its loops in
    ``sticky_loops``), and each named valve carries its ``valve`` tag.  Read through
    :meth:`~analytics.plantwide.UnitDiagnosis.from_dict`; the unit-wide fields it does
    not read are shown as stored.
    """
    diagnosis = UnitDiagnosis.from_dict(result)
    return {
        **result,
        "sticky_valves": [{**finding.to_dict(), "valve": valves.get(finding.loop, finding.loop)}
                          for finding in diagnosis.sticky_valves],
        "groups": [{**group.to_dict(),
                    "sticky_valves": [valves.get(loop, loop) for loop in group.sticky_valves],
                    "sticky_loops": list(group.sticky_valves)} for group in diagnosis.groups],
    }


def latest_unit_decision(session: Session, unit_id: str, valves: Mapping[str, str]
                         ) -> UnitDecision | None:
    """The decision of the unit's newest ``ok`` diagnosis (the one that has the last word)."""
    return unit_decision(latest_unit_run(session, unit_id, ok_only=True), valves)
