"""Tuning advice for a loop with a sticky valve (thesis chapter 5), verified by simulation."""

from __future__ import annotations

import json
from typing import Any

from fastapi import APIRouter, HTTPException

from analytics.errors import AnalyticsError
from analytics.tuning import advise
from service.api.deps import Analyst, SessionDep, StateDep, error_responses
from service.loop_model import ModelUnavailableError, identified_loop
from service.store.models import Loop
from service.tickets import latest_loop_run

# included by the loops router under /api/v1
router = APIRouter(tags=["advice"], responses=error_responses(409))

SIMULATED_S = 4000.0
"""Length of the simulations that verify each candidate tuning."""


def _advice_for_run(run_id: int, config: str, diagnosis: str) -> dict[str, Any]:
    """Advice is a pure function of the run and the loop's configuration (cached by
    :meth:`service.runtime.AppState.analyse_cached`; ``run_id`` is its key)."""
    model = identified_loop(json.loads(config), json.loads(diagnosis))
    return advise(model.closed_loop(SIMULATED_S)).to_dict()


@router.get("/loops/{loop_id}/advice")
def loop_advice(loop_id: str, session: SessionDep, state: StateDep, _: Analyst) -> dict[str, Any]:
    """Retunes that remove or reduce the stiction cycle until the valve is repaired.

    Built from the latest stiction estimate (S, J and the identified process)
    and the configured controller; every offer carries its predicted effect
    and was checked in simulation.  404 for an unknown loop; 409 with the reason
    when the loop has no estimate or no controller configuration (as the unit
    prediction does).
    """
    loop = session.get(Loop, loop_id)
    if loop is None:
        raise HTTPException(404, "Loop not found")
    run = latest_loop_run(session, loop_id)
    if run is None:
        raise HTTPException(409, "Advice not available: the loop has not been analysed yet")
    try:
        identified_loop(loop.config, run.result)
    except ModelUnavailableError as exc:
        raise HTTPException(409, f"Advice not available: {exc}") from None
    try:
        advice = state.analyse_cached(
            _advice_for_run, run.id, json.dumps(loop.config, sort_keys=True),
            json.dumps(run.result, sort_keys=True),
        )
    except AnalyticsError as exc:
        raise HTTPException(422, f"Advice not available: {exc}") from None
    return {"loop_id": loop_id, "run_id": run.id, **advice}
