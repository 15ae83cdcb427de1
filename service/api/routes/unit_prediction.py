"""Limit cycles of a unit of interacting loops with sticky valves (thesis chapter 3).

The model is the unit's process matrix from the plant file
(:class:`service.config.UnitProcessConfig`), the loops' configured controllers
and each loop's latest stiction estimate; :func:`service.prediction.predict_spec`
predicts it by the describing function (thesis Eqs. 3.11-3.14, 3.20, 3.23 with
the amplitude consistency of ERRATA item 9) and simulates it beside.  Both are
checked against the cycle the unit's latest diagnosis measured
(:class:`analytics.tuning.CycleAgreement`, issue 19): a model that does not
reproduce the measured period does not ``agree``, whatever prediction and
simulation say to each other.  As for a single loop's advice, the sticky
valve's estimate (its He or Kano model, the size combined over its windows) is
first simulated in the unit's model and, where it does not cycle as the unit
does, fitted to the measured cycle within its intervals
(:func:`analytics.cycle_fit.fit_valve_to_cycle`, ``valve_fit``); the model is
predicted with the valve that reproduces it, or the closest, with the error
stated.
"""

from __future__ import annotations

import json
from typing import Any

from fastapi import APIRouter, HTTPException
from sqlalchemy.orm import Session

from analytics.cycle_fit import CYCLES, fit_valve_to_cycle, valve_of
from analytics.errors import AnalyticsError
from analytics.limit_cycle import LimitCycleReport, equivalent_loop_phase
from analytics.plantwide import UnitDiagnosis
from analytics.quantification import StictionEstimate
from analytics.simulation import ClosedLoopModel
from analytics.tuning import CycleAgreement
from service.api.deps import (
    ERROR_RESPONSES,
    Analyst,
    SessionDep,
    StateDep,
    error_responses,
)
from service.api.schemas.prediction import UnitPrediction
from service.loop_model import valve_kind
from service.prediction import ModelError, check_model, predict_spec
from service.store.models import Loop, Unit
from service.stored import StoredDiagnosis, StoredValve
from service.tickets import latest_loop_run, latest_unit_run

router = APIRouter(prefix="/api/v1", tags=["units"],
                   responses={**ERROR_RESPONSES, **error_responses(404, 409)})

CONFIGURE_MATRIX = (
    "add 'process: {loops: [...], matrix: [[...]]}' to the unit in the plant file: one "
    "transfer function per row (PV) and column (valve) of the listed loops, entries as in "
    "the 'loopwatch predict' model file"
)


def _prediction_for(spec: str) -> LimitCycleReport:
    """The prediction is a pure function of the model (cached by its JSON with
    :meth:`service.runtime.AppState.analyse_cached`)."""
    _, report = predict_spec(json.loads(spec), source="unit model")
    return report


def _fitted_model(spec: str, sticky: int, period_s: float, amplitude: float | None,
                  intervals: str) -> tuple[dict[str, Any], dict[str, Any], str | None]:
    """The unit's model with loop ``sticky``'s valve fitted to the measured cycle
    (:func:`analytics.cycle_fit.fit_valve_to_cycle`, within the size's intervals), the fit
    (``valve_fit``), and why the harmonic balance cannot give the measured period, if it
    cannot (:func:`analytics.limit_cycle.equivalent_loop_phase`).  A pure function of its
    arguments (JSON text), cached like the prediction."""
    model_spec = json.loads(spec)
    model = ClosedLoopModel.from_dict(model_spec)
    S_interval, J_interval = (None if i is None else tuple(i) for i in json.loads(intervals))
    fit = fit_valve_to_cycle(model, period_s, amplitude, loop=sticky, S_interval=S_interval,
                             J_interval=J_interval)
    valves = list(model_spec["valves"])
    valves[sticky] = fit.chosen.valve.to_dict()
    phase = equivalent_loop_phase(model, sticky, period_s)
    describing = None
    if not -180.0 <= phase <= -90.0:
        describing = (
            f"the harmonic balance cannot give the measured {period_s:.3g} s with any size "
            f"of valve {sticky + 1}: the loop it sees there (the others closed, thesis Eq. "
            f"3.20) lags {-phase:.0f} degrees, and -1/N of a sticky valve lies between 90 "
            "and 180 degrees (thesis Table 5.1); the first-harmonic approximation does not "
            "describe this stick-slip cycle, the simulation is the model's prediction")
    # simulated as long as the fit simulated it: a 3 x 3 unit takes tens of periods to
    # settle into its cycle
    duration = max(model.duration, CYCLES * period_s)
    return {**model_spec, "valves": valves, "duration": duration}, fit.to_dict(), describing


def _controller(loop: Loop) -> dict[str, Any]:
    """The loop's configured controller in the model-file form (ideal PI/PID)."""
    config = loop.config.get("controller")
    if not config:
        raise HTTPException(409, f"Prediction not available: loop {loop.id!r} has no "
                                 "controller (Kc, Ti) in its configuration")
    controller = {"Kc": config["Kc"], "Td": config.get("Td", 0.0),
                  "action": config.get("action", "reverse")}
    if config.get("type") != "P" and config.get("Ti") is not None:
        controller["Ti"] = config["Ti"]
    return controller


def _valve(session: Session, loop_id: str
           ) -> tuple[dict[str, Any], dict[str, Any] | None, str | None,
                      tuple[tuple[float, float] | None, tuple[float, float] | None]]:
    """Where the loop's valve comes from (its entry of ``valves``), the valve in the
    model-file form (None: healthy), what is not known about it, and the intervals
    ``(S, J)`` of its size.

    A stiction finding gives the estimate's valve model (He or Kano, as the Hammerstein
    fit chose it; Choudhury for an estimate stored without one) at the size combined
    over the valve's windows (the final verdict's, :func:`service.verdicts.valve_size`;
    the latest estimate's when it has none; He's fs, fd when only those were
    estimated); no finding gives a healthy valve, and so does a valve the unit's
    diagnosis cleared (the run's final verdict, :func:`service.verdicts.valve_verdict`,
    with ``cleared_by_unit_run``: its loop cycles only with a sticky neighbour, thesis
    chapter 2).
    """
    unsized: tuple[None, None] = (None, None)
    run = latest_loop_run(session, loop_id)
    if run is None:
        return ({"loop": loop_id, "run_id": None, "verdict": None, "valve": None}, None,
                f"{loop_id}: not analysed yet; its valve is taken as healthy", unsized)
    healthy = {"loop": loop_id, "run_id": run.id, "verdict": run.verdict, "valve": None}
    diagnosis = StoredDiagnosis.from_dict(run.result)
    final = diagnosis.valve
    if final is not None and final.by_unit and run.verdict != "stiction":
        return {**healthy, "cleared_by_unit_run": final.unit_run_id}, None, None, unsized
    if run.verdict != "stiction":
        unknown = (f"{loop_id}: stiction undecided in analysis {run.id}; its valve is taken "
                   "as healthy") if run.verdict == "undecided" else None
        return healthy, None, unknown, unsized
    estimate = diagnosis.analysis.quantification
    # the final verdict's size, the unit's when the loop has none
    size: StoredValve | StictionEstimate | None = \
        final if final is not None and final.S is not None else estimate
    valve: dict[str, Any]
    if size is not None and size.S is not None:
        valve = valve_of(valve_kind(None if estimate is None else estimate.valve_model),
                         size.S, size.J or 0.0).to_dict()
    elif estimate is not None and estimate.fs is not None and estimate.fd is not None:
        valve = {"model": "he", "fs": estimate.fs, "fd": estimate.fd}
    else:
        raise HTTPException(409, f"Prediction not available: loop {loop_id!r} has a stiction "
                                 f"finding (analysis {run.id}) without a size estimate (S, J)")
    intervals = unsized if size is None else (size.S_interval, size.J_interval)
    return {**healthy, "valve": valve}, valve, None, intervals


def _measured_cycle(session: Session, unit_id: str, sticky: str
                    ) -> tuple[float | None, float | None, str | None]:
    """Period and OP amplitude of the cycle of loop ``sticky`` in the unit's latest ``ok``
    diagnosis (its oscillation group, :func:`analytics.plantwide.unit.diagnose_unit`), and
    what is not known about it; ``(None, None, None)`` when the diagnosis found no cycle
    of that loop."""
    run = latest_unit_run(session, unit_id, ok_only=True)
    if run is None or run.result is None:
        return None, None, (f"unit {unit_id!r} has no diagnosis yet: the prediction is not "
                            "checked against a measured cycle")
    diagnosis = UnitDiagnosis.from_dict(run.result, lenient=True)
    group = next((g for g in diagnosis.groups if sticky in g.loops), None)
    if group is None or group.period_s is None:
        return None, None, None
    member = next((m for m in group.members if m.signal == f"op_{sticky}"), None)
    return group.period_s, None if member is None else member.amplitude, None


def _against_measured(report: LimitCycleReport, loops: list[str], sticky: str,
                      period_s: float | None, amplitude: float | None) -> CycleAgreement:
    """The model's cycle against the measured one, for loop ``sticky``: the stable
    predicted cycle closest in period to the measured one (the slowest without a measured
    cycle) and the simulated cycle."""
    i = loops.index(sticky)
    stable = list(report.prediction.stable_cycles)
    if period_s is not None:
        stable.sort(key=lambda c: abs(c.period_s - period_s))
    predicted = (stable[0].period_s, stable[0].op_amplitudes[i]) if stable else (None, None)
    simulated = report.simulated
    sim = ((simulated.period_s, simulated.amplitudes[i]) if simulated.oscillating
           else (None, None))
    return CycleAgreement.between(period_s, amplitude, predicted, sim)


@router.get("/units/{unit_id}/prediction", response_model=UnitPrediction,
            response_model_exclude_unset=True)
def unit_prediction(unit_id: str, session: SessionDep, state: StateDep,
                    _: Analyst) -> dict[str, Any]:
    """The unit's stiction limit cycles: describing-function prediction and simulation.

    Every limit cycle of the unit's loops (frequency, period, OP amplitude per
    loop, stability) beside the cycle simulated with the same model, and the
    DF error (``comparison``), and both against the cycle of the first sticky
    loop in the unit's latest diagnosis (``comparison.measured_cycle``: period
    within 15 %, OP amplitude within 25 %); ``comparison.agree`` holds only when
    prediction, simulation and measurement agree (without a diagnosis:
    prediction and simulation, and ``unknown`` says so).  ``valves`` says where
    each valve comes from (a valve the unit's latest diagnosis clears is
    healthy, with ``cleared_by_unit_run``);
    ``unknown`` lists what was assumed.  404 for an unknown unit; 409 when the
    unit has no process matrix or a loop lacks a controller or a stiction size;
    422 when the loops are unstable without stiction.
    """
    if session.get(Unit, unit_id) is None:
        raise HTTPException(404, "Unit not found")
    unit = next((u for u in state.registry.plant.units if u.id == unit_id), None)
    if unit is None or unit.process is None:
        raise HTTPException(409, f"Prediction not available: unit {unit_id!r} has no process "
                                 f"matrix; {CONFIGURE_MATRIX}")
    loops = []
    for loop_id in unit.process.loops:
        loop = session.get(Loop, loop_id)
        if loop is None:  # the plant file and the store disagree (another replica's file)
            raise HTTPException(409, f"Prediction not available: the process matrix of unit "
                                     f"{unit_id!r} names loop {loop_id!r}, which is not in "
                                     "the store")
        loops.append(loop)
    controllers = [_controller(loop) for loop in loops]
    sources, valves, unknown, sizes = [], [], [], []
    for loop in loops:
        source, valve, note, size = _valve(session, loop.id)
        sources.append(source)
        valves.append(valve)
        sizes.append(size)
        if note:
            unknown.append(note)
    intervals = sorted({float(loop.config["ts"]) for loop in loops})
    if len(intervals) > 1:
        unknown.append(f"the loops are sampled every {intervals} s; the model is predicted "
                       f"and simulated at the shortest, {intervals[0]} s")
    answer = {"unit_id": unit_id, "loops": unit.process.loops, "dt": intervals[0],
              "valves": sources, "unknown": unknown}
    if all(valve is None for valve in valves):
        return {**answer, "limit_cycles": [], "simulated": None, "comparison": None,
                "note": "no valve of the unit has a stiction finding: no stiction limit "
                        "cycle to predict"}
    spec = {"dt": intervals[0], "process": {"matrix": unit.process.matrix},
            "controllers": controllers, "valves": valves, "names": unit.process.loops}
    i = next(i for i, valve in enumerate(valves) if valve is not None)
    sticky = unit.process.loops[i]
    period_s, amplitude, note = _measured_cycle(session, unit_id, sticky)
    if note:
        unknown.append(note)
    fit = describing = None
    try:
        if period_s is not None:
            check_model(spec)
            spec, fit, describing = state.analyse_cached(
                _fitted_model, json.dumps(spec, sort_keys=True), i, period_s, amplitude,
                json.dumps(sizes[i]))
        report = state.analyse_cached(_prediction_for, json.dumps(spec, sort_keys=True))
    except (ModelError, AnalyticsError) as exc:
        raise HTTPException(422, f"Prediction not available: {exc}") from None
    measured = _against_measured(report, unit.process.loops, sticky, period_s, amplitude)
    agree = report.agree
    if note is None:  # a diagnosis exists: the model must reproduce what it measured
        if period_s is None:  # ... which is no cycle of the sticky loop
            agree = agree and not (report.prediction.oscillates or report.simulated.oscillating)
        else:
            agree = agree and measured.agree
    fitted: dict[str, Any] = {} if fit is None else {"valve_fit": fit}
    if describing is not None:
        fitted["describing_note"] = describing
    return {**answer, **report.to_dict(), **fitted,
            "comparison": {**report.comparison_to_dict(), "agree": agree,
                           "measured_cycle": measured.to_dict()}}
