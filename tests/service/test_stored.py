"""The typed views of stored results (service.stored) read what the analyses store, and
runs stored before a field existed read with its default."""

import numpy as np
import pytest

from analytics.diagnosis import LoopDiagnosis
from analytics.errors import DataError
from analytics.plantwide import UnitDiagnosis
from analytics.synthetic_cases import synthetic_library
from service.analysis import analyse_window, health_score
from service.stored import (
    SizeWindow,
    StoredDiagnosis,
    StoredKpis,
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


def test_the_diagnosis_view_reads_the_analysis_and_what_the_service_adds(sticky_result):
    r = sticky_result
    d = StoredDiagnosis.from_dict(r)
    analysis = {k: v for k, v in r.items() if k in LoopDiagnosis.from_dict(r).to_dict()}
    assert d.analysis == LoopDiagnosis.from_dict(analysis)  # the one reader, leniently
    assert d.analysis.to_dict() == analysis
    assert d.analysed_period == r["oscillation"]["analysed_period_s"]
    assert d.health == r["health"] == health_score(d)
    assert d.first_sample_at == r["first_sample_at"]
    assert d.kpis.oscillation_index == r["kpis"]["oscillation_index"]
    assert d.kpis.saturation == r["kpis"]["saturation"]
    assert (d.manual, d.valve, d.gain_source) == (None, None, None)
    assert d.final == d.analysis.stiction


def test_runs_stored_before_a_field_existed_read_with_defaults():
    empty = StoredDiagnosis.from_dict({})
    a = empty.analysis
    assert (a.quality.usable, a.quality.issues, empty.oscillation.detected, a.stiction.verdict,
            a.stiction.confidence, a.stiction.methods, a.episodes, a.quantification,
            a.ellipse, a.process_type_source) == (
        False, (), False, None, 0.0, {}, (), None, None, "unknown")
    assert (empty.manual, empty.valve, empty.first_sample_at) == (None, None, None)
    assert empty.kpis == StoredKpis()
    assert StoredDiagnosis.from_dict(None) == empty
    old = StoredDiagnosis.from_dict({
        "oscillation": {"detected": True, "period_s": 120.0},  # before analysed_period_s
        "quantification": {"S": 4.0, "J": None},  # before intervals and the process
        "apparent_stiction": {"apparent_stiction": 3.1, "width_ratio": 0.4,
                              "op_amplitude": 3.9, "residual": 0.1},  # before the geometry
        "valve": {"verdict": "stiction", "confidence": 0.5, "S": 4.0, "J": 2.0}})
    assert old.analysed_period == 120.0
    estimate = old.analysis.quantification
    assert estimate is not None
    assert (estimate.S, estimate.J, estimate.model, estimate.S_interval, estimate.valve_model,
            estimate.stiction_found) == (4.0, None, None, None, None, False)
    assert old.analysis.ellipse is None  # the signature plot fits it again
    assert old.valve is not None and old.valve.decided_by == "loop"
    assert (old.valve.S_interval, old.valve.windows_combined) == (None, 0)
    assert old.final is old.valve
    with pytest.raises(DataError, match="loop diagnosis: the field 'samples' is missing"):
        LoopDiagnosis.from_dict({})  # strict: refuses what the lenient read fills


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


def test_a_stored_unit_diagnosis_reads_leniently_with_its_valve_decisions():
    unit = UnitDiagnosis.from_dict({
        "sticky_valves": [{"loop": "b", "confidence": 0.9, "period_s": 200.0, "S": 4.0,
                           "J": 2.0, "reason": "own valve needed"}],
        "groups": [{"period_s": 200.0, "loops": ["a", "b"],
                    "members": [{"signal": "op_b", "amplitude": 3.0}],
                    "evidence": [{"loop": "a", "own_valve_gain": 0.0},
                                 {"loop": "b", "own_valve_gain": 0.3}],
                    "sticky_valves": ["b"]}]}, lenient=True)
    assert unit.valve_decisions() == (["b"], ["a"])
    (finding,) = unit.sticky_valves
    assert (finding.loop, finding.confidence, finding.S, finding.reason) == (
        "b", 0.9, 4.0, "own valve needed")
    (group,) = unit.groups
    assert (group.period_s, group.loops, group.members[0].amplitude) == (200.0, ("a", "b"), 3.0)
    assert group.evidence[0].half_gains == (None, None)
    assert UnitDiagnosis.from_dict({}, lenient=True).valve_decisions() == ([], [])
    with pytest.raises(DataError, match="unit diagnosis: the field 'loops' is missing"):
        UnitDiagnosis.from_dict({})
