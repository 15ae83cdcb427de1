"""Limit cycles of loops with sticky valves: describing-function prediction and simulation.

A sticky valve driven by a sinusoidal OP of amplitude ``A`` passes on the
fundamental harmonic ``N(A) A`` (:mod:`analytics.describing`). Around a
closed loop the fundamental must reproduce itself (harmonic balance, thesis
Eqs. 3.11-3.14): with ``P(jw) = Gc(jw) G(jw)`` (row ``i`` scaled by
controller ``i``) and the OP phasors ``x``::

    (I + P(jw) diag(N_1(A_1), ..., N_n(A_n))) x = 0,     |x_k| = A_k  (sticky k)

Healthy valves have ``N = 1``. For one loop this is Eq. 3.16 (Eq. 5.11),
``G Gc = -1/N(A)``; with one sticky valve in a multi-loop system it is Eq. 3.20,
``L_eq(jw) = -1/N(A)`` with the other loops closed. With two or more sticky
valves ``det(...) = 0`` (Eqs. 3.14, 3.23) is one complex equation in
``(w, A_1, ..., A_p)``: ERRATA item 9 adds that the amplitudes must be the moduli
of the null vector ``x``. Solving for ``x`` itself (reference phase 0, free
phasors for the healthy loops) gives a square system of ``2n`` real equations
in ``2n`` unknowns, so solutions are isolated points.

* :func:`predict_limit_cycles` (and :func:`predict_model` for a
  :class:`~analytics.simulation.ClosedLoopModel`) finds every solution with
  ``w`` in a frequency range, judges its stability and refuses a loop that is
  unstable without stiction.
* :func:`simulate_limit_cycle` measures the exact limit cycle in a closed-loop
  simulation; :func:`compare` sets prediction and simulation side by side.
* :func:`nyquist_curves` returns the data of the Nyquist/DF plot.

Method. For one moving valve (and, with the other valves held at a grid of
amplitudes, for several) the equivalent loop ``L_eq(jw)`` is sampled on a
dense log grid (from the principal minors of ``P``, computed once);
``-1/N(A)`` is a curve whose phase is monotone in ``A`` on each branch, so
the phase condition picks ``A(w)`` and a sign change of the
magnitude condition ``log|L_eq| - log|1/N(A(w))|`` brackets a crossing. Every
bracket seeds a damped Gauss-Newton (Levenberg-Marquardt) solution of the
square system, run for all seeds at once; converged points are deduplicated.
A sticky valve may also stay stuck (``N = 0``) while the others cycle, if its
OP amplitude stays below its threshold; those solutions are searched too. For
one moving valve the end of the ``-1/N`` curve (``A -> S/2``, thesis Table 5.1)
is checked as well: a Nyquist curve through that point gives thesis Eq. 5.33.

Stability (Loeb's criterion [3]_, the quasi-static perturbation of the harmonic
balance): with ``F(s, A) = det(I + P(s) N(A))``, scaling the moving
amplitudes by ``1 + e`` moves the root ``s = jw`` by
``ds = -j (dF/de) / (dF/dw) e``; the cycle is stable if a larger amplitude
damps (``Re ds < 0``) and, at the slightly larger amplitude, the quasi-linear
loop has no other right-half-plane root (generalised Nyquist count of
``det(I + P(s) N)`` around the D-contour). For one loop this is the familiar
rule that ``-1/N(A)`` must cross the Nyquist curve from the encircled to the
outer side as ``A`` grows.

The analysis is continuous-time. A digital controller sampled at ``dt`` with a
zero-order hold adds about ``dt/2`` of dead time; pass it as ``hold_delay``.

Limits of the method, seen against simulation (tests/analytics/test_limit_cycle.py):
slow stick-slip cycles driven by integral action, in which the valve rests for
most of the period, have an OP whose fundamental lies below ``S/2`` where
``N = 0``; no sinusoidal-input DF represents them (thesis section 5.5.1 retune,
the column under tuning 3.25). Near the band edge the DF amplitude and period
are least accurate. The numerical DF of sampled-data models (He, Stenman) and
of Karnopp's model (which depends on frequency; it is tabulated at 1 rad/s)
is only approximate.

References
----------
.. [1] Thesis, chapter 3 (Eqs. 3.11-3.16, 3.20, 3.23, Table 3.2) and chapter 5
   (Eq. 5.11, Table 5.1, Eq. 5.33, section 5.5.1); ERRATA items 1, 6, 9.
.. [2] Gelb & Vander Velde (1968), *Multiple-Input Describing Functions and
   Nonlinear System Design*, McGraw-Hill, ch. 2-3 (harmonic balance, limit
   cycle stability).
.. [3] Loeb, J. M. (1956), "Advances in nonlinear servo theory", in
   *Frequency Response*, ed. Oldenburger, Macmillan (the Loeb criterion);
   Atherton, D. P. (1975), *Nonlinear Control Engineering*, Van Nostrand, ch. 7.
.. [4] MacFarlane & Postlethwaite (1977), "The generalized Nyquist stability
   criterion and multivariable root loci", Int. J. Control 25:81-127.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
import scipy.interpolate
import scipy.optimize
from numpy.typing import ArrayLike, NDArray

from analytics.describing import (
    DescribingChoice,
    ValveDescribingFunction,
    valve_describing_function,
)
from analytics.errors import ModelSpecError
from analytics.lti import TransferFunction
from analytics.simulation import ClosedLoopModel, PIDController
from analytics.types import ComplexArray, FloatArray
from analytics.valves import (
    IdealValve,
    ValveModel,
)

ProcessMatrix = Sequence[Sequence[TransferFunction | None]]

#: Points of the dense frequency grid per decade (crossing brackets).
GRID_PER_DECADE = 400
#: Amplitudes tried for each of the other moving valves when seeding a
#: multi-valve solution, as ``A / (S/2) - 1``.
SEED_EXCESS = np.geomspace(1e-3, 1e3, 13)
#: Converged when ``|(I + P N) x| / |x|`` is below this.
RESIDUAL_TOLERANCE = 1e-9
#: Relative amplitude step of the stability check.
STABILITY_STEP = 0.02


# ---------------------------------------------------------------------------- results
@dataclass(frozen=True)
class LimitCycle:
    """One solution of the harmonic balance.

    Attributes
    ----------
    omega : float
        Frequency, rad/s.
    amplitudes : tuple of float or None
        Amplitude of the OP (valve input) oscillation of each loop with a
        sticky valve, % of travel; ``None`` for healthy valves. It is ``A`` of
        the describing function ``N(A)``.
    stable : bool
        True if the cycle attracts (see the module notes); only stable cycles
        are observed in a plant. Never true at the band edge, nor when a
        valve stays stuck in a loop with integral action (the integrator walks
        its OP through the band).
    residual : float
        ``|(I + P(jw) N(A)) x| / |x|`` at the solution, ``x`` the OP phasors.
    op_amplitudes : tuple of float
        Predicted OP amplitude of every loop, healthy ones included.
    moving : tuple of bool
        Whether each valve moves; a sticky valve whose OP amplitude stays below
        its threshold stays stuck (``N = 0``). Healthy valves count as moving.
    at_band_edge : bool
        The solution lies at the end ``A -> S/2`` of the ``-1/N`` curve
        (e.g. thesis Eq. 5.33), where the valve only just moves.
    """

    omega: float
    amplitudes: tuple[float | None, ...]
    stable: bool
    residual: float
    op_amplitudes: tuple[float, ...]
    moving: tuple[bool, ...]
    at_band_edge: bool = False

    @property
    def period_s(self) -> float:
        """Period ``2 pi / omega``, s."""
        return 2.0 * math.pi / self.omega

    def to_dict(self) -> dict[str, Any]:
        """JSON form for ``loopwatch predict``."""
        return {
            "omega": self.omega,
            "period_s": self.period_s,
            "amplitudes": list(self.amplitudes),
            "stable": self.stable,
            "residual": self.residual,
            "op_amplitudes": list(self.op_amplitudes),
            "moving": list(self.moving),
            "at_band_edge": self.at_band_edge,
        }


@dataclass(frozen=True)
class Prediction:
    """Describing-function prediction for one closed-loop system.

    Attributes
    ----------
    limit_cycles : tuple of LimitCycle
        Every solution found in ``omega_range``, sorted by frequency; empty
        when the linear loop is unstable.
    linear_stable : bool
        Whether the loop is stable with every valve healthy (``N = 1``). If
        not, oscillations grow until something else (OP limits) stops them and
        no limit cycle is reported.
    omega_range : (float, float)
        Frequencies searched, rad/s.
    sticky : tuple of bool
        Which loops have a sticky valve.
    note : str
        Why nothing was predicted, or how the DF was obtained.
    """

    limit_cycles: tuple[LimitCycle, ...]
    linear_stable: bool
    omega_range: tuple[float, float]
    sticky: tuple[bool, ...]
    note: str = ""

    @property
    def oscillates(self) -> bool:
        """True if at least one predicted limit cycle is stable."""
        return any(cycle.stable for cycle in self.limit_cycles)

    @property
    def stable_cycles(self) -> tuple[LimitCycle, ...]:
        """The stable limit cycles."""
        return tuple(cycle for cycle in self.limit_cycles if cycle.stable)

    def to_dict(self) -> dict[str, Any]:
        """JSON form: ``{"limit_cycles": [...], "linear_stable", "omega_range", "note"}``."""
        return {
            "limit_cycles": [cycle.to_dict() for cycle in self.limit_cycles],
            "linear_stable": self.linear_stable,
            "omega_range": list(self.omega_range),
            "note": self.note,
        }


@dataclass(frozen=True)
class SimulatedLimitCycle:
    """The steady oscillation measured at the end of a closed-loop simulation.

    Attributes
    ----------
    oscillating : bool
        True if at least one loop's OP oscillates regularly with a steady
        amplitude in the analysed window.
    period_s : float or None
        Period of the oscillation, s: that of the sticky loop with the largest
        OP amplitude (of any loop if no sticky loop oscillates).
    amplitudes : tuple of float or None
        Amplitude of the fundamental harmonic of each loop's OP at its own
        period (the quantity ``A`` of the describing function), % of travel;
        ``None`` for a loop that does not oscillate.
    half_ranges : tuple of float
        ``(max - min) / 2`` of each OP in the window (``inf`` if it diverges;
        ``null`` in JSON).
    periods_s : tuple of float or None
        Period of each loop's OP (loops of decoupled sub-systems may differ).
    window_s : (float, float)
        Time window analysed, s.
    note : str
        ``"diverges"``, ``"growing"``, ``"decaying"`` or ``""``.
    """

    oscillating: bool
    period_s: float | None
    amplitudes: tuple[float | None, ...]
    half_ranges: tuple[float, ...]
    periods_s: tuple[float | None, ...]
    window_s: tuple[float, float]
    note: str = ""

    def to_dict(self) -> dict[str, Any]:
        """JSON form: ``{"oscillating", "period_s", "amplitudes", ...}``."""
        return {
            "oscillating": self.oscillating,
            "period_s": self.period_s,
            "amplitudes": list(self.amplitudes),
            "half_ranges": [h if math.isfinite(h) else None for h in self.half_ranges],
            "periods_s": list(self.periods_s),
            "window_s": list(self.window_s),
            "note": self.note,
        }


@dataclass(frozen=True)
class LimitCycleReport:
    """Describing-function prediction beside the simulated limit cycle.

    Attributes
    ----------
    prediction : Prediction
    simulated : SimulatedLimitCycle
    matched : LimitCycle or None
        The stable predicted cycle closest in period to the simulated one.
    period_error_pct : float or None
        ``100 (T_DF - T_sim) / T_sim``.
    amplitude_error_pct : tuple of float or None
        Per loop with a sticky valve, ``100 (A_DF - A_sim) / A_sim`` against the
        simulated fundamental amplitude; ``None`` elsewhere.
    """

    prediction: Prediction
    simulated: SimulatedLimitCycle
    matched: LimitCycle | None
    period_error_pct: float | None
    amplitude_error_pct: tuple[float | None, ...]

    @property
    def agree(self) -> bool:
        """True if prediction and simulation agree on whether the loop oscillates."""
        return self.prediction.oscillates == self.simulated.oscillating

    def comparison_to_dict(self) -> dict[str, Any]:
        """JSON form of the comparison: ``agree``, ``matched_omega``, ``period_error_pct``
        and ``amplitude_error_pct``."""
        return {
            "agree": self.agree,
            "matched_omega": None if self.matched is None else self.matched.omega,
            "period_error_pct": self.period_error_pct,
            "amplitude_error_pct": list(self.amplitude_error_pct),
        }

    def to_dict(self) -> dict[str, Any]:
        """JSON form for ``loopwatch predict``: the prediction's keys plus
        ``"simulated"`` and ``"comparison"`` (:meth:`comparison_to_dict`)."""
        return {
            **self.prediction.to_dict(),
            "simulated": self.simulated.to_dict(),
            "comparison": self.comparison_to_dict(),
        }


@dataclass(frozen=True)
class NyquistCurves:
    """Data of the Nyquist/DF plot, one curve pair per sticky valve.

    Attributes
    ----------
    omega : ndarray, shape (m,)
        Frequencies, rad/s.
    loops : tuple of int
        0-based index of each sticky loop, the row order of the arrays below.
    loop_response : ndarray of complex, shape (p, m)
        Linear side of the harmonic balance seen by each sticky valve: the
        equivalent loop ``L_eq(jw)`` of thesis Eq. 3.20 with the other loops
        closed, their sticky valves at the amplitudes of ``limit_cycle`` (or
        healthy, ``N = 1``, without one). For a single loop it is ``G Gc``.
    amplitudes : tuple of ndarray
        Amplitudes ``A`` of each valve's DF curve, from just above its band.
    negative_inverse_df : tuple of ndarray of complex
        ``-1/N(A)`` at those amplitudes.
    limit_cycle : LimitCycle or None
        The cycle the curves were drawn for; each pair of curves meets at it.
    """

    omega: FloatArray
    loops: tuple[int, ...]
    loop_response: ComplexArray
    amplitudes: tuple[FloatArray, ...]
    negative_inverse_df: tuple[ComplexArray, ...]
    limit_cycle: LimitCycle | None


# ---------------------------------------------------------------------------- linear side
def _horner(coefficients: FloatArray, s: ComplexArray) -> ComplexArray:
    """Polynomials (rows of ``coefficients``, descending powers) at every ``s``:
    shape ``(s.size, rows)``."""
    value = np.zeros((s.size, coefficients.shape[0]), dtype=np.complex128)
    for column in coefficients.T:
        value = value * s[:, None] + column
    return value


@dataclass(frozen=True)
class _LinearPart:
    """``P(s) = diag(gc_i(s) h(s)) G(s)``: controller, hold and process per loop."""

    process: tuple[tuple[TransferFunction | None, ...], ...]
    controllers: tuple[PIDController, ...]
    hold_delay: float

    @property
    def size(self) -> int:
        return len(self.controllers)

    @cached_property
    def _entries(self) -> dict[str, NDArray[Any]]:
        """Process entries as padded coefficient rows (and their derivatives),
        controller gains as arrays: everything :meth:`matrix` evaluates at once."""
        entries = [(i, j, g) for i, row in enumerate(self.process) for j, g in enumerate(row) if g]
        width = max(len(g.den) for _, _, g in entries)

        def padded(polys: list[NDArray[np.float64]]) -> FloatArray:
            table = np.zeros((len(polys), width))
            for row, poly in zip(table, polys, strict=True):
                if poly.size:
                    row[width - poly.size :] = poly
            return table

        nums = [np.asarray(g.num, dtype=np.float64) for _, _, g in entries]
        dens = [np.asarray(g.den, dtype=np.float64) for _, _, g in entries]
        ctrl = self.controllers
        return {
            "row": np.array([i for i, _, _ in entries]),
            "column": np.array([j for _, j, _ in entries]),
            "num": padded(nums),
            "den": padded(dens),
            "dnum": padded([np.asarray(np.polyder(x), dtype=np.float64) for x in nums]),
            "dden": padded([np.asarray(np.polyder(x), dtype=np.float64) for x in dens]),
            "delay": np.array([g.delay for _, _, g in entries]),
            "sign": np.array([1.0 if c.action == "reverse" else -1.0 for c in ctrl]),
            "kp": np.array([c.kp for c in ctrl]),
            "ki": np.array([c.ki for c in ctrl]),
            "kd": np.array([c.kd for c in ctrl]),
            "filter": np.array([c.derivative_filter_time(1.0) for c in ctrl]),
        }

    def matrix(self, s: ArrayLike) -> tuple[ComplexArray, ComplexArray]:
        """``P(s)`` and ``dP/ds``, shape ``s.shape + (n, n)``."""
        e = self._entries
        flat = np.asarray(s, dtype=np.complex128).reshape(-1)
        col = flat[:, None]
        hold = np.exp(-self.hold_delay * col)
        lag = 1.0 + e["filter"] * col
        c = e["sign"] * (e["kp"] + e["ki"] / col + e["kd"] * col / lag) * hold
        dc = e["sign"] * (-e["ki"] / col**2 + e["kd"] / lag**2) * hold - self.hold_delay * c
        num, den = _horner(e["num"], flat), _horner(e["den"], flat)
        dnum, dden = _horner(e["dnum"], flat), _horner(e["dden"], flat)
        delay = np.exp(-e["delay"] * col)
        value = num / den * delay
        slope = ((dnum * den - num * dden) / den**2 - e["delay"] * num / den) * delay
        n = self.size
        p = np.zeros((flat.size, n, n), dtype=np.complex128)
        dp = np.zeros_like(p)
        rows, columns = e["row"], e["column"]
        p[:, rows, columns] = c[:, rows] * value
        dp[:, rows, columns] = dc[:, rows] * value + c[:, rows] * slope
        shape = (*np.shape(s), n, n)
        return p.reshape(shape), dp.reshape(shape)

    def open_loop_unstable_poles(self) -> int:
        """Right-half-plane poles of the open loop (each entry realised on its own,
        as the simulator does); poles on the imaginary axis other than 0 are refused."""
        count = 0
        for row in self.process:
            for g in row:
                if g is None:
                    continue
                poles = g.poles()
                on_axis = np.abs(poles.real) <= 1e-12 * np.maximum(1.0, np.abs(poles))
                if np.any(on_axis & (np.abs(poles) > 1e-12)):
                    raise ModelSpecError(
                        "a process entry has poles on the imaginary axis away from s = 0; "
                        "the Nyquist count cannot handle it"
                    )
                count += int(np.sum((poles.real > 0) & ~on_axis))
        return count

    def crossover(self) -> float:
        """Highest frequency at which a diagonal loop ``|gc_i g_ii|`` falls through 1
        (rad/s); the frequency of the largest diagonal gain if none reaches 1."""
        omega = np.geomspace(1e-7, 1e4, 2201)
        p, _ = self.matrix(1j * omega)
        gain = np.abs(np.diagonal(p, axis1=-2, axis2=-1)).max(axis=-1)
        above = np.flatnonzero(gain >= 1.0)
        if above.size == 0 or above[-1] == omega.size - 1:
            return float(omega[int(np.argmax(gain))])
        k = int(above[-1])
        fraction = math.log(gain[k]) / math.log(gain[k] / gain[k + 1])
        return float(omega[k] * (omega[k + 1] / omega[k]) ** fraction)

    def rolloff_frequency(self, start: float) -> float:
        """A frequency above which every ``|P_ij| < 1e-3`` (the D-contour closes at 1)."""
        omega = start
        for _ in range(12):
            p, _ = self.matrix(np.array([1j * omega]))
            if np.abs(p).max() < 1e-3:
                return omega
            omega *= 10.0
        raise ModelSpecError(
            "the loop gain does not roll off at high frequency (improper controller "
            "with a biproper process); the Nyquist count needs a strictly proper loop"
        )


def _unwrapped_winding(
    values: Callable[[ComplexArray], ComplexArray],
    omega_small: float,
    omega_large: float,
) -> int | None:
    """Counter-clockwise turns of ``values(s)`` around 0 along the D-contour.

    The contour runs up the imaginary axis from ``-j omega_large`` to
    ``j omega_large``, passing ``s = 0`` on a right semicircle of radius
    ``omega_small``; the large arc is assumed to map close to a point (the loop
    gain has rolled off). The grid is bisected where the phase steps by more
    than ``pi / 4``. ``None`` if the curve passes through 0.
    """
    log_small, log_large = math.log(omega_small), math.log(omega_large)

    def contour(t: FloatArray) -> ComplexArray:
        down = np.exp(log_large - np.clip(t, 0, 1) * (log_large - log_small))
        arc = omega_small * np.exp(1j * (np.clip(t - 1, 0, 1) - 0.5) * math.pi)
        up = np.exp(log_small + np.clip(t - 2, 0, 1) * (log_large - log_small))
        return np.where(t < 1, -1j * down, np.where(t < 2, arc, 1j * up))

    t = np.concatenate(
        [np.linspace(0, 1, 1200, endpoint=False), np.linspace(1, 2, 60, endpoint=False)]
    )
    t = np.concatenate([t, np.linspace(2, 3, 1201)])
    f = values(contour(t))
    for _ in range(60):
        if not np.all(np.isfinite(f)) or np.any(f == 0):
            return None
        step = np.angle(f[1:] / f[:-1])
        coarse = np.flatnonzero(np.abs(step) > math.pi / 4)
        if coarse.size == 0:
            closing = np.angle(f[0] / f[-1])
            return round((step.sum() + closing) / (2 * math.pi))
        t_mid = 0.5 * (t[coarse] + t[coarse + 1])
        if np.min(t[coarse + 1] - t[coarse]) < 1e-13:
            return None
        t = np.insert(t, coarse + 1, t_mid)
        f = np.insert(f, coarse + 1, values(contour(t_mid)))
    return None


# ---------------------------------------------------------------------------- solver
@dataclass(frozen=True)
class _Configuration:
    """Which sticky valves move (DF ``N(A)``), which stay stuck (``N = 0``)."""

    moving: tuple[int, ...]
    stuck: tuple[int, ...]
    n: int

    @property
    def free(self) -> tuple[int, ...]:
        """Loops whose OP phasor is a free unknown (healthy or stuck valve)."""
        return tuple(i for i in range(self.n) if i not in self.moving)


class _HarmonicBalance:
    """Residual ``(I + P N) x`` of the square system and its Jacobian, batched."""

    def __init__(
        self, linear: _LinearPart, dfs: dict[int, ValveDescribingFunction], config: _Configuration
    ) -> None:
        self.linear = linear
        self.dfs = dfs
        self.config = config
        gains = np.ones(linear.size, dtype=np.complex128)
        gains[list(config.stuck)] = 0.0
        self.fixed_gains = gains

    def unpack(self, z: FloatArray) -> tuple[FloatArray, FloatArray, ComplexArray]:
        """Frequencies, moving amplitudes (batch, p) and OP phasors (batch, n)."""
        cfg = self.config
        p = len(cfg.moving)
        omega = np.exp(z[:, 0])
        excess = np.exp(z[:, 1 : 1 + p])
        thresholds = np.array([self.dfs[k].threshold for k in cfg.moving])
        amplitudes = thresholds * (1.0 + excess)
        phases = np.concatenate([np.zeros((z.shape[0], 1)), z[:, 1 + p : 2 * p]], axis=1)
        x = np.zeros((z.shape[0], cfg.n), dtype=np.complex128)
        x[:, list(cfg.moving)] = amplitudes * np.exp(1j * phases)
        free = z[:, 2 * p :]
        x[:, list(cfg.free)] = free[:, 0::2] + 1j * free[:, 1::2]
        return omega, amplitudes, x

    def gains(self, amplitudes: FloatArray) -> tuple[ComplexArray, ComplexArray]:
        """DF of every loop (batch, n) and the slopes of the moving ones (batch, p)."""
        n_batch = amplitudes.shape[0]
        gains = np.tile(self.fixed_gains, (n_batch, 1))
        slopes = np.zeros(amplitudes.shape, dtype=np.complex128)
        for column, k in enumerate(self.config.moving):
            gains[:, k] = self.dfs[k].value(amplitudes[:, column])
            slopes[:, column] = self.dfs[k].slope(amplitudes[:, column])
        return gains, slopes

    def evaluate(self, z: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Real residual (batch, 2n), Jacobian (batch, 2n, 2n) and ``|x|`` (batch)."""
        cfg = self.config
        omega, amplitudes, x = self.unpack(z)
        gains, slopes = self.gains(amplitudes)
        pm, dpm = self.linear.matrix(1j * omega)
        m = np.eye(cfg.n) + pm * gains[:, None, :]
        residual = np.einsum("bij,bj->bi", m, x)
        columns = [np.einsum("bij,bj->bi", dpm, gains * x) * (1j * omega)[:, None]]
        for column, k in enumerate(cfg.moving):
            rotation = x[:, k] / amplitudes[:, column]
            d_x = (amplitudes[:, column] - self.dfs[k].threshold) * rotation
            d_gain = slopes[:, column] * x[:, k] * (amplitudes[:, column] - self.dfs[k].threshold)
            columns.append(m[:, :, k] * d_x[:, None] + pm[:, :, k] * d_gain[:, None])
        for k in cfg.moving[1:]:
            columns.append(1j * x[:, k][:, None] * m[:, :, k])
        for k in cfg.free:
            columns.append(m[:, :, k])
            columns.append(1j * m[:, :, k])
        jac = np.stack(columns, axis=-1)  # 1 + p + (p - 1) + 2 (n - p) = 2n columns
        return (
            np.concatenate([residual.real, residual.imag], axis=1),
            np.concatenate([jac.real, jac.imag], axis=1),
            np.linalg.norm(x, axis=1),
        )

    def pack(self, omega: FloatArray, amplitudes: FloatArray, x: ComplexArray) -> FloatArray:
        """Unknowns from a guess; ``x`` is rotated so that the reference phase is 0."""
        cfg = self.config
        p = len(cfg.moving)
        thresholds = np.array([self.dfs[k].threshold for k in cfg.moving])
        reference = x[:, cfg.moving[0]]
        unit = np.where(np.abs(reference) > 0, reference / np.abs(reference), 1.0)
        x = x / unit[:, None]
        scale = amplitudes[:, 0] / np.maximum(np.abs(x[:, cfg.moving[0]]), 1e-300)
        x = x * scale[:, None]
        parts = [np.log(omega)[:, None], np.log(amplitudes / thresholds - 1.0)]
        if p > 1:
            parts.append(np.angle(x[:, list(cfg.moving[1:])]))
        free = x[:, list(cfg.free)]
        interleaved = np.empty((x.shape[0], 2 * free.shape[1]))
        interleaved[:, 0::2], interleaved[:, 1::2] = free.real, free.imag
        parts.append(interleaved)
        return np.concatenate(parts, axis=1)

    def solve(self, z: FloatArray, iterations: int = 80) -> tuple[FloatArray, FloatArray]:
        """Levenberg-Marquardt from every row of ``z`` at once; returns the final
        unknowns and the relative residuals ``|r| / |x|``.

        Rows leave the batch once converged (relative residual below 1e-3 of
        :data:`RESIDUAL_TOLERANCE`) or stalled (damping above 1e8).
        """
        z = z.copy()
        residual, jac, size = self.evaluate(z)
        cost = np.einsum("bi,bi->b", residual, residual)
        damping = np.full(z.shape[0], 1e-6)
        active = np.arange(z.shape[0])
        steps = 2 * len(self.config.moving)  # log omega, amplitudes, phases
        for _ in range(iterations):
            relative = np.sqrt(cost[active]) / size[active]
            keep = (relative >= RESIDUAL_TOLERANCE * 1e-3) & (damping[active] <= 1e8)
            active, residual, jac = active[keep], residual[keep], jac[keep]
            if active.size == 0:
                break
            normal = np.einsum("bki,bkj->bij", jac, jac)
            diagonal = np.einsum("bii->bi", normal)
            shift = damping[active, None] * diagonal + 1e-14 * diagonal.max(axis=1)[:, None]
            normal += shift[:, :, None] * np.eye(z.shape[1])
            gradient = np.einsum("bki,bk->bi", jac, residual)
            step = -np.linalg.solve(normal, gradient[..., None])[..., 0]
            biggest = np.abs(step[:, :steps]).max(axis=1)
            step *= np.minimum(1.0, 1.0 / np.maximum(biggest, 1e-300))[:, None]
            trial = z[active] + step
            with np.errstate(all="ignore"):  # a trial that overflows is rejected below
                residual_t, jac_t, size_t = self.evaluate(trial)
            cost_t = np.einsum("bi,bi->b", residual_t, residual_t)
            better = np.isfinite(cost_t) & (cost_t < cost[active])
            z[active[better]] = trial[better]
            cost[active[better]] = cost_t[better]
            size[active[better]] = size_t[better]
            residual = np.where(better[:, None], residual_t, residual)
            jac = np.where(better[:, None, None], jac_t, jac)
            damping[active] = np.where(better, damping[active] / 3.0, damping[active] * 4.0)
        return z, np.sqrt(cost) / size


def _null_vectors(m: ComplexArray) -> ComplexArray:
    """Right singular vector of the smallest singular value, per matrix."""
    _, _, vh = np.linalg.svd(m)
    return np.asarray(vh[:, -1, :].conj(), dtype=np.complex128)


def _determinant(m: ComplexArray) -> ComplexArray:
    """``det`` over the last two axes; closed forms up to 3 x 3 (many small
    matrices at once are much faster without LAPACK's per-matrix overhead)."""
    n = m.shape[-1]
    if n == 1:
        return m[..., 0, 0].copy()
    if n == 2:
        return m[..., 0, 0] * m[..., 1, 1] - m[..., 0, 1] * m[..., 1, 0]
    if n == 3:
        a, b, c = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
        d, e, f = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
        g, h, i = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
        return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    return np.asarray(np.linalg.det(m), dtype=np.complex128)


def _equivalent_loop(pm: ComplexArray, gains: ComplexArray, loop: int) -> ComplexArray:
    """``L_eq`` seen by the valve of ``loop`` (thesis Eq. 3.20).

    ``det(I + P N)`` is affine in that valve's ``N``: its column ``loop`` is
    ``e_loop + N P[:, loop]``, so ``det = d0 + N d1`` with that column replaced by
    ``e_loop`` (``d0``) or ``P[:, loop]`` (``d1``), and ``1 + N L_eq = 0`` with
    ``L_eq = d1 / d0``. ``gains`` (..., n) holds the other valves' DF.
    """
    n = pm.shape[-1]
    m = np.eye(n) + pm * gains[..., None, :]
    m[..., :, loop] = np.eye(n)[loop]
    d0 = _determinant(m)
    m[..., :, loop] = pm[..., :, loop]
    d1 = _determinant(m)
    return np.asarray(d1 / d0, dtype=np.complex128)


def _minor_coefficients(
    gains: ComplexArray, members: NDArray[np.bool_], loop: int
) -> ComplexArray:
    """``prod_{k in T, k != loop} N_k`` for every set ``T`` of loops (rows of ``members``,
    as in :attr:`LimitCyclePredictor.minor_members`) and every row of ``gains`` (batch, n)."""
    factors = np.where(members[None], gains[:, None, :], 1.0)
    factors[:, :, loop] = 1.0
    return np.asarray(factors.prod(axis=2), dtype=np.complex128)


def _edge_solution(
    loop: Callable[[FloatArray], ComplexArray], omega: FloatArray, edge: complex
) -> float | None:
    """Frequency at which the Nyquist curve passes through the end of the ``-1/N``
    curve (``A -> S/2``), e.g. thesis Eq. 5.33; None if it does not."""
    distance = np.abs(loop(omega) - edge) / abs(edge)
    k = int(np.argmin(distance))
    if distance[k] > 1e-2:
        return None
    lo, hi = math.log(omega[max(k - 1, 0)]), math.log(omega[min(k + 1, omega.size - 1)])
    result = scipy.optimize.minimize_scalar(
        lambda u: abs(complex(loop(np.array([math.exp(u)]))[0]) - edge),
        bounds=(lo, hi),
        method="bounded",
        options={"xatol": 1e-12},
    )
    if result.fun > 1e-7 * abs(edge):
        return None
    return math.exp(float(result.x))


class LimitCyclePredictor:
    """Everything :func:`predict_limit_cycles` needs about one system (thesis Eqs. 3.14,
    3.16): the linear part ``P(jw)`` on the seeding grid (``linear.matrix``), each sticky
    valve's describing function, the frequency range searched and the closed loop's
    right-half-plane roots for given valve gains (:meth:`unstable_roots`)."""

    def __init__(
        self,
        linear: _LinearPart,
        valves: Sequence[ValveModel],
        describing: DescribingChoice,
        omega_range: tuple[float, float],
        open_poles: int,
    ) -> None:
        self.linear = linear
        self.sticky = tuple(not isinstance(v, IdealValve) for v in valves)
        self.dfs = {k: valve_describing_function(v, describing)
                    for k, v in enumerate(valves) if self.sticky[k]}
        self.omega_range = omega_range
        decades = math.log10(omega_range[1] / omega_range[0])
        self.omega = np.geomspace(*omega_range, max(200, round(GRID_PER_DECADE * decades)))
        self.grid_matrix, _ = linear.matrix(1j * self.omega)
        self.open_poles = open_poles
        self.omega_small = omega_range[0] * 1e-4
        self.omega_large = linear.rolloff_frequency(omega_range[1] * 10)

    @cached_property
    def minor_members(self) -> NDArray[np.bool_]:
        """Row ``T`` (a bit mask of loops): which loops belong to ``T``, shape (2^n, n)."""
        masks = np.arange(1 << self.linear.size)
        return np.asarray((masks[:, None] >> np.arange(self.linear.size)) & 1, dtype=bool)

    @cached_property
    def grid_minors(self) -> ComplexArray:
        """Principal minors ``det P[T, T](jw)`` on the frequency grid, shape (2^n, grid);
        the empty set's minor is 1.

        ``det(I + P diag(N)) = sum_T prod_{k in T} N_k det P[T, T]`` (the expansion of
        a determinant by its columns), so the equivalent loop of any valve for any
        amplitudes of the others costs one small product (:func:`_minor_coefficients`)
        instead of two determinants per frequency.
        """
        minors = np.ones((self.minor_members.shape[0], self.omega.size), dtype=np.complex128)
        for mask, members in enumerate(self.minor_members[1:], start=1):
            loops = np.flatnonzero(members)
            minors[mask] = _determinant(self.grid_matrix[:, loops][:, :, loops])
        return minors

    def unstable_roots(self, gains: ComplexArray) -> int | None:
        """Right-half-plane roots of ``det(I + P(s) diag(gains)) = 0``."""
        n = self.linear.size

        def determinant(s: ComplexArray) -> ComplexArray:
            pm, _ = self.linear.matrix(s)
            return _determinant(np.eye(n) + pm * gains)

        turns = _unwrapped_winding(determinant, self.omega_small, self.omega_large)
        return None if turns is None else self.open_poles - turns

    def seeds(self, config: _Configuration) -> tuple[FloatArray, FloatArray]:
        """Guesses ``(omega, amplitudes)`` for one configuration.

        Each moving valve in turn sees its equivalent loop with the other moving
        valves held at the amplitudes of :data:`SEED_EXCESS`; every crossing of
        that loop with its ``-1/N`` curve is a guess. Taking each valve in turn
        matters: a valve far above its band (``N`` close to 1) barely changes
        the others' loops, so their crossings persist over its whole grid.
        """
        omegas, rows = [], []
        base = np.ones(self.linear.size, dtype=np.complex128)
        base[list(config.stuck)] = 0.0
        for last in config.moving:
            others = [k for k in config.moving if k != last]
            combinations = list(itertools.product(SEED_EXCESS, repeat=len(others)))
            grid = np.array(combinations, dtype=np.float64).reshape(len(combinations), -1)
            fixed = np.array([self.dfs[k].threshold for k in others]) * (1 + grid)
            gains = np.tile(base, (grid.shape[0], 1))
            for column, k in enumerate(others):
                gains[:, k] = self.dfs[k].value(fixed[:, column])
            coefficients = _minor_coefficients(gains, self.minor_members, last)
            contains_last = self.minor_members[:, last]
            # det(I + P N) = d0 + N_last d1 (Eq. 3.20): the minors with and without `last`
            # (einsum, not a BLAS product: a threaded BLAS crawls on a busy machine)
            d0 = np.einsum("bt,tw->bw", coefficients[:, ~contains_last],
                           self.grid_minors[~contains_last])
            d1 = np.einsum("bt,tw->bw", coefficients[:, contains_last],
                           self.grid_minors[contains_last])
            with np.errstate(divide="ignore", invalid="ignore"):  # no bracket where L_eq = 0
                row, omega, amplitude = self.dfs[last].crossings(d1 / d0, self.omega)
            guess = np.empty((row.size, len(config.moving)))
            for column, k in enumerate(config.moving):
                guess[:, column] = amplitude if k == last else fixed[row, others.index(k)]
            omegas.append(omega)
            rows.append(guess)
        return np.concatenate(omegas), np.concatenate(rows)

    def solve(self, config: _Configuration) -> list[LimitCycle]:
        balance = _HarmonicBalance(self.linear, self.dfs, config)
        omega, amplitudes = self.seeds(config)
        cycles = []
        if omega.size:
            gains, _ = balance.gains(amplitudes)
            pm, _ = self.linear.matrix(1j * omega)
            x = _null_vectors(np.eye(config.n) + pm * gains[:, None, :])
            z, relative = balance.solve(balance.pack(omega, amplitudes, x))
            cycles = self._accept(balance, z, relative)
        if len(config.moving) == 1:
            edge = self._edge_cycle(config)
            if edge is not None:
                cycles.append(edge)
        return cycles

    def _accept(
        self, balance: _HarmonicBalance, z: FloatArray, relative: FloatArray
    ) -> list[LimitCycle]:
        config = balance.config
        ok = np.isfinite(relative) & (relative < RESIDUAL_TOLERANCE)
        lo, hi = self.omega_range
        omega, amplitudes, x = balance.unpack(z[ok])
        within = (omega >= lo * (1 - 1e-9)) & (omega <= hi * (1 + 1e-9))
        stuck_ok = np.all(
            np.abs(x[:, list(config.stuck)])
            < np.array([self.dfs[k].threshold for k in config.stuck]),
            axis=1,
        )
        keep = within & stuck_ok
        cycles: list[LimitCycle] = []
        for w, amp, phasor, rel in zip(
            omega[keep], amplitudes[keep], x[keep], relative[ok][keep], strict=True
        ):
            if any(_same_cycle(w, phasor, c) for c in cycles):
                continue
            cycles.append(self._cycle(config, float(w), amp, phasor, float(rel), edge=False))
        return cycles

    def _edge_cycle(self, config: _Configuration) -> LimitCycle | None:
        """A solution at the end of the ``-1/N`` curve (one moving valve)."""
        k = config.moving[0]
        df = self.dfs[k]
        if df.edge is None:
            return None
        gains = np.ones(self.linear.size, dtype=np.complex128)
        gains[list(config.stuck)] = 0.0

        def loop(omega: FloatArray) -> ComplexArray:
            pm, _ = self.linear.matrix(1j * omega)
            return _equivalent_loop(pm, gains, k)

        w = _edge_solution(loop, self.omega, df.edge)
        if w is None:
            return None
        gains[k] = -1.0 / df.edge
        pm, _ = self.linear.matrix(np.array([1j * w]))
        m = np.eye(config.n) + pm[0] * gains
        x = _null_vectors(m[None])[0]
        x = x * df.threshold / abs(x[k])
        if np.any(np.abs(x[list(config.stuck)]) >= [self.dfs[j].threshold for j in config.stuck]):
            return None
        relative = float(np.linalg.norm(m @ x) / np.linalg.norm(x))
        return self._cycle(config, w, np.array([df.threshold]), x, relative, edge=True)

    def _cycle(
        self,
        config: _Configuration,
        omega: float,
        amplitudes: FloatArray,
        x: ComplexArray,
        residual: float,
        *,
        edge: bool,
    ) -> LimitCycle:
        moving_amplitude = dict(zip(config.moving, amplitudes, strict=True))
        return LimitCycle(
            omega=omega,
            amplitudes=tuple(
                (float(moving_amplitude.get(i, abs(x[i]))) if self.sticky[i] else None)
                for i in range(config.n)
            ),
            stable=not edge and self._stable(config, omega, amplitudes),
            residual=residual,
            op_amplitudes=tuple(float(abs(v)) for v in x),
            moving=tuple(i not in config.stuck for i in range(config.n)),
            at_band_edge=edge,
        )

    def _gains(self, config: _Configuration, amplitudes: FloatArray) -> ComplexArray:
        gains = np.ones(self.linear.size, dtype=np.complex128)
        gains[list(config.stuck)] = 0.0
        for k, a in zip(config.moving, amplitudes, strict=True):
            gains[k] = complex(self.dfs[k].value(np.array([a]))[0])
        return gains

    def _stable(self, config: _Configuration, omega: float, amplitudes: FloatArray) -> bool:
        """Loeb's criterion along the cycle's amplitude ray, then no other unstable root.

        A valve that stays stuck in a loop with integral action does not stay
        stuck: unless that loop's mean error is exactly zero its integrator walks
        the OP through the band, so such a solution is not sustained. (Band-edge
        solutions are excluded by the caller: the valve stops for any smaller
        amplitude, ``N = 0``, so a cycle nudged downwards dies instead of
        returning; at best they are semi-stable.)
        """
        if any(self.linear.controllers[k].ki != 0 for k in config.stuck):
            return False
        n = self.linear.size
        h = 1e-6

        def determinant(w: float, scale: float) -> complex:
            pm, _ = self.linear.matrix(np.array([1j * w]))
            gains = self._gains(config, amplitudes * scale)
            return complex(_determinant(np.eye(n) + pm[0] * gains))

        d_omega = (determinant(omega * (1 + h), 1.0) - determinant(omega * (1 - h), 1.0)) / (
            2 * h * omega
        )
        d_amplitude = (determinant(omega, 1 + h) - determinant(omega, 1 - h)) / (2 * h)
        if not (d_amplitude / d_omega).imag < 0:
            return False
        roots = self.unstable_roots(self._gains(config, amplitudes * (1 + STABILITY_STEP)))
        return roots == 0


def _same_cycle(omega: float, x: ComplexArray, cycle: LimitCycle) -> bool:
    return abs(math.log(omega / cycle.omega)) < 1e-6 and bool(
        np.allclose(np.abs(x), cycle.op_amplitudes, rtol=1e-5, atol=1e-9)
    )


def _configurations(sticky: Sequence[bool]) -> list[_Configuration]:
    """Every split of the sticky valves into moving (at least one) and stuck."""
    n = len(sticky)
    indices = [i for i in range(n) if sticky[i]]
    configs = []
    for size in range(len(indices), 0, -1):
        for moving in itertools.combinations(indices, size):
            stuck = tuple(i for i in indices if i not in moving)
            configs.append(_Configuration(moving, stuck, n))
    return configs


def _as_matrix(
    process: TransferFunction | ProcessMatrix, n: int
) -> tuple[tuple[TransferFunction | None, ...], ...]:
    if isinstance(process, TransferFunction):
        matrix: tuple[tuple[TransferFunction | None, ...], ...] = ((process,),)
    else:
        matrix = tuple(tuple(row) for row in process)
    if len(matrix) != n or any(len(row) != n for row in matrix):
        raise ModelSpecError(f"the process matrix must be {n} x {n}, one row per controller")
    return matrix


def limit_cycle_predictor(
    process: TransferFunction | ProcessMatrix,
    controllers: PIDController | Sequence[PIDController],
    valves: ValveModel | Sequence[ValveModel],
    omega_range: tuple[float, float] | None,
    describing: DescribingChoice,
    hold_delay: float,
) -> LimitCyclePredictor:
    """The solver of :func:`predict_limit_cycles` and :func:`nyquist_curves` for one system,
    its inputs validated (same parameters and errors as :func:`predict_limit_cycles`).

    Public for analyses that need the linear loops the prediction sees, such as
    :func:`analytics.plantwide.fingerprint.linear_check`.
    """
    controller_list = [controllers] if isinstance(controllers, PIDController) else list(controllers)
    valve_list = [valves] if isinstance(valves, ValveModel) else list(valves)
    n = len(controller_list)
    if len(valve_list) != n:
        raise ModelSpecError(f"need one valve per loop ({n}), got {len(valve_list)}")
    if all(isinstance(v, IdealValve) for v in valve_list):
        raise ModelSpecError("no sticky valve: a linear loop has no limit cycle to predict")
    if describing not in ("model", "equivalent"):
        raise ModelSpecError(f"describing must be 'model' or 'equivalent', got {describing!r}")
    if not (math.isfinite(hold_delay) and hold_delay >= 0):
        raise ModelSpecError(f"hold_delay must be finite and >= 0 s, got {hold_delay}")
    linear = _LinearPart(_as_matrix(process, n), tuple(controller_list), float(hold_delay))
    open_poles = linear.open_loop_unstable_poles()  # refuses poles on the imaginary axis
    if omega_range is None:
        centre = linear.crossover()
        omega_range = (centre / 10.0, centre * 10.0)
    lo, hi = (float(w) for w in omega_range)
    if not (0 < lo < hi and math.isfinite(hi)):
        raise ModelSpecError(f"omega_range must be 0 < low < high, got {omega_range}")
    return LimitCyclePredictor(linear, valve_list, describing, (lo, hi), open_poles)


def predict_limit_cycles(
    process: TransferFunction | ProcessMatrix,
    controllers: PIDController | Sequence[PIDController],
    valves: ValveModel | Sequence[ValveModel],
    *,
    omega_range: tuple[float, float] | None = None,
    describing: DescribingChoice = "model",
    hold_delay: float = 0.0,
) -> Prediction:
    """All limit cycles predicted by the describing function (thesis Eqs. 3.14, 3.16).

    Parameters
    ----------
    process : TransferFunction or n x n nested sequence
        Single-loop process or the matrix ``G[i][j]`` from valve ``j`` to PV
        ``i`` (``None`` for no coupling).
    controllers : PIDController or sequence of PIDController
        One per loop (reverse action: ``OP = Gc (SP - PV)``; the derivative
        filter is taken as in the simulator).
    valves : ValveModel or sequence of ValveModel
        One per loop; :class:`~analytics.valves.IdealValve` for a healthy one.
        At least one must be sticky.
    omega_range : (float, float), optional
        Frequencies searched, rad/s. Default: two decades centred on the
        highest gain crossover of the diagonal loops ``|gc_i g_ii| = 1``.
    describing : {"model", "equivalent"}
        ``"model"``: each valve's own DF (analytic for Choudhury's and Kano's
        models, :func:`~analytics.describing.numerical_df` for the others).
        ``"equivalent"``: Choudhury's DF with the equivalent (S, J) of the
        model (He: ``S = fs + fd, J = fs - fd``, thesis Eq. 1.2, ERRATA
        item 6), which is what the thesis does.
    hold_delay : float
        Dead time added to every loop, s (``dt / 2`` approximates the
        zero-order hold of a controller sampled at ``dt``).

    Returns
    -------
    Prediction
        With ``linear_stable=False`` and no cycles if the loop is unstable
        with healthy valves.

    Raises
    ------
    ModelSpecError
        Inconsistent sizes, no sticky valve, a process pole on the imaginary
        axis away from 0, or a loop gain that does not roll off.

    Examples
    --------
    The temperature loop of thesis section 5.5.1 with a valve S = 4, J = 2
    cycles under Kc = 10, Ti = 10 s; the retune Kc = 2, Ti = 100 s leaves no
    intersection (thesis Figs. 5.16 and 5.18):

    >>> from analytics.valves import ChoudhuryValve
    >>> g = TransferFunction.fopdt(0.4346, 27.58, 6.0)
    >>> valve = ChoudhuryValve(4.0, 2.0)
    >>> pred = predict_limit_cycles(g, PIDController.ideal(10.0, 10.0), valve)
    >>> [(round(c.period_s, 1), round(c.amplitudes[0], 2), c.stable) for c in pred.limit_cycles]
    [(37.8, 5.65, True)]
    >>> predict_limit_cycles(g, PIDController.ideal(2.0, 100.0), valve).limit_cycles
    ()
    """
    predictor = limit_cycle_predictor(process, controllers, valves, omega_range, describing,
                                      hold_delay)
    n = predictor.linear.size
    healthy_roots = predictor.unstable_roots(np.ones(n, dtype=np.complex128))
    if healthy_roots != 0:
        detail = "an undetermined number of" if healthy_roots is None else f"{healthy_roots}"
        return Prediction(
            (),
            False,
            predictor.omega_range,
            predictor.sticky,
            f"the loop is unstable with healthy valves ({detail} right-half-plane roots): "
            "oscillations grow instead of settling on a limit cycle",
        )
    cycles: list[LimitCycle] = []
    for config in _configurations(predictor.sticky):
        cycles.extend(predictor.solve(config))
    cycles.sort(key=lambda c: c.omega)
    sources = "; ".join(f"loop {k + 1}: {df.source}" for k, df in predictor.dfs.items())
    return Prediction(tuple(cycles), True, predictor.omega_range, predictor.sticky, sources)


def nyquist_curves(
    process: TransferFunction | ProcessMatrix,
    controllers: PIDController | Sequence[PIDController],
    valves: ValveModel | Sequence[ValveModel],
    *,
    limit_cycle: LimitCycle | None = None,
    omega_range: tuple[float, float] | None = None,
    describing: DescribingChoice = "model",
    hold_delay: float = 0.0,
    points: int = 1000,
) -> NyquistCurves:
    """Data of the Nyquist/DF plot (thesis Figs. 3.1, 3.7, 5.16), per sticky valve.

    Each sticky valve sees the equivalent loop of thesis Eq. 3.20 with the other
    loops closed; the other sticky valves enter with the DF at the amplitudes
    of ``limit_cycle`` (0 if it leaves them stuck) or as healthy valves if no
    cycle is given. Arguments as in :func:`predict_limit_cycles`; ``points``
    frequencies are spaced geometrically over ``omega_range``.

    Examples
    --------
    >>> from analytics.valves import ChoudhuryValve
    >>> g = TransferFunction.fopdt(0.4346, 27.58, 6.0)
    >>> curves = nyquist_curves(g, PIDController.ideal(10.0, 10.0), ChoudhuryValve(4.0, 2.0))
    >>> curve = curves.negative_inverse_df[0]
    >>> np.round(curve[[0, -1]], 3) + 0  # A -> S/2 and A -> inf, thesis Table 5.1
    array([ 0.-1.571j, -1.+0.j   ])
    """
    predictor = limit_cycle_predictor(process, controllers, valves, omega_range, describing,
                                      hold_delay)
    omega = np.geomspace(*predictor.omega_range, points)
    pm, _ = predictor.linear.matrix(1j * omega)
    loops = tuple(predictor.dfs)
    gains = np.ones(predictor.linear.size, dtype=np.complex128)
    if limit_cycle is not None:
        for k in loops:
            amplitude = limit_cycle.amplitudes[k]
            moving = limit_cycle.moving[k] and amplitude is not None
            gains[k] = complex(predictor.dfs[k].value(np.array([amplitude]))[0]) if moving else 0
    responses, amplitudes, curves = [], [], []
    for k in loops:
        responses.append(_equivalent_loop(pm, gains, k))
        a, curve = predictor.dfs[k].table()
        amplitudes.append(a)
        curves.append(curve)
    return NyquistCurves(
        omega, loops, np.array(responses), tuple(amplitudes), tuple(curves), limit_cycle
    )


def _model_parts(model: ClosedLoopModel) -> tuple[list[PIDController], list[ValveModel]]:
    return [loop.controller for loop in model.loops], [loop.valve for loop in model.loops]


def predict_model(
    model: ClosedLoopModel,
    *,
    omega_range: tuple[float, float] | None = None,
    describing: DescribingChoice = "model",
    include_hold: bool = True,
) -> Prediction:
    """:func:`predict_limit_cycles` for a :class:`~analytics.simulation.ClosedLoopModel`
    (the JSON model of ``loopwatch predict``).

    ``include_hold`` adds ``model.dt / 2`` of dead time for the sampled controller's
    zero-order hold, so that the prediction describes the system the simulator runs.
    Setpoints, biases, OP limits and disturbances do not enter the harmonic balance.

    Examples
    --------
    The column of thesis Eq. 3.24 with tuning 3.26 and valves 2 and 3 sticky, in
    continuous time with the thesis's (S, J) describing function: one cycle
    keeps valve 2 stuck (not sustained under integral action), the other moves
    both valves (thesis Table 3.2: 0.46 rad/s, i.e. 13.7 s):

    >>> from analytics.scenarios import column3x3
    >>> model = column3x3(sticky=(2, 3), tuning="3.26")
    >>> pred = predict_model(model, describing="equivalent", include_hold=False)
    >>> [(round(c.period_s, 2), c.moving, c.stable) for c in pred.limit_cycles]
    [(22.61, (True, False, True), False), (13.16, (True, True, True), True)]

    Sampled at 0.5 s the same loops are unstable even with healthy valves:

    >>> predict_model(model).linear_stable
    False
    """
    controllers, valves = _model_parts(model)
    return predict_limit_cycles(
        model.process,
        controllers,
        valves,
        omega_range=omega_range,
        describing=describing,
        hold_delay=model.dt / 2 if include_hold else 0.0,
    )


def nyquist_model(
    model: ClosedLoopModel,
    *,
    limit_cycle: LimitCycle | None = None,
    omega_range: tuple[float, float] | None = None,
    describing: DescribingChoice = "model",
    include_hold: bool = True,
) -> NyquistCurves:
    """:func:`nyquist_curves` for a :class:`~analytics.simulation.ClosedLoopModel`."""
    controllers, valves = _model_parts(model)
    return nyquist_curves(
        model.process,
        controllers,
        valves,
        limit_cycle=limit_cycle,
        omega_range=omega_range,
        describing=describing,
        hold_delay=model.dt / 2 if include_hold else 0.0,
    )



def equivalent_loop_phase(model: ClosedLoopModel, loop: int, period_s: float) -> float:
    """Phase of the loop seen by loop ``loop``'s valve at ``period_s``, degrees in (-360, 0].

    ``L_eq(jw)`` of thesis Eq. 3.20 with every other valve healthy and the hold of
    :func:`predict_model`.  The harmonic balance ``L_eq = -1/N(A)`` needs it between
    -180 and -90 degrees: ``-1/N`` of a sticky valve runs from ``-j pi S / (4 J)`` at
    ``A -> S/2`` to ``-1`` as ``A`` grows (thesis Table 5.1, ERRATA item 1), so at a
    phase outside that range no valve size cycles with that period.

    Examples
    --------
    The temperature loop of thesis section 5.5.1 (Kc 10, Ti 10 s) at its predicted
    36.4 s cycle, where ``-1/N`` is near ``-1``:

    >>> from analytics.scenarios import temperature_loop
    >>> round(equivalent_loop_phase(temperature_loop(), 0, 36.4))
    -173
    """
    if not (math.isfinite(period_s) and period_s > 0):
        raise ModelSpecError(f"period_s must be a positive number of seconds, got {period_s}")
    n = len(model.loops)
    if not 0 <= loop < n:
        raise ModelSpecError(f"loop must be 0 to {n - 1}, got {loop}")
    linear = _LinearPart(_as_matrix(model.process, n), tuple(lp.controller for lp in model.loops),
                         model.dt / 2)
    pm, _ = linear.matrix(np.array([2j * math.pi / period_s]))
    response = complex(_equivalent_loop(pm, np.ones((1, n), dtype=np.complex128), loop)[0])
    phase = math.degrees(math.atan2(response.imag, response.real))
    return phase - 360.0 if phase > 0 else phase


def _schmitt_rises(x: FloatArray, hysteresis: float) -> FloatArray:
    """Fractional sample indices where ``x`` rises through ``+hysteresis`` after
    having been below ``-hysteresis`` (a Schmitt trigger, immune to noise smaller
    than the hysteresis)."""
    high, low = x > hysteresis, x < -hysteresis
    state = np.where(high, 1, np.where(low, -1, 0))
    events = np.flatnonzero(state)
    if events.size < 2:
        return np.empty(0)
    settled = state[events]
    rises = events[1:][(settled[1:] == 1) & (settled[:-1] == -1)]
    before = x[rises - 1]
    fraction = (hysteresis - before) / (x[rises] - before)
    return np.asarray(rises - 1 + fraction, dtype=np.float64)


def _measure_cycle(
    x: FloatArray, dt: float, min_amplitude: float, max_spread: float
) -> tuple[float | None, float | None, float, str]:
    """Period, fundamental amplitude, half range and a note for one OP series."""
    centred = x - x.mean()
    half_range = float(0.5 * (centred.max() - centred.min()))
    if half_range < min_amplitude:
        return None, None, half_range, ""
    rises = _schmitt_rises(centred, 0.5 * half_range)
    if rises.size < 4:
        return None, None, half_range, ""
    intervals = np.diff(rises)
    if intervals.std() > max_spread * intervals.mean():
        return None, None, half_range, ""
    period = (rises[-1] - rises[0]) / (rises.size - 1)
    first, last = math.ceil(rises[0]), math.floor(rises[-1])
    segment = centred[first:last]
    phase = 2 * math.pi / period * np.arange(first, last)
    amplitude = float(2 * abs(np.mean(segment * np.exp(-1j * phase))))
    halves = np.array_split(centred, 2)
    growth = np.ptp(halves[1]) / max(np.ptp(halves[0]), 1e-300)
    note = "growing" if growth > 1.1 else "decaying" if growth < 1 / 1.1 else ""
    return float(period * dt), amplitude, half_range, note


def simulate_limit_cycle(
    model: ClosedLoopModel,
    *,
    duration: float | None = None,
    window_fraction: float = 0.5,
    min_amplitude: float = 0.01,
    max_period_spread: float = 0.1,
) -> SimulatedLimitCycle:
    """The "exact" limit cycle: simulate the loop and measure its steady oscillation.

    The model runs for ``duration`` (default ``model.duration``); the last
    ``window_fraction`` of the record is analysed. In each loop the OP is
    centred, its upward passes through half its half-range (with hysteresis)
    time the cycles; the oscillation counts if there are at least 4 passes,
    the intervals vary by less than ``max_period_spread`` (relative standard
    deviation), the half range exceeds ``min_amplitude`` (% of travel), and the
    peak-to-peak range changes by less than 10 % between the two halves of the
    window. The amplitude is that of the fundamental harmonic at the measured
    period over the whole cycles, the quantity ``A`` of the describing function.

    Examples
    --------
    >>> from analytics.scenarios import temperature_loop
    >>> sim = simulate_limit_cycle(temperature_loop())
    >>> sim.oscillating, round(sim.period_s, 1)
    (True, 35.0)
    """
    if not 0 < window_fraction <= 1:
        raise ModelSpecError(f"window_fraction must be in (0, 1], got {window_fraction}")
    result = model.run(duration=duration)
    start = round(result.t.size * (1 - window_fraction))
    window = (float(result.t[start]), float(result.t[-1]))
    op = result.op[:, start:]
    n = op.shape[0]
    if not np.all(np.isfinite(op)) or np.abs(op).max() > 1e6:
        return SimulatedLimitCycle(
            False, None, (None,) * n, (math.inf,) * n, (None,) * n, window, "diverges"
        )
    measured = [
        _measure_cycle(op[i], result.dt, min_amplitude, max_period_spread) for i in range(n)
    ]
    notes = {note for _, _, _, note in measured if note}
    steady = [period is not None and not note for period, _, _, note in measured]
    periods = tuple(m[0] if ok else None for m, ok in zip(measured, steady, strict=True))
    amplitudes = tuple(m[1] if ok else None for m, ok in zip(measured, steady, strict=True))
    sticky = [not isinstance(loop.valve, IdealValve) for loop in model.loops]
    candidates = [i for i in range(n) if steady[i] and sticky[i]] or [
        i for i in range(n) if steady[i]
    ]
    period = None
    if candidates:
        main = max(candidates, key=lambda i: amplitudes[i] or 0.0)
        period = periods[main]
    return SimulatedLimitCycle(
        oscillating=bool(candidates),
        period_s=period,
        amplitudes=amplitudes,
        half_ranges=tuple(m[2] for m in measured),
        periods_s=periods,
        window_s=window,
        note="growing" if "growing" in notes else ("decaying" if notes else ""),
    )


def compare(
    model: ClosedLoopModel,
    *,
    prediction: Prediction | None = None,
    duration: float | None = None,
    **options: Any,
) -> LimitCycleReport:
    """Describing-function prediction and simulated limit cycle side by side.

    ``prediction`` defaults to ``predict_model(model, **options)``. The stable
    predicted cycle closest in period to the simulated one is matched; errors
    are relative to the simulation.

    Examples
    --------
    The temperature loop of thesis section 5.5.1, sampled at 1 s:

    >>> from analytics.scenarios import temperature_loop
    >>> report = compare(temperature_loop())
    >>> round(report.simulated.period_s, 1), round(report.matched.period_s, 1)
    (35.0, 36.4)
    >>> round(report.period_error_pct, 1), round(report.amplitude_error_pct[0], 1)
    (4.0, -11.9)
    """
    if prediction is None:
        prediction = predict_model(model, **options)
    simulated = simulate_limit_cycle(model, duration=duration)
    matched = None
    period_error = None
    amplitude_errors: tuple[float | None, ...] = (None,) * len(model.loops)
    if simulated.period_s is not None and prediction.stable_cycles:
        sim_period = simulated.period_s
        matched = min(
            prediction.stable_cycles, key=lambda c: abs(math.log(c.period_s / sim_period))
        )
        period_error = 100.0 * (matched.period_s - sim_period) / sim_period
        amplitude_errors = tuple(
            None
            if predicted is None or measured is None
            else 100.0 * (predicted - measured) / measured
            for predicted, measured in zip(matched.amplitudes, simulated.amplitudes, strict=True)
        )
    return LimitCycleReport(prediction, simulated, matched, period_error, amplitude_errors)
