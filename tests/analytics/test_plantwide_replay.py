"""The time-domain replay of candidate sticky sets (analytics.plantwide.replay).

References used by the checks:

* the exact zero-order-hold recursion of analytics.lti.simulate_open_loop (the
  filters of the replay must be the same map from valve output to PV);
* the simulated 3x3 column of thesis section 2.4 (Eq. 2.10, tunings 2.11-2.13, He
  valves of Table 2.3, S = fs + fd), whose valve outputs and sticky valves are known.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import lfilter

from analytics.errors import ModelSpecError
from analytics.lti import TransferFunction, discretise, simulate_open_loop
from analytics.plantwide.replay import (
    _polynomials,
    _Problem,
    _set_misfit,
    _shifted,
    _slip_directions,
    _turning_points,
    replay_sticky_sets,
)
from analytics.scenarios import column3x3


def late_signals(model):
    run = model.run()
    late = run.t >= 2000.0
    return run, late


@pytest.mark.parametrize("tf", [
    TransferFunction.fopdt(-33.68, 8.15, 9.2),  # fractional dead time at 0.5 s
    TransferFunction.fopdt(0.66, 6.7, 2.5),  # whole samples
    TransferFunction.lead_lag(0.87, 11.61, 3.89, 18.8, 1.0),
])
def test_replay_filters_are_the_exact_sampled_model(tf):
    u = np.random.default_rng(3).standard_normal(400).cumsum()
    b, a = _polynomials(discretise(tf, 0.5))
    assert np.allclose(lfilter(b, a, u), simulate_open_loop(tf, u, 0.5), atol=1e-9)


def test_turning_points_of_a_triangle_are_its_extremes():
    k = np.arange(1000)
    triangle = np.abs((k % 100) - 50.0)  # maxima at 0, 100, ...; minima at 50, 150, ...
    index, direction = _turning_points(triangle + 0.01 * np.sin(k), 10.0)
    assert list(index[:4]) == [50, 100, 150, 200]
    assert list(direction[:4]) == [-1.0, 1.0, -1.0, 1.0]


def test_shifted_slips_keep_their_directions_and_take_the_op_there():
    op = np.linspace(0.0, 10.0, 101)
    jump = _slip_directions(np.repeat([0.0, 1.0, 0.0], [30, 40, 31]))
    base, moved = _shifted(op, jump, 2)
    assert list(np.flatnonzero(np.diff(moved)) + 1) == [32, 72]
    assert base[40] == op[32] and base[80] == op[72]


@pytest.mark.slow
def test_the_simulated_valve_outputs_fit_the_pvs_to_their_noise():
    # With the true valve outputs (the simulated MV) the residual is the measurement noise
    # alone (std 0.1 in every PV): the misfit in noise-variance units is about its samples,
    # somewhat fewer since the noise is read from the PVs' differences, which carry the
    # PVs' own moves too (0.69 of the samples here).
    model = column3x3(sticky=(1, 2), seed=7)
    run, late = late_signals(model)
    problem = _Problem(list(run.op[:, late]), list(run.pv[:, late]), model.process, 0.5)
    samples = problem.n * problem.rows[0].target.size
    truth = _set_misfit(problem, {0: run.mv[0][late], 1: run.mv[1][late]})
    healthy = _set_misfit(problem, {})
    assert 0.5 * samples < truth < 1.1 * samples
    assert healthy > 100 * samples


STICKY_SETS = ((1,), (2,), (3,), (1, 2), (1, 3), (2, 3), (1, 2, 3))
TRUE_S = {1: 6.0, 2: 4.0, 3: 5.0}  # Table 2.3, S = fs + fd


@pytest.fixture(scope="module")
def replayed():
    # Seed 7: none of the calibration seeds 100-103 the penalty was chosen on.
    found = {}
    for sticky in STICKY_SETS:
        run, late = late_signals(column3x3(sticky=sticky, seed=7))
        unit = {name: (run.op[i][late], run.pv[i][late]) for i, name in enumerate(run.names)}
        found[sticky] = replay_sticky_sets(unit, 0.5, column3x3().process)
    return found


@pytest.mark.slow
@pytest.mark.parametrize("sticky", STICKY_SETS)
def test_replay_names_every_simulated_sticky_set(replayed, sticky):
    # Issue 22 (and the fingerprint's xfails for valve 3 alone and beside valve 2).
    assert replayed[sticky].sticky_valves == tuple(f"loop{i}" for i in sticky)


@pytest.mark.slow
@pytest.mark.parametrize("sticky", [
    *(s for s in STICKY_SETS if s != (3,)),
    pytest.param((3,), marks=pytest.mark.xfail(
        strict=True, reason="valve 3 alone follows a wide OP swing in small slips (14 % "
        "on seeds 100-101): its replay runs free, and its S (3.7 against 5) is that of "
        "the nearest point of the coarse (fs, fd) grid, not fitted further")),
])
def test_replay_sizes_the_named_valves_within_25_percent(replayed, sticky):
    fit = replayed[sticky].fit_of(tuple(f"loop{i}" for i in sticky))
    assert fit is not None
    for i, s in zip(sticky, fit.S, strict=True):
        assert abs(s - TRUE_S[i]) <= 0.25 * TRUE_S[i]


def test_a_matrix_of_the_wrong_size_is_refused():
    unit = {"a": (np.zeros(3000), np.zeros(3000)), "b": (np.zeros(3000), np.zeros(3000))}
    with pytest.raises(ModelSpecError, match="2 x 2"):
        replay_sticky_sets(unit, 0.5, [[TransferFunction.fopdt(1.0, 5.0, 1.0)]])
