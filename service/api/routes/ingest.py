"""Historian push: JSON batches (simple, or a PI Web API ``streamsets/recorded`` answer)
and CSV."""

from __future__ import annotations

from typing import Any, cast

from fastapi import APIRouter, HTTPException, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse
from pydantic import TypeAdapter

from service.api.deps import ERROR_RESPONSES, Historian, StateDep
from service.api.schemas.ingest import IngestAnswer
from service.ingest import IngestError, IngestReport, PiStream, PiStreams, TagItems

router = APIRouter(prefix="/api/v1/ingest", tags=["ingest"], responses=ERROR_RESPONSES)

MAX_CSV_BYTES = 20 * 1024 * 1024

INGEST_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {"model": IngestAnswer, "description": "every item stored or already stored"},
    207: {"model": IngestAnswer,
          "description": "part of the batch refused; see the per-tag report"},
}


def _response(report: IngestReport) -> JSONResponse:
    """200 when every item was taken, 207 when part of the batch was refused."""
    return JSONResponse(status_code=207 if report.partial else 200, content=report.as_dict())


def _inlined(schema: dict[str, Any]) -> dict[str, Any]:
    """``schema`` with its ``$defs`` references replaced by the definitions."""
    defs = schema.pop("$defs", {})

    def resolve(node: Any) -> Any:
        if isinstance(node, dict):
            if "$ref" in node:
                return resolve(defs[node["$ref"].rsplit("/", 1)[1]])
            return {k: resolve(v) for k, v in node.items()}
        return [resolve(v) for v in node] if isinstance(node, list) else node

    return cast(dict[str, Any], resolve(schema))


BATCH_SCHEMA = _inlined(TypeAdapter(list[TagItems] | PiStreams | list[PiStream]).json_schema())


@router.post(
    "",
    responses=INGEST_RESPONSES,
    openapi_extra={"requestBody": {"required": True, "content": {
        "application/json": {"schema": BATCH_SCHEMA}}}},
)
async def ingest(request: Request, state: StateDep, _: Historian) -> JSONResponse:
    """Store samples of many tags: ``[{tag, items: [{timestamp, value, good}]}]``, or a
    PI Web API ``streamsets/recorded`` answer (``{Items: [{WebId, Name, Path, Items:
    [{Timestamp, Value, Good, ...}]}]}``, its streams mapped to tags by the plant file's
    ``pi_points``, by Path or Name; digital system states are stored as bad samples).

    Idempotent: items already stored with the same value count as
    ``already_stored``.  Unknown tags, bad timestamps, duplicates and
    conflicts are refused and counted per tag; NaN, null or ``good: false``
    values are stored as bad samples.  A batch of more than
    ``LOOPWATCH_MAX_BATCH_SAMPLES`` entries or items is refused (422) before it
    is validated; the body is read here and parsed and stored in the thread
    pool, so no batch holds up the event loop.
    """
    body = await request.body()
    try:
        return _response(await run_in_threadpool(state.ingest_json, body))
    except IngestError as exc:
        raise HTTPException(422, str(exc)) from None


@router.post(
    "/csv",
    responses=INGEST_RESPONSES,
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

