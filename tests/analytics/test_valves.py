"""Valve models: parameter handling, known answers and the stepping/batch contract."""

import math

import numpy as np
import pytest

from analytics.errors import ValveModelError
from analytics.valves import (
    ChoudhuryValve,
    DeadbandValve,
    HeValve,
    IdealValve,
    KanoValve,
    KarnoppValve,
    StenmanValve,
    ValveModel,
    fsfd_to_sj,
    sj_to_fsfd,
    valve_from_dict,
)

ALL_MODELS: list[ValveModel] = [
    IdealValve(),
    StenmanValve(2.0),
    ChoudhuryValve(4.0, 2.0),
    KanoValve(4.0, 2.0),
    HeValve(3.0, 1.0),
    DeadbandValve(3.0),
    KarnoppValve(2.0, 1.5, fv=0.05, natural_frequency=20.0),
]


def noisy_sine(n: int = 4000, amplitude: float = 6.0, noise: float = 0.3) -> np.ndarray:
    rng = np.random.default_rng(42)
    k = np.arange(n)
    return 50.0 + amplitude * np.sin(2 * np.pi * k / 400) + rng.normal(0, noise, n)


def reversal_travel(op: np.ndarray, mv: np.ndarray) -> list[float]:
    """OP travel from each OP turning point until the valve moves the new way."""
    travels = []
    slope = np.sign(np.diff(op))
    slope[slope == 0] = 1.0  # a flat sample at a peak is not a turning point of its own
    turns = np.flatnonzero(slope[1:] * slope[:-1] < 0) + 1
    for turn in turns:
        direction = slope[turn]
        moved = np.flatnonzero(np.diff(mv[turn:]) * direction > 1e-9)
        if moved.size:
            travels.append(abs(op[turn + 1 + moved[0]] - op[turn]))
    return travels


class TestParameters:
    @pytest.mark.parametrize(("S", "J", "fs", "fd"), [(4, 2, 3, 1), (5, 1, 3, 2), (3, 0, 1.5, 1.5)])
    def test_eq_1_2_both_ways(self, S, J, fs, fd):
        # Thesis Eq. 1.2: fs = (S + J)/2, fd = (S - J)/2
        assert sj_to_fsfd(S, J) == pytest.approx((fs, fd))
        assert fsfd_to_sj(fs, fd) == pytest.approx((S, J))

    def test_he_valve_exposes_equivalent_s_and_j(self):
        valve = HeValve(4.5, 1.5)  # Table 2.3, valve 1
        assert (valve.S, valve.J) == (6.0, 3.0)

    @pytest.mark.parametrize(
        ("build", "message"),
        [
            (lambda: ChoudhuryValve(-1.0, 0.0), "S must be >= 0"),
            (
                lambda: ChoudhuryValve(2.0, 3.0),
                "slip jump J=3.0 cannot exceed the stick band S=2.0",
            ),
            (lambda: KanoValve(math.nan, 1.0), "S must be finite"),
            (lambda: HeValve(1.0, 2.0), "fd=2.0 cannot exceed static friction fs=1.0"),
            (lambda: StenmanValve(-0.5), "d must be >= 0"),
            (lambda: DeadbandValve(math.inf), "deadband must be finite"),
            (lambda: KarnoppValve(1.0, 2.0), "fc_force=2.0 cannot exceed"),
            (
                lambda: KarnoppValve(1.0, 1.0, natural_frequency=0.0),
                "natural_frequency must be > 0",
            ),
            (lambda: sj_to_fsfd(1.0, 2.0), "cannot exceed the stick band"),
            (lambda: ChoudhuryValve("4", 2.0), "S must be a number"),
        ],
    )
    def test_invalid_parameters_are_refused_with_the_reason(self, build, message):
        with pytest.raises(ValveModelError, match=message):
            build()

    def test_nan_in_op_names_the_index(self):
        op = np.array([1.0, 2.0, np.nan, 3.0])
        with pytest.raises(ValveModelError, match="first at index 2"):
            HeValve(1.0, 0.5).simulate(op)
        with pytest.raises(ValveModelError, match="OP must be finite"):
            HeValve(1.0, 0.5).stepper(0.0).step(math.nan)

    def test_from_dict_round_trip_and_errors(self):
        for model in ALL_MODELS:
            assert valve_from_dict(model.to_dict()) == model
        assert valve_from_dict(None) == IdealValve()
        with pytest.raises(ValveModelError, match="unknown valve model 'sticky'"):
            valve_from_dict({"model": "sticky"})
        with pytest.raises(ValveModelError, match="missing 1 required positional argument: 'J'"):
            valve_from_dict({"model": "choudhury", "S": 4})
        with pytest.raises(ValveModelError, match="needs a 'model' key"):
            valve_from_dict({"S": 4, "J": 2})


class TestStepAndBatchAgree:
    @pytest.mark.parametrize("model", ALL_MODELS, ids=lambda m: m.name)
    def test_stepper_reproduces_simulate(self, model):
        op = noisy_sine()
        batch = model.simulate(op, dt=0.5)
        stepper = model.stepper(op[0], dt=0.5)
        stepped = np.array([stepper.step(x) for x in op])
        np.testing.assert_array_equal(batch, stepped)
        assert stepper.position == batch[-1]

    def test_empty_series(self):
        assert HeValve(1, 1).simulate([]).size == 0


class TestKnownAnswers:
    def test_ideal_valve_is_the_identity(self):
        op = noisy_sine()
        np.testing.assert_array_equal(IdealValve().simulate(op), op)

    def test_stenman_errata_form(self):
        # ERRATA item 2: y_k = y_{k-1} if |u_k - y_{k-1}| < d else u_k
        op = [0.0, 1.0, 1.9, 2.0, 1.0, -0.5, 0.1]
        assert StenmanValve(2.0).simulate(op).tolist() == [0.0, 0.0, 0.0, 2.0, 2.0, -0.5, -0.5]

    def test_he_model_slips_in_steps_of_fs_minus_fd_on_a_slow_ramp(self):
        # He et al. (2007): a slowly rising input makes the valve climb in slips of fs - fd
        op = np.linspace(0.0, 20.0, 20001)
        mv = HeValve(3.0, 1.0).simulate(op)
        jumps = np.diff(mv)[np.diff(mv) != 0]
        assert jumps.size > 5
        np.testing.assert_allclose(jumps[1:], 2.0, atol=2e-3)
        assert np.all(op - mv <= 3.0 + 1e-9)
        assert np.all(op[op > 3.0] - mv[op > 3.0] >= 1.0 - 1e-9)

    @pytest.mark.parametrize("cls", [ChoudhuryValve, KanoValve])
    def test_choudhury_and_kano_signature_on_a_sine(self, cls):
        # Choudhury et al. (2005), Fig. 4: after each reversal the valve sticks for S
        # of OP travel, slips by J, then follows OP with a lag of (S - J)/2.
        S, J = 5.0, 2.0
        k = np.arange(40000)
        op = 10.0 * np.sin(2 * np.pi * k / 10000)
        mv = cls(S, J).simulate(op)
        late = k > 12000
        travels = reversal_travel(op[late], mv[late])
        assert len(travels) == 6
        assert travels == pytest.approx([S] * 6, abs=0.02)
        jumps = np.abs(np.diff(mv[late]))
        assert jumps.max() == pytest.approx(J + np.abs(np.diff(op)).max(), abs=0.02)
        moving = late[1:] & (np.diff(mv) != 0) & (np.abs(np.diff(mv)) < 0.5)
        lag = np.abs(op[1:][moving] - mv[1:][moving])
        np.testing.assert_allclose(lag, (S - J) / 2, atol=1e-9)

    def test_deadband_lags_half_the_band_and_never_jumps(self):
        op = 10.0 * np.sin(2 * np.pi * np.arange(20000) / 5000)
        mv = DeadbandValve(4.0).simulate(op)
        assert np.abs(np.diff(mv)).max() <= np.abs(np.diff(op)).max() + 1e-12
        assert np.abs(op - mv).max() == pytest.approx(2.0, abs=1e-9)
        assert reversal_travel(op[6000:], mv[6000:]) == pytest.approx([4.0] * 6, abs=0.02)

    def test_kano_keeps_its_stop_point_under_noise_where_choudhury_resets_it(self):
        # Kano et al. (2004) fix the stop point; Choudhury's model moves it to every
        # OP turning point, so a noisy ramp keeps a Choudhury valve stuck longer.
        rng = np.random.default_rng(1)
        op = np.linspace(0.0, 12.0, 3000) + rng.normal(0.0, 0.2, 3000)
        moves_kano = np.count_nonzero(np.diff(KanoValve(4.0, 1.0).simulate(op)))
        moves_choudhury = np.count_nonzero(np.diff(ChoudhuryValve(4.0, 1.0).simulate(op)))
        kano_mv = KanoValve(4.0, 1.0).simulate(op)
        assert kano_mv[-1] > 5.0  # the Kano valve followed the ramp
        assert moves_kano > moves_choudhury

    def test_karnopp_without_friction_settles_at_op(self):
        valve = KarnoppValve(0.0, 0.0, fv=0.1, natural_frequency=10.0)
        mv = valve.simulate(np.full(200, 60.0), dt=0.1, initial_position=50.0)
        assert mv[-1] == pytest.approx(60.0, abs=1e-3)

    def test_karnopp_breaks_away_after_static_plus_coulomb_travel(self):
        # A stuck stem moves once the net force exceeds static friction; coming
        # from sliding, where it rested Coulomb friction away from OP, the OP
        # travel after a reversal is fs_force + fc_force (the stick band S).
        fs_force, fc_force = 2.0, 1.0
        valve = KarnoppValve(fs_force, fc_force, fv=0.5, natural_frequency=30.0)
        k = np.arange(40000)
        op = 10.0 * np.sin(2 * np.pi * k / 10000)
        mv = valve.simulate(op, dt=0.01)
        travels = reversal_travel(op[12000:], mv[12000:])
        assert travels == pytest.approx([fs_force + fc_force] * 6, abs=0.1)

    def test_initial_position_defaults_to_first_op(self):
        mv = ChoudhuryValve(4.0, 2.0).simulate([30.0, 31.0, 33.1])
        assert mv.tolist() == [30.0, 30.0, 33.1 - 1.0]
