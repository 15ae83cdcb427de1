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

All filtering is zero-phase and done in the frequency domain on one
zero-padded FFT of the mean- and trend-removed signal, so a 10,000-sample
window takes a few milliseconds.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import fft as sfft

from analytics.errors import DataError

__all__ = [
    "REGULARITY_CAP",
    "LoopOscillation",
    "MethodResult",
    "Oscillation",
    "OscillationReport",
    "bandpass",
    "detect_loop_oscillation",
    "detect_oscillations",
]

#: Regularity reported for (numerically) perfectly regular ACF zero crossings.
REGULARITY_CAP = 100.0
#: Fewest samples :func:`detect_oscillations` accepts.
MIN_SAMPLES = 64

FloatArray = NDArray[np.float64]


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
        units: the median over the complete cycles of ``(max - min) / 2``.
        For a sine this is its amplitude; for a square wave of amplitude
        ``A`` it is the fundamental's ``4 A / pi``.
    power_fraction : float
        Fraction of the detrended signal's variance inside the band.
    """

    period_s: float
    frequency_hz: float
    regularity: float
    amplitude: float
    power_fraction: float


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
        All significant oscillations, strongest (largest power) first.
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


@dataclass(frozen=True)
class _Spectrum:
    x: FloatArray  # detrended signal
    n: int
    nfft: int
    X: NDArray[np.complex128]  # rfft of x zero-padded to nfft (>= 2n: no wrap-around)
    P: FloatArray  # |X|^2
    f: FloatArray  # frequency of each channel, cycles per sample
    total: float  # sum(P[1:]), proportional to the variance


def _detrend(x: FloatArray) -> FloatArray:
    """Remove mean and least-squares linear trend."""
    n = x.size
    k = np.arange(n, dtype=np.float64)
    k -= k.mean()
    xc = x - x.mean()
    kk = float(np.dot(k, k))
    slope = float(np.dot(k, xc)) / kk if kk > 0 else 0.0
    return np.asarray(xc - slope * k, dtype=np.float64)


def _spectrum(x: FloatArray) -> _Spectrum:
    n = x.size
    nfft = sfft.next_fast_len(2 * n, real=True)
    X = sfft.rfft(x, nfft)
    P = X.real**2 + X.imag**2
    f = np.arange(P.size, dtype=np.float64) / nfft
    return _Spectrum(x, n, nfft, X, P, f, float(P[1:].sum()))


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


def _filterbank(
    spec: _Spectrum, centres: FloatArray, band_ratio: float, order: int
) -> tuple[FloatArray, FloatArray]:
    """Power fraction and mean spectral density of each band of a constant-Q bank.

    The periodogram channels are first summed into fine log-spaced bins so the
    cost does not grow with the window length.  The density is normalised by
    the filter's gain summed over the channels that exist, so bands that reach
    past 0 or the Nyquist frequency are not biased.
    """
    f = spec.f[1:]
    P = spec.P[1:]
    lo = float(centres[0]) / (4.0 * band_ratio)
    hi = 0.5 + 1e-12
    nb = max(int(np.ceil(np.log2(hi / lo) * 32)), 8)
    edges = lo * (hi / lo) ** (np.arange(nb + 1) / nb)
    idx = np.searchsorted(edges, f, side="right") - 1
    ok = (idx >= 0) & (idx < nb)
    pb = np.bincount(idx[ok], weights=P[ok], minlength=nb)
    cb = np.bincount(idx[ok], minlength=nb).astype(np.float64)
    fsum = np.bincount(idx[ok], weights=f[ok], minlength=nb)
    has = cb > 0
    fb = fsum[has] / cb[has]
    pb, cb = pb[has], cb[has]
    bw = band_ratio - 1.0 / band_ratio
    w2 = np.square((fb[None, :] / centres[:, None] - centres[:, None] / fb[None, :]) / bw)
    g = 1.0 / (1.0 + w2 if order == 1 else 1.0 + w2**order)
    power = g @ pb
    weight = g @ cb
    frac = power / spec.total
    dens = np.where(weight > 0, power / np.where(weight > 0, weight, 1.0), 0.0)
    return np.asarray(frac, dtype=np.float64), np.asarray(dens, dtype=np.float64)


def _zero_crossings(y: FloatArray) -> FloatArray:
    """Linearly interpolated positions of the sign changes of ``y``."""
    s = np.signbit(y)
    i = np.flatnonzero(s[1:] != s[:-1])
    y0, y1 = y[i], y[i + 1]
    return np.asarray(i + y0 / (y0 - y1), dtype=np.float64)


def _acf_regularity(
    spec: _Spectrum, f_lo: float, f_hi: float, n_intervals: int
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
    zc = _zero_crossings(acf)[: n_intervals + 1]
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
    """
    spec = _spectrum(_detrend(np.asarray(x, dtype=np.float64)))
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


def _measure(spec: _Spectrum, period: float, band_ratio: float, order: int) -> tuple[float, float]:
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
# public API


def detect_oscillations(
    x: ArrayLike,
    ts: float,
    *,
    min_period_samples: float = 6.0,
    max_period_fraction: float = 0.3,
    regularity_threshold: float = 1.0,
    min_prominence: float = 3.0,
    min_power_fraction: float = 0.05,
    max_oscillations: int = 4,
    band_ratio: float = 1.5,
    acf_band_ratio: float = 2.0,
    filter_order: int = 2,
    n_intervals: int = 10,
    iae_amplitude: float | None = None,
    iae_supervision_periods: float = 25.0,
    iae_n_lim: float = 10.0,
) -> OscillationReport:
    """Detect and characterise the oscillations in one signal.

    Algorithm (Thornhill, Huang & Zhang 2003, with automated band selection):

    1. Remove mean and linear trend; one zero-padded FFT gives the
       periodogram.
    2. A constant-Q bank of zero-phase Butterworth band-passes (edges
       ``fc / band_ratio .. fc * band_ratio``, 16 centres per octave between
       ``1 / (max_period_fraction N)`` and ``1 / min_period_samples``) gives
       each band's power fraction and mean spectral density.
    3. The prominence of a band is its density divided by the geometric mean
       of the densities one octave below and above.  Local maxima of the
       prominence holding at least ``min_power_fraction`` of the variance are
       the candidates, taken in order of power; a candidate must reach
       ``min_prominence``.  This gate keeps coloured noise (AR(1), random
       walk) out: the ACF of *any* band-passed signal oscillates near lag
       zero, so regularity alone is not enough.
    4. The ACF of the signal band-passed (ideal band, zero phase) to
       ``fc / acf_band_ratio .. fc * acf_band_ratio`` gives the zero-crossing
       intervals ``dt_i``, ``Tp = mean(2 dt_i)`` and
       ``r = Tp / (3 std(2 dt_i))``; ``r > regularity_threshold`` and ``1/Tp``
       inside the candidate's band make it an oscillation.
    5. Oscillations with the same period or at a harmonic of a stronger one
       (square or triangular stiction cycles have odd harmonics) are merged;
       the rest are reported strongest first with the amplitude of the
       band-passed component.
    6. Hagglund's (1995) IAE test runs on the detrended signal with the
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
        Longest period searched, as a fraction of the window length (0.3:
        at least about three cycles, enough ACF zero crossings).
    regularity_threshold : float, optional
        ``r`` must exceed this (1 in Thornhill et al. 2003).
    min_prominence : float, optional
        Spectral peak-to-background density ratio a band must reach.
    min_power_fraction : float, optional
        Fraction of the variance a band must hold.
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
        ``detected`` is True when at least one band passes steps 3 and 4;
        ``methods`` holds ``"spectral_peak"`` (statistic: largest prominence of
        a candidate band), ``"acf_regularity"`` (largest ``r`` of a prominent
        band) and ``"iae"`` (Hagglund's count; corroboration only: with ``a``
        relative to the data span it also counts large irregular
        disturbances, so it does not decide).

    Raises
    ------
    DataError
        If ``x`` is not 1-D, contains NaN/inf, has fewer than
        :data:`MIN_SAMPLES` samples, or ``ts`` is not positive.
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
    xd = _detrend(xa)
    spec = _spectrum(xd)

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

    per_octave = 16
    f_hi = min(1.0 / min_period_samples, 0.5 / band_ratio)
    f_lo = 1.0 / (max_period_fraction * n)
    found: list[tuple[float, float, float]] = []  # (power, period, r)
    best_prom = 0.0
    best_prom_period: float | None = None
    best_r = 0.0
    best_r_period: float | None = None
    if f_hi > f_lo:
        n_c = max(int(np.ceil(np.log2(f_hi / f_lo) * per_octave)), 2)
        step = np.log2(f_hi / f_lo) / n_c  # octaves per grid step
        flank = max(round(float(1.0 / step)), 1)  # grid steps in one octave
        # The grid extends one octave beyond the search range for the flanks.
        k = np.arange(-flank, n_c + flank + 1)
        grid = f_lo * (f_hi / f_lo) ** (k / n_c)
        frac, dens = _filterbank(spec, grid, band_ratio, filter_order)
        inner = np.arange(flank, flank + n_c + 1)
        lo_i, hi_i = inner - flank, inner + flank
        with np.errstate(divide="ignore", invalid="ignore"):
            prom_all = dens[inner] / np.sqrt(dens[lo_i] * dens[hi_i])
        prom = np.nan_to_num(prom_all, nan=0.0, posinf=REGULARITY_CAP)
        f_in = frac[inner]
        # Candidates are the local maxima of the prominence (the peak-to-
        # background contrast), which locates a peak without the bias of the
        # background slope (band power grows with fc for white noise, density
        # falls with fc for red noise).
        is_max = np.zeros(inner.size, dtype=bool)
        is_max[1:-1] = (prom[1:-1] > prom[:-2]) & (prom[1:-1] >= prom[2:])
        peaks = np.flatnonzero(is_max & (f_in >= min_power_fraction))
        peaks = peaks[np.argsort(f_in[peaks])[::-1]][: 3 * max_oscillations]
        for j in peaks:
            fc = float(grid[inner[j]])
            if prom[j] > best_prom:
                best_prom, best_prom_period = float(prom[j]), 1.0 / fc
            if prom[j] < min_prominence:
                continue
            period, r, _ = _acf_regularity(
                spec, fc / acf_band_ratio, fc * acf_band_ratio, n_intervals
            )
            if not np.isfinite(period):
                continue
            if not fc / band_ratio <= 1.0 / period <= fc * band_ratio:
                continue
            if r > best_r:
                best_r, best_r_period = r, period
            if r > regularity_threshold:
                found.append((float(f_in[j]), period, r))

    found.sort(key=lambda c: c[0], reverse=True)
    kept: list[tuple[float, float]] = []  # (period, r)
    for _, period, r in found:
        if any(_same_or_harmonic(period, p) for p, _ in kept):
            continue
        kept.append((period, r))
    oscillations: list[Oscillation] = []
    for period, r in kept:
        amp, pf = _measure(spec, period, band_ratio, filter_order)
        oscillations.append(
            Oscillation(
                period_s=period * ts,
                frequency_hz=1.0 / (period * ts),
                regularity=r,
                amplitude=amp,
                power_fraction=pf,
            )
        )
    oscillations.sort(key=lambda o: o.power_fraction, reverse=True)
    oscillations = oscillations[:max_oscillations]
    detected = bool(oscillations)

    spectral = MethodResult(
        "spectral_peak",
        best_prom >= min_prominence,
        None if best_prom_period is None else best_prom_period * ts,
        best_prom,
        min_prominence,
        f"largest peak-to-background density ratio {best_prom:.2f} (needs >= {min_prominence:g})",
    )
    if detected:
        acf_note = f"{len(oscillations)} regular oscillation(s), largest r = {best_r:.2f}"
    else:
        acf_note = f"no prominent band with r > {regularity_threshold:g} (largest r = {best_r:.2f})"
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
        ref_period = best_prom_period
    a = iae_amplitude if iae_amplitude is not None else 0.01 * span
    iae = _iae_method(xd, ts, ref_period, a, iae_supervision_periods, iae_n_lim)
    return OscillationReport(
        detected,
        tuple(oscillations),
        {"spectral_peak": spectral, "acf_regularity": acf, "iae": iae},
    )


def _same_or_harmonic(period: float, stronger: float) -> bool:
    """True if ``period`` is the stronger oscillation or one of its harmonics.

    Same oscillation: periods within 15 %.  Harmonic: ``stronger / period``
    within 5 % of an integer ``k`` in 2..10 (stiction limit cycles are
    square- or triangle-like and carry odd, sometimes even, harmonics).
    """
    ratio = stronger / period
    k = round(ratio)
    if k == 1:
        return abs(ratio - 1.0) <= 0.15
    return 2 <= k <= 10 and abs(ratio - k) <= 0.05 * k


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
        OP/PV pair with matching periods is the loop oscillation (period: their
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
        spec = _spectrum(_detrend(sig))
        if spec.total <= 0:
            return 0.0
        return _measure(spec, period_s / ts, band_ratio, order)[0]

    best: tuple[float, Oscillation, Oscillation] | None = None
    for o in osc_op:
        for p in osc_pv:
            tol = max(period_tolerance, 1.0 / (3.0 * min(o.regularity, p.regularity)))
            if abs(o.period_s - p.period_s) <= tol * max(o.period_s, p.period_s):
                score = o.power_fraction + p.power_fraction
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
