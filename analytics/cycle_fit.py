"""The valve of a loop model fitted to the cycle measured on the loop (issue 19).

Advice for a sticky valve is computed on a loop model (identified process,
configured controller, estimated valve), and is only as good as that model:
before any tuning is judged, the model at the current tuning must cycle as
the loop does.  :func:`fit_valve_to_cycle` checks the model's simulated
cycle against the measured one and, where it disagrees, says what is wrong
and fits the valve until the simulation gives the measured period and
amplitude, or states the error that remains.

What can be wrong, in the order it is tried:

1. nothing: the estimate's valve reproduces the cycle (period within
   :data:`~analytics.tuning.PERIOD_TOLERANCE`, OP amplitude within
   :data:`~analytics.tuning.AMPLITUDE_TOLERANCE`);
2. the valve *model*: the Hammerstein fit follows the measured OP with a
   He, Kano or Choudhury valve about equally well (on a cycle they move
   the valve alike), but in a closed loop they differ.  A Kano or Choudhury
   valve that slips moves with OP until OP turns, so integral action can
   bring the loop to rest while the valve moves; He's valve moves only in
   jumps of ``J`` (it sticks again after each slip) and never settles.  The
   same ``(S, J)`` in another model is simulated;
3. the valve *size*: ``S`` and ``J`` are fitted within their intervals.  The
   loop is linear but for the valve, and every one of these valve models is
   positively homogeneous (``S``, ``J`` and every signal scaled by ``c`` give
   the same motion scaled by ``c``), so the period of the cycle depends on
   ``J / S`` only and the amplitude is proportional to ``S`` at a given
   ``J / S``: the ratio is fitted to the period, then ``S`` to the amplitude;
4. the process: no valve within the intervals reproduces the cycle.  The
   process's dead time, which sets the phase lag at the cycle and with it the
   period, is fitted with the closest valve (a single loop's model; the
   valve's size is fitted again at the new dead time); the model keeps the
   closest of all and the error that remains is stated.

Simulations start from a setpoint step of the stick band and drop noise
(:func:`analytics.tuning.excited_model`), as the advice's own do, so the
simulation and its scaling hold exactly.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from analytics.errors import ModelSpecError
from analytics.limit_cycle import simulate_limit_cycle
from analytics.lti import TransferFunction
from analytics.simulation import ClosedLoopModel
from analytics.tuning import (
    AMPLITUDE_TOLERANCE,
    PERIOD_TOLERANCE,
    excited_model,
    relative_error,
)
from analytics.valves import ChoudhuryValve, HeValve, KanoValve, ValveModel, sj_to_fsfd

__all__ = ["CycleFit", "FittedValve", "ValveKind", "fit_valve_to_cycle", "valve_of"]

ValveKind = Literal["he", "kano", "choudhury"]

RATIO_POINTS = 9
"""Values of ``J / S`` simulated across the interval before the period is refined."""
REFINE_STEPS = 6
"""Bisection steps of ``J / S`` once the simulated period brackets the measured one."""
CYCLES = 30
"""Each simulation runs this many measured periods (at least the model's duration)."""
DELAY_POINTS = 13
"""Dead times tried when the process is fitted, from 0 to a quarter of the measured period
(90 degrees of phase at the cycle) or twice the identified one."""

Cause = Literal["none", "valve_model", "valve_size", "process"]


def valve_of(kind: ValveKind, S: float, J: float) -> ValveModel:
    """The ``kind`` valve with stick band ``S`` and slip jump ``J`` (He: thesis Eq. 1.2).

    >>> valve_of("he", 8.0, 4.0)
    HeValve(fs=6.0, fd=2.0)
    """
    if kind == "he":
        return HeValve(*sj_to_fsfd(S, J))
    if kind == "kano":
        return KanoValve(S, J)
    if kind == "choudhury":
        return ChoudhuryValve(S, J)
    raise ModelSpecError(f"valve kind must be he, kano or choudhury, got {kind!r}")


def _kind(valve: ValveModel) -> ValveKind:
    if isinstance(valve, HeValve):
        return "he"
    if isinstance(valve, KanoValve):
        return "kano"
    if isinstance(valve, ChoudhuryValve):
        return "choudhury"
    raise ModelSpecError(f"the valve to fit must be a He, Kano or Choudhury valve, got {valve!r}")


def _sj(valve: ValveModel) -> tuple[float, float]:
    if isinstance(valve, HeValve):
        return valve.S, valve.J
    assert isinstance(valve, ChoudhuryValve)
    return valve.S, valve.J


@dataclass(frozen=True)
class FittedValve:
    """One valve simulated in the loop model, and its cycle against the measured one.

    ``period_error`` and ``amplitude_error`` are ``(model - measured) / measured``;
    None where the simulation does not cycle (or nothing was measured).
    """

    kind: ValveKind
    S: float
    J: float
    period_s: float | None
    amplitude: float | None
    period_error: float | None
    amplitude_error: float | None

    @property
    def valve(self) -> ValveModel:
        """The valve model."""
        return valve_of(self.kind, self.S, self.J)

    @property
    def cycles(self) -> bool:
        """The simulated model cycles."""
        return self.period_s is not None

    @property
    def reproduces(self) -> bool:
        """Period within :data:`PERIOD_TOLERANCE`, amplitude within :data:`AMPLITUDE_TOLERANCE`
        (the amplitude is not judged where none was measured)."""
        p, a = self.period_error, self.amplitude_error
        return (p is not None and abs(p) <= PERIOD_TOLERANCE
                and (a is None or abs(a) <= AMPLITUDE_TOLERANCE))

    @property
    def misfit(self) -> float:
        """The larger of the two errors, each over its tolerance (inf without a cycle)."""
        if self.period_error is None:
            return math.inf
        a = 0.0 if self.amplitude_error is None else abs(self.amplitude_error)
        return max(abs(self.period_error) / PERIOD_TOLERANCE, a / AMPLITUDE_TOLERANCE)

    def describe(self) -> str:
        """``"He valve (S 8.48 %, J 4.26 %)"``."""
        name = {"he": "He", "kano": "Kano", "choudhury": "Choudhury"}[self.kind]
        return f"{name} valve (S {self.S:.3g} %, J {self.J:.3g} %)"

    def cycle_words(self) -> str:
        """What its simulation shows against the measurement."""
        if self.period_s is None:
            return "does not cycle in simulation (the loop comes to rest)"
        words = f"cycles at {self.period_s:.3g} s (period {self.period_error:+.0%}"
        if self.amplitude_error is not None:
            words += f", amplitude {self.amplitude_error:+.0%}"
        return words + ")"

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {"valve_model": self.kind, "S": self.S, "J": self.J,
                "period_s": self.period_s, "amplitude": self.amplitude,
                "period_error": self.period_error, "amplitude_error": self.amplitude_error,
                "reproduces": self.reproduces}


@dataclass(frozen=True)
class CycleFit:
    """The loop model's valve checked against the measured cycle, and fitted to it.

    Attributes
    ----------
    measured_period_s, measured_amplitude : float or None
        The loop's cycle (period; OP amplitude, first harmonic, % of span).
    estimated : FittedValve
        The estimate's valve as simulated in the model.
    chosen : FittedValve
        The valve the model keeps: the first that reproduces the cycle in the
        order of the module's list, else the closest one tried.
    cause : {"none", "valve_model", "valve_size", "process"}
        What the check found wrong (see the module).
    tried : tuple of FittedValve
        Every valve simulated, in the order tried.
    at_edge : bool
        The chosen valve's S or J lies on a bound of the intervals the fit was held to
        (and differs from the estimate's): the data would allow no larger change, a sign
        that the process, not the valve, is off.
    delay_s : (float, float) or None
        With cause ``"process"`` and a single loop's model: the identified dead time and
        the one the model keeps (equal when fitting it did not help), s.
    """

    measured_period_s: float | None
    measured_amplitude: float | None
    estimated: FittedValve
    chosen: FittedValve
    cause: Cause
    tried: tuple[FittedValve, ...]
    at_edge: bool = False
    delay_s: tuple[float, float] | None = None

    @property
    def reproduces(self) -> bool:
        """The chosen valve reproduces the measured cycle."""
        return self.chosen.reproduces

    @property
    def changed(self) -> bool:
        """The model's valve differs from the estimate's."""
        return self.chosen != self.estimated

    def fitted(self, model: ClosedLoopModel, loop: int = 0) -> ClosedLoopModel:
        """``model`` with loop ``loop``'s valve replaced by the chosen one (and the process's
        dead time by the fitted one, if it was fitted)."""
        if self.delay_s is not None:
            model = _with_delay(model, self.delay_s[1])
        return _with_valve(model, loop, self.chosen.valve)

    def explanation(self) -> str:
        """What the check found, what was changed and the error that remains, in words."""
        estimated = f"the estimated {self.estimated.describe()} {self.estimated.cycle_words()}"
        if self.cause == "none":
            return f"{estimated}: the estimate is kept"
        chosen = f"{self.chosen.describe()} {self.chosen.cycle_words()}"
        if self.cause == "valve_model":
            return (f"{estimated}: its valve model is wrong for this loop (the fit of the "
                    "measured OP and PV tells He's, Kano's and Choudhury's valves apart "
                    f"only weakly, the closed loop does); a {chosen}, and is simulated "
                    "instead")
        if self.cause == "valve_size":
            what = ("size is" if self.chosen.kind == self.estimated.kind
                    else "model and size are")
            edge = (" (at the edge of the intervals: the identified process, or a "
                    "neighbour's interaction, may be what is off)") * self.at_edge
            return (f"{estimated}: the valve's {what} off; fitted to the measured cycle "
                    f"within the estimate's intervals, a {chosen}{edge}, and is simulated "
                    "instead")
        text = (f"{estimated}; no He, Kano or Choudhury valve within the estimate's "
                "intervals reproduces the measured cycle: the identified process (or a "
                "neighbour's interaction) does not describe this cycle")
        if self.delay_s is not None and self.delay_s[0] != self.delay_s[1]:
            text += (f"; with the process's dead time fitted ({self.delay_s[0]:.3g} s "
                     f"identified, {self.delay_s[1]:.3g} s kept) a {chosen}")
        else:
            text += f"; the closest is a {chosen}"
        if self.reproduces:
            return text + ", and is simulated instead"
        return text + ", and the model keeps that error"

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {"measured": {"period_s": self.measured_period_s,
                             "amplitude": self.measured_amplitude},
                "cause": self.cause, "estimated": self.estimated.to_dict(),
                "chosen": self.chosen.to_dict(), "reproduces": self.reproduces,
                "tried": len(self.tried), "at_edge": self.at_edge,
                "delay_s": None if self.delay_s is None else list(self.delay_s),
                "explanation": self.explanation()}


def _with_valve(model: ClosedLoopModel, loop: int, valve: ValveModel) -> ClosedLoopModel:
    loops = list(model.loops)
    loops[loop] = dataclasses.replace(loops[loop], valve=valve)
    return dataclasses.replace(model, loops=tuple(loops))


def _with_delay(model: ClosedLoopModel, delay: float) -> ClosedLoopModel:
    assert isinstance(model.process, TransferFunction)  # a single loop's model
    return dataclasses.replace(model, process=dataclasses.replace(model.process, delay=delay))


class _Simulator:
    """Simulates the model with one valve in loop ``loop``; results cached by valve."""

    def __init__(self, model: ClosedLoopModel, loop: int, period_s: float | None,
                 amplitude: float | None) -> None:
        self.model, self.loop = model, loop
        self.period_s, self.amplitude = period_s, amplitude
        self.duration = max(model.duration, CYCLES * (period_s or 0.0))
        self.tried: dict[tuple[ValveKind, float, float], FittedValve] = {}

    def __call__(self, kind: ValveKind, S: float, J: float) -> FittedValve:
        key = (kind, float(S), float(J))
        if key not in self.tried:
            model = _with_valve(self.model, self.loop, valve_of(kind, S, J))
            sim = simulate_limit_cycle(excited_model(model, duration=self.duration))
            amplitude = sim.amplitudes[self.loop] if sim.oscillating else None
            period = sim.period_s if sim.oscillating else None
            self.tried[key] = FittedValve(
                kind, float(S), float(J), period, amplitude,
                relative_error(period, self.period_s), relative_error(amplitude, self.amplitude))
        return self.tried[key]


def _clip_sj(stick: float, ratio: float, s_range: tuple[float, float],
             j_range: tuple[float, float]) -> tuple[float, float]:
    """``(S, ratio S)`` held within the intervals (``S`` first, then ``J`` through ``S``)."""
    stick = min(max(stick, s_range[0]), s_range[1])
    if ratio > 0 and ratio * stick > j_range[1]:
        stick = max(s_range[0], j_range[1] / ratio)
    elif ratio > 0 and ratio * stick < j_range[0]:
        stick = min(s_range[1], j_range[0] / ratio)
    return stick, min(ratio * stick, stick)


def _fit_size(simulate: _Simulator, kind: ValveKind, S0: float, J0: float,
              s_range: tuple[float, float], j_range: tuple[float, float]) -> FittedValve:
    """The ``kind`` valve fitted to the measured cycle within the intervals: ``J / S`` to the
    period, then ``S`` to the amplitude along that ratio.

    Each ratio is simulated at the size within the intervals nearest ``S0`` (the period
    does not depend on the size at a given ratio, so every valve simulated lies within the
    intervals)."""
    low = max(0.0, j_range[0] / s_range[1])
    high = min(1.0, j_range[1] / max(s_range[0], 1e-12))
    if not low <= high:
        low = high = min(1.0, J0 / S0)

    def at(ratio: float, S: float = S0) -> FittedValve:
        return simulate(kind, *_clip_sj(S, ratio, s_range, j_range))

    ratios = np.unique(np.append(np.linspace(low, high, RATIO_POINTS), min(1.0, J0 / S0)))
    runs = [(float(r), at(float(r))) for r in ratios]
    cycling = [(r, v) for r, v in runs if v.period_error is not None]
    if not cycling:
        return min((v for _, v in runs), key=lambda v: v.misfit)
    ratio, best = min(cycling, key=lambda rv: abs(rv[1].period_error or 0.0))
    # refine between neighbours whose periods bracket the measured one
    for (r1, v1), (r2, v2) in itertools.pairwise(cycling):
        e1, e2 = v1.period_error, v2.period_error
        assert e1 is not None and e2 is not None
        if e1 * e2 <= 0 and ratio in (r1, r2):
            lo, hi, e_lo = r1, r2, e1
            for _ in range(REFINE_STEPS):
                mid = 0.5 * (lo + hi)
                v = at(mid)
                if v.period_error is None:
                    break
                if abs(v.period_error) < abs(best.period_error or 0.0):
                    ratio, best = mid, v
                if v.period_error * e_lo <= 0:
                    hi = mid
                else:
                    lo, e_lo = mid, v.period_error
            break
    if best.amplitude is None or simulate.amplitude is None:
        return best
    scaled = at(ratio, best.S * simulate.amplitude / best.amplitude)
    return min((best, scaled), key=lambda v: v.misfit)


def fit_valve_to_cycle(
    model: ClosedLoopModel,
    period_s: float | None,
    amplitude: float | None,
    *,
    loop: int = 0,
    S_interval: tuple[float, float] | None = None,
    J_interval: tuple[float, float] | None = None,
    kinds: Sequence[ValveKind] = ("he", "kano", "choudhury"),
) -> CycleFit:
    """Check ``model``'s simulated cycle against the measured one and fit loop ``loop``'s valve.

    Parameters
    ----------
    model : ClosedLoopModel
        The loop model with the estimate's valve (He, Kano or Choudhury) in loop ``loop``.
    period_s, amplitude : float or None
        The measured cycle: period (s) and OP amplitude (first harmonic, % of span).
        Without a measured period nothing is fitted (cause ``"none"``).
    S_interval, J_interval : (float, float), optional
        Where the data put ``S`` and ``J`` (the estimate's intervals); default the estimate
        itself (only the valve model is then free).
    kinds : sequence of str
        Valve models tried.

    Examples
    --------
    FV-105 of the demo (a He valve, fs 6 %, fd 2 %, on 1.2 e^-2s / (8 s + 1) under PI
    0.5, 8 s) cycles at 112 s; a Kano valve of the same S and J lets the loop settle:

    >>> from analytics.lti import TransferFunction
    >>> from analytics.simulation import Loop, PIDController
    >>> kano = ClosedLoopModel(TransferFunction.fopdt(1.2, 8.0, 2.0),
    ...     (Loop(PIDController.ideal(0.5, 8.0), KanoValve(8.0, 4.0), pv_bias=50.0),),
    ...     dt=1.0, duration=4000.0)
    >>> fit = fit_valve_to_cycle(kano, 112.0, 3.5)
    >>> fit.estimated.cycles, fit.cause, fit.chosen.kind, fit.reproduces
    (False, 'valve_model', 'he', True)
    """
    valve = model.loops[loop].valve
    kind0 = _kind(valve)
    S0, J0 = _sj(valve)
    if not S0 > 0:
        raise ModelSpecError(f"the valve to fit has no stick band (S = {S0:g})")
    simulate = _Simulator(model, loop, period_s, amplitude)
    estimated = simulate(kind0, S0, J0)
    others = [k for k in kinds if k != kind0]

    s_range = S_interval or (S0, S0)
    j_range = J_interval or (J0, J0)
    s_range = (min(s_range[0], S0), max(s_range[1], S0))
    j_range = (min(j_range[0], J0), max(j_range[1], J0))

    def result(chosen: FittedValve, cause: Cause,
               delay: tuple[float, float] | None = None) -> CycleFit:
        moved = (chosen.S, chosen.J) != (S0, J0)
        edge = moved and any(math.isclose(x, bound, rel_tol=1e-9)
                             for x, bounds in ((chosen.S, s_range), (chosen.J, j_range))
                             for bound in bounds)
        return CycleFit(period_s, amplitude, estimated, chosen, cause,
                        tuple(simulate.tried.values()), edge, delay)

    if period_s is None or estimated.reproduces:
        return result(estimated, "none")
    swapped = [simulate(k, S0, J0) for k in others]
    good = [v for v in swapped if v.reproduces]
    if good:
        return result(min(good, key=lambda v: v.misfit), "valve_model")
    fitted = [_fit_size(simulate, k, S0, J0, s_range, j_range) for k in (kind0, *others)]
    good = [v for v in fitted if v.reproduces]
    if good:
        return result(min(good, key=lambda v: v.misfit), "valve_size")
    closest = min((estimated, *swapped, *fitted), key=lambda v: v.misfit)
    if not isinstance(model.process, TransferFunction):
        return result(closest, "process")
    theta0 = model.process.delay
    delays = np.unique(np.append(np.linspace(0.0, max(2.0 * theta0, 0.25 * period_s),
                                             DELAY_POINTS), theta0))
    runs = {float(d): _Simulator(_with_delay(model, float(d)), loop, period_s, amplitude)
            for d in delays}
    best = min(runs, key=lambda d: runs[d](closest.kind, closest.S, closest.J).misfit)
    refitted = _fit_size(runs[best], closest.kind, closest.S, closest.J, s_range, j_range)
    at_best = min((runs[best](closest.kind, closest.S, closest.J), refitted),
                  key=lambda v: v.misfit)
    if at_best.misfit < closest.misfit:
        simulate.tried.update({k: v for d in delays for k, v in runs[float(d)].tried.items()
                               if d != theta0})
        return result(at_best, "process", (theta0, best))
    return result(closest, "process", (theta0, theta0))
