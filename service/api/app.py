"""The FastAPI application: routers, error translation, OpenAPI at ``/docs``."""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse

from service.alarms import AlarmStateError
from service.api.routes import alarms, dashboard, ingest, keys, loops, plots, system, tickets
from service.runtime import AppState
from service.tickets import TicketStateError

__all__ = ["create_app"]


def create_app(state: AppState) -> FastAPI:
    """The API over ``state`` (the caller starts and stops background work)."""
    app = FastAPI(
        title="loopwatch",
        summary="Control-loop monitoring: oscillation, valve stiction, alarms and repair tickets",
        version="0.1.0",
    )
    app.state.loopwatch = state
    for module in (system, loops, plots, alarms, tickets, ingest, keys, dashboard):
        app.include_router(module.router)

    @app.exception_handler(AlarmStateError)
    @app.exception_handler(TicketStateError)
    async def conflict(_: Request, exc: ValueError) -> JSONResponse:
        """An alarm or ticket transition that its state does not allow: 409."""
        return JSONResponse(status_code=409, content={"detail": str(exc)})

    return app
