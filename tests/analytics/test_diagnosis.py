"""The per-loop pipeline, and the accuracy floors of issue 3 on labelled data.

The floors are what the pipeline reaches today with one fixed configuration
(benchmarks/detection.py prints every case); they catch regressions.  The
synthetic library has ground truth by construction (analytics.synthetic_cases);
the ISDB loops were not used to tune the combination.
"""

import json
import re
import statistics

import numpy as np
import pytest

from analytics.diagnosis import LoopDiagnosis, diagnose_loop
from analytics.errors import DataError
from analytics.stiction.stick_jump import MIN_TRAVEL
from analytics.synthetic_cases import synthetic_library, transient_library, transient_sweep
from tests.shared_data import SHARED_DATA, isdb_labels, load_isdb_loop, require_file

CASES = {c.name: c for c in synthetic_library()}


def run(name, **options):
    case = CASES[name]
    r = case.simulate()
    return case, diagnose_loop(ts=case.ts, op=r.op[0], pv=r.pv[0], sp=r.sp[0], **options)


def test_sticky_valve_is_found_sized_and_explained():
    case, d = run("flow-kano-S4-J2-ts1", process_type="self-regulating")
    assert d.stiction.verdict == "stiction" and d.stiction.confidence > 0.3
    assert d.process_type_source == "given"
    assert d.quantification is not None
    assert abs(d.quantification.S - case.S) < 0.15 * case.S
    assert d.ellipse is not None and 0.5 * case.S < d.ellipse.apparent_stiction < 1.2 * case.S
    assert d.stiction.methods["hammerstein"].decision == "stiction"
    assert "for:" in d.stiction.reason


def test_method_notes_give_their_sizes_units():
    """QA: the loop page's method notes gave S, the apparent stiction and OP's travel as
    bare numbers; each now says % of (OP) span."""
    _, d = run("flow-kano-S4-J2-ts1", process_type="self-regulating")
    methods = d.stiction.methods
    assert f"(S = {d.quantification.S:.2f} % of OP span)" in methods["hammerstein"].note
    assert (f"apparent stiction {d.ellipse.apparent_stiction:.3g} % of OP span"
            in methods["ellipse"].note)
    for name in ("stick_jump", "stuck_sections"):
        note = methods[name].note
        assert re.search(r"OP (travelled about|went) [-\d.e]+ % of span", note) or (
            "travelled" not in note and "went" not in note), note


def test_an_external_disturbance_is_not_blamed_on_the_valve():
    _, d = run("temp-sine200s-ts2")
    assert d.oscillation.detected
    assert d.stiction.verdict == "no_stiction"
    assert d.quantification is None  # sizes only for sticky valves
    assert d.process_type_source in {"assumed", "inferred"}


@pytest.mark.parametrize(("name", "low", "high"), [
    ("temp-sine200s-ts2", 0.0, 0.05),  # a periodic forcing keeps its amplitude
    ("flow-kano-S8-J4-ts1", 0.0, 0.1),  # so does a stiction limit cycle
    ("flow-aggressive-ts1", 0.35, 0.65),  # a noise-driven resonance: Rayleigh, 0.52
])
def test_the_oscillation_says_how_steady_its_amplitude_is(name, low, high):
    _, d = run(name)
    assert low <= d.envelope_variation <= high
    assert d.to_dict()["oscillation"]["envelope_variation"] == d.envelope_variation


def test_on_a_regular_cycle_only_clear_slips_count():
    """A slow external sine is cut by the hold band at its peaks into holds two
    bands apart that look like small slips (flow-sine150s-ts1 has 8 of them);
    on a regular cycle the stick-jump method counts only slips of
    CYCLE_SLIP_BANDS, so it does not vote for the valve there, while the
    sticky valve's slips of a stiction cycle count."""
    _, sine = run("flow-sine150s-ts1")
    assert sine.oscillation.detected and sine.stiction.verdict == "no_stiction"
    assert sine.stiction.methods["stick_jump"].decision != "stiction"
    assert sine.episodes == ()  # the episodes reported are the slips that count
    _, sticky = run("flow-he-S4-J2-ts1")
    assert sticky.oscillation.detected
    assert sticky.stiction.methods["stick_jump"].decision == "stiction"


def test_a_valve_that_hardly_moves_is_not_judged():
    """Issue 17: too little OP travel to expose a stick band gives undecided with the
    travel seen, not a confident no_stiction."""
    _, d = run("level-noise-ts1")
    assert d.stiction.verdict == "undecided"
    assert d.stiction.reason.startswith("not enough valve movement to judge")
    assert d.op_travel is not None and d.op_travel < MIN_TRAVEL
    assert f"{d.op_travel:.3g}" in d.stiction.reason


def test_a_frozen_pv_while_op_travels_far_is_a_stuck_valve():
    k = np.arange(2000)
    op = 40.0 + 15.0 * np.sin(2 * np.pi * k / 700)  # the controller pushes +-15 %
    pv = np.full(k.size, 63.2)
    d = diagnose_loop(ts=1.0, op=op, pv=pv)
    assert d.stiction.verdict == "stiction" and d.pattern == "stuck"
    assert d.op_travel is not None and d.op_travel > 50
    assert d.stiction.reason.startswith("stuck")
    # The same frozen PV with a quiet OP is unusable data, not a finding.
    quiet = diagnose_loop(ts=1.0, op=np.full(k.size, 40.0), pv=pv)
    assert quiet.stiction.verdict == "undecided" and quiet.pattern is None


def test_a_stick_jump_valve_without_a_cycle_is_found_with_its_episodes():
    case = next(c for c in transient_library() if c.name == "flow-kano-S2-J0.5-load-steps-ts1")
    r = case.simulate()
    d = diagnose_loop(ts=case.ts, op=r.op[0], pv=r.pv[0], sp=r.sp[0],
                      process_type=case.process_type)
    assert not d.oscillation.detected
    assert d.stiction.verdict == "stiction" and d.pattern == "stick_jump"
    out = d.to_dict()["stiction"]
    assert out["pattern"] == "stick_jump" and out["episodes"]
    for episode in out["episodes"]:
        assert 0 <= episode["start_s"] < episode["jump_s"] <= episode["end_s"]
        assert abs(episode["op_travel"]) > abs(episode["op_during_jump"])


def test_an_irregular_stick_slip_cycle_is_still_examined():
    _, d = run("level-he-S8-J2-ts1", process_type="integrating")
    assert not d.oscillation.detected  # too irregular for Thornhill's r > 1
    assert d.cycle_period_s is not None
    assert d.stiction.verdict == "stiction"
    assert d.stiction.reason.startswith("irregular stick-slip cycle")


def test_unusable_data_gives_undecided_with_reasons():
    d = diagnose_loop(ts=1.0, op=np.full(500, 50.0), pv=np.full(500, 20.0))
    assert d.stiction.verdict == "undecided"
    assert "constant" in d.stiction.reason
    assert d.to_dict()["quality"]["usable"] is False


def test_quantised_data_set_nonlinearity_tests_aside():
    case = CASES["flow-kano-S4-J2-ts1"]
    r = case.simulate()
    coarse_pv = np.round(r.pv[0] / 0.5) * 0.5  # a coarse transmitter resolution
    d = diagnose_loop(ts=case.ts, op=r.op[0], pv=coarse_pv, process_type="self-regulating")
    assert "quantisation" in d.quality.codes()
    for name in ("bicoherence", "surrogate"):
        assert d.stiction.methods[name].decision == "undecided"
        assert "set aside" in d.stiction.methods[name].note


def test_json_form_has_the_cli_contract():
    _, d = run("flow-he-S4-J2-ts1", process_type="self-regulating")
    out = d.to_dict()
    assert {"samples", "ts", "quality", "oscillation", "stiction", "quantification"} <= set(out)
    assert set(out["quantification"]) >= {"S", "J", "fs", "fd", "fit_r2"}
    # The cycle battery, Hammerstein and the transient methods (slips count on a cycle too).
    assert len(out["stiction"]["methods"]) == 11
    assert out["stiction"]["pattern"] == "limit_cycle"
    assert {"episodes", "op_travel", "episode_stick_band"} <= set(out["stiction"])


@pytest.mark.slow
def test_synthetic_library_floor():
    """Issue 3: balanced accuracy >= 0.95 and S within 15 % (median) on the library.

    A healthy loop whose valve hardly moved is ``undecided`` by design (issue
    17); it counts as right, as it raises no ticket.
    """
    truth, verdicts, errors_S, errors_J = [], [], [], []
    for case in CASES.values():
        r = case.simulate()
        d = diagnose_loop(ts=case.ts, op=r.op[0], pv=r.pv[0], sp=r.sp[0],
                          process_type=case.process_type)
        truth.append(case.label)
        idle = d.stiction.reason.startswith("not enough valve movement")
        verdicts.append("no_stiction" if idle and case.label == "no_stiction"
                        else d.stiction.verdict)
        q = d.quantification
        if q is not None and q.S is not None and q.J is not None and case.S and case.J:
            errors_S.append(abs(q.S - case.S) / case.S)
            errors_J.append(abs(q.J - case.J) / case.J)
    recalls = [np.mean([v == label for t, v in zip(truth, verdicts, strict=True) if t == label])
               for label in ("stiction", "no_stiction")]
    assert np.mean(recalls) >= 0.95
    assert statistics.median(errors_S) < 0.15
    assert statistics.median(errors_J) < 0.6  # short of the 15 % target: see the closing note


@pytest.mark.slow
def test_isdb_floor():
    """At least 10 of the 14 ISDB loops right (Jelali & Huang 2010 labels; 11 today),
    no healthy loop called sticky."""
    correct = 0
    for row in isdb_labels():
        t, op, pv = load_isdb_loop(row["loop"])
        d = diagnose_loop(ts=float(row["ts_s"]), op=op, pv=pv, t=t)
        correct += d.stiction.verdict == row["label"]
        if row["label"] == "no_stiction":
            assert d.stiction.verdict != "stiction", row["loop"]
    assert correct >= 10


@pytest.mark.slow
def test_transient_library_floor():
    """Issue 17 on the non-oscillating library: at least 17 of its 20 sticky valves
    found (18 today), none of its 21 healthy look-alikes called sticky."""
    found = false_alarms = 0
    for case in transient_library():
        r = case.simulate()
        d = diagnose_loop(ts=case.ts, op=r.op[0], pv=r.pv[0], sp=r.sp[0],
                          process_type=case.process_type)
        if case.label == "stiction":
            found += d.stiction.verdict == "stiction"
        else:
            false_alarms += d.stiction.verdict == "stiction"
    assert found >= 17
    assert false_alarms == 0


@pytest.mark.slow
def test_sweep_set_point_and_load_steps_floor():
    """The library's loops on other seeds (transient_sweep), in the scenarios the
    stick-jump method is built for: set-point steps and ramps, load steps.  Today
    137 of 144 sticky valves found and 2 of 72 healthy valves called sticky; the
    random walks and saturation, where it is weak, are printed by
    benchmarks/detection.py, not held to a floor."""
    found = sticky = false_alarms = 0
    for case in transient_sweep():
        if case.name.split("-", 2)[2].rsplit("-seed", 1)[0] not in (
                "sp-steps", "sp-ramp", "load-steps"):
            continue
        r = case.simulate()
        d = diagnose_loop(ts=case.ts, op=r.op[0], pv=r.pv[0], sp=r.sp[0],
                          process_type=case.process_type)
        if case.label == "stiction":
            sticky += 1
            found += d.stiction.verdict == "stiction"
        else:
            false_alarms += d.stiction.verdict == "stiction"
    assert found >= 0.9 * sticky
    assert false_alarms <= 3


def plant_dev_windows(parts=((0.0, 1.0),)):
    """(label, diagnosis) of every labelled window of ../shared/data/plant_dev, or
    of the given parts of each (start and end as shares of the window)."""
    import csv

    from service.loop_csv import read_loop_csv

    labels = require_file(SHARED_DATA / "plant_dev" / "labels.csv")
    with labels.open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    for row in rows:
        data = read_loop_csv(labels.parent / f"{row['window']}.csv", ts=float(row["ts_s"]))
        n = len(data.op)
        for start, end in parts:
            part = slice(int(start * n), int(end * n))
            yield row["label"], diagnose_loop(
                ts=data.ts, op=data.op[part], pv=data.pv[part],
                sp=None if data.sp is None else data.sp[part], t=data.t[part])


@pytest.mark.slow
def test_plant_dev_floor():
    """Issue 17 on the plant's labelled windows: at least 9 of the 10 sticky windows
    found (most of them without a cycle), no healthy window called sticky."""
    found = false_alarms = 0
    for label, d in plant_dev_windows():
        if label == "stiction":
            found += d.stiction.verdict == "stiction"
        else:
            false_alarms += d.stiction.verdict == "stiction"
    assert found >= 9
    assert false_alarms == 0


@pytest.mark.slow
def test_parts_of_healthy_plant_windows_are_not_called_sticky():
    """Held-out windows of the plant are other cuts of its loops: halves and
    two-thirds of the 16 healthy windows (80 cuts) must not be called sticky
    either.  Two kinds of false alarm were found this way and closed: a
    micro-cycle of 0.15 % of OP on a healthy flow (now "not enough valve
    movement"), and a flow read as a level whose smoothed slope held through
    an OP reversal with no slip (the slope is taken only with episodes)."""
    parts = ((0.0, 0.5), (0.5, 1.0), (0.25, 0.75), (0.0, 2 / 3), (1 / 3, 1.0))
    false_alarms = [d.stiction.reason for label, d in plant_dev_windows(parts)
                    if label == "no_stiction" and d.stiction.verdict == "stiction"]
    assert not false_alarms


def test_a_given_process_gain_sizes_the_sticky_valve_and_leaves_the_verdict() -> None:
    """Issue 19: the verdict is reached with the gain fitted; the size uses the gain given
    (and a PV less the other inputs' effect, when given)."""
    case = CASES["flow-he-S8-J4-ts1"]  # K = 1.2
    res = case.simulate()
    signals = {"ts": case.ts, "op": res.op[0], "pv": res.pv[0], "sp": res.sp[0],
               "process_type": case.process_type}
    fitted = diagnose_loop(**signals)
    given = diagnose_loop(**signals, process_gain=1.2)
    assert given.stiction.verdict == fitted.stiction.verdict == "stiction"
    assert given.stiction.confidence == fitted.stiction.confidence
    q = given.quantification
    assert q is not None and q.gain_given and q.model is not None and q.model.K == 1.2
    shifted = diagnose_loop(**signals, process_gain=1.2, sizing_pv=res.pv[0] + 3.0)
    assert shifted.quantification is not None and shifted.quantification.S == q.S
    with pytest.raises(DataError, match="process_type"):
        diagnose_loop(ts=case.ts, op=res.op[0], pv=res.pv[0], process_gain=1.2)
    with pytest.raises(DataError, match="sizing_pv"):
        diagnose_loop(**signals, process_gain=1.2, sizing_pv=res.pv[0][:-1])


def assert_round_trip(d):
    """to_dict(from_dict(d)) == d to the byte, for the JSON as stored (json.loads of it),
    strict and lenient."""
    stored = json.dumps(d.to_dict())
    for lenient in (False, True):
        again = LoopDiagnosis.from_dict(json.loads(stored), lenient=lenient)
        assert json.dumps(again.to_dict()) == stored


def test_loop_diagnoses_of_the_library_round_trip_through_their_json_form():
    """Issue 25: sticky with a size (and one sized with a given gain), healthy, too little
    movement, unusable, stuck."""
    sticky = run("flow-kano-S4-J2-ts1", process_type="self-regulating")[1]
    assert sticky.quantification is not None and sticky.episode_size is not None
    healthy = run("temp-sine200s-ts2")[1]
    still = run("level-noise-ts1")[1]
    assert still.stiction.reason.startswith("not enough valve movement")
    gain = run("flow-he-S8-J4-ts1", process_type="self-regulating", process_gain=1.2)[1]
    k = np.arange(2000)
    stuck = diagnose_loop(ts=1.0, op=40.0 + 15.0 * np.sin(2 * np.pi * k / 700),
                          pv=np.full(k.size, 63.2))
    unusable = diagnose_loop(ts=1.0, op=np.full(500, 50.0), pv=np.full(500, 20.0))
    for d in (sticky, healthy, still, gain, stuck, unusable):
        assert_round_trip(d)
    again = LoopDiagnosis.from_dict(sticky.to_dict())
    assert again.stiction.verdict == "stiction" and again.quantification is not None
    assert again.quantification.S == sticky.quantification.S
    assert again.episodes == sticky.episodes  # sample indices back from the seconds
    assert again.ellipse == sticky.ellipse


@pytest.mark.slow
def test_loop_diagnoses_of_real_windows_round_trip():
    """Issue 25: three sticky and three healthy plant_dev windows, and the ISDB loops."""
    import csv

    from service.loop_csv import read_loop_csv

    labels = require_file(SHARED_DATA / "plant_dev" / "labels.csv")
    with labels.open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    chosen = [r for r in rows if r["label"] == "stiction"][:3] \
        + [r for r in rows if r["label"] == "no_stiction"][:3]
    verdicts = []
    for row in chosen:
        data = read_loop_csv(labels.parent / f"{row['window']}.csv", ts=float(row["ts_s"]))
        d = diagnose_loop(ts=data.ts, op=data.op, pv=data.pv, sp=data.sp, t=data.t)
        assert_round_trip(d)
        verdicts.append(d.stiction.verdict)
    for row in isdb_labels():
        t, op, pv = load_isdb_loop(row["loop"])
        d = diagnose_loop(ts=float(row["ts_s"]), op=op, pv=pv, t=t)
        assert_round_trip(d)
        verdicts.append(d.stiction.verdict)
    assert "stiction" in verdicts and "no_stiction" in verdicts


def test_a_stored_loop_diagnosis_missing_a_field_is_refused_naming_it():
    fresh = run("flow-kano-S4-J2-ts1", process_type="self-regulating")[1].to_dict()
    stored = json.loads(json.dumps(fresh))
    del stored["stiction"]["methods"]["hammerstein"]["decision"]
    with pytest.raises(DataError, match=r"loop diagnosis\.stiction\.methods\.hammerstein: "
                                        r"the field 'decision' is missing"):
        LoopDiagnosis.from_dict(stored)
    stored = json.loads(json.dumps(fresh))
    del stored["quantification"]["process"]["K"]
    with pytest.raises(DataError, match=r"loop diagnosis\.quantification\.process: "
                                        r"the field 'K' is missing"):
        LoopDiagnosis.from_dict(stored)
    with pytest.raises(DataError, match=r"loop diagnosis\.stiction\.episodes\[0\]: expected"):
        LoopDiagnosis.from_dict({**fresh, "stiction": {**fresh["stiction"], "episodes": [1]}})
