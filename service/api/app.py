"""The FastAPI application: routers, protections, error translation, the OpenAPI schema.

Every route needs an API key except the liveness probe ``/healthz`` and the
dashboard shell (``/`` and ``/static/*``: fixed files holding no plant data;
the page asks for a key and sends it with every API call).

The OpenAPI schema is served at ``/openapi.json`` to any active key (of any
role): it is part of the API, every client that uses it holds a key, and it
maps every route and role for whoever reads it.  The interactive ``/docs``
and ``/redoc`` pages are not served: they fetch the schema without a key,
and they load their code from a public CDN with an inline script, which a
plant network without internet access cannot reach and the Content Security
Policy of :mod:`service.security` forbids.  Tools that read OpenAPI
(Swagger UI or Postman on a workstation, client generators, schemathesis)
take the schema with the key in the ``X-API-Key`` header.

Every error answer has one shape, :class:`service.api.deps.Error`: a
``detail`` sentence, or for a request that does not fit the schema one
``{loc, msg, type}`` entry per problem (the first :data:`MAX_PROBLEMS`).
A bug is answered with a JSON 500 and logged once with its traceback
(:class:`UnexpectedErrorMiddleware`); the client's connection stays open.
"""

from __future__ import annotations

import logging
from typing import Annotated, Any

from fastapi import Depends, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy.exc import DataError, DBAPIError
from sqlalchemy.exc import TimeoutError as PoolTimeoutError
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.alarms import AlarmStateError
from service.api.deps import Principal, require
from service.api.routes import (
    advice,
    alarms,
    dashboard,
    ingest,
    keys,
    loops,
    model_check,
    plots,
    reports,
    system,
    tickets,
    unit_diagnosis,
    unit_prediction,
)
from service.logs import RequestIdMiddleware
from service.runtime import AnalysisUnavailableError, AppState
from service.security import install_protections, retry_after
from service.spool import StoreUnavailableError, is_store_outage
from service.tickets import TicketStateError

__all__ = ["MAX_PROBLEMS", "UnexpectedErrorMiddleware", "create_app"]

log = logging.getLogger(__name__)

MAX_PROBLEMS = 20
"""Problems listed in a 422 for a request that does not fit the schema."""

INTERNAL_ERROR = b'{"detail":"Internal server error"}'


class UnexpectedErrorMiddleware:
    """Answer an exception no handler took (a bug) with a JSON 500 and log it once.

    Starlette's own last-resort handler re-raises after answering, so uvicorn
    logs the error a second time and drops the keep-alive connection without
    ``Connection: close``; here the exception ends with the answer.  If the
    response had already started, it cannot be replaced: it is left
    unfinished and uvicorn closes the connection.
    """

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = False

        async def tracked_send(message: Message) -> None:
            nonlocal started
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, receive, tracked_send)
        except Exception:
            log.exception("%s %s: unexpected error", scope["method"], scope["path"])
            if started:
                return
            await send({"type": "http.response.start", "status": 500,
                        "headers": [(b"content-type", b"application/json"),
                                    (b"content-length", str(len(INTERNAL_ERROR)).encode())]})
            await send({"type": "http.response.body", "body": INTERNAL_ERROR})


def openapi_with_json_errors(app: FastAPI) -> dict[str, Any]:
    """The app's OpenAPI schema, every error answer as the JSON :class:`Error` body
    (FastAPI files a route's errors under its own media type: text/plain for
    ``/metrics``, images for plots)."""
    if app.openapi_schema is None:
        schema = app.openapi()
        for operations in schema["paths"].values():
            for operation in operations.values():
                for status, response in operation["responses"].items():
                    if status[0] in "45":
                        response["content"] = {"application/json": {
                            "schema": {"$ref": "#/components/schemas/Error"}}}
    return app.openapi()


def create_app(state: AppState) -> FastAPI:
    """The API over ``state`` (the caller starts and stops background work)."""
    app = FastAPI(
        title="loopwatch",
        summary="Control-loop monitoring: oscillation, valve stiction, alarms and repair tickets",
        version="0.1.0",
        openapi_url=None,
        docs_url=None,
        redoc_url=None,
    )
    app.state.loopwatch = state
    for module in (system, loops, advice, unit_diagnosis, unit_prediction, plots, model_check,
                   alarms, tickets, reports, ingest, keys, dashboard):
        app.include_router(module.router)

    @app.get("/openapi.json", include_in_schema=False)
    def openapi_schema(_: Annotated[Principal, Depends(require(None))]) -> dict[str, Any]:
        """The OpenAPI schema of the API (any active key)."""
        return openapi_with_json_errors(app)

    app.add_middleware(UnexpectedErrorMiddleware)  # innermost: its 500 gets the headers
    install_protections(app, state.settings)
    app.add_middleware(RequestIdMiddleware)  # outermost: every record of a request has its id
    unavailable_retry = retry_after(state.settings.spool_retry_s)

    @app.exception_handler(RequestValidationError)
    async def invalid_request(_: Request, exc: RequestValidationError) -> JSONResponse:
        """A request that does not fit the schema: 422 with where and what, never the
        input (it may be a secret or megabytes long)."""
        problems = [{"loc": list(e["loc"]), "msg": e["msg"], "type": e["type"]}
                    for e in exc.errors()[:MAX_PROBLEMS]]
        return JSONResponse(status_code=422, content={"detail": problems})

    @app.exception_handler(AnalysisUnavailableError)
    async def analysis_unavailable(_: Request, exc: AnalysisUnavailableError) -> JSONResponse:
        """The analysis process died or the analysis ran too long: 503."""
        return JSONResponse(status_code=503, content={"detail": str(exc)}, headers={
            "Retry-After": retry_after(state.settings.analysis_retry_s)})

    @app.exception_handler(PoolTimeoutError)
    async def store_busy(request: Request, _: PoolTimeoutError) -> JSONResponse:
        """Every database connection stayed busy while the request waited: 503."""
        log.warning("%s %s: no database connection free", request.method, request.url.path)
        return JSONResponse(status_code=503, headers={"Retry-After": unavailable_retry},
                            content={"detail": "The store is busy; try again later"})

    @app.exception_handler(AlarmStateError)
    @app.exception_handler(TicketStateError)
    async def conflict(_: Request, exc: ValueError) -> JSONResponse:
        """An alarm or ticket transition that its state does not allow: 409."""
        return JSONResponse(status_code=409, content={"detail": str(exc)})

    @app.exception_handler(StoreUnavailableError)
    async def store_unavailable(_: Request, exc: StoreUnavailableError) -> JSONResponse:
        """The store is unreachable and the request cannot wait for it: 503."""
        return JSONResponse(status_code=503, content={"detail": str(exc)},
                            headers={"Retry-After": unavailable_retry})

    @app.exception_handler(DBAPIError)
    async def database_error(request: Request, exc: DBAPIError) -> JSONResponse:
        """A value the store cannot hold (too long for its column, a NUL character): 422
        with the database's reason; the store unreachable: 503 (the driver's message, with
        host names, stays in the log); any other database error is a bug: 500."""
        if isinstance(exc, DataError):
            reason = str(exc.orig).strip().splitlines()[0] if str(exc.orig).strip() else ""
            return JSONResponse(status_code=422, content={
                "detail": f"A value cannot be stored: {reason or type(exc.orig).__name__}"})
        if not is_store_outage(exc):
            raise exc
        log.warning("%s %s: store unreachable: %s", request.method, request.url.path,
                    str(exc.orig).strip() or type(exc.orig).__name__)
        return await store_unavailable(
            request, StoreUnavailableError("The store is unreachable; try again later")
        )

    return app
