"""Loop health (service.analysis.health_score) and the alarm message of an analysis:
a valve that sticks without a sustained cycle is a bad actor too."""

import pytest

from service.analysis import health_score, stiction_pattern_text
from service.scheduling.results import alarm_message


def diagnosis(*, usable=True, warnings=0, detected=False, regularity=None,
              verdict="no_stiction", confidence=0.0, pattern=None, op_travel=None,
              reason="why"):
    """The parts of a LoopDiagnosis.to_dict() that health and alarm messages read."""
    return {
        "quality": {"usable": usable, "issues": [{"severity": "warning"}] * warnings
                    + ([] if usable else [{"severity": "fatal"}])},
        "oscillation": {"detected": detected, "regularity": regularity,
                        "period_s": 48.0 if detected else None},
        "stiction": {"verdict": verdict, "confidence": confidence, "pattern": pattern,
                     "op_travel": op_travel, "reason": reason},
    }


@pytest.mark.parametrize(("case", "health"), [
    (diagnosis(), 100.0),
    (diagnosis(warnings=2), 90.0),
    (diagnosis(verdict="undecided"), 100.0),
    # a sticky valve without a cycle is no longer healthy
    (diagnosis(verdict="stiction", confidence=0.75, pattern="stick_jump"), 70.0),
    (diagnosis(warnings=1, verdict="stiction", confidence=0.5, pattern="stick_jump"), 75.0),
    # a stuck valve freezes PV (unusable data) and is scored all the same
    (diagnosis(usable=False, verdict="stiction", confidence=0.9, pattern="stuck"), 64.0),
    (diagnosis(usable=False, verdict="undecided"), None),
    (diagnosis(detected=True, regularity=5.0), 55.0),
    (diagnosis(detected=True, regularity=20.0, verdict="stiction", confidence=1.0,
               pattern="limit_cycle"), 0.0),
])
def test_health(case, health):
    assert health_score(case) == (None if health is None else pytest.approx(health))


def test_a_sticky_valve_without_a_cycle_scores_below_a_healthy_loop():
    healthy = health_score(diagnosis())
    sticky = health_score(diagnosis(verdict="stiction", confidence=0.9, pattern="stick_jump"))
    assert sticky is not None and healthy is not None and sticky < healthy - 30


@pytest.mark.parametrize(("pattern", "op_travel", "words"), [
    ("limit_cycle", None, "limit cycle"),
    ("irregular_cycle", None, "irregular stick-slip cycle"),
    ("stick_jump", 8.0, "stick-jump: the valve holds while OP ramps, then jumps; no sustained "
                        "cycle"),
    ("stuck", 23.4, "stuck: OP travelled 23.4 % with no PV response"),
    ("stuck", None, "stuck: OP travels with no PV response"),
    (None, 5.0, None),
])
def test_stiction_pattern_text(pattern, op_travel, words):
    assert stiction_pattern_text(pattern, op_travel) == words


@pytest.mark.parametrize(("case", "message"), [
    (diagnosis(), "no oscillation"),
    (diagnosis(verdict="stiction", confidence=0.8, pattern="stick_jump"),
     "no oscillation; valve: stiction (stick-jump: the valve holds while OP ramps, then "
     "jumps; no sustained cycle)"),
    (diagnosis(detected=True, verdict="stiction", pattern="limit_cycle"),
     "oscillation, period 48 s; valve: stiction (limit cycle)"),
    (diagnosis(detected=True, verdict="no_stiction"), "oscillation, period 48 s; valve: "
     "no stiction"),
    (diagnosis(usable=False, verdict="stiction", pattern="stuck", op_travel=30.0),
     "data unusable, valve: stiction (stuck: OP travelled 30.0 % with no PV response)"),
    # the reason of unusable data is the diagnosis's own, which says so (it was said twice)
    (diagnosis(usable=False, verdict="undecided", reason="data unusable: PV flat"),
     "data unusable: PV flat"),
])
def test_alarm_messages_name_the_stiction_pattern(case, message):
    assert alarm_message(case) == message
