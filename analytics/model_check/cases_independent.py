"""A second, independent generator of loops with hidden effects (issue 21): the held-out set.

:mod:`analytics.model_check.cases` is the generator the model check was
developed on.  This one was written apart from it, to score the check on
loops it was not tuned on, and differs in every choice it can:

* its own closed-loop simulator (a plain Python loop over the valve kernel
  :func:`analytics.valves.valve_step`, the process updated in closed form),
  not :meth:`LoopModel.simulate`;
* valves of Kano's model as well as He's and Choudhury's, or healthy;
* sampling intervals of 0.5, 1 and 2 s; lambda (IMC) tuning instead of SIMC;
* coloured measurement noise (AR(1), coefficient 0-0.8) on a slow drift
  (a random walk whose spread is 0.3-1 times the noise's);
* set-point schedules of steps or ramps at irregular intervals;
* an external disturbance that is a periodic load at the process input
  (shaped by the process, with a third harmonic) or on the PV;
* installed characteristics that are equal-percentage (rangeability 5-50) or
  quick-opening (square root), not the check's exponential family alone;
* effect sizes drawn from barely detectable to large (below).

=============================  ====================================================
effect                         hidden in the true loop
=============================  ====================================================
``gain_mismatch``              K times 1.15-2.2 or 0.45-0.87
``deadtime_mismatch``          dead time longer or shorter by 2-8 samples
``time_constant_mismatch``     tau times 1.4-3 or 0.3-0.7 (integrator: a lag of 2-6 theta)
``valve_characteristic``       equal-percentage (R = 5-50) or quick-opening
``measurement_quantization``   resolution with q / sqrt(12) = 0.7-4 noise std
``external_disturbance``       periodic load, PV amplitude 2-15 noise std, period 20-500 samples
``asymmetric_stiction``        stick band 1.6-4 times larger in one direction
``position_dependent_stiction``  stick band raised by 2-6 % in a band 4-12 % wide
=============================  ====================================================

Valve-characteristic and position-dependent cases are self-regulating (an
integrating loop brings its valve back to the balance point, so the data
never show the valve elsewhere); every other class may be integrating.
Two effects can be hidden at once (:func:`independent_case` with a pair).
"""

from __future__ import annotations

import math

import numpy as np

from analytics.lti import FirstOrderProcess
from analytics.model_check.cases import CATALOGUE, HiddenEffectCase
from analytics.model_check.model import (
    LoopModel,
    Valve,
    friction_valve,
)
from analytics.simulation import PIDController
from analytics.types import INTEGRATING, SELF_REGULATING, FloatArray
from analytics.valves import (
    HE,
    LAST_INPUT,
    POSITION,
    ChoudhuryValve,
    HeValve,
    KanoValve,
    valve_step,
)

__all__ = ["POSITIONAL", "independent_case"]


POSITIONAL = ("valve_characteristic", "position_dependent_stiction")
"""Effects that only show when the valve works at several positions (self-regulating loops)."""


class _TrueLoop:
    """The simulated plant: process, PI controller, valve and the hidden effects.

    Attributes are set by :func:`independent_case`; the simulation is
    :meth:`run`.  ``schedule(position, direction)`` gives the valve's friction
    parameters where it stands and for the way it is pushed.
    """

    def __init__(self, base: LoopModel, friction: tuple[float, float]) -> None:
        self.base = base
        self.K, self.tau, self.theta = base.process.K, base.process.tau, base.process.theta
        self.integrating = base.process.integrating
        self.params = {(d, z): np.array(friction) for d in (1, -1) for z in (False, True)}
        self.zone = (math.inf, -math.inf)
        self.characteristic = "linear"
        self.rangeability = 1.0
        self.resolution = 0.0
        self.origin = 0.0
        self.load: tuple[float, float, float, bool] | None = None  # amplitude, period, phase, input

    def flow(self, mv: float) -> float:
        """Installed flow relative to ``op_bias``, with slope 1 there."""
        x0 = self.base.op_bias
        if self.characteristic == "linear":
            return mv - x0
        if self.characteristic == "equal_percentage":
            r = math.log(self.rangeability)
            return 100.0 / r * (math.exp(r * (mv - x0) / 100.0) - 1.0)
        # quick opening: flow ~ sqrt(travel), scaled to slope 1 at x0
        return 2.0 * math.sqrt(x0) * (math.sqrt(max(mv, 0.0)) - math.sqrt(x0))

    def run(self, sp: FloatArray, noise: FloatArray, pv_bias: float) -> tuple[FloatArray, ...]:
        """Closed loop from rest: measure PV, PI with anti-windup, valve, process."""
        base, n, dt = self.base, sp.size, self.base.dt
        c = base.controller
        kc, ki = c.kp, c.ki
        code = base.valve.base.code
        state = base.valve.base.initial_state(base.op_bias)
        delay = round(self.theta / dt)
        pole = math.exp(-dt / self.tau) if self.tau > 0 else 0.0
        inputs = np.zeros(n)
        op, mv, pv = np.empty(n), np.empty(n), np.empty(n)
        t = np.arange(n) * dt
        load_pv = np.zeros(n)
        load_in = np.zeros(n)
        if self.load is not None:
            amplitude, period, phase, at_input = self.load
            shape = np.sin(2 * np.pi * t / period + phase)
            shape += 0.3 * np.sin(3 * (2 * np.pi * t / period + phase))
            (load_in if at_input else load_pv)[:] = amplitude * shape
        level = lag = 0.0
        integral = base.op_bias
        for k in range(n):
            y = pv_bias + level + load_pv[k] + noise[k]
            if self.resolution > 0:
                y = self.origin + self.resolution * round((y - self.origin) / self.resolution)
            pv[k] = y
            e = sp[k] - y
            integral += ki * dt * e
            out = kc * e + integral
            low, high = c.op_limits
            if out > high:
                integral, out = min(integral, high - kc * e), high
            elif out < low:
                integral, out = max(integral, low - kc * e), low
            op[k] = out
            push = out - state[POSITION] if code == HE else out - state[LAST_INPUT]
            inside = self.zone[0] <= state[POSITION] <= self.zone[1]
            params = self.params[(1 if push >= 0 else -1, inside)]
            mv[k] = valve_step(code, params, state, out, dt)
            inputs[k] = self.flow(mv[k]) + load_in[k]
            u = inputs[k - delay] if k >= delay else 0.0
            if self.integrating:
                lag = pole * lag + (1.0 - pole) * u
                level += dt * self.K * lag
            else:
                level = pole * level + (1.0 - pole) * self.K * u
        return op, mv, pv


def _base_loop(
    rng: np.random.Generator, integrating: bool
) -> tuple[LoopModel, tuple[float, float]]:
    """A PI loop with lambda tuning and a friction valve (or a healthy one)."""
    ts = float(rng.choice([0.5, 1.0, 2.0]))
    theta = ts * float(rng.integers(1, 10))
    if integrating:
        K = float(10 ** rng.uniform(-2.3, -1.2))
        lam = theta * float(rng.uniform(2.0, 5.0))
        process = FirstOrderProcess(INTEGRATING, K, 0.0, theta)
        controller = PIDController.ideal(
            (2 * lam + theta) / (K * (lam + theta) ** 2), 2 * lam + theta
        )
    else:
        K = float(10 ** rng.uniform(-0.5, 0.5))
        tau = float(rng.uniform(max(3.0 * ts, 4.0), 60.0))
        lam = max(theta, tau * float(rng.uniform(0.3, 1.0)))
        process = FirstOrderProcess(SELF_REGULATING, K, tau, theta)
        controller = PIDController.ideal(tau / (K * (lam + theta)), tau)
    family = (HeValve, ChoudhuryValve, KanoValve)[int(rng.integers(0, 3))]
    like = family(0.0, 0.0)
    if rng.random() < 0.7:
        valve = friction_valve(like, float(rng.uniform(0.5, 4.0)), float(rng.uniform(0.1, 0.9)))
    else:
        valve = like
    params = valve.params_array()
    model = LoopModel(ts, process, controller, Valve(valve), float(rng.uniform(30.0, 70.0)))
    return model, (float(params[0]), float(params[1]))


def _schedule(
    rng: np.random.Generator, n: int, ts: float, spread: float, pv_bias: float
) -> FloatArray:
    """Set point: steps or ramps between random levels at irregular intervals."""
    sp = np.full(n, pv_bias)
    ramps = rng.random() < 0.5
    k = int(rng.integers(150, 500))
    level = pv_bias
    while k < n:
        target = pv_bias + float(rng.uniform(-spread, spread))
        if abs(target - level) < 0.3 * spread:
            target = level - math.copysign(0.5 * spread, target - level)
        length = int(rng.integers(20, 200)) if ramps else 1
        stop = min(k + length, n)
        sp[k:stop] = np.linspace(level, target, length + 1)[1 : stop - k + 1]
        sp[stop:] = target
        level = target
        k += int(rng.integers(400, 1600))
    return sp


def _noise(rng: np.random.Generator, n: int, std: float) -> FloatArray:
    """AR(1) noise of standard deviation ``std`` plus a slow random-walk drift."""
    phi = float(rng.uniform(0.0, 0.8))
    white = rng.normal(0.0, std * math.sqrt(1.0 - phi**2), n)
    coloured = np.empty(n)
    coloured[0] = rng.normal(0.0, std)
    for k in range(1, n):
        coloured[k] = phi * coloured[k - 1] + white[k]
    walk = np.cumsum(rng.normal(0.0, 1.0, n))
    walk -= np.linspace(walk[0], walk[-1], n)  # a drift that wanders, not a trend
    walk *= float(rng.uniform(0.3, 1.0)) * std / (float(np.std(walk)) or 1.0)
    return np.asarray(coloured + walk, dtype=np.float64)


def _hide(
    effect: str,
    rng: np.random.Generator,
    true: _TrueLoop,
    noise: float,
    positions: FloatArray,
) -> dict[str, float]:
    """Put ``effect`` into ``true`` (in place); its parameters."""
    base = true.base
    like = base.valve.base
    S = float(like.S)
    if effect == "gain_mismatch":
        ratio = float(rng.uniform(1.15, 2.2) if rng.random() < 0.5 else rng.uniform(0.45, 0.87))
        true.K *= ratio
        return {"ratio": ratio}
    if effect == "deadtime_mismatch":
        step = base.dt * int(rng.integers(2, 9))
        shorter = rng.random() < 0.5 and true.theta - step >= 0
        true.theta = true.theta - step if shorter else true.theta + step
        return {"theta": true.theta}
    if effect == "time_constant_mismatch":
        if true.integrating:
            true.tau = max(true.theta, base.dt) * float(rng.uniform(2.0, 6.0))
        else:
            longer = rng.random() < 0.5
            true.tau *= float(rng.uniform(1.4, 3.0) if longer else rng.uniform(0.3, 0.7))
        return {"tau": true.tau}
    if effect == "valve_characteristic":
        if rng.random() < 0.6:
            true.characteristic, true.rangeability = "equal_percentage", float(rng.uniform(5, 50))
            return {"curvature": math.log(true.rangeability)}
        true.characteristic = "quick_opening"
        return {"curvature": -100.0 / (2.0 * base.op_bias)}  # the local log-slope of sqrt
    if effect == "measurement_quantization":
        true.resolution = math.sqrt(12.0) * noise * float(rng.uniform(0.7, 4.0))
        true.origin = float(rng.uniform(0.0, true.resolution))
        return {"resolution": true.resolution, "origin": true.origin}
    if effect == "external_disturbance":
        amplitude = noise * float(rng.uniform(2.0, 15.0))
        period = base.dt * float(rng.uniform(20.0, 500.0))
        at_input = rng.random() < 0.5
        if at_input and not true.integrating:  # the process gain at the load's frequency
            w = 2 * np.pi / period
            amplitude /= true.K / math.sqrt(1.0 + (w * true.tau) ** 2)
        elif at_input:
            amplitude /= true.K * period / (2 * np.pi)
        true.load = (amplitude, period, float(rng.uniform(0, 2 * np.pi)), at_input)
        return {"period": period}
    if effect == "asymmetric_stiction":
        stuck = S * float(rng.uniform(1.6, 4.0)) if S > 0 else float(rng.uniform(1.0, 5.0))
        j = float(like.J / S) if S > 0 else float(rng.uniform(0.2, 0.8))
        direction = 1 if rng.random() < 0.5 else -1
        sticky = friction_valve(like, stuck, j).params_array()
        true.params[(direction, False)] = true.params[(direction, True)] = sticky
        return {("opening_S" if direction > 0 else "closing_S"): stuck}
    if effect == "position_dependent_stiction":
        centre = float(rng.choice(positions))
        half = 0.5 * float(rng.uniform(4.0, 12.0))
        stuck = S + float(rng.uniform(2.0, 6.0))
        inside = friction_valve(like, stuck, float(rng.uniform(0.2, 0.8)))
        true.zone = (centre - half, centre + half)
        for d in (1, -1):
            true.params[(d, True)] = inside.params_array()
        return {"low": centre - half, "high": centre + half, "zone_S": float(inside.S)}
    raise ValueError(f"unknown effect {effect!r}; expected one of {CATALOGUE}")


def independent_case(
    effects: str | tuple[str, ...], seed: int, samples: int = 6000
) -> HiddenEffectCase:
    """A loop of the independent generator hiding one effect (or two), from ``seed``.

    ``effects``: a name of :data:`analytics.model_check.cases.CATALOGUE`, or a
    pair of effect names hidden together.  The returned case's ``effect`` is
    the first and ``extra`` holds the second.

    Examples
    --------
    >>> case = independent_case("gain_mismatch", seed=1, samples=1000)
    >>> case.op.shape, case.effect
    ((1000,), 'gain_mismatch')
    """
    hidden = (effects,) if isinstance(effects, str) else tuple(effects)
    unknown = [e for e in hidden if e not in CATALOGUE]
    if unknown:
        raise ValueError(f"unknown effect(s) {unknown}; expected some of {CATALOGUE}")
    rng = np.random.default_rng([7919, *(CATALOGUE.index(e) for e in hidden), seed])
    integrating = not any(e in POSITIONAL for e in hidden) and rng.random() < 0.35
    base, friction = _base_loop(rng, integrating)
    pv_bias = float(rng.uniform(20.0, 80.0))
    noise_std = float(10 ** rng.uniform(-1.6, -0.7))
    # SP levels that move a self-regulating valve across 10-25 % of travel either side
    spread = (
        float(rng.uniform(10.0, 25.0)) * base.process.K if not integrating
        else float(rng.uniform(2.0, 6.0))
    )
    sp = _schedule(rng, samples, base.dt, spread, pv_bias)
    true = _TrueLoop(base, friction)
    # the valve's steady positions at the set-point levels held longest (self-regulating)
    values, counts = np.unique(sp, return_counts=True)
    positions = base.op_bias + (values[counts >= 200] - pv_bias) / base.process.K
    parameters: dict[str, float] = {}
    for effect in hidden:
        if effect != "none":
            parameters |= _hide(effect, rng, true, noise_std, positions)
    noise = _noise(rng, samples, noise_std)
    op, mv, pv = true.run(sp, noise, pv_bias)
    return HiddenEffectCase(
        hidden[0], parameters, base, None, base.dt, sp, op, mv, pv, noise_std, extra=hidden[1:]
    )
