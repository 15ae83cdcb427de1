"""Wave shapes of stiction cycles (thesis Tables 2.1-2.2) and the cycle tools shared
by the shape-based detectors.

A sticky valve turns whatever OP it receives into a square MV; the process and
the controller then smooth that square into the shapes of thesis Table 2.2:

===================  ==========  ============================  ===============
Process              Controller  OP                            PV
===================  ==========  ============================  ===============
Integrating          P           sharp triangle                sharp triangle
Integrating          PI          smooth triangle (parabolic)   sharp triangle
Fast self-regulating P           smooth square                 smooth square
Fast self-regulating PI          triangle                      smooth square
Slow self-regulating P           sharp triangle                sharp triangle
Slow self-regulating PI          smooth triangle (parabolic)   sharp triangle
===================  ==========  ============================  ===============

whereas a linear loop (an external sinusoidal disturbance, aggressive tuning)
low-pass filters a smooth excitation and shows sinusoids in both signals
(thesis section 2.3.3).  :func:`classify_cycle_shape` fits sine, triangle and
square templates (thesis Fig. 2.6) to one cycle; :class:`ShapeRulesDetector`
classifies OP and PV cycle by cycle and applies the table.

The module also holds the helpers that the area-ratio and curve-fitting
detectors share: the window check (:func:`window_problem`), the
shape-preserving filter (:func:`shape_filter`), the half-cycle segmentation
(:func:`half_cycle_bounds`) and the resampling of cycles to a fixed number of
points (:func:`resample_segments`).

References
----------
.. [1] Thesis section 2.3.3, Tables 2.1 and 2.2, Fig. 2.6 (square, triangular
   and sinusoidal structures).
.. [2] R. Srinivasan, R. Rengaswamy and R. Miller, "Control performance
   assessment 1: Qualitative approach for stiction diagnosis", Ind. Eng.
   Chem. Res. 44 (2005) 6708-6718 (thesis ref. [44]): the experimental
   summary behind the table and the cycle-by-cycle comparison with square
   and triangular shapes.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import lru_cache
from typing import ClassVar, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import fft as sfft

from analytics.oscillation import bandpass
from analytics.signals import upward_crossings, zero_crossings
from analytics.stiction.evidence import (
    INTEGRATING,
    NO_STICTION,
    SELF_REGULATING,
    STICTION,
    LoopWindow,
    MethodEvidence,
    ProcessType,
    margin_confidence,
)
from analytics.types import FloatArray

__all__ = [
    "SHAPES",
    "CycleShape",
    "Shape",
    "ShapeRulesDetector",
    "classify_cycle_shape",
    "half_cycle_bounds",
    "resample_segments",
    "shape_filter",
    "window_problem",
]


Shape = Literal["square", "triangular", "sinusoidal"]
SHAPES: tuple[Shape, ...] = ("square", "triangular", "sinusoidal")

#: Points per period at which cycles are compared with the templates.
POINTS_PER_CYCLE = 64
#: Fewest samples per period for which a wave shape can be told at all.
MIN_PERIOD_SAMPLES = 8.0
#: Duty cycles of the square templates and rise fractions of the triangles.
_ASYMMETRIES = (0.25, 0.375, 0.5, 0.625, 0.75)
#: Time constants (in periods) of the first-order lag that smooths the square
#: templates: a square, and the "smooth square" PV of a fast self-regulating loop.
_SQUARE_LAGS = (0.0, 0.025, 0.05)


# ----------------------------------------------------------------------------
# helpers shared by the shape-based detectors


def window_problem(
    window: LoopWindow, signals: tuple[str, ...], min_cycles: float
) -> str | None:
    """Why the shape-based methods cannot analyse ``window``, or None if they can.

    They need every signal named in ``signals``, a detected oscillation
    period of at least :data:`MIN_PERIOD_SAMPLES` samples and at least
    ``min_cycles`` complete cycles in the window.

    Examples
    --------
    >>> w = LoopWindow(ts=1.0, op=np.zeros(500), pv=np.zeros(500), period_s=200.0)
    >>> window_problem(w, ("op", "pv"), 3.0)
    'the window holds 2.5 cycles, at least 3 are needed'
    >>> window_problem(w, ("op", "pv"), 2.0) is None
    True
    """
    missing = [name for name in signals if getattr(window, name) is None]
    if missing:
        return f"the window has no {' and no '.join(n.upper() for n in missing)}"
    period = window.period_samples
    if period is None:
        return "the loop does not oscillate (no period detected)"
    if period < MIN_PERIOD_SAMPLES:
        return (
            f"the period is only {period:.1f} samples, too few samples per cycle "
            f"(at least {MIN_PERIOD_SAMPLES:g})"
        )
    cycles = window.samples / period
    if cycles < min_cycles:
        return f"the window holds {cycles:.1f} cycles, at least {min_cycles:g} are needed"
    return None


def shape_filter(x: ArrayLike, period_samples: float, *, harmonics: float = 7.0) -> FloatArray:
    """Remove drift and noise but keep the wave shape of an oscillation.

    Zero-phase Butterworth band-pass (:func:`analytics.oscillation.bandpass`)
    with half-power edges at half the oscillation frequency and at
    ``harmonics`` times it: the fundamental passes with a gain of about 0.98,
    the 3rd and 5th harmonics that make a square or a triangle are kept,
    trends and noise above the band are removed.

    Examples
    --------
    >>> k = np.arange(4000)
    >>> square = np.sign(np.sin(2 * np.pi * k / 100))
    >>> y = shape_filter(square + 0.001 * k, 100)
    >>> bool(np.percentile(np.abs(y[500:-500]), 25) > 0.9)   # still flat-topped
    True
    """
    centre = period_samples / np.sqrt(harmonics / 2.0)
    return bandpass(x, centre, band_ratio=float(np.sqrt(2.0 * harmonics)))


def half_cycle_bounds(x: FloatArray, hysteresis: float = 0.2) -> FloatArray:
    """Zero crossings of ``x`` that separate its half cycles.

    A new half cycle starts only when the signal, after crossing zero, goes
    on to reach ``hysteresis`` times its amplitude (``sqrt(2) std(x)``) on the
    other side, so noise that chatters around zero does not split a half
    cycle; the boundary is the last (interpolated) zero crossing before that.

    Returns
    -------
    ndarray
        Increasing fractional sample positions; half cycle ``i`` runs from
        element ``i`` to element ``i + 1``.

    Examples
    --------
    >>> k = np.arange(1000)
    >>> half_cycle_bounds(np.sin(2 * np.pi * (k + 0.5) / 100))[:3]
    array([ 49.5,  99.5, 149.5])
    """
    level = hysteresis * np.sqrt(2.0) * float(np.std(x))
    side = np.where(x > level, 1, np.where(x < -level, -1, 0))
    reached = np.flatnonzero(side)
    sides = side[reached]
    switches = reached[1:][sides[1:] != sides[:-1]]
    crossings = zero_crossings(x)
    before = np.searchsorted(crossings, switches) - 1
    return crossings[before[before >= 0]]


def resample_segments(
    x: FloatArray, starts: FloatArray, stops: FloatArray, points: int
) -> FloatArray:
    """Each segment ``[start, stop]`` of ``x`` linearly interpolated at ``points`` points.

    Returns an array of shape ``(len(starts), points)``; the end points are
    included, so a half cycle between two zero crossings starts and ends
    near zero.

    Examples
    --------
    >>> resample_segments(np.arange(10.0), np.array([0.0, 4.5]), np.array([2.0, 8.5]), 3)
    array([[0. , 1. , 2. ],
           [4.5, 6.5, 8.5]])
    """
    u = np.linspace(0.0, 1.0, points)
    positions = starts[:, None] + (stops - starts)[:, None] * u[None, :]
    values = np.interp(positions.ravel(), np.arange(x.size, dtype=np.float64), x)
    return values.reshape(positions.shape)


# ----------------------------------------------------------------------------
# the shape classifier


@dataclass(frozen=True)
class CycleShape:
    """Best-fitting wave shape of one cycle.

    Attributes
    ----------
    shape : {"square", "triangular", "sinusoidal"}
        The template with the smallest fit error.
    errors : mapping of str to float
        Normalised least-squares error ``1 - rho^2`` of each template (the
        residual variance over the signal variance; 0 is a perfect fit).  At
        64 points per cycle a pure triangle leaves 0.015 to the sine and 0.14
        to the (smoothed) squares; a pure square leaves 0.19 to the sine and
        0.25 to the triangles; a sine leaves 0.015 to the triangles and 0.08
        to the smoothed squares.
    distinct : bool
        True if the cycle is clearly sinusoidal or clearly not: a sine
        winner leaves at most ``1 / margin`` of the error of the better of
        square and triangle, a square or triangle winner at most
        ``1 / margin`` of the sine's error.  With ``margin = 1.5`` this is He
        et al.'s ``SI >= 0.6`` (see :mod:`analytics.stiction.curve_fit`).
    """

    shape: Shape
    errors: Mapping[str, float] = field(default_factory=dict)
    distinct: bool = False


def _lagged_square(phase: FloatArray, duty: float, lag: float) -> FloatArray:
    """Periodic response of a unit-gain first-order lag to a +-1 square wave.

    ``phase`` in ``[0, 1)`` is the position within the period, ``duty`` the
    share of the period at +1 and ``lag`` the time constant in periods
    (0: the square itself).  Within each level the output approaches it
    exponentially from the value the other level left (the "smooth square"
    PV of a fast self-regulating loop, thesis Table 2.2).
    """
    if lag == 0:
        return np.where(phase < duty, 1.0, -1.0)
    a, b = np.exp(-duty / lag), np.exp(-(1.0 - duty) / lag)
    low = (2.0 * b - 1.0 - a * b) / (1.0 - a * b)  # value at the start of the period
    high = 1.0 - (1.0 - low) * a  # value at the end of the +1 level
    rising = 1.0 - (1.0 - low) * np.exp(-phase / lag)
    falling = -1.0 + (high + 1.0) * np.exp(-(phase - duty) / lag)
    return np.where(phase < duty, rising, falling)


@lru_cache(maxsize=1)
def _template_spectra() -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
    """Conjugate spectra of the centred, unit-norm square and triangle templates.

    Squares: every duty cycle of :data:`_ASYMMETRIES` and lag of
    :data:`_SQUARE_LAGS`; triangles: every rise fraction of
    :data:`_ASYMMETRIES`; one period of :data:`POINTS_PER_CYCLE` points each,
    one template per row.  Every circular shift of a template is one phase,
    so one FFT correlation tries them all.
    """
    phase = np.arange(POINTS_PER_CYCLE) / POINTS_PER_CYCLE
    squares = [_lagged_square(phase, a, lag) for a in _ASYMMETRIES for lag in _SQUARE_LAGS]
    triangles = [
        np.where(phase < a, phase / a, (1.0 - phase) / (1.0 - a)) for a in _ASYMMETRIES
    ]
    spectra = []
    for bank in (np.stack(squares), np.stack(triangles)):
        bank = bank - bank.mean(axis=1, keepdims=True)
        bank /= np.linalg.norm(bank, axis=1, keepdims=True)
        spectra.append(np.conj(sfft.rfft(bank, axis=1)))
    return spectra[0], spectra[1]


def _shape_errors(cycles: FloatArray) -> FloatArray:
    """Normalised fit errors ``(n_cycles, 3)`` in the order of :data:`SHAPES`.

    Each row of ``cycles`` is one period sampled at :data:`POINTS_PER_CYCLE`
    points.  Every template has a free offset, amplitude and phase: the error
    is ``1 - max_phase rho^2`` with ``rho`` the correlation with the template,
    for all :data:`POINTS_PER_CYCLE` phases at once by FFT.  The sine's
    phase is solved exactly by regression on ``sin`` and ``cos``.
    """
    points = cycles.shape[1]
    centred = cycles - cycles.mean(axis=1, keepdims=True)
    energy = np.einsum("ij,ij->i", centred, centred)
    energy = np.where(energy > 0, energy, 1.0)
    spectrum = sfft.rfft(centred, axis=1)
    explained = []
    for bank in _template_spectra():
        correlation = sfft.irfft(spectrum[:, None, :] * bank[None, :, :], points, axis=2)
        explained.append(np.max(correlation**2, axis=(1, 2)))
    # The fundamental's share of the energy: |X_1|^2 carries half of it.
    explained.append(2.0 * np.abs(spectrum[:, 1]) ** 2 / points)
    return np.clip(1.0 - np.stack(explained, axis=1) / energy[:, None], 0.0, 1.0)


def _cycle_shapes(errors: FloatArray, margin: float) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """Index into :data:`SHAPES` of each row's best template and whether it is distinct.

    Distinct means clearly sinusoidal or clearly not: a sine must leave at
    most ``1 / margin`` of the error of the better of square and triangle; a
    square or triangle at most ``1 / margin`` of the sine's error.
    """
    best = np.argmin(errors, axis=1)
    sine = errors[:, SHAPES.index("sinusoidal")]
    other = np.delete(errors, SHAPES.index("sinusoidal"), axis=1).min(axis=1)
    distinct = np.where(
        best == SHAPES.index("sinusoidal"), other >= margin * sine, sine >= margin * other
    )
    return best, distinct


def classify_cycle_shape(
    x: ArrayLike, period_samples: float, *, margin: float = 1.5
) -> CycleShape:
    """Classify the wave shape of one cycle as square, triangular or sinusoidal.

    ``x`` is resampled to :data:`POINTS_PER_CYCLE` points per period and
    compared, with free offset, amplitude and phase, with a sine, with square
    waves (duty cycles 0.25 to 0.75, sharp or smoothed by a first-order lag
    of 2.5 or 5 % of the period: the "smooth square" of Table 2.2) and with
    triangles (rise fractions 0.25 to 0.75), the structures of thesis
    Fig. 2.6.  Filter noisy data first
    (:func:`shape_filter`).

    Parameters
    ----------
    x : array_like
        One period of the signal (or a whole number of periods).
    period_samples : float
        The period in samples.
    margin : float, optional
        Error ratio that makes the classification ``distinct`` (see
        :class:`CycleShape`).

    Returns
    -------
    CycleShape

    References
    ----------
    Thesis section 2.3.3 and Fig. 2.6.

    Examples
    --------
    >>> k = np.arange(200)
    >>> classify_cycle_shape(np.sin(2 * np.pi * k / 200 + 1.0), 200).shape
    'sinusoidal'
    >>> tri = np.abs(((k + 30) % 200) - 100.0)
    >>> fit = classify_cycle_shape(tri, 200)
    >>> fit.shape, fit.distinct, round(fit.errors["sinusoidal"], 3)
    ('triangular', True, 0.014)
    >>> classify_cycle_shape(np.where((k + 70) % 200 < 100, 2.0, -1.0), 200).shape
    'square'
    """
    xa = np.asarray(x, dtype=np.float64)
    cycles_in_x = max(round(xa.size / period_samples), 1)
    points = POINTS_PER_CYCLE * cycles_in_x
    resampled = resample_segments(
        xa, np.array([0.0]), np.array([xa.size * (1.0 - 1.0 / points)]), points
    )
    folded = resampled.reshape(cycles_in_x, POINTS_PER_CYCLE).mean(axis=0, keepdims=True)
    errors = _shape_errors(folded)
    best, distinct = _cycle_shapes(errors, margin)
    return CycleShape(
        SHAPES[int(best[0])],
        {shape: float(e) for shape, e in zip(SHAPES, errors[0], strict=True)},
        bool(distinct[0]),
    )


# ----------------------------------------------------------------------------
# thesis Table 2.2 as rules

_ALL_PATTERNS: frozenset[tuple[Shape, Shape]] = frozenset(
    {
        # (OP, PV).  Sharp and smooth (parabolic) triangles are one class here:
        # a parabolic OP fits a sine almost as well as a triangle, so a slow or
        # integrating loop under PI control may show (sinusoidal, triangular).
        ("triangular", "triangular"),  # integrating or slow, P
        ("sinusoidal", "triangular"),  # integrating or slow, PI (parabolic OP)
        ("square", "square"),  # fast self-regulating, P
        ("triangular", "square"),  # fast self-regulating, PI
    }
)
_STICTION_PATTERNS: dict[ProcessType | None, frozenset[tuple[Shape, Shape]]] = {
    # An integrating process turns the square MV into a ramp: PV is triangular.
    INTEGRATING: frozenset(pair for pair in _ALL_PATTERNS if pair[1] == "triangular"),
    SELF_REGULATING: _ALL_PATTERNS,
    None: _ALL_PATTERNS,
}
_LINEAR_PATTERN: tuple[Shape, Shape] = ("sinusoidal", "sinusoidal")


@dataclass(frozen=True, kw_only=True)
class ShapeRulesDetector:
    """Stiction from the OP and PV wave shapes of thesis Table 2.2.

    Every complete cycle (between upward zero crossings of the PV
    fundamental) of the shape-filtered OP and PV is classified with
    :func:`classify_cycle_shape`.  A cycle votes *stiction* when both shapes
    are distinct (clearly sinusoidal or clearly not) and the pair is one of
    Table 2.2's stiction patterns for the process type (all rows when it is
    unknown; an integrating PV must be triangular), and *linear* when both
    are distinct sinusoids; other cycles do not vote.  The index is the share
    of stiction votes among all cycles.

    Attributes
    ----------
    harmonics : float
        Upper edge of :func:`shape_filter`, in multiples of the oscillation
        frequency.
    margin : float
        ``distinct`` margin of the classifier (1.5, from He et al.'s
        ``SI = 0.6``).
    quorum : float
        Share of the cycles that must vote stiction (or linear) for a
        decision.  Table 2.2 is qualitative; 0.6 is this implementation's
        choice (a clear majority).
    min_cycles : float
        Fewest complete cycles in the window.
    max_cycles : int
        At most this many cycles, evenly spread over the window, are
        classified: the share of votes needs no more, and the cost stays
        bounded for fast oscillations in long windows.

    References
    ----------
    Thesis section 2.3.3, Tables 2.1-2.2 and Fig. 2.6.

    Examples
    --------
    A square PV with a triangular OP (a flow loop with PI control and a
    sticky valve):

    >>> t = np.arange(3000.0)
    >>> pv = np.sign(np.sin(2 * np.pi * t / 150))
    >>> op = -np.cumsum(pv) / 40
    >>> w = LoopWindow(ts=1.0, op=op, pv=pv, period_s=150.0)
    >>> ev = ShapeRulesDetector().detect(w)
    >>> ev.decision, ev.index
    ('stiction', 1.0)
    """

    harmonics: float = 7.0
    margin: float = 1.5
    quorum: float = 0.6
    min_cycles: float = 3.0
    max_cycles: int = 100
    name: ClassVar[str] = "shape_rules"

    def detect(self, window: LoopWindow) -> MethodEvidence:
        """Evidence from the OP/PV shape pairs of ``window`` (class docstring)."""
        problem = window_problem(window, ("op", "pv"), self.min_cycles)
        if problem is not None:
            return MethodEvidence.undecided(self.name, problem)
        assert window.op is not None and window.pv is not None
        period = float(window.period_samples or 0.0)
        up = upward_crossings(bandpass(window.pv, period))
        lengths = np.diff(up)
        regular = (lengths > 0.7 * period) & (lengths < 1.4 * period)
        if np.count_nonzero(regular) < self.min_cycles:
            return MethodEvidence.undecided(
                self.name,
                f"only {np.count_nonzero(regular)} regular cycles "
                f"(at least {self.min_cycles:g} are needed)",
            )
        starts, stops = up[:-1][regular], up[1:][regular]
        if starts.size > self.max_cycles:
            chosen = np.linspace(0, starts.size - 1, self.max_cycles).round().astype(np.int64)
            starts, stops = starts[chosen], stops[chosen]
        # The end point of a cycle is the start of the next one: leave it out.
        stops = stops - (stops - starts) / POINTS_PER_CYCLE
        shapes = []
        for signal in (window.op, window.pv):
            filtered = shape_filter(signal, period, harmonics=self.harmonics)
            errors = _shape_errors(resample_segments(filtered, starts, stops, POINTS_PER_CYCLE))
            shapes.append(_cycle_shapes(errors, self.margin))
        (op_shape, op_distinct), (pv_shape, pv_distinct) = shapes
        both = op_distinct & pv_distinct
        patterns = _STICTION_PATTERNS[window.process_type]
        pairs = [(SHAPES[i], SHAPES[j]) for i, j in zip(op_shape, pv_shape, strict=True)]
        sticky = both & np.array([pair in patterns for pair in pairs])
        linear = both & np.array([pair == _LINEAR_PATTERN for pair in pairs])
        n = len(pairs)
        share = float(np.count_nonzero(sticky) / n)
        linear_share = float(np.count_nonzero(linear) / n)
        counts = {f"{op}/{pv}": 0.0 for op in SHAPES for pv in SHAPES}
        for (op, pv), ok in zip(pairs, both, strict=True):
            if ok:
                counts[f"{op}/{pv}"] += 1.0
        details = {"cycles": float(n), "linear_share": linear_share} | {
            f"cycles_{key}": value for key, value in counts.items() if value
        }
        common = max(counts, key=lambda key: counts[key])
        if share >= self.quorum:
            return MethodEvidence(
                self.name, STICTION, share,
                margin_confidence(share, self.quorum, 0.15),
                f"{share:.0%} of {n} cycles show a stiction pattern of thesis Table 2.2 "
                f"(most often OP/PV = {common})",
                details,
            )
        if linear_share >= self.quorum:
            return MethodEvidence(
                self.name, NO_STICTION, share,
                margin_confidence(linear_share, self.quorum, 0.15),
                f"{linear_share:.0%} of {n} cycles have sinusoidal OP and PV, "
                "the shapes of a linear oscillation",
                details,
            )
        return MethodEvidence.undecided(
            self.name,
            f"no clear majority: {share:.0%} of {n} cycles match a stiction pattern, "
            f"{linear_share:.0%} are sinusoidal in OP and PV",
            share,
            details,
        )
