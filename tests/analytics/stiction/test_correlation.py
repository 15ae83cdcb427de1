"""Tests of analytics.stiction.correlation (Horch 1999): the zero crossings of
the cross-correlation against sinusoids with a known phase, the detector
against closed-loop simulations with a known valve, and the labelled ISDB
loops."""

from __future__ import annotations

import numpy as np
import pytest

from analytics.stiction.correlation import CrossCorrelationDetector, ccf_zero_crossings
from tests.analytics.stiction.test_shape_rules import (
    INTEGRATING_STICTION,
    SELF_REGULATING_STICTION,
    isdb_tally,
    simulated_window,
    with_changes,
)

PERIOD = 100


@pytest.mark.parametrize("lag", [0.0, 5.0, 12.5, 20.0, 24.0])
def test_zero_crossings_give_the_phase_of_a_lagged_sinusoid(lag: float) -> None:
    # r_uy(tau) ~ cos(2 pi (tau - lag) / P): zeros at lag -+ P/4, so
    # tau_l = P/4 - lag, tau_r = P/4 + lag and the index is 4 lag / P.
    k = np.arange(4000)
    op = np.sin(2 * np.pi * k / PERIOD)
    pv = np.sin(2 * np.pi * (k - lag) / PERIOD)
    tau_l, tau_r = ccf_zero_crossings(op, pv, PERIOD)
    # Within 0.2 % of the period: the sum over a window of 40 cycles that ends
    # mid-cycle adds a small odd term.
    assert tau_l == pytest.approx(PERIOD / 4 - lag, abs=0.2)
    assert tau_r == pytest.approx(PERIOD / 4 + lag, abs=0.2)


def test_counter_phase_is_even_and_quarter_lag_is_odd() -> None:
    k = np.arange(3000)
    op = np.sin(2 * np.pi * k / 150)
    detector = CrossCorrelationDetector()
    for pv, decision, index in [(-op, "no_stiction", 0.0),
                                (np.sin(2 * np.pi * (k - 37.5) / 150), "stiction", 1.0)]:
        window = simulated_window("flow_pi_he")
        evidence = detector.detect(with_changes(window, ts=1.0, op=op, pv=pv, sp=None,
                                                period_s=150.0))
        assert evidence.decision == decision
        assert evidence.index == pytest.approx(index, abs=0.01)


@pytest.mark.parametrize("name", SELF_REGULATING_STICTION)
def test_detects_stiction_in_simulated_self_regulating_loops(name: str) -> None:
    evidence = CrossCorrelationDetector().detect(simulated_window(name))
    assert evidence.decision == "stiction", evidence.note
    assert evidence.index is not None and evidence.index >= 2 / 3


@pytest.mark.parametrize("name", ["fast_sine_disturbance", "aggressive_tuning"])
def test_rejects_tight_tuning_and_a_disturbance_near_the_bandwidth(name: str) -> None:
    evidence = CrossCorrelationDetector().detect(simulated_window(name))
    assert evidence.decision == "no_stiction", evidence.note
    assert evidence.index is not None and evidence.index <= 1 / 3


def test_slow_external_disturbance_is_not_called_even() -> None:
    # Horch's limitation: well below the loop bandwidth the integral action
    # makes OP lead PV by nearly 90 degrees, so the CCF of a linear loop looks
    # odd-ish.  The index (about 0.63) stays short of the stiction threshold.
    evidence = CrossCorrelationDetector().detect(simulated_window("slow_sine_disturbance"))
    assert evidence.decision == "undecided"
    assert evidence.index is not None and 1 / 3 < evidence.index < 2 / 3


@pytest.mark.parametrize("name", INTEGRATING_STICTION)
def test_integrating_processes_are_undecided(name: str) -> None:
    evidence = CrossCorrelationDetector().detect(simulated_window(name))
    assert evidence.decision == "undecided"
    assert "self-regulating processes only" in evidence.note


@pytest.mark.parametrize(
    ("changes", "reason"),
    [
        ({"process_type": None}, "process type unknown"),
        ({"period_s": None}, "does not oscillate"),
        ({"op": None}, "no OP"),
        ({"period_s": 2000.0}, "cycles"),
    ],
)
def test_undecided_when_the_method_cannot_apply(changes: dict[str, object], reason: str) -> None:
    window = with_changes(simulated_window("flow_pi_he"), **changes)
    evidence = CrossCorrelationDetector().detect(window)
    assert evidence.decision == "undecided" and evidence.confidence == 0.0
    assert reason in evidence.note


def test_isdb_decisions_are_mostly_right() -> None:
    right, decided, evidence = isdb_tally(CrossCorrelationDetector())
    assert evidence["PAP7"].decision == "undecided"  # does not oscillate
    # Measured: 10 of 11 decided loops right (CHEM2, a stiction loop, looks even).
    assert decided >= 10 and right >= decided - 1
