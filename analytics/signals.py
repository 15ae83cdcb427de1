"""Signal helpers shared by the detectors: zero crossings and the autocorrelation.

Each is written once here; the oscillation detection (Thornhill et al. 2003:
ACF zero crossings), the cycle shapes (cycles cut at PV's upward crossings),
the OP-PV cross-correlation test, the model check's correlation time and the
dashboard's ACF plot use them.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from analytics.types import FloatArray

__all__ = ["autocorrelation", "upward_crossings", "zero_crossings"]


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
