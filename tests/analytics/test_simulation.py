"""Closed-loop simulator: checked against transfer-function algebra and the thesis cases."""

import dataclasses
import math

import numpy as np
import pytest
from scipy import signal

from analytics.errors import ModelSpecError
from analytics.lti import TransferFunction, discretise, simulate_open_loop
from analytics.oscillation import detect_oscillations
from analytics.scenarios import chapter4, column3x3
from analytics.simulation import (
    ClosedLoopModel,
    Disturbance,
    IdealGains,
    Loop,
    PIDController,
    simulate,
)
from analytics.valves import HeValve

FOPDT = TransferFunction.fopdt(K=2.0, tau=10.0, theta=3.0)


def closed_loop_step_by_algebra(g: TransferFunction, kp: float, ki: float, dt: float, n: int):
    """PV response to a unit SP step at k = 0 from z-domain algebra (independent path).

    Plant: y_k = C x_k, x_{k+1} = Ad x_k + B0 u_{k-d} (integer delay), i.e.
    G(z) = z^-d C (zI - Ad)^-1 B0. Controller: u_k = kp e_k + I_k,
    I_k = I_{k-1} + ki dt e_k, i.e. C(z) = ((kp + ki dt) z - kp) / (z - 1).
    """
    entry = discretise(g, dt)
    num_g, den_g = signal.ss2tf(entry.Ad, entry.B0.reshape(-1, 1), entry.C.reshape(1, -1), [[0.0]])
    num_g = np.trim_zeros(num_g[0], "f")
    den_g = np.polymul(den_g, np.r_[1.0, np.zeros(entry.delay_samples)])
    num_c, den_c = np.array([kp + ki * dt, -kp]), np.array([1.0, -1.0])
    open_num, open_den = np.polymul(num_g, num_c), np.polymul(den_g, den_c)
    closed_den = np.polyadd(open_den, open_num)
    _, y = signal.dlsim((open_num, closed_den, dt), np.ones(n))
    return y.ravel()


def dominant_period(x: np.ndarray, dt: float) -> tuple[float, float]:
    """Period of the largest Welch-spectrum peak and its share of the power."""
    f, p = signal.welch(x - x.mean(), fs=1.0 / dt, nperseg=4096)
    k = int(np.argmax(p[1:])) + 1
    return 1.0 / f[k], float(p[max(k - 2, 0) : k + 3].sum() / p.sum())


class TestAgainstAlgebra:
    @pytest.mark.parametrize(
        "g",
        [
            FOPDT,
            TransferFunction.second_order(1.5, 8.0, 3.0, 2.0),
            TransferFunction.integrating(0.05, 2.0),
        ],
        ids=["fopdt", "second_order", "integrating"],
    )
    def test_linear_loop_matches_closed_loop_transfer_function(self, g):
        dt, kp, ki = 0.5, 0.8, 0.05
        loop = Loop(
            PIDController.parallel(kp, ki, op_limits=(-1e6, 1e6)), setpoint=51.0, pv_bias=50.0
        )
        result = simulate(g, loop, dt=dt, duration=400.0)
        expected = closed_loop_step_by_algebra(g, kp, ki, dt, result.t.size)
        np.testing.assert_allclose(result.pv[0] - 50.0, expected, atol=1e-9)

    def test_p_only_offset_is_one_over_one_plus_loop_gain(self):
        kc = 1.5
        loop = Loop(PIDController.ideal(kc), setpoint=[(5.0, 54.0)], pv_bias=50.0)
        result = simulate(FOPDT, loop, dt=0.5, duration=600.0)
        # final-value theorem: y = K Kc / (1 + K Kc) * step
        assert result.pv[0, -1] - 50.0 == pytest.approx(4.0 * 2.0 * kc / (1 + 2.0 * kc), rel=1e-6)

    def test_input_disturbance_reproduces_every_matrix_entry_open_loop(self):
        # With zero controller gains OP stays at its bias, so PV_i is the open-loop
        # response of g_ij to a load step on valve j: checks matrix wiring and delays.
        g = [
            [TransferFunction.fopdt(1.0, 5.0, 1.3), TransferFunction.fopdt(-0.5, 3.0, 2.0)],
            [None, TransferFunction.lead_lag(0.8, 4.0, 6.0, 2.0, 0.7)],
        ]
        loops = [
            Loop(PIDController.parallel(0.0), pv_bias=0.0),
            Loop(
                PIDController.parallel(0.0),
                pv_bias=0.0,
                disturbances=(Disturbance("step", 2.0, at="input", time=1.0),),
            ),
        ]
        result = simulate(g, loops, dt=0.25, duration=60.0)
        u = np.where(result.t >= 1.0, 2.0, 0.0)
        np.testing.assert_allclose(result.pv[0], simulate_open_loop(g[0][1], u, 0.25), atol=1e-12)
        np.testing.assert_allclose(result.pv[1], simulate_open_loop(g[1][1], u, 0.25), atol=1e-12)

    def test_decoupled_loops_equal_separate_simulations(self):
        g2 = TransferFunction.fopdt(0.7, 4.0, 1.0)
        loop1 = Loop(
            PIDController.ideal(1.0, 12.0), valve=HeValve(2.0, 1.0), setpoint=[(3.0, 53.0)]
        )
        loop2 = Loop(
            PIDController.ideal(0.5, 8.0),
            setpoint=[(7.0, 45.0)],
            disturbances=(Disturbance("noise", 0.1, at="measurement", seed=3),),
        )
        both = simulate([[FOPDT, None], [None, g2]], [loop1, loop2], dt=0.5, duration=300.0)
        alone1 = simulate(FOPDT, loop1, dt=0.5, duration=300.0)
        alone2 = simulate(g2, loop2, dt=0.5, duration=300.0)
        np.testing.assert_array_equal(both.pv[0], alone1.pv[0])
        np.testing.assert_array_equal(both.op[1], alone2.op[0])


class TestController:
    def test_ideal_and_parallel_forms_agree(self):
        a = simulate(
            FOPDT,
            Loop(PIDController.ideal(0.8, 16.0), setpoint=[(1.0, 55.0)]),
            dt=0.5,
            duration=200.0,
        )
        b = simulate(
            FOPDT,
            Loop(PIDController.parallel(0.8, 0.05), setpoint=[(1.0, 55.0)]),
            dt=0.5,
            duration=200.0,
        )
        np.testing.assert_allclose(a.pv, b.pv, atol=1e-12)

    def test_direct_action_equals_negative_gains(self):
        g = TransferFunction.fopdt(-2.0, 10.0, 3.0)
        direct = PIDController.parallel(0.3, 0.02, action="direct")
        negative = PIDController.parallel(-0.3, -0.02)
        a = simulate(g, Loop(direct, setpoint=[(1.0, 45.0)]), dt=0.5, duration=300.0)
        b = simulate(g, Loop(negative, setpoint=[(1.0, 45.0)]), dt=0.5, duration=300.0)
        np.testing.assert_allclose(a.op, b.op, atol=1e-12)
        assert a.pv[0, -1] == pytest.approx(45.0, abs=1e-3)

    def test_output_limits_and_anti_windup(self):
        # A setpoint the valve cannot reach for 200 s, then back: OP stays within
        # limits and leaves saturation at once when the error changes sign.
        loop = Loop(PIDController.ideal(2.0, 5.0), setpoint=[(10.0, 200.0), (210.0, 50.0)])
        result = simulate(FOPDT, loop, dt=0.5, duration=400.0)
        op, t = result.op[0], result.t
        assert op.max() == 100.0 and op.min() >= 0.0
        assert np.all(op[(t > 60) & (t < 210)] == 100.0)
        first_below = t[(t >= 210) & (op < 100.0)][0]
        assert first_below - 210.0 <= 5.0  # a wound-up integrator would hold OP for ~100 s

    def test_derivative_acts_on_measurement_without_setpoint_kick(self):
        pid = PIDController.ideal(1.0, 20.0, Td=2.0)
        result = simulate(FOPDT, Loop(pid, setpoint=[(10.0, 52.0)]), dt=0.5, duration=100.0)
        step = np.flatnonzero(result.t == 10.0)[0]
        # at the step, OP changes by exactly the P and I terms, no derivative spike
        assert result.op[0, step] - result.op[0, step - 1] == pytest.approx(2.0 * (1 + 0.5 / 20.0))

    def test_noise_is_reproducible_with_a_seed(self):
        loop = Loop(
            PIDController.ideal(1.0, 10.0),
            disturbances=(Disturbance("noise", 0.2, at="measurement", seed=9),),
        )
        a = simulate(FOPDT, loop, dt=1.0, duration=100.0)
        b = simulate(FOPDT, loop, dt=1.0, duration=100.0)
        np.testing.assert_array_equal(a.pv, b.pv)
        assert np.std(a.pv[0]) > 0.1


def ideal_gains_grid() -> list[IdealGains]:
    """Kc, Ti, Td over decades, both signs of Kc, P-only included."""
    rng = np.random.default_rng(25)
    kc = 10 ** rng.uniform(-3, 2, 300) * rng.choice([-1.0, 1.0], 300)
    ti = np.append(10 ** rng.uniform(-1, 3, 299), math.inf)
    td = np.where(rng.random(300) < 0.5, 0.0, 10 ** rng.uniform(-1, 1, 300))
    return [IdealGains(*map(float, row)) for row in zip(kc, ti, td, strict=True)]


class TestIdealForm:
    """PIDController keeps the ideal-form gains it was given (issue 25)."""

    def test_ideal_gains_read_back_bit_for_bit(self):
        grid = ideal_gains_grid()
        inexact = 0
        for gains in grid:
            c = PIDController.ideal(*gains)
            assert c.as_ideal() == gains
            assert [x.hex() for x in c.as_ideal()] == [x.hex() for x in gains]
            # the parallel gains are those the ideal form always gave
            assert (c.kp, c.ki, c.kd) == (
                gains.Kc, 0.0 if math.isinf(gains.Ti) else gains.Kc / gains.Ti,
                gains.Kc * gains.Td,
            )
            inexact += math.isfinite(gains.Ti) and c.kp / c.ki != gains.Ti
        # Ti derived from kp / ki would miss for some of them: the test can fail
        assert inexact > 10

    def test_parallel_gains_have_the_ideal_form_of_the_textbook(self):
        # Kc = Kp, Ti = Kp / Ki, Td = Kd / Kp (Astrom & Hagglund 2006, sec. 3.2)
        assert PIDController.parallel(2.0, 0.5, 3.0).as_ideal() == IdealGains(2.0, 4.0, 1.5)
        assert PIDController.parallel(-0.5).as_ideal() == IdealGains(-0.5, math.inf, 0.0)
        for gains in ((0.0, 0.1), (-0.3, 0.02), (0.3, 0.0, -1.0)):
            with pytest.raises(ModelSpecError, match="ideal form"):
                PIDController.parallel(*gains).as_ideal()

    def test_gains_that_are_not_those_of_the_ideal_form_are_refused(self):
        c = PIDController.ideal(0.1, 11.0)
        with pytest.raises(ModelSpecError, match="not those of its ideal form"):
            dataclasses.replace(c, kp=0.2)  # a new gain, the old ideal form
        with pytest.raises(ModelSpecError, match="integral time Ti must be > 0"):
            PIDController(kp=1.0, ki=-0.1, ideal_form=IdealGains(1.0, -10.0))
        assert dataclasses.replace(c, kp=0.2, ki=0.02, ideal_form=None).as_ideal().Ti == 10.0

    def test_from_dict_keeps_the_ideal_form_and_the_json_in_parallel_gains(self):
        c = PIDController.from_dict({"Kc": 0.1, "Ti": 11.0, "op_bias": 40.0})
        assert c.as_ideal() == IdealGains(0.1, 11.0, 0.0)
        assert c.to_dict()["Ki"] == 0.1 / 11.0  # the JSON contract is unchanged
        assert PIDController.from_dict({"Kp": 0.1, "Ki": 0.1 / 11.0}).ideal_form is None


class TestThesisCases:
    def test_chapter4_loop_settles_with_a_healthy_valve(self):
        result = chapter4(sticky=False).run()
        late = result.t > 1500
        assert np.ptp(result.pv[0][late]) < 1e-6
        assert result.pv[0, -1] == pytest.approx(52.0, abs=1e-6)

    def test_chapter4_loop_cycles_with_the_he_valve(self):
        result = chapter4(sticky=True).run(duration=6000.0)
        late = result.t > 2000
        steps = np.diff(result.mv[0][late])
        directions = np.sign(steps[steps != 0])
        assert np.count_nonzero(np.diff(directions)) >= 6  # the valve keeps reversing
        assert np.ptp(result.pv[0][late]) > 0.5
        report = detect_oscillations(result.pv[0][late], result.dt)
        assert report.detected

    @pytest.mark.parametrize("sticky", [(1, 2), (1, 2, 3)])
    def test_column_loops_share_one_oscillation(self, sticky):
        # Thesis section 2.4 / Fig. 2.7: every PV oscillates at the common frequency.
        result = column3x3(sticky=sticky, duration=12000.0).run()
        late = result.t > 3000
        found = [dominant_period(pv[late], result.dt) for pv in result.pv]
        common = found[0][0]
        bin_hz = 1.0 / (4096 * result.dt)  # the Welch segment's frequency resolution
        for period, share in found:
            assert abs(1.0 / period - 1.0 / common) <= 1.01 * bin_hz, found  # one bin apart
            assert share > 0.1, found
        assert detect_oscillations(result.pv[1][late], result.dt).detected

    def test_column_frequency_rises_from_tuning_3_25_to_3_26(self):
        # Thesis Table 3.2: omega 0.16 (Eq. 3.25) -> 0.46 (Eq. 3.26) by the DF.
        periods = []
        for tuning in ("2.11", "3.26"):
            result = column3x3(sticky=(2, 3), tuning=tuning, duration=12000.0).run()
            late = result.t > 3000
            loop_periods = [dominant_period(pv[late], result.dt)[0] for pv in result.pv[:2]]
            assert loop_periods[0] == pytest.approx(loop_periods[1], rel=0.05)
            periods.append(loop_periods[0])
        assert periods[1] < 0.5 * periods[0]


class TestModelSpec:
    def test_json_model_round_trip(self):
        spec = {
            "dt": 0.5,
            "duration": 100,
            "process": {"type": "fopdt", "K": 0.66, "tau": 6.7, "theta": 2.6},
            "controller": {"Kp": 0.1, "Ki": 0.09},
            "valve": {"model": "he", "fs": 3, "fd": 2},
            "setpoint": [[10, 52]],
        }
        model = ClosedLoopModel.from_dict(spec)
        assert model.loops[0].valve == HeValve(3, 2)
        assert model.run().pv.shape == (1, 201)

    @pytest.mark.parametrize(
        ("spec", "message"),
        [
            ({"process": {"type": "fopdt", "K": 1, "tau": 1}}, "lacks the required key 'dt'"),
            (
                {
                    "dt": 1,
                    "process": {"matrix": [[{"type": "fopdt", "K": 1, "tau": 1}, None]]},
                    "controllers": [{"Kc": 1}],
                },
                "must be 1 x 1",
            ),
            (
                {"dt": 1, "process": {"type": "fopdt", "K": 1, "tau": 1}, "controller": {"Ti": 3}},
                "needs 'Kc'",
            ),
            (
                {
                    "dt": 1,
                    "process": {"type": "fopdt", "K": 1, "tau": 1},
                    "controller": {"Kc": 1, "Ti": -2},
                },
                "Ti must be > 0",
            ),
            ({"dt": 1, "process": {"type": "fopdt", "K": 1, "tau": 1}}, "loop 1 has no controller"),
            (
                {
                    "dt": 1,
                    "process": {"type": "fopdt", "K": 1, "tau": 1},
                    "controllers": [{"Kc": 1}, {"Kc": 1}],
                },
                "one entry per loop",
            ),
        ],
    )
    def test_bad_models_are_refused_with_the_key(self, spec, message):
        with pytest.raises(ModelSpecError, match=message):
            ClosedLoopModel.from_dict(spec)

    def test_invalid_arguments(self):
        loop = Loop(PIDController.ideal(1.0, 10.0))
        with pytest.raises(ModelSpecError, match="dt must be > 0"):
            simulate(FOPDT, loop, dt=0.0, duration=10.0)
        with pytest.raises(ModelSpecError, match="entry \\(1,1\\) is missing"):
            simulate([[None]], loop, dt=1.0, duration=10.0)
        with pytest.raises(ModelSpecError, match="op_bias=150"):
            PIDController.ideal(1.0, op_bias=150.0)


def test_manual_holds_op_and_the_return_to_automatic_is_bumpless():
    """In manual OP holds its last value; back in automatic the integrator has tracked it,
    so OP moves on from the held value by the PI law's increment alone (Astrom and
    Hagglund 2006, sec. 3.5): ``kp (e_k - e_{k-1}) + ki dt e_k``."""
    g = TransferFunction.fopdt(K=1.0, tau=20.0, theta=2.0)
    pid = PIDController.ideal(Kc=0.8, Ti=15.0)
    loop = Loop(pid, setpoint=[(10.0, 55.0)], manual=((100.0, 200.0),),
                disturbances=(Disturbance("step", 3.0, time=150.0),))
    res = simulate(g, loop, dt=1.0, duration=400.0)
    op, e = res.op[0], res.sp[0] - res.pv[0]
    np.testing.assert_array_equal(op[100:200], op[99])
    assert abs(e[199]) > 1.0  # the load came while in manual
    k = 200
    assert op[k] == pytest.approx(op[k - 1] + pid.kp * (e[k] - e[k - 1]) + pid.ki * e[k],
                                  rel=1e-12)
    assert abs(e[-1]) < 0.05  # automatic again removes the load's offset
