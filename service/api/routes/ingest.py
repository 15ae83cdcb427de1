"""Historian push: JSON batches (PI Web API ``streamsets/recorded`` shape) and CSV."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Body, Depends, HTTPException, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse

from service.api.deps import Principal, StateDep, require
from service.ingest import IngestError, IngestReport, TagItems

router = APIRouter(prefix="/api/v1/ingest", tags=["ingest"])
Historian = Annotated[Principal, Depends(require("ingest"))]

MAX_CSV_BYTES = 20 * 1024 * 1024


def _response(report: IngestReport) -> JSONResponse:
    """200 when every item was taken, 207 when part of the batch was refused."""
    return JSONResponse(status_code=207 if report.partial else 200, content=report.as_dict())


@router.post(
    "",
    responses={200: {"description": "every item stored or already stored"},
               207: {"description": "part of the batch refused; see the per-tag report"}},
)
def ingest(
    batch: Annotated[list[TagItems], Body()], state: StateDep, _: Historian
) -> JSONResponse:
    """Store samples of many tags: ``[{tag, items: [{timestamp, value, good}]}]``.

    Idempotent: items already stored with the same value count as
    ``already_stored``.  Unknown tags, bad timestamps, duplicates and
    conflicts are refused and counted per tag; NaN, null or ``good: false``
    values are stored as bad samples.
    """
    try:
        return _response(state.ingest(batch))
    except IngestError as exc:
        raise HTTPException(422, str(exc)) from None


@router.post(
    "/csv",
    openapi_extra={"requestBody": {"content": {"text/csv": {"schema": {"type": "string"}}}}},
)
async def ingest_csv(request: Request, state: StateDep, _: Historian) -> JSONResponse:
    """Store a CSV upload: long (``tag,timestamp,value[,good]``) or wide (a time column,
    then one column per tag)."""
    body = await request.body()
    if len(body) > MAX_CSV_BYTES:
        raise HTTPException(413, f"CSV larger than {MAX_CSV_BYTES // (1024 * 1024)} MiB")
    try:
        text = body.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise HTTPException(422, f"CSV is not UTF-8 text: {exc.reason} at byte {exc.start}") \
            from None
    try:
        report = await run_in_threadpool(state.ingest_csv, text)
    except IngestError as exc:
        raise HTTPException(422, str(exc)) from None
    return _response(report)

