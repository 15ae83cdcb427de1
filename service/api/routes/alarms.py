"""Operator alarms: list, detail with history, acknowledge, shelve, unshelve, service."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Body, HTTPException, Query, Request, Response
from pydantic import BaseModel, Field
from sqlalchemy.orm import Session

from service.alarms import (
    ALARM_STATES,
    AlarmNotFoundError,
    acknowledge,
    alarm_payload,
    get_alarm,
    list_alarms,
    remove_from_service,
    return_to_service,
    shelve,
    unshelve,
)
from service.api.deps import (
    ERROR_RESPONSES,
    NOT_MODIFIED,
    Admin,
    AppState,
    Offset,
    Operator,
    Reader,
    SessionDep,
    StateDep,
    error_responses,
    row_id,
    shared_answer,
)
from service.logs import audit
from service.store.models import Alarm

router = APIRouter(prefix="/api/v1/alarms", tags=["alarms"],
                   responses={**ERROR_RESPONSES, **error_responses(404, 409)})
AlarmId = Annotated[int, row_id("the alarm's id")]


class AlarmEventPublic(BaseModel):
    """One recorded transition."""

    at: float
    event: str
    from_state: str
    to_state: str
    actor: str
    note: str


class AlarmPublic(BaseModel):
    """An alarm and its current state."""

    id: int
    loop_id: str
    kind: str
    priority: str
    state: str
    condition_active: bool
    shelved_until: float | None
    message: str
    raised_at: float
    updated_at: float


class AlarmDetail(AlarmPublic):
    """An alarm with its full history."""

    events: list[AlarmEventPublic]


class AlarmsPublic(BaseModel):
    """A page of alarms."""

    data: list[AlarmPublic]
    count: int


class OperatorNote(BaseModel):
    """An optional note for the alarm's history."""

    note: str = Field(default="", max_length=500)


OptionalNote = Annotated[OperatorNote | None, Body()]
"""The note of an alarm action: the body may be left out (no note)."""


def _note(body: OperatorNote | None) -> str:
    return "" if body is None else body.note


class ShelveRequest(OperatorNote):
    """How long to shelve (at most 24 h)."""

    duration_s: float = Field(gt=0, le=24 * 3600)


def _detail(alarm: Alarm) -> AlarmDetail:
    return AlarmDetail.model_validate(alarm, from_attributes=True)


def _acted(session: Session, state: AppState, alarm: Alarm) -> AlarmDetail:
    """The alarm as answered after an action, which becomes an audit record and an
    ``alarm.changed`` event in the outbox (in the action's transaction)."""
    last = alarm.events[-1]
    audit(last.actor, f"alarm {last.event}", f"alarm {alarm.id} ({alarm.loop_id} {alarm.kind})",
          to_state=last.to_state, note=last.note)
    if state.outbox is not None:
        state.outbox.add(session, "alarm.changed", alarm_payload(alarm), state.clock())
    return _detail(alarm)


@router.get("", response_model=AlarmsPublic, responses=NOT_MODIFIED)
async def list_all(
    request: Request,
    app: StateDep,
    _: Reader,
    loop_id: str | None = None,
    unit: str | None = None,
    state: Annotated[str | None, Query(description=f"one of {', '.join(ALARM_STATES)}")] = None,
    offset: Offset = 0,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
) -> Response:
    """Alarms, highest priority and newest first: without ``state`` every alarm that is
    not normal (the operator's list), with it exactly the alarms in that state.

    A page is read once for the requests that ask within ``LOOPWATCH_READ_CACHE_S``
    while no alarm or loop is written (:mod:`service.read_cache`), and carries an
    ``ETag`` (304 when ``If-None-Match`` names it)."""
    if state is not None and state not in ALARM_STATES:
        raise HTTPException(422, f"state must be one of {', '.join(ALARM_STATES)}")

    def page() -> AlarmsPublic:
        with app.store.session() as session:
            alarms, count = list_alarms(session, loop_id=loop_id, unit_id=unit,
                                        state=state, limit=limit, offset=offset)
            return AlarmsPublic(data=[AlarmPublic.model_validate(a, from_attributes=True)
                                      for a in alarms], count=count)

    return await shared_answer(request, app, ("alarms page", loop_id, unit, state, offset,
                                              limit), page)


def _get(session: SessionDep, alarm_id: int) -> Alarm:
    try:
        return get_alarm(session, alarm_id)
    except AlarmNotFoundError:
        raise HTTPException(404, "Alarm not found") from None


@router.get("/{alarm_id}", response_model=AlarmDetail)
def detail(alarm_id: AlarmId, session: SessionDep, _: Reader) -> AlarmDetail:
    """One alarm with every transition it went through."""
    return _detail(_get(session, alarm_id))


@router.post("/{alarm_id}/acknowledge", response_model=AlarmDetail)
def ack(alarm_id: AlarmId, session: SessionDep, state: StateDep,
        key: Operator, body: OptionalNote = None) -> AlarmDetail:
    """Acknowledge (operator); 409 if the alarm is not waiting for it."""
    _get(session, alarm_id)
    alarm = acknowledge(session, alarm_id, actor=key.actor, now=state.clock(), note=_note(body))
    return _acted(session, state, alarm)


@router.post("/{alarm_id}/shelve", response_model=AlarmDetail)
def shelve_alarm(alarm_id: AlarmId, body: ShelveRequest, session: SessionDep, state: StateDep,
                 key: Operator) -> AlarmDetail:
    """Shelve for ``duration_s`` (operator); it comes back by itself."""
    _get(session, alarm_id)
    alarm = shelve(session, alarm_id, duration_s=body.duration_s, actor=key.actor,
                   now=state.clock(), note=body.note)
    return _acted(session, state, alarm)


@router.post("/{alarm_id}/unshelve", response_model=AlarmDetail)
def unshelve_alarm(alarm_id: AlarmId, session: SessionDep, state: StateDep,
                   key: Operator, body: OptionalNote = None) -> AlarmDetail:
    """End a shelve early (operator)."""
    _get(session, alarm_id)
    alarm = unshelve(session, alarm_id, actor=key.actor, now=state.clock(), note=_note(body))
    return _acted(session, state, alarm)


@router.post("/{alarm_id}/out-of-service", response_model=AlarmDetail)
def out_of_service(alarm_id: AlarmId, session: SessionDep, state: StateDep,
                   key: Admin, body: OptionalNote = None) -> AlarmDetail:
    """Remove from service (admin), e.g. while the loop is in manual for maintenance."""
    _get(session, alarm_id)
    alarm = remove_from_service(session, alarm_id, actor=key.actor, now=state.clock(),
                                note=_note(body))
    return _acted(session, state, alarm)


@router.post("/{alarm_id}/in-service", response_model=AlarmDetail)
def in_service(alarm_id: AlarmId, session: SessionDep, state: StateDep,
               key: Admin, body: OptionalNote = None) -> AlarmDetail:
    """Return to service (admin)."""
    _get(session, alarm_id)
    alarm = return_to_service(session, alarm_id, actor=key.actor, now=state.clock(),
                              note=_note(body))
    return _acted(session, state, alarm)
