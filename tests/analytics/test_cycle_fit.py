"""The valve of a loop model fitted to a measured cycle (:mod:`analytics.cycle_fit`),
checked against the simulated loops the cycles are measured on."""

import pytest

from analytics.cycle_fit import fit_valve_to_cycle, valve_of
from analytics.limit_cycle import simulate_limit_cycle
from analytics.lti import TransferFunction
from analytics.simulation import ClosedLoopModel, Loop, PIDController
from analytics.tuning import excited_model
from analytics.valves import HeValve, KanoValve

PROCESS = TransferFunction.fopdt(1.2, 8.0, 2.0)  # the demo's flow loops
CONTROLLER = PIDController.ideal(0.5, 8.0)


def loop_model(valve, process=PROCESS) -> ClosedLoopModel:
    return ClosedLoopModel(process, (Loop(CONTROLLER, valve, pv_bias=50.0),), dt=1.0,
                           duration=4000.0)


def measured(valve, process=PROCESS) -> tuple[float, float]:
    """The "plant": the loop simulated with its true valve (period, OP amplitude)."""
    cycle = simulate_limit_cycle(excited_model(loop_model(valve, process), duration=4000.0))
    assert cycle.oscillating and cycle.period_s is not None
    amplitude = cycle.amplitudes[0]
    assert amplitude is not None
    return cycle.period_s, amplitude


def test_a_he_valve_taken_for_a_kano_valve_is_found_by_its_cycle():
    """FV-105 of the demo: a He valve (fs 6, fd 2) whose cycle a Kano valve of the same S
    and J does not reproduce (the loop comes to rest); the check names the valve model and
    simulates the He valve, which gives the plant's cycle exactly (same model)."""
    period, amplitude = measured(HeValve(6.0, 2.0))
    fit = fit_valve_to_cycle(loop_model(KanoValve(8.0, 4.0)), period, amplitude)
    assert not fit.estimated.cycles
    assert fit.cause == "valve_model" and fit.chosen.kind == "he" and fit.changed
    assert (fit.chosen.S, fit.chosen.J) == (8.0, 4.0)
    assert fit.chosen.period_error == 0.0 and fit.chosen.amplitude_error == 0.0
    assert "does not cycle in simulation" in fit.explanation()
    assert isinstance(fit.fitted(loop_model(KanoValve(8.0, 4.0))).loops[0].valve, HeValve)


def test_an_estimate_that_reproduces_the_cycle_is_kept():
    period, amplitude = measured(KanoValve(4.0, 2.0), TransferFunction.fopdt(1.2, 6.0, 4.0))
    model = loop_model(KanoValve(4.2, 1.9), TransferFunction.fopdt(1.2, 6.0, 4.0))
    fit = fit_valve_to_cycle(model, period, amplitude)
    assert fit.cause == "none" and not fit.changed and fit.reproduces
    assert len(fit.tried) == 1


@pytest.mark.parametrize(("scale", "ratio"), [(0.6, 1.0), (1.5, 1.0), (1.0, 0.45)])
def test_a_size_off_is_fitted_back_within_the_intervals(scale, ratio):
    """The true He valve S 8, J 4; the estimate's S off by ``scale`` and its J / S by
    ``ratio``, the intervals wide enough to hold the truth.  The amplitude of a stiction
    cycle is proportional to S at a given J / S and its period depends on J / S alone
    (every valve model here is homogeneous), so the fit finds the plant's cycle and a
    size near the true one."""
    period, amplitude = measured(HeValve(6.0, 2.0))
    S0 = 8.0 * scale
    J0 = 4.0 * scale * ratio
    estimate = valve_of("he", S0, J0)
    fit = fit_valve_to_cycle(loop_model(estimate), period, amplitude,
                             S_interval=(4.0, 14.0), J_interval=(1.0, 7.0))
    assert not fit.estimated.reproduces
    assert fit.cause == "valve_size" and fit.chosen.kind == "he" and fit.reproduces
    errors = (fit.chosen.period_error, fit.chosen.amplitude_error)
    assert all(e is not None and abs(e) <= 0.05 for e in errors), errors
    assert abs(fit.chosen.S - 8.0) <= 0.8
    assert abs(fit.chosen.J / fit.chosen.S - 0.5) <= 0.07


def test_the_cycle_of_another_process_is_not_forced_onto_the_valve():
    """The plant's dead time is 16 s, the model's 2 s: no valve within the estimate's
    (narrow) intervals gives the plant's amplitude, so the check names the process and
    fits its dead time, which comes out near the plant's (within a step of its grid).
    (At 20 s of dead time this loop keeps no steady cycle: its OP swings 22-52 % in
    bursts, and which burst a run ends in turns on the last bits of the simulation.)"""
    plant = TransferFunction.fopdt(1.2, 8.0, 16.0)
    period, amplitude = measured(HeValve(6.0, 2.0), plant)
    model = loop_model(HeValve(6.0, 2.0))
    fit = fit_valve_to_cycle(model, period, amplitude,
                             S_interval=(7.5, 8.5), J_interval=(3.5, 4.5))
    assert fit.cause == "process" and not fit.estimated.reproduces
    assert fit.estimated.amplitude_error is not None and fit.estimated.amplitude_error < -0.5
    assert fit.delay_s is not None and fit.delay_s[0] == 2.0
    assert abs(fit.delay_s[1] - 16.0) <= 0.25 * period / 12
    assert fit.reproduces
    assert 7.5 <= fit.chosen.S <= 8.5 and 3.5 - 1e-9 <= fit.chosen.J <= 4.5 + 1e-9
    assert "dead time fitted (2 s identified" in fit.explanation()
    fitted = fit.fitted(model)
    assert isinstance(fitted.process, TransferFunction)
    assert fitted.process.delay == fit.delay_s[1] and fitted.process.den == plant.den
