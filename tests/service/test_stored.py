"""The typed views of stored results (service.stored) read what the analyses store, and
runs stored before a field existed read with its default."""

import numpy as np
import pytest

from analytics.synthetic_cases import synthetic_library
from service.analysis import analyse_window, health_score
from service.stored import (
    SizeWindow,
    StoredDiagnosis,
    StoredEstimate,
    StoredKpis,
    StoredUnitDiagnosis,
    StoredValve,
    ValveSize,
)
from service.verdicts import valve_decision, valve_verdict


@pytest.fixture(scope="module")
def sticky_result():
    """analyse_window's result for an hour of a Kano valve S = 4, J = 2 on a flow loop."""
    case = next(c for c in synthetic_library(3600) if c.name == "flow-kano-S4-J2-ts1")
    run = case.simulate()
    t = np.arange(run.op[0].size, dtype=float)
    loop = {"ts": 1.0, "ranges": {"op": [0, 100], "pv": [0, 100]},
            "process_type": "self-regulating"}
    return analyse_window(loop, 1.0, t, {"op": run.op[0], "pv": run.pv[0], "sp": run.sp[0]})


def test_the_diagnosis_view_reads_every_field_the_service_uses(sticky_result):
    r = sticky_result
    d = StoredDiagnosis.from_dict(r)
    assert (d.samples, d.ts, d.process_type) == (r["samples"], r["ts"], r["process_type"])
    assert d.quality.usable == r["quality"]["usable"]
    assert [i.code for i in d.quality.issues] == [i["code"] for i in r["quality"]["issues"]]
    osc = r["oscillation"]
    assert (d.oscillation.detected, d.oscillation.period_s, d.oscillation.regularity,
            d.oscillation.amplitude_op, d.oscillation.amplitude_pv,
            d.oscillation.analysed_period_s, d.oscillation.envelope_variation) == (
        osc["detected"], osc["period_s"], osc["regularity"], osc["amplitude_op"],
        osc["amplitude_pv"], osc["analysed_period_s"], osc["envelope_variation"])
    assert len(d.oscillation.oscillations) == len(osc["oscillations"])
    st = r["stiction"]
    assert (d.stiction.verdict, d.stiction.confidence, d.stiction.reason, d.stiction.pattern,
            d.stiction.op_travel, d.stiction.episode_stick_band) == (
        st["verdict"], st["confidence"], st["reason"], st["pattern"], st["op_travel"],
        st["episode_stick_band"])
    assert [(e.start_s, e.jump_s, e.end_s) for e in d.stiction.episodes] == [
        (e["start_s"], e["jump_s"], e["end_s"]) for e in st["episodes"]]
    q = r["quantification"]
    assert d.quantification is not None and q["S"] == d.quantification.S
    assert d.quantification.process is not None
    assert q["process"]["K"] == d.quantification.process.K
    assert d.quantification.valve_model == q["valve_model"]
    assert d.apparent_stiction == r["apparent_stiction"]
    assert d.health == r["health"] == health_score(d)
    assert d.first_sample_at == r["first_sample_at"]
    assert d.kpis.oscillation_index == r["kpis"]["oscillation_index"]
    assert d.kpis.saturation == r["kpis"]["saturation"]
    assert (d.manual, d.valve) == (None, None)
    assert d.final == d.stiction


def test_runs_stored_before_a_field_existed_read_with_defaults():
    empty = StoredDiagnosis.from_dict({})
    assert (empty.quality.usable, empty.oscillation.detected, empty.stiction.verdict,
            empty.quantification, empty.manual, empty.valve, empty.first_sample_at) == (
        False, False, None, None, None, None, None)
    assert empty.kpis == StoredKpis()
    assert StoredDiagnosis.from_dict(None) == empty
    old = StoredDiagnosis.from_dict({
        "oscillation": {"detected": True, "period_s": 120.0},  # before analysed_period_s
        "quantification": {"S": 4.0, "J": None},  # before intervals and the process
        "valve": {"verdict": "stiction", "confidence": 0.5, "S": 4.0, "J": 2.0}})
    assert old.oscillation.analysed_period == 120.0
    assert old.quantification == StoredEstimate(S=4.0)
    assert old.valve is not None and old.valve.decided_by == "loop"
    assert (old.valve.S_interval, old.valve.windows_combined) == (None, 0)
    assert old.final is old.valve


def test_the_stored_valve_reads_back_what_settling_writes(sticky_result):
    decision = valve_decision("FIC-1", sticky_result)
    assert valve_verdict("FIC-1", sticky_result) == decision.decision_dict()
    window = SizeWindow(0.0, 3600.0, 4.1, (3.9, 4.3), 1.9, (1.6, 2.2))
    size = ValveSize(4.1, 1.9, (3.9, 4.3), (1.6, 2.2), (window, window))
    stored = {**decision.decision_dict(), **size.to_dict()}
    back = StoredValve.from_dict(stored)
    assert back.decision_dict() == {**decision.decision_dict(), "S": 4.1, "J": 1.9}
    assert (back.S_interval, back.J_interval, back.windows_combined) == (
        (3.9, 4.3), (1.6, 2.2), 2)
    assert SizeWindow.from_dict(window.to_dict()) == window


def test_the_unit_view_reads_findings_groups_and_valve_decisions():
    unit = StoredUnitDiagnosis.from_dict({
        "sticky_valves": [{"loop": "b", "confidence": 0.9, "period_s": 200.0, "S": 4.0,
                           "J": 2.0, "reason": "own valve needed"}],
        "groups": [{"period_s": 200.0, "loops": ["a", "b"],
                    "members": [{"signal": "op_b", "amplitude": 3.0}],
                    "evidence": [{"loop": "a", "own_valve_gain": 0.0},
                                 {"loop": "b", "own_valve_gain": 0.3}],
                    "sticky_valves": ["b"]}]})
    assert unit.valve_decisions() == (["b"], ["a"])
    (finding,) = unit.sticky_valves
    assert (finding.loop, finding.confidence, finding.S, finding.reason) == (
        "b", 0.9, 4.0, "own valve needed")
    (group,) = unit.groups
    assert (group.period_s, group.loops, group.members[0].amplitude) == (200.0, ("a", "b"), 3.0)
    assert StoredUnitDiagnosis.from_dict(None).valve_decisions() == ([], [])
