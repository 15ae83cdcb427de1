"""Operator alarms of the loops: the ISA-18.2 / IEC 62682 alarm state machine.

States (the alarm state transition diagram of ISA-18.2, with the two
suppressed states the operator and the administrator control):

==================  ===================================================
``normal``          condition inactive, nothing to do
``unacknowledged``  condition active, not yet acknowledged
``acknowledged``    condition active, acknowledged
``rtn_unack``       returned to normal before anyone acknowledged it
``shelved``         suppressed by an operator until ``shelved_until``
``out_of_service``  removed from service by an administrator
==================  ===================================================

Events and where they lead (:data:`TRANSITIONS`):

* ``activated`` / ``returned_to_normal``: the analysis found the condition
  (de)activated.  ``unacknowledged`` clears to ``rtn_unack`` (the operator
  still has to see it), ``acknowledged`` clears to ``normal``.  While shelved
  or out of service the condition is tracked and recorded, the state stays.
* ``acknowledged``: operator, from ``unacknowledged`` or ``rtn_unack``.
* ``shelved`` (for a limited time, at most :data:`MAX_SHELVE_S`),
  ``unshelved``, ``shelve_expired`` (checked against ``now``).
* ``removed_from_service`` / ``returned_to_service``: administrator.

Leaving ``shelved`` or ``out_of_service`` lands in ``unacknowledged`` if the
condition is active (the operator must see it again), otherwise ``normal``.

Two kinds of alarm exist, one row per (loop, kind) that a condition coming
back re-uses: ``oscillation`` (the loop oscillates) and ``data_quality``
(the loop's data are unusable).  A stiction finding is not an operator
alarm: it goes to maintenance as a ticket (:mod:`service.tickets`).

Every transition is stored as an :class:`~service.store.models.AlarmEvent`
with its actor, time, from/to state and note.  Invalid transitions raise
:class:`AlarmStateError` (a ValueError; HTTP 409 at the API edge).
"""

from __future__ import annotations

from typing import Any, Literal, cast, get_args

from sqlalchemy import case, func, select
from sqlalchemy.orm import Session, selectinload

from service.config import Importance
from service.store.models import Alarm, AlarmEvent, Loop

__all__ = [
    "ALARM_STATES",
    "ANALYSIS_ACTOR",
    "MAX_SHELVE_S",
    "SYSTEM_ACTOR",
    "TRANSITIONS",
    "AlarmEventName",
    "AlarmKind",
    "AlarmNotFoundError",
    "AlarmState",
    "AlarmStateError",
    "acknowledge",
    "alarm_payload",
    "alarm_priority",
    "expire_shelves",
    "get_alarm",
    "list_alarms",
    "next_state",
    "remove_from_service",
    "return_to_service",
    "shelve",
    "unshelve",
    "update_alarms_from_analysis",
]

AlarmState = Literal[
    "normal", "unacknowledged", "acknowledged", "rtn_unack", "shelved", "out_of_service"
]
ALARM_STATES: tuple[AlarmState, ...] = get_args(AlarmState)
AlarmKind = Literal["oscillation", "data_quality"]
AlarmEventName = Literal[
    "activated",
    "returned_to_normal",
    "acknowledged",
    "shelved",
    "unshelved",
    "shelve_expired",
    "removed_from_service",
    "returned_to_service",
]

ANALYSIS_ACTOR = "analysis"
"""Actor of the condition changes found by the scheduler's analyses."""
SYSTEM_ACTOR = "system"
"""Actor of shelve expiries."""
MAX_SHELVE_S = 24 * 3600.0
"""Longest shelve: ISA-18.2 shelving is time-limited, so a shelved alarm is
reviewed at least once a day."""

_RESTORE: Literal["restore"] = "restore"
"""Target of leaving a suppressed state: ``unacknowledged`` if active, else ``normal``."""
_IN_SERVICE: tuple[AlarmState, ...] = ("normal", "unacknowledged", "acknowledged", "rtn_unack")

TRANSITIONS: dict[AlarmEventName, dict[AlarmState, AlarmState | Literal["restore"]]] = {
    "activated": {
        "normal": "unacknowledged",
        "rtn_unack": "unacknowledged",
        "shelved": "shelved",
        "out_of_service": "out_of_service",
    },
    "returned_to_normal": {
        "unacknowledged": "rtn_unack",
        "acknowledged": "normal",
        "shelved": "shelved",
        "out_of_service": "out_of_service",
    },
    "acknowledged": {"unacknowledged": "acknowledged", "rtn_unack": "normal"},
    "shelved": dict.fromkeys(_IN_SERVICE, "shelved"),
    "unshelved": {"shelved": _RESTORE},
    "shelve_expired": {"shelved": _RESTORE},
    "removed_from_service": dict.fromkeys((*_IN_SERVICE, "shelved"), "out_of_service"),
    "returned_to_service": {"out_of_service": _RESTORE},
}
"""For each event, the states it is allowed from and the state it leads to."""

_ACTIONS: dict[AlarmEventName, str] = {
    "activated": "activate",
    "returned_to_normal": "return to normal",
    "acknowledged": "acknowledge",
    "shelved": "shelve",
    "unshelved": "unshelve",
    "shelve_expired": "expire the shelve of",
    "removed_from_service": "remove from service",
    "returned_to_service": "return to service",
}

# ISA-18.2 sets priority by consequence and time to respond.  An oscillating
# loop costs quality and energy but develops slowly, so it never reaches the
# top; unusable data blind the monitoring while the DCS still controls, so a
# data-quality alarm sits one step lower.
_PRIORITIES: dict[AlarmKind, dict[str, str]] = {
    "oscillation": {"low": "low", "medium": "low", "high": "medium", "critical": "high"},
    "data_quality": {"low": "low", "medium": "low", "high": "low", "critical": "medium"},
}
_PRIORITY_RANK = {"high": 0, "medium": 1, "low": 2}


class AlarmStateError(ValueError):
    """The transition is not allowed in the alarm's current state."""


class AlarmNotFoundError(LookupError):
    """No alarm with that id."""


def next_state(state: AlarmState, event: AlarmEventName, *, condition_active: bool) -> AlarmState:
    """The state after ``event`` (pure ISA-18.2 logic, no store).

    ``condition_active`` is the condition after the event; it decides where
    leaving ``shelved`` or ``out_of_service`` lands.

    >>> next_state("unacknowledged", "returned_to_normal", condition_active=False)
    'rtn_unack'
    >>> next_state("shelved", "unshelved", condition_active=True)
    'unacknowledged'
    """
    allowed = TRANSITIONS[event]
    target = allowed.get(state)
    if target is None:
        raise AlarmStateError(
            f"cannot {_ACTIONS[event]} an alarm that is {state} "
            f"(possible when {' or '.join(allowed)})"
        )
    if target == _RESTORE:
        return "unacknowledged" if condition_active else "normal"
    return target


def alarm_priority(kind: AlarmKind, importance: Importance) -> str:
    """Priority (``low``, ``medium``, ``high``) of an alarm of ``kind`` on a loop of ``importance``.

    >>> alarm_priority("oscillation", "critical")
    'high'
    """
    if kind not in _PRIORITIES:
        raise ValueError(f"unknown alarm kind {kind!r} (expected {' or '.join(_PRIORITIES)})")
    by_importance = _PRIORITIES[kind]
    if importance not in by_importance:
        raise ValueError(
            f"unknown loop importance {importance!r} (expected {', '.join(by_importance)})"
        )
    return by_importance[importance]


def _label(alarm: Alarm) -> str:
    return f"alarm {alarm.id} ({alarm.loop_id} {alarm.kind})"


def _apply(alarm: Alarm, event: AlarmEventName, *, actor: str, now: float, note: str) -> None:
    """Move ``alarm`` through ``event`` and record the transition."""
    try:
        current = cast(AlarmState, alarm.state)
        state = next_state(current, event, condition_active=alarm.condition_active)
    except AlarmStateError as exc:
        raise AlarmStateError(f"{_label(alarm)}: {exc}") from None
    alarm.events.append(
        AlarmEvent(
            at=now, event=event, from_state=alarm.state, to_state=state, actor=actor, note=note
        )
    )
    alarm.state = state
    alarm.updated_at = now
    if state != "shelved":
        alarm.shelved_until = None


def alarm_payload(alarm: Alarm) -> dict[str, Any]:
    """What a notification of an alarm's change carries: the alarm and its latest transition."""
    last = alarm.events[-1] if alarm.events else None
    return {
        "alarm": {name: getattr(alarm, name) for name in (
            "id", "loop_id", "kind", "priority", "state", "condition_active", "message",
            "raised_at", "updated_at")},
        "change": None if last is None else {
            "at": last.at, "event": last.event, "from_state": last.from_state,
            "to_state": last.to_state, "actor": last.actor, "note": last.note},
    }


def _expire_if_due(alarm: Alarm, now: float) -> None:
    """End a shelve whose time is up; the event is stamped with the expiry time."""
    if alarm.state == "shelved" and alarm.shelved_until is not None and alarm.shelved_until <= now:
        _apply(alarm, "shelve_expired", actor=SYSTEM_ACTOR, now=alarm.shelved_until, note="")


def update_alarms_from_analysis(
    session: Session,
    loop_id: str,
    *,
    oscillating: bool,
    usable: bool,
    importance: Importance,
    message: str,
    now: float,
    out_of_service: bool = False,
) -> list[Alarm]:
    """Feed one analysis of a loop into its alarms; returns the alarms whose state changed.

    ``data_quality`` is active when the data are not ``usable``, unless the
    loop is ``out_of_service``: in manual too long to be judged, which is no
    fault of the data (ISA-18.2 suppresses a loop's alarms by design while it
    is out of service).  On unusable data nothing is known about oscillation,
    so the ``oscillation`` alarm is left as it is.  An alarm row is created
    the first time its condition is active and re-used afterwards
    (``raised_at`` is the latest activation).
    ``message`` describes the finding: it becomes the alarm's message while
    the condition is active and the note of every condition change.  The
    priority follows the loop's current ``importance``.
    """
    if session.get(Loop, loop_id) is None:
        raise LookupError(f"loop {loop_id!r} not found")
    conditions: dict[AlarmKind, bool] = {"data_quality": not usable and not out_of_service}
    if usable:
        conditions["oscillation"] = oscillating
    alarms = {a.kind: a for a in session.scalars(select(Alarm).where(Alarm.loop_id == loop_id))}
    changed = []
    for kind, active in conditions.items():
        priority = alarm_priority(kind, importance)
        alarm = alarms.get(kind)
        if alarm is None:
            if not active:
                continue
            alarm = Alarm(
                loop_id=loop_id, kind=kind, priority=priority, state="normal",
                condition_active=False, shelved_until=None, message=message,
                raised_at=now, updated_at=now,
            )
            session.add(alarm)
        before = alarm.state
        _expire_if_due(alarm, now)
        alarm.priority = priority
        if active:
            alarm.message = message
        if active != alarm.condition_active:
            alarm.condition_active = active
            if active:
                alarm.raised_at = now
            event: AlarmEventName = "activated" if active else "returned_to_normal"
            _apply(alarm, event, actor=ANALYSIS_ACTOR, now=now, note=message)
        if alarm.state != before:
            changed.append(alarm)
    session.flush()
    return changed


def expire_shelves(session: Session, *, now: float) -> list[Alarm]:
    """Unshelve every alarm whose shelve ended at or before ``now``; returns them."""
    due = session.scalars(
        select(Alarm)
        .where(Alarm.state == "shelved", Alarm.shelved_until <= now)
        .with_for_update()
    ).all()
    for alarm in due:
        _expire_if_due(alarm, now)
    session.flush()
    return list(due)


def _operate(
    session: Session, alarm_id: int, event: AlarmEventName, *, actor: str, now: float, note: str
) -> Alarm:
    """Apply a user action to an alarm, after ending its shelve if that is due."""
    alarm = session.get(Alarm, alarm_id, with_for_update=True)
    if alarm is None:
        raise AlarmNotFoundError(f"alarm {alarm_id} not found")
    _expire_if_due(alarm, now)
    _apply(alarm, event, actor=actor, now=now, note=note)
    session.flush()
    return alarm


def acknowledge(
    session: Session, alarm_id: int, *, actor: str, now: float, note: str = ""
) -> Alarm:
    """Operator acknowledges an ``unacknowledged`` or ``rtn_unack`` alarm."""
    return _operate(session, alarm_id, "acknowledged", actor=actor, now=now, note=note)


def shelve(
    session: Session,
    alarm_id: int,
    *,
    duration_s: float,
    actor: str,
    now: float,
    note: str = "",
) -> Alarm:
    """Operator shelves an alarm for ``duration_s`` seconds (0 < duration <= MAX_SHELVE_S)."""
    if not 0 < duration_s <= MAX_SHELVE_S:
        raise ValueError(
            f"shelve duration must be in (0, {MAX_SHELVE_S:g}] s, got {duration_s!r}"
        )
    alarm = _operate(session, alarm_id, "shelved", actor=actor, now=now, note=note)
    alarm.shelved_until = now + duration_s
    return alarm


def unshelve(
    session: Session, alarm_id: int, *, actor: str, now: float, note: str = ""
) -> Alarm:
    """Operator ends a shelve early."""
    return _operate(session, alarm_id, "unshelved", actor=actor, now=now, note=note)


def remove_from_service(
    session: Session, alarm_id: int, *, actor: str, now: float, note: str = ""
) -> Alarm:
    """Administrator takes an alarm out of service (e.g. the loop is in maintenance)."""
    return _operate(session, alarm_id, "removed_from_service", actor=actor, now=now, note=note)


def return_to_service(
    session: Session, alarm_id: int, *, actor: str, now: float, note: str = ""
) -> Alarm:
    """Administrator puts an out-of-service alarm back in service."""
    return _operate(session, alarm_id, "returned_to_service", actor=actor, now=now, note=note)


def list_alarms(
    session: Session,
    *,
    loop_id: str | None = None,
    unit_id: str | None = None,
    state: AlarmState | None = None,
    limit: int = 100,
    offset: int = 0,
) -> tuple[list[Alarm], int]:
    """Alarms, highest priority and newest first, and their total count.

    Without ``state`` every alarm that is not ``normal`` is listed (the
    operator's alarm list); with it, exactly the alarms in that state.
    """
    query = select(Alarm)
    if state is None:
        query = query.where(Alarm.state != "normal")
    elif state in ALARM_STATES:
        query = query.where(Alarm.state == state)
    else:
        raise ValueError(f"unknown alarm state {state!r} (expected {', '.join(ALARM_STATES)})")
    if loop_id is not None:
        query = query.where(Alarm.loop_id == loop_id)
    if unit_id is not None:
        query = query.join(Loop, Loop.id == Alarm.loop_id).where(Loop.unit_id == unit_id)
    count = session.scalar(select(func.count()).select_from(query.subquery())) or 0
    rank = case(_PRIORITY_RANK, value=Alarm.priority, else_=len(_PRIORITY_RANK))
    page = session.scalars(
        query.order_by(rank, Alarm.raised_at.desc(), Alarm.id.desc()).limit(limit).offset(offset)
    ).all()
    return list(page), count


def get_alarm(session: Session, alarm_id: int) -> Alarm:
    """The alarm with its events loaded, oldest event first."""
    alarm = session.get(Alarm, alarm_id, options=[selectinload(Alarm.events)])
    if alarm is None:
        raise AlarmNotFoundError(f"alarm {alarm_id} not found")
    return alarm
