"""Multi-loop stiction diagnosis of a unit (thesis chapter 2) on its latest windows."""

from __future__ import annotations

from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Depends, HTTPException
from fastapi.concurrency import run_in_threadpool
from sqlalchemy import select

from analytics.errors import AnalyticsError
from analytics.plantwide import diagnose_unit
from service.api.deps import Principal, SessionDep, StateDep, require
from service.store.models import Loop, Unit

router = APIRouter(tags=["units"])  # included by the loops router under /api/v1
Reader = Annotated[Principal, Depends(require("read"))]


@router.get("/units/{unit_id}/diagnosis")
async def unit_diagnosis(unit_id: str, session: SessionDep, state: StateDep,
                         _: Reader) -> dict[str, Any]:
    """Which valves of the unit stick: oscillation groups, the shape decomposition, the
    surrogate ranking of every OP and PV, and the named valves with their confidence.

    Runs on each loop's latest analysis window (``LOOPWATCH_WINDOW_S``) from the
    rolling buffers; the loops must share one sampling interval.  404 without
    loops or data; 422 when the windows cannot be analysed together.
    """
    if session.get(Unit, unit_id) is None:
        raise HTTPException(404, "Unit not found")
    loops = list(session.scalars(select(Loop).where(Loop.unit_id == unit_id)
                                 .order_by(Loop.id)))
    now = state.clock()
    signals: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    intervals = set()
    for loop in loops:
        window = state.buffers.window(loop.id, state.settings.window_s, now)
        op, pv = window.op, window.pv
        if op is not None and pv is not None and np.isfinite(op).all() and np.isfinite(pv).all():
            signals[loop.id] = (op, pv)
            intervals.add(window.ts)
    if not signals:
        raise HTTPException(404, "Unit diagnosis not available: no loop of the unit has a "
                                 "complete OP and PV window in the buffers")
    if len(intervals) > 1:
        raise HTTPException(422, "Unit diagnosis needs one sampling interval for all loops; "
                                 f"the unit has {sorted(intervals)}")
    try:
        result = await run_in_threadpool(
            diagnose_unit, signals, intervals.pop()
        )
    except AnalyticsError as exc:
        raise HTTPException(422, f"Unit diagnosis not available: {exc}") from None
    skipped = sorted({loop.id for loop in loops} - set(signals))
    return {"unit_id": unit_id, "window_end": now, "loops_without_complete_window": skipped,
            **result.to_dict()}
