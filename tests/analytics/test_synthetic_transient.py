"""The transient library (analytics.synthetic_cases.transient_library): stick-jump
stiction without a regular limit cycle and its healthy look-alikes.

The checks are on the true valve position MV, which a detector never sees: a
sticky case must really hold while OP moves and then jump, a healthy one must
have a valve that follows OP.  The old limit-cycle library is pinned so that
the new optional fields of SyntheticCase cannot change it.
"""

import hashlib
import math

import numpy as np
import pytest

from analytics.oscillation import detect_loop_oscillation
from analytics.simulation import SimulationResult
from analytics.synthetic_cases import SyntheticCase, synthetic_library, transient_library
from analytics.valves import HeValve, IdealValve, KanoValve

LIBRARY = transient_library()
RESULTS = {case.name: case.simulate() for case in LIBRARY}
STICKY = [c for c in LIBRARY if c.label == "stiction"]
HEALTHY = [c for c in LIBRARY if c.label == "no_stiction"]
HEALTHY_CAUSES = {
    "setpoint_steps", "load_steps", "slow_disturbance", "noisy_flow", "compression",
    "quantisation", "saturation", "p_only",
}


def holds(mv: np.ndarray, op: np.ndarray, min_samples: int = 10) -> list[float]:
    """OP travel (mean of the last 5 samples minus the first 5) over every
    stretch of at least ``min_samples`` samples in which MV does not move."""
    travel, start = [], 0
    for k in range(1, mv.size + 1):
        if k == mv.size or mv[k] != mv[k - 1]:
            if k - start >= min_samples:
                travel.append(abs(op[k - 5 : k].mean() - op[start : start + 5].mean()))
            start = k
    return travel


def test_library_size_names_and_labels():
    names = [c.name for c in LIBRARY]
    assert 30 <= len(LIBRARY) <= 45
    assert len(set(names)) == len(names)
    assert not set(names) & {c.name for c in synthetic_library(100)}
    assert len(STICKY) >= 15 and len(HEALTHY) >= 15
    assert {c.cause for c in STICKY} == {"stick_jump"}
    assert {c.cause for c in HEALTHY} == HEALTHY_CAUSES
    for case in LIBRARY:
        assert case.samples == 2000
        assert (case.process_type == "integrating") == case.process.is_integrating, case.name


@pytest.mark.parametrize("case", STICKY, ids=lambda c: c.name)
def test_sticky_case_ground_truth(case: SyntheticCase):
    assert case.S is not None and case.J is not None
    assert 0.5 <= case.S <= 3.0 and 0.0 <= case.J <= case.S / 2
    assert isinstance(case.valve, HeValve | KanoValve)
    assert math.isclose(case.valve.S, case.S) and math.isclose(case.valve.J, case.J)
    assert case.setpoint or any(d.kind == "step" for d in case.disturbances)  # events


@pytest.mark.parametrize("case", STICKY, ids=lambda c: c.name)
def test_sticky_valve_holds_while_op_moves_then_jumps(case: SyntheticCase):
    assert case.S is not None and case.J is not None
    res = RESULTS[case.name]
    op, mv = res.op[0], res.mv[0]
    steps = np.abs(np.diff(mv))
    assert np.mean(steps == 0) > 0.8  # stuck most of the time
    assert sum(t > case.S / 2 for t in holds(mv, op)) >= 2  # OP travels while MV holds
    if case.J > 0:
        assert np.sum(steps >= case.J / 2) >= 2  # slips are jumps of about J
    else:
        assert np.sum(steps > 0) >= 2  # a pure deadband: the valve moves, without a jump


@pytest.mark.parametrize("case", STICKY, ids=lambda c: c.name)
def test_sticky_cases_are_not_regular_limit_cycles(case: SyntheticCase):
    res = RESULTS[case.name]
    assert not detect_loop_oscillation(res.op[0], res.pv[0], case.ts).detected


@pytest.mark.parametrize("case", HEALTHY, ids=lambda c: c.name)
def test_healthy_valve_follows_op(case: SyntheticCase):
    assert isinstance(case.valve, IdealValve) and case.S is None and case.J is None
    res = RESULTS[case.name]
    op, mv = res.op[0], res.mv[0]
    low, high = case.controller.op_limits
    assert np.all((mv >= low) & (mv <= high))
    if case.op_compression is None:
        np.testing.assert_array_equal(mv, op)
    else:  # the recorded OP is compressed, the valve follows the true OP
        assert np.max(np.abs(mv - op)) <= case.op_compression
    if case.cause == "saturation":
        assert np.mean(op == high) > 0.05  # OP at its limit for a stretch
        assert np.mean(op == high) < 0.5
    if case.cause == "p_only":
        assert case.controller.ki == 0.0


def test_quantised_pv_lies_on_the_lattice():
    quantised = [c for c in HEALTHY if c.pv_quantum is not None]
    assert len(quantised) >= 2
    for case in quantised:
        assert case.pv_quantum is not None
        steps = RESULTS[case.name].pv[0] / case.pv_quantum
        np.testing.assert_allclose(steps, np.round(steps), atol=1e-9)
        assert np.mean(np.diff(steps) == 0) > 0.2


def test_compressed_signals_are_held_until_they_move_beyond_the_deadband():
    compressed = [c for c in HEALTHY if c.pv_compression is not None]
    assert len(compressed) >= 2 and any(c.op_compression is not None for c in compressed)
    for case in compressed:
        res = RESULTS[case.name]
        for signal, deadband in ((res.pv[0], case.pv_compression),
                                 (res.op[0], case.op_compression)):
            if deadband is None:
                continue
            change = np.abs(np.diff(signal))
            assert np.all((change == 0) | (change > deadband)), case.name
            assert np.mean(change == 0) > 0.5, case.name


def test_library_is_reproducible():
    again = transient_library()
    assert [c.name for c in again] == [c.name for c in LIBRARY]
    for case in again:
        first, second = RESULTS[case.name], case.simulate()
        for field in ("t", "sp", "op", "mv", "pv"):
            np.testing.assert_array_equal(getattr(first, field), getattr(second, field))


def test_events_fall_inside_the_window_at_other_lengths():
    for case in transient_library(600):
        res: SimulationResult = case.simulate()
        assert res.pv.shape == (1, 600)
        if case.setpoint:
            assert np.ptp(res.sp[0]) > 0, case.name


def test_old_library_is_unchanged():
    """Checksums of synthetic_library() computed before the transient fields were added
    (the first case and its sums recorded again when the simulation's matrix exponential
    became the same on every CPU, :func:`analytics.lti.exact_expm`)."""
    cases = synthetic_library()
    assert len(cases) == 72
    assert all(c.setpoint is None and c.pv_quantum is None and c.pv_compression is None
               and c.op_compression is None for c in cases)
    first = cases[0]
    assert first.name == "flow-he-S2-J1-ts0.5"
    pv = first.simulate().pv[0]
    assert (hashlib.sha256(np.round(pv, 6).tobytes()).hexdigest()
            == "a3c4bfc054df303d489d64cb04c2b3e80e1c5401d6acf9ac5054396fd6519ed4")
    expected = {
        "flow-he-S2-J1-ts0.5": (203967.61100776863, 10401793.477328155),
        "temp-he-S2-J1-ts2": (204009.8979804854, 10405291.856213458),
        "level-kano-S8-J4-ts1": (204066.32460354868, 10413658.703176122),
    }
    by_name = {c.name: c for c in cases}
    for name, (total, squares) in expected.items():
        pv = by_name[name].simulate().pv[0]
        assert float(pv.sum()) == pytest.approx(total, rel=1e-12, abs=0)
        assert float((pv**2).sum()) == pytest.approx(squares, rel=1e-12, abs=0)
