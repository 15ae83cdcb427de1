"""Loops, units, the bad-actor ranking and loop data."""

from __future__ import annotations

from itertools import pairwise
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, HTTPException, Query, Request, Response
from pydantic import BaseModel, Field, ValidationError
from sqlalchemy import BigInteger, cast, func, select
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
    shared_answer,
)
from service.api.schemas.diagnosis import KpisPublic, LoopDiagnosisPublic
from service.bad_actors import SCORED_KPIS, score_loop, scored_kpis
from service.config import LoopConfig
from service.logs import audit
from service.plant import TagConflictError
from service.store.models import Alarm, AnalysisRun, Loop, Sample, Tag, Unit
from service.tickets import run_episodes

router = APIRouter(prefix="/api/v1", tags=["loops"],
                   responses={**ERROR_RESPONSES, **error_responses(404)})


class LoopPublic(BaseModel):
    """A loop in lists: identity and its latest state."""

    id: str
    name: str
    unit: str | None
    valve_asset: str | None
    importance: str
    health: float | None
    oscillating: bool | None
    period_s: float | None
    verdict: str | None
    confidence: float | None
    S: float | None
    J: float | None
    analysed_at: float | None
    active_alarms: int


class LoopsPublic(BaseModel):
    """A page of loops."""

    data: list[LoopPublic]
    count: int


class BadActorPublic(LoopPublic):
    """A loop in the bad-actor ranking: its latest state and its KPI-based score over the
    period (:mod:`service.bad_actors`)."""

    score: float
    severity: float
    bad_share: float
    runs: int
    bad_runs: int
    worst: str | None
    why: str
    kpis: dict[str, Any] | None = Field(
        default=None, description="the KPIs of the loop's latest analysis run (as "
        "GET /loops/{id}/kpis gives them)")


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


class SeriesPublic(BaseModel):
    """One tag's samples over a time range (downsampled to at most max_points)."""

    tag: str
    signal: str
    t: list[float]
    value: list[float | None]


class LoopDataPublic(BaseModel):
    """Samples of every tag of a loop."""

    loop_id: str
    start: float
    end: float
    series: list[SeriesPublic]


_RUN_COLUMNS = (AnalysisRun.health, AnalysisRun.oscillating, AnalysisRun.period_s,
                AnalysisRun.verdict, AnalysisRun.confidence, AnalysisRun.S, AnalysisRun.J,
                AnalysisRun.started_at)

_STATE_FILTERS = {
    "oscillating": AnalysisRun.oscillating.is_(True),
    "stiction": AnalysisRun.verdict == "stiction",
    "healthy": AnalysisRun.oscillating.is_(False),
    "unknown": AnalysisRun.health.is_(None),
}


def _loop_rows(
    session: SessionDep,
    *,
    unit: str | None = None,
    loop_id: str | None = None,
    state: str | None = None,
    worst_first: bool = False,
    offset: int = 0,
    limit: int | None = None,
    trusted: bool = False,
) -> tuple[list[LoopPublic], int]:
    """Loops joined with their latest successful run and active-alarm count, in one query.

    Only the summary columns of the run are read (not the diagnosis JSON), and of the
    loop's configuration only the two fields listed (extracted by the database, not
    parsed here: the plant's whole configuration would be parsed on every request);
    filtering, ordering and paging happen in the database.  ``trusted`` builds the
    rows without validating them again (their columns have the models' types): for
    callers that read every loop.
    """
    latest = (
        select(AnalysisRun.loop_id, func.max(AnalysisRun.id).label("run_id"))
        .where(AnalysisRun.status == "ok").group_by(AnalysisRun.loop_id).subquery()
    )
    alarms = (
        select(Alarm.loop_id, func.count().label("n")).where(Alarm.state != "normal")
        .group_by(Alarm.loop_id).subquery()
    )
    query = (
        select(Loop.id, Loop.name, Loop.unit_id, Loop.config["valve_asset"].as_string(),
               Loop.config["importance"].as_string(), *_RUN_COLUMNS,
               func.coalesce(alarms.c.n, 0))
        .outerjoin(latest, latest.c.loop_id == Loop.id)
        .outerjoin(AnalysisRun, AnalysisRun.id == latest.c.run_id)
        .outerjoin(alarms, alarms.c.loop_id == Loop.id)
    )
    if unit is not None:
        query = query.where(Loop.unit_id == unit)
    if loop_id is not None:
        query = query.where(Loop.id == loop_id)
    if state is not None:
        query = query.where(_STATE_FILTERS[state])
    if state is None:  # one row per loop: the joined subqueries have one row per loop
        counted = select(func.count(Loop.id))
        if unit is not None:
            counted = counted.where(Loop.unit_id == unit)
        if loop_id is not None:
            counted = counted.where(Loop.id == loop_id)
        count = session.scalar(counted) or 0
    else:
        count = session.scalar(select(func.count()).select_from(query.subquery())) or 0
    order = ([AnalysisRun.health.is_(None), AnalysisRun.health, Loop.id] if worst_first
             else [Loop.id])
    rows = session.execute(query.order_by(*order).offset(offset).limit(limit)).all()
    make = LoopPublic.model_construct if trusted else LoopPublic
    data = [
        make(
            id=r[0], name=r[1], unit=r[2], valve_asset=r[3],
            importance="medium" if r[4] is None else r[4], health=r[5], oscillating=r[6],
            period_s=r[7], verdict=r[8], confidence=r[9], S=r[10], J=r[11], analysed_at=r[12],
            active_alarms=r[13],
        )
        for r in rows
    ]
    return data, count


_STATE_TESTS = {
    "oscillating": lambda r: r.oscillating is True,
    "stiction": lambda r: r.verdict == "stiction",
    "healthy": lambda r: r.oscillating is False,
    "unknown": lambda r: r.health is None,
}
""":data:`_STATE_FILTERS` on a row of :func:`loop_states`."""


def loop_states(session: SessionDep, app: AppState) -> list[LoopPublic]:
    """Every loop with its latest state, in the store's order of loop ids: read once and
    shared by the requests until a loop, run or alarm is written
    (:attr:`service.runtime.AppState.loop_views`).  The rows are shared: do not change
    them."""
    return app.loop_views.get(("loops",), lambda: _loop_rows(session, trusted=True)[0])


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


PERIOD_PATTERN = r"^[1-9][0-9]{0,2}[hd]$"
MAX_PERIOD_S = 92 * 86400.0


def period_length(period: str) -> float:
    """``"7d"`` or ``"36h"`` (:data:`PERIOD_PATTERN`) in seconds.

    >>> period_length("7d"), period_length("36h")
    (604800.0, 129600.0)

    Raises
    ------
    ValueError
        Longer than :data:`MAX_PERIOD_S`.
    """
    seconds = int(period[:-1]) * (86400.0 if period[-1] == "d" else 3600.0)
    if seconds > MAX_PERIOD_S:
        raise ValueError("period must be at most 92 days")
    return seconds


def period_seconds(period: str) -> float:
    """:func:`period_length` for a route: 422 beyond :data:`MAX_PERIOD_S`."""
    try:
        return period_length(period)
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None


def counted_runs(session: Session, since: float, until: float, bucket_s: float
                 ) -> dict[str, list[tuple[float, float | None, dict[str, Any] | None]]]:
    """Each loop's runs ``(started_at, health, kpis)`` started in ``(since, until]`` that
    count for its score, oldest first: one per ``bucket_s`` (the analysis window's length;
    buckets counted back from ``until``), the latest of its bucket.  Runs a minute apart on
    hour-long windows share most of their data, so they are one observation of the loop,
    not sixty, and a week is 168 runs a loop, not 10,080.  ``kpis`` holds only the KPIs
    the score reads (:func:`service.bad_actors.scored_kpis`).
    """
    # Whole milliseconds (a cast truncates on SQLite, rounds on PostgreSQL: harmless at 1 ms),
    # then integer division, which truncates on both.
    bucket = cast((until - AnalysisRun.started_at) * 1000.0, BigInteger) // max(
        1, round(bucket_s * 1000.0))
    chosen = (
        select(func.max(AnalysisRun.id))
        .where(AnalysisRun.status == "ok", AnalysisRun.started_at > since,
               AnalysisRun.started_at <= until)
        .group_by(AnalysisRun.loop_id, bucket)
    )
    # only the KPIs the score reads, extracted by the database from the runs' ``kpis``
    # column: parsing every run's diagnosis here cost more than the rest of the ranking
    runs: dict[str, list[tuple[float, float | None, dict[str, Any] | None]]] = {}
    for loop_id, started_at, health, *values in session.execute(
        select(AnalysisRun.loop_id, AnalysisRun.started_at, AnalysisRun.health,
               *(AnalysisRun.kpis[path].as_float() for path in SCORED_KPIS))
        .where(AnalysisRun.id.in_(chosen)).order_by(AnalysisRun.started_at, AnalysisRun.id)
    ):
        runs.setdefault(loop_id, []).append((started_at, health, scored_kpis(values)))
    return runs


def latest_kpis(session: Session) -> dict[str, dict[str, Any]]:
    """Each loop's KPIs of its latest successful run (loops without any left out)."""
    latest = (select(func.max(AnalysisRun.id)).where(AnalysisRun.status == "ok")
              .group_by(AnalysisRun.loop_id))
    rows = session.execute(select(AnalysisRun.loop_id, AnalysisRun.kpis)
                           .where(AnalysisRun.id.in_(latest)))
    return {loop_id: kpis for loop_id, kpis in rows if kpis}


def bad_actor_rows(session: Session, since: float, until: float, period: str,
                   bucket_s: float, runs: dict[str, list[tuple[float, float | None,
                                                              dict[str, Any] | None]]]
                   | None = None, loops: list[LoopPublic] | None = None
                   ) -> list[BadActorPublic]:
    """Every loop with its latest state and its score (:mod:`service.bad_actors`) over the
    runs started in ``(since, until]``, worst first: by score, then by health (loops not
    analysed last); the runs that count are :func:`counted_runs` (given as ``runs`` when
    the caller has them already), each with its latest run's KPIs.  ``loops``: every loop
    with its latest state (:func:`loop_states`; read here when not given).
    """
    if loops is None:
        loops = _loop_rows(session, trusted=True)[0]
    if runs is None:
        runs = counted_runs(session, since, until, bucket_s)
    kpis = latest_kpis(session)
    ranked = []
    for loop in loops:
        scored = score_loop([(health, k) for _, health, k in runs.get(loop.id, ())],
                            loop.importance, period)
        ranked.append(BadActorPublic.model_construct(
            **loop.__dict__, score=scored.score, severity=scored.severity,
            bad_share=scored.bad_share, runs=scored.runs, bad_runs=scored.bad_runs,
            worst=scored.worst, why=scored.why, kpis=kpis.get(loop.id),
        ))
    ranked.sort(key=lambda r: (-r.score, r.health is None,
                               r.health if r.health is not None else 0.0, r.id))
    return ranked


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
    return _loop_rows(session, loop_id=loop_id)[0][0]


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
    stiction = (diagnosis or {}).get("stiction") or {}
    return HealthPublic(
        loop_id=loop_id,
        health=latest.health if latest else None,
        latest=_run_public(latest) if latest else None,
        diagnosis=None if diagnosis is None else LoopDiagnosisPublic.model_validate(diagnosis),
        trend=[(r.started_at, r.health) for r in reversed(runs)],
        stiction_pattern=(stiction_pattern_text(stiction.get("pattern"), stiction.get("op_travel"))
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
) -> KpiHistoryPublic:
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
    rows = session.execute(
        select(AnalysisRun.id, AnalysisRun.started_at, AnalysisRun.window_start,
               AnalysisRun.window_end, AnalysisRun.health, AnalysisRun.kpis, chosen.c.total)
        .join(chosen, AnalysisRun.id == chosen.c.id)
        .order_by(AnalysisRun.started_at, AnalysisRun.id)
    ).all()
    data = [KpiPointPublic(run_id=r[0], started_at=r[1], window_start=r[2], window_end=r[3],
                           health=r[4], kpis=r[5]) for r in rows]
    return KpiHistoryPublic(loop_id=loop_id, since=since, until=until, data=data,
                            count=len(data), total=rows[0][6] if rows else 0)


def _downsample(t: np.ndarray, v: np.ndarray, max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Keep the min and max of equal buckets so oscillations survive downsampling."""
    if t.size <= max_points:
        return t, v
    buckets = max_points // 2
    edges = np.linspace(0, t.size, buckets + 1).astype(int)
    keep: list[int] = []
    for lo, hi in pairwise(edges):
        segment = v[lo:hi]
        finite = np.isfinite(segment)
        if not finite.any():
            keep.append(lo)
            continue
        idx = np.flatnonzero(finite)
        a = lo + idx[np.argmin(segment[finite])]
        b = lo + idx[np.argmax(segment[finite])]
        keep.extend(sorted({int(a), int(b)}))
    index = np.asarray(keep)
    return t[index], v[index]


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
    end = state.clock() if end is None else end
    start = end - 3600.0 if start is None else start
    if not end > start:
        raise HTTPException(422, "end must be after start")
    series = []
    for tag in session.scalars(select(Tag).where(Tag.loop_id == loop_id).order_by(Tag.signal)):
        rows = session.execute(
            select(Sample.time, Sample.value, Sample.good)
            .where(Sample.tag == tag.name, Sample.time >= start, Sample.time <= end)
            .order_by(Sample.time)
        ).all()
        t = np.array([r[0] for r in rows], dtype=float)
        v = np.array([r[1] if r[2] and r[1] is not None else np.nan for r in rows], dtype=float)
        t, v = _downsample(t, v, max_points)
        series.append(SeriesPublic(
            tag=tag.name, signal=tag.signal, t=t.tolist(),
            value=[None if not np.isfinite(x) else float(x) for x in v],
        ))
    return LoopDataPublic(loop_id=loop_id, start=start, end=end, series=series)


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
    data, count = _loop_rows(session, unit=unit_id)
    return LoopsPublic(data=data, count=count)
