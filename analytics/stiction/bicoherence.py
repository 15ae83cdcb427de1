"""Bicoherence test of the control error for non-Gaussianity and nonlinearity (Choudhury).

A linear loop driven by Gaussian noise (or by a sinusoid) has no phase
coupling between frequencies, so its squared bicoherence::

    bic^2(f1, f2) = |E[X(f1) X(f2) X*(f1 + f2)]|^2
                    / (E[|X(f1) X(f2)|^2] E[|X(f1 + f2)|^2] + eps)

is zero at every bifrequency.  A limit cycle from a sticky valve has
harmonics phase-locked to the fundamental, so the bicoherence at the
harmonic bifrequencies is large.  Choudhury, Shah & Thornhill (2004)
estimate ``bic^2`` by averaging ``K`` Hanning-windowed, half-overlapping
segments (direct FFT method) and define two indices on the principal domain
``0 < f2 <= f1, f1 + f2 <= 1/2``:

* non-Gaussianity index ``NGI = mean(bic^2_sig) - c_alpha / (2K)``, where
  ``2K bic^2`` is asymptotically chi-square with 2 degrees of freedom under
  Gaussianity, ``c_alpha = -2 ln(alpha)`` is its ``1 - alpha`` quantile, and
  ``bic^2_sig`` are the values above ``c_alpha / (2K)``; the mean is taken
  over the whole principal domain, the values that are not significant
  counting as zero (for Gaussian data a few percent of the bifrequencies
  pass the test by chance and NGI stays near ``-c_alpha / (2K)``);
* nonlinearity index ``NLI = |max bic^2 - (mean_r + 2 std_r)|`` with the
  robust mean and standard deviation ``mean_r``, ``std_r`` of the values left
  after dropping the largest and smallest 10 % (a linear non-Gaussian
  signal has a flat bicoherence and ``NLI ~ 0``).

The published decisions: ``NGI > 0.001`` non-Gaussian, ``NLI > 0.01``
nonlinear; a loop that is both is nonlinear, and with a locally linear
process and valve characteristic Choudhury's flowchart attributes the
nonlinearity to the valve.  Otherwise the oscillation is linear (an
external disturbance or the tuning).

Band-limiting (Choudhury's recommendation to keep the frequency range of the
oscillation): the control error is resampled so that one period spans
``segment_length / cycles_per_segment`` samples (by default 32 / 3 ~ 10.7:
the fundamental sits in FFT bin 3 of a segment and harmonics up to the
fifth are below Nyquist).  With an odd number of cycles per segment,
consecutive half-overlapping segments start half a cycle apart, so the
spectral leakage of a pure sinusoid, whose bispectrum carries its phase
once, alternates in sign from segment to segment and averages out, while
genuine harmonic coupling, whose bispectrum does not depend on the phase,
adds up.

The test cannot see a nonlinearity that produces odd harmonics only
(a half-wave symmetric square or triangle wave has a zero bispectrum), and
it needs many cycles: ``K = 2 c / cycles_per_segment - 1`` segments from
``c`` cycles.

References
----------
.. [1] M. A. A. S. Choudhury, S. L. Shah and N. F. Thornhill, "Diagnosis of
   poor control-loop performance using higher-order statistics",
   *Automatica* 40 (2004) 1719-1728 (NGI, NLI, the chi-square test).
.. [2] M. A. A. S. Choudhury, S. L. Shah and N. F. Thornhill, *Diagnosis of
   Process Nonlinearities and Valve Stiction*, Springer (2008)
   (the regularised bicoherence estimator, the thresholds 0.001 and 0.01,
   band-limiting, the decision flowchart).
.. [3] Y. C. Kim and E. J. Powers, "Digital bispectral analysis and its
   applications to nonlinear wave interactions", *IEEE Transactions on
   Plasma Science* 7 (1979) 120-131 (the normalisation).
.. [4] Thesis section 1.2.2, "Nonlinearity and Non-Gaussianity Analysis for
   the Control Error Signal".
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import fft as sfft
from scipy.signal import windows

from analytics.errors import DataError
from analytics.stiction.evidence import (
    NO_STICTION,
    STICTION,
    LoopWindow,
    MethodEvidence,
    margin_confidence,
)
from analytics.stiction.surrogate import MIN_PERIOD_SAMPLES, resample_whole_cycles
from analytics.types import FloatArray

__all__ = [
    "BicoherenceDetector",
    "BicoherenceResult",
    "bicoherence_indices",
    "squared_bicoherence",
]


def _principal_domain(segment_length: int) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """FFT bins ``(k1, k2)`` with ``0 < k2 <= k1`` and ``k1 + k2 <= segment_length / 2``."""
    half = segment_length // 2
    k1, k2 = np.meshgrid(np.arange(1, half), np.arange(1, half), indexing="ij")
    inside = (k2 <= k1) & (k1 + k2 <= half)
    return k1[inside], k2[inside]


def squared_bicoherence(
    x: ArrayLike, *, segment_length: int = 32, epsilon_quantile: float = 0.1
) -> tuple[FloatArray, FloatArray, FloatArray, int]:
    """Segment-averaged squared bicoherence on the principal domain.

    The mean is removed from each of the ``K`` half-overlapping segments of
    ``segment_length`` samples, which are then Hanning-windowed and
    transformed; the bispectrum and the two factors of the Kim-Powers
    denominator are averaged over the segments.  The denominator is
    regularised with ``eps``, the ``epsilon_quantile`` quantile of the
    denominators over the domain, so that bifrequencies with negligible power
    cannot show a large bicoherence (Choudhury et al. 2008 add a small
    constant; a quantile makes it independent of the signal's scale).

    Parameters
    ----------
    x : array_like
        Signal (already band-limited).
    segment_length : int
        FFT length of a segment (even).
    epsilon_quantile : float
        Quantile of the denominators used as ``eps`` (0 for none).

    Returns
    -------
    f1, f2 : ndarray
        Bifrequencies in cycles per sample, ``0 < f2 <= f1``, ``f1 + f2 <= 1/2``.
    bic2 : ndarray
        Squared bicoherence at ``(f1, f2)``.
    segments : int
        Number ``K`` of segments averaged.

    Raises
    ------
    DataError
        If ``x`` is shorter than one segment or constant.

    Examples
    --------
    Three tones whose phases wander but with the third locked to the sum of
    the other two are fully coupled at ``(f1, f2) = (4, 2) / 32``:

    >>> rng = np.random.default_rng(0)
    >>> k = np.arange(4096)
    >>> a, b = (np.cumsum(rng.normal(0, 0.05, k.size)) for _ in range(2))
    >>> x = (np.cos(2 * np.pi * 4 * k / 32 + a) + np.cos(2 * np.pi * 2 * k / 32 + b)
    ...      + np.cos(2 * np.pi * 6 * k / 32 + a + b))
    >>> f1, f2, bic2, segments = squared_bicoherence(x)
    >>> at = (f1 == 4 / 32) & (f2 == 2 / 32)
    >>> segments, round(float(bic2[at][0]), 2)
    (255, 0.99)
    """
    xa = np.asarray(x, dtype=np.float64)
    if segment_length < 8 or segment_length % 2:
        raise DataError(f"segment_length must be even and >= 8, got {segment_length}")
    step = segment_length // 2
    if xa.size < segment_length:
        raise DataError(f"{xa.size} samples are fewer than one segment of {segment_length}")
    segments = (xa.size - segment_length) // step + 1
    frames = np.lib.stride_tricks.sliding_window_view(xa, segment_length)[::step][:segments]
    frames = frames - frames.mean(axis=1, keepdims=True)
    spectra = sfft.rfft(frames * windows.hann(segment_length, sym=False), axis=1)
    k1, k2 = _principal_domain(segment_length)
    pair = spectra[:, k1] * spectra[:, k2]
    total = spectra[:, k1 + k2]
    bispectrum = np.mean(pair * np.conj(total), axis=0)
    denominator = np.mean(np.abs(pair) ** 2, axis=0) * np.mean(np.abs(total) ** 2, axis=0)
    if not np.max(denominator) > 0:
        raise DataError("the signal is constant: its bicoherence is undefined")
    eps = float(np.quantile(denominator, epsilon_quantile)) if epsilon_quantile > 0 else 0.0
    bic2 = np.abs(bispectrum) ** 2 / (denominator + eps)
    return k1 / segment_length, k2 / segment_length, bic2, int(segments)


@dataclass(frozen=True)
class BicoherenceResult:
    """Result of :func:`bicoherence_indices`.

    Attributes
    ----------
    ngi : float
        Non-Gaussianity index (non-Gaussian if ``> 0.001``).
    nli : float
        Nonlinearity index (nonlinear if ``> 0.01``).
    total_nonlinearity : float
        ``TNLI = sum(bic^2_sig)``, Choudhury's total nonlinearity index.
    max_bicoherence : float
        Largest ``bic^2`` on the principal domain.
    peak : tuple of float
        ``(f1, f2)`` of the largest ``bic^2``, in cycles per sample of ``x``,
        or in multiples of the oscillation frequency when a period was given.
    threshold : float
        ``c_alpha / (2K)``, the significance level of a single ``bic^2``.
    segments : int
        ``K``, segments averaged.
    samples_per_cycle : float or None
        Period of the analysed (resampled) signal in samples, None if it was
        not resampled.
    """

    ngi: float
    nli: float
    total_nonlinearity: float
    max_bicoherence: float
    peak: tuple[float, float]
    threshold: float
    segments: int
    samples_per_cycle: float | None


def bicoherence_indices(
    x: ArrayLike,
    *,
    period_samples: float | None = None,
    segment_length: int = 32,
    cycles_per_segment: int = 3,
    alpha: float = 0.05,
    trim: float = 0.1,
    epsilon_quantile: float = 0.1,
) -> BicoherenceResult:
    """Choudhury's NGI and NLI of a signal (usually the control error).

    Parameters
    ----------
    x : array_like
        Signal; the mean is removed segment by segment.
    period_samples : float, optional
        Oscillation period in samples of ``x``.  When given, the signal is
        first band-limited to the oscillation: resampled to
        ``segment_length / cycles_per_segment`` samples per cycle over its
        whole, end-matched cycles
        (:func:`analytics.stiction.surrogate.resample_whole_cycles`).
    segment_length : int
        FFT length of a segment; segments overlap by half.
    cycles_per_segment : int
        Oscillation cycles per segment after resampling (odd; see the
        module docstring).
    alpha : float
        Significance level of the chi-square test of a single ``bic^2``.
    trim : float
        Fraction dropped at each end for the robust mean and standard
        deviation in NLI (Choudhury's 10 %).
    epsilon_quantile : float
        See :func:`squared_bicoherence`.

    Returns
    -------
    BicoherenceResult

    Raises
    ------
    DataError
        As :func:`squared_bicoherence`, or if ``period_samples`` is shorter
        than :data:`analytics.stiction.surrogate.MIN_PERIOD_SAMPLES`.

    References
    ----------
    Choudhury, Shah & Thornhill (2004), NGI and NLI; their 2008 book.

    Examples
    --------
    Gaussian noise has no significant bicoherence:

    >>> noise = np.random.default_rng(1).standard_normal(4096)
    >>> result = bicoherence_indices(noise)
    >>> result.segments, result.ngi < 0.001
    (255, True)
    """
    samples_per_cycle: float | None = None
    series = np.asarray(x, dtype=np.float64)
    if period_samples is not None:
        if not (np.isfinite(period_samples) and period_samples >= MIN_PERIOD_SAMPLES):
            raise DataError(
                f"the period must span at least {MIN_PERIOD_SAMPLES:g} samples, "
                f"got {period_samples!r}"
            )
        samples_per_cycle = segment_length / cycles_per_segment
        series, _ = resample_whole_cycles(series, period_samples, samples_per_cycle)
    f1, f2, bic2, segments = squared_bicoherence(
        series, segment_length=segment_length, epsilon_quantile=epsilon_quantile
    )
    threshold = -2.0 * np.log(alpha) / (2 * segments)
    significant = bic2 > threshold
    total = float(bic2[significant].sum())
    ngi = total / bic2.size - threshold
    ordered = np.sort(bic2)
    cut = int(trim * ordered.size)
    robust = ordered[cut : ordered.size - cut]
    nli = abs(float(ordered[-1]) - (float(robust.mean()) + 2.0 * float(robust.std())))
    top = int(np.argmax(bic2))
    scale = samples_per_cycle if samples_per_cycle is not None else 1.0
    return BicoherenceResult(
        ngi=float(ngi),
        nli=nli,
        total_nonlinearity=total,
        max_bicoherence=float(ordered[-1]),
        peak=(float(f1[top] * scale), float(f2[top] * scale)),
        threshold=float(threshold),
        segments=segments,
        samples_per_cycle=samples_per_cycle,
    )


@dataclass(frozen=True, kw_only=True)
class BicoherenceDetector:
    """Stiction evidence from the bicoherence of the control error (Choudhury et al.).

    The error ``SP - PV`` (PV alone when SP is absent; the sign does not
    change the bicoherence) is band-limited to the loop oscillation and
    tested: non-Gaussian (``NGI > ngi_threshold``) and nonlinear
    (``NLI > nli_threshold``) is stiction evidence, otherwise the oscillation
    is linear.  Undecided without PV, without an oscillation period, with a
    period shorter than :data:`analytics.stiction.surrogate.MIN_PERIOD_SAMPLES`
    or with fewer than ``min_segments`` segments (about
    ``cycles_per_segment * (min_segments + 1) / 2`` cycles).

    Choudhury's flowchart then quantifies the stiction from the PV-OP
    plot; here the battery's shape-based methods play that part.

    Attributes
    ----------
    segment_length, cycles_per_segment, alpha, trim, epsilon_quantile
        As in :func:`bicoherence_indices`.
    ngi_threshold, nli_threshold : float
        Choudhury's published thresholds, 0.001 and 0.01.
    min_segments : int
        Fewest segments for a decision (the chi-square level ``c_alpha / 2K``
        is 0.37 at ``K = 8``).
    nli_confidence_scale : float
        Distance of NLI from its threshold that gives confidence 0.63 (the
        NGI distance is measured in units of ``c_alpha / 2K``).

    References
    ----------
    Choudhury, Shah & Thornhill (2004, 2008); thesis section 1.2.2.

    Examples
    --------
    A loop disturbed by a sinusoid oscillates linearly:

    >>> k = np.arange(3000)
    >>> rng = np.random.default_rng(0)
    >>> pv = np.sin(2 * np.pi * k / 40) + 0.2 * rng.standard_normal(k.size)
    >>> window = LoopWindow(ts=1.0, op=None, pv=pv, period_s=40.0)
    >>> BicoherenceDetector().detect(window).decision
    'no_stiction'
    """

    name: ClassVar[str] = "bicoherence"

    segment_length: int = 32
    cycles_per_segment: int = 3
    alpha: float = 0.05
    trim: float = 0.1
    epsilon_quantile: float = 0.1
    ngi_threshold: float = 0.001
    nli_threshold: float = 0.01
    min_segments: int = 8
    nli_confidence_scale: float = 0.1

    def detect(self, window: LoopWindow) -> MethodEvidence:
        """Evidence for or against stiction in ``window`` (see the class docstring)."""
        if window.pv is None:
            return MethodEvidence.undecided(self.name, "the bicoherence test needs PV")
        error = window.pv if window.sp is None else window.sp - window.pv
        period = window.period_samples
        if period is None:
            return MethodEvidence.undecided(
                self.name, "no oscillation period to band-limit the control error to"
            )
        if period < MIN_PERIOD_SAMPLES:
            return MethodEvidence.undecided(
                self.name, f"the period spans {period:.1f} samples: its harmonics are not sampled"
            )
        samples = int(window.samples // period) * self.segment_length / self.cycles_per_segment
        segments = int((samples - self.segment_length) // (self.segment_length // 2)) + 1
        if segments < self.min_segments:
            return MethodEvidence.undecided(
                self.name,
                f"{window.samples / period:.2f} cycles give {max(segments, 0)} segments, "
                f"the bicoherence test needs {self.min_segments}",
                details={"cycles": window.samples / period},
            )
        if np.ptp(error) == 0:
            return MethodEvidence.undecided(self.name, "the control error is constant")
        result = bicoherence_indices(
            error,
            period_samples=period,
            segment_length=self.segment_length,
            cycles_per_segment=self.cycles_per_segment,
            alpha=self.alpha,
            trim=self.trim,
            epsilon_quantile=self.epsilon_quantile,
        )
        details = {
            "ngi": result.ngi,
            "nli": result.nli,
            "total_nonlinearity": result.total_nonlinearity,
            "max_bicoherence": result.max_bicoherence,
            "peak_f1_per_f0": result.peak[0],
            "peak_f2_per_f0": result.peak[1],
            "significance_level": result.threshold,
            "segments": float(result.segments),
        }
        ngi_margin = margin_confidence(result.ngi, self.ngi_threshold, result.threshold)
        nli_margin = margin_confidence(result.nli, self.nli_threshold, self.nli_confidence_scale)
        if result.ngi <= self.ngi_threshold:
            note = (
                f"the control error is Gaussian (NGI = {result.ngi:.3f} <= "
                f"{self.ngi_threshold:g}): a linear oscillation"
            )
            return MethodEvidence(self.name, NO_STICTION, result.ngi, ngi_margin, note, details)
        if result.nli <= self.nli_threshold:
            note = (
                f"the control error is non-Gaussian but linear (NLI = {result.nli:.3f} <= "
                f"{self.nli_threshold:g})"
            )
            return MethodEvidence(self.name, NO_STICTION, result.ngi, nli_margin, note, details)
        note = (
            f"the control error is nonlinear (NGI = {result.ngi:.3f}, NLI = {result.nli:.2f}); "
            f"bicoherence peaks at ({result.peak[0]:.1f}, {result.peak[1]:.1f}) x the "
            f"oscillation frequency"
        )
        return MethodEvidence(
            self.name, STICTION, result.ngi, min(ngi_margin, nli_margin), note, details
        )
