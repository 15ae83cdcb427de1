"""Loops, units, the bad-actor ranking and loop data."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Query, Request, Response
from pydantic import BaseModel, ValidationError
from sqlalchemy import Row, Text, cast, func, select, text
from sqlalchemy.orm import Session

from service.analysis import stiction_pattern_text
from service.api.deps import (
    ERROR_RESPONSES,
    NOT_MODIFIED,
    Admin,
    AppState,
    Offset,
    Reader,
    SessionDep,
    StateDep,
    TimeQuery,
    error_responses,
    period_seconds,
    shared_answer,
)
from service.api.loop_data import read_loop_data
from service.api.schemas.diagnosis import KpisPublic, LoopDiagnosisPublic
from service.api.schemas.loops import BadActorPublic, LoopDataPublic, LoopPublic
from service.config import LoopConfig
from service.logs import audit
from service.plant import TagConflictError
from service.ranking import PERIOD_PATTERN, bad_actor_rows, loop_rows
from service.store.models import AnalysisRun, Loop, Unit
from service.stored import StoredDiagnosis
from service.tickets import run_episodes

router = APIRouter(prefix="/api/v1", tags=["loops"],
                   responses={**ERROR_RESPONSES, **error_responses(404)})


class LoopsPublic(BaseModel):
    """A page of loops."""

    data: list[LoopPublic]
    count: int


class BadActorsPublic(BaseModel):
    """The worst loops first; ``period`` the stretch the score covers."""

    data: list[BadActorPublic]
    count: int
    period: str
    since: float
    until: float


class KpiPointPublic(BaseModel):
    """The KPIs of one analysis run (None for a run stored before the KPIs were
    computed); ``kpis.dead_time_note`` says where the Harris index's dead time came from."""

    run_id: int
    started_at: float
    window_start: float | None
    window_end: float | None
    health: float | None
    kpis: KpisPublic | None


class KpiHistoryPublic(BaseModel):
    """A loop's KPI history, oldest first."""

    loop_id: str
    since: float
    until: float
    data: list[KpiPointPublic]
    count: int
    total: int
    """Runs in the range; more than ``count`` when they were thinned to ``limit``."""


class RunPublic(BaseModel):
    """One analysis run (the full diagnosis only in the loop's health view)."""

    id: int
    started_at: float
    window_start: float | None
    window_end: float | None
    status: str
    usable: bool | None
    oscillating: bool | None
    period_s: float | None
    verdict: str | None
    confidence: float | None
    S: float | None
    J: float | None
    health: float | None
    error: str | None


class RunsPublic(BaseModel):
    """A page of analysis runs, newest first."""

    data: list[RunPublic]
    count: int


class HealthPublic(BaseModel):
    """The latest diagnosis of a loop and the trend of its health.

    ``stiction_pattern`` names how the latest diagnosis's sticky valve shows
    (:func:`service.analysis.stiction_pattern_text`; None unless its final verdict,
    ``diagnosis["valve"]`` of :func:`service.verdicts.valve_verdict`, is stiction);
    ``episodes`` are its stick-jump episodes at UNIX times
    (:func:`service.tickets.run_episodes`).
    """

    loop_id: str
    health: float | None
    latest: RunPublic | None
    diagnosis: LoopDiagnosisPublic | None
    trend: list[tuple[float, float | None]]
    stiction_pattern: str | None = None
    episodes: list[dict[str, float]] = []


class UnitPublic(BaseModel):
    """A process unit and its loops."""

    id: str
    name: str
    loops: list[str]


class UnitsPublic(BaseModel):
    """All units."""

    data: list[UnitPublic]
    count: int


_STATE_TESTS = {
    "oscillating": lambda r: r.oscillating is True,
    "stiction": lambda r: r.verdict == "stiction",
    "healthy": lambda r: r.oscillating is False,
    "unknown": lambda r: r.health is None,
}
"""The ``state`` filters of :func:`service.ranking.loop_rows` on a row of :func:`loop_states`."""


def loop_states(session: SessionDep, app: AppState) -> list[LoopPublic]:
    """Every loop with its latest state, in the store's order of loop ids: read once and
    shared by the requests until a loop, run or alarm is written
    (:attr:`service.runtime.AppState.loop_views`).  The rows are shared: do not change
    them."""
    return app.loop_views.get(("loops",), lambda: loop_rows(session, trusted=True)[0])


@router.get("/loops", response_model=LoopsPublic, responses=NOT_MODIFIED)
async def list_loops(
    request: Request,
    app: StateDep,
    _: Reader,
    unit: str | None = None,
    state: Annotated[str | None, Query(pattern="^(oscillating|stiction|healthy|unknown)$")] = None,
    offset: Offset = 0,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
) -> Response:
    """Loops with their latest state; filter by unit and state, page with offset/limit.

    A page is computed once for the requests that ask within ``LOOPWATCH_READ_CACHE_S``
    while no loop, run or alarm is written, and carries an ``ETag`` (304 when
    ``If-None-Match`` names it)."""
    def page() -> LoopsPublic:
        with app.store.session() as session:
            rows = loop_states(session, app)
        if unit is not None:
            rows = [r for r in rows if r.unit == unit]
        if state is not None:
            rows = list(filter(_STATE_TESTS[state], rows))
        return LoopsPublic(data=rows[offset:offset + limit], count=len(rows))

    return await shared_answer(request, app, ("loops page", unit, state, offset, limit), page)


@router.get("/plant/bad-actors", response_model=BadActorsPublic, responses=NOT_MODIFIED)
async def bad_actors(
    request: Request, state: StateDep, _: Reader,
    limit: Annotated[int, Query(ge=1, le=1000)] = 20,
    period: Annotated[str, Query(pattern=PERIOD_PATTERN)] = "7d",
) -> Response:
    """Loops ranked by their bad-actor score over ``period`` (``7d``, ``36h``; at most 92
    days): KPI severity x loop importance x time spent bad (:mod:`service.bad_actors`),
    each with ``why``; then by latest health, worst first; loops not analysed last.  One
    run per analysis window length counts (:func:`bad_actor_rows`).

    The ranking is computed once for the requests that ask within
    ``LOOPWATCH_READ_CACHE_S`` while no loop, run or alarm is written
    (:mod:`service.read_cache`); ``since`` and ``until`` say which period it covers.
    The answer carries an ``ETag`` (304 when ``If-None-Match`` names it)."""
    seconds = period_seconds(period)

    def rank(session: Session) -> tuple[float, list[BadActorPublic]]:
        until = state.clock()
        return until, bad_actor_rows(session, until - seconds, until, period,
                                     state.settings.window_s,
                                     loops=loop_states(session, state))

    def recent(until: float) -> bool:
        return abs(state.clock() - until) <= state.settings.read_cache_s

    def page() -> BadActorsPublic:
        with state.store.session() as session:
            until, ranked = state.loop_views.get(
                ("bad-actors", period), lambda: rank(session), lambda answer: recent(answer[0]))
        return BadActorsPublic(data=ranked[:limit], count=len(ranked), period=period,
                               since=until - seconds, until=until)

    return await shared_answer(request, state, ("bad-actors page", period, limit), page,
                               lambda answer: recent(answer.until))


def _loop_or_404(session: SessionDep, loop_id: str) -> Loop:
    loop = session.get(Loop, loop_id)
    if loop is None:
        raise HTTPException(404, "Loop not found")
    return loop


@router.get("/loops/{loop_id}", response_model=LoopPublic)
def get_loop(loop_id: str, session: SessionDep, _: Reader) -> LoopPublic:
    """One loop with its latest state."""
    _loop_or_404(session, loop_id)
    return loop_rows(session, loop_id=loop_id)[0][0]


@router.get("/loops/{loop_id}/config", response_model=LoopConfig)
def get_loop_config(loop_id: str, session: SessionDep, _: Reader) -> dict[str, Any]:
    """The loop's configuration as in the plant file."""
    return _loop_or_404(session, loop_id).config


@router.put("/loops/{loop_id}", response_model=LoopPublic, status_code=200,
            responses=error_responses(409))
def put_loop(
    loop_id: str, body: dict[str, Any], session: SessionDep, state: StateDep, admin: Admin
) -> LoopPublic:
    """Create or replace a loop from its configuration (admin).  The loop is kept in the
    store and loaded at every start (a loop of the plant file with the same id takes
    its place again at the next start); 409 when one of its tags belongs to another
    loop."""
    try:
        loop = LoopConfig.model_validate({**body, "id": loop_id})
        created = state.registry.upsert_loop(session, loop, state.clock())
    except ValidationError as exc:
        raise HTTPException(
            422, exc.errors(include_url=False, include_context=False, include_input=False)
        ) from None
    except TagConflictError as exc:
        raise HTTPException(409, str(exc)) from None
    session.flush()
    state.buffers.add_loop(loop)
    audit(admin.actor, "added loop" if created else "changed loop", loop_id,
          config=loop.model_dump(mode="json", exclude_defaults=True))
    return get_loop(loop_id, session, admin)


def _run_public(run: AnalysisRun) -> RunPublic:
    return RunPublic.model_validate(run, from_attributes=True)


@router.get("/loops/{loop_id}/analyses", response_model=RunsPublic)
def list_analyses(
    loop_id: str,
    session: SessionDep,
    _: Reader,
    offset: Offset = 0,
    limit: Annotated[int, Query(ge=1, le=1000)] = 50,
) -> RunsPublic:
    """Analysis runs of a loop, newest first."""
    _loop_or_404(session, loop_id)
    count = session.scalar(select(func.count()).where(AnalysisRun.loop_id == loop_id)) or 0
    runs = session.scalars(
        select(AnalysisRun).where(AnalysisRun.loop_id == loop_id)
        .order_by(AnalysisRun.id.desc()).offset(offset).limit(limit)
    )
    return RunsPublic(data=[_run_public(r) for r in runs], count=count)


@router.get("/loops/{loop_id}/health", response_model=HealthPublic,
            response_model_exclude_unset=True)
def loop_health(
    loop_id: str, session: SessionDep, _: Reader,
    trend: Annotated[int, Query(ge=1, le=1000)] = 50,
) -> HealthPublic:
    """The latest diagnosis (every method's evidence included) and the health trend."""
    _loop_or_404(session, loop_id)
    runs = list(session.scalars(
        select(AnalysisRun).where(AnalysisRun.loop_id == loop_id, AnalysisRun.status == "ok")
        .order_by(AnalysisRun.id.desc()).limit(trend)
    ))
    latest = runs[0] if runs else None
    diagnosis = latest.result if latest else None
    analysis = StoredDiagnosis.from_dict(diagnosis).analysis
    return HealthPublic(
        loop_id=loop_id,
        health=latest.health if latest else None,
        latest=_run_public(latest) if latest else None,
        diagnosis=None if diagnosis is None else LoopDiagnosisPublic.model_validate(diagnosis),
        trend=[(r.started_at, r.health) for r in reversed(runs)],
        stiction_pattern=(stiction_pattern_text(analysis.pattern, analysis.op_travel)
                          if latest is not None and latest.verdict == "stiction" else None),
        episodes=[] if latest is None else run_episodes(latest),
    )


@router.get("/loops/{loop_id}/kpis", response_model=KpiHistoryPublic,
            response_model_exclude_unset=True)
def loop_kpis(
    loop_id: str, session: SessionDep, state: StateDep, _: Reader,
    since: Annotated[float | None, Query(ge=0)] = None,
    until: Annotated[float | None, Query(ge=0)] = None,
    limit: Annotated[int, Query(ge=1, le=10_000)] = 1000,
) -> Response:
    """The KPIs of the loop's successful runs started between ``since`` and ``until``
    (UNIX s; default: the last 30 days), oldest first.

    With more than ``limit`` runs in the range (a run a minute is 43,200 in 30 days), every
    ``k``-th run counting back from the newest is returned, ``k = ceil(total / limit)``,
    so the history spans the range; ``total`` says how many runs there were.  The thinning
    happens in the database, on the index of the ``ok`` runs by loop and time, and it reads
    the ``kpis`` column of the returned runs only, not their whole diagnosis.
    """
    _loop_or_404(session, loop_id)
    until = state.clock() if until is None else until
    since = until - 30 * 86400.0 if since is None else since
    if not until > since:
        raise HTTPException(422, "until must be after since")
    rows = _thinned_runs(session, loop_id, since, until, limit)
    # The answer is written here as the response model would write it, key for key, with
    # each run's KPIs passed on as the JSON text stored (the run's LoopKpis.to_dict, which
    # KpisPublic keeps as it is): parsing a thousand of them, validating them into models
    # and serialising them back took a third of the answer's time.
    data = ",".join(
        f'{{"run_id":{r[0]},"started_at":{_json_number(r[1])},'
        f'"window_start":{_json_number(r[2])},"window_end":{_json_number(r[3])},'
        f'"health":{_json_number(r[4])},"kpis":{r[5] or "null"}}}' for r in rows)
    return Response(
        f'{{"loop_id":{json.dumps(loop_id)},"since":{_json_number(since)},'
        f'"until":{_json_number(until)},"data":[{data}],"count":{len(rows)},'
        f'"total":{rows[0][6] if rows else 0}}}', media_type="application/json")


# The ids of the loop's ok runs in the range, newest first, in one array (from the
# index of the ok runs alone, the array built in the order of its subquery); every k-th
# of them, k = ceil(total / limit) in integer arithmetic, fetched by primary key.
_THINNED_RUNS_POSTGRESQL = text("""
WITH chosen AS MATERIALIZED (
    SELECT ARRAY(SELECT id FROM analysis_runs
                 WHERE loop_id = :loop_id AND status = 'ok'
                   AND started_at >= :since AND started_at <= :until
                 ORDER BY started_at DESC, id DESC) AS ids)
SELECT run.id, run.started_at, run.window_start, run.window_end, run.health,
       run.kpis::text, cardinality(chosen.ids)
FROM chosen
CROSS JOIN generate_series(1, cardinality(chosen.ids),
                           greatest((cardinality(chosen.ids) + :limit - 1) / :limit, 1)) AS k
JOIN analysis_runs AS run ON run.id = chosen.ids[k]
ORDER BY run.started_at, run.id""")


def _thinned_runs(session: Session, loop_id: str, since: float, until: float,
                  limit: int) -> Sequence[Row[*tuple[Any, ...]]]:
    """The runs :func:`loop_kpis` returns, oldest first: ``id``, ``started_at``,
    ``window_start``, ``window_end``, ``health``, ``kpis`` as JSON text, and the number
    of runs in the range.

    On PostgreSQL the ids of the range's runs are gathered in one array by an index-only
    scan and every k-th picked from it (:data:`_THINNED_RUNS_POSTGRESQL`); numbering and
    counting them with two window functions over the same scan took twice as long.
    Elsewhere (SQLite, no arrays) the window functions do it.
    """
    if session.get_bind().dialect.name == "postgresql":
        return session.execute(_THINNED_RUNS_POSTGRESQL, {
            "loop_id": loop_id, "since": since, "until": until, "limit": limit}).all()
    # One pass over the index of the ok runs numbers them newest first and counts them;
    # the step k = ceil(total / limit) in integer arithmetic (SQLite has no ceil).
    numbered = select(
        AnalysisRun.id,
        func.row_number().over(order_by=(AnalysisRun.started_at.desc(),
                                          AnalysisRun.id.desc())).label("rn"),
        func.count().over().label("total"),
    ).where(AnalysisRun.loop_id == loop_id, AnalysisRun.status == "ok",
            AnalysisRun.started_at >= since, AnalysisRun.started_at <= until).subquery()
    chosen = select(numbered.c.id, numbered.c.total).where(
        (numbered.c.rn - 1) % ((numbered.c.total + (limit - 1)) // limit) == 0).subquery()
    return session.execute(
        select(AnalysisRun.id, AnalysisRun.started_at, AnalysisRun.window_start,
               AnalysisRun.window_end, AnalysisRun.health, cast(AnalysisRun.kpis, Text),
               chosen.c.total)
        .join(chosen, AnalysisRun.id == chosen.c.id)
        .order_by(AnalysisRun.started_at, AnalysisRun.id)
    ).all()


def _json_number(value: float | None) -> str:
    """A float field in JSON as pydantic writes it: ``null`` for None, NaN and infinities."""
    return repr(float(value)) if value is not None and math.isfinite(value) else "null"


@router.get("/loops/{loop_id}/data", response_model=LoopDataPublic)
def loop_data(
    loop_id: str,
    session: SessionDep,
    state: StateDep,
    _: Reader,
    start: TimeQuery = None,
    end: TimeQuery = None,
    max_points: Annotated[int, Query(ge=10, le=100_000)] = 2000,
) -> LoopDataPublic:
    """Samples of the loop's tags between start and end (UNIX s; default: the last hour)."""
    _loop_or_404(session, loop_id)
    return read_loop_data(session, loop_id, state.clock(), start, end, max_points)


@router.get("/units", response_model=UnitsPublic)
def list_units(session: SessionDep, _: Reader) -> UnitsPublic:
    """Process units with their loops."""
    units = list(session.scalars(select(Unit).order_by(Unit.id)))
    members: dict[str, list[str]] = {}
    for loop_id, unit_id in session.execute(select(Loop.id, Loop.unit_id).order_by(Loop.id)):
        if unit_id is not None:
            members.setdefault(unit_id, []).append(loop_id)
    data = [UnitPublic(id=u.id, name=u.name, loops=members.get(u.id, [])) for u in units]
    return UnitsPublic(data=data, count=len(data))


@router.get("/units/{unit_id}", response_model=LoopsPublic)
def unit_loops(unit_id: str, session: SessionDep, _: Reader) -> LoopsPublic:
    """The loops of one unit with their latest state."""
    if session.get(Unit, unit_id) is None:
        raise HTTPException(404, "Unit not found")
    data, count = loop_rows(session, unit=unit_id)
    return LoopsPublic(data=data, count=count)
