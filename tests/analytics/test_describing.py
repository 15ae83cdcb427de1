"""Tests of analytics.describing against ERRATA item 1, thesis Table 5.1 / Fig. 5.2,
closed-form harmonics and the simulated valve models of analytics.valves."""

from __future__ import annotations

import math

import numpy as np
import pytest

from analytics.describing import (
    analytic_sj,
    choudhury_df,
    df_curve,
    negative_inverse_df,
    numerical_df,
    table_5_1_limits,
    valve_describing_function,
)
from analytics.errors import ValveModelError
from analytics.valves import (
    ChoudhuryValve,
    DeadbandValve,
    HeValve,
    KanoValve,
    KarnoppValve,
    StenmanValve,
    sj_to_fsfd,
)

ERRATA_N = 0.876 - 0.255j  # ERRATA item 1: S=4, J=2, A=5


def test_errata_value_analytic_and_simulated() -> None:
    analytic = complex(choudhury_df(5.0, 4.0, 2.0))
    simulated = complex(numerical_df(ChoudhuryValve(4.0, 2.0), 5.0))
    assert abs(analytic - ERRATA_N) < 0.005
    assert abs(simulated - ERRATA_N) < 0.005
    assert abs(simulated - analytic) < 1e-3


@pytest.mark.parametrize("model", [ChoudhuryValve, KanoValve])
@pytest.mark.parametrize(
    ("S", "J", "A"),
    [
        (4.0, 2.0, 5.0),
        (4.0, 2.0, 2.1),  # just above S/2, below (S + J)/2
        (4.0, 0.0, 3.0),  # deadband
        (4.0, 0.0, 200.0),
        (4.0, 4.0, 3.0),  # J = S
        (4.0, 4.0, 2.01),
        (1.0, 0.5, 0.52),
        (10.0, 3.0, 40.0),
    ],
)
def test_analytic_matches_simulated_limit_cycle(
    model: type[ChoudhuryValve], S: float, J: float, A: float
) -> None:
    simulated = complex(numerical_df(model(S, J), A, samples_per_period=4096))
    assert simulated != 0
    assert abs(simulated - complex(choudhury_df(A, S, J))) < 1e-3


def test_deadband_valve_is_choudhury_with_zero_jump() -> None:
    A = np.geomspace(1.0001, 300.0, 25)
    simulated = numerical_df(DeadbandValve(2.0), A)
    np.testing.assert_allclose(simulated, choudhury_df(A, 2.0, 0.0), rtol=0, atol=1e-6)


def test_no_motion_below_half_band_and_ideal_valve() -> None:
    np.testing.assert_array_equal(choudhury_df([0.5, 1.0, 2.0], 4.0, 2.0), 0)
    for valve in (KanoValve(4.0, 2.0), HeValve(3.0, 1.0)):
        np.testing.assert_array_equal(numerical_df(valve, [1.0, 1.9, 2.0]), 0)
    np.testing.assert_array_equal(choudhury_df([0.1, 7.0], 0.0, 0.0), 1)
    assert choudhury_df(np.ones((2, 3)), 1.0, 0.5).shape == (2, 3)


@pytest.mark.parametrize(("S", "J"), [(4.0, 1.0), (4.0, 2.0), (2.0, 2.0), (6.0, 3.0)])
def test_table_5_1_limits(S: float, J: float) -> None:
    small = complex(negative_inverse_df(choudhury_df(S / 2 * (1 + 1e-6), S, J)))
    large = complex(negative_inverse_df(choudhury_df(1e4 * S, S, J)))
    expected_small = -1j * math.pi * S / (4 * J)
    assert abs(small - expected_small) < 0.01 * abs(expected_small)
    assert abs(large - (-1.0)) < 1e-3
    limits = table_5_1_limits(S, J)
    assert limits["A->S/2"] == pytest.approx(expected_small)
    assert limits["A->inf"] == -1


def test_deadband_curve_fig_5_2() -> None:
    S = 4.0
    eps = np.geomspace(1e-8, 1e4, 4001)
    curve = negative_inverse_df(choudhury_df(S / 2 * (1 + eps), S, 0.0))
    assert np.all(curve.imag < 0)
    assert np.all(curve.real <= -1)  # never near the right half plane, and left of -1
    # Goes to -j infinity as A -> S/2: |imag| grows without bound and dominates.
    near = curve[[0, 400, 800]]  # eps = 1e-8, 1e-7, 1e-6
    assert near[0].imag < near[1].imag < near[2].imag < -1e5
    assert abs(near[0].imag) > 1e3 * abs(near[0].real)
    assert abs(curve[-1] - (-1.0)) < 1e-3
    assert table_5_1_limits(S, 0.0)["A->S/2"] == complex(-math.inf, -math.inf)


def test_stiction_curve_ends_on_negative_imaginary_axis() -> None:
    S, J = 4.0, 1.0
    eps = np.geomspace(1e-10, 1e3, 2000)
    curve = negative_inverse_df(choudhury_df(S / 2 * (1 + eps), S, J))
    assert np.all(curve.real < 0)
    assert abs(curve[0].real) < 1e-3
    assert curve[0].imag == pytest.approx(-math.pi, rel=1e-3)


def test_gain_and_phase() -> None:
    A = 0.5 * (1 + np.geomspace(1e-9, 1e4, 5000))
    for J in (0.0, 0.25, 0.5, 0.75, 1.0):
        phase = np.angle(choudhury_df(A, 1.0, J))
        assert np.all((phase > -math.pi / 2) & (phase <= 0))
    for J in (0.0, 0.25, 0.5):
        assert np.all(np.abs(choudhury_df(A, 1.0, J)) <= 1)


def test_choudhury_valve_does_not_move_below_half_band() -> None:
    # Below A = S/2 OP never travels S from a turning point: the valve must stay put
    # (a moving stick point once threw it back against OP, 0.9 -> 0.34 at A = 1.9).
    np.testing.assert_array_equal(numerical_df(ChoudhuryValve(4.0, 2.0), [1.9]), 0)


def test_full_slip_jump_amplifies_like_a_square_wave() -> None:
    # J = S at A -> S/2: the valve sits at +-A and jumps at the OP extremes, a
    # square wave of amplitude A lagging by 90 deg, fundamental 4A/pi.
    analytic = complex(choudhury_df(2.0 * (1 + 1e-9), 4.0, 4.0))
    assert analytic == pytest.approx(-4j / math.pi, abs=1e-3)
    simulated = complex(numerical_df(ChoudhuryValve(4.0, 4.0), 2.00001))
    assert abs(simulated) > 1.2
    assert simulated == pytest.approx(-4j / math.pi, abs=0.01)


def test_negative_inverse_of_zero_is_nan() -> None:
    result = negative_inverse_df([0.0, 0.5 - 0.5j])
    assert np.isnan(result[0].real) and np.isnan(result[0].imag)
    assert result[1] == pytest.approx(-1 - 1j)


@pytest.mark.parametrize(("fs", "fd"), [(4.5, 1.5), (3.0, 1.0), (4.0, 1.0)])  # thesis Table 2.3
def test_he_valve_is_a_deadband_of_width_fs_plus_fd_not_choudhury(fs: float, fd: float) -> None:
    # On a fine grid He's valve slips in steps J = fs - fd with y - OP in
    # [fd, fs]: within J/2 of a deadband of width S = fs + fd, so the
    # fundamentals differ by at most (2/pi) (J/2) * 2 / A = 2J/(pi A).
    S, J = fs + fd, fs - fd
    A = S * np.array([0.8, 1.25, 2.5, 12.5])
    he = numerical_df(HeValve(fs, fd), A)
    assert np.all(he != 0)
    assert np.all(np.abs(he - choudhury_df(A, S, 0.0)) <= 2 * J / (np.pi * A))
    choudhury = choudhury_df(A, S, J)
    assert np.all(np.abs(he) < np.abs(choudhury))
    assert np.abs(he - choudhury)[1] > 0.1


def test_he_without_slip_jump_is_the_deadband() -> None:
    A = np.array([1.6, 3.0, 20.0])
    np.testing.assert_allclose(
        numerical_df(HeValve(*sj_to_fsfd(3.0, 0.0)), A), choudhury_df(A, 3.0, 0.0), atol=1e-6
    )


def test_karnopp_without_stick_slip_tends_to_deadband() -> None:
    # fs_force = fc_force, fv = 0: quasi-statically (omega << wn) the stem rests
    # while |OP - x| <= fc and otherwise slides with x = OP - fc sign(v), a
    # deadband of width 2 fc; the stem dynamics add an error of order omega/wn.
    valve = KarnoppValve(fs_force=2.0, fc_force=2.0, fv=0.0, natural_frequency=20.0)
    A = np.array([3.0, 5.0, 10.0, 50.0])
    deadband = choudhury_df(A, 4.0, 0.0)
    slow = np.abs(numerical_df(valve, A, omega=0.1) - deadband).max()
    fast = np.abs(numerical_df(valve, A, omega=1.0) - deadband).max()
    assert slow < 5e-3
    assert fast > 2 * slow


def test_only_physics_model_depends_on_frequency() -> None:
    valve = ChoudhuryValve(4.0, 1.0)
    np.testing.assert_array_equal(
        numerical_df(valve, [3.0, 9.0], omega=1.0), numerical_df(valve, [3.0, 9.0], omega=7.0)
    )


def test_df_curve() -> None:
    A, N = df_curve(KanoValve(4.0, 2.0))
    assert A.shape == N.shape == (200,)
    assert A[0] == pytest.approx(2.002) and A[-1] == pytest.approx(200.0)
    np.testing.assert_array_equal(N, choudhury_df(A, 4.0, 2.0))
    A, N = df_curve(HeValve(3.0, 1.0), [3.0, 5.0])
    np.testing.assert_array_equal(N, numerical_df(HeValve(3.0, 1.0), [3.0, 5.0]))
    assert np.all(np.abs(N - choudhury_df(A, 4.0, 2.0)) > 0.2)


@pytest.mark.parametrize(
    ("S", "J"), [(-1.0, 0.0), (2.0, 3.0), (math.nan, 0.0), (4.0, math.nan), (math.inf, 1.0)]
)
def test_invalid_parameters(S: float, J: float) -> None:
    with pytest.raises(ValveModelError):
        choudhury_df(3.0, S, J)
    with pytest.raises(ValveModelError):
        table_5_1_limits(S, J)


@pytest.mark.parametrize("A", [0.0, -1.0, math.nan, [1.0, math.inf]])
def test_invalid_amplitudes(A: object) -> None:
    with pytest.raises(ValveModelError):
        choudhury_df(A, 4.0, 2.0)  # type: ignore[arg-type]
    with pytest.raises(ValveModelError):
        numerical_df(ChoudhuryValve(4.0, 2.0), A)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "kwargs", [{"omega": 0.0}, {"omega": math.nan}, {"samples_per_period": 8}, {"periods": 1}]
)
def test_invalid_simulation_settings(kwargs: dict[str, float]) -> None:
    with pytest.raises(ValveModelError):
        numerical_df(ChoudhuryValve(4.0, 2.0), 3.0, **kwargs)  # type: ignore[arg-type]


def test_stiction_df_slope_is_the_derivative_of_the_df() -> None:
    """The closed-form dN/dA the solvers use against central differences of Eq. 3.4."""
    S, J = 4.0, 1.5
    amplitudes = S / 2 * (1 + np.geomspace(1e-3, 1e4, 15))
    step = 1e-6 * amplitudes
    numerical = (choudhury_df(amplitudes + step, S, J) - choudhury_df(amplitudes - step, S, J)) / (
        2 * step
    )
    df = valve_describing_function(ChoudhuryValve(S, J))
    np.testing.assert_allclose(df.slope(amplitudes), numerical, rtol=1e-5)


@pytest.mark.parametrize(("valve", "model", "equivalent"), [
    (KanoValve(4.0, 2.0), (4.0, 2.0), (4.0, 2.0)),
    (HeValve(3.0, 1.0), None, (4.0, 2.0)),  # S = fs + fd, J = fs - fd (ERRATA item 6)
    (DeadbandValve(2.0), None, (2.0, 0.0)),
    (StenmanValve(1.5), None, (1.5, 1.5)),
])
def test_one_place_decides_which_describing_function_a_valve_gets(valve, model, equivalent):
    """The analytic (S, J) DF for the (S, J) models, the numerical one for the others
    unless their equivalent is asked for; df_curve and the solvers agree."""
    assert analytic_sj(valve, "model") == model
    assert analytic_sj(valve, "equivalent") == equivalent
    # The solvers tabulate a numerical DF and interpolate it: at its own points it is df_curve's.
    amplitudes, minus_inverse = valve_describing_function(valve, "model").table()
    amplitudes, minus_inverse = amplitudes[::20], minus_inverse[::20]
    _, curve = df_curve(valve, amplitudes)
    np.testing.assert_allclose(-1.0 / minus_inverse, curve, rtol=1e-9)
