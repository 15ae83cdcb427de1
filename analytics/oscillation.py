"""Oscillation detection in a single loop signal (OP alone or PV alone).

Two classical, complementary detectors are implemented and combined:

* **ACF regularity** -- N. F. Thornhill, B. Huang and H. Zhang, "Detection of
  multiple oscillations in control loops", *Journal of Process Control* 13
  (2003) 91-100.  Each peak of the power spectrum defines a frequency band;
  the signal is band-pass filtered to that band, its autocorrelation
  function (ACF) is computed, and the intervals ``dt_i`` between successive
  zero crossings of the ACF give the period ``Tp = 2 mean(dt_i)`` and the
  regularity ``r = mean(Tp_i) / (3 std(Tp_i))`` with ``Tp_i = 2 dt_i``
  (their eqs. 1-3).  An oscillation is declared when ``r > 1``.  Because every
  spectral band is tested separately, several oscillations in one signal
  are found and reported sorted by power.
* **IAE between zero crossings** -- T. Hagglund, "A control-loop performance
  monitor", *Control Engineering Practice* 3 (1995) 1543-1551.  The
  integrated absolute error between successive zero crossings is compared
  with ``IAE_lim = 2 a / omega`` (the IAE of one half cycle of a sine of
  amplitude ``a`` at frequency ``omega``, his eq. 3).  Half cycles exceeding the
  limit are counted as load disturbances; more than ``n_lim = 10`` of them in
  a supervision time ``T_sup = 50 T_i`` indicates an oscillation (his sec. 3).
  Offline, as in the evaluations of M. Jelali and B. Huang (eds.),
  *Detection and Diagnosis of Stiction in Control Loops*, Springer 2010,
  ch. 3, the ultimate frequency is replaced by the detected oscillation
  frequency and the count limit is scaled to the window length.

All filtering is zero-phase and done in the frequency domain with one FFT of
the (mean and linear-trend removed) signal, so a 10,000-sample window takes a
few milliseconds.  The band-pass filter is the squared magnitude of an analogue
Butterworth band-pass (equivalent to forward-backward ``filtfilt``
filtering), with unit gain at the band centre.
"""

from __future__ import annotations

from dataclasses import dataclass, field

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
        Oscillation period in seconds, ``Tp = 2 mean(dt_i)`` from the ACF zero
        crossings of the band-passed signal (Thornhill et al. 2003, eq. 1).
    frequency_hz : float
        ``1 / period_s``.
    regularity : float
        ``r = mean(Tp_i) / (3 std(Tp_i))`` (Thornhill et al. 2003, eq. 3);
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
        ``"acf_regularity"`` (Thornhill et al. 2003) or ``"iae"``
        (Hagglund 1995).
    detected : bool
        Whether this method alone indicates an oscillation.
    period_s : float or None
        Period the method worked with (None if it could not run).
    statistic : float
        ``acf_regularity``: the largest regularity ``r`` of any band;
        ``iae``: the number of half cycles whose IAE exceeded ``IAE_lim``.
    threshold : float
        The value ``statistic`` must exceed: 1 for the regularity,
        the window-scaled ``n_lim`` for the IAE count.
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
        True if at least one regular oscillation was found (see
        :func:`detect_oscillations` for the decision rule).
    oscillations : tuple of Oscillation
        All significant oscillations, strongest (largest power) first.
    methods : dict of str to MethodResult
        Per-method verdicts, keys ``"acf_regularity"`` and ``"iae"``.
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
        True if OP or PV oscillates (with a period consistent between the two
        when both oscillate).
    period_s : float or None
        Period of the loop oscillation (mean of OP and PV when both agree).
    regularity : float or None
        Largest regularity of the matched oscillation over OP and PV.
    amplitude_op, amplitude_pv : float or None
        Amplitude of the oscillation at ``period_s`` in OP / PV (band-passed
        half peak-to-peak, see :class:`Oscillation`); None where the signal is
        missing or nothing was detected.
    periods_consistent : bool or None
        True if both signals oscillate with periods within 15 %, False if both
        oscillate at different periods, None if fewer than two signals
        oscillate.
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
    X: NDArray[np.complex128]  # rfft of x zero-padded to nfft
    P: FloatArray  # |X|^2
    f: FloatArray  # cycles / sample
    total: float  # sum(P[1:]) ~ n * var(x) * nfft-scaling


def _detrend(x: FloatArray) -> FloatArray:
    n = x.size
    k = np.arange(n, dtype=np.float64)
    k -= k.mean()
    xc = x - x.mean()
    slope = float(np.dot(k, xc) / np.dot(k, k)) if n > 1 else 0.0
    return xc - slope * k


def _spectrum(x: FloatArray) -> _Spectrum:
    n = x.size
    nfft = sfft.next_fast_len(2 * n, real=True)
    X = sfft.rfft(x, nfft)
    P = X.real**2 + X.imag**2
    f = np.arange(P.size, dtype=np.float64) / nfft
    return _Spectrum(x, n, nfft, X, P, f, float(P[1:].sum()))


def _bandpass_gain(f: FloatArray, fc: float, band_ratio: float, order: int) -> FloatArray:
    """Squared magnitude of an analogue Butterworth band-pass centred at ``fc``.

    ``|H|^2 = 1 / (1 + ((f/fc - fc/f) / B)^(2 order))`` with ``B = q - 1/q`` so
    that the half-power edges lie at ``fc/q`` and ``fc q``.  Applying the
    squared magnitude (returned here) is the zero-phase forward-backward
    filter; gain is 1 at ``fc``.
    """
    bw = band_ratio - 1.0 / band_ratio
    with np.errstate(divide="ignore", over="ignore"):
        w = (f / fc - fc / f) / bw
        h2 = 1.0 / (1.0 + w ** (2 * order))  # 0 at f = 0
    return np.asarray(h2, dtype=np.float64)


def _filterbank(
    spec: _Spectrum, centres: FloatArray, band_ratio: float, order: int
) -> FloatArray:
    """Band power of every filter of a constant-Q bank (for peak picking).

    The periodogram is first summed into log-spaced bins (much finer than the
    filters) so that the cost does not grow with the number of samples.
    """
    f = spec.f[1:]
    P = spec.P[1:]
    lo = centres[0] / (4 * band_ratio)
    hi = min(0.5, centres[-1] * 4 * band_ratio)
    nb = max(int(np.ceil(np.log2(hi / lo) * 96)), 8)
    edges = lo * (hi / lo) ** (np.arange(nb + 1) / nb)
    idx = np.searchsorted(edges, f) - 1
    ok = (idx >= 0) & (idx < nb)
    pb = np.bincount(idx[ok], weights=P[ok], minlength=nb)
    fb = np.bincount(idx[ok], weights=f[ok] * P[ok], minlength=nb)
    has = pb > 0
    fb = np.where(has, fb / np.where(has, pb, 1.0), np.sqrt(edges[:-1] * edges[1:]))
    bw = band_ratio - 1.0 / band_ratio
    w = (fb[None, :] / centres[:, None] - centres[:, None] / fb[None, :]) / bw
    g = 1.0 / (1.0 + w ** (2 * order))
    return np.asarray(g @ pb, dtype=np.float64)


def _zero_crossings(y: FloatArray) -> FloatArray:
    """Linearly interpolated positions of the sign changes of ``y``."""
    s = np.signbit(y)
    i = np.flatnonzero(s[1:] != s[:-1])
    y0, y1 = y[i], y[i + 1]
    return np.asarray(i + y0 / (y0 - y1), dtype=np.float64)


def _acf_regularity(
    spec: _Spectrum, gain: FloatArray, n_intervals: int, max_lag: int
) -> tuple[float, float, int]:
    """Period (samples), regularity and number of intervals from the ACF.

    Thornhill et al. (2003), eqs. 1-3: the ACF of the band-passed signal is
    ``IFFT(|X|^2 |G|^2)``; the intervals between its zero crossings (the
    first, from lag 0 to the first crossing, is a quarter period and not
    used) give ``Tp_i = 2 dt_i``.
    """
    acf = sfft.irfft(spec.P * gain * gain, spec.nfft)[: max_lag + 1]
    zc = _zero_crossings(acf)[: n_intervals + 1]
    if zc.size < 4:
        return float("nan"), 0.0, max(zc.size - 1, 0)
    tp = 2.0 * np.diff(zc)
    mean = float(tp.mean())
    sd = float(tp.std(ddof=1))
    r = REGULARITY_CAP if sd * REGULARITY_CAP * 3 <= mean else mean / (3.0 * sd)
    return mean, r, tp.size


def _cycle_amplitude(y: FloatArray) -> float:
    """Median half peak-to-peak amplitude over the complete cycles of ``y``."""
    s = np.signbit(y)
    up = np.flatnonzero(s[:-1] & ~s[1:]) + 1  # negative -> non-negative
    if up.size >= 2:
        mx = np.maximum.reduceat(y, up[:-1])
        mn = np.minimum.reduceat(y, up[:-1])
        # reduceat runs to the next index; the last segment would run to the
        # end of the array, so only the first up.size - 1 segments are used.
        amps = 0.5 * (mx - mn)
        return float(np.median(amps))
    return float(np.sqrt(2.0) * np.std(y))


def _band_component(spec: _Spectrum, gain: FloatArray) -> FloatArray:
    y = sfft.irfft(spec.X * gain, spec.nfft)[: spec.n]
    return np.asarray(y, dtype=np.float64)


def _measure(
    spec: _Spectrum, period: float, band_ratio: float, order: int
) -> tuple[float, float]:
    """Amplitude and power fraction of the component at ``period`` (samples)."""
    gain = _bandpass_gain(spec.f, 1.0 / period, band_ratio, order)
    y = _band_component(spec, gain)
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
    if period is None or not np.isfinite(period):
        return MethodResult("iae", False, None, 0.0, float("nan"), "no dominant period to test")
    omega = 2.0 * np.pi / (period * ts)
    iae_lim = 2.0 * amplitude / omega
    zc = np.flatnonzero(np.signbit(x[1:]) != np.signbit(x[:-1])) + 1
    if zc.size < 2:
        return MethodResult(
            "iae", False, period * ts, 0.0, float("nan"), "fewer than two zero crossings"
        )
    # IAE of every complete half cycle between two zero crossings.
    iae = np.add.reduceat(np.abs(x), zc)[:-1] * ts
    count = int(np.count_nonzero(iae > iae_lim))
    t_window = x.size * ts
    t_sup = supervision_periods * period * ts
    limit = n_lim * t_window / t_sup
    return MethodResult(
        "iae",
        count > limit,
        period * ts,
        float(count),
        float(limit),
        f"{count} of {iae.size} half cycles exceed IAE_lim = {iae_lim:.4g} "
        f"(a = {amplitude:.4g}); n_lim scaled to the window = {limit:.1f}",
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
    min_power_fraction: float = 0.05,
    max_oscillations: int = 4,
    band_ratio: float = 1.5,
    filter_order: int = 2,
    n_intervals: int = 10,
    iae_amplitude: float | None = None,
    iae_supervision_periods: float = 25.0,
    iae_n_lim: float = 10.0,
) -> OscillationReport:
    """Detect and characterise oscillations in one signal.

    Parameters
    ----------
    x : array_like
        One uniformly sampled signal (OP or PV).  Mean and linear trend are
        removed first.
    ts : float
        Sampling interval in seconds.
    min_period_samples : float, optional
        Shortest period searched, in samples.
    max_period_fraction : float, optional
        Longest period searched as a fraction of the window (0.3: at least
        about three cycles, enough for the ACF zero crossings).
    regularity_threshold : float, optional
        ``r`` must exceed this (1 in Thornhill et al. 2003).
    min_power_fraction : float, optional
        A band must hold at least this fraction of the signal variance to be
        a candidate (suppresses tiny but regular components).
    max_oscillations : int, optional
        At most this many oscillations are reported.
    band_ratio : float, optional
        Half-power edges of each band-pass at ``fc / band_ratio`` and
        ``fc * band_ratio``: wide enough that band-passed noise loses its
        regularity within a few cycles, narrow enough to exclude the third
        harmonic of a square (stiction-like) wave.
    filter_order : int, optional
        Order of the Butterworth prototype (applied forward-backward).
    n_intervals : int, optional
        Number of ACF zero-crossing intervals used for the regularity
        (Thornhill et al. use ten).
    iae_amplitude : float, optional
        Hagglund's acceptable amplitude ``a``; default 1 % of the signal span
        (max - min).
    iae_supervision_periods : float, optional
        Supervision time ``T_sup`` in periods.  Hagglund uses
        ``T_sup = 50 T_i``; with the integral time ``T_i ~ Tp / 2`` of a
        typically tuned PI loop this is 25 periods.
    iae_n_lim : float, optional
        Hagglund's count limit per supervision time (10).

    Returns
    -------
    OscillationReport
        ``detected`` is True when the ACF method finds at least one band with
        ``r > regularity_threshold``; these are the reported oscillations.
        The IAE method is reported in ``methods["iae"]`` as corroboration
        only, since with ``a`` defined relative to the data span it also
        fires on large irregular (non-oscillatory) load disturbances.

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
    n = xa.size
    span = float(xa.max() - xa.min())
    xd = _detrend(xa)
    spec = _spectrum(xd)
    max_lag = n - 1

    no_acf = MethodResult("acf_regularity", False, None, 0.0, regularity_threshold, "")
    if spec.total <= 0 or span == 0:
        note = "signal is constant after detrending"
        return OscillationReport(
            False,
            (),
            {
                "acf_regularity": _replace_note(no_acf, note),
                "iae": MethodResult("iae", False, None, 0.0, float("nan"), note),
            },
        )

    f_hi = min(1.0 / min_period_samples, 0.5 / band_ratio)
    f_lo = 1.0 / (max_period_fraction * n)
    candidates: list[tuple[float, float, float, float]] = []  # power, period, r, fc
    best_r = 0.0
    best_any: tuple[float, float] | None = None  # (power, period) of strongest band
    if f_hi > f_lo:
        n_c = max(int(np.ceil(np.log2(f_hi / f_lo) * 16)), 3)
        centres = f_lo * (f_hi / f_lo) ** (np.arange(n_c + 1) / n_c)
        bank = _filterbank(spec, centres, band_ratio, filter_order)
        interior = np.flatnonzero((bank[1:-1] > bank[:-2]) & (bank[1:-1] >= bank[2:])) + 1
        interior = interior[np.argsort(bank[interior])[::-1]]
        for k in interior[: 2 * max_oscillations + 4]:
            fc = float(centres[k])
            gain = _bandpass_gain(spec.f, fc, band_ratio, filter_order)
            power = float((spec.P * gain).sum() / spec.total)
            if power < min_power_fraction:
                continue
            import os
            if os.environ.get("ACF_BRICK"):
                qq = float(os.environ["ACF_BRICK"])
                brick = ((spec.f >= fc / qq) & (spec.f <= fc * qq)).astype(np.float64)
                period, r, _ = _acf_regularity(spec, brick, n_intervals, max_lag)
            else:
                period, r, _ = _acf_regularity(spec, gain, n_intervals, max_lag)
            if not np.isfinite(period):
                continue
            in_band = fc / band_ratio <= 1.0 / period <= fc * band_ratio
            if best_any is None or power > best_any[0]:
                best_any = (power, period)
            if not in_band:
                continue
            best_r = max(best_r, r)
            if r > regularity_threshold:
                candidates.append((power, period, r, fc))

    candidates.sort(key=lambda c: c[0], reverse=True)
    kept: list[tuple[float, float, float]] = []  # period, r, fc
    for _, period, r, fc in candidates:
        if any(_same_or_harmonic(period, p) for p, _, _ in kept):
            continue
        kept.append((period, r, fc))
    oscillations: list[Oscillation] = []
    for period, r, _ in kept:
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
    if detected:
        acf_note = f"{len(oscillations)} regular oscillation(s); strongest r = {best_r:.2f}"
        acf_period: float | None = oscillations[0].period_s
    else:
        acf_note = f"no band with r > {regularity_threshold:g} (largest r = {best_r:.2f})"
        acf_period = None if best_any is None else best_any[1] * ts
    acf = MethodResult(
        "acf_regularity", detected, acf_period, best_r, regularity_threshold, acf_note
    )
    ref_period = None if acf_period is None else acf_period / ts
    a = iae_amplitude if iae_amplitude is not None else 0.01 * span
    iae = _iae_method(xd, ts, ref_period, a, iae_supervision_periods, iae_n_lim)
    return OscillationReport(detected, tuple(oscillations), {"acf_regularity": acf, "iae": iae})


def _replace_note(m: MethodResult, note: str) -> MethodResult:
    return MethodResult(m.method, m.detected, m.period_s, m.statistic, m.threshold, note)


def _same_or_harmonic(period: float, stronger: float, tol: float = 0.12) -> bool:
    """True if ``period`` is the stronger oscillation or one of its harmonics."""
    ratio = stronger / period
    k = round(ratio)
    return k >= 1 and abs(ratio - k) <= tol * k


def detect_loop_oscillation(
    op: ArrayLike | None,
    pv: ArrayLike | None,
    ts: float,
    *,
    period_tolerance: float = 0.15,
    **kwargs: float,
) -> LoopOscillation:
    """Detect a loop oscillation from OP and/or PV.

    Parameters
    ----------
    op, pv : array_like or None
        Controller output and process variable; either may be None.
    ts : float
        Sampling interval in seconds.
    period_tolerance : float, optional
        Relative difference under which OP and PV periods are the same
        oscillation (in a closed loop both oscillate at the loop frequency).
    **kwargs
        Passed on to :func:`detect_oscillations`.

    Returns
    -------
    LoopOscillation
        Oscillating if either signal oscillates.  When both do, the
        oscillation with a period common to OP and PV (the strongest such
        pair) is the loop oscillation; when their periods disagree the
        stronger-regularity one is reported with ``periods_consistent``
        False.  The amplitude in the other signal is measured at the same
        period even if that signal alone did not pass the test.

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
    rep_op = None if op_a is None else detect_oscillations(op_a, ts, **kwargs)  # type: ignore[arg-type]
    rep_pv = None if pv_a is None else detect_oscillations(pv_a, ts, **kwargs)  # type: ignore[arg-type]

    osc_op = rep_op.oscillations if rep_op is not None else ()
    osc_pv = rep_pv.oscillations if rep_pv is not None else ()
    period: float | None = None
    regularity: float | None = None
    consistent: bool | None = None
    # Strongest OP/PV pair with matching periods.
    best: tuple[float, Oscillation, Oscillation] | None = None
    for o in osc_op:
        for p in osc_pv:
            if abs(o.period_s - p.period_s) <= period_tolerance * max(o.period_s, p.period_s):
                score = o.power_fraction + p.power_fraction
                if best is None or score > best[0]:
                    best = (score, o, p)
    if best is not None:
        _, o, p = best
        period = 0.5 * (o.period_s + p.period_s)
        regularity = max(o.regularity, p.regularity)
        consistent = True
    elif osc_op or osc_pv:
        pool = list(osc_op[:1]) + list(osc_pv[:1])
        chosen = max(pool, key=lambda z: z.regularity)
        period = chosen.period_s
        regularity = chosen.regularity
        consistent = False if (osc_op and osc_pv) else None
    detected = period is not None

    def amp(sig: FloatArray | None) -> float | None:
        if sig is None or period is None:
            return None
        band_ratio = float(kwargs.get("band_ratio", 1.5))
        order = int(kwargs.get("filter_order", 2))
        spec = _spectrum(_detrend(sig))
        if spec.total <= 0:
            return 0.0
        return _measure(spec, period / ts, band_ratio, order)[0]

    return LoopOscillation(
        detected=detected,
        period_s=period,
        regularity=regularity,
        amplitude_op=amp(op_a),
        amplitude_pv=amp(pv_a),
        periods_consistent=consistent,
        op=rep_op,
        pv=rep_pv,
    )
