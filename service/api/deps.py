"""Shared state and dependencies of the API routes, and the parameter types they share."""

from __future__ import annotations

import asyncio
import hashlib
from collections.abc import AsyncIterator, Callable, Hashable, Iterator
from dataclasses import dataclass
from typing import Annotated, Any

from anyio import CancelScope, CapacityLimiter, to_thread
from fastapi import Depends, HTTPException, Path, Query, Request, Response, Security
from fastapi.security import APIKeyHeader
from pydantic import BaseModel, Field
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from service.auth import Permission, Principal
from service.ranking import period_length
from service.runtime import AppState
from service.security import retry_after

__all__ = [
    "ERROR_RESPONSES",
    "MAX_DB_INT",
    "MAX_TIME_S",
    "NOT_MODIFIED",
    "Analyst",
    "AppState",
    "Error",
    "Offset",
    "Principal",
    "Reader",
    "RequireKey",
    "SessionDep",
    "StateDep",
    "TimeQuery",
    "error_responses",
    "period_seconds",
    "require",
    "row_id",
    "shared_answer",
]

MAX_DB_INT = 2 ** 63 - 1
"""The largest integer both databases hold (BIGINT; SQLite's INTEGER)."""

MAX_TIME_S = 253402300799.0
"""9999-12-31T23:59:59Z: the last UNIX time a date can be printed for."""

Offset = Annotated[int, Query(ge=0, le=MAX_DB_INT, description="rows to skip")]
TimeQuery = Annotated[float | None, Query(ge=0, le=MAX_TIME_S, description="UNIX s")]


def row_id(description: str) -> Any:
    """A path parameter naming a stored row by its integer id (1 .. 2**63 - 1)."""
    return Path(ge=1, le=MAX_DB_INT, description=description)


def period_seconds(period: str) -> float:
    """:func:`period_length` for a route: 422 beyond :data:`service.ranking.MAX_PERIOD_S`."""
    try:
        return period_length(period)
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None


class ValidationProblem(BaseModel):
    """One problem with the request: where (``loc``) and what (``msg``)."""

    loc: list[str | int]
    msg: str
    type: str


class Error(BaseModel):
    """Every error answer: ``detail`` is a sentence saying what was wrong, or, for a
    request that does not fit the schema, one entry per problem."""

    detail: str | list[ValidationProblem] = Field(
        description="what was wrong and where")


ERROR_REASONS: dict[int, str] = {
    400: "the request cannot be read as sent",
    401: "missing, unknown or revoked API key",
    403: "the key's role may not do this",
    404: "not found",
    409: "the request conflicts with the current state",
    413: "the request body is larger than the limit",
    422: "the request does not fit the schema, or a value in it cannot be used",
    429: "too many requests for this key, failed authentications from this address, or "
         "expensive analyses of this key at once",
    503: "the store is unreachable or busy",
}
RETRIED = (429, 503)
"""Statuses that carry ``Retry-After``."""


def error_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """The OpenAPI responses of error ``codes``, with the :class:`Error` body."""
    responses: dict[int | str, dict[str, Any]] = {}
    for code in codes:
        responses[code] = {"model": Error, "description": ERROR_REASONS[code]}
        if code in RETRIED:
            responses[code]["headers"] = {"Retry-After": {
                "description": "seconds to wait before trying again",
                "schema": {"type": "integer", "minimum": 1}}}
    return responses


ERROR_RESPONSES = error_responses(400, 401, 403, 413, 422, 429, 503)
"""Errors any route behind a key may answer (route-specific: 404 and 409)."""


NOT_MODIFIED: dict[int | str, dict[str, Any]] = {304: {
    "description": "the answer is still the one whose ETag the request sent in "
                   "If-None-Match (no body)"}}
"""The extra response of the routes that answer through :func:`shared_answer`."""


@dataclass(frozen=True)
class JsonView:
    """An answer kept by the read cache with its JSON text and the text's ETag."""

    answer: BaseModel
    body: bytes
    etag: str

    @classmethod
    def of(cls, answer: BaseModel) -> JsonView:
        body = answer.model_dump_json().encode()
        return cls(answer, body, f'"{hashlib.blake2b(body, digest_size=16).hexdigest()}"')


async def shared_answer(request: Request, state: AppState, key: Hashable,
                        compute: Callable[[], BaseModel],
                        valid: Callable[[Any], bool] | None = None) -> Response:
    """The answer of ``compute()`` (a model of the loop, run and alarm tables) shared
    by the requests through :attr:`AppState.loop_views` (:mod:`service.read_cache`) as
    JSON text with an ``ETag``; ``valid(answer)``, when given, must hold too.

    A current answer is sent from the event loop; only a missing or stale one is
    computed (or waited for) in the thread pool, where ``compute`` opens its own
    session.  One half as old as ``LOOPWATCH_READ_CACHE_S`` is computed again in
    the background (:meth:`service.read_cache.ReadCache.refresh`).  A request whose
    ``If-None-Match`` names the answer's ETag gets 304 without a body.  Twenty
    dashboards polling the loop list, the ranking and the alarms each second made
    sixty trips a second through the thread pool, each waiting for the interpreter
    lock behind the ingest, for answers already at hand.
    """
    check = None if valid is None else (lambda view: valid(view.answer))
    views = state.loop_views
    view: JsonView | None = views.peek(key, check)
    if view is None:
        view = await run_in_threadpool(views.get, key, lambda: JsonView.of(compute()), check)
    elif views.refresh_ahead(key):
        asyncio.get_running_loop().run_in_executor(
            None, views.refresh, key, lambda: JsonView.of(compute()), check)
    headers = {"ETag": view.etag}
    if view.etag in (tag.strip() for tag in request.headers.get("if-none-match", "").split(",")):
        return Response(status_code=304, headers=headers)
    return Response(view.body, media_type="application/json", headers=headers)


async def get_state(request: Request) -> AppState:
    """The application's :class:`AppState` (async: it does no I/O, and a plain def
    would cost every request a trip through the thread pool)."""
    state: AppState = request.app.state.loopwatch
    return state


StateDep = Annotated[AppState, Depends(get_state)]


async def get_session(state: StateDep) -> AsyncIterator[Session]:
    """One transaction per request: committed when the route returns normally, rolled
    back when it raises.

    The session is opened on the event loop (no I/O: its connection is taken at its
    first statement, in the route's thread) and committed and closed in the thread
    pool: one trip through the pool per request instead of two (a plain generator is
    entered and left there).  As FastAPI leaves a plain generator, the commit cannot be
    cancelled and does not wait for the pool's capacity (a full pool of requests waiting
    for connections that sessions waiting to close hold would never drain).

    The transaction ends before the answer is sent (``scope="function"``; FastAPI's
    default ends it after): a client reading right after a 2xx sees its write, and a
    commit that fails is a 500 instead of a success for a write that was lost."""
    transaction = state.store.session()
    session = transaction.__enter__()
    try:
        yield session
    except BaseException as exc:
        with CancelScope(shield=True):
            await to_thread.run_sync(transaction.__exit__, type(exc), exc, exc.__traceback__,
                                     limiter=CapacityLimiter(1))
        raise
    with CancelScope(shield=True):
        await to_thread.run_sync(transaction.__exit__, None, None, None,
                                 limiter=CapacityLimiter(1))


SessionDep = Annotated[Session, Depends(get_session, scope="function")]

_key_header = APIKeyHeader(name="X-API-Key", auto_error=False)


class RequireKey:
    """A dependency that admits active keys, counted against their rate limit.

    ``permission`` None admits any active key; otherwise the key's role must
    grant it.  Missing, unknown or revoked key: 401; too many of those from
    the client's address: 429 with ``Retry-After`` before the key is looked
    up; over the key's rate limit: 429 with ``Retry-After``; a role without
    the permission: 403.  The route-table test reads ``permission`` to check
    every route's access.

    A key the store confirmed within ``LOOPWATCH_AUTH_CACHE_S`` is admitted on the
    event loop (:meth:`service.auth.KeyVerifier.cached`); only the others are looked up,
    in the thread pool.
    """

    def __init__(self, permission: Permission | None) -> None:
        self.permission = permission

    async def __call__(self, request: Request, state: StateDep,
                       key: Annotated[str | None, Security(_key_header)]) -> Principal:
        address = request.client.host if request.client else "unknown"
        failures = state.auth_failures
        blocked = failures.wait(address)
        if blocked > 0:
            raise HTTPException(
                429, f"Too many failed authentications from {address}; retry later",
                headers={"Retry-After": retry_after(blocked)})
        principal = state.keys.cached(key) if key else None
        if key and principal is None:
            principal = await run_in_threadpool(state.keys.verify, key)
        if principal is None:
            failures.acquire(address)
            raise HTTPException(401, "Missing API key (header X-API-Key)" if not key
                                else "Invalid or revoked API key")
        wait = state.limiter.acquire(principal.id)
        if wait > 0:
            raise HTTPException(
                429,
                f"Rate limit of {state.limiter.rate_per_s:g} requests/s (burst "
                f"{state.limiter.burst}) exceeded for key {principal.name!r}; retry later",
                headers={"Retry-After": retry_after(wait)},
            )
        if self.permission is not None and self.permission not in principal.permissions:
            raise HTTPException(403, f"Role {principal.role!r} may not {self.permission}")
        return principal


def require(permission: Permission | None) -> RequireKey:
    """The dependency admitting keys whose role grants ``permission`` (None: any key)."""
    return RequireKey(permission)


Reader = Annotated[Principal, Depends(require("read"))]
"""Any key whose role may read."""
Operator = Annotated[Principal, Depends(require("alarms"))]
"""A key whose role may act on alarms."""
Maintenance = Annotated[Principal, Depends(require("tickets"))]
"""A key whose role may change tickets."""
Historian = Annotated[Principal, Depends(require("ingest"))]
"""A key whose role may push samples."""
Admin = Annotated[Principal, Depends(require("admin"))]
"""An admin key."""


def _analysis_slot(state: StateDep, principal: Reader) -> Iterator[Principal]:
    """A reader holding one of its key's slots for expensive analyses until the answer.

    A key already running ``settings.analyses_per_key`` of them gets 429 with
    ``Retry-After``, so one client cannot take every worker thread and
    database connection; when the service runs all it admits (two per
    analysis process), 503 with ``Retry-After``.  The slot is given back when the
    route returns, before its answer is sent (``scope="function"``): a client that
    sends its next analysis as soon as it has the answer is not refused (the load
    benchmark's model-check clients were, now and then).
    """
    full = state.analyses.acquire(principal.id)
    retry = {"Retry-After": retry_after(state.settings.analysis_retry_s)}
    if full == "key":
        raise HTTPException(
            429, f"Key {principal.name!r} already runs {state.analyses.per_key} expensive "
                 "analysis at a time (model check, advice, unit diagnosis or prediction); "
                 "retry when it has finished", headers=retry)
    if full == "total":
        raise HTTPException(
            503, f"The service already runs its {state.analyses.total} expensive analyses "
                 "at once (LOOPWATCH_ANALYSIS_PROCESSES); retry later", headers=retry)
    try:
        yield principal
    finally:
        state.analyses.release(principal.id)


Analyst = Annotated[Principal, Depends(_analysis_slot, scope="function")]
"""A reader running an expensive analysis (model check, advice, unit diagnosis, prediction)."""
