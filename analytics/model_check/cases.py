"""Random loops with one hidden effect, to test and benchmark the model check.

:func:`hidden_effect_case` draws a loop (process type and parameters, a PI
tuning, a valve with or without stiction, measurement noise, setpoint
changes), hides one effect of the catalogue in the "true" loop, simulates it
(:meth:`LoopModel.simulate`) and returns the measured signals together with
the base model, which lacks the effect.  A check is given only the signals
and the base model.

The effects are drawn from sizes that change the loop's behaviour by more
than its noise, and the setpoint changes move the valve across its travel
(a position-dependent effect cannot show otherwise):

=============================  ==================================================
effect                         hidden in the true loop
=============================  ==================================================
``none``                       nothing
``gain_mismatch``              K times 1.3-1.7 or 0.55-0.77
``deadtime_mismatch``          dead time longer or shorter by max(2, 0.5-1 theta) s
``time_constant_mismatch``     tau times 1.7-2.5 or 0.35-0.6 (integrator: a lag of 3-8 theta)
``valve_characteristic``       exponential characteristic, curvature +-(2-4)
``measurement_quantization``   PV resolution 0.2-0.6 with noise 1-5 % of it
``external_disturbance``       sine on PV, amplitude max(4 noise, 0.3-1.2), period 15-400 s
``asymmetric_stiction``        stick band 2-3.5 times larger in one direction
``position_dependent_stiction``  S raised by 2.5-5 % in a band 5-10 % wide
=============================  ==================================================

Valve characteristic and position-dependent stiction cases use
self-regulating processes: in an integrating loop the valve returns to the
balance point after every setpoint change, so the data never show the valve
elsewhere.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from analytics.lti import FirstOrderProcess
from analytics.model_check.effects import EFFECTS
from analytics.model_check.model import (
    LoopModel,
    PeriodicLoad,
    Quantiser,
    StictionZone,
    Valve,
    friction_of,
    friction_valve,
)
from analytics.simulation import PIDController
from analytics.types import INTEGRATING, SELF_REGULATING, FloatArray
from analytics.valves import ChoudhuryValve, HeValve

__all__ = ["CATALOGUE", "HiddenEffectCase", "hidden_effect_case"]


CATALOGUE = ("none", *EFFECTS)
"""Every effect a case can hide, ``none`` first."""

PV_BIAS = 50.0
"""PV at rest with the valve at ``op_bias``; the first setpoint."""


@dataclass(frozen=True)
class HiddenEffectCase:
    """Measured signals of a loop with one hidden effect, and the base model without it.

    Attributes
    ----------
    effect : str
        The hidden effect (a name of :data:`CATALOGUE`).
    parameters : dict
        Its size, in the terms of the extended model.
    base_model : LoopModel
        The model a check is given.
    true_model : LoopModel or None
        The one that made the data (None when it lies outside the
        :class:`LoopModel` family, as in :mod:`~analytics.model_check.cases_independent`).
    ts : float
        Sampling interval, s.
    sp, op, mv, pv : ndarray
        Measured signals (MV: the true valve position).
    noise_std : float
        Standard deviation of the measurement noise.
    extra : tuple of str
        Effects hidden together with ``effect`` (two-effect cases).
    """

    effect: str
    parameters: dict[str, float]
    base_model: LoopModel
    true_model: LoopModel | None
    ts: float
    sp: FloatArray
    op: FloatArray
    mv: FloatArray
    pv: FloatArray
    noise_std: float
    extra: tuple[str, ...] = ()

    @property
    def effects(self) -> tuple[str, ...]:
        """Every hidden effect (``effect`` first)."""
        return (self.effect, *self.extra)


def _levels(rng: np.random.Generator, count: int, spread: float, gap: float) -> FloatArray:
    """``count`` values in ``[-spread, spread]`` at least ``gap`` apart (rejection sampling).

    Tens of thousands of draws may be rejected, so they are drawn a block at a
    time; the generator is then left as drawing one set at a time would leave it.
    """
    while True:
        before = rng.bit_generator.state
        draws = rng.uniform(-spread, spread, (4096, count))
        apart = np.min(np.diff(np.sort(draws, axis=1), axis=1), axis=1) >= gap
        if np.any(apart):
            first = int(np.argmax(apart))
            rng.bit_generator.state = before
            rng.uniform(-spread, spread, (first + 1, count))
            return draws[first]


def _base_loop(
    rng: np.random.Generator, integrating: bool
) -> tuple[LoopModel, FloatArray]:
    """A random PI loop (SIMC tuning, Skogestad 2003) and the MV offsets of its setpoint levels."""
    ts = 1.0
    theta = float(rng.integers(1, 8))
    if integrating:
        K = float(rng.uniform(0.01, 0.04))
        closed = theta * float(rng.uniform(3.0, 6.0))
        process = FirstOrderProcess(INTEGRATING, K, 0.0, theta)
        controller = PIDController.ideal(1.0 / (K * (closed + theta)), 4.0 * (closed + theta))
    else:
        K = float(rng.uniform(0.6, 2.0))
        tau = float(rng.uniform(5.0, 40.0))
        closed = max(theta, tau / 4.0) * float(rng.uniform(1.0, 2.0))
        process = FirstOrderProcess(SELF_REGULATING, K, tau, theta)
        controller = PIDController.ideal(
            tau / (K * (closed + theta)), min(tau, 4.0 * (closed + theta))
        )
    kind = HeValve if rng.random() < 0.5 else ChoudhuryValve
    like = kind(0.0, 0.0)
    if rng.random() < 0.75:
        valve = friction_valve(like, float(rng.uniform(1.0, 5.0)), float(rng.uniform(0.2, 0.8)))
    else:
        valve = like
    model = LoopModel(ts, process, controller, Valve(valve), float(rng.uniform(35.0, 65.0)))
    return model, _levels(rng, 5, 18.0, 8.0)


def _hide(
    effect: str, rng: np.random.Generator, base: LoopModel, offsets: FloatArray, noise: float
) -> tuple[LoopModel, dict[str, float], float]:
    """The true model, the effect's parameters and the measurement noise (``noise``
    unless the effect needs another)."""
    p, v = base.process, base.valve
    S, j = friction_of(v.base)
    if effect == "none":
        return base, {}, noise
    if effect == "gain_mismatch":
        ratio = float(rng.uniform(1.3, 1.7) if rng.random() < 0.5 else rng.uniform(0.55, 0.77))
        return replace(base, process=replace(p, K=p.K * ratio)), {"ratio": ratio}, noise
    if effect == "deadtime_mismatch":
        step = max(2.0, round(float(rng.uniform(0.5, 1.0)) * p.theta))
        theta = p.theta - step if rng.random() < 0.5 and p.theta - step >= 0 else p.theta + step
        return replace(base, process=replace(p, theta=theta)), {"theta": theta}, noise
    if effect == "time_constant_mismatch":
        if p.integrating:
            tau = p.theta * float(rng.uniform(3.0, 8.0))
        else:
            factor = rng.uniform(1.7, 2.5) if rng.random() < 0.5 else rng.uniform(0.35, 0.6)
            tau = p.tau * float(factor)
        return replace(base, process=replace(p, tau=tau)), {"tau": tau}, noise
    if effect == "valve_characteristic":
        c = float(rng.uniform(2.0, 4.0)) * (1 if rng.random() < 0.5 else -1)
        return replace(base, valve=replace(v, curvature=c)), {"curvature": c}, noise
    if effect == "measurement_quantization":
        q = float(rng.uniform(0.2, 0.6))
        grid = Quantiser(q, float(rng.uniform(0.0, q)))
        return (
            replace(base, quantiser=grid),
            {"resolution": q, "origin": grid.origin},
            q * float(rng.uniform(0.01, 0.05)),
        )
    if effect == "external_disturbance":
        load = PeriodicLoad(
            max(float(rng.uniform(0.3, 1.2)), 4.0 * noise),
            float(rng.uniform(15.0, 400.0)),
            float(rng.uniform(0.0, 2 * np.pi)),
        )
        params = {"amplitude": load.amplitude, "period": load.period, "phase": load.phase}
        return replace(base, load=load), params, noise
    if effect == "asymmetric_stiction":
        stuck = S * float(rng.uniform(2.0, 3.5)) if S > 0 else float(rng.uniform(2.0, 5.0))
        sticky = friction_valve(v.base, stuck, j if S > 0 else float(rng.uniform(0.2, 0.8)))
        if rng.random() < 0.5:
            return replace(base, valve=replace(v, opening=sticky)), {"opening_S": stuck}, noise
        return replace(base, valve=replace(v, closing=sticky)), {"closing_S": stuck}, noise
    if effect == "position_dependent_stiction":
        centre = base.op_bias + float(rng.choice(offsets))
        half = 0.5 * float(rng.uniform(5.0, 10.0))
        stuck = S + float(rng.uniform(2.5, 5.0))
        inside = friction_valve(v.base, stuck, float(rng.uniform(0.3, 0.7)))
        zone = StictionZone(centre - half, centre + half, inside)
        params = {"low": zone.low, "high": zone.high, "zone_S": inside.S}
        return replace(base, valve=replace(v, zone=zone)), params, noise
    raise ValueError(f"unknown effect {effect!r}; expected one of {CATALOGUE}")


def hidden_effect_case(
    effect: str | tuple[str, ...], seed: int, samples: int = 6000
) -> HiddenEffectCase:
    """A random loop hiding ``effect`` (or a pair of effects, hidden together),
    reproducible from ``seed``.

    Examples
    --------
    >>> case = hidden_effect_case("gain_mismatch", seed=1, samples=1000)
    >>> case.op.shape, case.base_model.process.K != case.true_model.process.K
    ((1000,), True)
    >>> hidden_effect_case(("gain_mismatch", "measurement_quantization"), 1, 1000).effects
    ('gain_mismatch', 'measurement_quantization')
    """
    hidden = (effect,) if isinstance(effect, str) else tuple(effect)
    unknown = [e for e in hidden if e not in CATALOGUE]
    if unknown:
        raise ValueError(f"unknown effect(s) {unknown}; expected some of {CATALOGUE}")
    rng = np.random.default_rng([*(CATALOGUE.index(e) for e in hidden), seed])
    integrating = not any(
        e in ("valve_characteristic", "position_dependent_stiction") for e in hidden
    ) and (rng.random() < 0.3)
    base, offsets = _base_loop(rng, integrating)
    noise_std = float(rng.uniform(0.02, 0.12))
    true: LoopModel = base
    parameters: dict[str, float] = {}
    for name in hidden:
        true, found, noise_std = _hide(name, rng, true, offsets, noise_std)
        parameters |= found
    gain = base.process.K
    levels = PV_BIAS + (rng.uniform(-4.0, 4.0, offsets.size) if integrating else gain * offsets)
    sp = np.full(samples, PV_BIAS)
    k = int(rng.integers(200, 600))
    level = 0
    while k < samples:
        sp[k:] = levels[level % levels.size]
        level += 1
        k += int(rng.integers(600, 1400))
    noise = rng.normal(0.0, noise_std, samples)
    sim = true.simulate(sp, noise=noise, pv_bias=PV_BIAS)
    return HiddenEffectCase(
        hidden[0], parameters, base, true, base.dt, sp, sim.op, sim.mv, sim.pv, noise_std,
        extra=hidden[1:],
    )
