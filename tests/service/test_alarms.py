"""Operator alarms: the ISA-18.2 state machine, and its records in the store."""

import pytest

from service.alarms import (
    ALARM_STATES,
    MAX_SHELVE_S,
    TRANSITIONS,
    AlarmNotFoundError,
    AlarmStateError,
    acknowledge,
    alarm_priority,
    expire_shelves,
    get_alarm,
    list_alarms,
    next_state,
    remove_from_service,
    return_to_service,
    shelve,
    unshelve,
    update_alarms_from_analysis,
)
from service.store.models import Alarm, AlarmEvent, Loop, Unit

T0 = 1_700_000_000.0


# --- pure state machine ----------------------------------------------------


@pytest.mark.parametrize(
    ("state", "event", "active", "expected"),
    [
        ("normal", "activated", True, "unacknowledged"),
        ("unacknowledged", "acknowledged", True, "acknowledged"),
        ("acknowledged", "returned_to_normal", False, "normal"),
        ("unacknowledged", "returned_to_normal", False, "rtn_unack"),
        ("rtn_unack", "acknowledged", False, "normal"),
        ("rtn_unack", "activated", True, "unacknowledged"),
        ("acknowledged", "shelved", True, "shelved"),
        ("shelved", "activated", True, "shelved"),
        ("shelved", "unshelved", True, "unacknowledged"),
        ("shelved", "shelve_expired", False, "normal"),
        ("shelved", "removed_from_service", True, "out_of_service"),
        ("out_of_service", "returned_to_normal", False, "out_of_service"),
        ("out_of_service", "returned_to_service", True, "unacknowledged"),
        ("out_of_service", "returned_to_service", False, "normal"),
    ],
)
def test_isa_18_2_transitions(state, event, active, expected):
    assert next_state(state, event, condition_active=active) == expected


@pytest.mark.parametrize(
    ("state", "event", "message"),
    [
        ("normal", "acknowledged", "cannot acknowledge an alarm that is normal "
                                   "(possible when unacknowledged or rtn_unack)"),
        ("acknowledged", "acknowledged", "cannot acknowledge an alarm that is acknowledged"),
        ("shelved", "shelved", "cannot shelve an alarm that is shelved"),
        ("normal", "unshelved", "cannot unshelve an alarm that is normal (possible when shelved)"),
        ("out_of_service", "removed_from_service",
         "cannot remove from service an alarm that is out_of_service"),
        ("acknowledged", "returned_to_service", "cannot return to service an alarm that is"),
        ("out_of_service", "shelved", "cannot shelve an alarm that is out_of_service"),
    ],
)
def test_invalid_transitions_say_state_and_request(state, event, message):
    with pytest.raises(AlarmStateError) as info:
        next_state(state, event, condition_active=False)
    assert str(info.value).startswith(message)
    assert isinstance(info.value, ValueError)


def test_every_transition_leads_to_a_known_state():
    for event, table in TRANSITIONS.items():
        for state in table:
            assert state in ALARM_STATES
            for active in (False, True):
                assert next_state(state, event, condition_active=active) in ALARM_STATES


@pytest.mark.parametrize(
    ("kind", "importance", "priority"),
    [
        ("oscillation", "low", "low"),
        ("oscillation", "high", "medium"),
        ("oscillation", "critical", "high"),
        ("data_quality", "high", "low"),
        ("data_quality", "critical", "medium"),
    ],
)
def test_priority_by_kind_and_importance(kind, importance, priority):
    assert alarm_priority(kind, importance) == priority


def test_unknown_importance_is_refused():
    with pytest.raises(ValueError, match=r"unknown loop importance 'vital' \(expected low, "):
        alarm_priority("oscillation", "vital")


# --- in the store ------------------------------------------------------------


def add_loop(session, loop_id="FIC-101", unit_id=None):
    session.add(Loop(id=loop_id, name=loop_id, unit_id=unit_id, config={},
                     created_at=T0, updated_at=T0))
    session.flush()


def analyse(session, *, at, loop_id="FIC-101", oscillating=False, usable=True,
            importance="medium", message="analysis"):
    return update_alarms_from_analysis(
        session, loop_id, oscillating=oscillating, usable=usable, importance=importance,
        message=message, now=at,
    )


def history(alarm):
    return [(e.event, e.from_state, e.to_state, e.actor, e.at) for e in alarm.events]


def test_oscillation_lifecycle_reuses_the_row_and_records_everything(store):
    with store.session() as s:
        add_loop(s)
        assert analyse(s, at=T0) == []
        assert s.query(Alarm).count() == 0
        (alarm,) = analyse(s, at=T0 + 60, oscillating=True, message="period 48 s")
        alarm_id = alarm.id
        assert (alarm.kind, alarm.state, alarm.priority) == ("oscillation", "unacknowledged", "low")
        assert alarm.message == "period 48 s"
        assert alarm.raised_at == T0 + 60
    with store.session() as s:
        assert analyse(s, at=T0 + 120, oscillating=True) == []  # still active: no change
        acknowledge(s, alarm_id, actor="olga", now=T0 + 130, note="seen")
        analyse(s, at=T0 + 180, oscillating=False)
        (again,) = analyse(s, at=T0 + 240, oscillating=True, importance="critical")
        assert again.id == alarm_id
        assert (again.state, again.priority) == ("unacknowledged", "high")
        assert again.raised_at == T0 + 240
    with store.session() as s:
        alarm = get_alarm(s, alarm_id)
        assert history(alarm) == [
            ("activated", "normal", "unacknowledged", "analysis", T0 + 60),
            ("acknowledged", "unacknowledged", "acknowledged", "olga", T0 + 130),
            ("returned_to_normal", "acknowledged", "normal", "analysis", T0 + 180),
            ("activated", "normal", "unacknowledged", "analysis", T0 + 240),
        ]
        assert alarm.events[1].note == "seen"
        assert s.query(Alarm).count() == 1


def test_return_to_normal_unacknowledged_then_acknowledge(store):
    with store.session() as s:
        add_loop(s)
        (alarm,) = analyse(s, at=T0, oscillating=True)
        analyse(s, at=T0 + 60, oscillating=False)
        assert alarm.state == "rtn_unack"
        assert not alarm.condition_active
        acknowledge(s, alarm.id, actor="olga", now=T0 + 90)
        assert alarm.state == "normal"
        assert list_alarms(s) == ([], 0)


def test_invalid_operator_action_is_refused_and_not_recorded(store):
    with store.session() as s:
        add_loop(s)
        (alarm,) = analyse(s, at=T0, oscillating=True)
        acknowledge(s, alarm.id, actor="olga", now=T0 + 10)
        alarm_id = alarm.id
    with store.session() as s:
        with pytest.raises(AlarmStateError) as info:
            acknowledge(s, alarm_id, actor="olga", now=T0 + 20)
        assert str(info.value) == (
            f"alarm {alarm_id} (FIC-101 oscillation): cannot acknowledge an alarm that is "
            "acknowledged (possible when unacknowledged or rtn_unack)"
        )
    with store.session() as s:
        assert s.query(AlarmEvent).count() == 2


def test_unknown_alarm_and_unknown_loop(store):
    with store.session() as s:
        with pytest.raises(AlarmNotFoundError, match="alarm 999 not found"):
            acknowledge(s, 999, actor="olga", now=T0)
        with pytest.raises(AlarmNotFoundError, match="alarm 999 not found"):
            get_alarm(s, 999)
        with pytest.raises(LookupError, match="loop 'nope' not found"):
            analyse(s, at=T0, loop_id="nope", oscillating=True)


def test_shelved_alarm_tracks_its_condition_and_expires(store):
    with store.session() as s:
        add_loop(s)
        (alarm,) = analyse(s, at=T0, oscillating=True)
        shelve(s, alarm.id, duration_s=3600, actor="olga", now=T0 + 10, note="known, valve job")
        assert (alarm.state, alarm.shelved_until) == ("shelved", T0 + 3610)
        assert analyse(s, at=T0 + 60, oscillating=False) == []
        assert analyse(s, at=T0 + 120, oscillating=True) == []
        assert (alarm.state, alarm.condition_active) == ("shelved", True)
        # the next analysis after the shelve ran out finds it expired
        (expired,) = analyse(s, at=T0 + 4000, oscillating=True)
        assert (expired.state, expired.shelved_until) == ("unacknowledged", None)
        assert history(alarm)[1:] == [
            ("shelved", "unacknowledged", "shelved", "olga", T0 + 10),
            ("returned_to_normal", "shelved", "shelved", "analysis", T0 + 60),
            ("activated", "shelved", "shelved", "analysis", T0 + 120),
            ("shelve_expired", "shelved", "unacknowledged", "system", T0 + 3610),
        ]


def test_expire_shelves_and_unshelve(store):
    with store.session() as s:
        add_loop(s, "A")
        add_loop(s, "B")
        (a,) = analyse(s, at=T0, loop_id="A", oscillating=True)
        (b,) = analyse(s, at=T0, loop_id="B", oscillating=True)
        analyse(s, at=T0 + 5, loop_id="A", oscillating=False)
        shelve(s, a.id, duration_s=100, actor="olga", now=T0 + 10)
        shelve(s, b.id, duration_s=1000, actor="olga", now=T0 + 10)
        assert expire_shelves(s, now=T0 + 50) == []
        assert expire_shelves(s, now=T0 + 110) == [a]
        assert a.state == "normal"  # its condition cleared while shelved
        assert b.state == "shelved"
        unshelve(s, b.id, actor="olga", now=T0 + 120)
        assert (b.state, b.shelved_until) == ("unacknowledged", None)
        with pytest.raises(AlarmStateError, match="cannot unshelve an alarm that is unack"):
            unshelve(s, b.id, actor="olga", now=T0 + 130)


def test_operator_action_after_the_shelve_ran_out_sees_the_expiry_first(store):
    with store.session() as s:
        add_loop(s)
        (alarm,) = analyse(s, at=T0, oscillating=True)
        shelve(s, alarm.id, duration_s=60, actor="olga", now=T0)
        acknowledge(s, alarm.id, actor="olga", now=T0 + 100)
        assert [e.event for e in alarm.events] == [
            "activated", "shelved", "shelve_expired", "acknowledged"
        ]
        assert alarm.state == "acknowledged"


@pytest.mark.parametrize("duration", [0, -5, MAX_SHELVE_S + 1, float("nan")])
def test_shelve_needs_a_limited_positive_duration(store, duration):
    with store.session() as s:
        add_loop(s)
        (alarm,) = analyse(s, at=T0, oscillating=True)
        with pytest.raises(ValueError, match=r"shelve duration must be in \(0, 86400\] s"):
            shelve(s, alarm.id, duration_s=duration, actor="olga", now=T0)
        assert alarm.state == "unacknowledged"


def test_out_of_service_suppresses_until_returned(store):
    with store.session() as s:
        add_loop(s)
        (alarm,) = analyse(s, at=T0, oscillating=True)
        remove_from_service(s, alarm.id, actor="admin", now=T0 + 10, note="loop in manual")
        analyse(s, at=T0 + 60, oscillating=False)
        with pytest.raises(AlarmStateError, match="is out_of_service"):
            acknowledge(s, alarm.id, actor="olga", now=T0 + 70)
        with pytest.raises(AlarmStateError, match="cannot shelve an alarm that is out_of_service"):
            shelve(s, alarm.id, duration_s=60, actor="olga", now=T0 + 70)
        return_to_service(s, alarm.id, actor="admin", now=T0 + 80)
        assert alarm.state == "normal"
        assert history(alarm)[-1] == ("returned_to_service", "out_of_service", "normal",
                                      "admin", T0 + 80)


def test_unusable_data_raise_data_quality_and_leave_oscillation_alone(store):
    with store.session() as s:
        add_loop(s)
        (osc,) = analyse(s, at=T0, oscillating=True)
        (dq,) = analyse(s, at=T0 + 60, usable=False, oscillating=False,
                        importance="critical", message="PV frozen")
        assert (dq.kind, dq.state, dq.priority, dq.message) == (
            "data_quality", "unacknowledged", "medium", "PV frozen"
        )
        assert (osc.state, osc.condition_active) == ("unacknowledged", True)
        changed = analyse(s, at=T0 + 120, oscillating=False)
        assert {a.kind: a.state for a in changed} == {
            "data_quality": "rtn_unack", "oscillation": "rtn_unack"
        }


def test_a_loop_out_of_service_raises_no_data_quality_alarm(store):
    """A loop in manual too long to be judged is out of service, not faulty data: its
    data-quality alarm stays quiet (ISA-18.2 suppression by design), and its oscillation
    alarm is left as it was."""
    with store.session() as s:
        add_loop(s)
        (osc,) = analyse(s, at=T0, oscillating=True)
        assert update_alarms_from_analysis(
            s, "FIC-101", oscillating=False, usable=False, importance="critical",
            message="in manual 90 % of the window", now=T0 + 60, out_of_service=True) == []
        assert s.query(Alarm).filter_by(kind="data_quality").count() == 0
        assert (osc.state, osc.condition_active) == ("unacknowledged", True)


def test_list_alarms_filters_and_orders(store):
    with store.session() as s:
        s.add(Unit(id="column", name="Column"))
        s.flush()
        add_loop(s, "A", unit_id="column")
        add_loop(s, "B")
        add_loop(s, "C", unit_id="column")
        (a,) = analyse(s, at=T0, loop_id="A", oscillating=True, importance="low")
        (b,) = analyse(s, at=T0 + 1, loop_id="B", oscillating=True, importance="critical")
        (c,) = analyse(s, at=T0 + 2, loop_id="C", oscillating=True, importance="low")
        analyse(s, at=T0 + 3, loop_id="C", oscillating=False)
        acknowledge(s, c.id, actor="olga", now=T0 + 4)  # C is back to normal
        acknowledge(s, a.id, actor="olga", now=T0 + 5)

        assert list_alarms(s) == ([b, a], 2)  # high before low; normal left out
        assert list_alarms(s, unit_id="column") == ([a], 1)
        assert list_alarms(s, state="normal") == ([c], 1)
        assert list_alarms(s, state="acknowledged", loop_id="A") == ([a], 1)
        assert list_alarms(s, loop_id="B", state="acknowledged") == ([], 0)
        assert list_alarms(s, limit=1, offset=1) == ([a], 2)
        with pytest.raises(ValueError, match="unknown alarm state 'active' \\(expected normal, "):
            list_alarms(s, state="active")
