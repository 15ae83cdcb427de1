"""Plant-wide oscillation detection: which signals share an oscillation.

One sticky valve (or one oscillating disturbance) makes many loops of a unit
oscillate at the same period.  Thornhill et al. (2003) find such plant-wide
oscillations by grouping the measurements whose spectra peak at the same
frequency; every distinct oscillation then has a root cause of its own.
Here every signal is screened with
:func:`analytics.oscillation.detect_oscillations`, and the oscillations are
grouped when

* their periods agree within ``max(period_tolerance, 1 / (3 r))`` (``r``
  the smaller regularity: ``Tp / (3 r)`` is the cycle-to-cycle spread of the
  period that Thornhill's regularity implies, as in
  :func:`analytics.oscillation.detect_loop_oscillation`), and
* their power spectra around the group's frequency are similar: the cosine
  similarity of the spectra over ``f / 2 .. 2 f`` must reach
  ``min_similarity``, so that a narrow line and a broad hump that happen to
  peak near each other are not taken for one oscillation.

The default search stops at periods of ``min_period_samples`` (its band
edges must stay below the Nyquist frequency).  A limit cycle at the scan rate
of a DCS, or aliased by slow historian sampling, has a period of two to a few
samples (the sticky reactor cooling valve of the Tennessee Eastman process at
3-minute sampling: 2.2 samples).  A second pass with a narrow band covers
those periods; because a narrow band makes any noise look regular, only
oscillations that hold most of the signal's variance are kept there.

:func:`envelope_variation` tells a self-sustained oscillation (a limit cycle,
constant amplitude) from a noise-driven resonance (randomly waxing and
waning, Rayleigh-distributed envelope).

References
----------
.. [1] N. F. Thornhill, B. Huang and H. Zhang, "Detection of multiple
   oscillations in control loops", J. Process Control 13 (2003) 91-100.
.. [2] N. F. Thornhill, F. Cox, M. A. Paulonis, "Diagnosis of plant-wide
   oscillation through data-driven analysis and process understanding",
   Control Eng. Practice 11 (2003) 1481-1490 (spectral similarity of the
   measurements of a unit).
.. [3] S. O. Rice, "Mathematical analysis of random noise", Bell System
   Technical Journal 24 (1945) 46-156 (the envelope of narrow-band Gaussian
   noise is Rayleigh-distributed).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from analytics.errors import DataError
from analytics.oscillation import (
    RAYLEIGH_ENVELOPE_CV,
    Oscillation,
    detect_oscillations,
    envelope_variation,
)
from analytics.signals import spectrum
from analytics.types import FloatArray

__all__ = [
    "RAYLEIGH_ENVELOPE_CV",
    "GroupMember",
    "OscillationGroup",
    "envelope_variation",
    "find_oscillation_groups",
]


FAST_PERIOD_BAND_RATIO = 1.05
"""Band edges of the second, fast-period pass (``fc / 1.05 .. fc * 1.05``)."""

FAST_PERIOD_MIN_POWER = 0.5
"""Share of the variance a fast-period oscillation must hold: a band of +-5 % lets
noise pass for a regular oscillation; a limit cycle at the scan rate dominates its
signal (94 % of XMV(10) in the Tennessee Eastman run with a sticky valve, against
at most 10 % for the spurious narrow-band peaks of normal operation)."""

_SPECTRUM_BINS = 24
"""Log-spaced bins over ``f / 2 .. 2 f`` in which spectra are compared."""


@dataclass(frozen=True)
class GroupMember:
    """One signal's share in a plant-wide oscillation.

    Attributes
    ----------
    signal : str
        The signal's name as given to :func:`find_oscillation_groups`.
    period_s : float
        Its own oscillation period, s.
    regularity : float
        Thornhill's regularity ``r`` of its oscillation.
    power_fraction : float
        Share of the signal's (detrended) variance at the oscillation: how
        much this signal takes part (the oscillation contribution).
    amplitude : float
        Half peak-to-peak amplitude of the band-passed oscillation, in the
        signal's units.
    similarity : float
        Cosine similarity of its spectrum around the group frequency with
        that of the group's strongest member (1 for that member).
    """

    signal: str
    period_s: float
    regularity: float
    power_fraction: float
    amplitude: float
    similarity: float


@dataclass(frozen=True)
class OscillationGroup:
    """Signals that oscillate together.

    Attributes
    ----------
    period_s : float
        Power-weighted mean period of the members, s.
    members : tuple of GroupMember
        Strongest (largest power fraction) first.
    """

    period_s: float
    members: tuple[GroupMember, ...]

    @property
    def signals(self) -> tuple[str, ...]:
        """Names of the member signals."""
        return tuple(m.signal for m in self.members)


def _band_spectrum(power: FloatArray, samples: int, period_samples: float) -> FloatArray:
    """Unit-norm ``power`` in log-spaced bins over ``f / 2 .. 2 f`` (``f = 1 / period``)."""
    freq = np.arange(power.size) / samples
    f0 = 1.0 / period_samples
    edges = f0 * np.geomspace(0.5, 2.0, _SPECTRUM_BINS + 1)
    index = np.searchsorted(edges, freq, side="right") - 1
    inside = (index >= 0) & (index < _SPECTRUM_BINS)
    binned = np.bincount(index[inside], weights=power[inside], minlength=_SPECTRUM_BINS)
    norm = float(np.linalg.norm(binned))
    return np.asarray(binned / norm if norm > 0 else binned, dtype=np.float64)


def _signal_oscillations(x: FloatArray, ts: float, min_period_samples: float) -> list[Oscillation]:
    """The oscillations of one signal: the default search, then the fast-period pass."""
    found = list(detect_oscillations(x, ts, min_period_samples=min_period_samples).oscillations)
    if min_period_samples > 2.0:
        fast = detect_oscillations(
            x, ts, min_period_samples=2.0,
            band_ratio=FAST_PERIOD_BAND_RATIO, acf_band_ratio=FAST_PERIOD_BAND_RATIO,
        )
        found.extend(
            o for o in fast.oscillations
            if o.period_s / ts < min_period_samples
            and o.power_fraction >= FAST_PERIOD_MIN_POWER
        )
    return found


def find_oscillation_groups(
    signals: Mapping[str, ArrayLike],
    ts: float,
    *,
    period_tolerance: float = 0.15,
    min_similarity: float = 0.5,
    min_period_samples: float = 6.0,
) -> tuple[OscillationGroup, ...]:
    """Group the signals of a unit (or a plant) by the oscillations they share.

    Parameters
    ----------
    signals : mapping of str to array_like
        Equally long, uniformly sampled, finite signals (OPs, PVs, other
        measurements) by name.
    ts : float
        Sampling interval, s.
    period_tolerance : float
        Smallest relative period difference accepted within a group (see
        the module docstring for the regularity-based widening).
    min_similarity : float
        Cosine similarity of band spectra needed to join a group.
    min_period_samples : float
        Shortest period of the default search; shorter periods (down to two
        samples) come from the fast-period pass.

    Returns
    -------
    tuple of OscillationGroup
        The groups, the one with the most members first (ties: larger total
        power fraction first).  A signal belongs to at most one group per
        oscillation it carries, so it can sit in several groups.

    Raises
    ------
    DataError
        If ``signals`` is empty, ``ts`` is not positive, or a signal is not
        one-dimensional, finite and as long as the others (the message names
        the signal).

    Examples
    --------
    Two loops shaken by one 50-sample cycle, a third by a 120-sample one:

    >>> k = np.arange(3000)
    >>> rng = np.random.default_rng(0)
    >>> noise = lambda: 0.2 * rng.standard_normal(k.size)
    >>> groups = find_oscillation_groups({
    ...     "a": np.sin(2 * np.pi * k / 50) + noise(),
    ...     "b": 0.5 * np.sin(2 * np.pi * k / 50 + 1.0) + noise(),
    ...     "c": np.sin(2 * np.pi * k / 120) + noise()}, 1.0)
    >>> [(round(g.period_s), g.signals) for g in groups]
    [(50, ('a', 'b')), (120, ('c',))]
    """
    if not (math.isfinite(ts) and ts > 0):
        raise DataError(f"sampling interval ts must be positive and finite, got {ts!r}")
    if not signals:
        raise DataError("no signals to group")
    arrays: dict[str, FloatArray] = {}
    for name, x in signals.items():
        a = np.asarray(x, dtype=np.float64)
        if a.ndim != 1:
            raise DataError(f"signal {name!r} must be one-dimensional, got shape {a.shape}")
        bad = np.flatnonzero(~np.isfinite(a))
        if bad.size:
            raise DataError(f"signal {name!r} has a non-finite value at index {bad[0]}")
        arrays[name] = a
    lengths = {a.size for a in arrays.values()}
    if len(lengths) > 1:
        sizes = {name: a.size for name, a in arrays.items()}
        raise DataError(f"signals differ in length: {sizes}")

    candidates = [
        (name, o) for name, a in arrays.items()
        for o in _signal_oscillations(a, ts, min_period_samples)
    ]
    candidates.sort(key=lambda c: c[1].power_fraction, reverse=True)
    samples = next(iter(lengths))
    # periodograms without the mean: channel i at i / samples
    power = {name: spectrum(a - a.mean()).P for name, a in arrays.items()}
    groups: list[list[tuple[str, Oscillation, float]]] = []
    for name, osc in candidates:
        for members in groups:
            head_name, head, _ = members[0]
            if any(m[0] == name for m in members):
                continue
            tolerance = max(period_tolerance, 1.0 / (3.0 * min(osc.regularity, head.regularity)))
            if abs(osc.period_s - head.period_s) > tolerance * max(osc.period_s, head.period_s):
                continue
            period = head.period_s / ts
            similarity = float(np.dot(_band_spectrum(power[name], samples, period),
                                      _band_spectrum(power[head_name], samples, period)))
            if similarity >= min_similarity:
                members.append((name, osc, similarity))
                break
        else:
            groups.append([(name, osc, 1.0)])
    result = []
    for members in groups:
        weights = np.array([o.power_fraction for _, o, _ in members])
        periods = np.array([o.period_s for _, o, _ in members])
        result.append(
            OscillationGroup(
                period_s=float(np.dot(weights, periods) / weights.sum()),
                members=tuple(
                    GroupMember(name, o.period_s, o.regularity, o.power_fraction, o.amplitude, s)
                    for name, o, s in members
                ),
            )
        )
    result.sort(key=lambda g: (len(g.members), sum(m.power_fraction for m in g.members)),
                reverse=True)
    return tuple(result)
