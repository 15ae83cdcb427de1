"""Cross-correlation stiction detection (Horch 1999).

For a self-regulating process under PI control, Horch observed that the
cross-correlation function (CCF) of OP and PV

    r_uy(tau) = sum_t u(t) y(t + tau)

is an *odd* function of the lag when a sticky valve causes the oscillation
(OP and PV about 90 degrees apart: the integral action ramps OP while the
valve is stuck) and an *even* one when an external oscillation or too tight
tuning does (OP and PV in counter-phase, 180 degrees).  With ``tau_l`` and
``tau_r`` the distances from lag 0 to the nearest zero crossings of the CCF
on the left and on the right, Horch's phase measure is::

    Delta_phi = pi (tau_r - tau_l) / (tau_r + tau_l)

(0 for an even CCF, +-pi for an odd one).  The index reported here is the
normalised ``|Delta_phi| / pi = |tau_r - tau_l| / (tau_r + tau_l)`` in
``[0, 1]``; Horch's thresholds ``|Delta_phi| < pi/3`` (no stiction) and
``|Delta_phi| > 2 pi/3`` (stiction) become 1/3 and 2/3, with no decision in
between.

Implementation notes.  OP and PV are band-passed around the oscillation
(:func:`analytics.oscillation.bandpass`, zero phase, so the OP-PV phase is
kept) before the CCF is computed with one FFT; the zero crossings are
interpolated linearly.

Integrating processes are not handled: the integrator adds 90 degrees
between valve and PV, so the CCF of an integrating loop is odd-looking with
or without stiction (and even under P-only control with stiction).  Horch
and Isaksson (2001) detect stiction there from the distribution of the
second difference of PV; that test is not implemented here (the
curve-fitting and shape-rule detectors cover integrating loops), and the
detector is undecided for integrating or unknown process types.

References
----------
.. [1] A. Horch, "A simple method for detection of stiction in control
   valves", Control Eng. Practice 7 (1999) 1221-1231 (thesis ref. [18]).
.. [2] A. Horch and A. J. Isaksson, "Detection of valve stiction in
   integrating processes", European Control Conference, Porto, 2001
   (thesis ref. [21]).
.. [3] M. Jelali and B. Huang (eds.), *Detection and Diagnosis of Stiction in
   Control Loops*, Springer, 2010 (thesis ref. [23]), chapter
   "Cross-correlation" (the ratio form of the index and the pi/3, 2 pi/3
   thresholds).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from scipy import fft as sfft

from analytics.oscillation import bandpass
from analytics.signals import zero_crossings
from analytics.stiction.evidence import (
    NO_STICTION,
    SELF_REGULATING,
    STICTION,
    LoopWindow,
    MethodEvidence,
    margin_confidence,
)
from analytics.stiction.shape_rules import window_problem
from analytics.types import FloatArray

__all__ = ["CrossCorrelationDetector", "ccf_zero_crossings"]


def ccf_zero_crossings(u: FloatArray, y: FloatArray, max_lag: int) -> tuple[float, float]:
    """Distances ``tau_l, tau_r`` (samples) from lag 0 to the CCF's nearest zero crossings.

    ``r_uy(tau) = sum_t u(t) y(t + tau)`` for ``|tau| <= max_lag``, computed
    with one zero-padded FFT.  A distance is ``nan`` if the CCF does not
    change sign within ``max_lag``.

    Examples
    --------
    PV lagging OP by 20 samples of a 100-sample period: the CCF peaks at
    lag 20 and crosses zero a quarter period either side of it:

    >>> k = np.arange(2000)
    >>> op, pv = np.sin(2 * np.pi * k / 100), np.sin(2 * np.pi * (k - 20) / 100)
    >>> tl, tr = ccf_zero_crossings(op, pv, 100)
    >>> round(tl, 1), round(tr, 1)
    (5.0, 45.0)
    """
    n = u.size
    nfft = sfft.next_fast_len(2 * n, real=True)
    cross = sfft.irfft(np.conj(sfft.rfft(u, nfft)) * sfft.rfft(y, nfft), nfft)
    right = cross[: max_lag + 1]  # lags 0, 1, ..., max_lag
    left = np.concatenate([cross[:1], cross[::-1][:max_lag]])  # lags 0, -1, ..., -max_lag
    crossings = []
    for branch in (left, right):
        zeros = zero_crossings(branch)
        crossings.append(float(zeros[0]) if zeros.size else float("nan"))
    return crossings[0], crossings[1]


@dataclass(frozen=True, kw_only=True)
class CrossCorrelationDetector:
    """Odd or even OP-PV cross-correlation (Horch 1999), see the module docstring.

    Attributes
    ----------
    no_stiction_below : float
        ``|Delta_phi| / pi`` at or below which the CCF is even: no stiction
        (1/3, Horch's pi/3).
    stiction_above : float
        ``|Delta_phi| / pi`` at or above which the CCF is odd: stiction
        (2/3, Horch's 2 pi/3).
    band_ratio : float
        Half-power edges of the band-pass at ``f / band_ratio`` and
        ``f * band_ratio`` around the oscillation frequency ``f``.
    min_cycles : float
        Fewest oscillation cycles in the window.

    References
    ----------
    Horch (1999), Control Eng. Practice 7, 1221-1231.

    Examples
    --------
    PV a quarter period behind OP, the phase a sticky valve gives:

    >>> k = np.arange(3000)
    >>> op = np.sin(2 * np.pi * k / 150)
    >>> pv = -np.cos(2 * np.pi * k / 150)
    >>> w = LoopWindow(ts=1.0, op=op, pv=pv, process_type="self-regulating", period_s=150.0)
    >>> ev = CrossCorrelationDetector().detect(w)
    >>> ev.decision, round(ev.index, 2)
    ('stiction', 1.0)
    """

    no_stiction_below: float = 1.0 / 3.0
    stiction_above: float = 2.0 / 3.0
    band_ratio: float = 1.5
    min_cycles: float = 3.0
    name: ClassVar[str] = "cross_correlation"

    def detect(self, window: LoopWindow) -> MethodEvidence:
        """Evidence from the symmetry of the OP-PV cross-correlation (class docstring)."""
        if window.process_type != SELF_REGULATING:
            kind = "unknown" if window.process_type is None else "integrating"
            return MethodEvidence.undecided(
                self.name,
                f"process type {kind}: the cross-correlation test holds for "
                "self-regulating processes only (an integrator shifts the phase by 90 degrees)",
            )
        problem = window_problem(window, ("op", "pv"), self.min_cycles)
        if problem is not None:
            return MethodEvidence.undecided(self.name, problem)
        assert window.op is not None and window.pv is not None
        period = float(window.period_samples or 0.0)
        op = bandpass(window.op, period, band_ratio=self.band_ratio)
        pv = bandpass(window.pv, period, band_ratio=self.band_ratio)
        tau_l, tau_r = ccf_zero_crossings(op, pv, int(np.ceil(period)))
        if not (np.isfinite(tau_l) and np.isfinite(tau_r)) or tau_l + tau_r <= 0:
            return MethodEvidence.undecided(
                self.name, "the cross-correlation does not cross zero within one period"
            )
        oddness = abs(tau_r - tau_l) / (tau_r + tau_l)
        details = {"tau_l_s": tau_l * window.ts, "tau_r_s": tau_r * window.ts,
                   "delta_phi_deg": 180.0 * (tau_r - tau_l) / (tau_r + tau_l)}
        what = f"|Delta_phi| = {180.0 * oddness:.0f} deg"
        if oddness >= self.stiction_above:
            return MethodEvidence(
                self.name, STICTION, oddness,
                margin_confidence(oddness, self.stiction_above, 0.1),
                f"{what}: the OP-PV cross-correlation is odd, as with a sticky valve",
                details,
            )
        if oddness <= self.no_stiction_below:
            return MethodEvidence(
                self.name, NO_STICTION, oddness,
                margin_confidence(oddness, self.no_stiction_below, 0.1),
                f"{what}: the OP-PV cross-correlation is even, as with an external "
                "oscillation or tight tuning",
                details,
            )
        return MethodEvidence.undecided(
            self.name,
            f"{what} lies between {180 * self.no_stiction_below:.0f} and "
            f"{180 * self.stiction_above:.0f} deg",
            oddness, details,
        )
