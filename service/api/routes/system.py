"""Liveness probe and Prometheus metrics."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends
from fastapi.responses import PlainTextResponse
from sqlalchemy import func, select

from service.api.deps import ERROR_RESPONSES, Principal, SessionDep, StateDep, require
from service.store.models import Alarm, Loop, Ticket

router = APIRouter(tags=["system"])


@router.get("/healthz")
def liveness() -> dict[str, str]:
    """Liveness probe (no key needed)."""
    return {"status": "ok"}


@router.get("/metrics", response_class=PlainTextResponse, responses=ERROR_RESPONSES)
def metrics(
    session: SessionDep, state: StateDep, _: Annotated[Principal, Depends(require("read"))]
) -> str:
    """Counters and gauges in the Prometheus text format; per connector whether data
    comes now (``loopwatch_connector_up``), its outages and their total length, and its
    samples since start: made, bad, delivered to ingest, given up, still on their way."""
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
    now = state.clock()
    for source in state.sources:
        outages = source.outages
        label = f'{{connector="{source.name}"}}'
        gauges[f"loopwatch_connector_up{label}"] = float(not outages or outages[-1].end is not None)
        gauges[f"loopwatch_connector_outages{label}"] = float(len(outages))
        gauges[f"loopwatch_connector_outage_seconds{label}"] = sum(
            (now if o.end is None else o.end) - o.start for o in outages)
        counters = source.counters
        for count in ("samples", "bad", "delivered", "undelivered", "pending"):
            gauges[f"loopwatch_connector_{count}{label}"] = float(getattr(counters, count))
    return state.metrics.render(gauges)
