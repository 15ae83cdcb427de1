"""Tests of analytics.stiction.area_ratio (Singhal and Salsbury 2005): the areas
of half cycles with a known peak position, the detector against closed-loop
simulations with a known valve, and the labelled ISDB loops."""

from __future__ import annotations

import numpy as np
import pytest

from analytics.stiction.area_ratio import AreaRatioDetector, half_cycle_areas
from tests.analytics.stiction.test_shape_rules import (
    INTEGRATING_STICTION,
    LINEAR_CASES,
    SELF_REGULATING_STICTION,
    isdb_tally,
    simulated_window,
    with_changes,
)

U = np.linspace(0.0, 1.0, 201)


@pytest.mark.parametrize("peak", [0.25, 0.5, 0.8])
def test_triangle_area_ratio_is_peak_over_remainder(peak: float) -> None:
    # Areas of the two straight flanks: peak / 2 and (1 - peak) / 2.
    half = np.minimum(U / peak, (1 - U) / (1 - peak))
    a1, a2 = half_cycle_areas(half[None, :])
    assert a1[0] / a2[0] == pytest.approx(peak / (1 - peak), rel=1e-9)


def test_half_sine_and_negative_half_cycles_are_symmetric() -> None:
    a1, a2 = half_cycle_areas(np.stack([np.sin(np.pi * U), -np.sin(np.pi * U)]))
    assert np.allclose(a1 / a2, 1.0)


def test_step_response_half_cycle_peaks_late() -> None:
    # First-order rise for 80 % of the half cycle, then a fast return: the
    # error of a loop whose valve is stuck (Singhal and Salsbury, Fig. 3).
    rise = 1 - np.exp(-U / 0.15)
    half = np.where(U < 0.8, rise, rise[160] * (1 - U) / 0.2)
    a1, a2 = half_cycle_areas(half[None, :])
    assert a1[0] / a2[0] > 4


@pytest.mark.parametrize("name", SELF_REGULATING_STICTION)
def test_detects_stiction_in_simulated_self_regulating_loops(name: str) -> None:
    evidence = AreaRatioDetector().detect(simulated_window(name))
    assert evidence.decision == "stiction", evidence.note
    assert evidence.index is not None and evidence.index >= 1.5


@pytest.mark.parametrize("name", LINEAR_CASES)
def test_rejects_linear_oscillations(name: str) -> None:
    evidence = AreaRatioDetector().detect(simulated_window(name))
    assert evidence.decision == "no_stiction", evidence.note
    assert evidence.index == pytest.approx(1.0, abs=0.1)


def test_reversed_asymmetry_also_counts_as_stiction() -> None:
    # Time-reversing the error swaps A1 and A2: R -> about 1/R, still far from 1.
    window = simulated_window("flow_pi_he")
    assert window.op is not None and window.pv is not None and window.sp is not None
    forward = AreaRatioDetector().detect(window)
    reverse = AreaRatioDetector().detect(
        with_changes(window, op=window.op[::-1], pv=window.pv[::-1], sp=window.sp[::-1])
    )
    assert reverse.decision == "stiction"
    assert forward.index is not None and reverse.index is not None
    assert reverse.index == pytest.approx(1 / forward.index, rel=0.1)


def test_without_set_point_the_pv_gives_the_same_ratio() -> None:
    window = simulated_window("fast_pi_kano")
    without_sp = AreaRatioDetector().detect(with_changes(window, sp=None))
    assert without_sp.index == pytest.approx(AreaRatioDetector().detect(window).index, rel=1e-6)


def test_unknown_process_type_decides_stiction_but_not_its_absence() -> None:
    detector = AreaRatioDetector()
    sticky = detector.detect(with_changes(simulated_window("flow_pi_he"), process_type=None))
    linear = detector.detect(with_changes(simulated_window("aggressive_tuning"),
                                          process_type=None))
    assert sticky.decision == "stiction"
    assert linear.decision == "undecided" and "integrating" in linear.note


@pytest.mark.parametrize("name", INTEGRATING_STICTION)
def test_integrating_processes_are_undecided(name: str) -> None:
    evidence = AreaRatioDetector().detect(simulated_window(name))
    assert evidence.decision == "undecided"
    assert "self-regulating processes only" in evidence.note


@pytest.mark.parametrize(
    ("changes", "reason"),
    [
        ({"period_s": None}, "does not oscillate"),
        ({"pv": None}, "no PV"),
        ({"period_s": 2000.0}, "cycles"),
    ],
)
def test_undecided_when_the_method_cannot_apply(changes: dict[str, object], reason: str) -> None:
    window = with_changes(simulated_window("flow_pi_he"), **changes)
    evidence = AreaRatioDetector().detect(window)
    assert evidence.decision == "undecided" and evidence.confidence == 0.0
    assert reason in evidence.note


def test_isdb_decisions() -> None:
    right, decided, evidence = isdb_tally(AreaRatioDetector())
    assert evidence["PAP7"].decision == "undecided"  # does not oscillate
    # Measured: 7 of 11 decided loops right; CHEM11, CHEM12 and PAP5 (stiction)
    # have symmetric error half cycles and PAP4 (no stiction) an asymmetric one.
    assert decided >= 10 and right >= 7
