"""The final verdict on a valve (service.verdicts): the unit's latest ``ok`` diagnosis has
the last word on the valves of its loops, and the ticket rule reads that verdict."""

from service.store.models import Unit, UnitAnalysisRun
from service.verdicts import (
    UnitDecision,
    latest_unit_decision,
    settle_run,
    valve_size,
    valve_verdict,
)
from tests.service.test_tickets import T0, WINDOW_S, add_loop, add_run, analyse

VALVES = {"AIC-501": "FV-501", "AIC-502": "FV-502", "TIC-503": "PV-503"}


def unit_result(sticky, cleared):
    """The parts of a UnitDiagnosis.to_dict() the decision reads: the named valves, and the
    own-valve test of every loop of the oscillation."""
    return {"sticky_valves": [{"loop": loop, "confidence": 0.8, "period_s": 200.0, "S": 4.0,
                               "J": 2.0, "reason": "its own stiction model is needed"}
                              for loop in sticky],
            "groups": [{"evidence": [{"loop": loop, "own_valve_gain": 0.1 if loop in sticky
                                      else 0.0} for loop in (*sticky, *cleared)]}]}


def unit_run(at, status, sticky, cleared):
    return UnitAnalysisRun(
        unit_id="column", started_at=at, window_start=at - WINDOW_S, window_end=at,
        status=status, loops=["AIC-501", "AIC-502", "TIC-503"], incomplete_loops=[],
        sticky_loops=sticky, cleared_loops=cleared,
        result=unit_result(sticky, cleared) if status == "ok" else None)


def own_diagnosis(verdict="stiction", S=34.0, J=31.0):
    return {"quality": {"usable": True, "issues": []},
            "oscillation": {"detected": True, "period_s": 200.0, "regularity": 10.0,
                            "amplitude_op": 3.0, "amplitude_pv": 1.5},
            "stiction": {"verdict": verdict, "confidence": 0.9, "reason": "shape rules",
                         "pattern": "limit_cycle", "op_travel": None},
            "quantification": {"S": S, "J": J}}


def test_the_latest_ok_unit_diagnosis_clears_its_valves_and_the_ticket_rule_follows(store):
    """Thesis chapter 2: a loop that cycles with a sticky neighbour gets no ticket; the
    valve the unit names does, and one it has not decided on follows its own findings."""
    with store.session() as s:
        s.add(Unit(id="column"))
        s.add_all([unit_run(T0, "ok", ["AIC-501"], ["AIC-502"]),  # older: not read
                   unit_run(T0 + WINDOW_S, "ok", ["AIC-502"], ["AIC-501"]),
                   unit_run(T0 + 2 * WINDOW_S, "failed", [], [])])  # newer, not decided
        for loop_id in VALVES:
            add_loop(s, loop_id)
        decision = latest_unit_decision(s, "column", VALVES)
        assert decision is not None and decision.cleared == ("AIC-501",)

        def decide(loop_id, unit=decision):
            run = add_run(s, at=T0 + 2 * WINDOW_S, loop_id=loop_id)
            run.result = {**run.result, **own_diagnosis()}
            settle_run(run, unit)
            return run, analyse(s, run, loop_id=loop_id, valve_asset=VALVES[loop_id], needed=1)

        run, ticket = decide("AIC-501")
        assert (run.verdict, run.S, run.J, ticket) == ("no_stiction", None, None, None)
        assert run.result["stiction"]["verdict"] == "stiction"  # its own finding stays
        assert run.result["valve"]["reason"] == "cycles because FV-502 sticks"
        assert decide("AIC-502")[1].valve_asset == "FV-502"
        assert decide("TIC-503")[1].valve_asset == "PV-503"  # the unit has not decided on it
        # no unit: its own verdict (the active ticket of FV-501 is opened now)
        assert decide("AIC-501", unit=None)[1].valve_asset == "FV-501"


def test_a_valve_the_unit_names_is_sticky_with_the_units_size_when_the_loop_has_none():

    unit = UnitDecision("column", 3, {"AIC-502": unit_result(["AIC-502"], [])["sticky_valves"][0]},
                        (), VALVES)
    verdict = valve_verdict("AIC-502", own_diagnosis("undecided", S=None, J=None), unit)
    assert (verdict["verdict"], verdict["S"], verdict["J"], verdict["own_verdict"],
            verdict["decided_by"], verdict["unit_run_id"]) == (
        "stiction", 4.0, 2.0, "undecided", "unit", 3)
    # several valves named: the reason names each
    both = UnitDecision("column", 3, {loop: unit.sticky["AIC-502"] for loop in ("AIC-501",
                                                                              "AIC-502")},
                        ("TIC-503",), VALVES)
    assert valve_verdict("TIC-503", own_diagnosis(), both)["reason"] == (
        "cycles because FV-501 and FV-502 stick")


def test_the_combined_size_says_what_its_j_rests_on():
    """Issue 19: a window whose J is known only through K J (the PV step of a slip) marks
    the combined size; one sized with the plant file's gain says where the gain came from;
    windows stored before these flags say nothing."""
    own = {"S": 4.2, "J": 1.9, "S_interval": [4.0, 4.4], "J_interval": [1.5, 2.3]}
    sticky = {"verdict": "stiction", "S": 4.2, "J": 1.9}
    vague = valve_size(sticky, {"quantification": {**own, "J_product_only": True}},
                       (0.0, 3600.0), [])
    assert vague["size_windows"][0]["J_product_only"] and not vague["size_windows"][0][
        "gain_given"]
    assert vague["J_note"].startswith("J is known only through K J in 1 of 1 windows")
    given = {**own, "gain_given": True, "gain_source": "the loop's process_model"}
    both = valve_size(sticky, {"quantification": given}, (3600.0, 7200.0),
                      vague["size_windows"])
    assert both["J_note"].startswith("J is known only through K J in 1 of 2 windows")
    assert valve_size(sticky, {"quantification": given}, (0.0, 3600.0), [])["J_note"] == (
        "J sized with the process gain from the loop's process_model")
    old = [{k: v for k, v in vague["size_windows"][0].items()
            if k not in ("gain_given", "gain_source", "J_product_only")}]
    assert valve_size(sticky, {"quantification": own}, (3600.0, 7200.0), old)["J_note"] is None
    assert valve_size({"verdict": "no_stiction", "S": None, "J": None}, {}, (0.0, 1.0),
                      [])["J_note"] is None
