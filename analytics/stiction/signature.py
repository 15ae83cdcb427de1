"""Valve-signature stiction methods: the fitted ellipse and the parallelogram.

A sticky valve traces a parallelogram in the OP-MV plane (thesis section
1.2.2, Fig. 1.6): while it sticks OP moves and MV does not, then MV slips and
follows OP.  When MV is not measured the OP-PV plot stands in for it.  Two
methods read that plot:

* **Ellipse** (Choudhury, Shah, Thornhill & Shook 2006).  OP and PV are
  band-passed to the oscillation (Choudhury et al. use a Wiener filter; here
  :func:`analytics.oscillation.bandpass`), an ellipse is fitted to the
  filtered OP-PV cloud by direct least squares, and its width along the OP
  axis through its centre is the *apparent stiction* in OP units.  In a
  closed loop with a linear controller the filtered OP and PV are related by
  the controller's frequency response, so this width, divided by the OP
  peak-to-peak, is ``|sin(phi)|`` for the OP-PV phase ``phi`` of the
  fundamental: near 1 (quadrature) in a stiction cycle under PI control, small
  in a fast oscillation from aggressive tuning.  :class:`EllipseDetector`
  decides on that ratio; :func:`fit_signature_ellipse` gives the quantity
  for quantification.
* **Parallelogram** (Yamashita 2006).  The movements of OP and of the valve
  signal (MV, else PV) are described by the qualitative symbols I
  (increasing), D (decreasing) and S (steady); the share of the time in
  which OP moves but the valve signal does not (symbols IS and DS: the
  sticking sides of the parallelogram) is the stiction index.
  :class:`ParallelogramDetector` implements it.

Yamashita's variant was chosen over Kano et al.'s (2004) method B because it
needs only OP and PV, which is what historians hold; with MV its index is
the share of time in which the valve stands still while OP moves, which is
Kano et al.'s sticking-section criterion.

References
----------
.. [1] M. A. A. S. Choudhury, S. L. Shah, N. F. Thornhill and D. S. Shook,
   "Automatic detection and quantification of stiction in control valves",
   Control Eng. Practice 14 (2006) 1395-1412 (sections 5-6: the Wiener
   filter, the ellipse fit and the apparent stiction
   ``2 m n / sqrt(m^2 sin^2 alpha + n^2 cos^2 alpha)``).
.. [2] M. A. A. S. Choudhury, M. Jain and S. L. Shah, "Stiction - definition,
   modelling, detection and quantification", J. Process Control 18 (2008)
   232-243 (apparent stiction in closed loop).
.. [3] A. Fitzgibbon, M. Pilu and R. B. Fisher, "Direct least square fitting
   of ellipses", IEEE Trans. PAMI 21 (1999) 476-480; R. Halir and J. Flusser,
   "Numerically stable direct least squares fitting of ellipses", WSCG 1998.
.. [4] Y. Yamashita, "An automatic method for detection of valve stiction in
   process control loops", Control Eng. Practice 14 (2006) 503-510.
.. [5] M. Kano, H. Maruta, H. Kugemoto and K. Shimizu, "Practical model and
   detection algorithm for valve stiction", IFAC DYCOPS, Cambridge MA, 2004
   (thesis ref. [24]).
.. [6] A. Horch, "A simple method for detection of stiction in control
   valves", Control Eng. Practice 7 (1999) 1221-1231 (thesis ref. [18]):
   OP and PV in quadrature under stiction, in phase under linear causes.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from analytics.errors import DataError
from analytics.oscillation import bandpass
from analytics.stiction.evidence import (
    INTEGRATING,
    NO_STICTION,
    STICTION,
    LoopWindow,
    MethodEvidence,
    margin_confidence,
)
from analytics.stiction.shape_rules import window_problem
from analytics.types import FloatArray

__all__ = [
    "EllipseDetector",
    "EllipseFit",
    "ParallelogramDetector",
    "fit_signature_ellipse",
]


#: ``1 - r^2`` below which the filtered cloud counts as a straight line (r: the
#: correlation of the filtered signals), i.e. MV = OP exactly.
_COLLINEAR = 1e-12


@dataclass(frozen=True)
class EllipseFit:
    """An ellipse fitted to the band-passed valve signature (OP, PV or MV).

    Attributes
    ----------
    centre : (float, float)
        Centre (OP, PV) of the ellipse, in signal units.  The filtered
        signals are re-centred on the means of the raw signals, so the
        ellipse overlays the raw OP-PV plot.
    semi_axes : (float, float)
        Semi-major and semi-minor axes ``m >= n`` in the plot's mixed units;
        ``n = 0`` when the cloud lies on a straight line (MV = OP).
    angle : float
        Angle ``alpha`` of the major axis from the OP axis, radians in
        ``(-pi/2, pi/2]`` (depends on the units of the two axes).
    apparent_stiction : float
        Width of the ellipse along the OP axis through its centre, in OP
        units (Choudhury et al. 2006):
        ``2 m n / sqrt(m^2 sin^2 alpha + n^2 cos^2 alpha)``.
    op_amplitude : float
        Half the ellipse's extent along the OP axis: the amplitude of the
        filtered OP.
    residual : float
        Relative RMS radial distance of the points from the ellipse,
        ``sqrt(mean((r_i - 1)^2))`` with ``r_i = 1`` on the ellipse (affine
        invariant, so independent of the units): 0 for a perfect ellipse,
        about 0.5 for band-passed noise.
    """

    centre: tuple[float, float]
    semi_axes: tuple[float, float]
    angle: float
    apparent_stiction: float
    op_amplitude: float
    residual: float

    @property
    def width_ratio(self) -> float:
        """Apparent stiction over the OP peak-to-peak: ``|sin phi|`` of the OP-PV phase."""
        return self.apparent_stiction / (2.0 * self.op_amplitude)

    def to_dict(self) -> dict[str, Any]:
        """JSON form: the apparent stiction, ``width_ratio``, ``op_amplitude`` and
        ``residual``, and the geometry (``centre``, ``semi_axes``, ``angle``) that a plot
        draws (the ``apparent_stiction`` of a loop diagnosis)."""
        return {
            "apparent_stiction": self.apparent_stiction,
            "width_ratio": self.width_ratio,
            "op_amplitude": self.op_amplitude,
            "residual": self.residual,
            "centre": list(self.centre),
            "semi_axes": list(self.semi_axes),
            "angle": self.angle,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> EllipseFit:
        """The fit of :meth:`to_dict`'s form (``width_ratio`` is derived, so not read).

        Raises
        ------
        KeyError
            If a field is missing: diagnoses stored before the geometry was kept
            have no ``centre``, ``semi_axes`` and ``angle``.
        """
        cx, cy = d["centre"]
        m, n = d["semi_axes"]
        return cls(centre=(float(cx), float(cy)), semi_axes=(float(m), float(n)),
                   angle=float(d["angle"]), apparent_stiction=float(d["apparent_stiction"]),
                   op_amplitude=float(d["op_amplitude"]), residual=float(d["residual"]))


def fit_signature_ellipse(
    op: ArrayLike, pv: ArrayLike, period_samples: float, *, band_ratio: float = 1.5
) -> EllipseFit:
    """Fit an ellipse to the OP-PV (or OP-MV) plot of one oscillation.

    1. OP and PV are band-passed around the oscillation with
       :func:`analytics.oscillation.bandpass` (zero phase, half-power edges at
       ``fc / band_ratio`` and ``fc * band_ratio``), which plays the part of
       the Wiener filter of [1]_.  One period at each end, where the filter
       has not settled, is dropped.
    2. Both signals are scaled to unit standard deviation and the conic
       ``a u^2 + b uv + c v^2 + d u + e v + f = 0`` is fitted by the direct
       least-squares ellipse fit of Fitzgibbon et al. in the numerically
       stable form of Halir and Flusser [3]_, which always returns an ellipse.
    3. The ellipse is mapped back to signal units; its width along the OP
       axis through the centre is the apparent stiction of [1]_ (see
       :class:`EllipseFit`).

    Parameters
    ----------
    op, pv : array_like
        Controller output and process variable (or valve position), same
        length, finite.
    period_samples : float
        Oscillation period in samples.
    band_ratio : float, optional
        Band-pass half width as a frequency ratio (1.5 keeps the third
        harmonic of a square wave out).

    Returns
    -------
    EllipseFit

    Raises
    ------
    DataError
        If the signals differ in length, are not finite, hold fewer than four
        periods, or either has no oscillation at ``period_samples``.

    References
    ----------
    .. [1] Choudhury, Shah, Thornhill & Shook (2006), Control Eng. Practice
       14:1395-1412, sections 5-6.
    .. [3] Fitzgibbon, Pilu & Fisher (1999); Halir & Flusser (1998).

    Examples
    --------
    OP and PV a quarter period apart trace a circle-like ellipse, as wide as
    the OP swing:

    >>> k = np.arange(2000)
    >>> op = 50 + 2 * np.sin(2 * np.pi * k / 100)
    >>> pv = 30 - np.cos(2 * np.pi * k / 100)
    >>> fit = fit_signature_ellipse(op, pv, 100)
    >>> round(fit.apparent_stiction, 1), round(fit.width_ratio, 3)
    (4.0, 1.0)
    >>> [round(c, 2) for c in fit.centre]
    [50.0, 30.0]
    """
    x_raw = np.asarray(op, dtype=np.float64)
    y_raw = np.asarray(pv, dtype=np.float64)
    if x_raw.ndim != 1 or x_raw.shape != y_raw.shape:
        raise DataError(f"op and pv must be 1-D of equal length, got {x_raw.shape}, {y_raw.shape}")
    if not (np.all(np.isfinite(x_raw)) and np.all(np.isfinite(y_raw))):
        raise DataError("op and pv must be finite")
    if not (np.isfinite(period_samples) and period_samples > 2):
        raise DataError(f"period_samples must exceed 2, got {period_samples!r}")
    edge = math.ceil(period_samples)
    if x_raw.size < 4 * edge:
        raise DataError(
            f"{x_raw.size} samples hold {x_raw.size / period_samples:.1f} periods; "
            "at least 4 are needed (one is dropped at each end)"
        )
    x = bandpass(x_raw, period_samples, band_ratio=band_ratio)[edge:-edge]
    y = bandpass(y_raw, period_samples, band_ratio=band_ratio)[edge:-edge]
    sx, sy = float(x.std()), float(y.std())
    for name, spread, raw in (("op", sx, x_raw), ("pv (the valve signal)", sy, y_raw)):
        if spread <= 1e-12 * (1.0 + float(np.abs(raw).max())):
            raise DataError(
                f"{name} does not oscillate at a period of {period_samples:.1f} samples"
            )
    u, v = (x - x.mean()) / sx, (y - y.mean()) / sy
    centre = (float(x_raw.mean() + x.mean()), float(y_raw.mean() + y.mean()))
    correlation = float(np.mean(u * v))
    conic = None if 1.0 - correlation**2 < _COLLINEAR else _direct_ellipse_fit(u, v)
    if conic is None:
        # The cloud is a segment (MV = OP): the degenerate ellipse of zero width.
        return EllipseFit(
            centre=centre,
            semi_axes=(float(np.sqrt(2.0 * (sx**2 + sy**2))), 0.0),
            angle=float(np.arctan2(np.sign(correlation) * sy, sx)),
            apparent_stiction=0.0,
            op_amplitude=float(np.sqrt(2.0) * sx),
            residual=0.0,
        )
    a, b, c, d, e, f = conic
    u0, v0 = np.linalg.solve(np.array([[2 * a, b], [b, 2 * c]]), np.array([-d, -e]))
    k = -(f + 0.5 * (d * u0 + e * v0))  # a U^2 + b U V + c V^2 = k about the centre
    # Quadratic form in signal units: the ellipse is z' Q z = 1, z = point - centre.
    q = np.array([[a / sx**2, b / (2 * sx * sy)], [b / (2 * sx * sy), c / sy**2]]) / k
    eigenvalues, eigenvectors = np.linalg.eigh(q)  # ascending: major axis first
    major = eigenvectors[:, 0]
    angle = float(np.arctan2(major[1], major[0]))
    if angle <= -np.pi / 2:
        angle += np.pi
    elif angle > np.pi / 2:
        angle -= np.pi
    z = np.stack([x - (x.mean() + sx * u0), y - (y.mean() + sy * v0)])
    radius = np.sqrt(np.einsum("in,ij,jn->n", z, q, z))
    return EllipseFit(
        centre=(float(centre[0] + sx * u0), float(centre[1] + sy * v0)),
        semi_axes=(float(1 / np.sqrt(eigenvalues[0])), float(1 / np.sqrt(eigenvalues[1]))),
        angle=angle,
        apparent_stiction=float(2.0 / np.sqrt(q[0, 0])),
        op_amplitude=float(np.sqrt(q[1, 1] / np.linalg.det(q))),
        residual=float(np.sqrt(np.mean((radius - 1.0) ** 2))),
    )


def _direct_ellipse_fit(u: FloatArray, v: FloatArray) -> FloatArray | None:
    """Conic ``(a, b, c, d, e, f)`` of the direct least-squares ellipse fit.

    Fitzgibbon et al. minimise the algebraic distance subject to
    ``4ac - b^2 = 1``; Halir and Flusser split the scatter matrix into its
    quadratic and linear parts so that the generalised eigenproblem becomes
    an ordinary 3 x 3 one.  Exactly one eigenvector satisfies
    ``4ac - b^2 > 0``; None if rounding leaves none (a degenerate cloud).
    """
    quadratic = np.stack([u * u, u * v, v * v], axis=1)
    linear = np.stack([u, v, np.ones_like(u)], axis=1)
    s1 = quadratic.T @ quadratic
    s2 = quadratic.T @ linear
    s3 = linear.T @ linear
    t = -np.linalg.solve(s3, s2.T)
    m = s1 + s2 @ t
    m = np.array([m[2] / 2.0, -m[1], m[0] / 2.0])  # inverse of the constraint matrix times m
    _, vectors = np.linalg.eig(m)
    vectors = np.real(vectors)
    ellipse = 4.0 * vectors[0] * vectors[2] - vectors[1] ** 2 > 0
    if not np.any(ellipse):
        return None
    a1 = vectors[:, int(np.flatnonzero(ellipse)[0])]
    return np.concatenate([a1, t @ a1])


def _valve_signal(window: LoopWindow) -> tuple[str, FloatArray | None]:
    """The valve-side signal of the signature: MV when measured, else PV."""
    if window.mv is not None:
        return "mv", window.mv
    return "pv", window.pv


def _integrating_without_mv(window: LoopWindow) -> bool:
    return window.mv is None and window.process_type == INTEGRATING


@dataclass(frozen=True, kw_only=True)
class EllipseDetector:
    """Stiction from the width of the OP-PV ellipse (Choudhury et al. 2006).

    :func:`fit_signature_ellipse` is applied to OP and the valve signal (MV
    when measured, else PV).  The index is the width ratio: the apparent
    stiction over the OP peak-to-peak of the ellipse, which equals
    ``|sin phi|`` for the phase ``phi`` between the fundamentals of the two
    signals.

    * Stiction if the ratio reaches ``width_ratio_threshold``, no stiction
      below.  The default ``1/sqrt(2)`` splits phases closer to quadrature
      (``45 <= |phi| <= 135`` degrees) from phases closer to in-phase or
      anti-phase: Horch's (1999) rule, that stiction under PI control puts OP
      and PV in quadrature and linear causes do not, read off the ellipse.
      Simulated FOPDT loops with PI control and Kano or He valves give ratios
      of 0.78-0.99 from OP-PV and 0.82-1.0 from OP-MV; aggressive
      proportional tuning gives 0.10; an ideal valve gives 0 from OP-MV.
    * Undecided if the ellipse explains the cloud poorly (``residual`` above
      ``max_residual``): the amplitude or phase wanders, as in noise-driven
      resonance of an aggressively tuned loop (0.43-0.50 in simulation, 0.5
      for band-passed noise), while stiction cycles gave 0.01-0.38.
    * Undecided without MV on an integrating process: the controller's
      integral action there sets the OP-PV phase of any slow cycle, and
      simulated level loops with sticky valves gave ratios 0.23-0.5.

    A linear loop driven by an external oscillation slower than the
    controller's integral time (``omega Ti < 1``) is also in quadrature and
    is flagged as stiction from OP-PV (a known limit of the phase rule); with
    MV it is not.

    Attributes
    ----------
    width_ratio_threshold : float
        Width ratio (``|sin phi|``) from which the signature counts as sticky.
    max_residual : float
        Largest :attr:`EllipseFit.residual` for a decision.
    min_cycles : float
        Fewest periods in the window (one is dropped at each end).
    band_ratio : float
        Band-pass half width (see :func:`fit_signature_ellipse`).
    confidence_scale : float
        ``scale`` of :func:`~analytics.stiction.evidence.margin_confidence`.

    References
    ----------
    .. [1] Choudhury, Shah, Thornhill & Shook (2006), Control Eng. Practice
       14:1395-1412.
    .. [2] Horch (1999), Control Eng. Practice 7:1221-1231.

    Examples
    --------
    A triangular OP and a square PV a quarter cycle apart (a flow loop with
    PI control and a sticky valve):

    >>> t = np.arange(3000.0)
    >>> pv = np.sign(np.sin(2 * np.pi * t / 150))
    >>> op = -np.cumsum(pv) / 40
    >>> ev = EllipseDetector().detect(LoopWindow(ts=1.0, op=op, pv=pv, period_s=150.0))
    >>> ev.decision, round(ev.index, 2)
    ('stiction', 1.0)
    """

    width_ratio_threshold: float = 1.0 / math.sqrt(2.0)
    max_residual: float = 0.4
    min_cycles: float = 4.0
    band_ratio: float = 1.5
    confidence_scale: float = 0.1
    name: ClassVar[str] = "ellipse"

    def detect(self, window: LoopWindow) -> MethodEvidence:
        """Evidence from the width of the fitted ellipse (class docstring)."""
        valve_name, valve = _valve_signal(window)
        problem = window_problem(window, ("op", valve_name), self.min_cycles)
        if problem is not None:
            return MethodEvidence.undecided(self.name, problem)
        if _integrating_without_mv(window):
            return MethodEvidence.undecided(
                self.name,
                "on an integrating process the OP-PV phase is set by the controller, "
                "not by the valve; the ellipse needs MV there",
            )
        assert window.op is not None and valve is not None
        period = float(window.period_samples or 0.0)
        try:
            fit = fit_signature_ellipse(window.op, valve, period, band_ratio=self.band_ratio)
        except DataError as exc:
            return MethodEvidence.undecided(self.name, str(exc))
        ratio = fit.width_ratio
        details = {
            "apparent_stiction": fit.apparent_stiction,
            "op_amplitude": fit.op_amplitude,
            "residual": fit.residual,
            "semi_major": fit.semi_axes[0],
            "semi_minor": fit.semi_axes[1],
            "angle_deg": math.degrees(fit.angle),
            "uses_mv": float(valve_name == "mv"),
        }
        plot = f"OP-{valve_name.upper()}"
        if fit.residual > self.max_residual:
            return MethodEvidence.undecided(
                self.name,
                f"an ellipse explains the filtered {plot} cloud poorly (residual "
                f"{fit.residual:.2f} > {self.max_residual:g}): the oscillation is not steady",
                ratio,
                details,
            )
        confidence = margin_confidence(ratio, self.width_ratio_threshold, self.confidence_scale)
        width = (
            f"apparent stiction {fit.apparent_stiction:.3g} % of OP span is {ratio:.2f} "
            f"of the OP peak-to-peak in the {plot} ellipse"
        )
        if ratio >= self.width_ratio_threshold:
            return MethodEvidence(
                self.name, STICTION, ratio, confidence,
                f"{width}: the signals are near quadrature, as in a stiction cycle",
                details,
            )
        return MethodEvidence(
            self.name, NO_STICTION, ratio, confidence,
            f"{width}: a thin ellipse, as from a linear oscillation",
            details,
        )


def _noise_std(x: FloatArray) -> float:
    """Robust standard deviation of white noise on ``x`` from its second differences.

    A smooth movement hardly changes the second difference and a slip is an
    outlier, so ``1.4826 MAD(diff(x, 2)) / sqrt(6)`` (the second difference of
    white noise has variance ``6 sigma^2``) estimates the noise alone.
    """
    second = np.diff(x, 2)
    return float(1.4826 * np.median(np.abs(second - np.median(second))) / np.sqrt(6.0))


def _movement_symbols(
    x: FloatArray, block: int, steady_band: float, noise_z: float
) -> NDArray[np.int8]:
    """Yamashita's qualitative symbols of ``x``: +1 I, -1 D, 0 S, one per block change.

    ``x`` is averaged over blocks of ``block`` samples; a change of the block
    mean is steady when it is smaller than ``steady_band`` times the mean
    absolute change, or than ``noise_z`` standard deviations of the change
    that white noise alone produces (``sigma sqrt(2 / block)``).
    """
    n_blocks = x.size // block
    change = np.diff(x[: n_blocks * block].reshape(n_blocks, block).mean(axis=1))
    band = max(
        steady_band * float(np.mean(np.abs(change))),
        noise_z * _noise_std(x) * np.sqrt(2.0 / block),
    )
    return (np.sign(change) * (np.abs(change) > band)).astype(np.int8)


@dataclass(frozen=True, kw_only=True)
class ParallelogramDetector:
    """Stiction from the sticking sides of the valve signature (Yamashita 2006).

    1. OP and the valve signal (MV when measured, else PV) are averaged over
       consecutive blocks of ``1 / segments_per_cycle`` of a period: the
       noise falls with the square root of the block length, while a slip
       spreads over at most two blocks, so the flat sticking sections stay
       flat (a band-pass filter would round them off).
    2. Each change between blocks becomes a symbol I, D or S
       (:func:`_movement_symbols`); the pair of symbols of OP and of the valve
       signal describes the movement in the OP-PV plot.
    3. The index of [4]_ is the share of the moving time in which OP moves
       and the valve signal is steady (IS and DS, the sticking sides of the
       parallelogram)::

           rho = (tau_IS + tau_DS) / (tau_total - tau_SS)

    Stiction if ``rho > index_threshold`` (0.25, Yamashita 2006); no
    stiction if ``rho < linear_threshold``; undecided between, where PV is a
    blurred valve signature (see below).  Undecided too when either signal
    shows fewer than ``min_moves_per_cycle`` resolved moves per cycle: its
    oscillation is buried in noise.

    The steady band is this implementation's choice: a change is steady below
    ``steady_band = 0.2`` times the mean absolute change (a sinusoid is then
    steady only around its turning points, 8 % of the cycle) or below
    ``noise_z = 3`` standard deviations of the change due to noise (so a
    noisy flat section stays steady).  Two sinusoids in quadrature, the
    signature of a linear loop, give ``rho = 0.08``; ``linear_threshold =
    0.15`` is about twice that.  In closed-loop simulation (FOPDT, PI):
    sticky Kano and He valves give 0.34-0.74 from OP-PV of a fast (flow)
    loop (time constant 1/12 to 1/22 of the period), 0.22-0.76 from OP-PV of
    a slower one (1/6 to 1/16 of the period), 0.57-0.87 from OP-MV
    (level loop included); ideal valves with sinusoidal disturbances 0
    (OP-MV) and 0.09-0.19 (OP-PV), aggressive proportional tuning 0.06-0.07.

    Without MV the method assumes that PV follows the valve within a small
    part of the cycle (flow and fast pressure loops); on slower processes PV
    keeps moving after each slip and ``rho`` falls into the undecided band.
    On an integrating process PV never rests, so without MV the method is
    undecided there.

    Attributes
    ----------
    index_threshold : float
        ``rho`` above which the signature is sticky.
    linear_threshold : float
        ``rho`` below which the valve signal follows OP.
    segments_per_cycle : int
        Symbols per oscillation period.
    steady_band : float
        Fraction of the mean absolute change below which a signal is steady.
    noise_z : float
        A change within this many noise standard deviations is steady.
    min_moves_per_cycle : float
        Fewest resolved moves (symbols I or D) per cycle in each signal.
    min_cycles : float
        Fewest periods in the window.
    confidence_scale : float
        ``scale`` of :func:`~analytics.stiction.evidence.margin_confidence`.

    References
    ----------
    .. [4] Yamashita (2006), Control Eng. Practice 14:503-510.
    .. [5] Kano, Maruta, Kugemoto & Shimizu (2004), IFAC DYCOPS.

    Examples
    --------
    A sticky valve (Kano's model, S = 1, J = 0.5) driven by a triangular OP
    of 2 % peak-to-peak sticks for half of each stroke, until OP has moved S
    (the blocks holding a slip or a turn count as moving, hence 0.36):

    >>> from analytics.valves import IdealValve, KanoValve
    >>> op = 2 * np.abs((np.arange(4000.0) % 200) / 100 - 1)
    >>> for valve in (KanoValve(S=1.0, J=0.5), IdealValve()):
    ...     w = LoopWindow(ts=1.0, op=op, pv=op, mv=valve.simulate(op), period_s=200.0)
    ...     ev = ParallelogramDetector().detect(w)
    ...     print(ev.decision, round(ev.index, 2))
    stiction 0.36
    no_stiction 0.0
    """

    index_threshold: float = 0.25
    linear_threshold: float = 0.15
    segments_per_cycle: int = 24
    steady_band: float = 0.2
    noise_z: float = 3.0
    min_moves_per_cycle: float = 2.0
    min_cycles: float = 3.0
    confidence_scale: float = 0.1
    name: ClassVar[str] = "parallelogram"

    def detect(self, window: LoopWindow) -> MethodEvidence:
        """Evidence from the qualitative OP-PV movements (class docstring)."""
        valve_name, valve = _valve_signal(window)
        problem = window_problem(window, ("op", valve_name), self.min_cycles)
        if problem is not None:
            return MethodEvidence.undecided(self.name, problem)
        if _integrating_without_mv(window):
            return MethodEvidence.undecided(
                self.name,
                "the PV of an integrating process never rests, so it cannot stand in "
                "for the valve position; the parallelogram needs MV there",
            )
        assert window.op is not None and valve is not None
        period = float(window.period_samples or 0.0)
        block = max(round(period / self.segments_per_cycle), 1)
        op_symbols, valve_symbols = (
            _movement_symbols(x, block, self.steady_band, self.noise_z)
            for x in (window.op, valve)
        )
        cycles = op_symbols.size * block / period
        for label, symbols in (("OP", op_symbols), (valve_name.upper(), valve_symbols)):
            moves = np.count_nonzero(symbols) / cycles
            if moves < self.min_moves_per_cycle:
                return MethodEvidence.undecided(
                    self.name,
                    f"{label} shows {moves:.1f} moves per cycle above its noise "
                    f"(at least {self.min_moves_per_cycle:g} are needed)",
                )
        op_moves = op_symbols != 0
        valve_rests = valve_symbols == 0
        sticking = int(np.count_nonzero(op_moves & valve_rests))
        moving = int(np.count_nonzero(op_moves | ~valve_rests))
        rho = sticking / moving
        total = op_symbols.size
        details = {
            "sticking_share": sticking / total,
            "both_moving_share": int(np.count_nonzero(op_moves & ~valve_rests)) / total,
            "valve_alone_share": int(np.count_nonzero(~op_moves & ~valve_rests)) / total,
            "both_steady_share": (total - moving) / total,
            "uses_mv": float(valve_name == "mv"),
        }
        share = (
            f"in {rho:.0%} of the moving time OP moves while {valve_name.upper()} rests "
            f"(symbols IS and DS of the OP-{valve_name.upper()} plot)"
        )
        if rho > self.index_threshold:
            return MethodEvidence(
                self.name, STICTION, rho,
                margin_confidence(rho, self.index_threshold, self.confidence_scale),
                f"{share}: the sticking sides of a parallelogram", details,
            )
        if rho < self.linear_threshold:
            return MethodEvidence(
                self.name, NO_STICTION, rho,
                margin_confidence(rho, self.linear_threshold, self.confidence_scale),
                f"{share}: the valve signal follows OP", details,
            )
        return MethodEvidence.undecided(
            self.name,
            f"{share}: between a linear signature ({self.linear_threshold:g}) and a "
            f"sticking one ({self.index_threshold:g})",
            rho,
            details,
        )
