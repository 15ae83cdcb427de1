"""Curve-fitting stiction detection (He, Wang, Pottmann and Qin 2007).

A sticky valve moves in jumps, so the process input is close to a square
wave.  In a self-regulating loop under PI control the integral action turns
the square control error into a *triangular* OP; in an integrating
(level) loop the process integrates the square MV into a *triangular* PV.
A linear oscillation (external disturbance, aggressive tuning) is
sinusoidal in both.  He et al. therefore fit, half cycle by half cycle, a
sinusoid and a triangle to the OP of self-regulating loops and to the PV of
integrating loops and compare the fit errors with the stiction index::

    SI = MSE_sin / (MSE_sin + MSE_tri)

``SI <= 0.4`` no stiction, ``SI >= 0.6`` stiction, in between undecided.

Implementation notes.  The signal is first passed through
:func:`~analytics.stiction.shape_rules.shape_filter` (drift and noise out,
harmonics up to the 7th kept) and cut into half cycles at its zero
crossings (:func:`~analytics.stiction.shape_rules.half_cycle_bounds`); each
half cycle is resampled to :data:`POINTS_PER_HALF_CYCLE` points.  Both
models have three linear parameters and one searched nonlinear one:

* sinusoid ``a sin(omega t) + b cos(omega t) + c`` with the frequency
  ``omega`` searched from 0.7 to 1.4 times that of the half cycle;
* triangle: two straight lines joined at a peak (values at start, peak and
  end), the peak position searched over every interior point.

``MSE_sin`` and ``MSE_tri`` are the mean squared residuals over all half
cycles.

References
----------
.. [1] Q. P. He, J. Wang, M. Pottmann and S. J. Qin, "A curve fitting method
   for detecting valve stiction in oscillating control loops", Ind. Eng.
   Chem. Res. 46 (2007) 4549-4560 (thesis ref. [17]): the index SI and its
   thresholds 0.4 and 0.6; OP for self-regulating, PV for integrating
   processes.
.. [2] Thesis section 1.2.2 ("Comparison of signals versus pre-defined
   shapes") and Table 2.2.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import ClassVar

import numpy as np

from analytics.stiction.evidence import (
    INTEGRATING,
    NO_STICTION,
    STICTION,
    LoopWindow,
    MethodEvidence,
    margin_confidence,
)
from analytics.stiction.shape_rules import (
    half_cycle_bounds,
    resample_segments,
    shape_filter,
    window_problem,
)
from analytics.types import FloatArray

__all__ = ["POINTS_PER_HALF_CYCLE", "CurveFitDetector", "half_cycle_fit_errors"]


#: Points at which each half cycle is fitted.
POINTS_PER_HALF_CYCLE = 32
#: Frequencies tried for the sinusoid, in multiples of the half cycle's own.
_SINE_FREQUENCIES = np.linspace(0.7, 1.4, 15)


def _orthonormal(basis: FloatArray) -> FloatArray:
    """Orthonormal bases spanning the same columns: ``(..., points, k) -> same shape``."""
    q, _ = np.linalg.qr(basis)
    return np.asarray(q, dtype=np.float64)


@lru_cache(maxsize=2)
def _model_bases(points: int) -> tuple[FloatArray, FloatArray]:
    """Orthonormal bases of the two models on a half cycle of ``points`` points.

    Returns the sinusoid bases, shape ``(n_frequencies, points, 3)``, and the
    triangle bases, shape ``(points - 2, points, 3)`` (one per peak
    position); least squares on a basis ``Q`` leaves ``|x|^2 - |Q^T x|^2``.
    """
    u = np.linspace(0.0, 1.0, points)
    angle = np.pi * _SINE_FREQUENCIES[:, None] * (u[None, :] - 0.5)
    sine = np.stack([np.sin(angle), np.cos(angle), np.ones_like(angle)], axis=-1)
    peaks = u[1:-1]
    rise = np.clip(u[None, :] / peaks[:, None], 0.0, 1.0)
    fall = np.clip((u[None, :] - peaks[:, None]) / (1.0 - peaks[:, None]), 0.0, 1.0)
    # Hat functions of a continuous two-segment line: start, peak and end values.
    triangle = np.stack([1.0 - rise, rise - fall, fall], axis=-1)
    return _orthonormal(sine), _orthonormal(triangle)


def half_cycle_fit_errors(half_cycles: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Mean squared residual of the best sinusoid and triangle for each half cycle.

    Parameters
    ----------
    half_cycles : ndarray, shape (n, points)
        Each row one half cycle sampled at ``points`` equally spaced points.

    Returns
    -------
    mse_sin, mse_tri : ndarray, shape (n,)
        Residuals of the two models of the module docstring.

    Examples
    --------
    >>> u = np.linspace(0.0, 1.0, 32)
    >>> bump = np.sin(np.pi * u)
    >>> ramp = np.minimum(u / u[21], (1.0 - u) / (1.0 - u[21]))  # peak on a grid point
    >>> mse_sin, mse_tri = half_cycle_fit_errors(np.stack([bump, ramp]))
    >>> bool(mse_sin[0] < 1e-12), bool(mse_tri[1] < 1e-12), bool(mse_sin[1] > 1e-4)
    (True, True, True)
    """
    points = half_cycles.shape[1]
    energy = np.einsum("ij,ij->i", half_cycles, half_cycles)
    explained = []
    for basis in _model_bases(points):
        # One matrix product for every candidate: (n, points) @ (points, models * 3).
        flat = basis.transpose(1, 0, 2).reshape(points, -1)
        projections = (half_cycles @ flat).reshape(half_cycles.shape[0], basis.shape[0], 3)
        explained.append(np.max(np.sum(projections**2, axis=-1), axis=1))
    best_sine, best_triangle = explained
    return (
        np.maximum(energy - best_sine, 0.0) / points,
        np.maximum(energy - best_triangle, 0.0) / points,
    )


@dataclass(frozen=True, kw_only=True)
class CurveFitDetector:
    """Stiction index ``SI = MSE_sin / (MSE_sin + MSE_tri)`` of He et al. (2007).

    The fitted signal is the OP for self-regulating processes and the PV for
    integrating ones; with the process type unknown the method is
    undecided, because the signal that should be triangular depends on it.

    Attributes
    ----------
    no_stiction_below : float
        ``SI`` at or below which the loop has no stiction (0.4, He et al.).
    stiction_above : float
        ``SI`` at or above which it has stiction (0.6, He et al.).
    harmonics : float
        Upper edge of the shape filter in multiples of the oscillation
        frequency.
    min_cycles : float
        Fewest oscillation cycles in the window.

    References
    ----------
    He, Wang, Pottmann and Qin (2007), Ind. Eng. Chem. Res. 46, 4549-4560.

    Examples
    --------
    A triangular OP of a self-regulating loop:

    >>> t = np.arange(3000.0)
    >>> op = np.abs((t % 150.0) - 75.0)
    >>> w = LoopWindow(ts=1.0, op=op, pv=-np.sign(np.sin(2 * np.pi * t / 150)),
    ...                process_type="self-regulating", period_s=150.0)
    >>> ev = CurveFitDetector().detect(w)
    >>> ev.decision, round(ev.index, 2)
    ('stiction', 0.84)
    """

    no_stiction_below: float = 0.4
    stiction_above: float = 0.6
    harmonics: float = 7.0
    min_cycles: float = 3.0
    name: ClassVar[str] = "curve_fitting"

    def detect(self, window: LoopWindow) -> MethodEvidence:
        """Evidence from the sinusoid and triangle fits (class docstring)."""
        if window.process_type is None:
            return MethodEvidence.undecided(
                self.name,
                "process type unknown: He et al. fit the OP of self-regulating and "
                "the PV of integrating loops",
            )
        signal_name = "pv" if window.process_type == INTEGRATING else "op"
        problem = window_problem(window, (signal_name,), self.min_cycles)
        if problem is not None:
            return MethodEvidence.undecided(self.name, problem)
        signal = window.pv if signal_name == "pv" else window.op
        assert signal is not None
        period = float(window.period_samples or 0.0)
        filtered = shape_filter(signal, period, harmonics=self.harmonics)
        bounds = half_cycle_bounds(filtered)
        lengths = np.diff(bounds)
        regular = (lengths > 0.25 * period) & (lengths < period)
        if np.count_nonzero(regular) < 2 * self.min_cycles:
            return MethodEvidence.undecided(
                self.name,
                f"only {np.count_nonzero(regular)} regular half cycles in the {signal_name.upper()}"
                f" (at least {2 * self.min_cycles:g} are needed)",
            )
        half_cycles = resample_segments(
            filtered, bounds[:-1][regular], bounds[1:][regular], POINTS_PER_HALF_CYCLE
        )
        mse_sin, mse_tri = (float(e.mean()) for e in half_cycle_fit_errors(half_cycles))
        total = mse_sin + mse_tri
        if total <= 0:
            return MethodEvidence.undecided(self.name, "both models fit exactly")
        si = mse_sin / total
        details = {
            "mse_sin": mse_sin,
            "mse_tri": mse_tri,
            "half_cycles": float(np.count_nonzero(regular)),
        }
        what = f"SI = {si:.2f} from {np.count_nonzero(regular)} half cycles of the " + (
            signal_name.upper()
        )
        if si >= self.stiction_above:
            return MethodEvidence(
                self.name, STICTION, si, margin_confidence(si, self.stiction_above, 0.1),
                f"{what}: triangular, as a sticky valve makes it", details,
            )
        if si <= self.no_stiction_below:
            return MethodEvidence(
                self.name, NO_STICTION, si,
                margin_confidence(si, self.no_stiction_below, 0.1),
                f"{what}: sinusoidal, as in a linear oscillation", details,
            )
        return MethodEvidence.undecided(
            self.name,
            f"{what} lies between {self.no_stiction_below:g} and {self.stiction_above:g}",
            si, details,
        )
