"""Sinusoidal-input describing functions (DF) of control-valve models.

The describing function ``N(A)`` of a nonlinearity is the complex gain from a
sinusoidal input ``A sin(wt)`` to the fundamental harmonic of its periodic
steady-state output [1]_: with ``y(t) ~ b1 sin(wt) + a1 cos(wt)``,
``N = (b1 + j a1) / A``. A limit cycle is predicted where the loop's frequency
response meets ``-1/N(A)`` (thesis Eq. 5.11).

* :func:`choudhury_df` is the closed form of Choudhury et al. [2]_ [3]_ for the
  two-parameter (S, J) stiction model, thesis Eq. 3.4 as corrected by ERRATA
  item 1. It holds for Choudhury's and Kano's models alike, whose limit
  cycles under a sinusoid coincide.
* :func:`numerical_df` computes ``N`` for any
  :class:`~analytics.valves.ValveModel` from a simulated steady cycle.
* :func:`df_curve` picks between the two; :func:`negative_inverse_df` and
  :func:`table_5_1_limits` give the nonlinear side of Eq. 5.11.

References
----------
.. [1] Gelb & Vander Velde (1968), *Multiple-Input Describing Functions and
   Nonlinear System Design*, McGraw-Hill, ch. 1-2 (sinusoidal-input DF).
.. [2] Choudhury, Thornhill & Shah (2005), "Modelling valve stiction",
   Control Eng. Practice 13:641-658 (describing function of the (S, J) model).
.. [3] Choudhury, Shah & Thornhill (2008), *Diagnosis of Process Nonlinearities
   and Valve Stiction*, Springer.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from typing import Literal

import numpy as np
import scipy.interpolate
from numpy.typing import ArrayLike, NDArray

from analytics.errors import ModelSpecError, ValveModelError
from analytics.types import ComplexArray, FloatArray
from analytics.valves import (
    ChoudhuryValve,
    DeadbandValve,
    HeValve,
    KarnoppValve,
    StenmanValve,
    ValveModel,
)

DescribingChoice = Literal["model", "equivalent"]
"""Which describing function a sticky valve gets (:func:`analytic_sj`)."""


def _amplitudes(A: ArrayLike) -> FloatArray:
    amplitudes = np.asarray(A, dtype=np.float64)
    if not np.all(np.isfinite(amplitudes) & (amplitudes > 0)):
        raise ValveModelError("input amplitudes A must be finite and > 0 (% of travel)")
    return amplitudes


def choudhury_df(A: ArrayLike, S: float, J: float) -> ComplexArray:
    """Analytic describing function of the (S, J) stiction model.

    Thesis Eq. 3.4 with the real part corrected as in ERRATA item 1 [2]_ [3]_::

        phi  = asin((A - S) / A)
        P_re = (A/2) sin(2 phi) - 2A cos(phi) - A (pi/2 + phi) + 2 (S - J) cos(phi)
        P_im = -(3A/2) + (A/2) cos(2 phi) + 2A sin(phi) - 2 (S - J) sin(phi)
        N    = -(P_re - j P_im) / (pi A)

    Parameters
    ----------
    A : array_like
        Amplitudes of the sinusoidal OP, % of travel, each finite and > 0.
    S : float
        Stick band plus deadband, % of travel.
    J : float
        Slip jump, % of travel (``0 <= J <= S``; ``J = 0`` is a pure deadband).

    Returns
    -------
    ndarray of complex
        ``N(A)``, same shape as ``A``. For ``A <= S/2`` the valve never moves in
        steady state and ``N = 0``; for ``J > 0`` ``N`` jumps at ``A = S/2`` from 0
        to ``-j 4J / (pi S)``. ``S = 0`` (an ideal valve) gives ``N = 1``.

    Raises
    ------
    ValveModelError
        If ``S`` or ``J`` is negative or not finite, ``J > S``, or an amplitude
        is not finite and positive.

    Notes
    -----
    ``|N| <= 1`` only while ``J`` is below about ``0.664 S``: a larger slip
    jump throws the valve past OP and the fundamental exceeds the input, up
    to ``4/pi`` (a square wave) for ``J = S`` at ``A -> S/2``.

    Examples
    --------
    >>> np.round(choudhury_df([1.0, 5.0], 4.0, 2.0), 3)
    array([0.   +0.j   , 0.876-0.255j])
    """
    ChoudhuryValve(S, J)  # validates S and J
    amplitude = _amplitudes(A)
    if S == 0:
        return np.ones(amplitude.shape, dtype=np.complex128)
    N = np.zeros(amplitude.shape, dtype=np.complex128)
    moving = amplitude > S / 2
    a = amplitude[moving]
    phi = np.arcsin((a - S) / a)
    p_re = a / 2 * np.sin(2 * phi) - 2 * a * np.cos(phi) - a * (np.pi / 2 + phi)
    p_re += 2 * (S - J) * np.cos(phi)
    p_im = -1.5 * a + a / 2 * np.cos(2 * phi) + 2 * a * np.sin(phi) - 2 * (S - J) * np.sin(phi)
    N[moving] = -(p_re - 1j * p_im) / (np.pi * a)
    return N


def negative_inverse_df(N: ArrayLike) -> ComplexArray:
    """``-1/N``, the nonlinear side of the harmonic-balance condition (thesis Eq. 5.11).

    Where ``N = 0`` (the valve does not move, so no limit cycle of that
    amplitude exists) the result is ``nan + nan j``, which plotting libraries
    draw as a gap in the curve instead of a spurious point at infinity.

    Examples
    --------
    >>> negative_inverse_df([0.5j, 0.0])
    array([ 0. +2.j, nan+nanj])
    """
    gain = np.asarray(N, dtype=np.complex128)
    result = np.full(gain.shape, complex(np.nan, np.nan))
    np.divide(-1.0, gain, out=result, where=gain != 0)
    return result


def numerical_df(
    valve: ValveModel,
    A: ArrayLike,
    *,
    omega: float = 1.0,
    samples_per_period: int = 2048,
    periods: int = 4,
) -> ComplexArray:
    """Describing function of any valve model from its simulated steady cycle.

    The valve is driven by ``A sin(omega t)`` sampled ``samples_per_period``
    times a period (``dt = 2 pi / (omega samples_per_period)``), for
    ``periods`` periods. The first period is discarded as transient; over the
    remaining whole periods ``b1 = (2/T) int y sin(wt)`` and
    ``a1 = (2/T) int y cos(wt)`` (rectangle rule, exact for a band-limited
    periodic ``y``) give ``N = (b1 + j a1) / A`` [1]_.

    Parameters
    ----------
    valve : ValveModel
        Any valve model.
    A : array_like
        Amplitudes of the sinusoidal OP, % of travel, each finite and > 0.
    omega : float
        Input frequency, rad/s. Only the physics-based
        :class:`~analytics.valves.KarnoppValve` depends on it; the data-driven
        models see the same samples at every frequency.
    samples_per_period : int
        Samples per input period (>= 16).
    periods : int
        Simulated periods, the first of them transient (>= 2).

    Returns
    -------
    ndarray of complex
        ``N(A)``, same shape as ``A``; 0 where the valve does not move.

    Notes
    -----
    The input starts at its trough, the valve at rest there (``y = -A``). A
    start at rest at mid-stroke would keep Kano's and He's valves stuck for
    ``S/2 < A <= (S + J)/2``, since from mid-band they need ``(S + J)/2`` of
    travel, although the limit cycle exists for every ``A > S/2``.

    Errors: a slip jump is timed to within one sample, so models with jumps
    carry an error of order ``J / (A samples_per_period)`` (below 2e-3 at the
    default for ``J <= S``). He's and Stenman's models are sampled-data
    models: on a fine grid they slip in steps of ``fs - fd`` (resp. ``d``),
    but once OP moves more than that per sample (``2 pi A / samples_per_period
    > fs - fd``) they follow it every sample and the DF changes with
    ``samples_per_period``.
    """
    amplitude = _amplitudes(A)
    if not (math.isfinite(omega) and omega > 0):
        raise ValveModelError(f"omega must be finite and > 0 rad/s, got {omega}")
    if samples_per_period < 16 or periods < 2:
        raise ValveModelError(
            f"need samples_per_period >= 16 and periods >= 2, "
            f"got {samples_per_period} and {periods}"
        )
    theta = -np.pi / 2 + 2 * np.pi / samples_per_period * np.arange(samples_per_period * periods)
    sin_t, cos_t = np.sin(theta), np.cos(theta)
    steady = slice(samples_per_period, None)
    basis = (sin_t[steady] + 1j * cos_t[steady]) * (2.0 / (samples_per_period * (periods - 1)))
    dt = 2 * np.pi / (omega * samples_per_period)
    N = np.empty(amplitude.shape, dtype=np.complex128)
    for index, a in np.ndenumerate(amplitude):
        y = valve.simulate(a * sin_t, dt=dt, initial_position=-a)[steady]
        N[index] = basis @ (y - y[-1]) / a  # the offset makes a stuck valve's N exactly 0
    return N


def df_curve(
    valve: ValveModel, amplitudes: ArrayLike | None = None, *, omega: float = 1.0
) -> tuple[FloatArray, ComplexArray]:
    """Describing function of a valve over a range of amplitudes.

    Choudhury's and Kano's valves use :func:`choudhury_df`; every other model
    uses :func:`numerical_df` (at ``omega``, which matters for
    :class:`~analytics.valves.KarnoppValve` only).

    He's valve is deliberately not mapped to ``choudhury_df(A, fs + fd, fs - fd)``:
    on a slowly varying OP it does not slide but slips in steps of ``fs - fd``,
    its residual ``y - OP`` swinging between ``fd`` and ``fs``, so on average it
    lags OP by ``S/2`` like a deadband of width ``S = fs + fd``, not by
    ``(S - J)/2``. Once it moves, its output stays within ``J/2`` of that
    deadband's, so
    ``|N_He - choudhury_df(A, S, 0)| <= 2J / (pi A)``, and its fundamental is
    smaller than Choudhury's: for ``S = 4, J = 2``, ``N_He = 0.317 - 0.283j``
    against ``0.692 - 0.424j`` at ``A = 3`` and ``0.643 - 0.306j`` against
    ``0.876 - 0.255j`` at ``A = 5``.

    Parameters
    ----------
    valve : ValveModel
        Any valve model.
    amplitudes : array_like, optional
        Amplitudes, % of travel. Default: 200 points spaced geometrically
        from ``(S/2)(1 + 1e-3)`` to ``50 S``, with ``S`` the valve's stick band
        (``fs + fd`` for He, the deadband, Stenman's ``d``,
        ``fs_force + fc_force`` for Karnopp, 1 % for an ideal valve).
    omega : float
        Input frequency, rad/s, for the numerical DF.

    Returns
    -------
    A : ndarray of float
        The amplitudes.
    N : ndarray of complex
        ``N(A)``.
    """
    if amplitudes is None:
        S = valve.stick_band or 1.0
        A = S / 2 * np.geomspace(1 + 1e-3, 100.0, 200)
    else:
        A = _amplitudes(amplitudes)
    sj = analytic_sj(valve)  # Choudhury's valve and its subclass, Kano's
    if sj is not None:
        return A, choudhury_df(A, *sj)
    return A, numerical_df(valve, A, omega=omega)


def table_5_1_limits(S: float, J: float) -> dict[str, complex]:
    """Limits of ``-1/N(A)`` for the (S, J) model, thesis Table 5.1.

    Returns
    -------
    dict
        ``"A->S/2"``: ``-j pi S / (4J)`` for ``J > 0``, where the stiction curve
        ends on the negative imaginary axis. For ``J = 0`` (deadband) both parts
        diverge: with ``A = (S/2)(1 + eps)``,
        ``-1/N ~ -pi / (3 sqrt(eps)) - j pi / (4 eps)``, so the curve leaves
        towards ``-j inf`` (thesis Fig. 5.2) and the value is ``-inf - j inf``.
        ``"A->inf"``: ``-1 + 0j``.

    Examples
    --------
    >>> table_5_1_limits(4.0, 2.0)
    {'A->S/2': -1.5707963267948966j, 'A->inf': (-1+0j)}
    """
    ChoudhuryValve(S, J)  # validates S and J
    small = complex(0.0, -math.pi * S / (4 * J)) if J > 0 else complex(-math.inf, -math.inf)
    return {"A->S/2": small, "A->inf": complex(-1.0, 0.0)}


# ---------------------------------------------------------------------------- for the solvers
@dataclass(frozen=True)
class ValveDescribingFunction:
    """Describing function of one sticky valve, ``N(A)`` for ``A > threshold``, as
    the harmonic-balance solvers use it (:mod:`analytics.limit_cycle`,
    :mod:`analytics.tuning`): its value, its slope, the end of its ``-1/N``
    curve and that curve tabulated by branches of monotone phase."""

    threshold: float
    value: Callable[[FloatArray], ComplexArray]
    slope: Callable[[FloatArray], ComplexArray]
    edge: complex | None  # lim_{A -> threshold+} -1/N, if finite
    source: str
    excess: FloatArray  # A / threshold - 1 of the tabulated -1/N curve

    def table(self) -> tuple[FloatArray, ComplexArray]:
        """Amplitudes ``threshold (1 + excess)`` and ``-1/N`` there."""
        amplitudes = self.threshold * (1.0 + self.excess)
        return amplitudes, -1.0 / self.value(amplitudes)

    @cached_property
    def branches(self) -> list[tuple[FloatArray, FloatArray, FloatArray]]:
        """The ``-1/N`` curve split where its phase turns: per branch the phase
        (ascending), ``log|-1/N|`` and ``A`` at the tabulated points."""
        amplitudes, curve = self.table()
        phase = np.unwrap(np.angle(curve))
        direction = np.sign(np.diff(phase))
        turns = np.flatnonzero(direction[1:] != direction[:-1]) + 1
        bounds = [0, *turns.tolist(), phase.size - 1]
        result = []
        for start, stop in itertools.pairwise(bounds):
            if direction[start] == 0:
                continue
            branch = np.arange(start, stop + 1)
            order = np.argsort(phase[branch])
            chosen = branch[order]
            result.append((phase[chosen], np.log(np.abs(curve[chosen])), amplitudes[chosen]))
        return result

    def crossings(
        self, loop: ComplexArray, omega: FloatArray
    ) -> tuple[NDArray[np.int64], FloatArray, FloatArray]:
        """Brackets where each row of ``loop`` (``L(jw)`` on the grid ``omega``) crosses
        ``-1/N(A)``: the row index, ``omega`` and ``A`` of every guess.

        On each branch of the ``-1/N`` curve whose phase is monotone in ``A``, the
        phase condition gives ``A`` for every ``w`` whose ``arg L`` lies in the
        branch's range; a sign change of ``log|L| - log|1/N|`` between grid points
        brackets a crossing (linear interpolation gives the guess).
        """
        loop = np.atleast_2d(loop)
        log_loop = np.log(np.abs(loop))
        rows, omegas, amplitudes = [], [], []
        for psi, log_radius, amp in self.branches:
            centre = 0.5 * (psi[0] + psi[-1])
            theta = centre + np.angle(loop * np.exp(-1j * centre))
            inside = (theta >= psi[0]) & (theta <= psi[-1])
            gap = log_loop - np.interp(theta, psi, log_radius)
            pair = inside[:, :-1] & inside[:, 1:] & (np.abs(np.diff(theta, axis=1)) < math.pi / 2)
            row, k = np.nonzero(pair & (np.sign(gap[:, :-1]) != np.sign(gap[:, 1:])))
            fraction = gap[row, k] / (gap[row, k] - gap[row, k + 1])
            omegas.append(omega[k] * (omega[k + 1] / omega[k]) ** fraction)
            angle = theta[row, k] + fraction * (theta[row, k + 1] - theta[row, k])
            amplitudes.append(np.interp(angle, psi, amp))
            rows.append(row)
        if not rows:
            return np.empty(0, dtype=np.int64), np.empty(0), np.empty(0)
        return np.concatenate(rows), np.concatenate(omegas), np.concatenate(amplitudes)


def _choudhury_slope(A: FloatArray, S: float, J: float) -> ComplexArray:
    """``dN/dA`` of the (S, J) describing function (thesis Eq. 3.4, ERRATA item 1), A > S/2.

    With ``u = S/A`` and ``c = cos(phi) = sqrt(u (2 - u))`` the DF reads
    ``N = [(1 + u) c + pi/2 + asin(1 - u) - 2 (S - J) c / A] / pi
    - j [S^2 + 2 (S - J)(A - S)] / (pi A^2)``; this is its derivative in closed form.
    """
    u = S / A
    c = np.sqrt(u * (2.0 - u))
    d_real_du = (2 * u * (1 - u) - 2 * (S - J) / S * u * (3 - 2 * u)) / (math.pi * c)
    d_imag = (2 * (S**2 + 2 * (S - J) * (A - S)) / A - 2 * (S - J)) / (math.pi * A**2)
    return np.asarray(-u / A * d_real_du + 1j * d_imag, dtype=np.complex128)


def _choudhury(S: float, J: float, source: str) -> ValveDescribingFunction:
    def value(A: FloatArray) -> ComplexArray:
        return choudhury_df(np.maximum(A, S / 2 * (1 + 1e-15)), S, J)

    def slope(A: FloatArray) -> ComplexArray:
        return _choudhury_slope(np.maximum(A, S / 2 * (1 + 1e-15)), S, J)

    edge = table_5_1_limits(S, J)["A->S/2"] if J > 0 else None
    return ValveDescribingFunction(S / 2, value, slope, edge, source, np.geomspace(1e-9, 1e4, 1400))


def _tabulated(valve: ValveModel) -> ValveDescribingFunction:
    """Numerical DF of any valve model, interpolated (PCHIP in ``log(A - threshold)``)."""
    nominal = valve.stick_band / 2
    amplitudes = nominal * (1.0 + np.geomspace(1e-3, 200.0, 160))
    gains = numerical_df(valve, amplitudes)
    stuck = np.flatnonzero(gains == 0)
    first = int(stuck[-1]) + 1 if stuck.size else 0
    if first >= amplitudes.size - 4:
        raise ModelSpecError(f"valve {valve!r} barely moves: no describing function to use")
    threshold = float(amplitudes[first - 1]) if first else nominal
    coordinate = np.log(amplitudes[first:] - threshold)
    real = scipy.interpolate.PchipInterpolator(coordinate, gains[first:].real, extrapolate=True)
    imag = scipy.interpolate.PchipInterpolator(coordinate, gains[first:].imag, extrapolate=True)
    low, high = coordinate[0], coordinate[-1]

    def value(A: FloatArray) -> ComplexArray:
        u = np.clip(np.log(np.maximum(A - threshold, 1e-300)), low, high)
        return np.asarray(real(u) + 1j * imag(u), dtype=np.complex128)

    def slope(A: FloatArray) -> ComplexArray:
        u = np.log(np.maximum(A - threshold, 1e-300))
        inside = (u >= low) & (u <= high)
        du = np.where(inside, 1.0 / np.maximum(A - threshold, 1e-300), 0.0)
        uc = np.clip(u, low, high)
        return np.asarray((real(uc, 1) + 1j * imag(uc, 1)) * du, dtype=np.complex128)

    excess = amplitudes[first:] / threshold - 1.0
    return ValveDescribingFunction(threshold, value, slope, None, f"numerical DF of {valve!r}",
                                   excess)


def equivalent_sj(valve: ValveModel) -> tuple[float, float] | None:
    """(S, J) of the two-parameter model equivalent to ``valve``, if there is one."""
    if isinstance(valve, ChoudhuryValve):
        return valve.S, valve.J
    if isinstance(valve, HeValve):
        return valve.S, valve.J  # thesis Eq. 1.2, ERRATA item 6
    if isinstance(valve, DeadbandValve):
        return valve.deadband, 0.0
    if isinstance(valve, StenmanValve):
        return valve.d, valve.d
    if isinstance(valve, KarnoppValve):
        return valve.stick_band, min(valve.stick_band, 2 * (valve.fs_force - valve.fc_force))
    return None


def analytic_sj(valve: ValveModel, describing: DescribingChoice = "model"
                ) -> tuple[float, float] | None:
    """The (S, J) whose analytic DF (:func:`choudhury_df`) stands for ``valve``, or None
    when its own DF must be computed numerically (:func:`numerical_df`).

    The one place that decides which describing function a valve gets:
    ``"model"`` uses the analytic DF only for the (S, J) models themselves
    (Choudhury's and Kano's valves); ``"equivalent"`` uses it for every valve
    with an equivalent (S, J) (:func:`equivalent_sj`).
    """
    if describing == "equivalent" or isinstance(valve, ChoudhuryValve):
        return equivalent_sj(valve)
    return None


def valve_describing_function(valve: ValveModel, describing: DescribingChoice = "model"
                              ) -> ValveDescribingFunction:
    """The describing function of ``valve`` for the harmonic-balance solvers: analytic
    or tabulated as :func:`analytic_sj` decides."""
    sj = analytic_sj(valve, describing)
    if sj is None:
        return _tabulated(valve)
    S, J = sj
    return _choudhury(S, J, f"Choudhury DF with S={S:g}, J={J:g}")
