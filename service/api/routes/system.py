"""Liveness probe and Prometheus metrics."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends
from fastapi.responses import PlainTextResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST

from service.api.deps import ERROR_RESPONSES, Principal, StateDep, require
from service.api.schemas.system import Liveness

router = APIRouter(tags=["system"])


@router.get("/healthz")
def liveness() -> Liveness:
    """Liveness probe (no key needed)."""
    return Liveness(status="ok")


@router.get("/metrics", response_class=PlainTextResponse, responses=ERROR_RESPONSES)
def metrics(state: StateDep, _: Annotated[Principal, Depends(require("read"))]) -> Response:
    """Counters, gauges and histograms in the Prometheus text format
    (:mod:`service.metrics`): ingest, analyses and their durations, the store's loops,
    alarms and tickets, and per connector whether data comes now
    (``loopwatch_connector_up``), its outages and their total length, and its samples
    since start: made, bad, delivered to ingest, given up, still on their way."""
    return Response(state.metrics.render(), media_type=CONTENT_TYPE_LATEST)
