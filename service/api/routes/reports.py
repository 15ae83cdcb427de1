"""The bad-actor report for a weekly meeting: the plant's worst loops with their KPIs.

``GET /api/v1/reports/bad-actors?period=7d&format=csv|pdf``: the loops worst
first (the ranking of ``/plant/bad-actors``, :mod:`service.bad_actors`), with
their score and why, latest diagnosis and KPIs, open tickets and, in the PDF,
a sparkline of each loop's severity over the period (:mod:`service.report`).
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query
from fastapi.responses import Response

from service.api.deps import ERROR_RESPONSES, Reader, SessionDep, StateDep, period_seconds
from service.api.schemas.files import BINARY, TEXT
from service.ranking import PERIOD_PATTERN
from service.report import build_report, report_csv, report_pdf

router = APIRouter(prefix="/api/v1/reports", tags=["reports"], responses=ERROR_RESPONSES)


@router.get("/bad-actors", response_class=Response,
            responses={200: {"content": {"text/csv": TEXT, "application/pdf": BINARY},
                             "description": "the report as a file"}})
def bad_actor_report(
    session: SessionDep, state: StateDep, _: Reader,
    period: Annotated[str, Query(pattern=PERIOD_PATTERN)] = "7d",
    fmt: Annotated[str, Query(alias="format", pattern="^(csv|pdf)$")] = "csv",
    limit: Annotated[int, Query(ge=1, le=10_000)] = 1000,
) -> Response:
    """The bad-actor report over ``period`` as a CSV file or a PDF document."""
    report = build_report(session, until=state.clock(), period_s=period_seconds(period),
                          period=period, window_s=state.settings.window_s, limit=limit)
    filename = f"bad-actors-{period}.{fmt}"
    headers = {"Content-Disposition": f'attachment; filename="{filename}"'}
    if fmt == "pdf":
        return Response(report_pdf(report), media_type="application/pdf", headers=headers)
    return Response(report_csv(report), media_type="text/csv; charset=utf-8", headers=headers)
