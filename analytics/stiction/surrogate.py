"""Surrogate-data nonlinearity index of an oscillating signal (Thornhill 2005).

A limit cycle caused by a nonlinearity (a sticky valve) is a non-sinusoidal
oscillation whose harmonics keep a fixed phase relation to the fundamental.
That phase coupling makes the signal more predictable than its *surrogates*:
series with the same power spectrum but random Fourier phases (thesis
Eqs. 2.7-2.8).  The nonlinearity index compares the nearest-neighbour
prediction error of the signal with those of ``M`` surrogates (thesis
Eq. 2.9, ERRATA item 3 for Eq. 2.6)::

    N = (mean(Gamma_surr) - Gamma_test) / (3 std(Gamma_surr))

``N > 1`` means nonlinear.  Because the index is strongest at the source of
a nonlinear oscillation and weaker in the loops it propagates to, the same
function ranks the OP and PV signals of a multi-loop unit (thesis section
2.3.5, step 3).

Preparation, as Thornhill prescribes: the signal is resampled so that one
period spans exactly ``S_n`` samples (thesis Remark 5 with ERRATA item 8:
at least 30), and a window of whole cycles whose ends match in value and
slope is cut out ("end matching"), so that the periodic continuation
implied by the discrete Fourier transform has no jump; otherwise the
surrogates of a strongly cyclic signal carry a spurious broadband edge and
even a sine looks nonlinear.  The embedding dimension and the prediction
horizon are both ``S_n`` (Remark 5): each row of the embedded matrix
(Eq. 2.5) is one cycle long and predicts the sample that follows it.

The exact K-nearest-neighbour search runs in one compiled kernel over the
test series and all surrogates at once: the squared distance between two
rows is updated along each diagonal of the distance matrix in O(1)
(``d(i+1, j+1) = d(i, j) - (x_i - x_j)^2 + (x_{i+E} - x_{j+E})^2``), and the
diagonals are visited by decreasing autocorrelation of their lag (one period
apart first), so that the neighbour lists fill with good candidates early
and most later candidates are rejected by a single comparison.

References
----------
.. [1] N. F. Thornhill, "Finding the source of nonlinearity in a process with
   plant-wide oscillation", *IEEE Transactions on Control Systems
   Technology* 13 (2005) 434-443.
.. [2] Thesis section 2.3.5, Eqs. 2.5-2.9 and Remarks 4-5; ERRATA items 3
   (Eq. 2.6 averages over the K neighbours) and 8 (S in Remark 5 is the
   number of samples per cycle).
.. [3] T. Schreiber and A. Schmitz, "Surrogate time series", *Physica D* 142
   (2000) 346-382 (end-point mismatch of Fourier surrogates).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray
from scipy import fft as sfft
from scipy import signal

from analytics.errors import DataError
from analytics.stiction.evidence import (
    NO_STICTION,
    STICTION,
    LoopWindow,
    MethodEvidence,
    margin_confidence,
)
from analytics.types import FloatArray

__all__ = [
    "MIN_PERIOD_SAMPLES",
    "SurrogateDetector",
    "SurrogateResult",
    "phase_randomised_surrogates",
    "resample_whole_cycles",
    "surrogate_nonlinearity_index",
]


#: Shortest period (in raw samples) whose second harmonic is still sampled.
MIN_PERIOD_SAMPLES = 4.0
#: Sentinel distance of an empty neighbour slot (finite: the kernel uses fastmath).
_FAR = 1e300


def _remove_cycle_trend(x: FloatArray, period_samples: float) -> FloatArray:
    """``x`` minus the straight line through the means of its whole cycles.

    A least-squares line through the samples themselves would be biased by
    the oscillation (over whole cycles a sine still correlates with a ramp)
    and subtracting it would add a sawtooth, whose phase-locked harmonics
    pass for nonlinearity.  The mean of each whole cycle is free of any
    periodic component, so the line through those means is the drift alone.
    """
    cycles = int(x.size // period_samples)
    if cycles < 2:
        return np.asarray(x - x.mean(), dtype=np.float64)
    edges = x.size - np.round((cycles - np.arange(cycles + 1)) * period_samples).astype(np.int64)
    means = np.add.reduceat(x, edges[:-1]) / np.diff(edges)
    centres = 0.5 * (edges[:-1] + edges[1:] - 1)
    slope, intercept = np.polyfit(centres, means, 1)
    return np.asarray(x - (intercept + slope * np.arange(x.size)), dtype=np.float64)


def resample_whole_cycles(
    x: ArrayLike,
    period_samples: float,
    samples_per_cycle: float,
    *,
    max_cycles: int | None = None,
) -> tuple[FloatArray, int]:
    """An end-matched window of whole cycles, resampled to ``samples_per_cycle`` per cycle.

    The drift is removed (:func:`_remove_cycle_trend`); the window spans
    ``c = floor(len(x) / period_samples)`` periods (at most ``max_cycles``,
    the latest ones), and among the windows of that length the one whose
    ends match best is kept: it minimises the squared jump between its
    first and last samples plus the squared slip between its first and last
    slopes (the end-point mismatch of Schreiber & Schmitz 2000;
    on ties the latest window wins).  The window is then resampled to
    ``round(c * samples_per_cycle)`` samples in the frequency domain
    (:func:`scipy.signal.resample`).

    Because the window holds whole cycles with matching ends, its periodic
    continuation is smooth: the Fourier resampling adds no edge ringing and
    the phase-randomised surrogates no spurious jump (Thornhill 2005).
    Fourier resampling is also shift-invariant, unlike a polyphase filter
    with a fractional factor, whose output noise is cyclostationary with
    the interpolation phase; such a periodic pattern in the noise is itself
    predictable and would pass for nonlinearity.  Downsampling this way is
    the band-limiting that Thornhill (2005) and Choudhury et al. (2004)
    apply before their tests: it keeps the harmonics that carry the shape
    of the cycle and drops the noise above them.

    Parameters
    ----------
    x : array_like
        One-dimensional signal.
    period_samples : float
        Oscillation period in samples of ``x``.
    samples_per_cycle : float
        Wanted period in samples of the result.
    max_cycles : int, optional
        Cycles kept at most.

    Returns
    -------
    y : ndarray
        The resampled window.
    cycles : int
        Number of whole cycles in it.

    Raises
    ------
    DataError
        If ``x`` holds less than one period.

    Examples
    --------
    >>> k = np.arange(1030)
    >>> y, cycles = resample_whole_cycles(np.sin(2 * np.pi * k / 50), 50.0, 10.0)
    >>> cycles, y.size, int(np.argmax(np.abs(np.fft.rfft(y))))
    (20, 200, 20)
    """
    xa = np.asarray(x, dtype=np.float64)
    if not (np.isfinite(period_samples) and period_samples > 0):
        raise DataError(f"period_samples must be positive, got {period_samples!r}")
    cycles = int(xa.size // period_samples)
    if max_cycles is not None:
        cycles = min(cycles, max_cycles)
    length = round(cycles * period_samples)
    if cycles < 1 or length < 3:
        raise DataError(f"{xa.size} samples hold less than one period of {period_samples:g}")
    region = xa[-min(xa.size, length + int(np.ceil(period_samples))) :]
    xd = _remove_cycle_trend(region, period_samples)
    starts = np.arange(xd.size - length, -1, -1)
    last = starts + length - 1
    jump = xd[starts] - xd[last]
    slip = (xd[starts + 1] - xd[starts]) - (xd[last] - xd[last - 1])
    best = int(starts[np.argmin(jump**2 + slip**2)])
    resampled = signal.resample(xd[best : best + length], round(cycles * samples_per_cycle))
    return np.asarray(resampled, dtype=np.float64), cycles


def phase_randomised_surrogates(x: ArrayLike, count: int, seed: int = 0) -> FloatArray:
    """Surrogates with the power spectrum of ``x`` and uniformly random Fourier phases.

    Thesis Eqs. 2.7-2.8: a phase ``phi_i ~ U(-pi, pi]`` is added to every
    frequency channel; the channels above the Nyquist frequency get the
    opposite phases, which :func:`scipy.fft.irfft` implies, and the zero
    channel (and, for even length, the Nyquist channel) keep phase 0 so
    that each surrogate is real.

    Parameters
    ----------
    x : array_like
        One-dimensional series (end-matched for cyclic data).
    count : int
        Number of surrogates ``M``.
    seed : int
        Seed of the random phases; the result is a pure function of
        ``(x, count, seed)``.

    Returns
    -------
    ndarray, shape (count, len(x))

    Examples
    --------
    >>> x = np.sin(np.arange(64) * 2 * np.pi / 16) + np.arange(64) % 3
    >>> s = phase_randomised_surrogates(x, 2, seed=1)
    >>> bool(np.allclose(np.abs(np.fft.rfft(s, axis=1)), np.abs(np.fft.rfft(x))))
    True
    """
    xa = np.asarray(x, dtype=np.float64)
    spectrum = sfft.rfft(xa)
    phases = np.random.default_rng(seed).uniform(-np.pi, np.pi, size=(count, spectrum.size))
    phases[:, 0] = 0.0
    if xa.size % 2 == 0:
        phases[:, -1] = 0.0
    surrogates = sfft.irfft(spectrum[None, :] * np.exp(1j * phases), n=xa.size, axis=1)
    return np.asarray(surrogates, dtype=np.float64)


@njit(cache=True, inline="always")
def _insert_neighbour(
    best_distance: FloatArray,
    best_index: NDArray[np.int64],
    worst: FloatArray,
    row: int,
    series: int,
    distance: float,
    neighbour: int,
) -> None:
    """Insert ``neighbour`` into the sorted K-list of ``row`` (insertion sort)."""
    k = best_distance.shape[2] - 1
    while k > 0 and best_distance[row, series, k - 1] > distance:
        best_distance[row, series, k] = best_distance[row, series, k - 1]
        best_index[row, series, k] = best_index[row, series, k - 1]
        k -= 1
    best_distance[row, series, k] = distance
    best_index[row, series, k] = neighbour
    worst[row, series] = best_distance[row, series, -1]


@njit(cache=True, fastmath=True)
def _prediction_errors(
    series: FloatArray, embedding: int, neighbours: int, diagonals: NDArray[np.int64]
) -> FloatArray:
    """Nearest-neighbour prediction error (thesis Eq. 2.6) of each column of ``series``.

    ``series`` is time-major, shape ``(length, n_series)``, so that the
    inner loops run over the series in contiguous memory.  Row ``i`` of the
    embedded matrix (Eq. 2.5) is ``x[i : i + E]`` and predicts ``x[i + E]``
    (``H = E``); the prediction is the mean of the values that follow its
    ``K`` nearest rows among those more than ``E / 2`` samples away
    (``diagonals`` lists the admissible offsets ``j - i`` in the order to
    visit them).  Returns ``sum_i (x[i + E] - mean_j x[j + E])^2`` per series.
    """
    length, n_series = series.shape
    rows = length - embedding
    best_distance = np.full((rows, n_series, neighbours), _FAR)
    best_index = np.zeros((rows, n_series, neighbours), dtype=np.int64)
    worst = np.full((rows, n_series), _FAR)
    distance = np.zeros(n_series)
    for offset in diagonals:
        distance[:] = 0.0
        for m in range(embedding):
            a = series[m]
            b = series[offset + m]
            for s in range(n_series):
                diff = a[s] - b[s]
                distance[s] += diff * diff
        for i in range(rows - offset):
            j = i + offset
            worst_i = worst[i]
            worst_j = worst[j]
            hits = 0
            if i > 0:
                leaving_i = series[i - 1]
                leaving_j = series[j - 1]
                entering_i = series[i + embedding - 1]
                entering_j = series[j + embedding - 1]
                for s in range(n_series):
                    out = leaving_i[s] - leaving_j[s]
                    into = entering_i[s] - entering_j[s]
                    value = distance[s] + (into * into - out * out)
                    distance[s] = value
                    hits += (value < worst_i[s]) + (value < worst_j[s])
            else:
                for s in range(n_series):
                    hits += (distance[s] < worst_i[s]) + (distance[s] < worst_j[s])
            if hits == 0:
                continue
            for s in range(n_series):
                value = distance[s]
                if value < worst_i[s]:
                    _insert_neighbour(best_distance, best_index, worst, i, s, value, j)
                if value < worst_j[s]:
                    _insert_neighbour(best_distance, best_index, worst, j, s, value, i)
    errors = np.zeros(n_series)
    for i in range(rows):
        for s in range(n_series):
            prediction = 0.0
            for k in range(neighbours):
                prediction += series[best_index[i, s, k] + embedding, s]
            error = series[i + embedding, s] - prediction / neighbours
            errors[s] += error * error
    return errors


@dataclass(frozen=True)
class SurrogateResult:
    """Result of :func:`surrogate_nonlinearity_index`.

    Attributes
    ----------
    index : float
        Nonlinearity index ``N`` (thesis Eq. 2.9); ``N > 1`` is nonlinear.
    test_error : float
        ``Gamma_test``, prediction error of the standardised signal (Eq. 2.6).
    surrogate_mean, surrogate_std : float
        Mean and (sample) standard deviation of the ``M`` surrogate errors.
    cycles : int
        Whole cycles in the analysed, end-matched window.
    samples_per_cycle : int
        ``S_n``, which is also the embedding dimension ``E`` and the
        prediction horizon ``H``.
    """

    index: float
    test_error: float
    surrogate_mean: float
    surrogate_std: float
    cycles: int
    samples_per_cycle: int


def surrogate_nonlinearity_index(
    x: ArrayLike,
    period_samples: float,
    *,
    neighbours: int = 8,
    surrogates: int = 50,
    seed: int = 0,
    samples_per_cycle: int = 30,
    max_cycles: int = 12,
    min_cycles: int = 8,
) -> SurrogateResult:
    """Thornhill's nonlinearity index of one oscillating signal.

    Steps (thesis section 2.3.5): resample to ``S_n`` samples per period
    and keep the end-matched window of the latest ``min(max_cycles, available)``
    whole cycles (:func:`resample_whole_cycles`), standardise it, build
    ``M`` phase-randomised surrogates (Eqs. 2.7-2.8), compute the
    ``K``-nearest-neighbour prediction error ``Gamma`` of the signal and of
    every surrogate with ``E = H = S_n`` (Eqs. 2.5-2.6) and return
    ``N = (mean(Gamma_surr) - Gamma_test) / (3 std(Gamma_surr))`` (Eq. 2.9).

    Parameters
    ----------
    x : array_like
        One signal (OP or PV), at least ``min_cycles`` periods long.
    period_samples : float
        Oscillation period in samples of ``x`` (e.g. from
        :func:`analytics.oscillation.detect_loop_oscillation`).
    neighbours : int
        ``K``, number of nearest neighbours (Thornhill's default 8).
    surrogates : int
        ``M``, number of surrogates (default 50).
    seed : int
        Seed of the surrogate phases: the index is deterministic for a seed.
    samples_per_cycle : int
        ``S_n = E = H``; the thesis (Remark 5) asks for at least 30.
    max_cycles : int
        Cycles analysed at most (the latest ones); the cost grows with the
        square of the window length.  Thornhill's defaults hold for more
        than 12 cycles.
    min_cycles : int
        Fewest whole cycles accepted.

    Returns
    -------
    SurrogateResult

    Raises
    ------
    DataError
        If the signal is shorter than ``min_cycles`` periods, the period is
        shorter than :data:`MIN_PERIOD_SAMPLES`, or the signal is constant.

    References
    ----------
    Thornhill (2005); thesis Eqs. 2.5-2.9 with ERRATA items 3 and 8 (see the
    module docstring).

    Examples
    --------
    The output of a first-order process driven by a square wave (a valve
    slipping between two positions, half cycles of 22 to 28 samples) is
    nonlinear; a sinusoid in noise is not:

    >>> from scipy.signal import lfilter
    >>> rng = np.random.default_rng(2)
    >>> halves = rng.integers(22, 29, 80)
    >>> mv = np.concatenate([np.full(h, (-1.0) ** i) for i, h in enumerate(halves)])
    >>> pv = lfilter([0.1], [1, -0.9], mv[:1500]) + 0.02 * rng.standard_normal(1500)
    >>> sine = np.sin(2 * np.pi * np.arange(1500) / 50) + 0.1 * rng.standard_normal(1500)
    >>> round(surrogate_nonlinearity_index(pv, 50.0).index, 1)
    1.8
    >>> surrogate_nonlinearity_index(sine, 50.0).index < 1
    True
    """
    xa = np.asarray(x, dtype=np.float64)
    if xa.ndim != 1:
        raise DataError(f"the signal must be one-dimensional, got shape {xa.shape}")
    if not (np.isfinite(period_samples) and period_samples >= MIN_PERIOD_SAMPLES):
        raise DataError(
            f"the period must span at least {MIN_PERIOD_SAMPLES:g} samples, got {period_samples!r}"
        )
    if neighbours < 1 or surrogates < 2 or samples_per_cycle < 4 or min_cycles < 3:
        raise DataError("need neighbours >= 1, surrogates >= 2, samples_per_cycle >= 4, "
                        "min_cycles >= 3")
    if xa.size < min_cycles * period_samples:
        raise DataError(
            f"{xa.size / period_samples:.2f} cycles in the signal, at least {min_cycles} needed"
        )
    window, cycles = resample_whole_cycles(
        xa, period_samples, samples_per_cycle, max_cycles=max_cycles
    )
    spread = float(window.std())
    if not spread > 1e-12 * float(np.max(np.abs(xa))):
        raise DataError("the signal is constant over the analysed cycles")
    test = (window - window.mean()) / spread
    fewest_candidates = test.size - samples_per_cycle - 2 * (samples_per_cycle // 2) - 1
    if fewest_candidates < neighbours:
        raise DataError(
            f"{cycles} cycles of {samples_per_cycle} samples leave {fewest_candidates} "
            f"admissible neighbours for some rows, {neighbours} are needed"
        )
    batch = np.vstack([test[None, :], phase_randomised_surrogates(test, surrogates, seed)])
    # Rows ``d`` apart are ``2 E (1 - acf(d))`` apart on average, for the
    # signal and for every surrogate alike (they share its circular
    # autocorrelation): visiting the offsets by decreasing autocorrelation
    # meets the nearest neighbours first.
    offsets = np.arange(samples_per_cycle // 2 + 1, test.size - samples_per_cycle)
    autocorrelation = sfft.irfft(np.abs(sfft.rfft(test)) ** 2, n=test.size)
    diagonals = offsets[np.argsort(-autocorrelation[offsets], kind="stable")]
    errors = _prediction_errors(
        np.ascontiguousarray(batch.T), samples_per_cycle, neighbours, diagonals
    )
    test_error = float(errors[0])
    surrogate_mean = float(errors[1:].mean())
    surrogate_std = float(errors[1:].std(ddof=1))
    index = (surrogate_mean - test_error) / (3.0 * surrogate_std) if surrogate_std > 0 else 0.0
    return SurrogateResult(
        index=float(index),
        test_error=test_error,
        surrogate_mean=surrogate_mean,
        surrogate_std=surrogate_std,
        cycles=cycles,
        samples_per_cycle=samples_per_cycle,
    )


@dataclass(frozen=True, kw_only=True)
class SurrogateDetector:
    """Stiction evidence from the surrogate nonlinearity index of PV (and OP).

    In a single loop with a linear process, a nonlinear oscillation points
    to the valve (thesis section 1.2.2, "Surrogate Analysis").  The index
    of PV decides (thesis Eq. 2.9: ``N > 1`` nonlinear; the thesis ranks
    sticky valves by the PV indices and finds the OP indices usually below
    1, Table 2.8); OP's index, when OP is given, is reported beside it.
    Undecided without an oscillation period, with fewer than ``min_cycles``
    cycles or with a period shorter than :data:`MIN_PERIOD_SAMPLES`.

    Attributes
    ----------
    neighbours, surrogates, seed, samples_per_cycle, max_cycles, min_cycles
        As in :func:`surrogate_nonlinearity_index` (Thornhill's defaults
        ``K = 8``, ``M = 50``; ``S_n = 30`` per the thesis).
    include_op : bool
        Also compute OP's index for the details (doubles the cost).
    threshold : float
        ``N`` above which the signal is nonlinear (1, Thornhill 2005).
    confidence_scale : float
        Distance of ``N`` from the threshold that gives confidence 0.63.

    References
    ----------
    Thornhill (2005); thesis section 2.3.5, Eq. 2.9, Table 2.8.

    Examples
    --------
    >>> from scipy.signal import lfilter
    >>> rng = np.random.default_rng(2)
    >>> halves = rng.integers(22, 29, 80)
    >>> mv = np.concatenate([np.full(h, (-1.0) ** i) for i, h in enumerate(halves)])
    >>> pv = lfilter([0.1], [1, -0.9], mv[:1500]) + 0.02 * rng.standard_normal(1500)
    >>> window = LoopWindow(ts=1.0, op=None, pv=pv, period_s=50.0)
    >>> evidence = SurrogateDetector().detect(window)
    >>> evidence.decision, round(evidence.index, 1)
    ('stiction', 1.8)
    """

    name: ClassVar[str] = "surrogate"

    neighbours: int = 8
    surrogates: int = 50
    seed: int = 0
    samples_per_cycle: int = 30
    max_cycles: int = 12
    min_cycles: int = 8
    include_op: bool = True
    threshold: float = 1.0
    confidence_scale: float = 1.0

    def _index(self, x: FloatArray, period_samples: float) -> SurrogateResult:
        return surrogate_nonlinearity_index(
            x,
            period_samples,
            neighbours=self.neighbours,
            surrogates=self.surrogates,
            seed=self.seed,
            samples_per_cycle=self.samples_per_cycle,
            max_cycles=self.max_cycles,
            min_cycles=self.min_cycles,
        )

    def detect(self, window: LoopWindow) -> MethodEvidence:
        """Evidence for or against stiction in ``window`` (see the class docstring)."""
        period = window.period_samples
        if period is None:
            return MethodEvidence.undecided(
                self.name, "no oscillation period: the surrogate test needs one"
            )
        cycles = window.samples / period
        if cycles < self.min_cycles:
            return MethodEvidence.undecided(
                self.name,
                f"only {cycles:.2f} cycles in the window, the surrogate test needs "
                f"{self.min_cycles}",
                details={"cycles": cycles},
            )
        if period < MIN_PERIOD_SAMPLES:
            return MethodEvidence.undecided(
                self.name,
                f"the period spans {period:.1f} samples: too few to see the cycle's shape",
            )
        details: dict[str, float] = {}
        results: dict[str, SurrogateResult] = {}
        op = window.op if self.include_op or window.pv is None else None
        for label, x in (("pv", window.pv), ("op", op)):
            if x is None or np.ptp(x) == 0:
                continue
            result = self._index(x, period)
            results[label] = result
            details[f"index_{label}"] = result.index
            details[f"test_error_{label}"] = result.test_error
            details[f"surrogate_mean_{label}"] = result.surrogate_mean
            details[f"surrogate_std_{label}"] = result.surrogate_std
        if not results:
            return MethodEvidence.undecided(self.name, "OP and PV are missing or constant")
        label = "pv" if "pv" in results else "op"
        decisive = results[label]
        details["cycles"] = float(decisive.cycles)
        details["samples_per_cycle"] = float(decisive.samples_per_cycle)
        n = decisive.index
        confidence = margin_confidence(n, self.threshold, self.confidence_scale)
        if n > self.threshold:
            note = (
                f"{label.upper()} is nonlinear (N = {n:.2f} > {self.threshold:g}): it is "
                f"more predictable than its phase-randomised surrogates, as a limit cycle is"
            )
            return MethodEvidence(self.name, STICTION, n, confidence, note, details)
        note = (
            f"{label.upper()} is not distinguishable from a linear signal "
            f"(N = {n:.2f} <= {self.threshold:g})"
        )
        return MethodEvidence(self.name, NO_STICTION, n, confidence, note, details)
