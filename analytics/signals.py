"""Signal helpers shared by the detectors: zero crossings, the autocorrelation, the
detrended signal and its spectrum.

Each is written once here; the oscillation detection (Thornhill et al. 2003:
ACF zero crossings, the band-pass filters and the spectral peaks), the
oscillation groups of a unit (band spectra), the cycle shapes (cycles cut at
PV's upward crossings), the OP-PV cross-correlation test, the model check's
correlation time and the dashboard's spectrum and ACF plots (:func:`power_spectrum`)
use them.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import fft as sfft
from scipy import signal as sps

from analytics.types import FloatArray

__all__ = ["Spectrum", "autocorrelation", "detrend", "power_spectrum", "shared",
           "shared_results", "spectrum", "upward_crossings", "zero_crossings"]

_R = TypeVar("_R")
_SHARED: ContextVar[dict[tuple[Any, ...], Any] | None] = ContextVar("_SHARED", default=None)


@contextmanager
def shared_results() -> Iterator[None]:
    """Within the block, :func:`shared` computes each result once.

    One loop's diagnosis runs many methods on the same OP and PV, and several
    filter them alike (:func:`analytics.oscillation.bandpass`) or take their
    noise (:func:`analytics.stiction.stick_jump.robust_noise`); the results
    are kept until the block ends, so no later window sees them.
    """
    token = _SHARED.set({})
    try:
        yield
    finally:
        _SHARED.reset(token)


def shared(fn: Callable[..., _R], x: FloatArray, *args: Any) -> _R:
    """``fn(x, *args)``, computed once per samples of ``x`` and ``args`` within
    :func:`shared_results` (an array result is then read-only); else computed."""
    memo = _SHARED.get()
    if memo is None:
        return fn(x, *args)
    key = (fn, x.dtype.str, x.shape, x.tobytes(), *args)
    if key not in memo:
        result = fn(x, *args)
        if isinstance(result, np.ndarray):
            result.setflags(write=False)
        memo[key] = result
    return memo[key]


def zero_crossings(y: FloatArray) -> FloatArray:
    """Linearly interpolated positions (in samples) of the sign changes of ``y``.

    >>> zero_crossings(np.array([1.0, -1.0, -3.0, 1.0])).tolist()
    [0.5, 2.75]
    """
    s = np.signbit(y)
    i = np.flatnonzero(s[1:] != s[:-1])
    y0, y1 = y[i], y[i + 1]
    return np.asarray(i + y0 / (y0 - y1), dtype=np.float64)


def upward_crossings(y: FloatArray) -> FloatArray:
    """Interpolated positions where ``y`` crosses zero going up.

    >>> upward_crossings(np.array([1.0, -1.0, -3.0, 1.0])).tolist()
    [2.75]
    """
    crossings = zero_crossings(y)
    below = y[np.floor(crossings).astype(np.int64)] < 0
    return crossings[below]


def autocorrelation(x: ArrayLike, max_lag: int) -> FloatArray:
    """Biased autocorrelation of the mean-removed finite samples of ``x`` at lags
    ``0..max_lag`` (at most ``n - 1``), 1 at lag 0 (0 throughout for a constant).

    Computed through the FFT with zero padding to twice the length, which
    gives the ordinary (not circular) estimate (Wiener-Khinchin).

    >>> np.round(autocorrelation([1.0, -1.0, 1.0, -1.0], 3), 3).tolist()
    [1.0, -0.75, 0.5, -0.25]
    """
    values = np.asarray(x, dtype=np.float64)
    values = values[np.isfinite(values)]
    if values.size < 2:
        raise ValueError("autocorrelation needs at least 2 finite samples")
    centred = values - values.mean()
    n = centred.size
    spectrum = np.fft.rfft(centred, 2 * n)
    acf = np.fft.irfft(spectrum * np.conj(spectrum), 2 * n)[: min(max_lag, n - 1) + 1]
    return np.asarray(acf / acf[0] if acf[0] > 0 else acf, dtype=np.float64)


def detrend(x: ArrayLike) -> FloatArray:
    """``x`` less its mean and its least-squares straight line.

    >>> detrend([1.0, 3.0, 5.0, 7.0]).tolist()
    [0.0, 0.0, 0.0, 0.0]
    """
    values = np.asarray(x, dtype=np.float64)
    k = np.arange(values.size, dtype=np.float64)
    k -= k.mean()
    centred = values - values.mean()
    kk = float(np.dot(k, k))
    slope = float(np.dot(k, centred)) / kk if kk > 0 else 0.0
    return np.asarray(centred - slope * k, dtype=np.float64)


@dataclass(frozen=True)
class Spectrum:
    """The discrete Fourier transform of a real signal and its power per channel.

    Attributes
    ----------
    n : int
        Samples of the signal.
    nfft : int
        Length of the transform (the signal zero-padded to it).
    X : ndarray of complex
        ``rfft`` of the signal zero-padded to ``nfft``: channels ``0 .. nfft // 2``.
    P : ndarray
        ``|X|^2``, the periodogram up to a constant factor.
    f : ndarray
        Frequency of each channel, cycles per sample (``k / nfft``).
    total : float
        ``sum(P[1:])``: proportional to the variance of the signal about its mean.
    """

    n: int
    nfft: int
    X: NDArray[np.complex128]
    P: FloatArray
    f: FloatArray
    total: float


def spectrum(x: ArrayLike, *, pad: bool = False) -> Spectrum:
    """The DFT of ``x`` as given (remove the mean or the trend first) and its power.

    With ``pad`` the signal is zero-padded to a fast length of at least twice
    its own, so that multiplying ``X`` by a filter's gain and transforming back
    filters linearly, without wrap-around (the band-pass filters and the
    band ACF of :mod:`analytics.oscillation`); without, ``nfft = n``.

    >>> s = spectrum(np.cos(2 * np.pi * np.arange(8) / 4))
    >>> s.nfft, float(s.f[int(np.argmax(s.P))]), round(s.total, 6)
    (8, 0.25, 16.0)
    """
    values = np.asarray(x, dtype=np.float64)
    n = values.size
    nfft = sfft.next_fast_len(2 * n, real=True) if pad else n
    X = np.asarray(sfft.rfft(values, nfft), dtype=np.complex128)
    P = np.asarray(X.real**2 + X.imag**2, dtype=np.float64)
    f = np.arange(P.size, dtype=np.float64) / nfft
    return Spectrum(n, nfft, X, P, f, float(P[1:].sum()))


def power_spectrum(x: ArrayLike, ts: float) -> tuple[FloatArray, FloatArray]:
    """Periods (s, longest first) and power of ``x`` normalised to its largest peak.

    A Hann-windowed periodogram of the linearly detrended signal
    (:func:`spectrum`; non-finite samples are left out of
    the mean and treated as its value), one-sided: the Nyquist channel, which
    has no negative-frequency twin, counts once.  The zero-frequency channel is
    dropped, so the first period is the window length.
    """
    values = np.asarray(x, dtype=np.float64)
    finite = np.isfinite(values)
    if finite.sum() < 8:
        raise ValueError(f"power_spectrum needs at least 8 finite samples, got {finite.sum()}")
    filled = np.where(finite, values, np.mean(values[finite]))
    spec = spectrum(detrend(filled) * sps.get_window("hann", filled.size))
    power = spec.P[1:].copy()
    if spec.nfft % 2 == 0:
        power[-1] /= 2.0
    peak = float(power.max())
    return spec.nfft * ts / np.arange(1, spec.P.size), power / peak if peak > 0 else power
