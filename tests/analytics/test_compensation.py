"""Stiction compensation: checked against the plain simulator, the He model itself, the
chapter 4 example of the thesis and its Tables 4.2-4.4."""

from dataclasses import replace

import numpy as np
import pytest

from analytics.compensation import (
    CHAPTER4_GAIN,
    CHAPTER4_VALVE,
    THESIS_TABLE_4_3,
    THESIS_TABLE_4_4,
    ConstantReinforcement,
    Knocker,
    ModelBasedCompensator,
    ModelBasedRun,
    NoCompensation,
    compare_compensators,
    compensation_metrics,
    he_inverse,
    model_based_sensitivity,
    simulate_compensated,
    two_move_inputs,
)
from analytics.errors import ModelSpecError, ValveModelError
from analytics.lti import TransferFunction
from analytics.scenarios import chapter4
from analytics.simulation import Disturbance, Loop, PIDController, simulate
from analytics.valves import ChoudhuryValve, HeValve

MODEL = chapter4()
PROCESS, LOOP, DT = MODEL.process, MODEL.loops[0], MODEL.dt
MV_SS = 50.0 + 2.0 / CHAPTER4_GAIN  # valve position that holds PV at SP = 52 (thesis SP = 2)


def run_chapter4(compensator, *, duration=4000.0, compensate_from=1000.0, loop=LOOP):
    return simulate_compensated(
        PROCESS, loop, compensator, dt=DT, duration=duration, compensate_from=compensate_from
    )


def model_based(**settings):
    return ModelBasedCompensator(valve=CHAPTER4_VALVE, process_gain=CHAPTER4_GAIN, **settings)


@pytest.fixture(scope="module")
def comparison():
    return {row.method: row for row in compare_compensators()}


# ---------------------------------------------------------------- the stepper
class TestStepperAgainstSimulator:
    def test_uncompensated_sticky_loop_matches_the_compiled_simulator(self):
        # Round-off differences grow through the valve's discontinuity, hence 2000 s.
        reference = MODEL.run(duration=2000.0)
        res = run_chapter4(NoCompensation(), duration=2000.0, compensate_from=0.0)
        np.testing.assert_allclose(res.pv, reference.pv[0], atol=1e-9)
        np.testing.assert_allclose(res.op, reference.op[0], atol=1e-9)
        np.testing.assert_allclose(res.mv, reference.mv[0], atol=1e-9)
        np.testing.assert_array_equal(res.valve_input, res.op)

    @pytest.mark.parametrize(
        "process",
        [
            TransferFunction.fopdt(1.5, 12.0, 3.7),
            TransferFunction.integrating(0.05, 2.5),
            TransferFunction.second_order(0.8, 6.0, 2.0),
        ],
        ids=["fopdt", "integrating", "second_order"],
    )
    def test_linear_loop_with_derivative_limits_and_loads_matches(self, process):
        loop = Loop(
            controller=PIDController.ideal(2.0, 20.0, 1.5, op_limits=(40.0, 58.0)),
            setpoint=[(5.0, 55.0), (300.0, 48.0)],
            disturbances=(
                Disturbance("sine", 0.5, period=47.0),
                Disturbance("noise", 0.05, at="measurement", seed=3),
                Disturbance("step", 1.0, at="input", time=150.0),
            ),
        )
        reference = simulate(process, loop, dt=0.5, duration=600.0)
        res = simulate_compensated(process, loop, NoCompensation(), dt=0.5, duration=600.0)
        assert res.op.max() == pytest.approx(58.0)  # the output limit is reached
        np.testing.assert_allclose(res.pv, reference.pv[0], atol=1e-9)
        np.testing.assert_allclose(res.op, reference.op[0], atol=1e-9)


# ---------------------------------------------------------------- He model inverse
class TestHeInverse:
    @pytest.mark.parametrize("fs, fd", [(3.0, 2.0), (4.5, 1.5), (1.0, 0.0), (2.0, 2.0)])
    def test_lands_on_the_nearest_reachable_position(self, fs, fd):
        # Thesis Eqs. 4.3 and 4.5: from y the He valve can stay or slip by >= fs - fd.
        valve, slip = HeValve(fs=fs, fd=fd), fs - fd
        rng = np.random.default_rng(0)
        for position, target in rng.uniform(40.0, 60.0, size=(500, 2)):
            landed = valve.stepper(position).step(he_inverse(valve, target, position))
            gap = abs(target - position)
            nearest = 0.0 if gap > slip else min(gap, slip - gap)
            assert abs(landed - target) == pytest.approx(nearest, abs=1e-8)

    @pytest.mark.parametrize("stuck", [49.0, 52.7, 53.1, 53.03, 58.0])
    @pytest.mark.parametrize("fs_error", [-1.0, 0.0, 1.5])
    def test_two_moves_land_on_target_whatever_the_true_fs(self, stuck, fs_error):
        # Eqs. 4.11-4.13: each move slips and the second lands at OP_end -+ fd, so the end
        # point is exact as long as fs is wrong by less than the margin.
        estimate = HeValve(fs=3.0, fd=2.0)
        true_valve = HeValve(fs=3.0 + fs_error, fd=2.0)
        op_mid, op_end = two_move_inputs(estimate, stuck, MV_SS, margin=2.0)
        stepper = true_valve.stepper(stuck)
        mid = stepper.step(op_mid)
        assert abs(mid - stuck) > 0  # the first move slipped
        assert stepper.step(op_end) == pytest.approx(MV_SS)
        assert (op_mid > stuck) == (stuck > MV_SS)  # thesis Remark: up first to close

    def test_a_wrong_fd_shifts_the_landing_by_the_error(self):
        op_mid, op_end = two_move_inputs(HeValve(fs=3.0, fd=1.5), 54.0, MV_SS, margin=2.0)
        stepper = CHAPTER4_VALVE.stepper(54.0)
        stepper.step(op_mid)
        assert stepper.step(op_end) == pytest.approx(MV_SS + 0.5)  # lands at OP_end + true fd


# ---------------------------------------------------------------- pulse compensators
class TestSignalCompensators:
    def test_knocker_pulse_train_follows_the_op_trend(self):
        run = Knocker(amplitude=2.0, width=2.0, period=5.0).start(dt=1.0, op=60.0)
        op = 60.0 - 0.1 * np.arange(20)
        added = np.array([run.step(k, 0.0, 0.0, u) for k, u in enumerate(op)]) - op
        expected = np.zeros(20)
        for start in (5, 10, 15):  # no trend known at the first pulse
            expected[start : start + 2] = -2.0
        np.testing.assert_allclose(added, expected, atol=1e-12)

    def test_constant_reinforcement_adds_a_in_the_sign_of_the_op_change(self):
        # Thesis Eq. 1.3: alpha_k = a_cr sign(du).
        run = ConstantReinforcement(amplitude=1.2).start(dt=1.0, op=50.0)
        op = [50.5, 50.5, 50.1, 50.3]
        added = [run.step(k, 0.0, 0.0, u) - u for k, u in enumerate(op)]
        assert added == pytest.approx([1.2, 0.0, -1.2, 1.2])

    def test_knocker_cuts_pv_error_but_wears_the_valve(self, comparison):
        # The known trade-off (thesis sec. 1.2.4; Hagglund 2002).
        none, knocker = comparison["none"], comparison["knocker"]
        assert knocker.iae < 0.6 * none.iae
        assert knocker.valve_travel > 10 * none.valve_travel
        assert knocker.valve_reversals > 10 * none.valve_reversals

    def test_constant_reinforcement_shows_the_same_trade_off(self, comparison):
        none, reinforcement = comparison["none"], comparison["constant reinforcement"]
        assert reinforcement.iae < 0.6 * none.iae
        assert reinforcement.valve_travel > 10 * none.valve_travel


# ---------------------------------------------------------------- model-based method
class TestModelBased:
    def test_removes_the_limit_cycle_of_the_chapter4_example(self):
        res = run_chapter4(model_based())
        late = compensation_metrics(res, start=3000.0)
        assert late.valve_reversals == 0
        assert late.valve_travel == 0.0
        assert np.abs(res.pv[3000:] - 52.0).max() < 0.03
        assert isinstance(res.run, ModelBasedRun)
        assert res.run.phase == "regulated"
        # Learned OP_ss against the analytic steady state (thesis: 53.0).
        assert res.run.op_ss_ == pytest.approx(MV_SS, abs=0.02)

    def test_without_compensation_the_loop_keeps_cycling(self):
        res = run_chapter4(NoCompensation())
        late = compensation_metrics(res, start=3000.0)
        assert late.valve_reversals >= 4
        assert np.ptp(res.pv[3000:]) > 0.5

    def test_beats_the_signal_compensators_on_error_and_on_wear(self, comparison):
        mb = comparison["model-based"]
        for other in ("none", "knocker", "constant reinforcement"):
            assert mb.iae < comparison[other].iae
            assert mb.final_pv_error < comparison[other].final_pv_error
        assert mb.valve_travel < comparison["knocker"].valve_travel / 4

    def test_holding_puts_the_controller_in_tracking(self):
        res = run_chapter4(model_based(), duration=2000.0)
        # Learning 1000-1500 s, holding from 1500 s: OP held at OP_ss, valve stuck.
        np.testing.assert_allclose(res.op[1501:], res.run.op_ss_)
        assert np.ptp(res.mv[1502:1800]) == 0.0

    def test_thesis_procedure_eq_4_6_learns_a_biased_op_ss(self):
        # Mean OP (Eq. 4.6 as printed) sits at the dither threshold: 52.79 here.
        res = run_chapter4(model_based(learn_from="op"), duration=2000.0)
        assert abs(res.run.op_ss_ - MV_SS) > 0.1

    def test_setpoint_change_is_relearned(self):
        loop = replace(LOOP, setpoint=[(10.0, 52.0), (2500.0, 53.5)])
        res = run_chapter4(model_based(), duration=5000.0, loop=loop)
        assert res.run.op_ss_ == pytest.approx(50.0 + 3.5 / CHAPTER4_GAIN, abs=0.03)
        assert np.abs(res.pv[4000:] - 53.5).max() < 0.03
        assert compensation_metrics(res, start=4000.0).valve_reversals == 0
        # The first setpoint had been reached and held before the change.
        assert np.abs(res.pv[2200:2500] - 52.0).max() < 0.03

    def test_repeated_regulation_corrects_a_wrong_fd(self):
        comp = ModelBasedCompensator(
            valve=HeValve(fs=3.0, fd=1.5), process_gain=CHAPTER4_GAIN, regulation_attempts=3
        )
        res = run_chapter4(comp)
        errors = res.run.pv_errors_
        assert len(errors) >= 3
        assert abs(errors[1]) > 0.2  # one regulation (the thesis): off by about K * 0.5
        assert abs(errors[-1]) <= comp.pv_tolerance
        assert compensation_metrics(res, start=3500.0).valve_reversals == 0


# ---------------------------------------------------------------- thesis Tables 4.3-4.4
SWITCH_ON_TIMES = (1000.0, 1200.0)


@pytest.fixture(scope="module")
def stiction_rows():
    cases = [(fs, fd, 0.0) for fs, fd in THESIS_TABLE_4_3]
    rows = model_based_sensitivity(cases, switch_on_times=SWITCH_ON_TIMES)
    return {(row.fs, row.fd): row for row in rows}


class TestSensitivityAgainstThesis:
    def test_exact_parameters_reproduce_table_4_2(self, stiction_rows):
        row = stiction_rows[3.0, 2.0]
        assert row.op_ss == pytest.approx(row.thesis_op_ss, abs=0.05)  # 53.0
        assert row.pv_error_one_move < 0.03  # thesis: PV_ss = 2.00

    @pytest.mark.parametrize("fs", [2.5, 3.5])  # Table 4.3, rows 3-4
    def test_an_fs_error_leaves_an_offset_as_in_table_4_3(self, stiction_rows, fs):
        exact, wrong = stiction_rows[3.0, 2.0], stiction_rows[fs, 2.0]
        assert wrong.thesis_pv_error > exact.thesis_pv_error  # thesis: 2.08 vs 2.00
        assert wrong.pv_error_one_move > exact.pv_error_one_move

    def test_underestimating_fs_is_worse_than_overestimating(self, stiction_rows):
        # Our finding (the thesis has 2.08 both ways): minimum slips of the learning
        # phase fail when fs is too small, and the internal model loses the valve.
        assert stiction_rows[2.5, 2.0].pv_error_one_move > stiction_rows[3.5, 2.0].pv_error_one_move

    @pytest.mark.parametrize("fd", [1.5, 2.5])  # Table 4.3, rows 1-2
    def test_an_fd_error_shifts_the_landing_unlike_table_4_3(self, stiction_rows, fd):
        # He's model lands at OP_end -+ fd, so one regulation is off by about K |fd error|
        # (0.33 % here); the thesis reports 0.03 and 0.01. Repeating fixes it.
        row = stiction_rows[3.0, fd]
        assert row.pv_error_one_move > 0.5 * CHAPTER4_GAIN * 0.5
        assert abs(row.thesis_pv_error) < 0.05
        assert row.pv_error_repeated < 0.03

    @pytest.mark.parametrize("gain_error", sorted(THESIS_TABLE_4_4))
    def test_a_gain_error_barely_matters_as_in_table_4_4(self, gain_error):
        (row,) = model_based_sensitivity(
            [(3.0, 2.0, gain_error)], switch_on_times=SWITCH_ON_TIMES[:1], regulation_attempts=1
        )
        assert abs(row.thesis_pv_error) < 0.035  # thesis: 1.973-2.032
        assert row.pv_error_one_move < 0.035
        # Our OP_ss is learned through the valve model, independent of K; the thesis's
        # column follows 50 + 2/K_hat (53.8 at -20 %).
        assert row.op_ss == pytest.approx(MV_SS, abs=0.02)
        assert row.thesis_op_ss == pytest.approx(50.0 + 2.0 / (0.66 * (1 + gain_error)), abs=0.06)


# ---------------------------------------------------------------- refusals
class TestRefusals:
    @pytest.mark.parametrize(
        "build, message",
        [
            (lambda: Knocker(amplitude=0.0), "knocker amplitude must be a finite number > 0"),
            (lambda: Knocker(amplitude=2.0, width=4.0, period=4.0), "must exceed the pulse"),
            (lambda: ConstantReinforcement(amplitude=float("nan")), "amplitude must be"),
            (lambda: model_based(regulation_attempts=0), "regulation_attempts must be"),
            (lambda: model_based(learning_time=-5.0), "learning_time must be"),
            (lambda: model_based(move_margin=-1.0), "move_margin must be"),
            (
                lambda: ModelBasedCompensator(valve=CHAPTER4_VALVE, process_gain=0.0),
                "process_gain K must be finite and non-zero",
            ),
            (
                lambda: ModelBasedCompensator(valve=ChoudhuryValve(5.0, 1.0), process_gain=0.66),
                "valve must be a HeValve, got ChoudhuryValve",
            ),
        ],
    )
    def test_bad_settings(self, build, message):
        with pytest.raises(ModelSpecError, match=message):
            build()

    def test_fd_above_fs_is_refused_by_the_valve_model(self):
        with pytest.raises(ValveModelError, match=r"fd=2\.0 cannot exceed static friction fs=1\.0"):
            ModelBasedCompensator(valve=HeValve(fs=1.0, fd=2.0), process_gain=0.66)

    def test_durations_shorter_than_a_sample(self):
        with pytest.raises(ModelSpecError, match=r"knocker width=0.2 s is shorter than one sample"):
            run_chapter4(Knocker(amplitude=2.0, width=0.2, period=3.0), compensate_from=0.0)

    @pytest.mark.parametrize(
        "kwargs, message",
        [
            ({"dt": 0.0, "duration": 10.0}, "dt must be"),
            ({"dt": 1.0, "duration": 0.5}, "duration must be at least one sample"),
            ({"dt": 1.0, "duration": 10.0, "compensate_from": -1.0}, "compensate_from must be"),
        ],
    )
    def test_bad_simulation_arguments(self, kwargs, message):
        with pytest.raises(ModelSpecError, match=message):
            simulate_compensated(PROCESS, LOOP, NoCompensation(), **kwargs)
