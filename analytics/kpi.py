"""Loop performance KPIs: the standard figures of control-loop performance tools.

One function per figure, each pure (arrays in, numbers out), each for
signals already in % of span:

* :func:`error_statistics` -- mean, standard deviation and IAE of the
  control error ``SP - PV``, and the share of time PV spent within its limits;
* :func:`harris_index` -- the minimum-variance (Harris) index with the
  Desborough-Harris normalisation, from the dead time in samples;
* :func:`identify_dead_time` -- that dead time, when none is configured, from
  the window's set-point steps or the operator's OP moves in manual;
* :func:`valve_travel_per_day` and :func:`reversals_per_day` -- OP travel
  beyond noise and its direction changes (the valve's wear);
* :func:`saturation` -- the share of time OP sat at its limits;
* :func:`setpoint_responses` -- overshoot, settling time and IAE of each
  set-point step in the window;
* :func:`service_factor` -- the share of time in normal mode (auto or
  cascade) from a mode signal;
* :func:`oscillation_index` -- from the oscillation detection's result.

:func:`loop_kpis` computes them all for one window into a :class:`LoopKpis`.

References
----------
.. [1] T. J. Harris, "Assessment of control loop performance", Can. J. Chem.
   Eng. 67 (1989) 856-861.
.. [2] L. Desborough and T. Harris, "Performance assessment measures for
   univariate feedback control", Can. J. Chem. Eng. 70 (1992) 1186-1197.
.. [3] M. Jelali, *Control Performance Management in Industrial Automation*,
   Springer 2013, ch. 2 (error statistics, IAE), ch. 3 (minimum-variance
   benchmark), ch. 7 (valve travel and reversals, saturation, service factor).
.. [4] K. J. Astrom and T. Hagglund, *Advanced PID Control*, ISA 2006, sec.
   4.2 (set-point response: overshoot, settling time with a 2 % band, IAE).
.. [5] N. F. Thornhill, B. Huang and H. Zhang, "Detection of multiple
   oscillations in control loops", J. Process Control 13 (2003) 91-100.
.. [6] S. Bjorklund and L. Ljung, "A review of time-delay estimation
   techniques", Proc. 42nd IEEE CDC (2003) 2502-2507, sec. 3 (the ARX
   method: the delay of the ARX model with the smallest loss).
.. [7] L. Ljung, *System Identification: Theory for the User*, 2nd ed.,
   Prentice Hall 1999, sec. 13.4 (direct identification in closed loop needs
   excitation beyond the feedback) and sec. 16.4 (the chi-square test of
   model structures).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import solve_toeplitz

from analytics.serial import Reader
from analytics.stiction.stick_jump import (
    moving_average,
    op_travel,
    robust_noise,
    travel_increments,
)
from analytics.types import FloatArray

__all__ = [
    "DeadTimeEstimate",
    "ErrorStatistics",
    "HarrisIndex",
    "LoopKpis",
    "ServiceFactor",
    "SetpointResponse",
    "error_statistics",
    "harris_index",
    "identify_dead_time",
    "longest_normal_stretch",
    "loop_health",
    "loop_kpis",
    "manual_samples",
    "oscillation_index",
    "reversals_per_day",
    "saturation",
    "service_factor",
    "setpoint_responses",
    "valve_travel_per_day",
]

Mode = Literal["auto", "cascade", "manual"]
DAY_S = 86400.0


@dataclass(frozen=True)
class ErrorStatistics:
    """Statistics of the control error ``e = SP - PV`` (% of span).

    Attributes
    ----------
    mean, std : float
        Mean and (population) standard deviation of ``e``.
    iae : float
        Integral of the absolute error, ``sum |e_k| ts`` (% s).
    within_limits : float or None
        Share (0..1) of samples whose PV lies within ``limits``; None without limits.
    """

    mean: float
    std: float
    iae: float
    within_limits: float | None


def error_statistics(sp: FloatArray, pv: FloatArray, ts: float,
                     limits: tuple[float, float] | None = None) -> ErrorStatistics:
    """Mean, standard deviation and IAE of ``SP - PV``, and time within PV limits.

    Samples where SP or PV is missing (NaN) are left out (Jelali 2013, sec. 2.1).

    Examples
    --------
    >>> s = error_statistics(np.array([50.0, 50, 50, 50]), np.array([49.0, 51, 49, 51]), 2.0,
    ...                      limits=(49.5, 60.0))
    >>> (s.mean, s.std, s.iae, s.within_limits)
    (0.0, 1.0, 8.0, 0.5)
    """
    e = np.asarray(sp, dtype=np.float64) - np.asarray(pv, dtype=np.float64)
    e = e[np.isfinite(e)]
    if e.size == 0:
        return ErrorStatistics(float("nan"), float("nan"), float("nan"), None)
    within = None
    if limits is not None:
        p = np.asarray(pv, dtype=np.float64)
        p = p[np.isfinite(p)]
        within = float(np.mean((p >= limits[0]) & (p <= limits[1]))) if p.size else None
    return ErrorStatistics(float(e.mean()), float(e.std()), float(np.abs(e).sum() * ts), within)


@dataclass(frozen=True)
class HarrisIndex:
    """The minimum-variance benchmark of one window.

    Attributes
    ----------
    mv_variance : float
        Estimated minimum achievable variance ``sigma_mv^2`` (``%^2``): the
        variance of the ``d``-step-ahead prediction error of the output.
    mse : float
        Mean square of the control error (variance plus squared mean).
    ratio : float
        ``sigma_mv^2 / mse``, the Harris index: 1 at minimum-variance control,
        towards 0 the further from it.
    normalised : float
        Desborough-Harris normalised index ``eta = 1 - ratio``: 0 at
        minimum variance, towards 1 for a poorly performing loop.
    dead_time : int
        The dead time ``d`` in samples used.
    """

    mv_variance: float
    mse: float
    ratio: float
    normalised: float
    dead_time: int


def harris_index(error: FloatArray, dead_time: int, order: int | None = None
                 ) -> HarrisIndex | None:
    """Minimum-variance (Harris) index with the Desborough-Harris normalisation.

    Under feedback the first ``d`` terms of the output's impulse response to
    the disturbance's white-noise source cannot be changed by any controller
    (``d`` the dead time in samples, counting the zero-order hold: a
    continuous dead time ``theta`` gives ``d = floor(theta / ts) + 1``).  So
    the minimum variance is the variance of the ``d``-step-ahead prediction
    error, which Desborough and Harris (1992, eq. 12-14) estimate by the
    least-squares regression of ``y_t`` on ``y_{t-d}, ..., y_{t-d-m+1}``
    (``y`` the mean-removed error).  Here the regression's normal equations
    are solved in their autocovariance (Yule-Walker, Toeplitz) form, with
    autocovariances over the pairs of present samples, so gaps cost nothing
    and the order can be high; the residual variance is corrected for the
    ``m`` fitted coefficients (``N / (N - m)``).  Their normalised index is
    ``eta = 1 - sigma_mv^2 / mse`` with the mean square error ``mse``
    (variance plus squared offset, which a minimum-variance controller would
    remove).

    ``order`` defaults to ``1.7 sqrt(N)`` (102 for an hour at 1 s), not the
    paper's 20-30: under integral action the closed loop's output has a zero
    near 1, its autoregressive form decays slowly, and a short model
    overestimates the ratio by 5-8 % (``tests/analytics/test_kpi.py``
    measures it); a much longer one underestimates it from the autocovariance
    estimates' own error.

    Returns None with fewer than ``10 m`` samples, or a constant error.

    References
    ----------
    Harris (1989); Desborough and Harris (1992), eq. 12-14 and 18.
    """
    if dead_time < 1:
        raise ValueError(f"dead_time must be at least one sample, got {dead_time}")
    e = np.asarray(error, dtype=np.float64)
    present = np.isfinite(e)
    count = int(present.sum())
    m = int(np.ceil(1.7 * np.sqrt(count))) if order is None else order
    if count < 10 * m or count < 2:
        return None
    mean = float(e[present].mean())
    y = np.where(present, e - mean, 0.0)
    lags = dead_time + m
    nfft = 1 << int(2 * e.size - 1).bit_length()
    spectrum = np.fft.rfft(y, nfft)
    mask = np.fft.rfft(present.astype(np.float64), nfft)
    products = np.fft.irfft(spectrum * np.conj(spectrum), nfft)[:lags]
    pairs = np.rint(np.fft.irfft(mask * np.conj(mask), nfft)[:lags])
    if np.any(pairs < 1):
        return None
    r = products / pairs  # autocovariance over the pairs of present samples
    if not r[0] > 0:
        return None
    alpha = solve_toeplitz(r[:m], r[dead_time:lags])
    # The residual variance of m fitted coefficients, corrected for the degrees of freedom.
    mv = max(float(r[0] - alpha @ r[dead_time:lags]), 0.0) * count / (count - m)
    mse = float(r[0] + mean**2)
    ratio = mv / mse
    return HarrisIndex(mv, mse, ratio, 1.0 - ratio, dead_time)


@dataclass(frozen=True)
class DeadTimeEstimate:
    """The dead time :func:`identify_dead_time` found in a window, or why it found none.

    Attributes
    ----------
    samples : int or None
        The dead time ``d`` in samples as :func:`harris_index` counts it (the
        hold's sample included); None when the window does not tell it.
    note : str
        What it was identified from (``"identified from set-point steps"``,
        ``"identified from the operator's OP moves in manual"``), or why not.
    """

    samples: int | None
    note: str


def _moves_beyond_noise(x: FloatArray, floor: float = 0.0) -> bool:
    """Whether ``x`` moves beyond its noise within any of its runs of present samples.

    A backlash of three noise standard deviations (:func:`robust_noise`, and
    no narrower than ``floor``) follows each run, as the valve travel counts
    OP's moves (:func:`analytics.stiction.stick_jump.travel_increments`).
    """
    present = np.isfinite(x)
    edges = np.diff(np.concatenate(([0], present.astype(np.int8), [0])))
    values = x[present]
    if values.size < 3:
        return False
    band = max(3.0 * robust_noise(values), floor)
    return any(travel_increments(x[start:stop], band).sum() > 0.0
               for start, stop in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1),
                                      strict=True) if stop - start > 1)


@njit(cache=True)
def _lagged_dot(a: FloatArray, b: FloatArray, lag_a: int, lag_b: int,
                starts: NDArray[np.int64], stops: NDArray[np.int64]) -> float:
    """``sum_t a_{t-lag_a} b_{t-lag_b}`` over the rows ``starts[s] <= t < stops[s]``."""
    total = 0.0
    for s in range(starts.size):
        lo, hi = starts[s], stops[s]
        total += np.dot(a[lo - lag_a:hi - lag_a], b[lo - lag_b:hi - lag_b])
    return total


@njit(cache=True)
def _lag_gram(y: FloatArray, u: FloatArray, na: int, start: int
              ) -> tuple[int, FloatArray]:
    """The rows and Gram matrix of the ARX delay scan's regressors (:func:`_arx_delay`).

    Rows are the samples ``t`` whose lags ``y_t .. y_{t-na}`` and
    ``u_t .. u_{t-start}`` are all present; columns the constant, then those
    lags, each centred on its mean over the rows (so the constant is
    orthogonal to them: ``gram[0, 0]`` is the number of rows, the rest of
    its row and column 0).

    Equal in exact arithmetic to stacking the centred lags into a matrix
    ``X`` and forming ``X.T @ X``, but in ``O(N (na + start))`` instead of
    ``O(N (na + start)^2)``: only the products with a column of lag 0 are
    summed over the rows; every other one follows along its diagonal, since
    over a run of rows ``lo <= t < hi``
    ``sum_t a_{t-i} b_{t-j} = sum_t a_{t-i+1} b_{t-j+1} + a_{lo-i} b_{lo-j}
    - a_{hi-i} b_{hi-j}`` (the sum shifted by one sample, plus the product
    entering at the run's start and minus the one leaving at its end; all of
    these samples are lags of the run's rows, so present).  The signals are
    offset by their first row's values before summing and the column means
    taken off at the end, ``G_qr = S_qr - s_q s_r / N``, so the products
    stay of the size of the signals' variation; a signal held over the rows
    gives exact zeros, hence a singular matrix, as the stacked lags would.
    """
    n = y.size
    if u.size != n:
        raise ValueError("y and u must have the same length")
    starts = np.empty(n, dtype=np.int64)
    stops = np.empty(n, dtype=np.int64)
    runs = 0
    run_y = run_u = 0
    inside = False
    for t in range(n):  # the runs of rows, from the lengths of the runs of present samples
        run_y = run_y + 1 if np.isfinite(y[t]) else 0
        run_u = run_u + 1 if np.isfinite(u[t]) else 0
        if t >= start and run_y > na and run_u > start:
            if not inside:
                starts[runs] = t
                inside = True
        elif inside:
            stops[runs] = t
            runs += 1
            inside = False
    if inside:
        stops[runs] = n
        runs += 1
    starts, stops = starts[:runs], stops[:runs]
    rows = int(np.sum(stops - starts))
    p = na + start + 2  # columns: y at lags 0 .. na, then u at lags 0 .. start
    gram = np.zeros((p + 1, p + 1))
    gram[0, 0] = rows
    if rows == 0:
        return 0, gram
    ys = y - y[starts[0]]
    us = u - u[starts[0]]
    lag = np.empty(p, dtype=np.int64)
    for q in range(p):
        lag[q] = q if q <= na else q - na - 1
    sums = np.empty(p)  # s_q: column sums over the rows
    products = np.empty((p, p))  # S_qr for q <= r
    for q in range(p):
        x = ys if q <= na else us
        i = lag[q]
        if i == 0:
            sums[q] = 0.0
            for s in range(runs):
                sums[q] += np.sum(x[starts[s]:stops[s]])
        else:
            sums[q] = sums[q - 1]
            for s in range(runs):
                sums[q] += x[starts[s] - i] - x[stops[s] - i]
        for r in range(q, p):
            z = ys if r <= na else us
            j = lag[r]
            if i == 0 or j == 0:
                products[q, r] = _lagged_dot(x, z, i, j, starts, stops)
            else:
                total = products[q - 1, r - 1]
                for s in range(runs):
                    total += (x[starts[s] - i] * z[starts[s] - j]
                              - x[stops[s] - i] * z[stops[s] - j])
                products[q, r] = total
    for q in range(p):
        for r in range(q, p):
            gram[q + 1, r + 1] = gram[r + 1, q + 1] = products[q, r] - sums[q] * sums[r] / rows
    return rows, gram


def _arx_delay(u: FloatArray, y: FloatArray, max_delay: int, na: int, nb: int,
               chi2: tuple[float, float]) -> tuple[int | None, str]:
    """The delay from ``u`` to ``y`` by an ARX delay scan, or None and why not.

    For each delay ``k = 0 .. max_delay`` the model
    ``y_t = c + sum_{i=1}^{na} a_i y_{t-i} + sum_{j=0}^{nb-1} b_j u_{t-k-j} + e_t``
    is fitted by least squares over the rows whose lags are all present
    (Bjorklund and Ljung 2003, sec. 3; all from one Gram matrix of the lagged
    signals, :func:`_lag_gram`, so a delay costs one small solve) and its
    loss ``V_k`` (residual mean square) compared by ``N ln(V_k / V_min)``,
    chi-square distributed when the delays fit alike (Ljung 1999, sec.
    16.4).  Delays shorter than
    the true one fit as well as it whenever their ``nb`` lags reach it, so the
    delay is the *longest* one whose loss is not significantly above the
    smallest (below ``chi2[1]``).  It stands only when the test tells it
    sharply: its own loss is within the tighter ``chi2[0]`` of the smallest
    (else the first samples of the response hide in the noise, and the onset
    may be a sample earlier), and no delay fits alike more than ``nb - 1``
    samples before it (those no longer reach it).  ``u`` must explain ``y``
    beyond ``y``'s own past by the test at ``chi2[1]``.  A delay of 0 (PV
    moving with ``u`` at the same sample, as no sampled process can) or of
    ``max_delay`` is no estimate.  A smallest loss under ``1e-10`` of ``y``'s
    variance is rounding error: ``y`` a noise-free function of the lags, and
    no noise to judge the fit by.
    """
    start = max(na, max_delay + nb - 1)
    if y.size - start < 10 * (1 + na + nb):
        return None, "too few samples"
    # Columns: 1, y_t, y_{t-1..t-na}, u_{t-0..t-start}; rows t whose lags are all present.
    rows, gram = _lag_gram(y, u, na, start)
    if rows < 10 * (1 + na + nb):
        return None, "too few complete samples"
    past = [0, *range(2, na + 2)]  # the constant and y's own past

    def losses_of(columns: NDArray[np.intp]) -> FloatArray:
        """Residual mean squares of the models of these columns (one row a model)."""
        r = gram[columns, 1]
        coef = np.linalg.solve(gram[columns[:, :, None], columns[:, None, :]], r[..., None])
        return np.maximum(gram[1, 1] - np.sum(coef[..., 0] * r, axis=1), 0.0) / rows

    models = np.array([past + list(range(na + 2 + k, na + 2 + k + nb))
                       for k in range(max_delay + 1)])
    try:
        losses = losses_of(models)
        own_past = float(losses_of(np.array([past]))[0])
    except np.linalg.LinAlgError:  # PV held, or its lags collinear with the input's
        return None, "PV or they do not vary enough to fit"
    best = float(losses.min())
    if not best > 1e-10 * gram[1, 1] / rows:
        return None, "PV follows them exactly: no noise to judge the fit by"
    if rows * np.log(own_past / best) < chi2[1]:
        return None, "they explain nothing of PV beyond PV's own past"
    excess = rows * np.log(losses / best)
    alike = np.flatnonzero(excess < chi2[1])
    d = int(alike[-1])
    if excess[d] >= chi2[0] or alike[0] < d - nb + 1:
        return None, (f"too weak to tell the delay: {alike[0]} to {alike[-1]} samples fit "
                      "alike")
    if d == 0:
        return None, "PV moves with them at the same sample, as no sampled process can"
    if d == max_delay:
        return None, f"the delay is {max_delay} samples or longer, beyond those searched"
    return d, ""


def identify_dead_time(op: FloatArray, pv: FloatArray, sp: FloatArray | None = None,
                       manual: NDArray[np.bool_] | None = None, *, max_delay: int = 30,
                       na: int = 4, nb: int = 4, chi2: tuple[float, float] = (9.49, 18.47),
                       pv_noise: float | None = None) -> DeadTimeEstimate:
    """The loop's dead time in samples, from the window's external excitation only.

    Under feedback alone OP is a function of past PV, and the data do not
    tell the delay in general (Ljung 1999, sec. 13.4: identifiability in
    closed loop needs a signal from outside the loop, a set-point change or
    a dither).  A dither cannot be told from the controller's own moves in
    OP, so the delay is identified only from what the window shows to come
    from outside:

    * the operator's OP moves in manual (``manual`` marks those samples): no
      feedback acts, and the delay from OP to PV is the dead time;
    * set-point moves in auto or cascade: the controller passes them to OP
      at once, so the delay from SP to PV is the process's dead time too, and
      SP, unlike OP, is not correlated with the disturbance (the indirect
      approach, Ljung 1999, sec. 13.5).

    A signal counts when it moves beyond three noise standard deviations of
    its own (and, for SP, of PV: a step PV's noise hides tells nothing).
    Each is scanned by an ARX delay scan (Bjorklund and Ljung 2003, sec. 3;
    the longest delay whose loss is within a chi-square test of the
    smallest, Ljung 1999, sec. 16.4; ``chi2`` the 0.95 and 0.999 quantiles
    with 4 degrees of freedom, ``nb = 4``, :func:`_arx_delay`), manual moves
    first; the first conclusive scan gives the dead time, and weak
    excitation gives 'unknown' with the delays that fitted alike rather than
    a guess.  The model's first lag
    counts the hold's sample, as :func:`harris_index` wants it.  Samples
    where a signal is missing are left out with the rows that lag them.
    ``pv_noise`` is PV's noise standard deviation outside manual when the
    caller has it already (:func:`analytics.stiction.stick_jump.robust_noise`
    of those samples, as :func:`setpoint_responses` takes it too).

    Examples
    --------
    A first-order process behind three samples of dead time (two whole and the
    hold's), its OP stepped by hand:

    >>> rng = np.random.default_rng(0)
    >>> op = np.repeat(rng.normal(size=40), 50)
    >>> pv = np.zeros(2000)
    >>> for t in range(3, 2000):
    ...     pv[t] = 0.8 * pv[t - 1] + 0.5 * op[t - 3] + 0.1 * rng.normal()
    >>> identify_dead_time(op, pv, manual=np.ones(2000, dtype=bool))
    DeadTimeEstimate(samples=3, note="identified from the operator's OP moves in manual")
    >>> identify_dead_time(op, pv, np.full(2000, 50.0)).note[:44]
    'unknown: no set-point moves beyond noise and'
    """
    u, y = np.asarray(op, dtype=np.float64), np.asarray(pv, dtype=np.float64)
    hand = np.zeros(y.size, dtype=bool) if manual is None else np.asarray(manual, dtype=bool)
    sources = []
    if hand.any():
        moved = np.where(hand, u, np.nan)
        if _moves_beyond_noise(moved):
            sources.append(("the operator's OP moves in manual", moved, np.where(hand, y, np.nan)))
    if sp is not None:
        s = np.where(hand, np.nan, np.asarray(sp, dtype=np.float64))
        auto_pv = np.where(hand, np.nan, y)
        floor = 3.0 * (_pv_noise(auto_pv) if pv_noise is None else pv_noise)
        if _moves_beyond_noise(s, floor):
            sources.append(("set-point steps", s, auto_pv))
    if not sources:
        return DeadTimeEstimate(None, "unknown: no set-point moves beyond noise and no OP "
                                      "moves in manual in the window; under feedback alone "
                                      "the dead time cannot be identified")
    reasons = []
    for name, excitation, response in sources:
        d, why = _arx_delay(excitation, response, max_delay, na, nb, chi2)
        if d is not None:
            return DeadTimeEstimate(d, f"identified from {name}")
        reasons.append(f"from {name}, {why}")
    return DeadTimeEstimate(None, "unknown: " + "; ".join(reasons))


def _finite(x: FloatArray) -> FloatArray:
    x = np.asarray(x, dtype=np.float64)
    return x[np.isfinite(x)]


def _pv_noise(pv: FloatArray) -> float:
    """PV's noise standard deviation over its present samples (0 for fewer than three)."""
    finite_pv = _finite(pv)
    return robust_noise(finite_pv) if finite_pv.size > 2 else 0.0


def valve_travel_per_day(op: FloatArray, ts: float) -> float:
    """OP travel beyond noise, in % of span per day.

    :func:`analytics.stiction.stick_jump.op_travel` (OP smoothed over three
    samples, a backlash of three noise standard deviations, so noise adds no
    travel) scaled from the window's length to a day (Jelali 2013, sec. 7.3:
    the valve travel index of valve monitoring).  Missing samples are skipped.

    Examples
    --------
    Three steps of 10 % in 400 samples at 216 s (one day); the backlash
    ``b = 3 robust_noise(op) = 1.84`` takes ``b`` off the first move and ``2 b``
    off each move after a reversal, ``30 - 5 b``:

    >>> op = np.repeat([0.0, 10.0, 0.0, 10.0], 100)
    >>> round(valve_travel_per_day(op, 216.0), 5)
    20.80291
    """
    x = _finite(op)
    if x.size < 2:
        return 0.0
    return op_travel(x) * DAY_S / (x.size * ts)


def reversals_per_day(op: FloatArray, ts: float) -> float:
    """Direction changes of OP's moves beyond noise, per day.

    The moves are those :func:`valve_travel_per_day` sums
    (:func:`analytics.stiction.stick_jump.travel_increments`); a move upwards
    means OP rose at that sample (the backlash follows OP only while OP leaves
    its band), so the direction of each move is the sign of OP's difference.
    A reversal is a move opposite to the previous one (Jelali 2013, sec. 7.3).

    Examples
    --------
    >>> op = np.repeat([0.0, 10.0, 0.0, 10.0], 100)
    >>> reversals_per_day(op, 216.0)
    2.0
    """
    return _valve_figures(op, ts)[1]


def _valve_figures(op: FloatArray, ts: float) -> tuple[float, float]:
    """:func:`valve_travel_per_day` and :func:`reversals_per_day` of ``op`` together.

    One smoothing, noise estimate and backlash pass for both (:func:`loop_kpis`
    wants both): the moves :func:`analytics.stiction.stick_jump.op_travel`
    sums, OP smoothed over three samples with a backlash of three noise
    standard deviations.
    """
    x = _finite(op)
    if x.size < 2:
        return 0.0, 0.0
    smoothed = moving_average(x, 3)
    moves = travel_increments(smoothed, 3.0 * robust_noise(x))
    idx = np.flatnonzero(moves > 0)
    idx = idx[idx > 0]
    direction = np.sign(smoothed[idx] - smoothed[idx - 1])
    direction = direction[direction != 0]
    reversals = int(np.count_nonzero(direction[1:] != direction[:-1]))
    return (float(moves.sum()) * DAY_S / (x.size * ts),
            reversals * DAY_S / (x.size * ts))


def saturation(op: FloatArray, low: float = 0.0, high: float = 100.0,
               margin: float = 0.5) -> float:
    """Share (0..1) of samples with OP at a limit: within ``margin`` of ``low`` or ``high``.

    Time at the output limits (Jelali 2013, sec. 7.4): a saturated loop has
    no control authority left.

    >>> saturation(np.array([0.0, 0.2, 50, 99.8, 100, 60]))
    0.6666666666666666
    """
    x = _finite(op)
    if x.size == 0:
        return 0.0
    return float(np.mean((x <= low + margin) | (x >= high - margin)))


@dataclass(frozen=True)
class SetpointResponse:
    """The response to one set-point step.

    Attributes
    ----------
    at_s : float
        When the step came, s from the window's first sample.
    step : float
        Size of the step (% of span, signed).
    overshoot : float
        Largest excursion of PV beyond the new set point in the step's
        direction, in % of the step (0 without overshoot).
    settling_time_s : float or None
        Time from the step until PV enters the settling band around the new
        set point for good; None when it had not settled before the next
        step or the window's end.
    iae : float
        ``sum |SP - PV| ts`` from the step to the next one or the window's end (% s).
    duration_s : float
        How long the response was observed.
    """

    at_s: float
    step: float
    overshoot: float
    settling_time_s: float | None
    iae: float
    duration_s: float


def setpoint_responses(sp: FloatArray, pv: FloatArray, ts: float, *, min_step: float = 1.0,
                       band: float = 0.02, noise_sigmas: float = 3.0,
                       pv_noise: float | None = None) -> tuple[SetpointResponse, ...]:
    """Overshoot, settling time and IAE of each set-point step in the window.

    A step is a change of SP of at least ``min_step`` (% of span) from one
    sample to the next; its response runs until the next step or the window's
    end.  The settling band is ``band`` of the step (2 %, Astrom and
    Hagglund 2006, sec. 4.2) but no narrower than ``noise_sigmas`` noise
    standard deviations of PV (:func:`analytics.stiction.stick_jump.robust_noise`
    of its present samples, or ``pv_noise`` when the caller has it already),
    so measurement noise alone does not keep a loop from settling.

    References
    ----------
    Astrom and Hagglund (2006), sec. 4.2 (overshoot, settling time, IAE).
    """
    s = np.asarray(sp, dtype=np.float64)
    p = np.asarray(pv, dtype=np.float64)
    ds = np.diff(s)
    steps = np.flatnonzero(np.abs(np.nan_to_num(ds)) >= min_step) + 1
    if steps.size == 0:
        return ()
    noise = _pv_noise(p) if pv_noise is None else pv_noise
    ends = np.append(steps[1:], s.size)
    out = []
    for k, end in zip(steps, ends, strict=True):
        step = float(s[k] - s[k - 1])
        target = s[k:end]
        e = target - p[k:end]
        ok = np.isfinite(e)
        if not ok.any():
            continue
        signed = -np.sign(step) * e  # > 0 where PV is beyond the set point in the step's way
        overshoot = max(0.0, float(np.nanmax(np.where(ok, signed, np.nan)))) / abs(step) * 100
        width = max(band * abs(step), noise_sigmas * noise)
        outside = np.flatnonzero(~ok | (np.abs(np.nan_to_num(e)) > width))
        if outside.size and outside[-1] == e.size - 1:
            settling = None
        else:
            settling = float((outside[-1] + 1) * ts) if outside.size else 0.0
        out.append(SetpointResponse(
            at_s=float(k * ts), step=step, overshoot=overshoot, settling_time_s=settling,
            iae=float(np.abs(e[ok]).sum() * ts), duration_s=float((end - k) * ts),
        ))
    return tuple(out)


@dataclass(frozen=True)
class ServiceFactor:
    """Time in each controller mode, as shares (0..1) of the samples.

    Attributes
    ----------
    auto, cascade, manual, unknown : float
        Shares of the samples in each mode; ``unknown`` for raw values the
        mapping does not name (and missing ones).
    normal : float
        ``auto + cascade``: the service factor.
    manual_s : float
        Time in manual (s).
    """

    auto: float
    cascade: float
    manual: float
    unknown: float
    normal: float
    manual_s: float


def service_factor(mode: ArrayLike, mapping: Mapping[Any, Mode], ts: float) -> ServiceFactor:
    """The share of time in normal mode (auto or cascade) and the time in manual.

    ``mode`` holds the raw mode values (as the DCS reports them: numbers or
    strings); ``mapping`` says which raw value means ``auto``, ``cascade`` or
    ``manual``.  The service factor of Jelali (2013, sec. 7.2): a loop that
    spends its time in manual is no loop.

    Examples
    --------
    >>> f = service_factor([1, 1, 2, 0, 0, 0, 1, 9], {0: "manual", 1: "auto", 2: "cascade"}, 10.0)
    >>> (f.normal, f.manual, f.unknown, f.manual_s)
    (0.5, 0.375, 0.125, 30.0)
    """
    raw = np.asarray(mode)
    n = raw.size
    if n == 0:
        return ServiceFactor(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    counts = {"auto": 0, "cascade": 0, "manual": 0}
    values, frequency = np.unique(raw, return_counts=True)
    for value, count in zip(values.tolist(), frequency.tolist(), strict=True):
        name = mapping.get(value)
        if name is not None:
            counts[name] += int(count)
    auto, cascade, manual = (counts[k] / n for k in ("auto", "cascade", "manual"))
    return ServiceFactor(auto, cascade, manual, 1.0 - auto - cascade - manual, auto + cascade,
                         counts["manual"] * ts)


def manual_samples(mode: ArrayLike, mapping: Mapping[Any, Mode]) -> NDArray[np.bool_]:
    """Which samples of the raw ``mode`` signal the ``mapping`` names manual.

    >>> manual_samples([1, 0, 0, 2], {0: "manual", 1: "auto", 2: "cascade"}).tolist()
    [False, True, True, False]
    """
    names_manual = [raw for raw, name in mapping.items() if name == "manual"]
    return np.isin(np.asarray(mode), names_manual)


def longest_normal_stretch(manual: NDArray[np.bool_]) -> slice:
    """The longest run of samples not in manual (the first of equal runs; empty if none).

    A controller is judged on the time it controlled (Jelali 2013, sec. 7.2):
    the stiction and oscillation diagnosis of a window with a stretch in
    manual is made on its longest stretch in auto or cascade.

    >>> longest_normal_stretch(np.array([0, 0, 1, 1, 0, 0, 0, 1], dtype=bool))
    slice(4, 7, None)
    >>> longest_normal_stretch(np.ones(3, dtype=bool))
    slice(0, 0, None)
    """
    edges = np.diff(np.concatenate(([1], manual.astype(np.int8), [1])))
    starts, stops = np.flatnonzero(edges == -1), np.flatnonzero(edges == 1)
    if starts.size == 0:
        return slice(0, 0)
    k = int(np.argmax(stops - starts))
    return slice(int(starts[k]), int(stops[k]))


def oscillation_index(detected: bool, regularity: float | None) -> float:
    """Oscillation index 0 (none) .. 1 (a strongly regular oscillation).

    ``min(r, 10) / 10`` for a detected oscillation of regularity ``r``
    (Thornhill et al. 2003: ``r > 1`` is a regular oscillation, the larger the
    more certainly a persistent cycle), 0 when none was detected -- the same
    scale the loop health score uses (:func:`loop_health`).

    >>> oscillation_index(True, 4.0), oscillation_index(False, 4.0), oscillation_index(True, 25)
    (0.4, 0.0, 1.0)
    """
    if not detected or regularity is None:
        return 0.0
    return min(float(regularity), 10.0) / 10.0


def loop_health(*, usable: bool, quality_warnings: int, oscillating: bool,
                regularity: float | None, stiction_confidence: float | None) -> float | None:
    """Loop health from 0 (bad actor) to 100 (healthy); None when the data are unusable.

    A loop that does not oscillate scores 100 less 5 per data-quality warning
    (at most 20).  An oscillating loop starts at 70 and loses up to 30 for a
    regular oscillation (30 times its :func:`oscillation_index`: the more
    regular, the more certainly a persistent cycle).  Either loses up to 40
    for a stiction verdict (``stiction_confidence * 40``; None without one): a
    regularly cycling loop with a confidently sticky valve is the worst actor,
    and a valve that sticks without a sustained cycle is a bad actor too, if a
    milder one.  A stuck valve freezes PV, which makes the data unusable for
    everything else; its stiction verdict is scored all the same.

    >>> loop_health(usable=True, quality_warnings=1, oscillating=False, regularity=None,
    ...             stiction_confidence=None)
    95.0
    >>> loop_health(usable=True, quality_warnings=0, oscillating=True, regularity=5.0,
    ...             stiction_confidence=0.5)
    35.0
    """
    sticky = stiction_confidence is not None
    if not usable and not sticky:
        return None
    if oscillating:
        score = 70.0 - oscillation_index(True, regularity) * 30.0
    else:
        score = 100.0 - min(20, 5 * quality_warnings)
    if stiction_confidence is not None:
        score -= 40.0 * float(stiction_confidence)
    return max(0.0, score)


@dataclass(frozen=True)
class LoopKpis:
    """The performance KPIs of one loop window (signals in % of span).

    Attributes
    ----------
    samples, ts : int, float
        Window length and sampling interval (s).
    error : ErrorStatistics or None
        None without SP and PV.
    harris : HarrisIndex or None
        None when the dead time is unknown or there are too few samples.
    dead_time_source : {"configured", "identified", "unknown"}
        Where the dead time came from: the loop's configuration, the window
        (:func:`identify_dead_time`), or nowhere.
    travel_per_day, reversals_per_day, saturation : float or None
        OP figures; None without OP.
    setpoint_responses : tuple of SetpointResponse
    service_factor : ServiceFactor or None
        None without a mode signal.
    oscillation_index : float or None
        None when the oscillation detection did not run.
    notes : tuple of str
        What was skipped and why.
    dead_time_samples : int or None
        The dead time ``d`` in samples (the hold's counted); None when unknown.
    dead_time_s : float or None
        The same in seconds, ``(d - 1) ts``: the whole samples of the dead
        time without the hold's, the shortest continuous dead time that gives ``d``.
    dead_time_note : str
        The source in words, for the pages beside the index: ``"configured"``,
        ``"identified from set-point steps"`` (or ``"... from the operator's
        OP moves in manual"``), ``"unknown: ..."`` with the reason.
    """

    samples: int
    ts: float
    error: ErrorStatistics | None
    harris: HarrisIndex | None
    dead_time_source: str
    travel_per_day: float | None
    reversals_per_day: float | None
    saturation: float | None
    setpoint_responses: tuple[SetpointResponse, ...] = ()
    service_factor: ServiceFactor | None = None
    oscillation_index: float | None = None
    notes: tuple[str, ...] = field(default=())
    dead_time_samples: int | None = None
    dead_time_s: float | None = None
    dead_time_note: str = "unknown"

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready form (NaN becomes None)."""
        def clean(value: Any) -> Any:
            if isinstance(value, float) and not np.isfinite(value):
                return None
            if isinstance(value, dict):
                return {k: clean(v) for k, v in value.items()}
            if isinstance(value, list | tuple):
                return [clean(v) for v in value]
            return value

        result: dict[str, Any] = clean(asdict(self))
        return result

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None, *, lenient: bool = False) -> LoopKpis:
        """The KPIs of :meth:`to_dict`'s form: ``to_dict(from_dict(d)) == d`` (a NaN
        figure was stored as None and reads None).

        ``lenient`` reads KPIs stored by an older version, or none at all (the
        service's runs of unusable data): a missing field reads as its default, and
        a missing ``samples`` and ``ts`` as 0 and NaN.

        Raises
        ------
        DataError
            A field is missing (strict reading) or a part is not an object; the
            message names it (``loop kpis.harris``).
        """
        read = Reader(d, "loop kpis", lenient=lenient)

        def optional(key: str, part: type[Any]) -> Any:
            return None if read(key) is None else read.part(key).flat(part)

        return cls(
            samples=read("samples", 0), ts=read("ts", float("nan")),
            error=optional("error", ErrorStatistics), harris=optional("harris", HarrisIndex),
            dead_time_source=read("dead_time_source", "unknown"),
            travel_per_day=read("travel_per_day"), reversals_per_day=read("reversals_per_day"),
            saturation=read("saturation"),
            setpoint_responses=tuple(r.flat(SetpointResponse)
                                     for r in read.items("setpoint_responses")),
            service_factor=optional("service_factor", ServiceFactor),
            oscillation_index=read("oscillation_index"),
            notes=tuple(read("notes", ())), dead_time_samples=read("dead_time_samples"),
            dead_time_s=read("dead_time_s"), dead_time_note=read("dead_time_note", "unknown"),
        )


def loop_kpis(ts: float, *, op: FloatArray | None = None, pv: FloatArray | None = None,
              sp: FloatArray | None = None, dead_time: int | None = None,
              pv_limits: tuple[float, float] | None = None,
              mode: Sequence[Any] | FloatArray | None = None,
              mode_mapping: Mapping[Any, Mode] | None = None,
              oscillation: Mapping[str, Any] | None = None) -> LoopKpis:
    """All KPIs of one window; signals in % of span, ``dead_time`` in samples (or None).

    ``oscillation`` is the oscillation part of a diagnosis
    (:meth:`analytics.diagnosis.LoopDiagnosis.to_dict`: ``detected``, ``regularity``).

    The minimum-variance index uses the configured ``dead_time``; without one
    the dead time :func:`identify_dead_time` finds from the window's set-point
    steps or the operator's OP moves in manual (never from the loop under
    feedback alone).  ``dead_time_source`` and ``dead_time_note`` say which,
    or why it stayed unknown.

    With a ``mode`` signal, the samples in manual are left out of the
    controller's figures -- error statistics, minimum-variance index,
    set-point responses and saturation -- since in manual no controller acts
    (Jelali 2013, sec. 7.2: assess a loop on its time in normal mode); a note
    says how much was left out.  Valve travel and reversals count every
    sample: the valve wears in manual too.
    """
    notes: list[str] = []
    whole_pv, whole_sp = pv, sp  # manual samples included: the identification wants them
    n = max((x.size for x in (op, pv, sp) if x is not None), default=0)
    factor = None
    manual = np.zeros(n, dtype=bool)
    if mode is not None and mode_mapping is not None:
        factor = service_factor(mode, mode_mapping, ts)
        manual = manual_samples(mode, mode_mapping)
        if manual.any():
            notes.append(
                f"in manual {100 * factor.manual:.0f} % of the window ({factor.manual_s:.0f} s): "
                "error statistics, minimum-variance index, set-point responses and saturation "
                "are of the samples in auto or cascade")
            sp, pv = (None if x is None else np.where(manual, np.nan, x) for x in (sp, pv))
    error = harris = None
    configured = dead_time is not None
    note = "configured" if configured else "unknown: no SP or no PV"
    responses: tuple[SetpointResponse, ...] = ()
    if sp is not None and pv is not None:
        error = error_statistics(sp, pv, ts, pv_limits)
        # PV's noise outside manual, once for the identification and the responses
        noise = None if configured or op is None else _pv_noise(pv)
        responses = setpoint_responses(sp, pv, ts, pv_noise=noise)
        if not configured:
            note = "unknown: no OP to identify it from"
            if op is not None and whole_pv is not None:
                estimate = identify_dead_time(op, whole_pv, whole_sp, manual, pv_noise=noise)
                dead_time, note = estimate.samples, estimate.note
        if dead_time is None:
            notes.append(f"dead time {note}; no minimum-variance (Harris) index")
        else:
            harris = harris_index(sp - pv, dead_time)
            if harris is None:
                notes.append("too few complete samples for the minimum-variance index")
    else:
        notes.append("no SP or no PV: no error statistics")
    travel = reversals = sat = None
    if op is not None and np.isfinite(op).any():
        travel, reversals = _valve_figures(op, ts)
        sat = saturation(np.where(manual, np.nan, op))
    osc = None if oscillation is None else oscillation_index(
        bool(oscillation.get("detected")), oscillation.get("regularity"))
    return LoopKpis(
        samples=n, ts=ts, error=error, harris=harris,
        dead_time_source="configured" if configured else (
            "unknown" if dead_time is None else "identified"),
        travel_per_day=travel, reversals_per_day=reversals, saturation=sat,
        setpoint_responses=responses, service_factor=factor, oscillation_index=osc,
        notes=tuple(notes), dead_time_samples=dead_time,
        dead_time_s=None if dead_time is None else (dead_time - 1) * ts,
        dead_time_note=note,
    )
