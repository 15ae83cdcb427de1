"""Liveness probe and Prometheus metrics."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends
from fastapi.responses import PlainTextResponse
from sqlalchemy import func, select

from service.api.deps import Principal, SessionDep, StateDep, require
from service.store.models import Alarm, Loop, Ticket

router = APIRouter(tags=["system"])


@router.get("/healthz")
def liveness() -> dict[str, str]:
    """Liveness probe (no key needed)."""
    return {"status": "ok"}


@router.get("/metrics", response_class=PlainTextResponse)
def metrics(
    session: SessionDep, state: StateDep, _: Annotated[Principal, Depends(require("read"))]
) -> str:
    """Counters and gauges in the Prometheus text format."""
    gauges = {
        "loopwatch_loops": float(session.scalar(select(func.count()).select_from(Loop)) or 0),
        "loopwatch_alarms_active": float(
            session.scalar(select(func.count()).where(Alarm.state != "normal")) or 0
        ),
        "loopwatch_tickets_open": float(
            session.scalar(
                select(func.count()).where(Ticket.state.in_(("open", "acknowledged", "scheduled")))
            ) or 0
        ),
    }
    return state.metrics.render(gauges)
