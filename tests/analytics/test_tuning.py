"""Tuning advice (analytics.tuning) checked against the frequency response computed
from ``TransferFunction.frequency_response``, classic analytic limits, the thesis
(chapter 5: Eqs. 5.16-5.45, Tables 5.9 and 5.11, section 5.5), the exact
describing-function solver of analytics.limit_cycle and closed-loop simulation.

Where the thesis and the independent checks disagree, the test pins the
disagreement and the evidence (a simulation) that settles it.
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from numpy.typing import NDArray

from analytics.describing import choudhury_df
from analytics.diagnosis import diagnose_loop
from analytics.errors import ModelSpecError
from analytics.limit_cycle import predict_limit_cycles, simulate_limit_cycle
from analytics.lti import TransferFunction
from analytics.scenarios import chapter4, level_loop, temperature_loop
from analytics.simulation import ClosedLoopModel, Disturbance, Loop, PIDController
from analytics.synthetic_cases import synthetic_library
from analytics.tuning import (
    MAX_LOAD_ERROR_RATIO,
    TABLE_5_11,
    Detuning,
    FirstOrderProcess,
    OscillationEffect,
    SafeTuningMap,
    Tuning,
    advise,
    analyse_single_loop,
    cycle_origin,
    detune,
    excited_model,
    inverse_gain,
    load_error,
    safe_tuning_map,
    table_5_11_rule,
)
from analytics.valves import ChoudhuryValve, HeValve, IdealValve, KanoValve, ValveModel

TEMPERATURE = TransferFunction.fopdt(0.4346, 27.58, 6.0)  # thesis Eq. 5.42
FOPDT = TransferFunction.fopdt(1.0, 10.0, 5.0)
INTEGRATING = TransferFunction.integrating(0.05, 3.0)
VALVE = ChoudhuryValve(4.0, 2.0)  # thesis Eq. 5.41


def loop_response(
    process: TransferFunction, kc: float, ti: float, omega: NDArray[np.float64]
) -> NDArray[np.complex128]:
    """``Kc (1 + 1/(j w Ti)) G(jw)`` from the transfer function itself."""
    return np.asarray(kc * (1 - 1j / (omega * ti)) * process.frequency_response(omega))


def settles(
    process: TransferFunction, controller: PIDController, *, dt: float, duration: float
) -> bool:
    """A healthy loop after a setpoint step: True if it comes to rest (with an offset
    under P control), False if it oscillates or grows."""
    unlimited = dataclasses.replace(controller, op_limits=(-1e12, 1e12))
    model = ClosedLoopModel(
        process, (Loop(unlimited, IdealValve(), setpoint=[(1.0, 51.0)]),), dt, duration
    )
    pv = model.run().pv[0]
    tail = pv[-pv.size // 10 :]
    return bool(np.all(np.isfinite(pv)) and np.ptp(tail) < 0.01)


# ----------------------------------------------------------------------------- chapter 5 forms
CLASSES = {
    "SR, P": (FOPDT, 1.3, math.inf),
    "SR, PI": (FOPDT, 1.3, 8.0),
    "SR, PI, no delay": (TransferFunction.fopdt(1.0, 10.0), 2.0, 4.0),
    "Int, P": (INTEGRATING, 2.0, math.inf),
    "Int, PI": (INTEGRATING, 2.0, 30.0),
    "Int, PI, no delay": (TransferFunction.integrating(0.05), 2.0, 30.0),
}


@pytest.mark.parametrize("case", sorted(CLASSES))
def test_closed_forms_are_the_frequency_response(case: str) -> None:
    """Eqs. 5.12-5.15, 5.21-5.23, 5.32, 5.34-5.36 against G(jw) Gc(jw)."""
    process, kc, ti = CLASSES[case]
    omega = np.geomspace(1e-4, 10.0, 500)
    np.testing.assert_allclose(
        FirstOrderProcess.of(process).open_loop_response(kc, ti, omega),
        loop_response(process, kc, ti, omega),
        rtol=1e-12,
    )


CROSSINGS = {
    # process, Kc, Ti; Ti > theta + tau gives F on the negative imaginary axis
    "SR, P": (FOPDT, 1.3, math.inf),
    "SR, PI, Ti > theta + tau": (FOPDT, 1.3, 40.0),
    "SR, PI, Ti < theta + tau": (FOPDT, 1.3, 8.0),
    "Int, P": (INTEGRATING, 2.0, math.inf),
    "Int, PI, Ti > theta": (INTEGRATING, 2.0, 30.0),
    "Int, PI, Ti < theta": (INTEGRATING, 2.0, 1.5),
}


@pytest.mark.parametrize("case", sorted(CROSSINGS))
def test_f_and_h_are_the_first_axis_crossings(case: str) -> None:
    """w* and w** put G Gc on the imaginary and the real axis, and no crossing
    comes earlier (a dense scan of the frequency response)."""
    process, kc, ti = CROSSINGS[case]
    analysis = analyse_single_loop(process, PIDController.ideal(kc, ti), VALVE)
    w_f, w_h = analysis.omega_f, analysis.omega_h
    assert w_f is not None and w_h is not None
    at_f, at_h = loop_response(process, kc, ti, np.array([w_f, w_h]))
    assert abs(at_f.real) < 1e-9 * abs(at_f) and at_f.imag == pytest.approx(analysis.f_imag)
    assert abs(at_h.imag) < 1e-9 * abs(at_h) and at_h.real == pytest.approx(analysis.h_real)
    for first, part in ((w_f, "real"), (w_h, "imag")):
        scan = loop_response(process, kc, ti, np.linspace(1e-4 * first, first * (1 - 1e-6), 20001))
        values = getattr(scan, part)
        assert np.all(np.sign(values) == np.sign(values[0]))


def test_crossing_equations_as_corrected() -> None:
    """The printed fixed-point equations hold at the roots, with the corrections of
    the module notes: 5.18 and 5.40 as printed, 5.19, 5.28 and 5.39 with pi/2 or pi
    added; the printed F_imag and H_real of Eqs. 5.16, 5.17, 5.25, 5.26 agree."""
    K, tau, theta = 1.0, 10.0, 5.0
    sr_p = analyse_single_loop(FOPDT, PIDController.ideal(1.3), VALVE)
    w1, w2 = sr_p.omega_f, sr_p.omega_h
    assert w1 is not None and w2 is not None
    assert theta * w1 == pytest.approx(math.atan(1 / (tau * w1)))  # Eq. 5.18
    assert theta * w2 == pytest.approx(math.pi - math.atan(tau * w2))  # Eq. 5.19 + pi
    f_imag = -1.3 / (1 + (tau * w1) ** 2) * (math.sin(theta * w1) + tau * w1 * math.cos(theta * w1))
    h_real = 1.3 / (1 + (tau * w2) ** 2) * (math.cos(theta * w2) - tau * w2 * math.sin(theta * w2))
    assert sr_p.f_imag == pytest.approx(f_imag) and sr_p.h_real == pytest.approx(h_real)

    ti = 40.0
    sr_pi = analyse_single_loop(FOPDT, PIDController.ideal(1.3, ti), VALVE)
    w1, w2 = sr_pi.omega_f, sr_pi.omega_h
    assert w1 is not None and w2 is not None

    def alpha_beta(w: float) -> float:
        return math.atan(ti * w) - math.atan(tau * w)  # Eqs. 5.29-5.30

    assert theta * w1 == pytest.approx(alpha_beta(w1))  # Eq. 5.27
    assert theta * w2 == pytest.approx(alpha_beta(w2) + math.pi / 2)  # Eq. 5.28 corrected
    c1, s1, c2, s2 = (
        math.cos(theta * w1),
        math.sin(theta * w1),
        math.cos(theta * w2),
        math.sin(theta * w2),
    )
    eq_5_25 = (
        -K
        * 1.3
        / ((1 + tau**2 * w1**2) * ti * w1)
        * (c1 * (1 + tau * ti * w1**2) + s1 * (ti * w1 - tau * w1))
    )
    eq_5_26 = (
        K
        * 1.3
        / ((1 + tau**2 * w2**2) * ti * w2)
        * (c2 * (ti * w2 - tau * w2) - s2 * (1 + tau * ti * w2**2))
    )
    assert sr_pi.f_imag == pytest.approx(eq_5_25) and sr_pi.h_real == pytest.approx(eq_5_26)

    ti = 30.0
    int_pi = analyse_single_loop(INTEGRATING, PIDController.ideal(2.0, ti), VALVE)
    w1, w2 = int_pi.omega_f, int_pi.omega_h
    assert w1 is not None and w2 is not None
    assert 3.0 * w2 == pytest.approx(math.atan(ti * w2))  # Eq. 5.40
    assert 3.0 * w1 == pytest.approx(math.atan(ti * w1) + math.pi / 2)  # Eq. 5.39 corrected


@pytest.mark.parametrize("factor", [0.9, 1.1])
def test_integrating_p_control_ultimate_gain(factor: float) -> None:
    """K e^-theta s/s under P control: w** = pi/(2 theta), H_real = -2 K Kc theta/pi,
    so the loop is stable below K Kc theta = pi/2 (the classic ultimate gain). The
    chapter's test H_real > -1, the Nyquist count and a simulation agree."""
    kc = factor * math.pi / (2 * 0.05 * 3.0)
    analysis = analyse_single_loop(INTEGRATING, PIDController.ideal(kc), VALVE)
    assert analysis.omega_h == pytest.approx(math.pi / 6.0)
    assert analysis.h_real == pytest.approx(-2 * 0.05 * kc * 3.0 / math.pi)
    assert analysis.low_frequency_real == pytest.approx(-0.05 * kc * 3.0)  # Table 5.7
    stable = factor < 1
    assert analysis.linear_stable is stable and analysis.thesis_linear_stable is stable
    assert settles(INTEGRATING, PIDController.ideal(kc), dt=0.01, duration=600.0) is stable


def test_temperature_loop_section_5_5_1() -> None:
    """Eqs. 5.44-5.45: the loop cycles under Kc = 10, Ti = 10 s (Ti < theta + tau =
    33.58 s, F on the positive imaginary axis, Fig. 5.16); under Kc = 2, Ti = 100 s
    F_imag > -pi S/(4J) = -1.57 and no cycle is predicted (Fig. 5.18)."""
    before = analyse_single_loop(TEMPERATURE, PIDController.ideal(10.0, 10.0), VALVE)
    after = analyse_single_loop(TEMPERATURE, PIDController.ideal(2.0, 100.0), VALVE)
    assert before.process.theta + (before.process.tau or 0.0) == pytest.approx(33.58)
    assert before.band_edge_imag == pytest.approx(-1.5708, abs=1e-4)
    assert before.f_imag is not None and before.f_imag > 0
    assert before.thesis_oscillation and before.df_oscillation
    assert before.low_frequency_real == pytest.approx(0.4346 * 10 * (1 - 33.58 / 10))  # 5.24
    assert after.f_imag is not None and -1.5708 < after.f_imag < 0
    assert after.thesis_oscillation is False and after.df_oscillation is False
    assert before.rule.actions == ("raise Ti", "lower Kc")


# ----------------------------------------------------------------------------- Table 5.11
TABLE_CASES = {
    # name: process, Ti values (None: P), valve; where the chapter's condition decides
    "SR & P, dead time": (FOPDT, None, VALVE),
    # Ti = theta + tau = 15 s is the degenerate border of Figs. 5.5-5.6 (d = 0)
    "SR & PI, dead time": (FOPDT, [2.0, 6.0, 12.0, 40.0, 100.0], VALVE),
    "SR & PI, no dead time": (TransferFunction.fopdt(1.0, 10.0), [2.0, 5.0, 20.0, 80.0], VALVE),
    "Int. & P, dead time": (INTEGRATING, None, VALVE),
    "Int. & PI, dead time": (INTEGRATING, [5.0, 20.0, 100.0, 400.0], VALVE),
    "Int. & PI, no dead time": (TransferFunction.integrating(0.05), [5.0, 50.0, 400.0], VALVE),
    "Int. & P, dead time, deadband": (INTEGRATING, None, ChoudhuryValve(4.0, 0.0)),
}


@pytest.mark.parametrize("case", sorted(TABLE_CASES))
def test_table_5_11_conditions_match_the_describing_function(case: str) -> None:
    """Where the chapter's conditions decide (Eq. 5.20, Fig. 5.6, sections 5.4.1-5.4.2)
    they agree with the exact describing-function solution on every stable tuning
    of a grid; "maybe" rows (SR & PI without delay, Ti < tau) are left open."""
    process, tis, valve = TABLE_CASES[case]
    decided = 0
    for kc in np.geomspace(0.1, 15.0, 9):
        for ti in tis or [math.inf]:
            analysis = analyse_single_loop(process, PIDController.ideal(kc, ti), valve)
            if not analysis.linear_stable or analysis.thesis_oscillation is None:
                continue
            decided += 1
            assert analysis.thesis_oscillation == analysis.df_oscillation, (kc, ti)
    assert decided >= 5


def test_self_regulating_pi_without_delay_cycles_only_if_ti_below_tau() -> None:
    """Table 5.11 prints "maybe, if tau_I > tau"; section 5.3.1 (Eq. 5.14) puts the
    curve in the third quadrant only for Ti < tau. The exact solution: cycles for
    some gains with Ti < tau, never with Ti > tau; the simulation agrees."""
    process = TransferFunction.fopdt(1.0, 10.0)
    below = safe_tuning_map(process, VALVE, np.geomspace(0.5, 50, 12), [2.0, 5.0])
    above = safe_tuning_map(process, VALVE, np.geomspace(0.5, 50, 12), [12.0, 50.0])
    assert below.linear_stable.all() and above.linear_stable.all()
    assert not below.limit_cycle_free.all() and above.limit_cycle_free.all()
    assert table_5_11_rule("self-regulating", False, "PI").stiction_oscillation.endswith("Ti < tau")
    i = int(np.argmax(~below.limit_cycle_free[:, 0]))
    model = ClosedLoopModel(
        process,
        (Loop(PIDController.ideal(float(below.kc[i]), 2.0), VALVE, setpoint=[(1.0, 52.0)]),),
        dt=0.02,
        duration=800.0,
    )
    simulated = simulate_limit_cycle(model)
    assert simulated.oscillating
    assert known_period(simulated.period_s) == pytest.approx(
        2 * math.pi / below.omega[i, 0], rel=0.15
    )


def known_period(value: float | None) -> float:
    assert value is not None
    return value


def test_table_5_11_integrating_p_without_delay_does_not_cycle() -> None:
    """Table 5.11 says "yes"; the only solution is the band edge of Eq. 5.33, which
    is not a stable cycle, and the simulation settles (see test_limit_cycle)."""
    process = TransferFunction.integrating(0.05)
    analysis = analyse_single_loop(process, PIDController.ideal(2.0), VALVE)
    assert analysis.thesis_oscillation is True and analysis.df_oscillation is False
    model = ClosedLoopModel(
        process, (Loop(PIDController.ideal(2.0), VALVE, setpoint=[(1.0, 60.0)]),), 0.5, 20000.0
    )
    assert not simulate_limit_cycle(model).oscillating


def test_deadband_makes_self_regulating_pi_loops_cycle() -> None:
    """Table 5.11's deadband column says "no" for SR & PI; with Ti < theta + tau the
    deadband curve meets G Gc (Fig. 5.6 geometry) and the simulation cycles."""
    valve = ChoudhuryValve(4.0, 0.0)
    analysis = analyse_single_loop(FOPDT, PIDController.ideal(1.2, 4.0), valve)
    assert analysis.rule.deadband_oscillation == "no"
    assert analysis.df_oscillation
    model = ClosedLoopModel(
        FOPDT, (Loop(PIDController.ideal(1.2, 4.0), valve, setpoint=[(1.0, 52.0)]),), 0.05, 4000.0
    )
    assert simulate_limit_cycle(model).oscillating


def test_integrating_pi_with_ti_below_theta_is_unstable() -> None:
    """Table 5.11's option (1) for Int. & PI with dead time, Ti < theta: the chapter's
    test H_real > -1 passes, but the loop is unstable for every gain (a pair of
    right-half-plane roots, Re s ~ K Kc (theta/Ti - 1)/2 for small gains). The
    map and a simulation of the healthy loop agree."""
    tuning_map = safe_tuning_map(INTEGRATING, VALVE, np.geomspace(0.05, 20.0, 8), [0.5, 1.5, 2.5])
    assert not tuning_map.linear_stable.any()
    analysis = analyse_single_loop(INTEGRATING, PIDController.ideal(0.5, 1.5), VALVE)
    assert analysis.thesis_linear_stable and not analysis.linear_stable
    assert not settles(INTEGRATING, PIDController.ideal(0.5, 1.5), dt=0.01, duration=600.0)
    assert settles(INTEGRATING, PIDController.ideal(0.5, 30.0), dt=0.01, duration=1500.0)


def test_table_5_11_has_every_class_once() -> None:
    keys = {(r.process_type, r.dead_time, r.control) for r in TABLE_5_11}
    assert len(keys) == len(TABLE_5_11) == 8
    with pytest.raises(ModelSpecError):
        table_5_11_rule("self-regulating", True, "PID")  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- trends
def test_level_loop_table_5_9_trend() -> None:
    """Section 5.5.2, Table 5.9: raising Ti (10, 20, 100 s) at Kc = 2 moves the crossing
    to lower frequency and amplitude (Fig. 5.23); the simulation confirms (Fig. 5.24)."""
    process, valve = TransferFunction.fopdt(0.5717, 544.5), ChoudhuryValve(5.0, 1.4)
    predicted, simulated = [], []
    for ti in (10.0, 20.0, 100.0):
        (cycle,) = predict_limit_cycles(process, PIDController.ideal(2.0, ti), valve).limit_cycles
        predicted.append((cycle.omega, cycle.amplitudes[0]))
        loop = Loop(PIDController.ideal(2.0, ti), valve, setpoint=[(10.0, 55.0)])
        sim = simulate_limit_cycle(ClosedLoopModel(process, (loop,), 1.0, 60000.0))
        simulated.append((2 * math.pi / known_period(sim.period_s), sim.amplitudes[0]))
        assert 2 * math.pi / known_period(sim.period_s) == pytest.approx(cycle.omega, rel=0.1)
    assert [w for w, _ in predicted] == sorted((w for w, _ in predicted), reverse=True)
    assert [a for _, a in predicted] == sorted((a for _, a in predicted), reverse=True)
    assert [w for w, _ in simulated] == sorted((w for w, _ in simulated), reverse=True)


def test_industrial_level_loop_section_5_5_3() -> None:
    """Section 5.5.3: G = 0.0092 e^-0.08s/s (minutes), He valve fs = 3.2, fd = 0.3;
    Kc 1.0 -> 0.6 and Ti 1.5 -> 15 min "significantly reduced the frequency with
    some increase of the magnitude". The PV amplitude |G(jw) N(A) A| rises while
    the frequency falls, predicted and simulated."""
    process, valve = TransferFunction.integrating(0.0092, 0.08), HeValve(3.2, 0.3)
    results = []
    for kc, ti in ((1.0, 1.5), (0.6, 15.0)):
        prediction = predict_limit_cycles(
            process, PIDController.ideal(kc, ti), valve, describing="equivalent"
        )
        (cycle,) = prediction.stable_cycles
        amplitude = cycle.amplitudes[0]
        assert amplitude is not None
        gain = abs(complex(process.frequency_response(cycle.omega)))
        pv_df = gain * abs(complex(choudhury_df(amplitude, valve.S, valve.J))) * amplitude
        controller = PIDController.ideal(kc, ti, op_limits=(-1e9, 1e9))
        model = ClosedLoopModel(
            process, (Loop(controller, valve, setpoint=[(1.0, 51.0)]),), 0.01, 20000
        )
        pv = model.run().pv[0, -1_000_000:]
        results.append((cycle.omega, pv_df, np.ptp(pv) / 2))
    (w_before, pv_before, sim_before), (w_after, pv_after, sim_after) = results
    assert w_after < w_before / 3
    assert pv_after > pv_before and sim_after > sim_before


# ----------------------------------------------------------------------------- the map
MAP_CASES: dict[
    str, tuple[TransferFunction, ValveModel, list[float], list[float] | None, float]
] = {
    "temperature, Choudhury": (
        TEMPERATURE,
        VALVE,
        np.geomspace(0.5, 20, 7).tolist(),
        np.geomspace(2, 500, 7).tolist(),
        0.5,
    ),
    "level, Kano": (
        TransferFunction.integrating(0.02, 3.0),
        KanoValve(3, 1),
        np.geomspace(0.2, 40, 7).tolist(),
        np.geomspace(1, 1000, 7).tolist(),
        0.0,
    ),
    "chapter 4, He (numerical DF)": (
        TransferFunction.fopdt(0.66, 6.7, 2.6),
        HeValve(3.0, 2.0),
        np.geomspace(0.01, 0.2, 6).tolist(),
        np.geomspace(0.25, 11, 6).tolist(),
        0.5,
    ),
    "FOPDT, P control": (FOPDT, ChoudhuryValve(4, 0.5), np.geomspace(0.1, 5, 12).tolist(), None, 0),
}


@pytest.mark.parametrize("case", sorted(MAP_CASES))
def test_map_matches_the_exact_solver(case: str) -> None:
    """Every grid point: the Nyquist count and the existence of a stable cycle agree
    with predict_limit_cycles; the cycle's frequency and amplitude within 2 % and
    5 % for the analytic (Choudhury/Kano) describing function."""
    process, valve, kc, ti, hold = MAP_CASES[case]
    tuning_map = safe_tuning_map(process, valve, kc, ti, hold_delay=hold)
    assert 0 < tuning_map.linear_stable.sum() < tuning_map.linear_stable.size or ti is None
    for i, k in enumerate(kc):
        for j, t in enumerate(ti or [math.inf]):
            exact = predict_limit_cycles(process, PIDController.ideal(k, t), valve, hold_delay=hold)
            assert exact.linear_stable == tuning_map.linear_stable[i, j], (k, t)
            if not exact.linear_stable:
                continue
            assert exact.oscillates != tuning_map.limit_cycle_free[i, j], (k, t)
            if exact.oscillates and isinstance(valve, ChoudhuryValve):
                cycle = max(exact.stable_cycles, key=lambda c: c.amplitudes[0] or 0.0)
                assert tuning_map.omega[i, j] == pytest.approx(cycle.omega, rel=0.02)
                assert tuning_map.amplitude[i, j] == pytest.approx(cycle.amplitudes[0], rel=0.05)


def test_map_stability_boundary_is_the_ultimate_gain() -> None:
    """P control of the FOPDT: stable below Ku = sqrt(1 + tau^2 w180^2)/K with
    theta w180 + atan(tau w180) = pi; the simulation agrees on both sides."""
    w180 = float(
        next(w for w in np.linspace(0.01, 1.0, 100001) if 5 * w + math.atan(10 * w) >= math.pi)
    )
    ku = math.sqrt(1 + (10 * w180) ** 2)
    tuning_map = safe_tuning_map(FOPDT, VALVE, [0.97 * ku, 1.03 * ku])
    assert tuning_map.linear_stable[:, 0].tolist() == [True, False]
    assert settles(FOPDT, PIDController.ideal(0.9 * ku), dt=0.01, duration=3000.0)
    assert not settles(FOPDT, PIDController.ideal(1.1 * ku), dt=0.01, duration=3000.0)


def test_map_figure_5_17_and_its_json() -> None:
    tuning_map = safe_tuning_map(TEMPERATURE, VALVE, [2.0, 10.0], [10.0, 100.0])
    assert tuning_map.safe.tolist() == [[False, True], [False, False]]
    assert np.all(tuning_map.travel_rate[~tuning_map.safe] > 0)
    data = json.loads(json.dumps(tuning_map.to_dict(), allow_nan=False))
    assert data["Kc"] == [2.0, 10.0] and data["linear_stable"] == [[True, True], [True, True]]
    assert data["omega"][0][1] is None  # no cycle at the safe point


def test_map_refuses_what_it_cannot_map() -> None:
    with pytest.raises(ModelSpecError, match="healthy"):
        safe_tuning_map(FOPDT, IdealValve(), [1.0])
    with pytest.raises(ModelSpecError, match="positive feedback"):
        safe_tuning_map(TransferFunction.fopdt(-1.0, 10.0, 5.0), VALVE, [1.0])
    with pytest.raises(ModelSpecError, match="open-loop stable"):
        safe_tuning_map(TransferFunction((1.0,), (10.0, -1.0)), VALVE, [1.0])
    with pytest.raises(ModelSpecError, match="Kc"):
        safe_tuning_map(FOPDT, VALVE, [0.0, 1.0])
    with pytest.raises(ModelSpecError, match="Ti"):
        safe_tuning_map(FOPDT, VALVE, [1.0], [-5.0])
    with pytest.raises(ModelSpecError, match="chapter 5"):
        FirstOrderProcess.of(TransferFunction.second_order(1.0, 5.0, 2.0))


def test_direct_action_mirrors_reverse_action() -> None:
    positive = safe_tuning_map(FOPDT, VALVE, [0.5, 1.5], [5.0, 40.0])
    negative = safe_tuning_map(
        TransferFunction.fopdt(-1.0, 10.0, 5.0), VALVE, [0.5, 1.5], [5.0, 40.0], action="direct"
    )
    np.testing.assert_array_equal(positive.linear_stable, negative.linear_stable)
    np.testing.assert_array_equal(positive.limit_cycle_free, negative.limit_cycle_free)


# ----------------------------------------------------------------------------- advice
@pytest.fixture(scope="module")
def temperature_advice():
    return advise(temperature_loop())


@pytest.fixture(scope="module")
def unbounded_temperature_advice():
    return advise(temperature_loop(), max_load_error_ratio=math.inf)


def test_temperature_advice_is_verified(temperature_advice) -> None:
    """Every offered retune cuts the simulated valve travel of the current cycle
    (35 s, thesis Fig. 5.15) by at least 5 % and keeps the error a load leaves within
    the bound."""
    advice = temperature_advice
    assert advice.current_simulated.oscillating
    assert known_period(advice.current_simulated.period_s) == pytest.approx(35.0, rel=0.01)
    assert advice.recommendations
    for recommendation in (*advice.recommendations, *advice.rejected):
        assert recommendation.load_error_ratio is not None
        assert recommendation.load_error_ratio <= MAX_LOAD_ERROR_RATIO * (1 + 1e-9)
    for recommendation in advice.recommendations:
        assert recommendation.outcome in ("removed", "reduced")
        assert recommendation.simulated.travel_rate < 0.95 * advice.current_simulated.travel_rate


@pytest.mark.parametrize("process", [TEMPERATURE, FOPDT, INTEGRATING], ids=str)
@pytest.mark.parametrize(("kc", "ti"), [(1.0, 40.0), (0.5, 100.0), (0.8, math.inf)])
def test_load_error_is_what_a_simulated_load_step_leaves(process, kc, ti) -> None:
    """load_error against the linear loop simulated after a unit load step at the valve:
    its integrated error under PI (the final-value theorem's Ti / Kc), its offset under
    P; the tunings are checked stable first."""
    if process is INTEGRATING and math.isinf(ti):
        kc /= 10  # a P-controlled integrator with this dead time needs a smaller gain
    controller = PIDController.ideal(kc, ti)
    assert settles(process, controller, dt=0.05, duration=6000.0)
    model = ClosedLoopModel(process, (Loop(
        controller, IdealValve(), setpoint=50.0,
        disturbances=(Disturbance("step", 1.0, at="input", time=50.0),)),), 0.05, 6000.0)
    run = model.run()
    error = run.sp[0] - run.pv[0]
    expected = float(load_error(kc, ti, inverse_gain(process)))
    if math.isinf(ti):
        assert -float(np.mean(error[-2000:])) == pytest.approx(expected, rel=0.01)
    else:
        assert -float(np.sum(error) * model.dt) == pytest.approx(expected, rel=0.01)


def test_advice_does_not_trade_the_cycle_for_a_loop_that_hardly_controls(
        temperature_advice, unbounded_temperature_advice) -> None:
    """Without the bound the search goes to the edges of its box: a tenth of the gain or
    ten times the integral time, ten times the error a load leaves.  With it, every
    candidate stays within three times, and the notes name the cycle-free tuning that
    lies beyond."""
    unbounded = unbounded_temperature_advice
    assert max(r.load_error_ratio or 0.0 for r in unbounded.recommendations) >= 9.9
    assert unbounded.to_dict()["max_load_error_ratio"] is None
    assert temperature_advice.to_dict()["max_load_error_ratio"] == MAX_LOAD_ERROR_RATIO
    assert any("the map predicts no cycle at" in note and "times the current error after a "
               "load step" in note for note in temperature_advice.notes)
    with pytest.raises(ModelSpecError, match="max_load_error_ratio must be >= 1"):
        advise(temperature_loop(), max_load_error_ratio=0.5)


def test_the_thesis_cycle_free_tuning_without_the_bound(unbounded_temperature_advice) -> None:
    """Searched without a bound on the load error, the first offer is the map's cycle-free
    pick, safe by the thesis's own conditions (Eqs. 5.44-5.45) and robust (Ms <= 2)."""
    advice = unbounded_temperature_advice
    best = advice.recommendations[0]
    assert not best.predicted.oscillating and best.source.startswith("safe-tuning map")
    assert best.max_sensitivity is not None and best.max_sensitivity <= 2.0
    (tuning,) = best.tunings
    check = analyse_single_loop(
        TEMPERATURE, tuning.apply(PIDController.ideal(1.0, 1.0)), VALVE, hold_delay=0.5
    )
    assert tuning.ti > check.process.theta + 27.58  # Eq. 5.44
    assert check.f_imag is not None and check.f_imag > -math.pi * 4 / 8  # Eq. 5.45
    # its simulated cycle is the slow stick-slip the describing function cannot see
    assert known_period(best.simulated.period_s) > 3 * 35.0


def test_advice_json(temperature_advice) -> None:
    data = json.loads(json.dumps(temperature_advice.to_dict(), allow_nan=False))
    assert data["loops"] == ["TIC"]
    assert data["analysis"]["rule"]["dynamics"] == "SR & PI, dead time"
    assert set(data["recommendations"][0]) >= {"tunings", "predicted", "simulated", "outcome"}
    assert data["maps"]["TIC"]["Kc"][0] == pytest.approx(1.0)  # 0.1 x the current Kc


def test_integrating_advice_reduces_and_refuses_ti_below_theta() -> None:
    advice = advise(level_loop(), points=12)
    assert advice.current_simulated.oscillating
    assert any("Ti below theta not offered" in note for note in advice.notes)
    assert advice.recommendations
    assert all(r.outcome == "reduced" for r in advice.recommendations)
    # Table 5.9's trend: a longer Ti slows the predicted cycle (within the load-error bound,
    # Ti 2.85 times as long, the simulated travel does not fall by 5 %: not offered)
    raise_ti = next(r for r in (*advice.recommendations, *advice.rejected)
                    if r.source.endswith("raise Ti"))
    assert known_period(raise_ti.predicted.period_s) > known_period(
        advice.current_predicted.period_s
    )


def test_chapter_4_loop_retuned_by_table_5_11() -> None:
    """The He valve of chapter 4: raising Ti removes the cycle, predicted and simulated."""
    advice = advise(chapter4(), points=10)
    raise_ti = next(r for r in advice.recommendations if r.source.endswith("raise Ti"))
    assert raise_ti.outcome == "removed" and not raise_ti.predicted.oscillating
    (tuning,) = raise_ti.tunings
    assert tuning.kc == pytest.approx(0.1) and tuning.ti > 1 / 0.9


def test_no_cycle_in_simulation_means_nothing_to_offer() -> None:
    """An integrating process under P control without delay: the band-edge solution
    of Eq. 5.33 is not a stable cycle and the loop settles; nothing is offered."""
    loop = Loop(PIDController.ideal(2.0), ChoudhuryValve(4.0, 2.0), setpoint=[(1.0, 60.0)])
    advice = advise(
        ClosedLoopModel(TransferFunction.integrating(0.05), (loop,), 0.5, 4000.0), points=6
    )
    assert not advice.current_simulated.oscillating
    assert advice.recommendations == ()
    assert any("no steady cycle" in note for note in advice.notes)


@pytest.mark.slow
def test_multi_loop_procedure_section_5_6() -> None:
    """A 2x2 plant, valve 1 sticky: step 1 maps loop 1 alone, step 2 finds a
    combination that is stable as a whole; the simulation confirms the reduction.
    That combination leaves 22 times the error after a load step: within the default
    bound on it, nothing on the 3 x 3 grid is offered and the notes say why."""
    process = (
        (TransferFunction.fopdt(1.0, 10.0, 2.0), TransferFunction.fopdt(0.3, 8.0, 3.0)),
        (TransferFunction.fopdt(0.2, 12.0, 4.0), TransferFunction.fopdt(0.8, 6.0, 1.0)),
    )
    loops = (
        Loop(PIDController.ideal(3.0, 6.0), VALVE, name="A"),
        Loop(PIDController.ideal(1.0, 8.0), IdealValve(), name="B"),
    )
    bounded = advise(ClosedLoopModel(process, loops, 0.2, 3000.0))
    assert not bounded.recommendations and not bounded.rejected
    assert any(note.startswith("loop 1: no tuning in the search box") and "at most 3 times "
               "the current error after a load step" in note for note in bounded.notes)
    advice = advise(ClosedLoopModel(process, loops, 0.2, 3000.0),
                    max_load_error_ratio=math.inf)
    assert set(advice.maps) == {0}
    (recommendation,) = advice.recommendations
    assert recommendation.load_error_ratio == pytest.approx(22.36, rel=1e-3)
    assert recommendation.tunings[1] == advice.current[1]  # the healthy loop is kept
    controllers = [
        t.apply(loop.controller) for t, loop in zip(recommendation.tunings, loops, strict=True)
    ]
    prediction = predict_limit_cycles(process, controllers, [VALVE, IdealValve()], hold_delay=0.1)
    assert prediction.linear_stable and not prediction.oscillates
    assert recommendation.simulated.travel_rate < 0.2 * advice.current_simulated.travel_rate


def test_advice_refusals() -> None:
    with pytest.raises(ModelSpecError, match="derivative"):
        Tuning.of(PIDController.ideal(1.0, 10.0, 2.0))
    with pytest.raises(ModelSpecError, match="no sticky valve"):
        advise(dataclasses.replace(chapter4(sticky=False)))
    with pytest.raises(ModelSpecError, match="kc_factors"):
        advise(temperature_loop(), kc_factors=(2.0, 0.5))


def test_excited_model_adds_a_step_and_drops_noise() -> None:
    model = excited_model(temperature_loop(noise_std=0.3), duration=100.0)
    assert model.loops[0].disturbances == () and model.duration == 100.0
    bare = dataclasses.replace(temperature_loop().loops[0], setpoint=None)
    stepped = excited_model(dataclasses.replace(temperature_loop(), loops=(bare,)), duration=50.0)
    assert stepped.loops[0].setpoint == [(10.0, 54.0)]  # the stick band S = 4


def test_effects_from_prediction() -> None:
    prediction = predict_limit_cycles(TEMPERATURE, PIDController.ideal(10.0, 10.0), VALVE)
    effect = OscillationEffect.predicted(prediction)
    (cycle,) = prediction.limit_cycles
    assert effect.travel_rate == pytest.approx(4 * (cycle.amplitudes[0] or 0) / cycle.period_s)
    unstable = predict_limit_cycles(FOPDT, PIDController.ideal(5.0, 10.0), VALVE)
    assert math.isinf(OscillationEffect.predicted(unstable).travel_rate)
    assert isinstance(safe_tuning_map(FOPDT, VALVE, [1.0]), SafeTuningMap)


@pytest.mark.parametrize(("name", "origin"), [
    ("temp-sine200s-ts2", "forced"), ("flow-sine60s-ts1", "forced"),
    ("flow-aggressive-ts1", "own"), ("temp-aggressive-ts2", "own"),
    ("level-aggressive-ts1", "own"),
    ("temp-sine1000s-ts2", "unknown"),  # 3.6 cycles: too few to judge
])
def test_a_forced_cycle_is_told_from_the_loops_own(name, origin):
    """Sines entering healthy loops keep their amplitude; over-tuned loops driven by noise
    wax and wane (the synthetic library's ground truth, through the whole diagnosis)."""
    case = next(c for c in synthetic_library() if c.name == name)
    sim = case.simulate()
    d = diagnose_loop(ts=case.ts, op=sim.op[0], pv=sim.pv[0])
    cycles = d.samples * d.ts / d.oscillation.period_s
    assert cycle_origin(d.envelope_variation, cycles, 0.0)[0] == origin


@pytest.mark.parametrize("tuning", [Tuning(3.0, 4.0), Tuning(-0.5, math.inf)])
def test_detuning_is_its_json_read_back(tuning):
    """``Kc / m`` for each gain margin m (the phase crossover stays at the measured
    period), and ``from_dict`` inverts ``to_dict`` through JSON text (P control: Ti null)."""
    detuning = detune(tuning, 11.5)
    assert [t.kc for t in detuning.recommendations] == [tuning.kc / 2, tuning.kc / 3]
    assert all(t.ti == tuning.ti for t in detuning.recommendations)
    stored = json.loads(json.dumps(detuning.to_dict()))
    assert Detuning.from_dict(stored) == detuning
    assert Tuning.from_dict(stored["current"][0]) == tuning
    with pytest.raises(ModelSpecError, match="gain margins > 1"):
        detune(tuning, 11.5, (1.0,))


def plant_valve_travel(model: ClosedLoopModel, kc: float, ti: float, noise: float,
                       seed: int) -> float:
    """Mean valve travel per second (% per s) of ``model`` retuned to PI ``kc``, ``ti``
    with measurement noise of ``noise`` (seed ``seed``), over 3 h after its first hour."""
    (loop,) = model.loops
    noisy = dataclasses.replace(
        loop, controller=PIDController.ideal(kc, ti), setpoint=[(10.0, 51.0)],
        disturbances=(Disturbance("noise", noise, at="measurement", seed=seed),))
    run = dataclasses.replace(model, loops=(noisy,), duration=14_400.0).run()
    mv = run.mv[0][run.t >= 3600.0]
    return float(np.abs(np.diff(mv)).mean() / model.dt)


def test_a_retune_that_lets_the_noise_slip_the_valve_more_is_not_offered() -> None:
    """The demo's FV-105 loop (He valve fs 6, fd 2, PI 0.5 / 8 s, PV noise 0.05): the
    safe-tuning map's pick (Kc 1, Ti 12 s) removes the noise-free cycle, but with the
    noise the valve slips more often than under the current tuning.  Checked on two
    noise sequences other than the advice's own."""
    case = next(c for c in synthetic_library(100) if c.name == "flow-he-S8-J4-ts1")
    model = ClosedLoopModel(case.process, (Loop(PIDController.ideal(0.5, 8.0), case.valve,
                                                pv_bias=50.0),), dt=case.ts, duration=4000.0)
    noise = case.disturbances[0].magnitude
    quiet = advise(model, describing="equivalent")
    advice = advise(model, describing="equivalent", measurement_noise=(noise,))
    assert quiet.current_travel_rate_with_noise is None
    assert advice.current_travel_rate_with_noise is not None
    offered = {r.tunings for r in advice.recommendations}
    withdrawn = [r for r in quiet.recommendations if r.tunings not in offered]
    assert withdrawn and all(r.outcome == "removed" for r in withdrawn)
    assert "more gain lets the noise slip the valve" in advice.notes[-2]
    for seed in (11, 12):
        current = plant_valve_travel(model, 0.5, 8.0, noise, seed)
        for r in advice.recommendations:
            assert plant_valve_travel(model, r.tunings[0].kc, r.tunings[0].ti, noise,
                                      seed) < 0.95 * current
        for r in withdrawn:
            assert plant_valve_travel(model, r.tunings[0].kc, r.tunings[0].ti, noise,
                                      seed) > current


def test_measurement_noise_needs_a_level_per_loop() -> None:
    with pytest.raises(ModelSpecError, match="one finite standard deviation >= 0 per loop"):
        advise(temperature_loop(), measurement_noise=(0.1, 0.1))
    with pytest.raises(ModelSpecError, match="per loop"):
        advise(temperature_loop(), measurement_noise=(float("nan"),))
