"""Valve stiction quantification by Hammerstein identification.

A sticky valve followed by a linear process is a Hammerstein system: OP
drives a stiction model whose output MV drives a linear model whose output is
PV.  For each candidate stick band ``S`` and slip jump ``J`` the valve model
turns the measured OP into MV, the linear part is fitted from MV to the
measured PV by least squares, and the candidate is scored by the output
error of the fitted model (the PV the model simulates from MV alone, not a
one-step-ahead prediction).  A coarse grid over ``(S, J)`` spanning the OP
travel per cycle, followed by shrinking pattern steps around the best point,
finds the pair.  This is the separable least-squares and global-search scheme
of Jelali (2008) [1]_ and of the PATS package of thesis Appendix A (search
bounds, Hammerstein fits over the search space, best output MSE; Lee, Ren &
Huang 2008 [2]_, thesis ref. [28]).

Valve models: He's (thesis ref. [17], [4]_) and Kano's [5]_, both with the
parameters ``(S, J)`` of thesis Eq. 1.2.  They agree on a clean limit cycle
but not on a slow OP ramp, where He's valve climbs in slips of ``J`` and
Kano's follows OP smoothly; both are tried and the better fit is kept.

Linear part, first order with dead time, optionally with an integrator::

    x_b = block mean of the lag of MV               (lag, a = exp(-h / tau) per block)
    PV_b = c + d b + K x_b                         self-regulating (FOPDT)
    PV_b - PV_{b-1} = c + d b + K h x_b            integrating

on block means of ``h / ts`` raw samples (``h`` about a 25th of the
oscillation period), with MV delayed by a whole number of *raw* samples
before the averaging; the lag's block means are exact for MV held at its
block mean (:func:`_lag_step`).  The dead time needs that resolution: a later slip of
a larger stick band and a longer dead time look alike, so a coarse delay
would bias S by the OP travel in one block.  The offset ``c`` and ramp
``d b`` take up the unknown operating point and a slow drift (for an
integrating process, the unknown MV at which PV balances).  An integrating
process is fitted on the PV increments: from MV to the rate of change of PV
it is self-regulating, and model errors do not accumulate into a drift.  For
given ``(a, delay)`` the model is linear in ``(c, d, K)``, so the inner
problem is ordinary least squares whose residual is the output error; ``a``
and the delay are searched on a grid.  The sign of ``K`` must give negative
feedback with the controller (read from the same-sample correlation of the
OP and PV increments, see :func:`_feedback_sign`); otherwise the inverse of
the controller fits a healthy-valve model to a smooth PV.

The process gain.  In a stiction limit cycle OP travels only just past S:
the valve slips once per OP reversal and MV is nearly a square wave of height
J, whose PV step is ``K J``.  The window pins that product firmly; J alone
rests on the small travel after each slip and on the shape of the linear
model.  A gain known from elsewhere (a step test, the plant's process model)
is fitted as given (``process_gain``; :func:`quantify_with_gain` uses it after
the fit with the gain fitted), and J is then the slip that moves PV by the
measured step.  Without one, J is fitted again with the gain halved and
doubled (:func:`_gain_profile`): when either fits about as well, the estimate
says that only ``K J`` is known (``J_product_only``) and widens J's interval.

The valve's state at the start is unknown and matters for long: in a limit
cycle OP swings barely more than S, so a model valve that starts in the
wrong place, or misses one reversal, stays out of step for many cycles.  The
model valve starts on the trailing edge of its band at an OP turning point
(:func:`_first_turning_point`), a He valve where it last slipped
(:meth:`_Window._approaches`), and the score begins a period later.  The
same sensitivity makes the search surface rough across S, with a narrow
optimum close to the OP travel per cycle, and smooth in J at the right S:
a coarse scan along S, dense near that bound, gives the distinct basins
(:func:`_basins`); at each, J is searched alone (:func:`_line_search_j`),
then both by pattern steps.  The intervals of S and J are likelihood-ratio
intervals over every candidate scored, widened by the search's model error
(:func:`_profile_intervals`).

References
----------
.. [1] M. Jelali (2008), "Estimation of valve stiction in control loops using
   separable least-squares and global search algorithms", J. Process Control
   18:632-642.
.. [2] K. H. Lee, Z. Ren & B. Huang (2008), "Novel closed-loop stiction
   detection and quantification method via system identification", ADCONIP,
   Jasper (thesis ref. [28]; thesis Appendix A, steps 2-4).
.. [3] M. A. A. S. Choudhury, M. Jain & S. L. Shah (2008), "Stiction -
   definition, modelling, detection and quantification", J. Process Control
   18:232-243 (Hammerstein quantification with a grid over S and J).
.. [4] Q. P. He, J. Wang, M. Pottmann & S. J. Qin (2007), "A curve fitting
   method for detecting valve stiction in oscillating control loops", Ind.
   Eng. Chem. Res. 46:4549-4560.
.. [5] M. Kano, H. Maruta, H. Kugemoto & K. Shimizu (2004), "Practical model
   and detection algorithm for valve stiction", IFAC DYCOPS.
.. [6] D. M. Bates & D. G. Watts (1988), "Nonlinear Regression Analysis and
   Its Applications", Wiley (Sec. 6.1, likelihood-ratio regions).
.. [7] C. J. Geyer (1992), "Practical Markov chain Monte Carlo", Statist.
   Sci. 7:473-483 (Sec. 3.3, initial positive sequence).
.. [8] Particle Data Group (2022), "Review of Particle Physics", Prog. Theor.
   Exp. Phys. 083C01, Introduction Sec. 5.2.2 (averaging with a scale factor).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import minimize_scalar
from scipy.stats import chi2, norm

from analytics.errors import DataError
from analytics.lti import FirstOrderProcess
from analytics.oscillation import bandpass, detect_loop_oscillation
from analytics.serial import Reader
from analytics.signals import autocorrelation
from analytics.types import INTEGRATING, SELF_REGULATING, FloatArray, ProcessType
from analytics.valves import HE, HeValve, KanoValve, ValveModel, sj_to_fsfd, valve_series

__all__ = [
    "GAIN_PROFILE",
    "GIVEN_GAIN_R2_LOSS",
    "INTERVAL_LEVEL",
    "MIN_FIT_R2",
    "MIN_R2_GAIN",
    "VALVE_MODELS",
    "CombinedValue",
    "FitTrace",
    "ProcessType",
    "SearchSummary",
    "StictionEstimate",
    "combine_windows",
    "quantify_stiction",
    "quantify_with_gain",
]


VALVE_MODELS: dict[str, Callable[[float, float], ValveModel]] = {
    "he": lambda S, J: HeValve(*sj_to_fsfd(S, J)),
    "kano": KanoValve,
}
"""Stiction models the search can use, built from ``(S, J)``."""

LEAD_IN = 4
"""Samples that bring the model valve to the first OP turning point (:meth:`_Window.build`)."""
TAU_FRACTIONS = np.geomspace(0.02, 3.0, 13)
"""Process time constants tried, as fractions of the oscillation period (and tau = 0):
steps of a factor 1.5 (with steps of 2.3 the demo's FV-105, a lag of 8 s in a 113 s
cycle, fell between 5.2 and 12 s, and a Kano valve of a smaller S fitted better)."""


MIN_FIT_R2 = 0.6
"""Output-error R^2 below which an estimate is flagged as a poor fit."""
INTERVAL_LEVEL = 0.95
"""Confidence level of the intervals of S and J (:func:`_profile_intervals`)."""
MODEL_ERROR = (0.15, 0.22)
"""Model error of the search for S and J, as a fraction of the OP travel per cycle,
added to either side of their likelihood intervals (:func:`_profile_intervals`).

The likelihood sees the noise, not the bias of a Hammerstein model whose valve
is replayed open loop on a rough surface (a slip a sample early moves the
best S; J trades against the process gain).  Calibrated on the stiction cases
of :func:`analytics.synthetic_cases.synthetic_library`: the 85th percentile of
the distance from the simulated S and J to the likelihood interval is 0.15 and
0.22 of the OP travel.  Calibrated on one half of the cases (alternate cases),
the other half's intervals hold S in 84-89 % and J in 53-100 % of the cases:
nominal 95 % intervals that hold the truth about 80 % of the time, J's less
surely."""
GAIN_PROFILE = (0.5, 2.0)
"""Process gains, as factors of the fitted one, at which J is fitted again when no gain
is given (:func:`_gain_profile`): a J that fits about as well with the gain halved or
doubled is known only through the product ``K J``."""
GIVEN_GAIN_R2_LOSS = 0.02
"""R^2 a fit with a given process gain may lose against the fit with the gain fitted before
:func:`quantify_with_gain` calls the gain wrong for the window (on the demo plant the
simulated gains lose at most 0.004; the 3x3 column's start-up hour, whose cycle has not
settled, loses 0.2)."""
MIN_R2_GAIN = 0.02
"""R^2 a stiction model must add over a healthy valve for ``stiction_found``
(stiction cases of the synthetic library gain 0.05-0.3, linear loops at most 0.011)."""

@dataclass(frozen=True)
class SearchSummary:
    """How the (S, J) search went and how sharply the data pin the answer.

    Attributes
    ----------
    valve_model : str
        The stiction model that fitted best (a key of :data:`VALVE_MODELS`).
    s_max : float
        Upper bound of the S search: the median peak-to-peak OP travel per
        oscillation cycle, %.
    evaluations : int
        Stiction candidates scored (counted once per process type tried).
    s_range, j_range : (float, float)
        Smallest and largest S and J among the candidates whose output-error
        variance is within ``near_optimal_tolerance`` of the best: a wide range
        means the data do not determine that parameter.
    r2_ideal_valve : float
        Output-error R^2 of the best linear model with a healthy valve (S = 0).
    samples_per_cycle : float
        Oscillation period in block-averaged samples.
    downsample_factor : int
        Raw samples averaged into one sample of the fit.
    cycles : float
        Oscillation cycles in the analysed window.
    mv_travel_fraction : float
        Peak-to-peak travel of the model MV over that of OP (near 0: the
        model valve hardly moves).
    """

    valve_model: str
    s_max: float
    evaluations: int
    s_range: tuple[float, float]
    j_range: tuple[float, float]
    r2_ideal_valve: float
    samples_per_cycle: float
    downsample_factor: int
    cycles: float
    mv_travel_fraction: float


@dataclass(frozen=True)
class FitTrace:
    """Block-averaged signals of the scored window, for plotting the fit.

    Attributes
    ----------
    t_s : ndarray
        Block centre times from the start of the window, s.
    op, mv : ndarray
        Measured OP and the MV of the identified valve model.
    pv, pv_fit : ndarray
        The fitted quantity, measured and simulated by the identified
        Hammerstein model: PV, or for an integrating process the PV increment
        per block (see ``quantity``).
    quantity : {"pv", "pv_increment"}
        What ``pv`` and ``pv_fit`` hold.
    """

    t_s: FloatArray
    op: FloatArray
    mv: FloatArray
    pv: FloatArray
    pv_fit: FloatArray
    quantity: Literal["pv", "pv_increment"]


@dataclass(frozen=True)
class StictionEstimate:
    """Result of :func:`quantify_stiction`.

    Attributes
    ----------
    S, J : float or None
        Stick band plus deadband and slip jump, in OP units (% of span when
        OP is); None when the method could not run (see ``issues``).
    fs, fd : float or None
        The same in He's parametrisation, ``S = fs + fd``, ``J = fs - fd``
        (thesis Eq. 1.2).
    fit_r2 : float or None
        Output-error R^2 of the simulated PV over the scored window.
    model : FirstOrderProcess or None
        The identified linear part, from MV (% of travel) to PV (plant units);
        ``tau = 0`` when no lag was found, and ``theta`` is the MV delay less the
        one sample of the hold (a PV sample can answer the MV of the sample
        before at the earliest).
    search : SearchSummary or None
        Search bound, chosen valve model and the near-optimal region.
    trace : FitTrace or None
        The fitted signals.
    period_s : float or None
        Oscillation period used, s.
    stiction_found : bool
        True when the best model has a stick band that matters: ``S`` at least
        ``min_stick_band`` of the OP travel per cycle, explaining at least
        ``min_r2_gain`` more of the variance than a healthy valve.
    trustworthy : bool
        True when an estimate exists and none of ``issues`` applies.
    issues : tuple of str
        Why the estimate is missing or not to be trusted: no oscillation, too
        few cycles, a poor fit, S at the search bound, a model valve that
        hardly moves, J undetermined.
    S_interval, J_interval : (float, float) or None
        Nominal :data:`INTERVAL_LEVEL` intervals of S and J: likelihood-ratio
        intervals over the candidates scored, widened by the search's model
        error (:func:`_profile_intervals`, :data:`MODEL_ERROR`; they hold the
        simulated valve in about 80 % of the synthetic library's cases);
        None without an estimate.  With ``J_product_only`` the interval of J
        also spans the J of the gain profile (:func:`_gain_profile`).
    gain_given : bool
        The process gain was given (``process_gain``), not fitted: J is the
        slip that moves PV by the measured step through that gain.
    J_product_only : bool
        No gain was given and J fits about as well with the fitted gain halved
        or doubled (:data:`GAIN_PROFILE`): the window pins ``K J`` (:attr:`slip_step`),
        not J (in a stiction limit cycle OP travels only just past S, the
        valve slips once per reversal and MV is nearly a square wave of height
        J).  An issue says so.
    """

    S: float | None
    J: float | None
    fs: float | None
    fd: float | None
    fit_r2: float | None
    model: FirstOrderProcess | None
    search: SearchSummary | None
    trace: FitTrace | None
    period_s: float | None
    stiction_found: bool
    trustworthy: bool
    issues: tuple[str, ...]
    S_interval: tuple[float, float] | None = None
    J_interval: tuple[float, float] | None = None
    gain_given: bool = False
    J_product_only: bool = False

    @property
    def valve_model(self) -> str | None:
        """The valve model the search chose; None without a search."""
        return None if self.search is None else self.search.valve_model

    @property
    def slip_step(self) -> float | None:
        """The product of the process gain and J, which a limit cycle pins best: the PV
        step of one slip (for an integrating process, the step of PV's rate of change)."""
        if self.J is None or self.model is None:
            return None
        return self.model.K * self.J

    def to_dict(self) -> dict[str, Any] | None:
        """JSON form ``{S, J, fs, fd, fit_r2, ...}``; None when nothing was estimated."""
        if self.S is None or self.model is None or self.search is None:
            return None
        return {
            "S": self.S,
            "J": self.J,
            "fs": self.fs,
            "fd": self.fd,
            "fit_r2": self.fit_r2,
            "stiction_found": self.stiction_found,
            "trustworthy": self.trustworthy,
            "issues": list(self.issues),
            "S_interval": None if self.S_interval is None else list(self.S_interval),
            "J_interval": None if self.J_interval is None else list(self.J_interval),
            "interval_level": INTERVAL_LEVEL,
            "gain_given": self.gain_given,
            "J_product_only": self.J_product_only,
            "KJ": self.slip_step,
            "valve_model": self.search.valve_model,
            "process": {
                "K": self.model.K,
                "tau": self.model.tau,
                "theta": self.model.theta,
                "integrating": self.model.integrating,
            },
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], where: str = "quantification", *,
                  lenient: bool = False) -> StictionEstimate:
        """The estimate of :meth:`to_dict`'s form: ``to_dict(from_dict(d)) == d``.

        ``KJ`` and ``interval_level`` are derived, so not read.  What :meth:`to_dict`
        does not keep is left empty: no ``trace`` and no ``period_s`` (None), and of the
        ``search`` only the ``valve_model`` (its numbers NaN, its counts 0).  Estimates
        stored before the intervals, ``gain_given`` and ``J_product_only`` read None and
        False.  ``lenient`` (see :meth:`analytics.diagnosis.LoopDiagnosis.from_dict`):
        missing numbers read None, flags False, issues none, and without a ``process``
        there is no ``model``.

        Raises
        ------
        DataError
            A field is missing or of the wrong kind; the message names it and ``where``.
        """
        read = Reader(d, where, lenient=lenient)
        process = read("process")
        nan = math.nan
        return cls(
            S=read("S"), J=read("J"), fs=read("fs"), fd=read("fd"), fit_r2=read("fit_r2"),
            model=None if lenient and not process else _process_from_dict(read.part("process")),
            search=SearchSummary(read("valve_model"), nan, 0, (nan, nan), (nan, nan), nan, nan,
                                 0, nan, nan),
            trace=None, period_s=None, stiction_found=read("stiction_found", False),
            trustworthy=read("trustworthy", False), issues=tuple(read("issues", ())),
            S_interval=None if read.get("S_interval") is None else read.pair("S_interval"),
            J_interval=None if read.get("J_interval") is None else read.pair("J_interval"),
            gain_given=bool(read.get("gain_given")),
            J_product_only=bool(read.get("J_product_only")),
        )


def _process_from_dict(process: Reader) -> FirstOrderProcess:
    """The ``process`` of an estimate's JSON form."""
    return FirstOrderProcess(INTEGRATING if process("integrating") else SELF_REGULATING,
                             process("K"), process("tau"), process("theta"))


@dataclass(frozen=True)
class CombinedValue:
    """One parameter combined over the windows of a valve (:func:`combine_windows`).

    Attributes
    ----------
    value : float
        Weighted median of the windows' estimates.
    interval : (float, float)
        Confidence interval at :data:`INTERVAL_LEVEL`, not below 0.
    windows : int
        Estimates combined.
    """

    value: float
    interval: tuple[float, float]
    windows: int


def _weighted_median(values: FloatArray, weights: FloatArray) -> float:
    """The value where the cumulative weight of the sorted values reaches half (the mean
    of the two values on either side when it does so exactly between them)."""
    order = np.argsort(values)
    v, cum = values[order], np.cumsum(weights[order])
    half = 0.5 * cum[-1]
    k = int(np.searchsorted(cum, half))
    if k + 1 < v.size and math.isclose(cum[k], half):
        return float(0.5 * (v[k] + v[k + 1]))
    return float(v[k])


LACK_OF_FIT_FLOOR = 1e-3
"""Smallest unexplained share ``1 - R^2`` :func:`combine_windows` counts: fits closer than
R^2 0.999 are all as good as the model gets (measurement noise, historian rounding)."""


def combine_windows(
    values: Sequence[float], intervals: Sequence[tuple[float, float]],
    fit_r2: Sequence[float | None] | None = None,
) -> CombinedValue:
    """Combine estimates of one parameter (S or J) from windows that do not overlap.

    Each window's estimate gets the weight ``1 / sigma^2``, ``sigma`` its
    interval's width over ``2 z`` (``z`` the normal quantile of
    :data:`INTERVAL_LEVEL``), but at least the median ``sigma`` of the windows
    and 1 % of the estimate: a window whose interval is wider than usual
    counts less, and none counts more than a typical one (a window fitted
    in a wrong basin of the rough search surface can have a narrow interval
    around its wrong value).

    With ``fit_r2``, each window's output-error R^2, a window the model does
    not describe counts less.  The intervals carry the search's model error as
    calibrated on windows its model describes (:data:`MODEL_ERROR`), which a
    window the model does not describe (a start-up transient, a load change)
    exceeds.  The variance of a least-squares estimate is proportional to the
    residual variance of its fit (``s^2 (J^T J)^-1``, Bates & Watts 1988
    [6]_), so ``sigma`` is scaled by ``sqrt(u / u_best)``, ``u = 1 - R^2`` (at
    least :data:`LACK_OF_FIT_FLOOR`) and ``u_best`` the best fit among the
    windows: windows of one loop see about the same PV variance, so the ratio
    is that of their residual variances.  Two windows that disagree then leave
    the decision to the one whose model fits (with equal weights the weighted
    median of two is the estimate whose interval happens to be the narrower).
    A window without an R^2 keeps its ``sigma``.

    The combined value is the weighted median, which a minority of such windows
    cannot drag.  Its standard error is that of the weighted mean, ``1 /
    sqrt(sum w)``, scaled up when the windows scatter more than their intervals
    say: the PDG's scale factor [8]_ in a robust form, ``sigma = max(1 /
    sqrt(sum w), 1.4826 MAD_w / sqrt(N))`` with ``MAD_w`` the weighted median
    absolute deviation from the combined value.  The interval is the value plus
    or minus ``z sigma``.

    Raises
    ------
    ValueError
        If there is no estimate, the lengths differ, or an interval does not
        hold its estimate.

    Examples
    --------
    Three windows agree, a fourth fell into another basin of the fit:

    >>> c = combine_windows([4.0, 4.1, 3.9, 2.7],
    ...                     [(3.8, 4.2), (3.9, 4.3), (3.7, 4.1), (2.6, 2.8)])
    >>> round(c.value, 2), c.windows
    (3.95, 4)
    >>> c.interval[0] < 3.95 < c.interval[1]
    True

    The demo's FV-502: its first hour is the column's start-up (R^2 0.91), the
    second a steady cycle (R^2 0.99); their S intervals are as wide and exclude
    each other, and the steady hour decides:

    >>> c = combine_windows([2.22, 4.18], [(1.58, 2.85), (3.54, 4.82)], [0.910, 0.991])
    >>> round(c.value, 2), c.interval[0] > 2.85
    (4.18, True)
    """
    x = np.asarray(values, dtype=np.float64)
    bounds = np.asarray(intervals, dtype=np.float64).reshape(-1, 2)
    if x.size == 0 or bounds.shape[0] != x.size:
        raise ValueError(f"need one interval per estimate, got {x.size} estimates and "
                         f"{bounds.shape[0]} intervals")
    if fit_r2 is not None and len(fit_r2) != x.size:
        raise ValueError(f"need one R^2 per estimate (or None), got {len(fit_r2)} for "
                         f"{x.size} estimates")
    if np.any(bounds[:, 0] > x) or np.any(x > bounds[:, 1]):
        raise ValueError("every interval must hold its estimate")
    z = float(norm.ppf(0.5 + 0.5 * INTERVAL_LEVEL))
    sigma = (bounds[:, 1] - bounds[:, 0]) / (2.0 * z)
    sigma = np.maximum(sigma, np.maximum(float(np.median(sigma)), 0.01 * np.abs(x)))
    if fit_r2 is not None:
        unexplained = np.array([math.nan if r is None or not math.isfinite(r)
                                else max(1.0 - r, LACK_OF_FIT_FLOOR) for r in fit_r2])
        known = np.isfinite(unexplained)
        if known.any():
            best = float(unexplained[known].min())
            sigma = sigma * np.where(known, np.sqrt(np.where(known, unexplained, best) / best),
                                     1.0)
    weights = 1.0 / np.maximum(sigma, 1e-9) ** 2
    value = _weighted_median(x, weights)
    scatter = 1.4826 * _weighted_median(np.abs(x - value), weights) / math.sqrt(x.size)
    spread = z * max(1.0 / math.sqrt(float(weights.sum())), scatter)
    return CombinedValue(value, (max(value - spread, 0.0), value + spread), int(x.size))


# ----------------------------------------------------------------------------
# compiled kernels


@njit(cache=True, inline="always")
def _block_mean(cm: FloatArray, factor: int, delay: int, b: int) -> float:
    """Mean over block ``b`` of MV delayed by ``delay`` raw samples, from its cumulative
    sum ``cm`` (``cm[k]`` is the sum of the first ``k`` raw MV samples).  A block
    reaching before the first sample averages what exists (it lies in the unscored
    start)."""
    lo = max(b * factor - delay, 0)
    hi = max((b + 1) * factor - delay, 0)
    return (cm[hi] - cm[lo]) / (hi - lo) if hi > lo else cm[1]


@njit(cache=True)
def _delayed_block_means(cm: FloatArray, factor: int, delay: int, n_blocks: int) -> FloatArray:
    """The :func:`_block_mean` of every block."""
    out = np.empty(n_blocks)
    for b in range(n_blocks):
        out[b] = _block_mean(cm, factor, delay, b)
    return out


@njit(cache=True, inline="always")
def _lag_gains(a: float, factor: int) -> tuple[float, float]:
    """Gains ``(a, g)`` of :func:`_lag_step` for the pole ``a`` per block of ``factor``
    raw samples (no lag for ``a = 0``)."""
    r = a ** (1.0 / factor) if a > 0.0 else 0.0
    end_gain = a if a > 0.0 else 0.0
    mean_gain = r * (1.0 - end_gain) / (factor * (1.0 - r)) if r > 0.0 else 0.0
    return end_gain, mean_gain


@njit(cache=True, inline="always")
def _lag_step(
    state: float, u: float, end_gain: float, mean_gain: float
) -> tuple[float, float]:
    """One block of the lag ``x_k = r x_{k-1} + (1 - r) u_k`` of the raw samples
    (``r = a^(1 / factor)``, ``a`` the lag's pole per block), driven by the raw samples
    held at the block's mean ``u``: the lag's mean over the block and its state at
    the block's end.

    The state ``e`` at the end of a block and the mean over the next follow
    exactly from the raw recursion (gains from :func:`_lag_gains`)::

        e_b = a e_{b-1} + (1 - a) u_b
        mean_b = g e_{b-1} + (1 - g) u_b,    g = r (1 - a) / (factor (1 - r))

    A lag run on the block means as if they were samples (``x_b = a x_{b-1} +
    (1 - a) u_b``) takes the block mean for the state at the block's end,
    half a block late: on a lag of a few blocks its output error was a few
    tenths of a percent of PV's variance even with the true valve and
    process, enough for a valve model that slips at another time to fit
    better (the demo's FV-105, He S 8, J 4, read as a Kano valve of S 6.96
    in one window: R^2 0.993 against 0.991 for its own valve, 0.9998 with the
    exact lag).
    """
    return (mean_gain * state + (1.0 - mean_gain) * u,
            end_gain * state + (1.0 - end_gain) * u)


@njit(cache=True)
def _lags(u: FloatArray, factor: int, poles: FloatArray) -> FloatArray:
    """Block means of the lag of each pole of ``poles`` driven by the block means ``u``
    (:func:`_lag_step`), one column per pole, the lag starting at rest at ``u[0]``.

    The poles run side by side (the columns are contiguous per block), so their
    recursions overlap instead of waiting on each other.
    """
    n_blocks, n_poles = u.shape[0], poles.shape[0]
    end_gain = np.empty(n_poles)
    mean_gain = np.empty(n_poles)
    for p in range(n_poles):
        end_gain[p], mean_gain[p] = _lag_gains(poles[p], factor)
    out = np.empty((n_blocks, n_poles))
    state = np.full(n_poles, u[0])
    for b in range(n_blocks):
        row = out[b]
        for p in range(n_poles):
            row[p], state[p] = _lag_step(state[p], u[b], end_gain[p], mean_gain[p])
    return out


@njit(cache=True)
def _residual(
    s_r: float, s_rr: float, s_tr: float, s_ry: float, s_yy: float, m: int, sign: float,
    fixed: float,
) -> tuple[float, float]:
    """Residual and gain of ``y ~ c + d i + K r`` from the sums over ``i < m``.

    A gain of the sign opposite to ``sign`` (when not 0) is no fit.  A
    ``fixed`` gain (not NaN) is taken as given: only ``c`` and ``d`` are fitted.

    ``y`` has been detrended (its own line removed), so by the
    Frisch-Waugh-Lovell theorem only ``r`` needs its line removed:
    ``var_r = s_rr - s_r^2 / m - s_tr^2 / s_tt`` with ``s_tr`` taken about the
    mean index; with ``K`` fixed the residual is ``s_yy - 2 K s_ry + K^2 var_r``.
    """
    s_tt = m * (m * m - 1.0) / 12.0
    var_r = s_rr - s_r * s_r / m - s_tr * s_tr / s_tt
    if not math.isnan(fixed):
        return max(s_yy - 2.0 * fixed * s_ry + fixed * fixed * max(var_r, 0.0), 0.0), fixed
    if not var_r > 1e-12 * s_rr:
        return s_yy, 0.0
    gain = s_ry / var_r
    if gain * sign < 0.0:
        return s_yy, 0.0
    return max(s_yy - s_ry * gain, 0.0), gain


@njit(cache=True)
def _fit_at_delay(
    cm: FloatArray, factor: int, delay: int, a: float, y: FloatArray, start: int,
    sign: float, fixed: float,
) -> tuple[float, float]:
    """Residual and gain of ``y_i ~ c + d i + K x_{start + i}`` (``y`` detrended;
    ``K = fixed`` unless NaN), ``x`` the lag of pole ``a`` (:func:`_lag_step`) of MV
    delayed by ``delay`` raw samples (:func:`_block_mean`): the lag and the sums of
    the fit in one pass."""
    m = y.shape[0]
    t_mean = 0.5 * (m - 1)
    end_gain, mean_gain = _lag_gains(a, factor)
    state = _block_mean(cm, factor, delay, 0)
    for b in range(start):
        state = _lag_step(state, _block_mean(cm, factor, delay, b), end_gain, mean_gain)[1]
    s_r = s_rr = s_tr = s_ry = s_yy = 0.0
    for i in range(m):
        v, state = _lag_step(state, _block_mean(cm, factor, delay, start + i), end_gain,
                             mean_gain)
        s_r += v
        s_rr += v * v
        s_tr += (i - t_mean) * v
        s_ry += v * y[i]
        s_yy += y[i] * y[i]
    return _residual(s_r, s_rr, s_tr, s_ry, s_yy, m, sign, fixed)


@njit(cache=True)
def _prefix_sums(x: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Running sums of ``x[k]``, ``x[k]^2`` and ``k x[k]`` down each column of ``x``,
    with a leading row of zeros."""
    n, n_columns = x.shape
    p1 = np.zeros((n + 1, n_columns))
    p2 = np.zeros((n + 1, n_columns))
    pk = np.zeros((n + 1, n_columns))
    for k in range(n):
        for p in range(n_columns):
            v = x[k, p]
            p1[k + 1, p] = p1[k, p] + v
            p2[k + 1, p] = p2[k, p] + v * v
            pk[k + 1, p] = pk[k, p] + k * v
    return p1, p2, pk


@njit(cache=True)
def _cross_products(x: FloatArray, lo: int, targets: FloatArray, n_q: int) -> FloatArray:
    """``out[t, q * P + p] = sum_i x[lo + q + i, p] targets[t, i]`` for ``q < n_q``, ``P``
    the columns of ``x``.

    Each sum runs over ``i`` in order, as a single dot product would.  For one
    ``i`` the sums of every ``q`` and ``p`` take the rows ``lo + i .. lo + i + n_q - 1``,
    which are contiguous: each ``i`` adds one slice of ``x`` times ``targets[t, i]``,
    four ``i`` at a time so that each sum is loaded and stored once per four.
    """
    n_t, m = targets.shape
    n_columns = x.shape[1]
    span = n_q * n_columns
    flat = x.ravel()
    out = np.zeros((n_t, span))
    for t in range(n_t):
        y = targets[t]
        sums = out[t]
        i = 0
        while i + 4 <= m:
            at = (lo + i) * n_columns
            x0 = flat[at : at + span]
            x1 = flat[at + n_columns : at + n_columns + span]
            x2 = flat[at + 2 * n_columns : at + 2 * n_columns + span]
            x3 = flat[at + 3 * n_columns : at + 3 * n_columns + span]
            y0, y1, y2, y3 = y[i], y[i + 1], y[i + 2], y[i + 3]
            for k in range(span):
                sums[k] = sums[k] + x0[k] * y0 + x1[k] * y1 + x2[k] * y2 + x3[k] * y3
            i += 4
        for rest in range(i, m):
            at = (lo + rest) * n_columns
            x0 = flat[at : at + span]
            for k in range(span):
                sums[k] += x0[k] * y[rest]
    return out


VECTOR_COLUMNS = 16
"""The compiled loops over the columns of :func:`_lags` and :func:`_prefix_sums` run
in vector registers in groups of this many columns (8 lanes of AVX-512, unrolled
twice) and one column at a time for the rest: the 14 poles of the full linear-model
grid are padded to 16, which costs less than the scalar loop over 14; the three
poles around a point are left as they are."""


@njit(cache=True)
def _best_linear_fits(
    cm: FloatArray,
    factor: int,
    targets: FloatArray,
    start: int,
    poles: FloatArray,
    limits: NDArray[np.int64],
    sign: float,
    fixed: FloatArray,
) -> tuple[FloatArray, NDArray[np.int64], NDArray[np.int64]]:
    """Best output-error fit of each target row over poles and delays (the gain of row
    ``t`` fixed at ``fixed[t]`` unless NaN).

    Delays of ``1 + j factor`` raw samples (``j`` from ``limits[2]`` to
    ``limits[3]``) are tried with every pole ``limits[0]..limits[1]``, using
    running sums so that a delay costs one pass of ``r y`` products
    (:func:`_cross_products`); for each target's best pole the raw delay is
    then refined by halving steps.
    Returns the residual, pole index and raw delay per target.
    """
    n_t, m = targets.shape
    n_blocks = start + m
    t_mean = 0.5 * (m - 1)
    s_yy = np.array([np.sum(targets[t] ** 2) for t in range(n_t)])
    best = np.full(n_t, np.inf)
    best_pole = np.full(n_t, limits[0])
    best_delay = np.ones(n_t, dtype=np.int64)
    tried = poles[limits[0] : limits[1] + 1]
    n_tried = tried.shape[0]
    if n_tried > VECTOR_COLUMNS // 2:  # padded with the last pole, never chosen
        width = -(-n_tried // VECTOR_COLUMNS) * VECTOR_COLUMNS
        tried = np.concatenate((tried, np.full(width - n_tried, tried[-1])))
    x = _lags(_delayed_block_means(cm, factor, 1, n_blocks), factor, tried)
    p1, p2, pk = _prefix_sums(x)
    lo_min = start - limits[3]
    n_poles = x.shape[1]
    cross = _cross_products(x, lo_min, targets, limits[3] - limits[2] + 1)
    for p in range(n_tried):
        for j in range(limits[2], limits[3] + 1):
            lo = start - j
            s_r = p1[lo + m, p] - p1[lo, p]
            s_rr = p2[lo + m, p] - p2[lo, p]
            s_tr = pk[lo + m, p] - pk[lo, p] - (lo + t_mean) * s_r
            for t in range(n_t):
                s_ry = cross[t, (lo - lo_min) * n_poles + p]
                sse = _residual(s_r, s_rr, s_tr, s_ry, s_yy[t], m, sign, fixed[t])[0]
                if sse < best[t]:
                    best[t] = sse
                    best_pole[t] = limits[0] + p
                    best_delay[t] = 1 + j * factor
    max_delay = 1 + limits[3] * factor
    for t in range(n_t):
        step = factor // 2
        while step >= 1:
            centre = best_delay[t]
            for delay in (centre - step, centre + step):
                if 1 <= delay <= max_delay:
                    sse = _fit_at_delay(cm, factor, delay, poles[best_pole[t]], targets[t],
                                        start, sign, fixed[t])[0]
                    if sse < best[t]:
                        best[t] = sse
                        best_delay[t] = delay
            step //= 2
    return best, best_pole, best_delay


@njit(cache=True)
def _every_linear_fit(
    cm: FloatArray,
    factor: int,
    target: FloatArray,
    start: int,
    poles: FloatArray,
    max_delay: int,
    sign: float,
    fixed: float,
) -> tuple[float, int, int]:
    """Best output-error fit of ``target`` over every pole and every raw delay from 1 to
    ``max_delay``: residual, pole index and delay (for the one healthy-valve candidate,
    see :meth:`_Window.score_healthy_valve`)."""
    best, best_pole, best_delay = np.inf, 0, 1
    for ip in range(poles.shape[0]):
        for delay in range(1, max_delay + 1):
            sse = _fit_at_delay(cm, factor, delay, poles[ip], target, start, sign, fixed)[0]
            if sse < best:
                best, best_pole, best_delay = sse, ip, delay
    return best, best_pole, best_delay


@njit(cache=True)
def _valve_cumsum(
    code: int,
    params: FloatArray,
    approach: float,
    state: FloatArray,
    valve_input: FloatArray,
    first_turn: int,
    op0: float,
    dt: float,
) -> FloatArray:
    """Cumulative sum (leading 0) of the model MV less ``op0`` (see :meth:`_Window.valve_cumsum`).

    The valve runs from a copy of ``state`` over ``valve_input`` (four
    lead-in samples, the last replaced by ``approach``, then OP from
    ``first_turn``); before ``first_turn`` its MV is held at the position
    after the lead-in.
    """
    run_input = valve_input.copy()
    run_input[LEAD_IN - 1] = approach
    run = valve_series(code, params, state.copy(), run_input, dt)
    n = first_turn + run.shape[0] - LEAD_IN
    cm = np.empty(n + 1)
    cm[0] = total = 0.0
    for k in range(n):
        held = k < first_turn
        total += (run[LEAD_IN] if held else run[LEAD_IN + k - first_turn]) - op0
        cm[k + 1] = total
    return cm


@njit(cache=True)
def _score_candidates(
    code: int,
    params: FloatArray,
    approaches: FloatArray,
    state: FloatArray,
    valve_run: tuple[FloatArray, int, float, float],
    factor: int,
    targets: FloatArray,
    start: int,
    poles: FloatArray,
    limits: NDArray[np.int64],
    sign: float,
    fixed: FloatArray,
) -> tuple[FloatArray, NDArray[np.int64], NDArray[np.int64]]:
    """:func:`_best_linear_fits` of the valve of each row of ``params``.

    ``approaches`` holds each row's last lead-in sample and ``valve_run``
    the last four arguments of :func:`_valve_cumsum`.  Returns arrays of
    shape ``(candidates, targets)``.
    """
    shape = (params.shape[0], targets.shape[0])
    sse = np.empty(shape)
    pole = np.empty(shape, dtype=np.int64)
    delay = np.empty(shape, dtype=np.int64)
    valve_input, first_turn, op0, dt = valve_run
    for c in range(shape[0]):
        cm = _valve_cumsum(
            code, params[c], approaches[c], state, valve_input, first_turn, op0, dt
        )
        sse[c], pole[c], delay[c] = _best_linear_fits(
            cm, factor, targets, start, poles, limits, sign, fixed
        )
    return sse, pole, delay


# ----------------------------------------------------------------------------
# search

Score = tuple[float, int, int]
"""Output-error residual, pole index and raw MV delay of one candidate's best fit."""


@dataclass(frozen=True)
class _Window:
    """The analysed data and the linear-model grid (built by :meth:`build`).

    ``targets`` holds one detrended row per process type: PV for a
    self-regulating process, the PV increment per block for an integrating
    one (a process with an integrator is self-regulating from MV to the rate
    of change of PV, and fitting that rate keeps model errors from
    accumulating into a drift).  ``signals`` holds the same rows before
    detrending.
    """

    op: FloatArray
    op_blocks: FloatArray
    signals: FloatArray
    targets: FloatArray
    first: int
    start: int
    factor: int
    ts: float
    period_blocks: float
    poles: FloatArray
    max_block_delay: int
    s_max: float
    valve_input: FloatArray
    first_turn: int
    turn_travel: float
    gain_sign: float
    fixed_gains: FloatArray

    @classmethod
    def build(
        cls,
        op: FloatArray,
        pv: FloatArray,
        ts: float,
        period: float,
        samples_per_cycle: int,
        max_samples: int,
        max_delay_fraction: float,
        process_gain: float | None = None,
    ) -> _Window | None:
        """Average the most recent ``max_samples`` blocks of about a
        ``samples_per_cycle``-th of the period (``factor`` raw samples each); None when
        less than a period is left to score after the model valve's start.

        A ``process_gain`` fixes the gain of either target row: ``K`` of PV, ``K h``
        of the PV increment per block of ``h`` seconds (an integrating process).
        """
        factor = max(1, int(period // samples_per_cycle))
        n_blocks = min(op.size // factor, max_samples)
        first = op.size - n_blocks * factor
        op_w = np.ascontiguousarray(op[first:])
        op_blocks = op_w.reshape(n_blocks, factor).mean(axis=1)
        pv_blocks = pv[first:].reshape(n_blocks, factor).mean(axis=1)
        period_blocks = period / factor
        max_block_delay = max(1, int(max_delay_fraction * period_blocks))
        s_max = _op_travel_per_cycle(op_w, period)
        first_turn, direction = _first_turning_point(op_w, op_blocks, factor, period_blocks)
        # Score once the delayed model MV no longer reaches back before the start.
        start = max(math.ceil(period_blocks), first_turn // factor) + max_block_delay + 1
        if n_blocks - start < period_blocks:
            return None
        signals = np.array([pv_blocks[start:], pv_blocks[start:] - pv_blocks[start - 1 : -1]])
        # Steps of 2 s_max >= 2 S: every model moves at each and arrives moving; the
        # last lead-in sample is set per candidate (:meth:`_approaches`).
        lead_in = op_w[first_turn] - direction * s_max * np.array([6.0, 4.0, 2.0, 0.0])
        since = op_w[max(first_turn - round(period), 0) : first_turn + 1]
        turn_travel = float(np.ptp(since)) if since.size > 0.5 * period else s_max
        return cls(
            op=op_w,
            op_blocks=op_blocks,
            signals=signals,
            targets=np.array([_detrend_line(row) for row in signals]),
            first=first,
            start=start,
            factor=factor,
            ts=float(ts),
            period_blocks=period_blocks,
            poles=np.concatenate([[0.0], np.exp(-1.0 / (TAU_FRACTIONS * period_blocks))]),
            max_block_delay=max_block_delay,
            s_max=s_max,
            valve_input=np.concatenate([lead_in, op_w[first_turn:]]),
            first_turn=first_turn,
            turn_travel=turn_travel,
            gain_sign=_feedback_sign(op_w, pv[first:]),
            fixed_gains=np.array([math.nan, math.nan]) if process_gain is None
            else np.array([process_gain, process_gain * ts * factor]),
        )

    def evaluate(
        self,
        valve_model: str,
        candidates: Sequence[tuple[float, float]],
        rows: Sequence[int],
        limits: tuple[int, int, int, int],
    ) -> list[list[Score]]:
        """Scores of each ``(S, J)`` candidate for each target row in ``rows``."""
        if not candidates:
            return []
        code, params, state = self._valve_kernel_args(valve_model, candidates)
        sse, pole, delay = _score_candidates(
            code, params, self._approaches(candidates), state, self._valve_run(), self.factor,
            np.ascontiguousarray(self.targets[list(rows)]), self.start, self.poles,
            np.array(limits, dtype=np.int64), self.gain_sign,
            np.ascontiguousarray(self.fixed_gains[list(rows)]),
        )
        return [
            [(float(sse[c, t]), int(pole[c, t]), int(delay[c, t])) for t in range(len(rows))]
            for c in range(len(candidates))
        ]

    def score_healthy_valve(self, row: int) -> Score:
        """The healthy valve's (``S = J = 0``) best fit of target ``row`` over every pole and
        every raw delay.

        The grid search of the stiction candidates refines the delay at the best
        pole of whole-block delays only; over hundreds of candidates some land
        near their best, while the one healthy candidate may not, and stiction
        then seems to add R^2 it does not (a healthy valve of the demo's column,
        AIC-501, gained 0.022 against the threshold 0.02: 0.016 once its own fit
        was searched in full).  It is one candidate, so it is fitted in full.
        """
        code, params, state = self._valve_kernel_args("kano", [(0.0, 0.0)])
        cm = _valve_cumsum(code, params[0], float(self._approaches([(0.0, 0.0)])[0]), state,
                           *self._valve_run())
        sse, pole, delay = _every_linear_fit(
            cm, self.factor, np.ascontiguousarray(self.targets[row]), self.start, self.poles,
            1 + self.max_block_delay * self.factor, self.gain_sign, float(self.fixed_gains[row]))
        return float(sse), int(pole), int(delay)

    def valve_cumsum(self, valve_model: str, S: float, J: float) -> FloatArray:
        """Cumulative sum (leading 0) of the model MV, relative to the first OP sample.

        The valve starts at the first OP turning point, brought there by a
        lead-in (see :func:`_first_turning_point`); before it MV is held
        (those samples are not scored).
        """
        code, params, state = self._valve_kernel_args(valve_model, [(S, J)])
        approach = float(self._approaches([(S, J)])[0])
        return _valve_cumsum(code, params[0], approach, state, *self._valve_run())

    def _approaches(self, candidates: Sequence[tuple[float, float]]) -> FloatArray:
        """The last lead-in sample of each ``(S, J)``: where the valve last slipped.

        A valve that sticks and slips does not forget where it stands: He's
        model has no other state than its position, and a model valve started
        a little off slips a sample or two off at every reversal for as long
        as it runs (a wrong start cost FV-105 of the demo R^2 0.99 -> 0.13).
        In a limit cycle a He valve slips ``S`` of OP travel after its
        previous slip (``fs`` to overcome, ``fd`` already behind it), and OP
        goes on by the loop's reaction before it turns, on both sides alike:
        the travel into the turn is ``S + 2 delta``, and the valve slipped
        ``delta = (travel - S) / 2`` before the turn (at most ``J``: the
        valve would slip again).  Kano's valve, moving into the turn, follows
        OP whatever the approach.
        """
        turn = self.valve_input[LEAD_IN]
        direction = math.copysign(1.0, turn - self.valve_input[0])
        delta = [min(max(0.5 * (self.turn_travel - S), 0.0), J) for S, J in candidates]
        return np.asarray(turn - direction * np.asarray(delta), dtype=np.float64)

    def _valve_kernel_args(
        self, valve_model: str, candidates: Sequence[tuple[float, float]]
    ) -> tuple[int, FloatArray, FloatArray]:
        """Model code, parameter rows and initial state for the compiled valve kernels.

        The candidates are checked at once as a model checks its own (S, J)
        (finite, ``0 <= J <= S``): one model is built, of the first invalid
        candidate if any, so that it raises the model's own error.  The rows
        are the models' :meth:`~analytics.valves.ValveModel.params_array`:
        ``(S, J)``, or He's ``(fs, fd)`` (thesis Eq. 1.2, as
        :func:`~analytics.valves.sj_to_fsfd`).  Building a model per
        candidate cost a tenth of the search.  The kernels check nothing
        (the valve input is finite, as ``quantify_stiction`` checked OP).
        """
        sj = np.array(candidates, dtype=np.float64).reshape(-1, 2)
        S, J = sj[:, 0], sj[:, 1]
        valid = np.isfinite(sj).all(axis=1) & (J >= 0.0) & (J <= S)
        model = VALVE_MODELS[valve_model](*candidates[int(np.argmin(valid))])
        params = np.column_stack(((S + J) / 2.0, (S - J) / 2.0)) if model.code == HE else sj
        return model.code, params, model.initial_state(float(self.valve_input[0]))

    def _valve_run(self) -> tuple[FloatArray, int, float, float]:
        """Valve input, first turning point, first OP sample, ts: see :func:`_valve_cumsum`."""
        return self.valve_input, self.first_turn, float(self.op[0]), self.ts


def _detrend_line(y: FloatArray) -> FloatArray:
    t = np.arange(y.size, dtype=np.float64)
    slope, intercept = np.polyfit(t, y, 1)
    return np.asarray(y - (slope * t + intercept), dtype=np.float64)


def _op_travel_per_cycle(op: FloatArray, period: float) -> float:
    """Median peak-to-peak OP over the cycles, after removing a one-period moving average."""
    p = max(round(period), 2)
    csum = np.concatenate([[0.0], np.cumsum(op)])
    moving = (csum[p:] - csum[:-p]) / p
    fast = op[p // 2 : p // 2 + moving.size] - moving
    n_cycles = fast.size // p
    if n_cycles == 0:
        return float(np.ptp(op))
    return float(np.median(np.ptp(fast[: n_cycles * p].reshape(n_cycles, p), axis=1)))


def _feedback_sign(op: FloatArray, pv: FloatArray, min_correlation: float = 0.2) -> float:
    """Sign the process gain must have for negative feedback, or 0 when unclear.

    OP at a sample is computed from PV at the same sample, while the valve
    acts on PV one sample later at the earliest, so the same-sample
    correlation of the increments of OP and PV is the controller's
    proportional action: negative for a reverse-acting controller, which
    needs a positive process gain.  Without this constraint the inverse of
    the controller (PV proportional to minus OP, through a healthy valve)
    fits a loop whose PV is smooth almost as well as the process does.
    """
    d_op, d_pv = np.diff(op), np.diff(pv)
    norm = math.sqrt(float(np.dot(d_op, d_op)) * float(np.dot(d_pv, d_pv)))
    correlation = float(np.dot(d_op, d_pv)) / norm if norm > 0 else 0.0
    return -float(np.sign(correlation)) if abs(correlation) >= min_correlation else 0.0


def _first_turning_point(
    op: FloatArray, op_blocks: FloatArray, factor: int, period_blocks: float
) -> tuple[int, float]:
    """Index of the OP extreme where the model valve starts, and its kind (+1 max, -1 min).

    The valve's state at the first sample is unknown, and with OP swinging
    barely more than the stick band (as in a limit cycle) a model valve
    started in the wrong place stays stuck, or out of step, for many cycles:
    started at the first OP sample, halfway through its band, it never moves
    if OP swings less than the band about that point.  At a turning point of
    a limit cycle the state is known: the valve has followed OP (or slipped
    just before the turn) and rests on the trailing edge of its band.  Of the
    extremes of the band-passed block means in the first three periods (with
    a quarter period on either side), the least pronounced is taken, so that
    an unusually large swing (a start-up transient) does not leave the model
    valve beyond the reach of the later ones; it is then located on the
    samples of ``op`` within that reach.
    """
    smooth = bandpass(op_blocks, period_blocks)
    slope = np.sign(np.diff(smooth))
    reach = max(1, round(0.25 * period_blocks))
    turns = np.flatnonzero(slope[1:] * slope[:-1] < 0) + 1
    turns = turns[(turns >= reach) & (turns < op_blocks.size - reach)]
    if turns.size == 0:
        return 0, 1.0
    turns = turns[turns < turns[0] + 3.0 * period_blocks]
    turn = int(turns[np.argmin(np.abs(smooth[turns]))])
    kind = -float(slope[turn])  # +1 where the slope turns from rising to falling
    lo = (turn - reach) * factor
    return lo + int(np.argmax(kind * op[lo : (turn + reach + 1) * factor])), kind


def _coarse_grid(s_max: float, n_s: int, n_j: int) -> list[tuple[float, float]]:
    """``(0, 0)`` and ``n_s`` values of S, each with ``n_j`` values of J/S (cell centres).

    In a stiction limit cycle OP reverses soon after the valve slips, so S is
    usually a large fraction of the OP travel per cycle ``s_max``, and the
    optimum there is narrow; the S values are spaced evenly in
    ``log(s_max - S)``, from ``0.003 s_max`` to ``0.8 s_max`` below the bound.
    """
    grid = [(0.0, 0.0)]
    ratios = (np.arange(n_j) + 0.5) / n_j
    for margin in np.geomspace(0.8, 0.003, n_s):
        S = s_max * (1.0 - float(margin))
        grid.extend((S, S * float(f)) for f in ratios)
    return grid


def _neighbour_limits(window: _Window, pole: int, delay: int) -> tuple[int, int, int, int]:
    """The linear-model grid narrowed to the neighbours of a pole and a raw delay's block."""
    block = (delay - 1) // window.factor
    return (
        max(pole - 1, 0),
        min(pole + 1, window.poles.size - 1),
        max(block - 1, 0),
        min(block + 1, window.max_block_delay),
    )


def _score_into(
    table: dict[tuple[float, float], Score],
    window: _Window,
    valve_model: str,
    row: int,
    candidates: Sequence[tuple[float, float]],
    limits: tuple[int, int, int, int],
) -> None:
    """Score ``candidates`` on target ``row`` within ``limits`` into ``table``."""
    scores = window.evaluate(valve_model, candidates, [row], limits)
    table.update((c, s[0]) for c, s in zip(candidates, scores, strict=True))


def _refine(
    window: _Window,
    valve_model: str,
    row: int,
    table: dict[tuple[float, float], Score],
    point: tuple[float, float],
    step: float,
    rounds: int,
) -> None:
    """Pattern search in (S, J) from ``point``: 3 x 3 steps, halving the step each round.

    Scores go into ``table``; the linear-model grid is narrowed to the
    neighbours of the current point's pole and delay block.
    """
    for _ in range(rounds):
        S, J = point
        _, pole, delay = table[point]
        around: list[tuple[float, float]] = []
        for i in (-1, 0, 1):
            for j in (-1, 0, 1):
                s_new = min(max(S + i * step, 0.0), window.s_max)
                candidate = (s_new, min(max(J + j * step, 0.0), s_new))
                if candidate not in table and candidate not in around:
                    around.append(candidate)
        _score_into(table, window, valve_model, row, around, _neighbour_limits(window, pole, delay))
        point = min([point, *around], key=lambda c: table[c][0])
        step /= 2.0


def _line_search_j(
    window: _Window,
    valve_model: str,
    row: int,
    table: dict[tuple[float, float], Score],
    point: tuple[float, float],
    points: int,
    rounds: int,
) -> tuple[float, float]:
    """Search J alone at the S of ``point``: ``points`` values over ``0..S``, then
    ``rounds`` steps of half the spacing, halving, about the best; the best point.

    In a limit cycle S sets when the valve slips (the OP travel from one
    slip or reversal to the next) and J how far: at the right S the output
    error is smooth in J, while the (S, J) surface is rough across S.  So J
    is found in one dimension, as the slip's size read from PV.  Scores go
    into ``table``; the linear-model grid is narrowed to the neighbours of
    the pole and delay of ``point``.
    """
    S = point[0]
    if S <= 0.0:
        return point
    limits = _neighbour_limits(window, *table[point][1:])

    def score(values: Sequence[float]) -> None:
        new = [(S, J) for J in values if (S, J) not in table]
        _score_into(table, window, valve_model, row, new, limits)

    def best() -> tuple[float, float]:
        return min((c for c in table if c[0] == S), key=lambda c: table[c][0])

    score([float(J) for J in np.linspace(0.0, S, points)])
    step = 0.5 * S / max(points - 1, 1)
    for _ in range(rounds):
        J = best()[1]
        score([min(max(J + sign * step, 0.0), S) for sign in (-1.0, 1.0)])
        step /= 2.0
    return best()


def _basins(
    coarse: Sequence[tuple[float, float]], table: dict[tuple[float, float], Score], starts: int
) -> list[tuple[tuple[float, float], float]]:
    """The ``starts`` best local minima of the coarse scan along S, each with the gap to
    its nearest neighbour in S.

    The output error is rough across S (a model valve that slips a sample
    early or late at one reversal stays out of step for a while), so its
    best coarse points often sit in one basin; refining distinct local
    minima instead keeps the other basins in the race.
    """
    by_s: dict[float, tuple[float, float]] = {}
    for c in coarse:
        if c[0] not in by_s or table[c][0] < table[by_s[c[0]]][0]:
            by_s[c[0]] = c
    values = sorted(by_s)
    cost = [table[by_s[v]][0] for v in values]
    found = []
    for i, v in enumerate(values):
        left = cost[i - 1] if i > 0 else math.inf
        right = cost[i + 1] if i + 1 < len(values) else math.inf
        if v > 0.0 and cost[i] <= min(left, right):
            gaps = [abs(values[k] - v) for k in (i - 1, i + 1) if 0 <= k < len(values)]
            found.append((by_s[v], min(gaps)))
    found.sort(key=lambda item: table[item[0]][0])
    return found[:starts]


def _effective_samples(residual: FloatArray) -> float:
    """Independent samples a correlated residual is worth: ``m / tau``, ``tau = 1 + 2 sum
    rho_k`` over the autocorrelations up to the first that is not positive (Geyer's
    initial positive sequence, [7]_); at least 2."""
    m = residual.size
    if m < 2:
        return float(m)
    rho = autocorrelation(residual, m - 1)  # 0 throughout for a constant residual
    stop = np.flatnonzero(rho[1:] <= 0)
    k = int(stop[0]) + 1 if stop.size else m
    tau = 1.0 + 2.0 * float(np.sum(rho[1:k]))
    return max(m / tau, 2.0)


def _profile_intervals(
    table: dict[tuple[float, float], Score], n_eff: float, level: float, s_max: float
) -> tuple[tuple[float, float], tuple[float, float]]:
    """Likelihood-ratio intervals of S and J from every candidate the search scored.

    With Gaussian residuals of unknown variance, the profile likelihood of a
    candidate against the best is ``(SSE / SSE_min)^(-n/2)``, and the
    candidates with ``n ln(SSE / SSE_min) <= chi2_1(level)`` form the
    interval of either parameter (Wilks; Bates & Watts 1988 [6]_, Sec.
    6.1).  The residual of a limit cycle is correlated, so ``n`` is the
    effective number of independent samples (:func:`_effective_samples`).
    The interval of S is the span of S over those candidates, that of J the
    span of J: the candidates sample the coarse scan along S, the
    refinements and the line search along J at the best S (the profile in
    J), so an S or J that fits about as well anywhere in the search widens
    its interval.  Each interval is then widened on either side by the
    search's model error, :data:`MODEL_ERROR` times ``s_max``.
    """
    best = min(s[0] for s in table.values())
    limit = best * math.exp(float(chi2.ppf(level, 1)) / n_eff)
    inside = np.array([c for c, s in table.items() if s[0] <= limit])
    intervals = []
    for column in (0, 1):
        lo, hi = float(inside[:, column].min()), float(inside[:, column].max())
        margin = MODEL_ERROR[column] * s_max
        intervals.append((max(lo - margin, 0.0), hi + margin))
    return intervals[0], intervals[1]


def _final_fit(
    window: _Window, cm: FloatArray, row: int, pole: int, delay: int
) -> tuple[float, float, FloatArray]:
    """Refine the lag continuously at the best delay: pole, gain and the fitted target."""
    n_blocks = window.start + window.targets.shape[1]
    target = window.targets[row]
    fixed = float(window.fixed_gains[row])

    def residual(a: float) -> float:
        return float(_fit_at_delay(cm, window.factor, delay, a, target, window.start,
                                   window.gain_sign, fixed)[0])

    a = float(window.poles[pole])
    lo = float(window.poles[max(pole - 1, 0)])
    hi = float(window.poles[min(pole + 1, window.poles.size - 1)])
    found = minimize_scalar(residual, bounds=(lo, hi), method="bounded", options={"xatol": 1e-4})
    if float(found.fun) < residual(a):
        a = float(found.x)
    u = _delayed_block_means(cm, window.factor, delay, n_blocks)
    x = _lags(u, window.factor, np.array([a]))[window.start :, 0]
    m = x.size
    line = np.column_stack([np.ones(m), np.arange(m, dtype=np.float64)])
    if not math.isnan(fixed):  # the gain is given: only the offset and ramp are fitted
        coef = np.linalg.lstsq(line, target - fixed * x, rcond=None)[0]
        return a, fixed, np.asarray(line @ coef + fixed * x, dtype=np.float64)
    regressors = np.column_stack([line, x])
    coef = np.linalg.lstsq(regressors, target, rcond=None)[0]
    return a, float(coef[2]), np.asarray(regressors @ coef, dtype=np.float64)


def _gain_profile(
    window: _Window,
    valve_model: str,
    row: int,
    point: tuple[float, float],
    gain: float,
    limit: float,
    limits: tuple[int, int, int, int],
    j_search: tuple[int, int] = (5, 2),
) -> list[tuple[float, float]]:
    """``(factor, J)`` of each gain factor of :data:`GAIN_PROFILE` at which a J fits the
    window within ``limit`` (an output-error residual).

    The row's gain is fixed at ``factor * gain`` and J is searched alone at
    the S of ``point`` (:func:`_line_search_j` with ``j_search``, from
    ``J / factor``, the J that keeps ``K J``), on the linear-model grid
    ``limits``.  In a stiction limit cycle the valve slips once per
    OP reversal and then follows OP only for the little OP travel past S:
    MV is nearly a square wave of height J, and the PV step of a slip is
    ``K J``.  J is then told from K only by that little travel and by the
    shape of the fitted linear model; where the process is not of that
    shape (a loop of a unit, whose neighbours answer its slips), a doubled
    gain with half the slip fits as well (the demo's FV-502: K -0.72, J
    4.18 and K -1.44, J 1.9 in one window).
    """
    S = point[0]
    found = []
    for factor in GAIN_PROFILE:
        fixed = window.fixed_gains.copy()
        fixed[row] = factor * gain
        scaled = dataclasses.replace(window, fixed_gains=fixed)
        table: dict[tuple[float, float], Score] = {}
        start = (S, min(point[1] / factor, S))
        _score_into(table, scaled, valve_model, row, [start], limits)
        best = _line_search_j(scaled, valve_model, row, table, start, *j_search)
        if table[best][0] <= limit:
            found.append((factor, best[1]))
    return found


def _not_quantified(reason: str, period_s: float | None) -> StictionEstimate:
    return StictionEstimate(
        None, None, None, None, None, None, None, None, period_s, False, False, (reason,)
    )


def quantify_stiction(
    op: ArrayLike,
    pv: ArrayLike,
    ts: float,
    *,
    process_type: ProcessType | None = None,
    process_gain: float | None = None,
    period_s: float | None = None,
    valve_models: Sequence[str] = ("he", "kano"),
    samples_per_cycle: int = 25,
    max_samples: int = 1000,
    max_delay_fraction: float = 0.5,
    grid: tuple[int, int] = (72, 1),
    starts: int = 3,
    refine_rounds: int = 3,
    j_search: tuple[int, int] = (9, 3),
    min_cycles: float = 3.0,
    min_fit_r2: float = MIN_FIT_R2,
    min_stick_band: float = 0.1,
    min_r2_gain: float = MIN_R2_GAIN,
    near_optimal_tolerance: float = 0.05,
    seeds: Sequence[tuple[str, float, float]] = (),
) -> StictionEstimate:
    """Estimate valve stiction (S, J) of one loop by Hammerstein identification.

    Parameters
    ----------
    op, pv : array_like
        Controller output (% of span) and process variable, equally long.
    ts : float
        Sampling interval, s.
    process_type : {"self-regulating", "integrating"} or None
        Structure of the linear part; None fits both and keeps the larger R^2.
    process_gain : float, optional
        The process gain from MV (% of travel) to PV, known independently of
        these data (a step test, a configured process model): fitted as given,
        so that J is the slip whose PV step the data show through that gain.
        Needs ``process_type`` (for an integrating process, the gain of PV's
        rate of change, per second).  Without it the gain is fitted, and J is
        profiled over it (:func:`_gain_profile`, ``J_product_only``).
    period_s : float, optional
        Oscillation period; detected with
        :func:`analytics.oscillation.detect_loop_oscillation` when omitted.
    valve_models : sequence of str
        Stiction models tried (keys of :data:`VALVE_MODELS`); each is refined
        and the better fit is reported.
    samples_per_cycle : int, optional
        Raw samples are averaged in blocks to about this many per period.
    max_samples : int, optional
        At most this many blocks are fitted (the most recent ones).
    max_delay_fraction : float, optional
        Longest dead time searched, as a fraction of the period.
    grid : (int, int), optional
        Coarse scan: ``grid[0]`` values of S below the OP travel per cycle
        (the bound of the search space, thesis Appendix A step 2), dense
        near it, each with ``grid[1]`` values of ``J / S`` (see
        :func:`_coarse_grid`).
    starts : int, optional
        Local minima of the coarse scan along S (distinct basins, see
        :func:`_basins`) refined for each valve model.
    refine_rounds : int, optional
        3 x 3 pattern steps from each start, the first half the gap to the
        nearest coarse S, each halving the step.
    j_search : (int, int), optional
        Values of J over ``0..S`` and halving steps of the line search in J
        at each start's S, before its pattern steps (:func:`_line_search_j`).
    min_cycles : float, optional
        Fewest oscillation cycles the window must hold.
    min_fit_r2 : float, optional
        Output-error R^2 below which the fit is flagged as poor.
    min_stick_band : float, optional
        ``S`` below this fraction of the OP travel per cycle is no stiction.
    min_r2_gain : float, optional
        Fraction of the variance the stiction model must explain beyond the
        healthy-valve fit (``fit_r2 - search.r2_ideal_valve``) to count as
        stiction.
    near_optimal_tolerance : float, optional
        Candidates within this relative excess residual of the best define
        ``search.s_range`` and ``search.j_range``.
    seeds : sequence of (str, float, float), optional
        Further starts ``(valve model, S, J)``, refined like the basins of
        the coarse scan (:func:`quantify_with_gain` starts from the estimate
        with the gain fitted).

    Returns
    -------
    StictionEstimate
        With ``S = J = None`` when the loop does not oscillate, holds fewer
        than ``min_cycles`` cycles, or OP does not move.

    Raises
    ------
    DataError
        If the signals are not 1-D, differ in length or hold NaN/inf, ``ts``
        is not positive, or ``process_type`` or ``valve_models`` is unknown.

    Notes
    -----
    Identifiability.  S shows in the OP travel between an OP reversal and the
    PV reversal, J in the size of the PV step after each reversal.  A slip
    jump that moves PV less than its noise over a few samples cannot be told
    from ``J = 0``, and a process lag much longer than the period filters the
    jump away: ``search.j_range`` then spans much of ``0..S`` and the estimate
    is flagged.  A limit cycle needs OP to cross the whole stick band, so the
    S search ends at the OP travel per cycle; an S at that bound means the
    model valve hardly moves and the data do not support the model.  The
    healthy valve (S = 0) is one of the candidates, and a linear loop fits it
    as well as any stiction model.

    References
    ----------
    Jelali (2008); Lee, Ren & Huang (2008), thesis ref. [28] and Appendix A;
    Choudhury, Jain & Shah (2008); He et al. (2007) and Kano et al. (2004) for
    the valve models; thesis Eq. 1.2 for ``fs = (S + J) / 2``,
    ``fd = (S - J) / 2``.  See the module docstring.

    Examples
    --------
    A level loop (integrating process) with a Kano valve of S = 3, J = 1:

    >>> from analytics.scenarios import level_loop
    >>> res = level_loop().run()
    >>> est = quantify_stiction(res.op[0], res.pv[0], res.dt, process_type="integrating")
    >>> round(est.S, 1), est.stiction_found, est.model.integrating
    (3.0, True, True)
    >>> est.fs == (est.S + est.J) / 2
    True
    """
    op_a = np.ascontiguousarray(op, dtype=np.float64)
    pv_a = np.ascontiguousarray(pv, dtype=np.float64)
    if op_a.ndim != 1 or op_a.shape != pv_a.shape:
        raise DataError(
            f"op and pv must be 1-D and equally long, got shapes {op_a.shape} and {pv_a.shape}"
        )
    if not (math.isfinite(ts) and ts > 0):
        raise DataError(f"sampling time ts must be positive and finite, got {ts!r}")
    if not (np.all(np.isfinite(op_a)) and np.all(np.isfinite(pv_a))):
        raise DataError("op and pv must be finite; screen them with analytics.quality")
    if process_type not in (None, "self-regulating", "integrating"):
        raise DataError(
            f"process_type must be 'self-regulating', 'integrating' or None, got {process_type!r}"
        )
    if process_gain is not None and (
            process_type is None or not (math.isfinite(process_gain) and process_gain != 0)):
        raise DataError("process_gain must be finite and not 0, and needs process_type, got "
                        f"{process_gain!r} with process_type {process_type!r}")
    unknown = [m for m in valve_models if m not in VALVE_MODELS]
    if unknown or not valve_models:
        raise DataError(f"valve_models must be among {sorted(VALVE_MODELS)}, got {valve_models}")

    if period_s is None:
        period_s = detect_loop_oscillation(op_a, pv_a, ts).period_s
        if period_s is None:
            return _not_quantified("the loop does not oscillate", None)
    period = period_s / ts
    if op_a.size < min_cycles * period:
        return _not_quantified(
            f"only {op_a.size / period:.1f} oscillation cycles in the window "
            f"(need {min_cycles:g})",
            period_s,
        )

    window = _Window.build(
        op_a, pv_a, ts, period, samples_per_cycle, max_samples, max_delay_fraction,
        process_gain,
    )
    if window is None:
        return _not_quantified(
            f"OP turns too late in the window ({op_a.size / period:.1f} cycles) to replay "
            "a valve model over a whole cycle", period_s,
        )
    s_max = window.s_max
    if not s_max > 0:
        return _not_quantified("OP does not move", period_s)
    signals = window.signals
    sst = np.sum((signals - signals.mean(axis=1, keepdims=True)) ** 2, axis=1)
    sst = np.where(sst > 0, sst, np.inf)

    rows = [0, 1] if process_type is None else [int(process_type == "integrating")]
    coarse = _coarse_grid(s_max, *grid)
    full = (0, window.poles.size - 1, 0, window.max_block_delay)
    tables: dict[tuple[str, int], dict[tuple[float, float], Score]] = {}
    for valve_model in valve_models:
        scores = window.evaluate(valve_model, coarse, rows, full)
        for t, row in enumerate(rows):
            tables[valve_model, row] = {c: s[t] for c, s in zip(coarse, scores, strict=True)}
    for row in rows:
        healthy = window.score_healthy_valve(row)
        for valve_model in valve_models:
            if healthy[0] < tables[valve_model, row][0.0, 0.0][0]:
                tables[valve_model, row][0.0, 0.0] = healthy

    def unexplained(key: tuple[str, int]) -> float:
        return min(s[0] for s in tables[key].values()) / float(sst[key[1]])

    # Refine the better process type of each valve model from its best coarse
    # points (the surface is rough: a model valve that misses one reversal
    # stays out of step), then keep the better model.
    chosen = [min((k for k in tables if k[0] == v), key=unexplained) for v in valve_models]
    for valve_model, row in chosen:
        table = tables[valve_model, row]
        points = _basins(coarse, table, starts)
        for model_name, seed_S, seed_J in seeds:
            if model_name == valve_model and seed_S > 0.0:
                point = (min(seed_S, s_max), min(seed_J, seed_S, s_max))
                _score_into(table, window, valve_model, row, [point], full)
                points.append((point, min(abs(c[0] - point[0]) for c in coarse if c[0] > 0.0)))
        for point, gap in points:
            point = _line_search_j(window, valve_model, row, table, point, *j_search)
            _refine(window, valve_model, row, table, point, 0.5 * gap, refine_rounds)
    valve_model, row = min(chosen, key=unexplained)
    table = tables[valve_model, row]
    (S, J), (sse, pole, delay) = min(table.items(), key=lambda item: item[1][0])
    cm = window.valve_cumsum(valve_model, S, J)
    a, gain, fitted_detrended = _final_fit(window, cm, row, pole, delay)
    n_eff = _effective_samples(window.targets[row] - fitted_detrended)
    S_interval, J_interval = _profile_intervals(table, n_eff, INTERVAL_LEVEL, s_max)
    target = signals[row]
    fitted = target - (window.targets[row] - fitted_detrended)
    sse_final = float(np.sum((target - fitted) ** 2))
    fit_r2 = 1.0 - sse_final / float(sst[row])
    sse_ideal = table[0.0, 0.0][0]
    h = ts * window.factor
    integrating = row == 1
    model = FirstOrderProcess(
        kind=INTEGRATING if integrating else SELF_REGULATING,
        K=gain / h if integrating else gain,
        tau=0.0 if a <= 0.0 else -h / math.log(a),
        theta=(delay - 1) * ts,
    )

    near = [c for c, s in table.items() if s[0] <= sse * (1.0 + near_optimal_tolerance)]
    start, n_blocks = window.start, window.op_blocks.size
    mv_b = _delayed_block_means(cm, window.factor, 0, n_blocks)[start:] + window.op[0]
    op_b = window.op_blocks[start:]
    op_travel = float(np.ptp(op_b))
    mv_travel = float(np.ptp(mv_b)) / op_travel if op_travel > 0 else 0.0
    search = SearchSummary(
        valve_model=valve_model,
        s_max=s_max,
        evaluations=sum(len(t) for t in tables.values()) // len(rows),
        s_range=(min(c[0] for c in near), max(c[0] for c in near)),
        j_range=(min(c[1] for c in near), max(c[1] for c in near)),
        r2_ideal_valve=1.0 - sse_ideal / float(sst[row]),
        samples_per_cycle=window.period_blocks,
        downsample_factor=window.factor,
        cycles=n_blocks / window.period_blocks,
        mv_travel_fraction=mv_travel,
    )
    t_s = np.asarray((window.first + (np.arange(start, n_blocks) + 0.5) * window.factor) * ts)
    trace = FitTrace(t_s, op_b, mv_b, target, fitted, "pv_increment" if integrating else "pv")

    stiction_found = bool(
        min_stick_band * s_max <= S and fit_r2 - search.r2_ideal_valve >= min_r2_gain
    )
    J_interval_lo, J_interval_hi = J_interval
    profile = [] if process_gain is not None or not (stiction_found and J > 0.0) else (
        _gain_profile(window, valve_model, row, (S, J), gain,
                      sse * (1.0 + near_optimal_tolerance), _neighbour_limits(window, pole, delay)))
    if profile:
        margin = MODEL_ERROR[1] * s_max
        J_interval = (max(min(J_interval_lo, min(j for _, j in profile) - margin), 0.0),
                      max(J_interval_hi, max(j for _, j in profile) + margin))

    issues = []
    if fit_r2 < min_fit_r2:
        issues.append(f"poor fit: output-error R^2 {fit_r2:.2f} < {min_fit_r2:g}")
    if s_max <= S:
        issues.append(f"S = {S:.3g} lies at the search bound (OP travel per cycle {s_max:.3g})")
    if mv_travel < 0.05:
        issues.append(f"the model valve hardly moves (MV travel {mv_travel:.1%} of OP travel)")
    if S > 0 and search.j_range[1] - search.j_range[0] > 0.5 * S:
        issues.append(
            f"J is poorly determined: {search.j_range[0]:.3g} to {search.j_range[1]:.3g} "
            "fit almost equally well"
        )
    if profile:
        alternatives = ", ".join(f"K {f * model.K:.3g} with J {j:.3g}" for f, j in profile)
        issues.append(
            f"J is not told from the process gain: K J = {model.K * J:.3g} is pinned, but "
            f"{alternatives} fit almost as well as K {model.K:.3g} with J {J:.3g}; a "
            "process gain known from elsewhere (a step test) fixes J"
        )
    fs, fd = sj_to_fsfd(S, J)
    return StictionEstimate(
        S=S,
        J=J,
        fs=fs,
        fd=fd,
        fit_r2=fit_r2,
        model=model,
        search=search,
        trace=trace,
        period_s=period_s,
        stiction_found=stiction_found,
        trustworthy=not issues,
        issues=tuple(issues),
        S_interval=S_interval,
        J_interval=J_interval,
        gain_given=process_gain is not None,
        J_product_only=bool(profile),
    )


def quantify_with_gain(
    fitted: StictionEstimate,
    op: ArrayLike,
    pv: ArrayLike,
    ts: float,
    *,
    process_type: ProcessType,
    process_gain: float,
    max_r2_loss: float = GIVEN_GAIN_R2_LOSS,
) -> StictionEstimate:
    """The estimate of S and J with a process gain known from elsewhere, given the one
    with the gain fitted (:func:`quantify_stiction` on the same window).

    A stiction limit cycle pins the PV step of a slip, ``K J``, better than J
    (see :func:`_gain_profile`): a gain from a step test or the plant's
    process model fixes J.  The window is fitted again with the gain fixed
    (``process_gain``, as :func:`quantify_stiction` takes it), from the
    coarse scan's basins and from ``fitted`` with J scaled to keep ``K J``;
    the fixed gain also decides between valve models that the fitted gain
    leaves open.  When that
    fit explains at least ``max_r2_loss`` less of PV than ``fitted`` (the
    window does not behave as the gain says: a cycle that has not settled, a
    neighbour's loop acting differently), S stays that of ``fitted`` and J
    becomes ``K J`` of ``fitted`` over the given gain (at most S), its
    interval scaled alike; an issue says so.  A gain of the sign opposite to
    the fitted one leaves ``fitted`` as it is, with an issue.

    Returns
    -------
    StictionEstimate
        With ``gain_given`` True when the gain was used; ``fitted`` when it has
        no estimate.

    Examples
    --------
    A flow loop (K = 1.2) with a He valve of S = 8, J = 4:

    >>> from analytics.synthetic_cases import synthetic_library
    >>> case = next(c for c in synthetic_library() if c.name == "flow-he-S8-J4-ts1")
    >>> run = case.simulate()
    >>> fitted = quantify_stiction(run.op[0], run.pv[0], case.ts,
    ...                            process_type="self-regulating")
    >>> given = quantify_with_gain(fitted, run.op[0], run.pv[0], case.ts,
    ...                            process_type="self-regulating", process_gain=1.2)
    >>> given.gain_given, given.model.K
    (True, 1.2)
    """
    if fitted.S is None or fitted.J is None or fitted.model is None or fitted.fit_r2 is None:
        return fitted
    K = fitted.model.K
    if K * process_gain <= 0.0:
        return dataclasses.replace(fitted, trustworthy=False, issues=(*fitted.issues, (
            f"the given process gain {process_gain:.3g} has the sign opposite to the one the "
            f"window fits ({K:.3g}): check the configured process model")))
    seed = (fitted.search.valve_model if fitted.search is not None else "he", fitted.S,
            fitted.J * K / process_gain)
    given = quantify_stiction(op, pv, ts, process_type=process_type,
                              process_gain=process_gain, period_s=fitted.period_s,
                              seeds=(seed,))
    if (given.S is not None and given.fit_r2 is not None
            and given.fit_r2 >= fitted.fit_r2 - max_r2_loss):
        return given
    scale = K / process_gain
    J = min(fitted.J * scale, fitted.S)
    J_interval = None if fitted.J_interval is None else (
        min(fitted.J_interval[0] * scale, J), max(fitted.J_interval[1] * scale, J))
    fs, fd = sj_to_fsfd(fitted.S, J)
    why = ("no estimate" if given.fit_r2 is None
           else f"R^2 {given.fit_r2:.2f} against {fitted.fit_r2:.2f} with the gain fitted")
    return dataclasses.replace(
        fitted, J=J, fs=fs, fd=fd, J_interval=J_interval, gain_given=True,
        model=dataclasses.replace(fitted.model, K=process_gain),
        J_product_only=False, trustworthy=False,
        issues=(*(i for i in fitted.issues if not i.startswith("J is not told")), (
            f"the given process gain {process_gain:.3g} fits this window worse ({why}): S "
            f"from the fitted model, J = K J / {process_gain:.3g} = "
            f"{fitted.model.K * fitted.J:.3g} / {process_gain:.3g}"
            + (", at most S" if J == fitted.S else ""))),
    )
