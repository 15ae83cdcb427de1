"""How many sticky valves shape a group's cycle: the decomposition of thesis section 2.3.5.

A sticky valve turns any OP into a square MV; the process turns that square
into a square, a smooth square or a triangle (thesis Table 2.1), while a
healthy valve passes a smooth signal that the low-pass loop reduces to a
sinusoid.  With ``n`` valves acting on a PV at the common frequency, one
cycle of the PV is therefore the sum of ``k`` known shapes (one per sticky
valve) and ``n - k`` sinusoids, each with its own bias, magnitude and phase
(thesis step 2, Fig. 2.6).  Sinusoids of one frequency add up to one
sinusoid, so the model of a cycle is::

    y(t) = b + c cos(2 pi t / T) + d sin(2 pi t / T) + sum_{j=1..k} a_j s_j(t - t_j)

Each ``s_j`` is a square wave of duty ``delta`` passed through a first-order
lag of time constant ``lambda`` (in periods): ``lambda = 0`` is the square,
small ``lambda`` the smooth square of a fast process, ``lambda -> inf`` (an
integrator) the triangle of a slow or integrating one -- the two geometric
parameters per shape of thesis Remark 1.  The components are chosen greedily
(largest drop of the residual over every shape and every shift) and then
revised one at a time until none changes (backfitting).

Choosing k by the fit alone would always pick the largest: a model with
more components fits any cycle at least as well.  The thesis compares raw
MSEs (Tables 2.4-2.6); here each PV is cut into its cycles, the model is
fitted to the mean of the training cycles and scored on held-out cycles
(``folds``-fold cross-validation over interleaved cycles), and ``k`` is the
smallest number of shapes whose held-out error is within one standard error
of the best (the one-standard-error rule; the standard error is that of the
per-cycle difference to the best ``k``) or within ``min_gain`` of it (1 % of a
PV's variance): in a long record of very regular cycles a tenth of a percent
is "significant", yet no valve worth naming contributes so little.

The count is only as good as the premise that a healthy valve contributes a
sinusoid.  On the simulated column (thesis section 2.4) it does not hold:
the healthy loops answer every slip of the sticky valve with their own
closed-loop transients, and those shapes are counted too
(``benchmarks/plantwide.py`` prints the figures).

References
----------
.. [1] Thesis section 2.3.5 (step 2, Remarks 1-3), Tables 2.1, 2.4-2.7,
   Fig. 2.6 and Fig. 2.8.
.. [2] L. Breiman, J. Friedman, R. Olshen and C. Stone, *Classification and
   Regression Trees*, Wadsworth 1984, section 3.4.3 (the one-standard-error
   rule); T. Hastie, R. Tibshirani and J. Friedman, *The Elements of
   Statistical Learning*, 2nd ed., Springer 2009, section 7.10.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import fft as sfft

from analytics.errors import DataError
from analytics.oscillation import bandpass
from analytics.signals import upward_crossings
from analytics.stiction.shape_rules import (
    POINTS_PER_CYCLE,
    classify_cycle_shape,
    resample_segments,
)
from analytics.types import FloatArray

__all__ = [
    "SHAPE_DUTIES",
    "SHAPE_LAGS",
    "CycleFit",
    "ShapeDecomposition",
    "decompose_cycles",
    "fit_cycle",
]


SHAPE_DUTIES = (0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5)
"""Duty cycles of the square waves (a duty ``d`` and ``1 - d`` differ only in sign)."""
SHAPE_LAGS = (0.0, 0.02, 0.05, 0.1, 0.2, 0.5, math.inf)
"""First-order lags (time constants in periods) that turn the square into a smooth
square (small) or a triangle (``inf``: the integrated square)."""


@lru_cache(maxsize=1)
def _shape_bank() -> FloatArray:
    """Every shape at every shift, unit norm and zero mean: rows ``(shape * POINTS + shift)``."""
    points = POINTS_PER_CYCLE
    harmonic = np.arange(points // 2 + 1)
    omega = 2.0 * np.pi * harmonic
    phase = (np.arange(points) + 0.5) / points
    rows: list[FloatArray] = []
    for duty in SHAPE_DUTIES:
        square = sfft.rfft(np.where(phase < duty, 1.0, -1.0))
        for lag in SHAPE_LAGS:
            response: NDArray[np.complex128]
            if lag == 0.0:
                response = np.ones(harmonic.size, dtype=np.complex128)
            elif math.isinf(lag):
                response = np.zeros(harmonic.size, dtype=np.complex128)
                response[1:] = 1.0 / (1j * omega[1:])
            else:
                response = np.asarray(1.0 / (1.0 + 1j * omega * lag), dtype=np.complex128)
            shape = sfft.irfft(square * response, points)
            shape -= shape.mean()
            shape /= np.linalg.norm(shape)
            rows.extend(np.roll(shape, shift) for shift in range(points))
    return np.asarray(rows, dtype=np.float64)


@dataclass(frozen=True)
class CycleFit:
    """A cycle fitted by bias, one sinusoid and ``k`` shapes (:func:`fit_cycle`).

    Attributes
    ----------
    fitted : ndarray
        The model cycle.
    components : tuple of ndarray
        Each shape times its amplitude (zero mean).
    shapes : tuple of str
        ``"square"``, ``"triangular"`` or ``"sinusoidal"`` for each component, as
        :func:`analytics.stiction.shape_rules.classify_cycle_shape` names it.
    duties, lags : tuple of float
        Duty cycle and lag (periods) of each component's square wave.
    """

    fitted: FloatArray
    components: tuple[FloatArray, ...]
    shapes: tuple[str, ...]
    duties: tuple[float, ...]
    lags: tuple[float, ...]


def _design(base: FloatArray, chosen: list[int]) -> FloatArray:
    """``base`` followed by the bank rows ``chosen`` as columns."""
    bank = _shape_bank()
    return np.column_stack([base, *(bank[c] for c in chosen)])


def _best_addition(y: FloatArray, base: FloatArray, chosen: list[int]) -> int:
    """The bank row whose addition to ``chosen`` lowers the least-squares residual most."""
    bank = _shape_bank()
    q, _ = np.linalg.qr(_design(base, chosen))
    residual = y - q @ (q.T @ y)
    projection = bank @ q
    left = 1.0 - np.einsum("ij,ij->i", projection, projection)
    usable = left > 1e-6
    gain = np.zeros(bank.shape[0])
    gain[usable] = (bank[usable] @ residual) ** 2 / left[usable]
    return int(np.argmax(gain))


def _cycle_base() -> FloatArray:
    """Bias, cosine and sine of one period: the columns every model shares."""
    angle = 2.0 * np.pi * np.arange(POINTS_PER_CYCLE) / POINTS_PER_CYCLE
    return np.column_stack([np.ones(POINTS_PER_CYCLE), np.cos(angle), np.sin(angle)])


def _backfit(y: FloatArray, base: FloatArray, chosen: list[int], max_rounds: int) -> list[int]:
    """Revise the shapes one at a time, each the best given the others, until none changes."""
    chosen = list(chosen)
    for _ in range(max_rounds):
        changed = False
        for j in range(len(chosen)):
            best = _best_addition(y, base, chosen[:j] + chosen[j + 1:])
            if best != chosen[j]:
                chosen[j], changed = best, True
        if not changed:
            break
    return chosen


def _nested_shapes(y: FloatArray, max_k: int, max_rounds: int) -> list[list[int]]:
    """The shapes (bank rows) of the fits with ``k = 0 .. max_k``, each grown from the last."""
    base = _cycle_base()
    fits: list[list[int]] = [[]]
    for _ in range(max_k):
        grown = [*fits[-1], _best_addition(y, base, fits[-1])]
        fits.append(_backfit(y, base, grown, max_rounds))
    return fits


def _fitted(y: FloatArray, chosen: list[int]) -> tuple[FloatArray, FloatArray]:
    """Least-squares coefficients and fitted cycle for the shapes ``chosen``."""
    design = _design(_cycle_base(), chosen)
    coef = np.asarray(np.linalg.lstsq(design, y, rcond=None)[0], dtype=np.float64)
    return coef, np.asarray(design @ coef, dtype=np.float64)


def fit_cycle(y: ArrayLike, k: int, *, max_rounds: int = 5) -> CycleFit:
    """Least-squares fit of one cycle by bias, a sinusoid and ``k`` known shapes.

    ``y`` holds one period at :data:`analytics.stiction.shape_rules.POINTS_PER_CYCLE`
    points.  See the module docstring for the model and the search.

    Examples
    --------
    A square wave of duty 0.3 plus a sinusoid is split back into the two:

    >>> t = np.arange(64) / 64
    >>> y = np.where((t + 0.2) % 1 < 0.3, 1.0, -1.0) + 0.5 * np.sin(2 * np.pi * t)
    >>> fit = fit_cycle(y, 1)
    >>> fit.shapes, fit.duties, float(np.abs(y - fit.fitted).max()) < 1e-9
    (('square',), (0.3,), True)
    """
    ya = np.asarray(y, dtype=np.float64)
    if ya.shape != (POINTS_PER_CYCLE,):
        raise DataError(f"a cycle must hold {POINTS_PER_CYCLE} points, got shape {ya.shape}")
    if k < 0:
        raise DataError(f"the number of shapes must be >= 0, got {k}")
    chosen = _nested_shapes(ya, k, max_rounds)[k]
    coef, fitted = _fitted(ya, chosen)
    bank = _shape_bank()
    components = tuple(float(a) * bank[c] for a, c in zip(coef[3:], chosen, strict=True))
    per_duty = len(SHAPE_LAGS) * POINTS_PER_CYCLE
    return CycleFit(
        fitted=fitted,
        components=components,
        shapes=tuple(
            classify_cycle_shape(c, POINTS_PER_CYCLE).shape for c in components
        ),
        duties=tuple(SHAPE_DUTIES[c // per_duty] for c in chosen),
        lags=tuple(SHAPE_LAGS[(c % per_duty) // POINTS_PER_CYCLE] for c in chosen),
    )


@dataclass(frozen=True)
class ShapeDecomposition:
    """Result of :func:`decompose_cycles`.

    Attributes
    ----------
    k : int
        Number of known shapes (sticky valves) chosen by the one-standard-error
        rule on the held-out error.
    n : int
        Number of valves that can act on the PVs (the loops of the group).
    held_out_error : tuple of float
        Mean held-out squared error per cycle point for ``k = 0, 1, ...``,
        summed over the PVs (each scaled to unit variance): the
        cross-validated counterpart of thesis Tables 2.4-2.6.
    held_out_se : tuple of float
        Standard error of each ``held_out_error`` entry's per-cycle
        difference to the best one.
    per_signal_error : mapping of str to tuple of float
        The same error for each PV alone.
    structures : mapping of str to tuple of str
        Each PV's structure with ``k`` shapes, fitted to all its cycles, in
        the notation of thesis Table 2.7: the shapes, then ``n - k``
        ``"sinusoidal"``.
    cycles : mapping of str to int
        Complete cycles used per PV.
    """

    k: int
    n: int
    held_out_error: tuple[float, ...]
    held_out_se: tuple[float, ...]
    per_signal_error: Mapping[str, tuple[float, ...]]
    structures: Mapping[str, tuple[str, ...]]
    cycles: Mapping[str, int]


def _cycles(x: FloatArray, period: float) -> FloatArray:
    """The complete cycles of ``x`` (between upward zero crossings of its fundamental),
    resampled to ``POINTS_PER_CYCLE`` points, in units of ``std(x)``.

    The cycles are not filtered: a filter would round the corners of the squares
    that the shapes are looking for, and the noise averages out over the cycles.
    """
    centred = x - x.mean()
    up = upward_crossings(bandpass(x, period))
    lengths = np.diff(up)
    regular = (lengths > 0.7 * period) & (lengths < 1.4 * period)
    starts, stops = up[:-1][regular], up[1:][regular]
    stops = stops - (stops - starts) / POINTS_PER_CYCLE  # the next cycle's first point
    spread = float(centred.std())
    scale = spread if spread > 0 else 1.0
    return resample_segments(centred / scale, starts, stops, POINTS_PER_CYCLE)


def decompose_cycles(
    pvs: Mapping[str, ArrayLike],
    period_samples: float,
    *,
    n_valves: int,
    max_k: int = 3,
    folds: int = 5,
    min_cycles: int = 6,
    min_gain: float = 0.01,
) -> ShapeDecomposition:
    """Choose the number of sticky valves from the shapes of the PV cycles (thesis step 2).

    Parameters
    ----------
    pvs : mapping of str to array_like
        The PVs of the loops that oscillate together, equally long.
    period_samples : float
        The common period, in samples.
    n_valves : int
        Valves that act on these PVs (``n``); ``k`` is at most
        ``min(n_valves, max_k)``.
    max_k : int
        Most shapes tried.
    folds : int
        Folds of the cross-validation over interleaved cycles.
    min_cycles : int
        Fewest complete cycles per PV.
    min_gain : float
        Held-out error (in units of one PV's variance) that more shapes must
        save before they count: an extra sticky valve must explain a visible
        part of the cycles, not just be detectable in a long record.

    Returns
    -------
    ShapeDecomposition

    Raises
    ------
    DataError
        If no PV is given, the period is shorter than 8 samples, or a PV holds
        fewer than ``min_cycles`` complete cycles (the message names it).

    Examples
    --------
    Two square waves of different duty cycles and phases in one PV, and a
    sinusoid in another, with noise:

    >>> rng = np.random.default_rng(0)
    >>> t = np.arange(4000) / 100
    >>> squares = np.where(t % 1 < 0.3, 1.0, -1.0) + np.where((t + 0.5) % 1 < 0.15, 0.8, -0.8)
    >>> result = decompose_cycles({
    ...     "pv1": squares + 0.1 * rng.standard_normal(t.size),
    ...     "pv2": np.sin(2 * np.pi * t) + 0.1 * rng.standard_normal(t.size)},
    ...     100.0, n_valves=3)
    >>> result.k, result.structures["pv1"]
    (2, ('square', 'square', 'sinusoidal'))
    """
    if not pvs:
        raise DataError("no PV to decompose")
    if not period_samples >= 8.0:
        raise DataError(
            f"the period spans {period_samples:.1f} samples; shapes need at least 8 per cycle"
        )
    largest = max(0, min(n_valves, max_k))
    cycles: dict[str, FloatArray] = {}
    for name, x in pvs.items():
        xa = np.asarray(x, dtype=np.float64)
        found = _cycles(xa, period_samples)
        if found.shape[0] < max(min_cycles, folds):
            raise DataError(
                f"{name}: {found.shape[0]} complete cycles, at least "
                f"{max(min_cycles, folds)} are needed"
            )
        cycles[name] = found
    per_signal: dict[str, FloatArray] = {}
    for name, c in cycles.items():
        fold = np.arange(c.shape[0]) % folds
        errors = np.zeros((largest + 1, c.shape[0]))
        for f in range(folds):
            held_out = fold == f
            mean_cycle = c[~held_out].mean(axis=0)
            for k, chosen in enumerate(_nested_shapes(mean_cycle, largest, max_rounds=5)):
                fitted = _fitted(mean_cycle, chosen)[1]
                errors[k, held_out] = np.mean((c[held_out] - fitted) ** 2, axis=1)
        per_signal[name] = errors
    # Cycles are counted per PV; the total compares k over the cycles all PVs share.
    shared = min(e.shape[1] for e in per_signal.values())
    total = sum(e[:, :shared] for e in per_signal.values())
    assert isinstance(total, np.ndarray)
    mean = total.mean(axis=1)
    best = int(np.argmin(mean))
    difference = total - total[best]
    se = difference.std(axis=1, ddof=1) / math.sqrt(shared)
    k = next(
        j for j in range(largest + 1)
        if difference[j].mean() <= max(se[j], min_gain)
    )
    structures = {}
    for name, c in cycles.items():
        fit = fit_cycle(c.mean(axis=0), k)
        structures[name] = fit.shapes + ("sinusoidal",) * (n_valves - k)
    return ShapeDecomposition(
        k=k,
        n=n_valves,
        held_out_error=tuple(float(v) for v in mean),
        held_out_se=tuple(float(v) for v in se),
        per_signal_error={name: tuple(float(v) for v in e.mean(axis=1))
                          for name, e in per_signal.items()},
        structures=structures,
        cycles={name: int(c.shape[0]) for name, c in cycles.items()},
    )
