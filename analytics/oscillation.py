"""Oscillation detection in a single loop signal (OP alone or PV alone).

Methods
-------
* **ACF regularity** -- N. F. Thornhill, B. Huang and H. Zhang, "Detection of
  multiple oscillations in control loops", *Journal of Process Control* 13
  (2003) 91-100.  Each peak of the power spectrum defines a frequency band;
  the signal is band-pass filtered to that band, its autocorrelation
  function (ACF) is computed, and the intervals ``dt_i`` between successive
  zero crossings of the ACF give the period and its regularity::

      Tp_i = 2 dt_i,   Tp = mean(Tp_i),   r = mean(Tp_i) / (3 std(Tp_i))

  An oscillation is regular when ``r > 1``.  Because each spectral band is
  tested separately, several oscillations in one signal are found; they are
  reported sorted by power.
* **Spectral peak prominence** (automation of the band selection that
  Thornhill et al. do from the spectrum): a band is only tested if its mean
  spectral density stands ``min_prominence`` times above the geometric mean
  of the densities one octave below and above.  The ACF of *any* band-passed
  signal oscillates near lag zero, so without this gate coloured noise
  (AR(1), random walk) passes ``r > 1`` in most windows.
* **IAE between zero crossings** -- T. Hagglund, "A control-loop performance
  monitor", *Control Engineering Practice* 3 (1995) 1543-1551.  The integrated
  absolute error between successive zero crossings is compared with::

      IAE_lim = 2 a / omega_u

  (the IAE of one half cycle of a sine of amplitude ``a`` at ``omega_u``).
  Half cycles above the limit are load disturbances; more than ``n_lim = 10``
  of them within the supervision time ``T_sup = 50 T_i`` means oscillation.
  Offline, with no controller data, ``omega_u`` is replaced by the detected
  frequency ``2 pi / Tp``, ``T_i`` by ``Tp / 2`` and ``n_lim`` is scaled to the
  window length.  It is reported for corroboration; it does not decide (with
  ``a`` set relative to the data span it also fires on coloured noise).

* **Significance of slow peaks** -- the prominence of a band with few cycles
  in the window is compared with the 1 % quantile of the ``F`` distribution of
  a ratio of periodogram averages (Priestley, *Spectral Analysis and Time
  Series*, 1981, sec. 6.1): random walks and drifts make a few slow "cycles"
  that stand out by chance, a sustained slow oscillation stands out more.
* **Sliding-window (segment) analysis** -- the same test on the halves and
  quarters of the window (Thornhill et al. 2003 use the time-localised view
  for oscillations that come and go; Hagglund 1995 supervises a moving time
  ``T_sup``): oscillations present in only part of the window, or riding on a
  drifting mean, are found where they are.
* **Hilbert envelope** -- the envelope of the band-passed component (Gabor
  1946) gives the part of the window where an oscillation is present; a
  segment detection must be present over at least half the window.

All filtering is zero-phase and done in the frequency domain on zero-padded
FFTs of the mean- and trend-removed window and segments, so a 10,000-sample
window takes about ten milliseconds and a 100,000-sample one well under 100.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import fft as sfft
from scipy import signal
from scipy.stats import f as f_dist

from analytics.errors import DataError
from analytics.signals import Spectrum, detrend, shared, spectrum, zero_crossings
from analytics.types import FloatArray

__all__ = [
    "LIMIT_CYCLE_ENVELOPE_CV",
    "RAYLEIGH_ENVELOPE_CV",
    "REGULARITY_CAP",
    "LoopOscillation",
    "MethodResult",
    "Oscillation",
    "OscillationReport",
    "bandpass",
    "detect_loop_oscillation",
    "detect_oscillations",
    "envelope_variation",
]

#: Regularity reported for (numerically) perfectly regular ACF zero crossings.
REGULARITY_CAP = 100.0
#: Fewest samples :func:`detect_oscillations` accepts.
MIN_SAMPLES = 64
#: Longest period, as a fraction of the window, from which the filter-bank
#: grid is laid (the longest period searched before slower ones were added).
GRID_REFERENCE_FRACTION = 0.3
#: Ratio of the 90th to the 10th percentile of a Rayleigh distribution, the
#: envelope of band-limited Gaussian noise: ``sqrt(ln 10 / ln(10 / 9))``.
RAYLEIGH_SPREAD = float(np.sqrt(np.log(10.0) / np.log(10.0 / 9.0)))


@dataclass(frozen=True)
class Oscillation:
    """One oscillation found in a signal.

    Attributes
    ----------
    period_s : float
        Oscillation period in seconds, ``Tp = mean(2 dt_i)`` over the
        intervals ``dt_i`` between ACF zero crossings of the band-passed
        signal (Thornhill et al. 2003).
    frequency_hz : float
        ``1 / period_s``.
    regularity : float
        ``r = mean(Tp_i) / (3 std(Tp_i))`` (Thornhill et al. 2003);
        ``r > 1`` is a regular oscillation.  Capped at :data:`REGULARITY_CAP`.
    amplitude : float
        Half peak-to-peak amplitude of the band-passed component, in signal
        units: the median over the complete cycles, while the oscillation is
        present, of ``(max - min) / 2``.
        For a sine this is its amplitude; for a square wave of amplitude
        ``A`` it is the fundamental's ``4 A / pi``.
    power_fraction : float
        Fraction of the detrended signal's variance inside the band.
    presence : float
        Fraction of the window in which the oscillation is present: the span
        ``present_from_s .. present_to_s`` over the window length.
    present_from_s, present_to_s : float or None
        Where the oscillation is present, in seconds from the first sample:
        the longest stretch where the Hilbert envelope of the band-passed
        component stands above the background (see :func:`_presence`).  None
        when not measured.
    method : str
        What found it: ``"acf_regularity"`` (the whole window) or
        ``"segment_acf_regularity"`` (only segments of it, an intermittent
        oscillation or one hidden by a drift).
    """

    period_s: float
    frequency_hz: float
    regularity: float
    amplitude: float
    power_fraction: float
    presence: float = 1.0
    present_from_s: float | None = None
    present_to_s: float | None = None
    method: str = "acf_regularity"


@dataclass(frozen=True)
class MethodResult:
    """Verdict of one detection method.

    Attributes
    ----------
    method : str
        ``"spectral_peak"``, ``"acf_regularity"`` (Thornhill et al. 2003) or
        ``"iae"`` (Hagglund 1995).
    detected : bool
        Whether this method alone indicates an oscillation.
    period_s : float or None
        Period the statistic refers to (None if the method could not run).
    statistic : float
        ``spectral_peak``: the largest peak-to-background density ratio of a
        candidate band; ``acf_regularity``: the largest regularity ``r`` of a
        prominent band; ``iae``: the number of half cycles whose IAE exceeded
        ``IAE_lim``.
    threshold : float
        The value ``statistic`` must reach (prominence) or exceed (``r``,
        IAE count): ``min_prominence``, ``regularity_threshold`` and the
        window-scaled ``n_lim``.
    note : str
        Short human-readable explanation.
    """

    method: str
    detected: bool
    period_s: float | None
    statistic: float
    threshold: float
    note: str


@dataclass(frozen=True)
class OscillationReport:
    """Result of :func:`detect_oscillations`.

    Attributes
    ----------
    detected : bool
        True if at least one band is both a prominent spectral peak and
        regular (``r > 1``); see :func:`detect_oscillations`.
    oscillations : tuple of Oscillation
        All significant oscillations: those found in the whole window first,
        then those found only in segments of it, each strongest (largest
        power) first.
    methods : dict of str to MethodResult
        Per-method verdicts, keys ``"spectral_peak"``, ``"acf_regularity"``
        and ``"iae"``.
    """

    detected: bool
    oscillations: tuple[Oscillation, ...]
    methods: dict[str, MethodResult] = field(default_factory=dict)

    @property
    def dominant(self) -> Oscillation | None:
        """The strongest oscillation, or None."""
        return self.oscillations[0] if self.oscillations else None


@dataclass(frozen=True)
class LoopOscillation:
    """Result of :func:`detect_loop_oscillation` for one control loop.

    Attributes
    ----------
    detected : bool
        True if OP or PV oscillates.
    period_s : float or None
        Period of the loop oscillation (mean of OP and PV when both agree).
    regularity : float or None
        Largest regularity of the matched oscillation over OP and PV.
    amplitude_op, amplitude_pv : float or None
        Amplitude of the oscillation at ``period_s`` in OP / PV (band-passed
        half peak-to-peak, see :class:`Oscillation`); None where the signal is
        missing or nothing was detected.
    periods_consistent : bool or None
        True if OP and PV both oscillate with matching periods (see
        :func:`detect_loop_oscillation`), False if both oscillate but at
        different periods, None if at most one signal oscillates.
    op, pv : OscillationReport or None
        Per-signal reports (None where the signal is missing).
    """

    detected: bool
    period_s: float | None
    regularity: float | None
    amplitude_op: float | None
    amplitude_pv: float | None
    periods_consistent: bool | None
    op: OscillationReport | None
    pv: OscillationReport | None


# ----------------------------------------------------------------------------
# spectral machinery


def _bandpass_gain(f: FloatArray, fc: float, band_ratio: float, order: int) -> FloatArray:
    """Squared magnitude of an analogue Butterworth band-pass centred at ``fc``.

    ``|H|^2 = 1 / (1 + ((f/fc - fc/f) / B)^(2 order))`` with ``B = q - 1/q``, so
    the half-power edges lie at ``fc/q`` and ``fc q`` (``q = band_ratio``).
    Multiplying the DFT by this squared magnitude is the zero-phase
    forward-backward (``filtfilt``) filter; the gain is 1 at ``fc``.
    """
    bw = band_ratio - 1.0 / band_ratio
    with np.errstate(divide="ignore", over="ignore"):
        w = (f / fc - fc / f) / bw
        h2 = 1.0 / (1.0 + w ** (2 * order))  # 0 at f = 0
    return np.asarray(h2, dtype=np.float64)


@dataclass(frozen=True)
class _Bank:
    """The part of :func:`_filterbank` that depends only on the channels' frequencies."""

    bins: NDArray[np.int64]  # fine bin of each channel that falls in one
    in_bins: NDArray[np.bool_]  # which channels do (of ``f[1:]``)
    n_bins: int
    occupied: NDArray[np.bool_]  # bins holding a channel
    gain: FloatArray  # filter gain, band x occupied bin
    weight: FloatArray  # each band's gain summed over the channels


@lru_cache(maxsize=64)
def _bank(nfft: int, centres: tuple[float, ...], band_ratio: float, order: int) -> _Bank:
    """The fine log-spaced bins of the channels of an ``nfft``-point transform and the
    gains of the bands at ``centres`` over them (cached: the segments of a window,
    and the windows of a loop, share their lengths)."""
    f = (np.arange(nfft // 2 + 1, dtype=np.float64) / nfft)[1:]
    fc = np.array(centres)
    lo = float(fc[0]) / (4.0 * band_ratio)
    hi = 0.5 + 1e-12
    nb = max(int(np.ceil(np.log2(hi / lo) * 32)), 8)
    edges = lo * (hi / lo) ** (np.arange(nb + 1) / nb)
    idx = np.searchsorted(edges, f, side="right") - 1
    ok = (idx >= 0) & (idx < nb)
    cb = np.bincount(idx[ok], minlength=nb).astype(np.float64)
    fsum = np.bincount(idx[ok], weights=f[ok], minlength=nb)
    has = cb > 0
    fb = fsum[has] / cb[has]
    bw = band_ratio - 1.0 / band_ratio
    w2 = np.square((fb[None, :] / fc[:, None] - fc[:, None] / fb[None, :]) / bw)
    g = 1.0 / (1.0 + w2 if order == 1 else 1.0 + w2**order)
    bank = _Bank(idx[ok], ok, nb, has, g, g @ cb[has])
    for array in (bank.bins, bank.in_bins, bank.occupied, bank.gain, bank.weight):
        array.setflags(write=False)  # shared by every caller
    return bank


def _filterbank(
    spec: Spectrum, centres: FloatArray, band_ratio: float, order: int
) -> tuple[FloatArray, FloatArray]:
    """Power fraction and mean spectral density of each band of a constant-Q bank.

    The periodogram channels are first summed into fine log-spaced bins so the
    cost does not grow with the window length (:func:`_bank`).  The density is
    normalised by the filter's gain summed over the channels that exist, so
    bands that reach past 0 or the Nyquist frequency are not biased.
    """
    bank = _bank(spec.nfft, tuple(centres.tolist()), band_ratio, order)
    P = spec.P[1:]
    pb = np.bincount(bank.bins, weights=P[bank.in_bins], minlength=bank.n_bins)
    power = bank.gain @ pb[bank.occupied]
    weight = bank.weight
    frac = power / spec.total
    dens = np.where(weight > 0, power / np.where(weight > 0, weight, 1.0), 0.0)
    return np.asarray(frac, dtype=np.float64), np.asarray(dens, dtype=np.float64)


def _acf_regularity(
    spec: Spectrum, f_lo: float, f_hi: float, n_intervals: int
) -> tuple[float, float, int]:
    """Period (samples), regularity and number of intervals from the ACF.

    Thornhill et al. (2003): ``Tp_i = 2 dt_i``, ``r = mean(Tp_i) / (3 std(Tp_i))``.
    The signal is band-passed by an ideal zero-phase frequency-domain filter
    that zeroes every DFT channel outside ``[f_lo, f_hi]``; the ACF of the
    filtered signal is then
    ``IFFT(|X|^2 on the band)`` (Wiener-Khinchin, zero padding to ``>= 2N``
    gives the ordinary biased ACF).  The first interval, from lag 0 to the
    first zero crossing, is a quarter period and is not used; the next
    ``n_intervals`` intervals give ``Tp_i = 2 dt_i``.  An ideal band keeps
    band-limited noise from looking regular: its ACF envelope changes sign
    every ``1 / (f_hi - f_lo)`` lags, which breaks the zero-crossing pattern,
    whereas a sustained oscillation keeps the crossings evenly spaced.
    """
    band = (spec.f >= f_lo) & (spec.f <= f_hi)
    acf = sfft.irfft(np.where(band, spec.P, 0.0), spec.nfft)[: spec.n]
    zc = zero_crossings(acf)[: n_intervals + 1]
    if zc.size < 4:
        return float("nan"), 0.0, max(zc.size - 1, 0)
    tp = 2.0 * np.diff(zc)
    mean = float(tp.mean())
    sd = float(tp.std(ddof=1))
    r = REGULARITY_CAP if 3.0 * sd * REGULARITY_CAP <= mean else mean / (3.0 * sd)
    return mean, r, int(tp.size)


def bandpass(
    x: ArrayLike, period_samples: float, *, band_ratio: float = 1.5, order: int = 2
) -> FloatArray:
    """Zero-phase Butterworth band-pass of ``x`` around one period.

    The mean and linear trend are removed, then the DFT is multiplied by the
    squared magnitude of :func:`_bandpass_gain` (half-power edges at
    ``fc / band_ratio`` and ``fc * band_ratio``, ``fc = 1 / period_samples``):
    the forward-backward filter, with no phase shift, so that the shapes and
    the OP-PV phase that stiction methods look at are kept.

    Examples
    --------
    >>> k = np.arange(2000)
    >>> y = bandpass(np.sin(2 * np.pi * k / 50) + 0.01 * k, 50)
    >>> round(float(np.max(np.abs(y[200:-200]))), 2)
    1.0

    Within :func:`analytics.signals.shared_results` it is computed once
    (:func:`~analytics.signals.shared`): the methods of one diagnosis
    band-pass the same OP and PV about the same period (the
    cross-correlation, the shape rules, curve fitting, the ellipse of the
    battery and of the diagnosis), a millisecond each on 10,000 samples.
    """
    return shared(_bandpass, np.asarray(x, dtype=np.float64), float(period_samples),
                  float(band_ratio), int(order))


def _bandpass(x: FloatArray, period_samples: float, band_ratio: float, order: int) -> FloatArray:
    """:func:`bandpass`, computed."""
    spec = spectrum(detrend(x), pad=True)
    gain = _bandpass_gain(spec.f, 1.0 / period_samples, band_ratio, order)
    return np.asarray(sfft.irfft(spec.X * gain, spec.nfft)[: spec.n], dtype=np.float64)


def _cycle_amplitude(y: FloatArray) -> float:
    """Median half peak-to-peak amplitude over the complete cycles of ``y``."""
    s = np.signbit(y)
    up = np.flatnonzero(s[:-1] & ~s[1:]) + 1  # negative -> non-negative
    if up.size >= 2:
        # Segment k runs from up[k] to up[k+1]; the last reduceat segment runs
        # to the end of the array (an incomplete cycle) and is dropped.
        mx = np.maximum.reduceat(y, up)[:-1]
        mn = np.minimum.reduceat(y, up)[:-1]
        return float(np.median(0.5 * (mx - mn)))
    return float(np.sqrt(2.0) * np.std(y))


def _measure(spec: Spectrum, period: float, band_ratio: float, order: int) -> tuple[float, float]:
    """Amplitude and power fraction of the component at ``period`` (samples).

    The component is extracted with the zero-phase Butterworth band-pass of
    :func:`_bandpass_gain` centred on ``1 / period``.
    """
    gain = _bandpass_gain(spec.f, 1.0 / period, band_ratio, order)
    y = np.asarray(sfft.irfft(spec.X * gain, spec.nfft)[: spec.n], dtype=np.float64)
    amp = _cycle_amplitude(y)
    pf = float((spec.P * gain).sum() / spec.total) if spec.total > 0 else 0.0
    return amp, pf


# ----------------------------------------------------------------------------
# Hagglund's IAE method


def _iae_method(
    x: FloatArray,
    ts: float,
    period: float | None,
    amplitude: float,
    supervision_periods: float,
    n_lim: float,
) -> MethodResult:
    """Hagglund (1995) load-disturbance count, offline version.

    ``IAE_i = integral |x| dt`` between successive zero crossings of the
    detrended signal; a half cycle with ``IAE_i > IAE_lim = 2 a / omega``
    (Hagglund 1995, with ``omega = 2 pi / Tp`` in place of ``omega_u``) is a load disturbance.  The
    count over the window is compared with ``n_lim`` per supervision time
    ``T_sup`` scaled to the window length.
    """
    if period is None or not np.isfinite(period):
        return MethodResult("iae", False, None, 0.0, float("nan"), "no dominant period to test")
    omega = 2.0 * np.pi / (period * ts)
    iae_lim = 2.0 * amplitude / omega
    zc = np.flatnonzero(np.signbit(x[1:]) != np.signbit(x[:-1])) + 1
    if zc.size < 2:
        return MethodResult(
            "iae", False, period * ts, 0.0, float("nan"), "fewer than two zero crossings"
        )
    iae = np.add.reduceat(np.abs(x), zc)[:-1] * ts  # complete half cycles only
    count = int(np.count_nonzero(iae > iae_lim))
    limit = n_lim * (x.size * ts) / (supervision_periods * period * ts)
    return MethodResult(
        "iae",
        count > limit,
        period * ts,
        float(count),
        float(limit),
        f"{count} of {iae.size} half cycles exceed IAE_lim = {iae_lim:.4g} "
        f"(a = {amplitude:.4g}, Tp = {period * ts:.4g} s); n_lim scaled to the "
        f"window = {limit:.1f}",
    )


# ----------------------------------------------------------------------------
# one window: Thornhill et al. (2003) with automated band selection


@dataclass(frozen=True)
class _Settings:
    """Parameters of :func:`_scan_window` (see :func:`detect_oscillations`)."""

    min_period_samples: float
    max_period_fraction: float
    regularity_threshold: float
    min_prominence: float
    min_power_fraction: float
    max_oscillations: int
    band_ratio: float
    acf_band_ratio: float
    filter_order: int
    n_intervals: int


@dataclass(frozen=True)
class _Scan:
    """Regular prominent bands of one window and the best statistics seen."""

    found: tuple[tuple[float, float, float], ...]  # (power fraction, period, r)
    best_prominence: float = 0.0
    best_prominence_period: float | None = None
    best_regularity: float = 0.0
    best_regularity_period: float | None = None


def _scan_window(x: FloatArray, s: _Settings, spec: Spectrum | None = None) -> _Scan:
    """Steps 1-4 of :func:`detect_oscillations` on one window.

    The power fraction that gates a band is taken over the variance at the
    searched frequencies (``f >= 1 / (max_period_fraction N)``): a drift
    slower than the longest searched period is not an oscillation, and must
    not hide a small regular one riding on it.  ``spec`` is the padded
    spectrum of ``x`` detrended, when the caller has it (the whole window's).
    """
    n = x.size
    if spec is None:
        spec = spectrum(detrend(x), pad=True)
    if spec.total <= 0:
        return _Scan(())
    f_hi = min(1.0 / s.min_period_samples, 0.5 / s.band_ratio)
    f_lo = 1.0 / (s.max_period_fraction * n)
    if f_hi <= f_lo:
        return _Scan(())
    # About 16 centres per octave, laid from the period GRID_REFERENCE_FRACTION N
    # up and continued with the same spacing down to f_lo, so that the centres
    # (and the periods measured from them) do not move when the search is
    # extended to slower periods.
    f_ref = max(f_lo, 1.0 / (GRID_REFERENCE_FRACTION * n))
    if f_hi <= f_ref:
        f_ref = f_lo
    n_c = max(int(np.ceil(np.log2(f_hi / f_ref) * 16)), 2)
    step = np.log2(f_hi / f_ref) / n_c  # octaves per grid step
    flank = max(round(float(1.0 / step)), 1)  # grid steps in one octave
    slow = int(np.ceil(np.log2(f_ref / f_lo) / step - 1e-9))  # steps below f_ref
    # The grid extends one octave beyond the search range for the flanks.
    k = np.arange(-flank - slow, n_c + flank + 1)
    grid = f_ref * (f_hi / f_ref) ** (k / n_c)
    frac, dens = _filterbank(spec, grid, s.band_ratio, s.filter_order)
    searched = float(spec.P[spec.f >= f_lo / s.band_ratio].sum())
    frac_searched = frac * (spec.total / searched) if searched > 0 else frac
    inner = np.arange(flank, flank + slow + n_c + 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        prom_all = dens[inner] / np.sqrt(dens[inner - flank] * dens[inner + flank])
    prom = np.nan_to_num(prom_all, nan=0.0, posinf=REGULARITY_CAP)
    f_in = frac_searched[inner]
    # Candidates are the local maxima of the prominence (the peak-to-background
    # contrast), which locates a peak without the bias of the background slope
    # (band power grows with fc for white noise, density falls for red noise).
    is_max = np.zeros(inner.size, dtype=bool)
    is_max[1:-1] = (prom[1:-1] > prom[:-2]) & (prom[1:-1] >= prom[2:])
    peaks = np.flatnonzero(is_max & (f_in >= s.min_power_fraction))
    peaks = peaks[np.argsort(f_in[peaks])[::-1]][: 3 * s.max_oscillations]
    found: list[tuple[float, float, float]] = []
    best_prom, best_prom_period = 0.0, None
    best_r, best_r_period = 0.0, None
    for j in peaks:
        fc = float(grid[inner[j]])
        if prom[j] > best_prom:
            best_prom, best_prom_period = float(prom[j]), 1.0 / fc
        if prom[j] < max(s.min_prominence, _significant_prominence(fc * n, s.band_ratio)):
            continue
        period, r, _ = _acf_regularity(
            spec, fc / s.acf_band_ratio, fc * s.acf_band_ratio, s.n_intervals
        )
        if not np.isfinite(period) or not fc / s.band_ratio <= 1.0 / period <= fc * s.band_ratio:
            continue
        if r > best_r:
            best_r, best_r_period = r, period
        if r > s.regularity_threshold:
            found.append((float(f_in[j]), period, r))
    return _Scan(tuple(found), best_prom, best_prom_period, best_r, best_r_period)


def _significant_prominence(cycles: float, band_ratio: float, level: float = 0.99) -> float:
    """Prominence that smooth (coloured) noise exceeds with probability ``1 - level``.

    A band holding ``cycles`` cycles of the window spans about
    ``(q - 1/q) cycles`` independent periodogram ordinates (``q`` =
    ``band_ratio``), each a chi-square variable with 2 degrees of freedom
    (Priestley, *Spectral Analysis and Time Series*, 1981, sec. 6.1); the
    flank bands one octave below and above span half and twice as many.  The
    ratio of the band's mean density to the flanks' is then ``F``-distributed
    under a smooth spectrum, and the quantile of that ``F`` is the prominence a
    peak must reach.  It only matters for slow bands, with few ordinates
    (random walks and drifts look like a few slow cycles); with more than
    about ten cycles it drops below the default ``min_prominence``.
    """
    width = round(max((band_ratio - 1.0 / band_ratio) * cycles, 1.0), 2)
    return _f_quantile(level, 2.0 * width, 2.0 * 2.5 * width)


@lru_cache(maxsize=4096)
def _f_quantile(level: float, dfn: float, dfd: float) -> float:
    """Quantile of the ``F(dfn, dfd)`` distribution (cached: slow bands recur)."""
    return float(f_dist.ppf(level, dfn, dfd))


# ----------------------------------------------------------------------------
# segments and presence


def _segments(n: int, min_samples: int, levels: int) -> list[tuple[int, int]]:
    """The window, its halves, quarters, ... (``levels`` of them), 75 % overlap.

    Level ``m`` has segments of ``n / 2^m`` samples starting every
    ``n / 2^(m+1)``; levels whose segments would be shorter than
    ``min_samples`` are left out.
    """
    spans = [(0, n)]
    for m in range(1, levels):
        parts = 2**m
        if n / parts < min_samples:
            break
        spans += [
            (round(i * n / (4 * parts)), round((i + 4) * n / (4 * parts)))
            for i in range(4 * parts - 3)
        ]
    return spans


def _corroborated_stretch(spans: list[tuple[int, int]], n: int) -> int:
    """Length of the longest stretch where segment detections corroborate.

    The window itself (``(0, n)`` in ``spans``) is its own evidence.  Segment
    detections are merged into contiguous stretches; a stretch counts only if
    two of its detections come from windows at different positions (neither
    contains the other), so that one lucky segment, or a segment and a
    sub-segment of the same data, do not make an oscillation.
    """
    if (0, n) in spans:
        return n
    best = 0
    ordered = sorted(spans)
    group = [ordered[0]]
    for span in [*ordered[1:], None]:
        if span is not None and span[0] <= max(b for _, b in group):
            group.append(span)
            continue
        independent = any(
            (a1 < a2 and b1 < b2) or (a2 < a1 and b2 < b1)
            for i, (a1, b1) in enumerate(group)
            for a2, b2 in group[i + 1 :]
        )
        if independent:
            best = max(best, max(b for _, b in group) - group[0][0])
        if span is not None:
            group = [span]
    return best


@dataclass
class _Cluster:
    """Detections of one oscillation in the window and its segments."""

    period: float
    regularity: float
    window_samples: int
    spans: list[tuple[int, int]]


def _envelope(spec: Spectrum, gain: FloatArray) -> FloatArray:
    """Hilbert envelope of the signal filtered by the zero-phase ``gain``.

    The analytic signal is the inverse DFT of the band-passed spectrum with
    the negative frequencies removed (Gabor 1946; Feldman, *Hilbert Transform
    Applications in Mechanical Vibration*, Wiley 2011, ch. 2), so the envelope
    costs one complex FFT.
    """
    # The band-passed signal holds next to no power above the last channel where
    # the gain exceeds 1e-4 (-40 dB), so the analytic signal is computed on a coarser
    # time grid of twice that many points and interpolated (the envelope is
    # smooth on the scale of the period).
    used = int(np.flatnonzero(gain > 1e-4 * gain.max())[-1]) + 1 if gain.max() > 0 else 1
    size = min(sfft.next_fast_len(4 * used), spec.nfft)
    full = np.zeros(size, dtype=np.complex128)
    top = min(used, size // 2 + 1)
    full[:top] = spec.X[:top] * gain[:top]
    full[1:top] *= 2.0
    if size == spec.nfft and spec.nfft % 2 == 0 and top == spec.X.size:
        full[top - 1] /= 2.0  # the Nyquist channel is not doubled
    z = np.abs(sfft.ifft(full)) * (size / spec.nfft)
    t = np.arange(spec.n, dtype=np.float64)
    return np.asarray(np.interp(t, np.arange(size) * (spec.nfft / size), z), dtype=np.float64)


def _presence(spec: Spectrum, gain: FloatArray, period: float) -> tuple[FloatArray, int, int]:
    """Where the component passed by ``gain`` (period ``period`` samples) is present.

    Returns the band-passed component and the first and last (exclusive)
    sample of the longest stretch where it is present.  The envelope of
    band-limited Gaussian noise is Rayleigh distributed, so its 90th and 10th
    percentiles stand :data:`RAYLEIGH_SPREAD` apart; an envelope that varies
    less shows no sign of the oscillation stopping, and it is present
    throughout.  Otherwise it is present where the Hilbert envelope exceeds
    the geometric mean of the two percentiles (halfway, on a log scale,
    between the background and the oscillation); gaps shorter than three
    periods are closed.
    """
    y = np.asarray(sfft.irfft(spec.X * gain, spec.nfft)[: spec.n], dtype=np.float64)
    envelope = _envelope(spec, gain)
    low, high = (float(q) for q in np.quantile(envelope, [0.1, 0.9]))
    if high <= RAYLEIGH_SPREAD * low:
        return y, 0, spec.n
    on = envelope >= np.sqrt(low * high)
    edges = np.flatnonzero(np.diff(np.concatenate(([0], on.view(np.int8), [0]))))
    runs: list[list[int]] = []
    for a, b in zip(edges[0::2].tolist(), edges[1::2].tolist(), strict=True):
        if runs and a - runs[-1][1] < 3.0 * period:
            runs[-1][1] = b
        else:
            runs.append([a, b])
    first, last = max(runs, key=lambda r: r[1] - r[0])
    return y, first, last


# ----------------------------------------------------------------------------
# public API


def detect_oscillations(
    x: ArrayLike,
    ts: float,
    *,
    min_period_samples: float = 6.0,
    max_period_fraction: float = 0.5,
    regularity_threshold: float = 1.0,
    min_prominence: float = 2.5,
    min_power_fraction: float = 0.05,
    max_oscillations: int = 4,
    band_ratio: float = 1.5,
    acf_band_ratio: float = 2.0,
    filter_order: int = 2,
    n_intervals: int = 10,
    segment_levels: int = 3,
    min_segment_samples: int = 250,
    min_presence: float = 0.5,
    segment_regularity_threshold: float = 2.0,
    iae_amplitude: float | None = None,
    iae_supervision_periods: float = 25.0,
    iae_n_lim: float = 10.0,
) -> OscillationReport:
    """Detect and characterise the oscillations in one signal.

    Algorithm (Thornhill, Huang & Zhang 2003, with automated band selection,
    run on the window and on its segments):

    1. Remove mean and linear trend; one zero-padded FFT gives the
       periodogram.
    2. A constant-Q bank of zero-phase Butterworth band-passes (edges
       ``fc / band_ratio .. fc * band_ratio``, 16 centres per octave between
       ``1 / (max_period_fraction N)`` and ``1 / min_period_samples``) gives
       each band's power fraction (of the variance at the searched
       frequencies, so a slow drift does not hide an oscillation) and mean
       spectral density.
    3. The prominence of a band is its density divided by the geometric mean
       of the densities one octave below and above.  Local maxima of the
       prominence holding at least ``min_power_fraction`` of the variance are
       the candidates, taken in order of power; a candidate must reach
       ``min_prominence`` and, if the window holds few of its cycles, the 1 %
       significance level of a smooth spectrum (:func:`_significant_prominence`).
       This gate keeps coloured noise (AR(1), random walk) out: the ACF of
       *any* band-passed signal oscillates near lag zero, so regularity alone
       is not enough.
    4. The ACF of the signal band-passed (ideal band, zero phase) to
       ``fc / acf_band_ratio .. fc * acf_band_ratio`` gives the zero-crossing
       intervals ``dt_i``, ``Tp = mean(2 dt_i)`` and
       ``r = Tp / (3 std(2 dt_i))``; ``r > regularity_threshold`` and ``1/Tp``
       inside the candidate's band make it an oscillation.
    5. Sliding-window analysis, when the whole window shows no oscillation:
       steps 1-4 also run on the halves, quarters, ... (``segment_levels``
       levels, 75 % overlap, each segment detrended on its own) so that an
       oscillation present in only part of the window, or riding on a
       drifting mean, is not diluted by the rest of the window (the
       spectrogram argument of Thornhill et al. 2003, sec. 5, and of
       Hägglund 1995, who supervises a moving time ``T_sup``). Detections
       with the same period (within 15 %) are one oscillation. One found in
       the whole window is reported; one found only in segments is reported
       when segments at different positions (neither inside the other)
       detect it over one contiguous stretch of at least ``min_presence`` of
       the window, so a short burst or one lucky segment is not a loop
       oscillation.
    6. Oscillations at a harmonic of a stronger one (square or triangular
       stiction cycles have odd harmonics) are merged; the rest are reported
       with the amplitude of the band-passed component and, from its Hilbert
       envelope, the part of the window where it is present: those of the
       whole window first, then those of segments only, each strongest
       first.
    7. Hagglund's (1995) IAE test runs on the detrended signal with the
       dominant period and is reported in ``methods["iae"]``.

    Parameters
    ----------
    x : array_like
        One uniformly sampled signal (OP or PV).
    ts : float
        Sampling interval in seconds.
    min_period_samples : float, optional
        Shortest period searched, in samples.
    max_period_fraction : float, optional
        Longest period searched, as a fraction of the window (or segment)
        length: 0.5 admits two cycles (three ACF zero-crossing intervals).
    regularity_threshold : float, optional
        ``r`` must exceed this (1 in Thornhill et al. 2003).
    min_prominence : float, optional
        Spectral peak-to-background density ratio a band must reach.  2.5 was
        chosen on the 49 loops of the Jelali & Huang benchmark (it is the
        choice of every leave-one-industry-out fold; 3 misses loops whose
        irregular cycles stand at 2.6-2.9) -- see ``benchmarks/oscillation.py``.
    min_power_fraction : float, optional
        Fraction of the variance at the searched frequencies a band must hold.
    max_oscillations : int, optional
        At most this many oscillations are reported.
    band_ratio : float, optional
        Half-power edges of the Butterworth bank and of the amplitude
        filter at ``fc / band_ratio`` and ``fc * band_ratio``; 1.5 excludes
        the third harmonic of a square wave.
    acf_band_ratio : float, optional
        Edges of the ideal band-pass used for the ACF.
    filter_order : int, optional
        Order of the Butterworth prototype (applied forward-backward).
    n_intervals : int, optional
        Number of ACF zero-crossing intervals in the regularity.
    segment_levels : int, optional
        Levels of the sliding-window analysis: 1 is the window alone, 2 adds
        its halves, 3 its quarters.
    min_segment_samples : int, optional
        Segments shorter than this are not analysed.
    min_presence : float, optional
        Fraction of the window an oscillation's detections must cover.
    segment_regularity_threshold : float, optional
        ``r`` an oscillation found only in segments must exceed (measured in
        the longest segment that found it).  Twice Thornhill's limit: up to
        18 windows are tested instead of one, and noise with a spectral hump
        (an underdamped loop driven by noise) passes ``r > 1`` in one or two
        of them.
    iae_amplitude : float, optional
        Hagglund's acceptable amplitude ``a``; default 1 % of the signal span
        ``max(x) - min(x)``.
    iae_supervision_periods : float, optional
        Supervision time ``T_sup`` in periods.  Hagglund uses
        ``T_sup = 50 T_i``; with ``T_i ~ Tp / 2`` this is 25 periods.
    iae_n_lim : float, optional
        Hagglund's count limit per supervision time (10).

    Returns
    -------
    OscillationReport
        ``detected`` is True when at least one oscillation passes steps 3-5;
        ``methods`` holds ``"spectral_peak"`` (statistic: largest prominence of
        a candidate band in the whole window), ``"acf_regularity"`` (largest
        ``r`` of a prominent band in the window or a segment) and ``"iae"``
        (Hagglund's count; corroboration only: with ``a`` relative to the data
        span it also counts large irregular disturbances, so it does not
        decide).

    Raises
    ------
    DataError
        If ``x`` is not 1-D, contains NaN/inf, has fewer than
        :data:`MIN_SAMPLES` samples, or ``ts`` is not positive.

    References
    ----------
    N. F. Thornhill, B. Huang, H. Zhang, J. Process Control 13 (2003) 91-100.
    T. Hagglund, Control Eng. Practice 3 (1995) 1543-1551.
    """
    xa = np.asarray(x, dtype=np.float64)
    if xa.ndim != 1:
        raise DataError(f"signal must be one-dimensional, got shape {xa.shape}")
    if not (np.isfinite(ts) and ts > 0):
        raise DataError(f"sampling time ts must be positive and finite, got {ts!r}")
    if xa.size < MIN_SAMPLES:
        raise DataError(f"signal has {xa.size} samples, at least {MIN_SAMPLES} are needed")
    if not np.all(np.isfinite(xa)):
        bad = int(np.count_nonzero(~np.isfinite(xa)))
        raise DataError(
            f"signal has {bad} NaN/inf samples; screen it with analytics.quality.assess_quality"
        )
    if min_period_samples < 2 or not 0 < max_period_fraction <= 1:
        raise DataError("need min_period_samples >= 2 and 0 < max_period_fraction <= 1")
    n = xa.size
    span = float(xa.max() - xa.min())
    xd = detrend(xa)
    spec = spectrum(xd, pad=True)

    if spec.total <= 0 or span == 0:
        note = "signal is constant after detrending"
        return OscillationReport(
            False,
            (),
            {
                "spectral_peak": MethodResult(
                    "spectral_peak", False, None, 0.0, min_prominence, note
                ),
                "acf_regularity": MethodResult(
                    "acf_regularity", False, None, 0.0, regularity_threshold, note
                ),
                "iae": MethodResult("iae", False, None, 0.0, float("nan"), note),
            },
        )

    settings = _Settings(
        min_period_samples,
        max_period_fraction,
        regularity_threshold,
        min_prominence,
        min_power_fraction,
        max_oscillations,
        band_ratio,
        acf_band_ratio,
        filter_order,
        n_intervals,
    )
    clusters: list[_Cluster] = []
    whole: _Scan | None = None
    best_r, best_r_period = 0.0, None
    for a, b in _segments(n, min_segment_samples, segment_levels):
        scan = _scan_window(xa[a:b], settings, spec if b - a == n else None)
        if whole is None:  # the window itself comes first
            whole = scan
        if scan.best_regularity > best_r:
            best_r, best_r_period = scan.best_regularity, scan.best_regularity_period
        for _, period, r in sorted(scan.found, reverse=True):  # strongest first
            match = next((c for c in clusters if _same_or_harmonic(period, c.period)), None)
            if match is None:
                clusters.append(_Cluster(period, r, b - a, [(a, b)]))
            elif _same_or_harmonic(period, match.period, harmonics=False):
                match.spans.append((a, b))
                if b - a > match.window_samples:  # the longest window measures best
                    match.period, match.regularity, match.window_samples = period, r, b - a
        if whole.found:
            break  # the segments look for what the whole window misses; it missed nothing
    assert whole is not None

    oscillations: list[Oscillation] = []
    for c in clusters:
        in_window = c.window_samples == n
        if not in_window and c.regularity <= segment_regularity_threshold:
            continue
        if _corroborated_stretch(c.spans, n) < int(min_presence * n):
            continue
        gain = _bandpass_gain(spec.f, 1.0 / c.period, band_ratio, filter_order)
        y, first, last = _presence(spec, gain, c.period)
        if not in_window and last - first < int(min_presence * n):
            continue  # a burst that the segments holding it made look longer
        oscillations.append(
            Oscillation(
                period_s=c.period * ts,
                frequency_hz=1.0 / (c.period * ts),
                regularity=c.regularity,
                amplitude=_cycle_amplitude(y[first:last]),
                power_fraction=float((spec.P * gain).sum() / spec.total),
                presence=(last - first) / n,
                present_from_s=first * ts,
                present_to_s=last * ts,
                method="acf_regularity" if in_window else "segment_acf_regularity",
            )
        )
    # Oscillations of the whole window first: one seen only in segments is secondary.
    oscillations.sort(key=lambda o: (o.method != "acf_regularity", -o.power_fraction))
    oscillations = oscillations[:max_oscillations]
    detected = bool(oscillations)

    spectral = MethodResult(
        "spectral_peak",
        whole.best_prominence >= min_prominence,
        None if whole.best_prominence_period is None else whole.best_prominence_period * ts,
        whole.best_prominence,
        min_prominence,
        f"largest peak-to-background density ratio {whole.best_prominence:.2f} "
        f"(needs >= {min_prominence:g})",
    )
    if detected:
        acf_note = f"{len(oscillations)} regular oscillation(s), largest r = {best_r:.2f}"
    else:
        acf_note = (
            f"no prominent band with r > {regularity_threshold:g} over at least "
            f"{min_presence:.0%} of the window (largest r = {best_r:.2f})"
        )
    acf = MethodResult(
        "acf_regularity",
        detected,
        None if best_r_period is None else best_r_period * ts,
        best_r,
        regularity_threshold,
        acf_note,
    )
    if oscillations:
        ref_period: float | None = oscillations[0].period_s / ts
    elif best_r_period is not None:
        ref_period = best_r_period
    else:
        ref_period = whole.best_prominence_period
    a_iae = iae_amplitude if iae_amplitude is not None else 0.01 * span
    iae = _iae_method(xd, ts, ref_period, a_iae, iae_supervision_periods, iae_n_lim)
    return OscillationReport(
        detected,
        tuple(oscillations),
        {"spectral_peak": spectral, "acf_regularity": acf, "iae": iae},
    )


def _same_or_harmonic(period: float, stronger: float, *, harmonics: bool = True) -> bool:
    """True if ``period`` is the stronger oscillation or one of its harmonics.

    Same oscillation: periods within 15 %.  Harmonic: ``stronger / period``
    within 5 % of an integer ``k`` in 2..10 (stiction limit cycles are
    square- or triangle-like and carry odd, sometimes even, harmonics).
    """
    ratio = stronger / period
    k = round(ratio)
    if k == 1:
        return abs(ratio - 1.0) <= 0.15
    return harmonics and 2 <= k <= 10 and abs(ratio - k) <= 0.05 * k


def detect_loop_oscillation(
    op: ArrayLike | None,
    pv: ArrayLike | None,
    ts: float,
    *,
    period_tolerance: float = 0.15,
    **kwargs: Any,
) -> LoopOscillation:
    """Detect a loop oscillation from OP and/or PV.

    In a closed loop OP and PV oscillate at the same (loop) frequency, so
    either signal alone can reveal it; when both are available their periods
    should agree.

    Parameters
    ----------
    op, pv : array_like or None
        Controller output and process variable, same length; either may be
        None.
    ts : float
        Sampling interval in seconds.
    period_tolerance : float, optional
        Smallest relative difference allowed between the OP and PV periods of
        one oscillation.  The tolerance actually used is
        ``max(period_tolerance, 1 / (3 r))`` with ``r`` the smaller of the two
        regularities: ``Tp / (3 r)`` is the cycle-to-cycle standard deviation
        of the period implied by the regularity of Thornhill et al. (2003), so irregular
        oscillations are allowed a proportionally wider match.
    **kwargs
        Passed on to :func:`detect_oscillations`.

    Returns
    -------
    LoopOscillation
        Oscillating if either signal oscillates.  When both do, the strongest
        OP/PV pair with matching periods, preferring oscillations of the whole
        window to those of segments only, is the loop oscillation (period: their
        mean; regularity: the larger; amplitudes: each signal's own).  If no
        pair matches, the more regular of the two dominant oscillations is
        reported with ``periods_consistent`` False.  If only one signal
        oscillates, the amplitude in the other is measured at the same period
        with the same band-pass.

    Raises
    ------
    DataError
        If both signals are None, their lengths differ, or as
        :func:`detect_oscillations`.
    """
    if op is None and pv is None:
        raise DataError("detect_loop_oscillation needs at least one of op and pv")
    op_a = None if op is None else np.asarray(op, dtype=np.float64)
    pv_a = None if pv is None else np.asarray(pv, dtype=np.float64)
    if op_a is not None and pv_a is not None and op_a.shape != pv_a.shape:
        raise DataError(f"op has shape {op_a.shape} but pv has shape {pv_a.shape}")
    rep_op = None if op_a is None else detect_oscillations(op_a, ts, **kwargs)
    rep_pv = None if pv_a is None else detect_oscillations(pv_a, ts, **kwargs)
    osc_op = rep_op.oscillations if rep_op is not None else ()
    osc_pv = rep_pv.oscillations if rep_pv is not None else ()

    band_ratio = float(kwargs.get("band_ratio", 1.5))
    order = int(kwargs.get("filter_order", 2))

    def amp_at(sig: FloatArray | None, period_s: float) -> float | None:
        if sig is None:
            return None
        spec = spectrum(detrend(sig), pad=True)
        if spec.total <= 0:
            return 0.0
        return _measure(spec, period_s / ts, band_ratio, order)[0]

    best: tuple[tuple[bool, float], Oscillation, Oscillation] | None = None
    for o in osc_op:
        for p in osc_pv:
            tol = max(period_tolerance, 1.0 / (3.0 * min(o.regularity, p.regularity)))
            if abs(o.period_s - p.period_s) <= tol * max(o.period_s, p.period_s):
                whole = o.method == p.method == "acf_regularity"
                score = (whole, o.power_fraction + p.power_fraction)
                if best is None or score > best[0]:
                    best = (score, o, p)
    if best is not None:
        _, o, p = best
        return LoopOscillation(
            detected=True,
            period_s=0.5 * (o.period_s + p.period_s),
            regularity=max(o.regularity, p.regularity),
            amplitude_op=o.amplitude,
            amplitude_pv=p.amplitude,
            periods_consistent=True,
            op=rep_op,
            pv=rep_pv,
        )
    if not (osc_op or osc_pv):
        return LoopOscillation(False, None, None, None, None, None, rep_op, rep_pv)
    chosen = max(list(osc_op[:1]) + list(osc_pv[:1]), key=lambda z: z.regularity)
    return LoopOscillation(
        detected=True,
        period_s=chosen.period_s,
        regularity=chosen.regularity,
        amplitude_op=amp_at(op_a, chosen.period_s),
        amplitude_pv=amp_at(pv_a, chosen.period_s),
        periods_consistent=False if (osc_op and osc_pv) else None,
        op=rep_op,
        pv=rep_pv,
    )


RAYLEIGH_ENVELOPE_CV = math.sqrt(4.0 / math.pi - 1.0)
"""Coefficient of variation of a Rayleigh variable (0.523): the envelope of a
narrow-band Gaussian process, e.g. a lightly damped loop driven by noise (Rice 1945)."""


LIMIT_CYCLE_ENVELOPE_CV = 0.5 * RAYLEIGH_ENVELOPE_CV
"""Envelope variation below which an oscillation keeps its amplitude, as a limit
cycle or a periodic forcing does: half the Rayleigh value of a noise-driven
resonance (0.26).  The sticky
reactor cooling valve of the Tennessee Eastman process gives 0.08; normal
operation of the same loop 0.45-0.55."""


def envelope_variation(x: ArrayLike, period_samples: float, *, band_ratio: float = 1.2) -> float:
    """Coefficient of variation of the envelope of the oscillation at ``period_samples``.

    The signal is band-passed around the period
    (:func:`analytics.oscillation.bandpass`), its envelope is the magnitude
    of the analytic signal (Hilbert transform), and the result is
    ``std(envelope) / mean(envelope)`` over the window without two periods
    at either end.  A limit cycle keeps its amplitude: near 0.  The envelope
    of a resonance driven by noise is Rayleigh-distributed: about
    :data:`RAYLEIGH_ENVELOPE_CV` = 0.523 (Rice 1945).

    Raises
    ------
    DataError
        If the window holds fewer than eight periods.

    Examples
    --------
    >>> k = np.arange(4000)
    >>> rng = np.random.default_rng(1)
    >>> cycle = np.sign(np.sin(2 * np.pi * k / 40)) + 0.3 * rng.standard_normal(k.size)
    >>> round(envelope_variation(cycle, 40.0), 2)
    0.03
    """
    xa = np.asarray(x, dtype=np.float64)
    if xa.size < 8 * period_samples:
        raise DataError(
            f"{xa.size / period_samples:.1f} periods in the window, the envelope needs 8"
        )
    component = bandpass(xa, period_samples, band_ratio=band_ratio)
    margin = math.ceil(2 * period_samples)
    envelope = np.abs(signal.hilbert(component))[margin:-margin]
    mean = float(envelope.mean())
    return float(envelope.std() / mean) if mean > 0 else 0.0
