"""Tuning advice for an oscillating loop (thesis chapter 5), checked against the measured
cycle: retunes for a sticky valve verified by simulation, detuning for an over-tuned loop."""

from __future__ import annotations

import dataclasses
import json
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Query

from analytics.cycle_fit import fit_valve_to_cycle
from analytics.errors import AnalyticsError
from analytics.tuning import (
    MAX_LOAD_ERROR_RATIO,
    CycleAgreement,
    Detuning,
    Tuning,
    advise,
    cycle_origin,
    detune,
)
from service.api.deps import ERROR_RESPONSES, Analyst, SessionDep, StateDep, error_responses
from service.api.schemas.advice import LoopAdvice
from service.loop_model import ModelUnavailableError, identified_loop
from service.store.models import Loop
from service.stored import StoredDiagnosis
from service.tickets import latest_loop_run

router = APIRouter(prefix="/api/v1", tags=["advice"],
                   responses={**ERROR_RESPONSES, **error_responses(404, 409)})

SIMULATED_S = 4000.0
"""Length of the simulations that verify each candidate tuning."""


def _advice_for_run(run_id: int, config: str, diagnosis: str, max_load_error_ratio: float
                    ) -> dict[str, Any]:
    """Advice for a sticky valve, from a model checked against the measured cycle.

    The estimate's valve is simulated in the identified loop first; where the
    model does not cycle as the loop does, the valve is fitted to the measured
    cycle (:func:`analytics.cycle_fit.fit_valve_to_cycle`: its model, then its
    size within the estimate's intervals), and the advice is computed on the
    valve that reproduces it, or on the closest one with the error stated.
    A He valve's describing function is Eq. 3.4 at its equivalent S and J (its
    own sinusoidal DF is zero at the OP amplitudes below S / 2 of its stick-slip
    cycles, so it would predict no cycle anywhere on the map).  Every retune is
    checked once more with the window's PV noise, which keeps a sticky valve
    slipping where the noise-free model comes to rest.  No retune may leave more than
    ``max_load_error_ratio`` times the current error after a load step.

    A pure function of the run and the loop's configuration (cached by
    :meth:`service.runtime.AppState.analyse_cached`; ``run_id`` is its key)."""
    stored = StoredDiagnosis.from_dict(json.loads(diagnosis))
    model = identified_loop(json.loads(config), stored)
    period, amplitude = stored.oscillation.period_s, stored.oscillation.amplitude_op
    loop_model = model.closed_loop(SIMULATED_S)
    fit = fit_valve_to_cycle(loop_model, period, amplitude, S_interval=model.S_interval,
                             J_interval=model.J_interval)
    noise = stored.analysis.pv_noise  # None for runs stored before it was kept
    advice = advise(fit.fitted(loop_model), describing="equivalent",
                    measurement_noise=None if noise is None else (noise,),
                    max_load_error_ratio=max_load_error_ratio)
    agreement = CycleAgreement.of(advice, period, amplitude)
    if fit.changed:
        advice = dataclasses.replace(advice, notes=(fit.explanation(), *advice.notes))
    return {"kind": "stiction", **advice.to_dict(), "valve_fit": fit.to_dict(),
            "measured_cycle": agreement.to_dict()}


def _detuning(config: dict[str, Any], period_s: float) -> Detuning:
    """Detuning of a loop that cycles with a healthy valve (:func:`analytics.tuning.detune`)."""
    controller = config["controller"]
    tuning = Tuning(float(controller["Kc"]), float(controller.get("Ti") or "inf"))
    return detune(tuning, period_s)


@router.get("/loops/{loop_id}/advice", response_model=LoopAdvice)
def loop_advice(
    loop_id: str, session: SessionDep, state: StateDep, _: Analyst,
    max_load_error_ratio: Annotated[float, Query(
        ge=1.0, description="Most a retune may multiply the error a load step leaves "
        "(integrated error Ti/|Kc| under PI, the offset under P) against the current "
        "tuning; 'inf' searches the whole box")] = MAX_LOAD_ERROR_RATIO,
) -> dict[str, Any]:
    """What to retune, from a model checked against the loop's measured cycle.

    A sticky valve (final verdict ``stiction``): retunes that remove or reduce the
    stiction cycle until the valve is repaired, from the latest estimate (S, J and the
    identified process) and the configured controller; every offer carries its predicted
    effect and was checked in simulation (also with the measured PV noise), slows the
    rejection of loads at most ``max_load_error_ratio`` times, and ``measured_cycle``
    says whether the model reproduces the measured cycle. A loop that cycles with a
    healthy valve: detuning with the predicted gain margin.  404 for an unknown loop;
    409 with the reason and what to configure when the loop has no controller, no
    analysis, no cycle, a valve cleared by its unit's diagnosis, a cycle of steady
    amplitude with a healthy valve (forced from outside:
    :func:`analytics.tuning.cycle_origin`), or a model the advice cannot analyse.
    """
    loop = session.get(Loop, loop_id)
    if loop is None:
        raise HTTPException(404, "Loop not found")
    if not loop.config.get("controller"):
        raise HTTPException(409, "Advice not available: the loop's configuration has no "
                                 "controller; configure controller: {type: PI, Kc, Ti, action} "
                                 f"(plant file or PUT /api/v1/loops/{loop_id})")
    run = latest_loop_run(session, loop_id)
    if run is None or run.result is None:
        raise HTTPException(409, "Advice not available: the loop has not been analysed yet")
    result = run.result
    stored = StoredDiagnosis.from_dict(result)
    valve = stored.valve
    verdict = stored.final.verdict
    oscillating = stored.oscillation.detected
    if verdict != "stiction":
        if not oscillating:
            raise HTTPException(409, "Advice not available: the loop does not cycle and its "
                                     "valve is not sticky; there is nothing to retune")
        if valve is not None and valve.by_unit:
            raise HTTPException(409, f"Advice not available: the loop {valve.reason} (unit "
                                     f"{valve.unit_id}'s diagnosis); retuning it would not "
                                     "remove the cause: see the advice for that valve's loop")
        if verdict != "no_stiction":
            raise HTTPException(409, "Advice not available: the loop cycles but whether its "
                                     f"valve sticks is {verdict}; no model to advise from")
        oscillation = stored.oscillation
        assert oscillation.period_s is not None and stored.analysis.samples is not None \
            and stored.analysis.ts is not None  # a detected oscillation of an analysed window
        origin, why = cycle_origin(
            stored.analysis.envelope_variation,
            stored.analysis.samples * stored.analysis.ts / oscillation.period_s,
            stored.kpis.saturation)
        if origin == "forced":
            raise HTTPException(409, f"Advice not available: {why}")
        detuning = _detuning(loop.config, float(oscillation.period_s))
        return {"loop_id": loop_id, "run_id": run.id,
                **dataclasses.replace(detuning, notes=(*detuning.notes, why)).to_dict()}
    try:
        identified_loop(loop.config, stored)
    except ModelUnavailableError as exc:
        raise HTTPException(409, f"Advice not available: {exc}") from None
    try:
        advice = state.analyse_cached(
            _advice_for_run, run.id, json.dumps(loop.config, sort_keys=True),
            json.dumps(result, sort_keys=True), max_load_error_ratio,
        )
    except AnalyticsError as exc:
        # the identified model is beyond what the analysis handles: the server's limit
        raise HTTPException(409, f"Advice not available for the identified model: {exc}"
                            ) from None
    return {"loop_id": loop_id, "run_id": run.id, **advice}
