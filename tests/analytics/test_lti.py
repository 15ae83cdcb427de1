"""Tests of analytics.lti against analytic responses and scipy.signal."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import scipy.linalg
import scipy.signal

from analytics.errors import ModelSpecError
from analytics.lti import (
    TransferFunction,
    discretise,
    exact_expm,
    process_gain,
    simulate_open_loop,
)

G33 = TransferFunction.lead_lag(0.87, 11.61, 3.89, 18.8, theta=1.0)


def _step_samples(tf: TransferFunction, dt: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    t = dt * np.arange(n)
    return t, simulate_open_loop(tf, np.ones(n), dt)


@pytest.mark.parametrize(
    ("theta", "dt", "fractional"),
    [(0.0, 0.1, False), (3.0, 0.5, False), (0.3, 0.1, False), (0.25, 0.1, True), (1.37, 0.2, True)],
)
def test_fopdt_step_is_exact(theta: float, dt: float, fractional: bool) -> None:
    K, tau = 2.5, 1.7
    tf = TransferFunction.fopdt(K, tau, theta)
    assert discretise(tf, dt).fractional is fractional
    t, y = _step_samples(tf, dt, 200)
    expected = K * (1.0 - np.exp(-np.maximum(t - theta, 0.0) / tau))
    np.testing.assert_allclose(y, expected, rtol=0, atol=1e-10)
    assert np.all(y[t < theta - 1e-12] == 0.0)


@pytest.mark.parametrize("theta", [0.0, 0.6, 0.45])
def test_integrating_ramp(theta: float) -> None:
    K, dt = -0.8, 0.15
    t, y = _step_samples(TransferFunction.integrating(K, theta), dt, 100)
    np.testing.assert_allclose(y, K * np.maximum(t - theta, 0.0), rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.diff(y[t > theta + dt]) / dt, K, rtol=1e-10)


def test_second_order_step_analytic() -> None:
    K, tau1, tau2, theta, dt = 1.3, 4.0, 1.5, 0.7, 0.2
    t, y = _step_samples(TransferFunction.second_order(K, tau1, tau2, theta), dt, 300)
    s = np.maximum(t - theta, 0.0)
    expected = K * (1 - (tau1 * np.exp(-s / tau1) - tau2 * np.exp(-s / tau2)) / (tau1 - tau2))
    np.testing.assert_allclose(y, expected, rtol=0, atol=1e-10)


@pytest.mark.parametrize(
    "tf",
    [
        G33,
        TransferFunction.underdamped(1.2, 0.9, 0.3, theta=0.55),
        TransferFunction.second_order(-0.5, 2.0, 0.3, theta=2.0),
    ],
)
@pytest.mark.parametrize("dt", [0.1, 0.3])
def test_step_matches_scipy_step(tf: TransferFunction, dt: float) -> None:
    # scipy's step starts at T[0] = 0 on a uniform grid: use a grid of h = 0.05 s,
    # on which every delayed sampling instant t_k - theta of these cases lies.
    t, y = _step_samples(tf, dt, 400)
    after = t >= tf.delay
    h = 0.05
    idx = np.round((t[after] - tf.delay) / h).astype(int)
    _, ref = scipy.signal.step((tf.num, tf.den), T=h * np.arange(idx[-1] + 1))
    np.testing.assert_allclose(y[after], ref[idx], rtol=0, atol=1e-9)
    assert np.all(y[~after] == 0.0)


def test_biproper_output_is_left_limit() -> None:
    # 2 (5 s + 1) / (s + 1): jumps to 10 at t = theta, then decays to 2.
    K, lead, lag, dt = 2.0, 5.0, 1.0, 0.1
    for theta, first in [(0.3, 4), (0.25, 3)]:
        tf = TransferFunction.lead_lag(K, lead, lag, theta=theta)
        assert math.isclose(discretise(tf, dt).D, K * lead / lag)
        t, y = _step_samples(tf, dt, 80)
        s = t - theta
        expected = np.where(s > 1e-12, K * (1 - (1 - lead / lag) * np.exp(-s / lag)), 0.0)
        np.testing.assert_allclose(y, expected, rtol=0, atol=1e-10)
        assert y[first - 1] == 0.0 and y[first] > K


def test_sinusoid_matches_fine_lsim() -> None:
    # The ZOH staircase and the delay are exact on a 10x finer grid, so lsim
    # with interp=False (itself exact for piecewise-constant input) is a reference.
    tf = TransferFunction.underdamped(1.5, 1.1, 0.25, theta=0.37)
    dt, sub, n = 0.1, 10, 400
    u = np.sin(0.7 * dt * np.arange(n)) + 0.3 * np.cos(2.3 * dt * np.arange(n))
    y = simulate_open_loop(tf, u, dt)

    shift = round(tf.delay / (dt / sub))
    j = np.arange(n * sub)
    u_fine = np.where(j >= shift, u[np.maximum(j - shift, 0) // sub], 0.0)
    _, y_fine, _ = scipy.signal.lsim((tf.num, tf.den), u_fine, j * (dt / sub), interp=False)
    np.testing.assert_allclose(y, y_fine[::sub], rtol=0, atol=1e-9)


def test_fopdt_frequency_response_analytic() -> None:
    K, tau, theta = 3.0, 2.0, 0.8
    w = np.logspace(-3, 2, 200)
    g = TransferFunction.fopdt(K, tau, theta).frequency_response(w)
    np.testing.assert_allclose(np.abs(g), K / np.sqrt(1 + (w * tau) ** 2), rtol=1e-12)
    phase = -np.arctan(w * tau) - w * theta
    np.testing.assert_allclose(g, np.abs(g) * np.exp(1j * phase), rtol=1e-12)


@pytest.mark.parametrize("dt", [0.1, 0.3, 0.37])
def test_discrete_frequency_response_low_frequency(dt: float) -> None:
    # At low frequency the sampled model is G(jw) with the hold's half-sample lag.
    w = np.array([1e-4, 1e-3, 1e-2]) / dt
    h = discretise(G33, dt).frequency_response(w)
    np.testing.assert_allclose(h, G33.frequency_response(w) * np.exp(-0.5j * w * dt), rtol=1e-4)


@pytest.mark.parametrize(
    "tf",
    [TransferFunction.fopdt(2.0, 0.5, 0.33), TransferFunction.lead_lag(2.0, 3.0, 0.5, theta=0.3)],
)
def test_discrete_frequency_response_is_steady_state_gain(tf: TransferFunction) -> None:
    # A sampled sinusoid through the recursion settles to |H| and arg H.
    dt, w = 0.1, 2.0
    k = np.arange(3000)
    y = simulate_open_loop(tf, np.sin(w * dt * k), dt)
    h = discretise(tf, dt).frequency_response(w)
    np.testing.assert_allclose(y[-500:], np.imag(h * np.exp(1j * w * dt * k[-500:])), atol=1e-9)


def test_model_properties() -> None:
    assert G33.dc_gain == pytest.approx(0.87)
    assert G33.is_stable and not G33.is_integrating
    integ = TransferFunction.integrating(-2.0, 1.0)
    assert integ.is_integrating and not integ.is_stable and integ.dc_gain == -math.inf
    assert sorted(G33.poles().real) == pytest.approx([-1 / 3.89, -1 / 18.8])
    # A cancelled factor s is not an integrator.
    assert not TransferFunction((1.0, 0.0), (1.0, 1.0, 0.0)).is_integrating
    assert not TransferFunction.underdamped(1.0, 2.0, 0.0).is_stable
    assert TransferFunction((1.0, 0.0), (1.0, 1.0)).dc_gain == 0.0
    assert TransferFunction((0.0,), (1.0, 1.0)).dc_gain == 0.0


def test_pure_gain_with_delay() -> None:
    tf = TransferFunction((3.0,), (1.0,), delay=0.25)
    np.testing.assert_array_equal(simulate_open_loop(tf, np.ones(5), 0.1), [0, 0, 0, 3, 3])
    assert tf.dc_gain == 3.0 and tf.is_stable


def test_dict_round_trip() -> None:
    spec = {
        "type": "lead_lag",
        "K": 0.87,
        "tau_lead": 11.61,
        "tau_lag1": 3.89,
        "tau_lag2": 18.8,
        "theta": 1.0,
    }
    assert TransferFunction.from_dict(spec) == G33
    assert TransferFunction.from_dict(G33.to_dict()) == G33
    assert TransferFunction.from_dict({"type": "fopdt", "K": 1, "tau": 2}).delay == 0.0
    assert TransferFunction.from_dict({"type": "integrating", "K": 2, "theta": 3}).den == (1, 0)


@pytest.mark.parametrize(
    ("build", "name"),
    [
        (lambda: TransferFunction.fopdt(1.0, 0.0), "tau"),
        (lambda: TransferFunction.fopdt(1.0, -2.0), "tau"),
        (lambda: TransferFunction.second_order(1.0, 1.0, -1.0), "tau2"),
        (lambda: TransferFunction.fopdt(1.0, 1.0, theta=-0.1), "theta"),
        (lambda: TransferFunction((1.0,), (1.0, math.nan)), "den"),
        (lambda: TransferFunction((math.inf,), (1.0, 1.0)), "num"),
        (lambda: TransferFunction((1.0, 2.0, 3.0), (1.0, 1.0)), "improper"),
        (lambda: TransferFunction((1.0,), (0.0, 1.0)), "den"),
        (lambda: TransferFunction((1.0,), ()), "den"),
        (lambda: TransferFunction((1.0,), (1.0, 1.0), delay=-1.0), "delay"),
        (lambda: discretise(TransferFunction.fopdt(1.0, 1.0), 0.0), "dt"),
        (lambda: TransferFunction.from_dict({"type": "foo", "K": 1}), "foo"),
        (lambda: TransferFunction.from_dict({"type": "fopdt", "K": 1}), "tau"),
        (lambda: TransferFunction.from_dict({"num": [1]}), "den"),
        (
            lambda: TransferFunction.from_dict({"type": "fopdt", "K": 1, "tau": 1, "delay": 2}),
            "delay",
        ),
        (lambda: TransferFunction.from_dict({"type": "fopdt", "K": "x", "tau": 1}), "K"),
    ],
)
def test_validation_errors(build: Callable[[], Any], name: str) -> None:
    with pytest.raises(ModelSpecError, match=name):
        build()


@pytest.mark.parametrize(("model", "expected"), [
    (TransferFunction.fopdt(-2.36, 5.0, 3.0), ("self-regulating", -2.36)),
    (TransferFunction.lead_lag(0.87, 11.61, 3.89, 18.8, 1.0), ("self-regulating", 0.87)),
    (TransferFunction.integrating(0.02, 4.0), ("integrating", 0.02)),
    (TransferFunction((0.5,), (10.0, 1.0, 0.0), 1.0), ("integrating", 0.5)),
])
def test_process_gain_is_the_steady_state_or_the_integrating_gain(
        model: TransferFunction, expected: tuple[str, float]) -> None:
    kind, gain = process_gain(model)
    assert (kind, gain) == (expected[0], pytest.approx(expected[1]))


@pytest.mark.parametrize("model", [TransferFunction((1.0,), (1.0, 0.0, 0.0)),
                                   TransferFunction((1.0, 0.0), (5.0, 1.0))])
def test_process_gain_refuses_models_without_one(model: TransferFunction) -> None:
    with pytest.raises(ModelSpecError):
        process_gain(model)


def test_exact_expm_of_a_rotation_is_cos_and_sin() -> None:
    for angle in (1e-6, 0.3, 2.0, 40.0):
        rotation = exact_expm(np.array([[0.0, -angle], [angle, 0.0]]))
        c, s = math.cos(angle), math.sin(angle)
        np.testing.assert_allclose(rotation, [[c, -s], [s, c]], rtol=0, atol=1e-12)


def test_exact_expm_matches_scipy() -> None:
    rng = np.random.default_rng(3)
    for order in (1, 2, 3, 5):
        for scale in (0.01, 1.0, 10.0):
            a = rng.normal(size=(order, order)) * scale
            expected = scipy.linalg.expm(a)
            np.testing.assert_allclose(exact_expm(a), expected, rtol=0,
                                       atol=1e-11 * np.abs(expected).max())


_DISCRETISED_COLUMN = """
import hashlib
import numpy as np
from analytics.lti import discretise
from analytics.scenarios import column3x3
model = column3x3(sticky=(2,), duration=600.0)
entries = [discretise(g, model.dt) for row in model.process for g in row if g is not None]
run = model.run()
parts = [x for e in entries for x in (e.Ad, e.B0, e.B1)] + [run.op, run.pv]
print(hashlib.sha256(b"".join(np.ascontiguousarray(x).tobytes() for x in parts)).hexdigest())
"""


def _avx2() -> bool:
    try:
        with open("/proc/cpuinfo") as info:
            return " avx2" in info.read()
    except OSError:
        return False


@pytest.mark.skipif(not _avx2(), reason="OpenBLAS's Haswell kernels need an x86-64 CPU with AVX2")
def test_discretisation_and_simulation_do_not_depend_on_the_blas_kernel() -> None:
    # The stick-slip column amplifies a last-bit difference in Ad into another cycle
    # (178 s against 200 s): scipy.linalg.expm through OpenBLAS's Haswell kernels gave
    # other bits than through its Sandybridge ones.
    digests = set()
    for kernel in ("Sandybridge", "Haswell"):
        env = {**os.environ, "OPENBLAS_CORETYPE": kernel}
        done = subprocess.run([sys.executable, "-c", _DISCRETISED_COLUMN], env=env, check=True,
                              capture_output=True, text=True, timeout=300)
        digests.add(done.stdout.strip())
    assert len(digests) == 1
