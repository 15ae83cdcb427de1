"""Controller tuning against stiction-induced oscillation (thesis chapter 5).

A sticky valve makes a loop cycle where the open-loop frequency response
``L(jw) = G(jw) Gc(jw)`` meets ``-1/N(A)`` (thesis Eq. 5.11). Retuning the
controller moves ``L`` and can take it off the ``-1/N`` curve (the cycle
disappears) or move the crossing to a lower frequency and amplitude (the cycle
slows down and shrinks). This module holds:

* :func:`analyse_single_loop`: the single-loop analysis of sections 5.3-5.4 for
  first-order self-regulating and integrating processes, with and without dead
  time, under P and PI control: the points F (first crossing of the imaginary
  axis, ``F_imag``) and H (first crossing of the real axis, ``H_real``), their
  frequencies ``w*`` and ``w**`` (Eqs. 5.16-5.19, 5.25-5.30, 5.37-5.40), the
  low-frequency real part ``d`` (Eq. 5.24, Tables 5.2-5.8) and the matching row
  of Table 5.11 (:data:`TABLE_5_11`);
* :func:`safe_tuning_map`: the map of Fig. 5.17 over a ``Kc x Ti`` grid: where
  the linear loop is stable and where no stiction limit cycle is predicted;
* :func:`advise`: recommendations with their predicted effect, each verified by
  simulation (:func:`analytics.limit_cycle.simulate_limit_cycle`) before it is
  offered; for multi-loop systems the two-step procedure of section 5.6.

Corrections to the printed equations (each checked against the frequency
response in tests/analytics/test_tuning.py): Eq. 5.15's imaginary part carries
a stray factor ``tau w`` (Eq. 5.16 is right); Eq. 5.19 lacks ``pi``:
``theta w** = pi - atan(tau w**)``; Eq. 5.28 should read
``theta w** = alpha - beta + pi/2``; Eqs. 5.37-5.38 are not the parts of
Eq. 5.36 (which is right; they are used here); Eq. 5.39 lacks ``pi``:
``theta w* = atan(tau_I w*) + pi/2``. Table 5.11's condition for a
self-regulating process without delay under PI control reads ``tau_I > tau``;
the analysis of section 5.3.1 (Eq. 5.14) and the row's own action
(``tau_I`` up) give ``tau_I < tau``.

Where Table 5.11 and the checks disagree (tests/analytics/test_tuning.py):

* Int. & PI with delay, option ``tau_I < theta``: the linear loop is unstable
  for every gain (a right-half-plane pair, ``Re s ~ K Kc (theta/tau_I - 1)/2``
  for small gains), although ``H_real > -1``; the map excludes it and
  :func:`advise` says so.
* Int. & P without delay: the only solution is the band edge of Eq. 5.33, which
  is not a stable cycle; the loop settles.
* Deadband column, SR & PI: with ``tau_I < tau (+ theta)`` the deadband curve
  meets ``G Gc`` and the loop cycles.

What the simulation adds. The describing function sees only cycles whose OP
fundamental exceeds ``S/2``. With integral action and a slip jump ``J > 0`` the
simulated loop often keeps a slow stick-slip cycle (the integrator walks OP
through the stick band) where no ``-1/N`` crossing exists (see
:mod:`analytics.limit_cycle`), so a retune the DF says removes the cycle may be
verified as *reduced*: slower and smaller.

References
----------
.. [1] Thesis chapter 5 (Eqs. 5.9-5.40, Tables 5.1-5.8 and 5.11, Figs. 5.16-5.18,
   section 5.5.1, section 5.6); chapter 3 (Eq. 3.14); ERRATA items 1 and 9.
.. [2] Astrom & Hagglund (2006), *Advanced PID Control*, ISA, sec. 4.8 (the
   maximum sensitivity ``Ms = max 1/|1 + L|`` as the robustness constraint).
.. [3] Atherton (1975), *Nonlinear Control Engineering*, ch. 7 (a single-loop
   limit cycle is stable where ``-1/N`` leaves the encircled region).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike

from analytics.describing import (
    DescribingChoice,
    ValveDescribingFunction,
    equivalent_sj,
    table_5_1_limits,
    valve_describing_function,
)
from analytics.errors import ModelSpecError
from analytics.limit_cycle import (
    GRID_PER_DECADE,
    Prediction,
    SimulatedLimitCycle,
    predict_limit_cycles,
    simulate_limit_cycle,
)
from analytics.lti import FirstOrderProcess, TransferFunction, process_gain
from analytics.oscillation import RAYLEIGH_ENVELOPE_CV
from analytics.simulation import ClosedLoopModel, Disturbance, PIDController
from analytics.types import BoolArray, ComplexArray, FloatArray, IntArray, ProcessType
from analytics.valves import IdealValve, ValveModel

Control = Literal["P", "PI"]
Action = Literal["raise Ti", "lower Kc", "Ti below theta"]
Outcome = Literal["removed", "reduced", "not improved", "unstable"]

#: Robustness limit on the maximum sensitivity for recommended tunings [2]_
#: (``Ms <= 2`` guarantees a gain margin >= 2 and a phase margin >= 29 degrees).
MS_LIMIT = 2.0
#: A verified reduction must cut the simulated valve travel rate by this fraction.
MIN_REDUCTION = 0.05

MAX_LOAD_ERROR_RATIO = 3.0
"""Most a recommended retune may multiply the error that a load leaves (:func:`load_error`:
the integrated error after a load step under PI control, the offset under P) against the
current tuning.  A retune that removes the cycle only by slowing the loop further hardly
controls: it swaps the valve's cycle for loads that go uncorrected, and repairing the valve
is the answer.  Three times is the most the product's own detuning of a linearly
oscillating loop costs (:func:`detune`: ``Kc / 3`` for a gain margin of 3 from about 1,
:data:`DETUNING_GAIN_MARGINS`)."""
#: The describing function of a valve, built once per valve (a tabulated one costs
#: a simulation per amplitude).
_describing_function = functools.lru_cache(maxsize=64)(valve_describing_function)
#: Complex loop-response samples evaluated at once in :func:`safe_tuning_map`.
_CHUNK_SAMPLES = 2_000_000
#: Safe picks of the map the exact solver may refute before the search gives up.
_MAX_REFUTED = 20
#: Rows searched together for crossings of ``-1/N`` in :func:`safe_tuning_map`.
_BRACKET_GROUP = 32
#: Longest verification simulation, samples.
_MAX_SAMPLES = 2_000_000

NOISY_RUN_S = 14_400.0
"""Length of the simulation with the measured PV noise that checks each retune."""

NOISY_SETTLE_S = 3_600.0
"""Its start, left out of the valve travel (the setpoint step and the settling)."""

NOISE_SEEDS = (20_260_301, 20_260_302, 20_260_303, 20_260_304)
"""Seeds of that noise, one run each: the same sequences for the current tuning and every
retune.  One run is not enough: a retune that removes the noise-free cycle with more gain
can rest for long stretches in one noise sequence and slip all along in another (the
demo's FIC-101 model at Kc 1: 0.75 or 1.48 times the current travel in one run, 1.04 or
1.50 over these four, as the last bits of the identified process fall)."""


def load_error(kc: ArrayLike, ti: ArrayLike, inverse_k: float) -> FloatArray:
    """The error a unit load step at the valve leaves under the tuning ``Kc``, ``Ti``
    (Astrom & Hagglund 2006 [2]_, ch. 4: the load-disturbance criteria).

    With integral action, the integrated error ``IE = Ti / |Kc|``: the final-value
    theorem on ``E(s) = -G(s) / (s (1 + G(s) C(s)))`` gives ``1 / ki`` for every stable
    loop, self-regulating or integrating.  Under P control (``Ti`` infinite) the offset
    ``1 / (1/|K| + |Kc|)``, where ``inverse_k`` is ``1/|K|`` (:func:`inverse_gain`) of a
    self-regulating process and 0 of an integrating one.  Only ratios between tunings of
    the same structure are meaningful.

    >>> float(load_error(2.0, 10.0, 0.5)), float(load_error(2.0, math.inf, 0.5))
    (5.0, 0.4)
    """
    gain = np.abs(np.asarray(kc, dtype=np.float64))
    integral = np.asarray(ti, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        return np.asarray(np.where(np.isinf(integral), 1.0 / (inverse_k + gain),
                                   integral / gain), dtype=np.float64)


def inverse_gain(process: TransferFunction) -> float:
    """``1/|K|`` of a self-regulating ``process``, 0 of an integrating one (for
    :func:`load_error`), and 0 of a process without a gain to take (two integrators: P
    control's offset is then ``1/|Kc|``, as for one)."""
    try:
        kind, gain = process_gain(process)
    except ModelSpecError:
        return 0.0
    return 0.0 if kind == "integrating" else 1.0 / abs(gain)


def _json_float(value: float | None) -> float | None:
    """``value`` for JSON: ``None`` for missing, infinite or NaN."""
    return None if value is None or not math.isfinite(value) else float(value)


# ---------------------------------------------------------------------------- ch. 5 analysis
@dataclass(frozen=True)
class TuningRule:
    """One row of thesis Table 5.11: what stiction does and which retune helps.

    Attributes
    ----------
    process_type, dead_time, control
        The row's dynamics: process class, whether it has dead time, P or PI.
    deadband_oscillation, stiction_oscillation : str
        The table's verdicts ("no", "yes", "maybe, if ...").
    actions : tuple of str
        Recommended changes in the table's order.
    new_oscillation : tuple of str
        Expected result of each action: "no" (removed) or "reduced".
    """

    process_type: ProcessType
    dead_time: bool
    control: Control
    deadband_oscillation: str
    stiction_oscillation: str
    actions: tuple[Action, ...]
    new_oscillation: tuple[str, ...]

    def label(self) -> str:
        """The row as the table names it, e.g. ``"SR & PI, dead time"``."""
        kind = "SR" if self.process_type == "self-regulating" else "Int."
        return f"{kind} & {self.control}, {'dead time' if self.dead_time else 'no dead time'}"

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {
            "dynamics": self.label(),
            "deadband_oscillation": self.deadband_oscillation,
            "stiction_oscillation": self.stiction_oscillation,
            "actions": list(self.actions),
            "new_oscillation": list(self.new_oscillation),
        }


TABLE_5_11: tuple[TuningRule, ...] = (
    TuningRule("self-regulating", False, "P", "no", "no", (), ()),
    # printed "maybe, if tau_I > tau"; section 5.3.1 and the action give tau_I < tau
    TuningRule("self-regulating", False, "PI", "no", "maybe, if Ti < tau", ("raise Ti",), ("no",)),
    TuningRule(
        "self-regulating", True, "P", "no", "maybe, if F_imag <= -pi S/(4J)", ("lower Kc",), ("no",)
    ),
    TuningRule(
        "self-regulating",
        True,
        "PI",
        "no",
        "yes, if theta + tau > Ti",
        ("raise Ti", "lower Kc"),
        ("no", "reduced"),
    ),
    TuningRule("integrating", False, "P", "no", "yes", ("lower Kc",), ("reduced",)),
    TuningRule("integrating", False, "PI", "yes", "yes", ("raise Ti",), ("reduced",)),
    TuningRule("integrating", True, "P", "no", "yes", ("lower Kc",), ("reduced",)),
    TuningRule(
        "integrating",
        True,
        "PI",
        "yes, if Ti > theta",
        "yes, if Ti > theta",
        ("Ti below theta", "raise Ti"),
        ("no", "reduced"),
    ),
)
"""Thesis Table 5.11, one :class:`TuningRule` per row (SR: self-regulating)."""


def table_5_11_rule(process_type: ProcessType, dead_time: bool, control: Control) -> TuningRule:
    """The row of :data:`TABLE_5_11` for a process class and controller type.

    Examples
    --------
    >>> table_5_11_rule("integrating", True, "PI").actions
    ('Ti below theta', 'raise Ti')
    """
    for rule in TABLE_5_11:
        if (rule.process_type, rule.dead_time, rule.control) == (process_type, dead_time, control):
            return rule
    raise ModelSpecError(f"no Table 5.11 row for {process_type!r}, {control!r}")


@dataclass(frozen=True)
class SingleLoopAnalysis:
    """The chapter 5 analysis of one loop at its current tuning.

    Attributes
    ----------
    process : FirstOrderProcess
    control : {"P", "PI"}
    kc, ti : float
        Controller gain (modulus) and integral time, s (``inf`` for P).
    omega_f, f_imag : float or None
        ``w*`` (rad/s) and the imaginary part of ``G Gc`` there: the point F
        (Eqs. 5.16, 5.18, 5.25, 5.27, 5.36, 5.39).
    omega_h, h_real : float or None
        ``w**`` and the real part there: the point H (Eqs. 5.17, 5.19, 5.26,
        5.28, 5.36, 5.40).
    low_frequency_real : float
        ``lim Re G Gc`` for ``w -> 0``; ``d`` of Eq. 5.24 is its modulus.
    band_edge_imag : float or None
        ``-pi S / (4 J)``, where ``-1/N`` starts (Table 5.1); None for a
        deadband (``J = 0``) or a valve without an (S, J) equivalent.
    rule : TuningRule
        The row of Table 5.11.
    thesis_oscillation : bool or None
        Whether the chapter's conditions predict a stiction cycle (e.g.
        Eq. 5.20, ``F_imag <= -pi S/(4J)``); None where the chapter leaves it
        open ("maybe").
    thesis_linear_stable : bool
        The chapter's test ``H_real > -1`` (section 5.3.2).
    linear_stable : bool
        The Nyquist count of the loop with a healthy valve (rigorous).
    df_oscillation : bool
        Whether the describing function predicts a stable limit cycle
        (:func:`analytics.limit_cycle.predict_limit_cycles`).
    """

    process: FirstOrderProcess
    control: Control
    kc: float
    ti: float
    omega_f: float | None
    f_imag: float | None
    omega_h: float | None
    h_real: float | None
    low_frequency_real: float
    band_edge_imag: float | None
    rule: TuningRule
    thesis_oscillation: bool | None
    thesis_linear_stable: bool
    linear_stable: bool
    df_oscillation: bool

    def to_dict(self) -> dict[str, Any]:
        """JSON form (infinite values as null)."""
        return {
            "process": {
                **dataclasses.asdict(self.process),
                "tau": None if self.process.integrating else self.process.tau,
            },
            "control": self.control,
            "Kc": self.kc,
            "Ti": _json_float(self.ti),
            "omega_f": self.omega_f,
            "f_imag": self.f_imag,
            "omega_h": self.omega_h,
            "h_real": self.h_real,
            "low_frequency_real": _json_float(self.low_frequency_real),
            "band_edge_imag": self.band_edge_imag,
            "rule": self.rule.to_dict(),
            "thesis_oscillation": self.thesis_oscillation,
            "thesis_linear_stable": self.thesis_linear_stable,
            "linear_stable": self.linear_stable,
            "df_oscillation": self.df_oscillation,
        }


def _thesis_oscillation(
    process: FirstOrderProcess, ti: float, f_imag: float | None, edge: float | None, j: float
) -> bool | None:
    """Stiction (``J > 0``) or deadband cycle by the conditions of sections 5.3-5.4."""
    delayed = process.theta > 0
    if j == 0:  # the deadband column of Table 5.11
        if not process.integrating or not math.isfinite(ti):
            return False
        return not delayed or ti > process.theta
    if process.integrating:  # always, except PI with Ti < theta
        return not (delayed and math.isfinite(ti) and ti < process.theta)
    if not delayed:
        return None if math.isfinite(ti) and ti < process.tau else False
    if f_imag is None or edge is None:
        return None
    if math.isfinite(ti) and f_imag > 0:  # Fig. 5.6: theta + tau > Ti
        return True
    return f_imag <= edge  # Eq. 5.20


def analyse_single_loop(
    process: TransferFunction,
    controller: PIDController,
    valve: ValveModel,
    *,
    hold_delay: float = 0.0,
    describing: DescribingChoice = "model",
) -> SingleLoopAnalysis:
    """The single-loop analysis of thesis sections 5.3-5.4 at the current tuning.

    Parameters
    ----------
    process : TransferFunction
        ``K e^{-theta s}/(tau s + 1)`` or ``K e^{-theta s}/s``.
    controller : PIDController
        P or PI (no derivative action), acting so that the loop gain is positive.
    valve : ValveModel
        The sticky valve; its (S, J) give the band edge ``-pi S/(4J)``.
    hold_delay : float
        Dead time added for the sampled controller's hold, s (``dt / 2``).
    describing : {"model", "equivalent"}
        Describing function of the valve for ``df_oscillation`` (see
        :func:`analytics.limit_cycle.predict_limit_cycles`).

    Examples
    --------
    The temperature loop of thesis section 5.5.1 under Kc = 10, Ti = 10 s has
    ``Ti < theta + tau`` (Eq. 5.44), so F lies on the positive imaginary axis
    and the loop cycles whatever the stiction:

    >>> from analytics.valves import ChoudhuryValve
    >>> g = TransferFunction.fopdt(0.4346, 27.58, 6.0)
    >>> a = analyse_single_loop(g, PIDController.ideal(10.0, 10.0), ChoudhuryValve(4.0, 2.0))
    >>> round(a.omega_f, 4), round(a.f_imag, 3), a.thesis_oscillation, a.df_oscillation
    (0.5029, 0.319, True, True)
    >>> round(a.band_edge_imag, 2), a.rule.actions
    (-1.57, ('raise Ti', 'lower Kc'))
    """
    tuning = Tuning.of(controller)
    first_order = FirstOrderProcess.of(process, hold_delay=hold_delay)
    control: Control = "P" if math.isinf(tuning.ti) else "PI"
    kc, ti = abs(tuning.kc), tuning.ti
    omega_f, omega_h = first_order.crossing_frequencies(ti)
    f_imag = h_real = None
    if omega_f is not None:
        f_imag = float(first_order.open_loop_response(kc, ti, np.array([omega_f]))[0].imag)
    if omega_h is not None:
        h_real = float(first_order.open_loop_response(kc, ti, np.array([omega_h]))[0].real)
    sj = equivalent_sj(valve)
    edge = None
    if sj is not None and sj[1] > 0:
        edge = table_5_1_limits(*sj)["A->S/2"].imag
    prediction = predict_limit_cycles(
        process, controller, valve, hold_delay=hold_delay, describing=describing
    )
    return SingleLoopAnalysis(
        process=first_order,
        control=control,
        kc=kc,
        ti=ti,
        omega_f=omega_f,
        f_imag=f_imag,
        omega_h=omega_h,
        h_real=h_real,
        low_frequency_real=first_order.low_frequency_real(kc, ti),
        band_edge_imag=edge,
        rule=table_5_11_rule(first_order.kind, first_order.theta > 0, control),
        thesis_oscillation=None
        if sj is None
        else _thesis_oscillation(first_order, ti, f_imag, edge, sj[1]),
        thesis_linear_stable=h_real is None or h_real > -1.0,
        linear_stable=prediction.linear_stable,
        df_oscillation=prediction.oscillates,
    )


# ---------------------------------------------------------------------------- safe-tuning map
@dataclass(frozen=True)
class SafeTuningMap:
    """Thesis Fig. 5.17 over a ``Kc x Ti`` grid.

    Attributes
    ----------
    kc : ndarray, shape (p,)
        Controller gains (moduli; the sign follows the controller action).
    ti : ndarray, shape (q,)
        Integral times, s; ``[inf]`` for P control.
    linear_stable : ndarray of bool, shape (p, q)
        The loop is stable with a healthy valve (bottom of Fig. 5.17).
    limit_cycle_free : ndarray of bool, shape (p, q)
        ``G Gc`` does not meet ``-1/N(A)``: no stiction limit cycle (top).
        False where the linear loop is unstable (it oscillates anyway).
    max_sensitivity : ndarray, shape (p, q)
        ``Ms = max_w 1/|1 + G Gc|`` on the frequency grid; ``inf`` where unstable.
    omega, amplitude : ndarray, shape (p, q)
        Frequency (rad/s) and OP amplitude (% of travel) of the predicted
        stable cycle, interpolated on the grid (the crossing with the largest
        ``A``, which is the stable one for a stable loop [3]_); NaN without one.
    """

    kc: FloatArray
    ti: FloatArray
    linear_stable: BoolArray
    limit_cycle_free: BoolArray
    max_sensitivity: FloatArray
    omega: FloatArray
    amplitude: FloatArray

    @property
    def safe(self) -> BoolArray:
        """Stable and free of stiction limit cycles: the overlap of Fig. 5.17."""
        return np.asarray(self.linear_stable & self.limit_cycle_free, dtype=np.bool_)

    @property
    def travel_rate(self) -> FloatArray:
        """Predicted valve travel per second, ``4 A / T = 2 A w / pi`` (% per s); 0 without a
        cycle, ``inf`` where the linear loop is unstable."""
        rate = np.where(self.limit_cycle_free, 0.0, 2 * self.amplitude * self.omega / np.pi)
        return np.asarray(np.where(self.linear_stable, rate, np.inf), dtype=np.float64)

    def to_dict(self) -> dict[str, Any]:
        """JSON form: the grid and the two masks of Fig. 5.17 (rows: ``Kc``)."""

        def matrix(values: FloatArray) -> list[list[float | None]]:
            return [[_json_float(float(v)) for v in row] for row in values]

        return {
            "Kc": self.kc.tolist(),
            "Ti": [_json_float(float(t)) for t in self.ti],
            "linear_stable": self.linear_stable.tolist(),
            "limit_cycle_free": self.limit_cycle_free.tolist(),
            "max_sensitivity": matrix(self.max_sensitivity),
            "omega": matrix(self.omega),
            "amplitude": matrix(self.amplitude),
        }


def _map_action(controller: PIDController) -> Literal["reverse", "direct"]:
    """Action of ``controller`` once its gain is taken as a modulus."""
    reverse = (controller.action == "reverse") == (controller.kp >= 0)
    return "reverse" if reverse else "direct"


def _unstable_roots(loop: ComplexArray, types: IntArray) -> tuple[IntArray, BoolArray]:
    """Right-half-plane closed-loop roots of each row of ``loop`` (``L(jw)`` on a grid
    from the low-frequency asymptote to where ``|L| < 1/2``), by the argument
    principle on the Nyquist D-contour indented around the ``types`` poles at
    ``s = 0``; and whether the grid resolved the argument (steps below ``pi/3``).

    By symmetry the contour's change of ``arg(1 + L)`` is twice the change from
    ``0+`` to ``inf`` plus the indentation, ``-type pi``: starting the unwrapped
    argument on the branch nearest ``-type pi/2`` makes it ``2 arg(1 + L(j inf))``.
    """
    phase = np.unwrap(np.angle(1 + loop), axis=1)
    phase += 2 * np.pi * np.round((-types[:, None] * np.pi / 2 - phase[:, :1]) / (2 * np.pi))
    roots = np.asarray(-2 * np.round(phase[:, -1] / (2 * np.pi)), dtype=np.int64)
    resolved = (np.abs(np.diff(phase, axis=1)).max(axis=1) <= np.pi / 3) & (roots >= 0)
    return roots, np.asarray(resolved, dtype=np.bool_)


def _cycle_brackets(
    loop: ComplexArray, omega: FloatArray, df: ValveDescribingFunction, searched: BoolArray
) -> tuple[IntArray, FloatArray, FloatArray]:
    """Crossings of ``-1/N`` by the ``searched`` rows of ``loop``: row, ``w`` and ``A``
    of each. A row can only cross where ``|L|`` lies within the moduli of the
    ``-1/N`` curve; rows are grouped by that frequency window and each group is
    searched over its own span (a tabulated curve has many branches, each a pass)."""
    _, curve = df.table()
    modulus = np.abs(loop)
    reachable = (modulus >= 0.99 * np.abs(curve).min()) & (modulus <= 1.01 * np.abs(curve).max())
    reachable &= searched[:, None]
    rows = np.flatnonzero(reachable.any(axis=1))
    first = np.argmax(reachable[rows], axis=1)
    last = reachable.shape[1] - 1 - np.argmax(reachable[rows, ::-1], axis=1)
    order = np.argsort(first, kind="stable")
    found: list[IntArray] = []
    omegas: list[FloatArray] = []
    amplitudes: list[FloatArray] = []
    for group in np.array_split(order, max(1, math.ceil(order.size / _BRACKET_GROUP))):
        if group.size == 0:
            continue
        span = slice(max(int(first[group].min()) - 1, 0), int(last[group].max()) + 2)
        hit, w, amplitude = df.crossings(loop[rows[group], span], omega[span])
        found.append(np.asarray(rows[group][hit], dtype=np.int64))
        omegas.append(w)
        amplitudes.append(amplitude)
    if not found:
        return np.empty(0, dtype=np.int64), np.empty(0), np.empty(0)
    return np.concatenate(found), np.concatenate(omegas), np.concatenate(amplitudes)


def _frequency_grid(
    response: Callable[[FloatArray], ComplexArray],
    process: TransferFunction,
    kc: FloatArray,
    ti: FloatArray,
    delay: float,
    radius: float,
) -> FloatArray:
    """Frequencies resolving every tuning's ``L(jw)`` where it can meet ``-1/N`` or
    wind around -1: from the low-frequency asymptote to where the most aggressive
    tuning's ``|L|`` falls below ``radius / 2`` for good; log-spaced (as densely as
    :mod:`analytics.limit_cycle` brackets) and at most ``pi / (8 delay)`` apart so
    that the dead time's rotation is resolved."""
    coarse = np.geomspace(1e-9, 1e5, 561)
    strongest = kc.max() * (1 - 1j / (ti.min() * coarse)) * response(coarse)
    above = np.flatnonzero(np.abs(strongest) >= radius / 2)
    if above.size and above[-1] == coarse.size - 1:
        raise ModelSpecError("the loop gain does not roll off at high frequency")
    top = coarse[above[-1] + 1] * 2 if above.size else coarse[int(np.argmax(np.abs(strongest)))]
    corners = [abs(r) for r in (*process.poles(), *np.roots(process.num)) if abs(r) > 0]
    corners += [1 / t for t in (delay, ti.max(), ti.min()) if 0 < t < math.inf]
    bottom = 1e-3 * min([*corners, top / 10])
    weakest = kc.min() * (1 - 1j / (ti.max() * coarse)) * response(coarse)
    if process.integrators > 0 or math.isfinite(ti.max()):
        for _ in range(12):
            if abs(np.interp(np.log(bottom), np.log(coarse), np.abs(weakest))) >= 10:
                break
            bottom /= 10
    grid = np.geomspace(bottom, top, max(50, math.ceil(GRID_PER_DECADE * math.log10(top / bottom))))
    if delay > 0:
        linear = np.linspace(0.0, top, math.ceil(top * delay * 8 / np.pi) + 2)
        grid = np.union1d(grid, linear[linear > bottom])
    return grid


def safe_tuning_map(
    process: TransferFunction,
    valve: ValveModel,
    kc: ArrayLike,
    ti: ArrayLike | None = None,
    *,
    action: Literal["reverse", "direct"] = "reverse",
    hold_delay: float = 0.0,
    describing: DescribingChoice = "model",
) -> SafeTuningMap:
    """Where on a ``Kc x Ti`` grid the loop is stable and free of stiction cycles (Fig. 5.17).

    For every tuning ``L(jw) = Kc (1 + 1/(j w Ti)) G(jw) e^{-j w hold_delay}``
    is evaluated on one frequency grid. Linear stability: the argument of
    ``1 + L`` along the Nyquist D-contour (indented around the poles at 0);
    rows whose phase steps are too coarse to count on (near the stability
    boundary) are recounted on a 16 times finer grid, then, if still unresolved,
    with :func:`analytics.limit_cycle.predict_limit_cycles`. Stiction: a sign
    change of the gap between ``L`` and the ``-1/N`` curve on each of its
    branches (the bracketing of :mod:`analytics.limit_cycle`). A tabulated
    ``-1/N`` (He, Stenman, Karnopp) has many narrow branches, and a crossing
    through one can fall between grid points: :func:`advise` confirms a safe
    pick with the exact solver.

    Parameters
    ----------
    process : TransferFunction
        Open-loop stable or integrating process (no right-half-plane poles).
    valve : ValveModel
        The sticky valve.
    kc : array_like
        Controller gains, > 0 (moduli).
    ti : array_like, optional
        Integral times, s, > 0; omitted for P control.
    action : {"reverse", "direct"}
        Controller action; it must make the loop gain positive.
    hold_delay : float
        Extra dead time for the controller's hold, s.
    describing : {"model", "equivalent"}
        Describing function of the valve (as in
        :func:`~analytics.limit_cycle.predict_limit_cycles`).

    Raises
    ------
    ModelSpecError
        A healthy valve, an unstable process, a positive-feedback action,
        non-positive gains or integral times, or a loop that does not roll off.

    Examples
    --------
    The temperature loop of section 5.5.1: the original tuning cycles, the
    retune Kc = 2, Ti = 100 s is safe (thesis Fig. 5.17):

    >>> from analytics.valves import ChoudhuryValve
    >>> g = TransferFunction.fopdt(0.4346, 27.58, 6.0)
    >>> m = safe_tuning_map(g, ChoudhuryValve(4.0, 2.0), [2.0, 10.0], [10.0, 100.0])
    >>> m.linear_stable.tolist(), m.safe.tolist()
    ([[True, True], [True, True]], [[False, True], [False, False]])
    """
    if isinstance(valve, IdealValve):
        raise ModelSpecError("the valve is healthy: there is no stiction cycle to map")
    kc_values = np.atleast_1d(np.asarray(kc, dtype=np.float64))
    ti_values = np.array([math.inf]) if ti is None else np.atleast_1d(np.asarray(ti, dtype=float))
    if kc_values.ndim != 1 or not np.all(np.isfinite(kc_values) & (kc_values > 0)):
        raise ModelSpecError(f"controller gains Kc must be finite and > 0, got {kc_values}")
    if ti_values.ndim != 1 or not np.all(ti_values > 0) or np.any(np.isnan(ti_values)):
        raise ModelSpecError(f"integral times Ti must be > 0 s, got {ti_values}")
    if action not in ("reverse", "direct"):
        raise ModelSpecError(f"action must be 'reverse' or 'direct', got {action!r}")
    if np.any(process.poles().real > 1e-12 * np.maximum(1.0, np.abs(process.poles()))):
        raise ModelSpecError("the safe-tuning map needs an open-loop stable or integrating process")
    sign = 1.0 if action == "reverse" else -1.0
    if sign * process.dc_gain <= 0:
        raise ModelSpecError(
            f"a {action}-acting controller on a process of gain {process.dc_gain:g} is "
            "positive feedback; use the other action"
        )
    delay = process.delay + hold_delay
    df = _describing_function(valve, describing)
    _, curve = df.table()
    radius = min(1.0, float(np.abs(curve).min()))

    def response(omega: FloatArray) -> ComplexArray:
        with np.errstate(divide="ignore", invalid="ignore"):
            values = process.frequency_response(omega) * np.exp(-1j * omega * hold_delay)
        return np.asarray(sign * values, dtype=np.complex128)

    omega = _frequency_grid(response, process, kc_values, ti_values, delay, radius)
    pairs = np.array([(k, t) for k in kc_values for t in ti_values])
    n_rows = len(pairs)
    integrators = process.integrators

    def loop_response(rows: slice | IntArray, frequencies: FloatArray) -> ComplexArray:
        gains, times = pairs[rows, :1], pairs[rows, 1:]
        return np.asarray(
            gains * (1 - 1j / (times * frequencies)) * response(frequencies), dtype=np.complex128
        )

    def types(rows: slice | IntArray) -> IntArray:
        return np.asarray(integrators + np.isfinite(pairs[rows, 1]), dtype=np.int64)

    stable = np.zeros(n_rows, dtype=np.bool_)
    resolved = np.zeros(n_rows, dtype=np.bool_)
    free = np.ones(n_rows, dtype=np.bool_)
    sensitivity = np.full(n_rows, np.inf)
    cycle_omega = np.full(n_rows, np.nan)
    cycle_amplitude = np.full(n_rows, np.nan)
    rows_per_chunk = max(1, _CHUNK_SAMPLES // omega.size)
    for start in range(0, n_rows, rows_per_chunk):
        chunk = slice(start, min(start + rows_per_chunk, n_rows))
        loop = loop_response(chunk, omega)
        roots, resolved[chunk] = _unstable_roots(loop, types(chunk))
        stable[chunk] = roots == 0
        sensitivity[chunk] = 1 / np.abs(1 + loop).min(axis=1)
        searched = stable[chunk] | ~resolved[chunk]
        rows, w, amplitude = _cycle_brackets(loop, omega, df, searched)
        for row, w_k, a_k in zip(start + rows, w, amplitude, strict=True):
            free[row] = False
            if not a_k <= cycle_amplitude[row]:  # also when NaN: the first crossing
                cycle_omega[row], cycle_amplitude[row] = w_k, a_k
    unresolved = np.flatnonzero(~resolved)
    if unresolved.size:  # near the stability boundary: 16 times finer, then exact
        fine = np.geomspace(omega[:-1], omega[1:], 17, endpoint=False, axis=1).ravel()
        fine = np.append(fine, omega[-1])
        loop = loop_response(unresolved, fine)
        roots, resolved[unresolved] = _unstable_roots(loop, types(unresolved))
        stable[unresolved] = roots == 0
        sensitivity[unresolved] = 1 / np.abs(1 + loop).min(axis=1)
    for index in np.flatnonzero(~resolved):
        k, t = pairs[index]
        controller = PIDController(kp=sign * k, ki=0.0 if math.isinf(t) else sign * k / t)
        exact = predict_limit_cycles(
            process, controller, valve, hold_delay=hold_delay, describing=describing
        )
        stable[index] = exact.linear_stable
    sensitivity[~stable] = np.inf
    free[~stable] = False
    shape = (kc_values.size, ti_values.size)
    return SafeTuningMap(
        kc=kc_values,
        ti=ti_values,
        linear_stable=stable.reshape(shape),
        limit_cycle_free=free.reshape(shape),
        max_sensitivity=sensitivity.reshape(shape),
        omega=cycle_omega.reshape(shape),
        amplitude=cycle_amplitude.reshape(shape),
    )


# ---------------------------------------------------------------------------- advice
@dataclass(frozen=True)
class Tuning:
    """A P or PI tuning ``Kc (1 + 1/(Ti s))`` (thesis Eq. 5.10).

    Attributes
    ----------
    kc : float
        Proportional gain, signed as the controller's ``kp``.
    ti : float
        Integral time, s; ``inf`` for P control.
    """

    kc: float
    ti: float

    @classmethod
    def of(cls, controller: PIDController) -> Tuning:
        """The tuning of a P or PI controller.

        Raises
        ------
        ModelSpecError
            If the controller has derivative action or no proportional gain.
        """
        if controller.kd != 0:
            raise ModelSpecError(
                "tuning advice covers P and PI controllers (thesis ch. 5); "
                f"this one has derivative gain Kd = {controller.kd:g}"
            )
        if controller.kp == 0:
            raise ModelSpecError("tuning advice needs a proportional gain Kc != 0")
        ti = math.inf if controller.ki == 0 else controller.kp / controller.ki
        if ti <= 0:
            raise ModelSpecError(
                f"Kp = {controller.kp:g} and Ki = {controller.ki:g} have opposite signs "
                "(negative integral time)"
            )
        return cls(controller.kp, ti)

    def apply(self, controller: PIDController) -> PIDController:
        """``controller`` with this tuning (action, limits and bias kept), in parallel gains."""
        ki = 0.0 if math.isinf(self.ti) else self.kc / self.ti
        return dataclasses.replace(controller, kp=self.kc, ki=ki, ideal_form=None)

    def to_dict(self) -> dict[str, float | None]:
        """``{"Kc", "Ti"}`` (``Ti`` null for P control)."""
        return {"Kc": self.kc, "Ti": _json_float(self.ti)}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Tuning:
        """The tuning of :meth:`to_dict`'s form (``Ti`` null: P control).

        >>> Tuning.from_dict({"Kc": 2.0, "Ti": None})
        Tuning(kc=2.0, ti=inf)
        """
        return cls(float(d["Kc"]), math.inf if d["Ti"] is None else float(d["Ti"]))


@dataclass(frozen=True)
class OscillationEffect:
    """An oscillation as predicted (describing function) or simulated.

    Attributes
    ----------
    oscillating : bool
        A stable limit cycle is predicted, or the simulation cycles.
    period_s : float or None
        Period of that cycle, s.
    amplitudes : tuple of float or None
        OP amplitude per loop, % of travel (``None`` where a loop's OP does
        not cycle or, predicted, where the valve is healthy).
    travel_rate : float
        Valve travel per second of the sticky loops, ``sum 4 A_k / T``
        (% per s): 0 without a cycle, ``inf`` if the loop is unstable.
    note : str
        "unstable", "diverges", or the simulation's note.
    """

    oscillating: bool
    period_s: float | None
    amplitudes: tuple[float | None, ...]
    travel_rate: float
    note: str = ""

    @classmethod
    def predicted(cls, prediction: Prediction) -> OscillationEffect:
        """The most vigorous stable cycle of a prediction (none: removed)."""
        n = len(prediction.sticky)
        if not prediction.linear_stable:
            return cls(True, None, (None,) * n, math.inf, "unstable")
        best: OscillationEffect | None = None
        for cycle in prediction.stable_cycles:
            rate = sum(
                4 * a / cycle.period_s
                for a, sticky in zip(cycle.amplitudes, prediction.sticky, strict=True)
                if sticky and a is not None
            )
            if best is None or rate > best.travel_rate:
                best = cls(True, cycle.period_s, cycle.amplitudes, rate)
        return best or cls(False, None, (None,) * n, 0.0)

    @classmethod
    def simulated(
        cls, simulation: SimulatedLimitCycle, sticky: Sequence[bool]
    ) -> OscillationEffect:
        """The steady oscillation measured at the end of a simulation."""
        n = len(sticky)
        if simulation.note == "diverges":
            return cls(True, None, (None,) * n, math.inf, "diverges")
        rate = sum(
            4 * a / t
            for a, t, s in zip(simulation.amplitudes, simulation.periods_s, sticky, strict=True)
            if s and a is not None and t is not None
        )
        return cls(
            simulation.oscillating,
            simulation.period_s,
            simulation.amplitudes,
            rate,
            simulation.note,
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {
            "oscillating": self.oscillating,
            "period_s": self.period_s,
            "amplitudes": list(self.amplitudes),
            "travel_rate": _json_float(self.travel_rate),
            "note": self.note,
        }


@dataclass(frozen=True)
class Recommendation:
    """A retune with its predicted and its simulated effect.

    Attributes
    ----------
    tunings : tuple of Tuning
        New tuning of every loop (unchanged loops repeat their current one).
    source : str
        Where the candidate comes from: a Table 5.11 action, the safe-tuning
        map, or the section 5.6 search.
    predicted : OscillationEffect
        Describing-function prediction.
    simulated : OscillationEffect
        Verification by simulation.
    outcome : {"removed", "reduced", "not improved", "unstable"}
        Judged on the simulation against the current tuning's: "removed" if
        it no longer cycles, "reduced" if its valve travel rate falls by at
        least :data:`MIN_REDUCTION`.
    max_sensitivity : float or None
        ``Ms`` of the retuned loop (single loop only).
    travel_rate_with_noise : float or None
        Valve travel per second of the sticky loops (% per s) with the measured PV
        noise (:meth:`_Evaluator.travel_with_noise`); None when no noise was given.
    load_error_ratio : float or None
        The error a load step at a valve leaves, against the current tuning's: the
        largest over the loops (:func:`load_error`); at most :data:`MAX_LOAD_ERROR_RATIO`
        (or the bound given to :func:`advise`) for a retune the search may pick.
    """

    tunings: tuple[Tuning, ...]
    source: str
    predicted: OscillationEffect
    simulated: OscillationEffect
    outcome: Outcome
    max_sensitivity: float | None = None
    travel_rate_with_noise: float | None = None
    load_error_ratio: float | None = None

    @property
    def offered(self) -> bool:
        """True if the simulation confirms an improvement."""
        return self.outcome in ("removed", "reduced")

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {
            "tunings": [t.to_dict() for t in self.tunings],
            "source": self.source,
            "predicted": self.predicted.to_dict(),
            "simulated": self.simulated.to_dict(),
            "outcome": self.outcome,
            "max_sensitivity": None
            if self.max_sensitivity is None
            else _json_float(self.max_sensitivity),
            "travel_rate_with_noise": self.travel_rate_with_noise,
            "load_error_ratio": _json_float(self.load_error_ratio),
        }


@dataclass(frozen=True)
class TuningAdvice:
    """Tuning advice for a loop or a multi-loop unit (``/api/v1/loops/{id}/advice``).

    Attributes
    ----------
    loops : tuple of str
        Loop names.
    current : tuple of Tuning
        The tunings the advice starts from.
    current_predicted, current_simulated : OscillationEffect
        The oscillation at the current tuning, predicted and simulated.
    analysis : SingleLoopAnalysis or None
        The chapter 5 analysis (single first-order loops only).
    maps : dict of int to SafeTuningMap
        Safe-tuning map of each sticky loop (isolated, section 5.6 step 1).
    recommendations : tuple of Recommendation
        Verified retunes, best first.
    rejected : tuple of Recommendation
        Candidates the simulation did not confirm.
    notes : tuple of str
        Why an action was not offered, what the simulation adds.
    current_travel_rate_with_noise : float or None
        The current tuning's valve travel with the measured PV noise; None when no
        noise was given.
    max_load_error_ratio : float
        The bound on a retune's :attr:`Recommendation.load_error_ratio` the search kept to.
    """

    loops: tuple[str, ...]
    current: tuple[Tuning, ...]
    current_predicted: OscillationEffect
    current_simulated: OscillationEffect
    analysis: SingleLoopAnalysis | None
    maps: dict[int, SafeTuningMap]
    recommendations: tuple[Recommendation, ...]
    rejected: tuple[Recommendation, ...]
    notes: tuple[str, ...]
    current_travel_rate_with_noise: float | None = None
    max_load_error_ratio: float = MAX_LOAD_ERROR_RATIO

    def to_dict(self) -> dict[str, Any]:
        """JSON form for the service."""
        return {
            "loops": list(self.loops),
            "current": [t.to_dict() for t in self.current],
            "current_predicted": self.current_predicted.to_dict(),
            "current_simulated": self.current_simulated.to_dict(),
            "analysis": None if self.analysis is None else self.analysis.to_dict(),
            "maps": {self.loops[k]: m.to_dict() for k, m in self.maps.items()},
            "recommendations": [r.to_dict() for r in self.recommendations],
            "rejected": [r.to_dict() for r in self.rejected],
            "notes": list(self.notes),
            "current_travel_rate_with_noise": self.current_travel_rate_with_noise,
            "max_load_error_ratio": _json_float(self.max_load_error_ratio),
        }


def excited_model(
    model: ClosedLoopModel, *, duration: float, step: float | None = None
) -> ClosedLoopModel:
    """``model`` set up to show its steady limit cycle in a simulation of ``duration`` s.

    A loop with a sticky valve and without a setpoint schedule gets a setpoint
    step at 10 s of ``step`` (default: the largest stick band, at least 1 % of
    span): a loop at rest with a stuck valve stays at rest, which would hide any
    cycle.  Loops with a healthy valve keep their setpoint (stepped only when no
    valve is sticky): a step moves the operating point by ``G(0)^-1`` times the
    step, and in an ill-conditioned unit that can drive a healthy loop's OP to
    its limit and open it (a 4 % step of every loop of thesis column Eq. 2.10
    needs its reboiler OP 68 % of span above its rest; at its limit the model
    cycles as the 2 x 2 of loops 1 and 2, at 143 s instead of the 3 x 3's 200 s).
    Noise disturbances are dropped, so that cycles of different tunings are
    compared without the scatter noise puts on their period; setpoint
    schedules and deterministic disturbances are kept.

    Examples
    --------
    >>> from analytics.scenarios import level_loop
    >>> model = excited_model(level_loop(), duration=500.0)
    >>> model.loops[0].setpoint, model.loops[0].disturbances, model.duration
    ([(20.0, 55.0)], (), 500.0)
    """
    if step is None:
        step = max(1.0, *(loop.valve.stick_band for loop in model.loops))
    sticky = [not isinstance(loop.valve, IdealValve) for loop in model.loops]
    kicked = sticky if any(sticky) else [True] * len(sticky)
    loops = tuple(
        dataclasses.replace(
            loop,
            setpoint=[(10.0, loop.pv_bias + step)] if loop.setpoint is None and kick
            else loop.setpoint,
            disturbances=tuple(d for d in loop.disturbances if d.kind != "noise"),
        )
        for loop, kick in zip(model.loops, kicked, strict=True)
    )
    return dataclasses.replace(model, loops=loops, duration=duration)


def _with_tunings(model: ClosedLoopModel, tunings: Sequence[Tuning]) -> ClosedLoopModel:
    loops = tuple(
        dataclasses.replace(loop, controller=tuning.apply(loop.controller))
        for loop, tuning in zip(model.loops, tunings, strict=True)
    )
    return dataclasses.replace(model, loops=loops)


def _process_matrix(model: ClosedLoopModel) -> tuple[tuple[TransferFunction | None, ...], ...]:
    if isinstance(model.process, TransferFunction):
        return ((model.process,),)
    return model.process


class _Evaluator:
    """Predicts and simulates retunes of one model, against its current tuning."""

    def __init__(
        self,
        model: ClosedLoopModel,
        *,
        hold_delay: float,
        describing: DescribingChoice,
        measurement_noise: Sequence[float] | None = None,
    ) -> None:
        self.model = model
        self.hold_delay = hold_delay
        self.describing = describing
        self.measurement_noise = measurement_noise
        self._noisy: dict[tuple[Tuning, ...], float] = {}
        self.sticky = tuple(not isinstance(loop.valve, IdealValve) for loop in model.loops)
        self._predictions: dict[tuple[Tuning, ...], Prediction] = {}
        self._simulations: dict[tuple[Tuning, ...], OscillationEffect] = {}
        self.current = tuple(Tuning.of(loop.controller) for loop in model.loops)
        self.inverse_gains = tuple(inverse_gain(row[i])  # type: ignore[arg-type]
                                   for i, row in enumerate(_process_matrix(model)))
        self.current_predicted = OscillationEffect.predicted(self.predict(self.current))
        self.current_simulated = self.simulate(self.current)

    def predict(self, tunings: tuple[Tuning, ...]) -> Prediction:
        """Describing-function prediction at ``tunings`` (cached)."""
        if tunings not in self._predictions:
            controllers = [
                t.apply(loop.controller) for t, loop in zip(tunings, self.model.loops, strict=True)
            ]
            self._predictions[tunings] = predict_limit_cycles(
                self.model.process,
                controllers,
                [loop.valve for loop in self.model.loops],
                hold_delay=self.hold_delay,
                describing=self.describing,
            )
        return self._predictions[tunings]

    def duration(self, tunings: tuple[Tuning, ...]) -> float:
        """Long enough for 30 periods of the slowest relevant cycle: the predicted
        ones and the period of each diagonal loop's gain crossover."""
        periods = [c.period_s for c in self.predict(tunings).limit_cycles]
        for i, row in enumerate(_process_matrix(self.model)):
            g = row[i]
            assert g is not None  # the simulator refuses a missing diagonal entry
            omega = np.geomspace(1e-6, 1e3, 1801)
            ti = tunings[i].ti
            gain = np.abs(tunings[i].kc * (1 - 1j / (ti * omega)) * g.frequency_response(omega))
            above = np.flatnonzero(gain >= 1)
            if above.size and above[-1] < omega.size - 1:
                periods.append(2 * np.pi / omega[above[-1]])
        slowest = max(periods, default=0.0)
        return min(max(self.model.duration, 30 * slowest), _MAX_SAMPLES * self.model.dt)

    def simulate(self, tunings: tuple[Tuning, ...]) -> OscillationEffect:
        """The simulated cycle at ``tunings`` (cached); not run if the loop is unstable."""
        if tunings not in self._simulations:
            if not self.predict(tunings).linear_stable:
                effect = OscillationEffect(True, None, (None,) * len(tunings), math.inf, "unstable")
            else:
                model = excited_model(
                    _with_tunings(self.model, tunings), duration=self.duration(tunings)
                )
                effect = OscillationEffect.simulated(simulate_limit_cycle(model), self.sticky)
            self._simulations[tunings] = effect
        return self._simulations[tunings]

    def travel_with_noise(self, tunings: tuple[Tuning, ...]) -> float | None:
        """Valve travel per second of the sticky loops (mean ``|MV_k - MV_(k-1)|`` / dt, % per s) at
        ``tunings`` with the measured PV noise added to every loop (cached; None without a
        noise level). The setpoint step of :func:`excited_model`, then :data:`NOISY_RUN_S` s
        of which the first :data:`NOISY_SETTLE_S` are left out, averaged over the runs of
        :data:`NOISE_SEEDS`; the same noise sequences for every tuning (common random
        numbers), so the comparison carries little of its scatter. A noise-free model can
        settle where the loop, shaken by its noise, keeps slipping: a retune that removes
        the noise-free cycle with more gain can make the valve travel more."""
        if self.measurement_noise is None:
            return None
        if tunings not in self._noisy:
            excited = excited_model(_with_tunings(self.model, tunings), duration=NOISY_RUN_S)
            rates = []
            for seed in NOISE_SEEDS:
                loops = tuple(
                    dataclasses.replace(loop, disturbances=(
                        *loop.disturbances,
                        Disturbance("noise", std, at="measurement", seed=seed + 1000 * i)))
                    for i, (loop, std) in enumerate(
                        zip(excited.loops, self.measurement_noise, strict=True))
                )
                run = dataclasses.replace(excited, loops=loops).run()
                settled = run.t >= NOISY_SETTLE_S
                rates.append(sum(np.abs(np.diff(run.mv[i][settled])).mean() / self.model.dt
                                 for i, sticky in enumerate(self.sticky) if sticky))
            self._noisy[tunings] = float(np.mean(rates))
        return self._noisy[tunings]

    def load_error_ratio(self, tunings: tuple[Tuning, ...]) -> float:
        """The largest ratio over the loops of :func:`load_error` at ``tunings`` to the
        current tuning's."""
        return max(
            float(load_error(new.kc, new.ti, g) / load_error(now.kc, now.ti, g))
            for new, now, g in zip(tunings, self.current, self.inverse_gains, strict=True))

    def recommend(
        self, tunings: tuple[Tuning, ...], source: str, max_sensitivity: float | None = None
    ) -> Recommendation:
        """Predict and simulate ``tunings`` and judge them against the current tuning;
        with a noise level, an improvement must also hold with the noise
        (:meth:`travel_with_noise`, by :data:`MIN_REDUCTION`)."""
        prediction = self.predict(tunings)
        predicted = OscillationEffect.predicted(prediction)
        simulated = self.simulate(tunings)
        baseline = self.current_simulated
        outcome: Outcome
        if not prediction.linear_stable or math.isinf(simulated.travel_rate):
            outcome = "unstable"
        elif not baseline.oscillating:  # nothing the simulation could confirm
            outcome = "not improved"
        elif not simulated.oscillating and not simulated.note:
            outcome = "removed"
        elif simulated.oscillating and simulated.travel_rate < (1 - MIN_REDUCTION) * (
            baseline.travel_rate
        ):
            outcome = "reduced"
        else:
            outcome = "not improved"
        noisy = None
        if outcome in ("removed", "reduced"):
            noisy, current = self.travel_with_noise(tunings), self.travel_with_noise(self.current)
            if noisy is not None and current is not None and noisy > (1 - MIN_REDUCTION) * current:
                outcome = "not improved"
        return Recommendation(tunings, source, predicted, simulated, outcome, max_sensitivity,
                              noisy, self.load_error_ratio(tunings))


def _search_box(
    tuning: Tuning, kc_factors: tuple[float, float], ti_factors: tuple[float, float], points: int
) -> tuple[FloatArray, FloatArray | None]:
    kc = abs(tuning.kc) * np.geomspace(*kc_factors, points)
    ti = None if math.isinf(tuning.ti) else tuning.ti * np.geomspace(*ti_factors, points)
    return kc, ti


def _robustness_limit(current: SafeTuningMap, ms_limit: float) -> float:
    """Largest ``Ms`` a recommendation may have: ``ms_limit``, or the current
    tuning's if that is stable and already less robust (never make it worse)."""
    ms_now = float(current.max_sensitivity[0, 0])
    return max(ms_limit, ms_now) if math.isfinite(ms_now) else ms_limit


def _load_error_ratios(tuning_map: SafeTuningMap, current: Tuning, inverse_k: float
                       ) -> FloatArray:
    """:func:`load_error` over the grid of ``tuning_map`` (rows ``Kc``) against ``current``."""
    kc, ti = np.meshgrid(tuning_map.kc, tuning_map.ti, indexing="ij")
    return load_error(kc, ti, inverse_k) / load_error(current.kc, current.ti, inverse_k)


def _pick(tuning_map: SafeTuningMap, allowed: BoolArray) -> tuple[int, int, bool] | None:
    """The best grid point of ``allowed``: if any is safe, the safe one with the most
    integral action (``Kc / Ti``, or ``Kc`` for P); else the one with the smallest
    predicted valve travel rate. Returns its indices and whether it is safe."""
    if not allowed.any():
        return None
    safe = allowed & tuning_map.safe
    kc, ti = np.meshgrid(tuning_map.kc, tuning_map.ti, indexing="ij")
    if safe.any():
        score = np.where(safe, kc / np.where(np.isinf(ti), 1.0, ti), -np.inf)
        i, j = np.unravel_index(int(np.argmax(score)), score.shape)
    else:
        score = np.where(allowed, tuning_map.travel_rate, np.inf)
        i, j = np.unravel_index(int(np.argmin(score)), score.shape)
    return int(i), int(j), bool(safe.any())


def advise(
    model: ClosedLoopModel,
    *,
    kc_factors: tuple[float, float] = (0.1, 2.0),
    ti_factors: tuple[float, float] = (0.2, 10.0),
    points: int = 30,
    ms_limit: float = MS_LIMIT,
    include_hold: bool = True,
    describing: DescribingChoice = "model",
    multi_loop_points: int = 3,
    max_sweeps: int = 2,
    measurement_noise: Sequence[float] | None = None,
    max_load_error_ratio: float = MAX_LOAD_ERROR_RATIO,
) -> TuningAdvice:
    """Retunes that remove or reduce a stiction cycle, each verified by simulation.

    Single loop (thesis sections 5.3-5.5): the chapter 5 analysis of the
    current tuning (first-order processes), each action of its Table 5.11 row
    applied to its one parameter, and the best point of the safe-tuning map
    over ``Kc`` in ``kc_factors`` and ``Ti`` in ``ti_factors`` times the
    current values (``points`` each). Candidates must be stable with ``Ms <=
    ms_limit`` (or no less robust than the current tuning, if that is already
    beyond it) and leave at most ``max_load_error_ratio`` times the current
    tuning's error after a load step (:func:`load_error`). Among those the
    map's pick is the safe one with the most integral action ``Kc / Ti``
    (``Kc`` for P control), confirmed by the exact solver: it removes the
    predicted cycle at the least cost in disturbance rejection; if no tuning
    is safe, the one with the smallest predicted valve travel ``4 A / T``. A
    one-parameter action picks the same way along its parameter.

    Multi-loop (section 5.6): step 1 maps each sticky loop in isolation and
    keeps its stable tunings with ``Ms <= ms_limit`` on a
    ``multi_loop_points x multi_loop_points`` grid (loops with healthy valves
    keep their tuning, as in section 5.6.1); step 2 searches the combinations
    loop by loop (``max_sweeps`` rounds) for the smallest predicted valve
    travel (Eq. 3.14 with ERRATA item 9; no cycle counts as 0, ties go to the
    most integral action), subject to the stability of the whole system. Where
    the describing function misses the current cycle (the simulation cycles,
    the DF predicts nothing), the simulated valve travel ranks instead.

    Every candidate is predicted (:func:`~analytics.limit_cycle.predict_limit_cycles`)
    and simulated (:func:`~analytics.limit_cycle.simulate_limit_cycle`) from a
    setpoint step (:func:`excited_model`); it is offered only if the simulated
    cycle is removed or its valve travel rate falls by :data:`MIN_REDUCTION`.
    Offered retunes come removed first, then those the describing function
    says remove the cycle, then by simulated valve travel.

    Parameters
    ----------
    model : ClosedLoopModel
        Process, P/PI controllers and valves; its ``dt`` is the controller's
        sampling period and its ``duration`` the shortest verification run.
    include_hold : bool
        Count the controller's zero-order hold as ``dt / 2`` of dead time.
    describing : {"model", "equivalent"}
        Describing function of the valves.
    measurement_noise : sequence of float, optional
        Each loop's PV noise (standard deviation, PV units): a retune is offered
        only if it also makes the valves travel less than the current tuning with
        that noise on every PV (:meth:`_Evaluator.travel_with_noise`).  Without it
        the verification is noise-free.
    max_load_error_ratio : float
        Bound (>= 1) on how much a retune may slow the rejection of loads
        (:data:`MAX_LOAD_ERROR_RATIO`); ``inf`` searches the whole box.

    Raises
    ------
    ModelSpecError
        No sticky valve, derivative action, or a model the map cannot handle; a
        noise level per loop that is missing or negative.
    """
    if not all(f > 0 for f in (*kc_factors, *ti_factors)) or not (
        kc_factors[0] < kc_factors[1] and ti_factors[0] < ti_factors[1]
    ):
        raise ModelSpecError(
            f"kc_factors and ti_factors must be (low, high) with 0 < low < high, "
            f"got {kc_factors} and {ti_factors}"
        )
    if points < 2 or multi_loop_points < 1:
        raise ModelSpecError(
            f"points must be >= 2 and multi_loop_points >= 1, got {points}, {multi_loop_points}"
        )
    if not max_load_error_ratio >= 1:
        raise ModelSpecError(
            f"max_load_error_ratio must be >= 1 (1: no slower than now), "
            f"got {max_load_error_ratio}")
    if all(isinstance(loop.valve, IdealValve) for loop in model.loops):
        raise ModelSpecError("no sticky valve: there is no stiction cycle to advise on")
    if measurement_noise is not None and (
        len(measurement_noise) != len(model.loops)
        or not all(math.isfinite(x) and x >= 0 for x in measurement_noise)
    ):
        raise ModelSpecError(
            f"measurement_noise needs one finite standard deviation >= 0 per loop "
            f"({len(model.loops)}), got {list(measurement_noise)}"
        )
    hold_delay = model.dt / 2 if include_hold else 0.0
    evaluator = _Evaluator(model, hold_delay=hold_delay, describing=describing,
                           measurement_noise=measurement_noise)
    names = tuple(loop.name or f"loop{i + 1}" for i, loop in enumerate(model.loops))
    if len(model.loops) == 1:
        candidates, analysis, maps, notes = _single_loop_plan(
            model, evaluator, kc_factors, ti_factors, points, hold_delay, describing, ms_limit,
            max_load_error_ratio,
        )
    else:
        analysis = None
        candidates, maps, notes = _multi_loop_plan(
            evaluator,
            kc_factors,
            ti_factors,
            multi_loop_points,
            hold_delay,
            describing,
            ms_limit,
            max_sweeps,
            max_load_error_ratio,
        )
    recommendations: list[Recommendation] = []
    seen: set[tuple[Tuning, ...]] = set()
    for tunings, source, ms in candidates:
        if tunings in seen or tunings == evaluator.current:
            continue
        seen.add(tunings)
        recommendations.append(evaluator.recommend(tunings, source, ms))
    offered = sorted(
        (r for r in recommendations if r.offered),
        key=lambda r: (
            r.outcome != "removed",
            r.predicted.travel_rate > 0,
            r.simulated.travel_rate,
        ),
    )
    if not evaluator.current_simulated.oscillating:
        note = evaluator.current_simulated.note
        notes.append(
            f"the simulation of the current tuning shows no steady cycle{f' ({note})' * bool(note)}"
            ": no retune can be verified as an improvement"
        )
    elif not evaluator.current_predicted.oscillating:
        notes.append(
            "the simulation cycles although the describing function predicts no limit "
            "cycle: a stick-slip cycle whose OP fundamental stays below S/2"
        )
    # checked with noise only once the noise-free simulation confirmed them
    withdrawn = [r for r in recommendations
                 if r.travel_rate_with_noise is not None and not r.offered]
    if withdrawn:
        current_noisy = evaluator.travel_with_noise(evaluator.current)
        worst = max(withdrawn, key=lambda r: r.travel_rate_with_noise or 0.0)
        notes.append(
            f"{len(withdrawn)} retune(s) that improve the noise-free simulation make the "
            "valve travel as much or more with the measured PV noise, and are not offered "
            f"(up to {(worst.travel_rate_with_noise or 0.0) / (current_noisy or math.inf):.2g} "
            "times the current tuning's travel): more gain lets the noise slip the valve"
        )
    if any(r.predicted.travel_rate == 0 and r.outcome == "reduced" for r in recommendations):
        notes.append(
            "where the describing function predicts no cycle, the simulation still shows "
            "a slow stick-slip cycle (integral action walks OP through the stick band): "
            "the retune reduces the oscillation rather than removing it"
        )
    return TuningAdvice(
        loops=names,
        current=evaluator.current,
        current_predicted=evaluator.current_predicted,
        current_simulated=evaluator.current_simulated,
        analysis=analysis,
        maps=maps,
        recommendations=tuple(offered),
        rejected=tuple(r for r in recommendations if not r.offered),
        notes=tuple(notes),
        current_travel_rate_with_noise=evaluator.travel_with_noise(evaluator.current),
        max_load_error_ratio=max_load_error_ratio,
    )


Candidate = tuple[tuple[Tuning, ...], str, float | None]


def _single_loop_plan(
    model: ClosedLoopModel,
    evaluator: _Evaluator,
    kc_factors: tuple[float, float],
    ti_factors: tuple[float, float],
    points: int,
    hold_delay: float,
    describing: DescribingChoice,
    ms_limit: float,
    max_load_error_ratio: float,
) -> tuple[list[Candidate], SingleLoopAnalysis | None, dict[int, SafeTuningMap], list[str]]:
    """Candidates for one loop: each Table 5.11 action along its one parameter, then
    the best point of the safe-tuning map (see :func:`advise`)."""
    loop = model.loops[0]
    process = model.process
    assert isinstance(process, TransferFunction)
    current = evaluator.current[0]
    sign = math.copysign(1.0, current.kc)
    kc0, ti0 = abs(current.kc), current.ti
    notes: list[str] = []
    candidates: list[Candidate] = []

    def tuning_map(kc: ArrayLike, ti: ArrayLike | None) -> SafeTuningMap:
        return safe_tuning_map(
            process,
            loop.valve,
            kc,
            ti,
            action=_map_action(loop.controller),
            hold_delay=hold_delay,
            describing=describing,
        )

    same_ti = None if math.isinf(ti0) else [ti0]
    robustness = _robustness_limit(tuning_map([kc0], same_ti), ms_limit)

    def consider(line: SafeTuningMap, source: str, what: str) -> None:
        """Add the best point of ``line``; a safe pick is confirmed by the exact solver
        first (the map's bracketing can miss a crossing through a narrow branch of
        a tabulated ``-1/N`` curve), and dropped from the map if refuted."""
        robust = line.linear_stable & (line.max_sensitivity <= robustness)
        slowed = _load_error_ratios(line, current, evaluator.inverse_gains[0])
        allowed = robust & (slowed <= max_load_error_ratio * (1 + 1e-9))
        beyond = _pick(line, robust & line.safe & ~allowed)
        if beyond is not None and not (allowed & line.safe).any():
            i, j, _ = beyond
            notes.append(
                f"{source}: the map predicts no cycle at Kc = {line.kc[i]:.3g}, Ti = "
                f"{line.ti[j]:.3g} s, but that tuning leaves {slowed[i, j]:.3g} times the "
                f"current error after a load step (the bound is {max_load_error_ratio:.3g}): "
                "not offered")
        for _ in range(_MAX_REFUTED):
            picked = _pick(line, allowed)
            if picked is None:
                notes.append(
                    f"{source} not offered: every {what} in the search box leaves the linear "
                    f"loop unstable or less robust than Ms = {robustness:.3g}"
                    if not robust.any() else
                    f"{source} not offered: every {what} in the search box that keeps the "
                    f"loop stable with Ms <= {robustness:.3g} leaves more than "
                    f"{max_load_error_ratio:.3g} times the current error after a load step: "
                    "the loop would hardly control, the valve needs repair"
                )
                return
            i, j, safe = picked
            tuning = Tuning(sign * float(line.kc[i]), float(line.ti[j]))
            if safe and evaluator.predict((tuning,)).oscillates:
                allowed[i, j] = False
                continue
            if source == "safe-tuning map":
                source += (
                    ": no predicted cycle, most integral action"
                    if safe
                    else ": smallest predicted valve travel (no safe tuning in the box)"
                )
            candidates.append(((tuning,), source, float(line.max_sensitivity[i, j])))
            return

    try:
        analysis: SingleLoopAnalysis | None = analyse_single_loop(
            process, loop.controller, loop.valve, hold_delay=hold_delay, describing=describing
        )
    except ModelSpecError as exc:
        analysis = None
        notes.append(f"no chapter 5 analysis: {exc}")
    if analysis is not None:
        theta = analysis.process.theta
        for action in analysis.rule.actions:
            source = f"Table 5.11 ({analysis.rule.label()}): {action}"
            if action == "lower Kc":
                lower = kc0 * np.geomspace(kc_factors[0], 1.0, points)[:-1]
                consider(tuning_map(lower, same_ti), source, "lower Kc")
            elif action == "raise Ti":
                higher = ti0 * np.geomspace(1.0, ti_factors[1], points)[1:]
                consider(tuning_map([kc0], higher), source, "higher Ti")
            elif theta > 0:  # "Ti below theta"
                below = np.geomspace(min(ti0 * ti_factors[0], theta / 10), theta, points)[:-1]
                consider(tuning_map([kc0], below), source, f"Ti < theta = {theta:g} s")
    kc, ti = _search_box(current, kc_factors, ti_factors, points)
    full = tuning_map(kc, ti)
    consider(full, "safe-tuning map", "tuning")
    return candidates, analysis, {0: full}, notes


def _multi_loop_plan(
    evaluator: _Evaluator,
    kc_factors: tuple[float, float],
    ti_factors: tuple[float, float],
    points: int,
    hold_delay: float,
    describing: DescribingChoice,
    ms_limit: float,
    max_sweeps: int,
    max_load_error_ratio: float,
) -> tuple[list[Candidate], dict[int, SafeTuningMap], list[str]]:
    """Section 5.6: safe intervals per isolated sticky loop, then the combination."""
    model = evaluator.model
    matrix = _process_matrix(model)
    maps: dict[int, SafeTuningMap] = {}
    options: dict[int, list[Tuning]] = {}
    notes: list[str] = []
    for k, loop in enumerate(model.loops):
        if not evaluator.sticky[k]:
            continue
        current = evaluator.current[k]
        diagonal = matrix[k][k]
        assert diagonal is not None
        kc, ti = _search_box(current, kc_factors, ti_factors, points)
        try:
            tuning_map = safe_tuning_map(
                diagonal,
                loop.valve,
                kc,
                ti,
                action=_map_action(loop.controller),
                hold_delay=hold_delay,
                describing=describing,
            )
            here = safe_tuning_map(
                diagonal,
                loop.valve,
                [abs(current.kc)],
                None if math.isinf(current.ti) else [current.ti],
                action=_map_action(loop.controller),
                hold_delay=hold_delay,
                describing=describing,
            )
        except ModelSpecError as exc:
            raise ModelSpecError(f"loop {k + 1} on its own (section 5.6 step 1): {exc}") from None
        maps[k] = tuning_map
        sign = math.copysign(1.0, current.kc)
        robustness = _robustness_limit(here, ms_limit)
        slowed = _load_error_ratios(tuning_map, current, evaluator.inverse_gains[k])
        allowed = (tuning_map.linear_stable & (tuning_map.max_sensitivity <= robustness)
                   & (slowed <= max_load_error_ratio * (1 + 1e-9)))
        options[k] = [current] + [
            Tuning(sign * float(tuning_map.kc[i]), float(tuning_map.ti[j]))
            for i, j in zip(*np.nonzero(allowed), strict=True)
        ]
        if len(options[k]) == 1:
            notes.append(
                f"loop {k + 1}: no tuning in the search box is stable in isolation with "
                f"Ms <= {robustness:.3g} and leaves at most {max_load_error_ratio:.3g} times "
                "the current error after a load step; kept as it is"
            )

    blind = evaluator.current_simulated.oscillating and not evaluator.current_predicted.oscillating

    def score(tunings: tuple[Tuning, ...]) -> tuple[float, float]:
        """Valve travel of the cycle, then the least integral action; unstable: infinite.
        The travel is the describing function's, or the simulation's where the DF
        misses the current cycle (a stick-slip cycle below ``S/2``)."""
        travel = OscillationEffect.predicted(evaluator.predict(tunings)).travel_rate
        if math.isinf(travel):
            return math.inf, math.inf
        if blind:
            travel = evaluator.simulate(tunings).travel_rate
        integral = sum(
            math.log(abs(t.kc) / (t.ti if math.isfinite(t.ti) else 1.0))
            for k, t in enumerate(tunings)
            if k in options
        )
        return travel, -integral

    best = evaluator.current
    best_score = score(best)
    for _ in range(max_sweeps):
        improved = False
        for k, choices in options.items():
            for choice in choices:
                trial = (*best[:k], choice, *best[k + 1 :])
                if trial == best:
                    continue
                trial_score = score(trial)
                if trial_score < best_score:
                    best, best_score, improved = trial, trial_score, True
        if not improved:
            break
    candidates: list[Candidate] = []
    if best != evaluator.current:
        candidates.append(
            (best, "section 5.6: combination with the smallest predicted cycle", None)
        )
    else:
        notes.append("section 5.6: no combination in the search box predicts a smaller cycle")
    return candidates, maps, notes


#: The loop model reproduces the measured cycle if its period is within this
#: fraction of the measured one (issue 19's rule before any advice).
PERIOD_TOLERANCE = 0.15
#: ... and its OP amplitude (first harmonic) within this fraction.
AMPLITUDE_TOLERANCE = 0.25


def relative_error(model: float | None, measured: float | None) -> float | None:
    """``(model - measured) / measured``; None without both, or a measured value <= 0."""
    if model is None or measured is None or not measured > 0 or not math.isfinite(model):
        return None
    return (model - measured) / measured


@dataclass(frozen=True)
class CycleAgreement:
    """The cycle of the loop model against the cycle measured on the plant.

    Advice is only as good as the model it is computed on: before the effect
    of a retune is believed, the model at the current tuning must cycle as
    the loop does, within :data:`PERIOD_TOLERANCE` in period and
    :data:`AMPLITUDE_TOLERANCE` in OP amplitude (both the first harmonic, the
    ``A`` of the describing function, thesis Eq. 3.4).  The simulation of the
    model is the reference; the describing-function prediction is compared
    too, because it is only a first-harmonic approximation (Atherton 1975,
    ch. 7 [3]_): a stick-slip cycle under integral action is far from
    sinusoidal and its harmonic balance can miss the period by tens of percent
    where the simulation of the same model does not.

    Attributes
    ----------
    measured_period_s, measured_amplitude : float or None
        The loop's cycle (diagnosis: period and OP amplitude, % of span).
    predicted_period_error, simulated_period_error : float or None
        ``(model - measured) / measured``; None where a side has no cycle.
    predicted_amplitude_error, simulated_amplitude_error : float or None
        The same for the OP amplitude.
    """

    measured_period_s: float | None
    measured_amplitude: float | None
    predicted_period_error: float | None
    simulated_period_error: float | None
    predicted_amplitude_error: float | None
    simulated_amplitude_error: float | None

    @classmethod
    def of(cls, advice: TuningAdvice, period_s: float | None,
           amplitude: float | None) -> CycleAgreement:
        """Compare the current tuning's predicted and simulated cycle of ``advice``
        (loop 0) with the measured ``period_s`` and OP ``amplitude``."""
        predicted, simulated = advice.current_predicted, advice.current_simulated
        return cls.between(period_s, amplitude,
                           (predicted.period_s, predicted.amplitudes[0]),
                           (simulated.period_s, simulated.amplitudes[0]))

    @classmethod
    def between(cls, period_s: float | None, amplitude: float | None,
                predicted: tuple[float | None, float | None],
                simulated: tuple[float | None, float | None]) -> CycleAgreement:
        """Compare a model's ``predicted`` and ``simulated`` cycle, each ``(period_s, OP
        amplitude)`` (None where that side has no cycle), with the measured one.

        >>> c = CycleAgreement.between(200.0, None, (None, None), (210.0, None))
        >>> c.simulated_period_error, c.reproduces, c.predicted_agrees
        (0.05, True, False)
        """
        return cls(
            period_s, amplitude,
            relative_error(predicted[0], period_s),
            relative_error(simulated[0], period_s),
            relative_error(predicted[1], amplitude),
            relative_error(simulated[1], amplitude),
        )

    @property
    def reproduces(self) -> bool:
        """The simulated model cycles with the measured period and amplitude."""
        period, amplitude = self.simulated_period_error, self.simulated_amplitude_error
        return (period is not None and abs(period) <= PERIOD_TOLERANCE
                and (amplitude is None or abs(amplitude) <= AMPLITUDE_TOLERANCE))

    @property
    def predicted_agrees(self) -> bool:
        """The describing function predicts the measured period."""
        error = self.predicted_period_error
        return error is not None and abs(error) <= PERIOD_TOLERANCE

    @property
    def agree(self) -> bool:
        """The model reproduces the measured cycle in simulation and in prediction."""
        return self.reproduces and self.predicted_agrees

    def explanation(self) -> str:
        """What agrees and what does not, in words.

        >>> CycleAgreement(100.0, 2.0, 0.35, 0.05, 0.1, -0.1).explanation()[:58]
        'the model reproduces the measured cycle (100 s): simulated'
        """
        if self.measured_period_s is None:
            return "no cycle was measured: the model cannot be checked against the loop"
        measured = f"{self.measured_period_s:.3g} s"
        if self.simulated_period_error is None:
            return (f"the model disagrees with the measurement: the loop cycles at {measured} "
                    "but the simulated model does not cycle; its process or valve estimate "
                    "is wrong, so the predicted effects below are not reliable")
        parts = [f"simulated period {self.simulated_period_error:+.0%}"]
        if self.simulated_amplitude_error is not None:
            parts.append(f"amplitude {self.simulated_amplitude_error:+.0%}")
        if self.reproduces:
            text = f"the model reproduces the measured cycle ({measured}): {', '.join(parts)}"
        else:
            text = (f"the model disagrees with the measurement ({measured}): {', '.join(parts)}"
                    f" (limits {PERIOD_TOLERANCE:.0%} and {AMPLITUDE_TOLERANCE:.0%}); the "
                    "identified process or valve does not describe this cycle, so the "
                    "predicted effects below are not reliable")
        if self.predicted_period_error is None:
            text += "; the describing function predicts no cycle"
        elif not self.predicted_agrees:
            text += (f"; the describing function's period is {self.predicted_period_error:+.0%}"
                     " off (first-harmonic approximation of a non-sinusoidal stick-slip "
                     "cycle): the simulation is the reference")
        return text

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {
            "measured": {"period_s": self.measured_period_s,
                         "amplitude": self.measured_amplitude},
            "period_error": {"predicted": self.predicted_period_error,
                             "simulated": self.simulated_period_error},
            "amplitude_error": {"predicted": self.predicted_amplitude_error,
                                "simulated": self.simulated_amplitude_error},
            "reproduces": self.reproduces,
            "agree": self.agree,
            "explanation": self.explanation(),
        }


#: Gain margins offered by :func:`detune` (Astrom & Hagglund 2006, sec. 4.8 [2]_:
#: 2-5 is the usual range).
DETUNING_GAIN_MARGINS = (2.0, 3.0)


#: Share of the window OP sat at a limit from which a steady cycle may be a linear
#: loop past its stability limit, its amplitude held by saturation.
SATURATED_SHARE = 0.05
#: Envelope variation below which a cycle counts as forced (steady amplitude).
FORCED_ENVELOPE_CV = 0.05
#: Fewest cycles in the window for that judgement.
ENVELOPE_MIN_CYCLES = 12.0

CycleOrigin = Literal["forced", "own", "unknown"]


def cycle_origin(envelope_variation: float | None, cycles: float, saturation: float | None
                 ) -> tuple[CycleOrigin, str]:
    """Whether a cycle with a healthy valve is the loop's own or forced, and why.

    A loop that cycles by its own tuning is a lightly damped linear loop driven
    by noise: its cycle waxes and wanes, the envelope Rayleigh-distributed
    (coefficient of variation 0.52, Rice 1945).  A cycle that keeps its
    amplitude is forced from outside -- a disturbance, another loop's cycle --
    and detuning does not remove it, unless OP saturates
    (:data:`SATURATED_SHARE`): a loop past its stability limit is held at a
    steady amplitude by its output limits.  The envelope's variation is
    estimated from few cycles with a large spread, so the judgement needs
    :data:`ENVELOPE_MIN_CYCLES` and a clearly steady envelope
    (:data:`FORCED_ENVELOPE_CV`).  In the synthetic library, windows of 12
    cycles: external sines 0.01; over-tuned loops at least 0.04-0.09, their 10th
    percentile 0.13-0.21 (one window of 296 of the flow loop fell below 0.05).

    >>> cycle_origin(0.01, 20.0, 0.0)[0], cycle_origin(0.4, 20.0, 0.0)[0]
    ('forced', 'own')
    >>> cycle_origin(0.01, 20.0, 0.3)[0], cycle_origin(0.01, 7.0, 0.0)[0]
    ('unknown', 'unknown')
    """
    if envelope_variation is None or cycles < ENVELOPE_MIN_CYCLES:
        return "unknown", (f"whether the cycle is the loop's own (its amplitude waxes and "
                           f"wanes) or forced from outside (a steady amplitude) needs "
                           f"{ENVELOPE_MIN_CYCLES:g} cycles in the window; it holds "
                           f"{cycles:.1f}")
    if envelope_variation >= FORCED_ENVELOPE_CV:
        return "own", (f"its amplitude waxes and wanes (envelope variation "
                       f"{envelope_variation:.2f}; a noise-driven resonance gives about "
                       f"{RAYLEIGH_ENVELOPE_CV:.2f}), as a loop cycling by its own tuning does")
    if saturation is not None and saturation >= SATURATED_SHARE:
        return "unknown", (f"the cycle keeps its amplitude (envelope variation "
                           f"{envelope_variation:.2f}) but OP saturates {saturation:.0%} of "
                           "the time: a loop past its stability limit, held by its output "
                           "limits, looks the same")
    return "forced", (f"the cycle keeps its amplitude (envelope variation "
                      f"{envelope_variation:.2f}; a loop cycling by its own tuning waxes and "
                      f"wanes, about {RAYLEIGH_ENVELOPE_CV:.2f}) and OP does not saturate: it "
                      "is forced from outside (a disturbance or another loop's cycle) and "
                      "detuning would not remove it; look for its source")


@dataclass(frozen=True)
class Detuning:
    """Result of :func:`detune`: ``Kc`` lowered by each gain margin, ``Ti`` kept.

    Attributes
    ----------
    current : Tuning
        The loop's tuning, at its ultimate point.
    ultimate_period_s : float
        The measured period, taken as the ultimate period, s.
    gain_margins : tuple of float
        The gain margins offered: ``Kc / m`` for each ``m``.
    notes : tuple of str
        What the advice assumes.
    """

    current: Tuning
    ultimate_period_s: float
    gain_margins: tuple[float, ...]
    notes: tuple[str, ...]

    @property
    def recommendations(self) -> tuple[Tuning, ...]:
        """The detuned tunings, one per gain margin."""
        return tuple(dataclasses.replace(self.current, kc=self.current.kc / m)
                     for m in self.gain_margins)

    def to_dict(self) -> dict[str, Any]:
        """JSON form (the advice endpoint's ``detuning``)."""
        return {
            "kind": "detuning",
            "current": [self.current.to_dict()],
            "ultimate_period_s": self.ultimate_period_s,
            "recommendations": [{
                "tunings": [tuning.to_dict()],
                "source": f"ultimate point at the measured period: Kc / {m:g}",
                "gain_margin": m,
                "predicted": {"oscillating": False, "period_s": None},
            } for m, tuning in zip(self.gain_margins, self.recommendations, strict=True)],
            "notes": list(self.notes),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Detuning:
        """The detuning of :meth:`to_dict`'s form (the recommendations are derived)."""
        (current,) = d["current"]
        return cls(Tuning.from_dict(current), float(d["ultimate_period_s"]),
                   tuple(float(r["gain_margin"]) for r in d["recommendations"]),
                   tuple(d["notes"]))


def detune(tuning: Tuning, period_s: float,
           gain_margins: Sequence[float] = DETUNING_GAIN_MARGINS) -> Detuning:
    """Detuning of a loop that cycles by itself (a linear oscillation: over-tuned).

    A loop whose linear closed loop cycles steadily sits at its ultimate
    point: ``L(j w_u) = Kc C(j w_u) G(j w_u) = -1`` at the measured
    ``w_u = 2 pi / period_s`` (Astrom & Hagglund 2006, sec. 6.2, the point
    relay autotuning measures [2]_).  Scaling ``Kc`` alone does not change the
    phase of ``L``, so the phase crossover stays at ``w_u`` and the gain
    margin of ``Kc / m`` is ``m``, whatever the process.  A noise-driven,
    lightly damped loop sits a little inside the stability limit (gain margin
    slightly above 1), so the margins given are lower bounds.  ``Ti`` is kept.

    Examples
    --------
    >>> advice = detune(Tuning(3.0, 4.0), 11.5)
    >>> [(t.kc, m) for t, m in zip(advice.recommendations, advice.gain_margins)]
    [(1.5, 2.0), (1.0, 3.0)]
    """
    if not period_s > 0 or any(not m > 1 for m in gain_margins):
        raise ModelSpecError(f"need a period > 0 and gain margins > 1, got {period_s}, "
                             f"{list(gain_margins)}")
    return Detuning(tuning, period_s, tuple(gain_margins), (
        f"the loop cycles at {period_s:.3g} s with a healthy valve: taken as its "
        "ultimate point (gain margin 1 now), lowering Kc by m gives a gain margin of "
        "at least m; if the cycle comes from a disturbance entering the loop, detuning "
        "does not remove it (its period would not change with Kc)",
    ))
