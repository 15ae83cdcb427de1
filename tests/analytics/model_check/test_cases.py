"""analytics.model_check.cases: random loops hiding one known effect."""

from dataclasses import replace

import numpy as np
import pytest

from analytics.model_check import LoopModel
from analytics.model_check.cases import CATALOGUE, PV_BIAS, _levels, hidden_effect_case
from analytics.model_check.model import friction_of


class TestLevels:
    def test_random_loops_draw_their_levels_as_one_set_at_a_time(self) -> None:
        rng, reference = np.random.default_rng(0), np.random.default_rng(0)
        while True:  # the rejection sampling the block-wise draws must reproduce
            values = reference.uniform(-18.0, 18.0, 5)
            if np.min(np.diff(np.sort(values))) >= 8.0:
                break
        np.testing.assert_array_equal(_levels(rng, 5, 18.0, 8.0), values)
        assert rng.uniform() == reference.uniform()  # the generators are left alike



SEEDS = range(6)


def without(effect: str, true: LoopModel, base: LoopModel) -> LoopModel:
    """``true`` with the part ``effect`` changes taken from ``base``."""
    if effect in ("gain_mismatch", "deadtime_mismatch", "time_constant_mismatch"):
        return replace(true, process=base.process)
    if effect in ("valve_characteristic", "asymmetric_stiction", "position_dependent_stiction"):
        return replace(true, valve=base.valve)
    if effect == "measurement_quantization":
        return replace(true, quantiser=base.quantiser)
    if effect == "external_disturbance":
        return replace(true, load=base.load)
    return true


def within(x: float, *ranges: tuple[float, float]) -> bool:
    return any(low - 1e-12 <= x <= high + 1e-12 for low, high in ranges)


@pytest.mark.parametrize("effect", CATALOGUE)
def test_a_case_hides_its_effect_alone_and_of_the_documented_size(effect: str) -> None:
    """The true loop differs from the base model in the effect's part only, by a size
    of the table of the module docstring."""
    for seed in SEEDS:
        case = hidden_effect_case(effect, seed, samples=300)
        base, true = case.base_model, case.true_model
        assert true is not None and without(effect, true, base) == base
        p, q = base.process, true.process
        if effect == "none":
            assert true == base and case.parameters == {}
        elif effect == "gain_mismatch":
            assert within(q.K / p.K, (1.3, 1.7), (0.55, 0.77))
            assert case.parameters["ratio"] == pytest.approx(q.K / p.K, rel=1e-12)
        elif effect == "deadtime_mismatch":
            assert q.theta >= 0 and within(abs(q.theta - p.theta), (2.0, max(2.0, p.theta)))
        elif effect == "time_constant_mismatch":
            assert (within(q.tau / p.theta, (3.0, 8.0)) if p.integrating
                    else within(q.tau / p.tau, (1.7, 2.5), (0.35, 0.6)))
        elif effect == "valve_characteristic":
            assert within(abs(true.valve.curvature), (2.0, 4.0))
        elif effect == "measurement_quantization":
            q_true = true.quantiser
            assert q_true is not None and within(q_true.resolution, (0.2, 0.6))
            assert within(case.noise_std / q_true.resolution, (0.01, 0.05))
        elif effect == "external_disturbance":
            load = true.load
            assert load is not None and within(load.period, (15.0, 400.0))
            assert load.amplitude >= max(0.3, 4.0 * case.noise_std) - 1e-12
        elif effect == "asymmetric_stiction":
            S = friction_of(base.valve.base)[0]
            (side,) = [v for v in (true.valve.opening, true.valve.closing) if v is not None]
            assert within(side.S / S, (2.0, 3.5)) if S > 0 else within(side.S, (2.0, 5.0))
        else:
            zone = true.valve.zone
            assert zone is not None and within(zone.high - zone.low, (5.0, 10.0))
            assert within(zone.valve.S - friction_of(base.valve.base)[0], (2.5, 5.0))


@pytest.mark.parametrize("seed", SEEDS)
def test_base_loops_are_simc_tuned(seed: int) -> None:
    """The SIMC rules of Skogestad (2003), J. Process Control 13:291-309: for a
    first-order process Kc = tau / (K (tc + theta)), Ti = min(tau, 4 (tc + theta)); for an
    integrator Kc = 1 / (K (tc + theta)), Ti = 4 (tc + theta)."""
    for effect in ("none", "gain_mismatch"):
        case = hidden_effect_case(effect, seed, samples=300)
        p, gains = case.base_model.process, case.base_model.controller.as_ideal()
        if p.integrating:
            closed_plus_theta = 1.0 / (p.K * gains.Kc)
            assert gains.Ti == pytest.approx(4.0 * closed_plus_theta, rel=1e-12)
            assert within((closed_plus_theta - p.theta) / p.theta, (3.0, 6.0))
        else:
            closed_plus_theta = p.tau / (p.K * gains.Kc)
            assert gains.Ti == pytest.approx(min(p.tau, 4.0 * closed_plus_theta), rel=1e-12)
            slowest = max(p.theta, p.tau / 4.0)
            assert within((closed_plus_theta - p.theta) / slowest, (1.0, 2.0))


@pytest.mark.parametrize("effect", ["none", "gain_mismatch", "asymmetric_stiction"])
def test_the_signals_are_those_of_the_true_loop(effect: str) -> None:
    """Replayed open loop, the measured OP gives the case's MV and, but for the
    measurement noise (of the stated size), its PV: the closed-loop simulation and the
    open-loop replay are two paths through the same model."""
    case = hidden_effect_case(effect, 3, samples=4000)
    true = case.true_model
    assert true is not None
    mv, x = true.replay(case.op, initial_position=true.op_bias)
    np.testing.assert_allclose(mv, case.mv, atol=1e-9)
    noise = case.pv - (PV_BIAS + x)
    assert np.std(noise) == pytest.approx(case.noise_std, rel=0.05)
    assert abs(np.mean(noise)) < 4.0 * case.noise_std / np.sqrt(noise.size)
