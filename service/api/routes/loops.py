"""Loops, units, the bad-actor ranking and loop data."""

from __future__ import annotations

from itertools import pairwise
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Query
from pydantic import BaseModel, ValidationError
from sqlalchemy import func, select

from service.api.deps import (
    ERROR_RESPONSES,
    Offset,
    Principal,
    SessionDep,
    StateDep,
    TimeQuery,
    error_responses,
    require,
)
from service.api.routes import advice, unit_diagnosis
from service.config import LoopConfig
from service.plant import TagConflictError
from service.store.models import Alarm, AnalysisRun, Loop, Sample, Tag, Unit

router = APIRouter(prefix="/api/v1", tags=["loops"],
                   responses={**ERROR_RESPONSES, **error_responses(404)})
router.include_router(advice.router)
router.include_router(unit_diagnosis.router)
Reader = Annotated[Principal, Depends(require("read"))]
Admin = Annotated[Principal, Depends(require("admin"))]


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
    """The latest diagnosis of a loop and the trend of its health."""

    loop_id: str
    health: float | None
    latest: RunPublic | None
    diagnosis: dict[str, Any] | None
    trend: list[tuple[float, float | None]]


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
) -> tuple[list[LoopPublic], int]:
    """Loops joined with their latest successful run and active-alarm count, in one query.

    Only the summary columns of the run are read (not the diagnosis JSON), and
    filtering, ordering and paging happen in the database.
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
        select(Loop.id, Loop.name, Loop.unit_id, Loop.config, *_RUN_COLUMNS,
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
    count = session.scalar(select(func.count()).select_from(query.subquery())) or 0
    order = ([AnalysisRun.health.is_(None), AnalysisRun.health, Loop.id] if worst_first
             else [Loop.id])
    rows = session.execute(query.order_by(*order).offset(offset).limit(limit)).all()
    data = [
        LoopPublic(
            id=r[0], name=r[1], unit=r[2], valve_asset=r[3].get("valve_asset"),
            importance=r[3].get("importance", "medium"), health=r[4], oscillating=r[5],
            period_s=r[6], verdict=r[7], confidence=r[8], S=r[9], J=r[10], analysed_at=r[11],
            active_alarms=r[12],
        )
        for r in rows
    ]
    return data, count


@router.get("/loops", response_model=LoopsPublic)
def list_loops(
    session: SessionDep,
    _: Reader,
    unit: str | None = None,
    state: Annotated[str | None, Query(pattern="^(oscillating|stiction|healthy|unknown)$")] = None,
    offset: Offset = 0,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
) -> LoopsPublic:
    """Loops with their latest state; filter by unit and state, page with offset/limit."""
    data, count = _loop_rows(session, unit=unit, state=state, offset=offset, limit=limit)
    return LoopsPublic(data=data, count=count)


@router.get("/plant/bad-actors", response_model=LoopsPublic)
def bad_actors(
    session: SessionDep, _: Reader, limit: Annotated[int, Query(ge=1, le=1000)] = 20
) -> LoopsPublic:
    """Loops ranked by health, worst first; loops not yet analysed come last."""
    data, count = _loop_rows(session, worst_first=True, limit=limit)
    return LoopsPublic(data=data, count=count)


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


@router.get("/loops/{loop_id}/config")
def get_loop_config(loop_id: str, session: SessionDep, _: Reader) -> dict[str, Any]:
    """The loop's configuration as in the plant file."""
    return _loop_or_404(session, loop_id).config


@router.put("/loops/{loop_id}", response_model=LoopPublic, status_code=200,
            responses=error_responses(409))
def put_loop(
    loop_id: str, body: dict[str, Any], session: SessionDep, state: StateDep, _: Admin
) -> LoopPublic:
    """Create or replace a loop from its configuration (admin).  The loop is kept in the
    store and loaded at every start (a loop of the plant file with the same id takes
    its place again at the next start); 409 when one of its tags belongs to another
    loop."""
    try:
        loop = LoopConfig.model_validate({**body, "id": loop_id})
        state.registry.upsert_loop(session, loop, state.clock())
    except ValidationError as exc:
        raise HTTPException(
            422, exc.errors(include_url=False, include_context=False, include_input=False)
        ) from None
    except TagConflictError as exc:
        raise HTTPException(409, str(exc)) from None
    session.flush()
    state.buffers.add_loop(loop)
    return get_loop(loop_id, session, _)


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


@router.get("/loops/{loop_id}/health", response_model=HealthPublic)
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
    return HealthPublic(
        loop_id=loop_id,
        health=latest.health if latest else None,
        latest=_run_public(latest) if latest else None,
        diagnosis=latest.result if latest else None,
        trend=[(r.started_at, r.health) for r in reversed(runs)],
    )


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
