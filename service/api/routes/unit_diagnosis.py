"""Multi-loop stiction diagnosis of a unit (thesis chapter 2) on its latest windows."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, HTTPException
from sqlalchemy import select

from analytics.errors import AnalyticsError
from service.analysis import UnitWindowsError, analyse_unit, unit_windows
from service.api.deps import ERROR_RESPONSES, Analyst, SessionDep, StateDep, error_responses
from service.api.schemas.units import UnitDiagnosisPublic
from service.config import LoopConfig
from service.store.models import Loop, Unit
from service.tickets import latest_unit_run
from service.verdicts import named_valves

router = APIRouter(prefix="/api/v1", tags=["units"],
                   responses={**ERROR_RESPONSES, **error_responses(404)})


@router.get("/units/{unit_id}/diagnosis", response_model=UnitDiagnosisPublic,
            response_model_exclude_unset=True)
def unit_diagnosis(unit_id: str, session: SessionDep, state: StateDep,
                   _: Analyst) -> dict[str, Any]:
    """Which valves of the unit stick: oscillation groups, the shape decomposition, the
    surrogate ranking of every OP and PV, and the named valves with their confidence.
    Valves are named by their tags (:func:`service.verdicts.named_valves`): each
    group's ``sticky_valves`` lists valve tags and ``sticky_loops`` their loops.

    The scheduler's latest diagnosis of the unit (``source`` "scheduler", with
    its ``round_end``; 422 with the reason if it failed).  Only when none is
    stored is it computed now (``source`` "on_demand") from each loop's
    latest window (``LOOPWATCH_WINDOW_S``; from the store on an API replica); the loops
    must share one sampling interval.  404 without loops or data; 422 when
    the windows cannot be analysed together.
    """
    if session.get(Unit, unit_id) is None:
        raise HTTPException(404, "Unit not found")
    loops = [LoopConfig.model_validate(loop.config) for loop in session.scalars(
        select(Loop).where(Loop.unit_id == unit_id).order_by(Loop.id))]
    valves = {loop.id: loop.valve_asset or loop.id for loop in loops}
    stored = latest_unit_run(session, unit_id)
    if stored is not None:
        if stored.result is None:
            raise HTTPException(422, "Unit diagnosis not available: the scheduler's latest "
                                     f"attempt ended '{stored.status}': {stored.error}")
        return {"unit_id": unit_id, "source": "scheduler", "round_end": stored.round_end,
                "window_end": stored.window_end,
                "loops_without_complete_window": stored.incomplete_loops,
                **named_valves(stored.result, valves)}
    now = state.clock()
    if not loops:
        raise HTTPException(404, "Unit diagnosis not available: the unit has no loops")
    window_s = state.settings.window_s
    windows = unit_windows(state.buffers_for(session, loops, window_s, now), loops, window_s,
                           now)
    if not windows.signals:
        raise HTTPException(404, "Unit diagnosis not available: no loop of the unit has a "
                                 "complete OP and PV window")
    try:
        result = state.analyse(analyse_unit, windows.signals, windows.ts)
    except (UnitWindowsError, AnalyticsError) as exc:
        raise HTTPException(422, f"Unit diagnosis not available: {exc}") from None
    return {"unit_id": unit_id, "source": "on_demand", "round_end": None, "window_end": now,
            "loops_without_complete_window": list(windows.incomplete),
            **named_valves(result, valves)}
