"""Area-ratio stiction detection (Singhal and Salsbury 2005).

In a self-regulating loop a sticky valve moves the process input in jumps,
so between jumps the control error drifts away from zero like a step
response (rising towards its peak at a decreasing rate) and comes back
sharply after the valve slips.  In each half cycle of the error, between two
zero crossings, the area before the peak ``A1`` is then larger than the area
after it ``A2``.  Aggressive tuning or an external disturbance give a
sinusoidal, symmetric error and ``A1 ~ A2``.  The index is::

    R = A1 / A2

computed for each half cycle and averaged.  Singhal and Salsbury decide
stiction for ``R > 1`` and no stiction for ``R ~ 1``; the thesis summary
reads "values far from 1 indicate stiction", and industrial loops with a
valve that overshoots when it slips do show ``R < 1``.  With noise and
irregular cycles ``R`` of a linear loop scatters around 1, so this
implementation decides on the asymmetry ``max(R, 1/R)`` with a band of no
decision: at most 1.2 no stiction, at least 1.5 stiction (the band is this
module's choice; the paper gives no numbers for it).

Implementation notes.  The control error is ``SP - PV`` (``PV`` minus its
trend when there is no set point; the sign does not change ``R``).  It is
passed through :func:`~analytics.stiction.shape_rules.shape_filter` (drift
and noise out, harmonics up to the 7th kept, so that noise neither adds zero
crossings nor moves the peak), cut at its zero crossings
(with hysteresis, :func:`~analytics.stiction.shape_rules.half_cycle_bounds`)
and every half cycle resampled to :data:`POINTS_PER_HALF_CYCLE` points.  The
average over half cycles is ``sum(A1) / sum(A2)``, which weights each half
cycle by its size and so is not thrown by a small half cycle with a tiny
``A2``.

References
----------
.. [1] A. Singhal and T. I. Salsbury, "A simple method for detecting valve
   stiction in oscillating control loops", J. Process Control 15 (2005)
   371-382 (thesis ref. [40]).
.. [2] Thesis section 1.2.2, "Area Calculation for Control Error Signal".
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from analytics.stiction.evidence import (
    INTEGRATING,
    NO_STICTION,
    SELF_REGULATING,
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

__all__ = ["POINTS_PER_HALF_CYCLE", "AreaRatioDetector", "half_cycle_areas"]


#: Points at which each half cycle is integrated.
POINTS_PER_HALF_CYCLE = 128


def half_cycle_areas(half_cycles: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Areas before and after the peak of each half cycle.

    Parameters
    ----------
    half_cycles : ndarray, shape (n, points)
        Each row one half cycle between two zero crossings, equally spaced.

    Returns
    -------
    a1, a2 : ndarray, shape (n,)
        Trapezoidal areas of ``|x|`` from the start to the peak and from the
        peak to the end, in units of the sample spacing.

    Examples
    --------
    A half sine is symmetric; a half cycle that peaks late is not:

    >>> u = np.linspace(0.0, 1.0, 101)
    >>> a1, a2 = half_cycle_areas(np.stack([np.sin(np.pi * u), np.minimum(u / 0.8, (1 - u) / 0.2)]))
    >>> np.round(a1 / a2, 2)
    array([1., 4.])
    """
    magnitude = np.abs(half_cycles)
    trapezoids = 0.5 * (magnitude[:, 1:] + magnitude[:, :-1])
    cumulative = np.concatenate(
        [np.zeros((magnitude.shape[0], 1)), np.cumsum(trapezoids, axis=1)], axis=1
    )
    peak = np.argmax(magnitude, axis=1)
    a1 = cumulative[np.arange(magnitude.shape[0]), peak]
    return a1, cumulative[:, -1] - a1


@dataclass(frozen=True, kw_only=True)
class AreaRatioDetector:
    """Area ratio ``R = A1 / A2`` of the control error (Singhal and Salsbury 2005).

    The method is derived for self-regulating processes.  In an integrating
    loop with stiction the error is a symmetric triangle (``R ~ 1``), so a
    symmetric error says nothing there: integrating processes are undecided,
    and with the process type unknown only a stiction decision is made.

    Attributes
    ----------
    no_stiction_below : float
        ``max(R, 1/R)`` at or below which the loop has no stiction.
    stiction_above : float
        ``max(R, 1/R)`` at or above which it has stiction.
    harmonics : float
        Upper edge of the shape filter in multiples of the oscillation
        frequency.
    min_cycles : float
        Fewest oscillation cycles in the window.

    References
    ----------
    Singhal and Salsbury (2005), J. Process Control 15, 371-382.

    Examples
    --------
    An error that rises slowly and falls fast in every half cycle:

    >>> t = np.arange(3000.0)
    >>> half = (t % 75.0) / 75.0
    >>> error = np.sign(np.sin(2 * np.pi * t / 150)) * (1 - np.exp(-4 * half)) * (1 - half**8)
    >>> w = LoopWindow(ts=1.0, op=None, pv=-error, sp=np.zeros(3000),
    ...                process_type="self-regulating", period_s=150.0)
    >>> ev = AreaRatioDetector().detect(w)
    >>> ev.decision, ev.index > 1.5
    ('stiction', True)
    """

    no_stiction_below: float = 1.2
    stiction_above: float = 1.5
    harmonics: float = 7.0
    min_cycles: float = 3.0
    name: ClassVar[str] = "area_ratio"

    def detect(self, window: LoopWindow) -> MethodEvidence:
        """Evidence from the area ratio of the control error (class docstring)."""
        if window.process_type == INTEGRATING:
            return MethodEvidence.undecided(
                self.name,
                "the area ratio applies to self-regulating processes only "
                "(an integrating loop with stiction has a symmetric triangular error)",
            )
        problem = window_problem(window, ("pv",), self.min_cycles)
        if problem is not None:
            return MethodEvidence.undecided(self.name, problem)
        assert window.pv is not None
        error = window.pv if window.sp is None else window.sp - window.pv
        period = float(window.period_samples or 0.0)
        filtered = shape_filter(error, period, harmonics=self.harmonics)
        bounds = half_cycle_bounds(filtered)
        lengths = np.diff(bounds)
        regular = (lengths > 0.25 * period) & (lengths < period)
        n_half = int(np.count_nonzero(regular))
        if n_half < 2 * self.min_cycles:
            return MethodEvidence.undecided(
                self.name,
                f"only {n_half} regular half cycles of the control error "
                f"(at least {2 * self.min_cycles:g} are needed)",
            )
        half_cycles = resample_segments(
            filtered, bounds[:-1][regular], bounds[1:][regular], POINTS_PER_HALF_CYCLE
        )
        a1, a2 = half_cycle_areas(half_cycles)
        ratio = float(a1.sum() / a2.sum())
        asymmetry = max(ratio, 1.0 / ratio)
        details = {
            "half_cycles": float(n_half),
            "median_half_cycle_ratio": float(np.median(a1 / np.maximum(a2, 1e-300))),
        }
        what = f"R = A1/A2 = {ratio:.2f} over {n_half} half cycles of the control error"
        if asymmetry >= self.stiction_above:
            shape = (
                "it drifts away slowly and returns sharply" if ratio > 1
                else "it leaves sharply and returns slowly"
            )
            return MethodEvidence(
                self.name, STICTION, ratio,
                margin_confidence(asymmetry, self.stiction_above, 0.5),
                f"{what}: {shape}, as with valve jumps", details,
            )
        if asymmetry <= self.no_stiction_below and window.process_type == SELF_REGULATING:
            return MethodEvidence(
                self.name, NO_STICTION, ratio,
                margin_confidence(asymmetry, self.no_stiction_below, 0.1),
                f"{what}: the half cycles are symmetric, as in a linear oscillation",
                details,
            )
        if asymmetry <= self.no_stiction_below:
            return MethodEvidence.undecided(
                self.name,
                f"{what}: symmetric, but with the process type unknown an integrating "
                "loop with stiction cannot be ruled out",
                ratio, details,
            )
        return MethodEvidence.undecided(
            self.name,
            f"{what} lies between {self.no_stiction_below:g} and {self.stiction_above:g}",
            ratio, details,
        )
