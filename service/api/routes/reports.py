"""The bad-actor report for a weekly meeting: the plant's worst loops with their KPIs.

``GET /api/v1/reports/bad-actors?period=7d&format=csv``: one row per loop,
worst first (the ranking of ``/plant/bad-actors``, :mod:`service.bad_actors`),
with its score and why, its latest diagnosis and KPIs, and its open tickets.
The PDF form is not built yet: ``format`` takes ``csv`` only.
"""

from __future__ import annotations

import csv
import io
from typing import Annotated, Any

from fastapi import APIRouter, Query
from fastapi.responses import Response
from sqlalchemy import func, select

from service.api.deps import ERROR_RESPONSES, SessionDep, StateDep
from service.api.routes.loops import PERIOD_PATTERN, Reader, bad_actor_rows, period_seconds
from service.store.models import AnalysisRun, Ticket

router = APIRouter(prefix="/api/v1/reports", tags=["reports"], responses=ERROR_RESPONSES)

COLUMNS = (
    "rank", "loop", "name", "unit", "importance", "score", "severity", "bad_share", "runs",
    "bad_runs", "worst", "why", "health", "oscillating", "period_s", "verdict",
    "oscillation_index", "harris_ratio", "error_std", "travel_per_day", "reversals_per_day",
    "saturation", "open_tickets",
)
"""The report's columns; the KPIs (% of span) are those of the latest analysis run."""

OPEN_TICKET_STATES = ("open", "acknowledged", "scheduled")


def _latest_kpis(session: SessionDep) -> dict[str, dict[str, Any]]:
    latest = (select(func.max(AnalysisRun.id)).where(AnalysisRun.status == "ok")
              .group_by(AnalysisRun.loop_id))
    rows = session.execute(select(AnalysisRun.loop_id, AnalysisRun.result["kpis"])
                           .where(AnalysisRun.id.in_(latest)))
    return {loop_id: kpis for loop_id, kpis in rows if kpis}


def _open_tickets(session: SessionDep) -> dict[str, list[str]]:
    tickets: dict[str, list[str]] = {}
    for ticket_id, loop_id, valve in session.execute(
        select(Ticket.id, Ticket.loop_id, Ticket.valve_asset)
        .where(Ticket.state.in_(OPEN_TICKET_STATES)).order_by(Ticket.id)
    ):
        tickets.setdefault(loop_id, []).append(f"#{ticket_id} {valve}")
    return tickets


def _number(value: Any, digits: int = 4) -> str:
    return "" if value is None else f"{float(value):.{digits}g}"


@router.get("/bad-actors", responses={200: {"content": {"text/csv": {}}}})
def bad_actor_report(
    session: SessionDep, state: StateDep, _: Reader,
    period: Annotated[str, Query(pattern=PERIOD_PATTERN)] = "7d",
    fmt: Annotated[str, Query(alias="format", pattern="^csv$")] = "csv",
    limit: Annotated[int, Query(ge=1, le=10_000)] = 1000,
) -> Response:
    """The bad-actor report over ``period`` as CSV (the only ``format`` so far)."""
    until = state.clock()
    since = until - period_seconds(period)
    ranked = bad_actor_rows(session, since, until, period, state.settings.window_s)[:limit]
    kpis, tickets = _latest_kpis(session), _open_tickets(session)
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(COLUMNS)
    for rank, row in enumerate(ranked, start=1):
        k = kpis.get(row.id, {})
        writer.writerow([
            rank, row.id, row.name, row.unit or "", row.importance, _number(row.score),
            _number(row.severity), _number(row.bad_share), row.runs, row.bad_runs,
            row.worst or "", row.why, _number(row.health),
            "" if row.oscillating is None else str(row.oscillating).lower(),
            _number(row.period_s), row.verdict or "",
            _number(k.get("oscillation_index")), _number((k.get("harris") or {}).get("ratio")),
            _number((k.get("error") or {}).get("std")), _number(k.get("travel_per_day")),
            _number(k.get("reversals_per_day")), _number(k.get("saturation")),
            "; ".join(tickets.get(row.id, [])),
        ])
    filename = f"bad-actors-{period}.csv"
    return Response(out.getvalue(), media_type="text/csv; charset=utf-8",
                    headers={"Content-Disposition": f'attachment; filename="{filename}"'})
