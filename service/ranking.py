"""The bad-actor ranking from the store: each loop's latest state, the runs of a period that
count for its score (:mod:`service.bad_actors`), and the period's length."""

from __future__ import annotations

from typing import Any

from sqlalchemy import BigInteger, cast, func, select
from sqlalchemy.orm import Session

from service.api.schemas.loops import BadActorPublic, LoopPublic
from service.bad_actors import SCORED_KPIS, score_loop, scored_kpis
from service.store.models import Alarm, AnalysisRun, Loop
from service.stored import StoredKpis

__all__ = ["PERIOD_PATTERN", "bad_actor_rows", "counted_runs", "loop_rows", "period_length"]

_RUN_COLUMNS = (AnalysisRun.health, AnalysisRun.oscillating, AnalysisRun.period_s,
                AnalysisRun.verdict, AnalysisRun.confidence, AnalysisRun.S, AnalysisRun.J,
                AnalysisRun.started_at)

_STATE_FILTERS = {
    "oscillating": AnalysisRun.oscillating.is_(True),
    "stiction": AnalysisRun.verdict == "stiction",
    "healthy": AnalysisRun.oscillating.is_(False),
    "unknown": AnalysisRun.health.is_(None),
}


def loop_rows(
    session: Session,
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


def counted_runs(session: Session, since: float, until: float, bucket_s: float
                 ) -> dict[str, list[tuple[float, float | None, StoredKpis | None]]]:
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
    runs: dict[str, list[tuple[float, float | None, StoredKpis | None]]] = {}
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
                                                              StoredKpis | None]]]
                   | None = None, loops: list[LoopPublic] | None = None
                   ) -> list[BadActorPublic]:
    """Every loop with its latest state and its score (:mod:`service.bad_actors`) over the
    runs started in ``(since, until]``, worst first: by score, then by health (loops not
    analysed last); the runs that count are :func:`counted_runs` (given as ``runs`` when
    the caller has them already), each with its latest run's KPIs.  ``loops``: every loop
    with its latest state (:func:`loop_rows`; read here when not given).
    """
    if loops is None:
        loops = loop_rows(session, trusted=True)[0]
    if runs is None:
        runs = counted_runs(session, since, until, bucket_s)
    kpis = latest_kpis(session)
    ranked = []
    for loop in loops:
        scored = score_loop([(health, k) for _, health, k in runs.get(loop.id, ())],
                            loop.importance, period)
        ranked.append(BadActorPublic.model_construct(
            **loop.__dict__, **scored.__dict__, kpis=kpis.get(loop.id)))
    ranked.sort(key=lambda r: (-r.score, r.health is None,
                               r.health if r.health is not None else 0.0, r.id))
    return ranked
