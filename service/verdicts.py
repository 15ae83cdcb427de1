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
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from sqlalchemy.orm import Session

from service.analysis import health_score, valve_decisions
from service.store.models import AnalysisRun, UnitAnalysisRun
from service.tickets import latest_unit_run

__all__ = ["UnitDecision", "latest_unit_decision", "named_valves", "settle_run",
           "unit_decision", "valve_verdict"]


@dataclass(frozen=True)
class UnitDecision:
    """What a unit's diagnosis decided on its valves.

    Attributes
    ----------
    unit_id, run_id : str, int
        The unit and its diagnosis (:class:`~service.store.models.UnitAnalysisRun`).
    sticky : dict
        ``loop id -> finding`` (``confidence``, ``S``, ``J``, ``reason``) of each loop whose
        valve the diagnosis names sticky, most confident first.
    cleared : tuple of str
        The loops whose valves it clears (:func:`service.analysis.valve_decisions`).
    valves : dict
        ``loop id -> valve tag`` of the unit's loops (the loop id when no valve is
        configured).
    """

    unit_id: str
    run_id: int
    sticky: dict[str, dict[str, Any]]
    cleared: tuple[str, ...]
    valves: dict[str, str]


def unit_decision(run: UnitAnalysisRun | None, valves: Mapping[str, str]
                  ) -> UnitDecision | None:
    """The decision of a stored unit diagnosis; None when it is missing or not ``ok``."""
    if run is None or run.status != "ok" or run.result is None:
        return None
    sticky, cleared = valve_decisions(run.result)
    findings = {f["loop"]: f for f in run.result["sticky_valves"]}
    return UnitDecision(run.unit_id, run.id, {loop: findings[loop] for loop in sticky},
                        tuple(cleared), dict(valves))


def _valve_list(tags: list[str]) -> str:
    """``"FV-1"``, ``"FV-1 and FV-2"``, ``"FV-1, FV-2 and FV-3"``."""
    return tags[0] if len(tags) == 1 else ", ".join(tags[:-1]) + " and " + tags[-1]


def valve_verdict(loop_id: str, diagnosis: Mapping[str, Any],
                  unit: UnitDecision | None = None) -> dict[str, Any]:
    """The final verdict on the valve of ``loop_id``: the one every page and rule reads.

    Without a unit decision on the loop's valve it is the loop's own
    (``diagnosis["stiction"]``, sizes from ``diagnosis["quantification"]``).  A
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
        valve tags the unit names; empty when decided by the loop).

    Examples
    --------
    >>> own = {"stiction": {"verdict": "stiction", "confidence": 0.8, "reason": "shape"},
    ...        "quantification": {"S": 34.0, "J": 31.0}}
    >>> unit = UnitDecision("column", 7, {"AIC-502": {"confidence": 0.9, "S": 4.0, "J": 2.0,
    ...     "reason": "own valve needed"}}, ("TIC-503",), {"AIC-502": "FV-502"})
    >>> v = valve_verdict("TIC-503", own, unit)
    >>> v["verdict"], v["reason"], v["S"], v["own_verdict"], v["decided_by"]
    ('no_stiction', 'cycles because FV-502 sticks', None, 'stiction', 'unit')
    >>> valve_verdict("TIC-503", own)["verdict"]
    'stiction'
    """
    own = diagnosis["stiction"]
    size = diagnosis.get("quantification") or {}
    verdict = {
        "verdict": own["verdict"], "confidence": own["confidence"],
        "S": size.get("S"), "J": size.get("J"), "reason": own["reason"],
        "decided_by": "loop", "own_verdict": own["verdict"],
        "unit_id": None, "unit_run_id": None, "sticky_valves": [],
    }
    if unit is None or (loop_id not in unit.cleared and loop_id not in unit.sticky):
        return verdict
    tags = [unit.valves.get(loop, loop) for loop in unit.sticky]
    verdict.update(decided_by="unit", unit_id=unit.unit_id, unit_run_id=unit.run_id,
                   sticky_valves=tags)
    if loop_id in unit.cleared:
        reason = (f"cycles because {_valve_list(tags)} {'sticks' if len(tags) == 1 else 'stick'}"
                  if tags else "its own valve is not needed to explain its cycle, and unit "
                               f"{unit.unit_id}'s diagnosis names no sticky valve")
        strongest = max((float(f["confidence"]) for f in unit.sticky.values()), default=0.0)
        verdict.update(verdict="no_stiction", confidence=strongest, S=None, J=None,
                       reason=reason)
        return verdict
    finding = unit.sticky[loop_id]
    own_sticky = own["verdict"] == "stiction"
    verdict.update(
        verdict="stiction",
        confidence=max(float(finding["confidence"]),
                       float(own["confidence"]) if own_sticky else 0.0),
        reason=finding["reason"],
    )
    if verdict["S"] is None:
        verdict.update(S=finding.get("S"), J=finding.get("J"))
    return verdict


def settle_run(run: AnalysisRun, unit: UnitDecision | None) -> None:
    """Store the final verdict (:func:`valve_verdict`) in an ``ok`` run: its columns and
    ``result["valve"]``, and the health that follows from it.  Settling again with the
    same decision changes nothing."""
    if run.result is None:
        return
    verdict = valve_verdict(run.loop_id, run.result, unit)
    result = {**run.result, "valve": verdict}
    result["health"] = health_score(result)
    run.result = result
    run.verdict, run.confidence = verdict["verdict"], verdict["confidence"]
    run.S, run.J = verdict["S"], verdict["J"]
    run.health = result["health"]


def named_valves(result: Mapping[str, Any], valves: Mapping[str, str]) -> dict[str, Any]:
    """A unit diagnosis (:meth:`analytics.plantwide.UnitDiagnosis.to_dict`) as the API shows
    it: each oscillation group's ``sticky_valves`` names valve tags (its loops in
    ``sticky_loops``), and each named valve carries its ``valve`` tag.

    >>> named = named_valves({"sticky_valves": [{"loop": "AIC-502"}],
    ...                       "groups": [{"sticky_valves": ["AIC-502"]}]}, {"AIC-502": "FV-502"})
    >>> named["sticky_valves"]
    [{'loop': 'AIC-502', 'valve': 'FV-502'}]
    >>> named["groups"]
    [{'sticky_valves': ['FV-502'], 'sticky_loops': ['AIC-502']}]
    """
    return {
        **result,
        "sticky_valves": [{**f, "valve": valves.get(f["loop"], f["loop"])}
                          for f in result["sticky_valves"]],
        "groups": [{**g, "sticky_valves": [valves.get(loop, loop) for loop in g["sticky_valves"]],
                    "sticky_loops": list(g["sticky_valves"])} for g in result["groups"]],
    }


def latest_unit_decision(session: Session, unit_id: str, valves: Mapping[str, str]
                         ) -> UnitDecision | None:
    """The decision of the unit's newest ``ok`` diagnosis (the one that has the last word)."""
    return unit_decision(latest_unit_run(session, unit_id, ok_only=True), valves)
