"""Data-quality screening of a loop window before any nonlinearity test.

Oscillation, nonlinearity and stiction tests silently give wrong answers on
data that are mostly missing, frozen, clipped, coarsely quantised or
reconstructed from a compressed historian archive.  This module screens a
window of loop data (time stamps plus any of ``op``, ``pv``, ``sp`` ...) and
reports every problem found as a :class:`QualityIssue`; problems that make the
window unusable for the downstream tests are *fatal* and switch
:attr:`QualityReport.usable` off.

The checks follow the data pre-processing recommendations of

* M. Jelali and B. Huang (eds.), *Detection and Diagnosis of Stiction in
  Control Loops*, Springer, 2010 (the chapter on data pre-processing and
  the International Stiction Data Base evaluation);
* N. F. Thornhill and A. Horch, "Advances and new directions in plant-wide
  disturbance detection and diagnosis", *Control Engineering Practice* 15
  (2007) 1196-1206 (data problems that defeat nonlinearity tests);
* N. F. Thornhill, M. A. A. S. Choudhury and S. L. Shah, "The impact of
  compression on data-driven process analyses", *Journal of Process
  Control* 14 (2004) 389-398 (compression detection and compression factor).

Bad data *content* never raises: it is reported.  Only structurally invalid
calls (no signals, non-1-D arrays, mismatched lengths, no way to know the
sampling time) raise :class:`analytics.errors.DataError`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from analytics.errors import DataError

Severity = Literal["info", "warning", "fatal"]

__all__ = [
    "QualityIssue",
    "QualityLimits",
    "QualityReport",
    "Severity",
    "assess_quality",
]


SET_POINT_SIGNALS = frozenset({"sp"})
"""Signals that are constant or stepwise by design: only their missing values are
checked (a constant set point is normal operation, not a frozen transmitter)."""

HELD_BY_DESIGN_SIGNALS = frozenset({"mv"})
"""Signals whose held stretches are the symptom under study: a sticky valve's
position stays put between slips (thesis Fig. 1.3), so runs of identical or
straight-line values in MV are neither a frozen transmitter nor historian
compression; MV is screened for missing values, saturation and quantisation."""


@dataclass(frozen=True)
class QualityIssue:
    """One finding of the data-quality screen.

    Attributes
    ----------
    code : str
        Stable machine-readable identifier, one of ``"nonfinite"``,
        ``"too_few_samples"``, ``"time_nonfinite"``, ``"time_not_increasing"``,
        ``"time_duplicate"``, ``"ts_mismatch"``, ``"gaps"``,
        ``"irregular_sampling"``, ``"constant"``, ``"flatline"``,
        ``"saturation"``, ``"quantisation"``, ``"compression"``.
    signal : str or None
        Name of the signal concerned (a key of ``signals``), ``"t"`` for the
        time stamps, or ``None`` for window-wide findings.
    severity : {"info", "warning", "fatal"}
        ``"fatal"`` findings make the window unusable.
    message : str
        Human-readable explanation including the measured quantity.
    value : float or None
        The key measured quantity (documented per code in
        :func:`assess_quality`), ``None`` when there is none.
    """

    code: str
    signal: str | None
    severity: Severity
    message: str
    value: float | None


@dataclass(frozen=True)
class QualityReport:
    """Result of :func:`assess_quality`.

    Attributes
    ----------
    usable : bool
        ``False`` if at least one issue is fatal.
    issues : tuple of QualityIssue
        All findings, in the order the checks ran.
    ts : float
        Sampling interval in seconds (given, or the median time-stamp step).
    samples : int
        Number of samples in the window.
    """

    usable: bool
    issues: tuple[QualityIssue, ...]
    ts: float
    samples: int

    def reasons(self) -> tuple[str, ...]:
        """Messages of the fatal issues, i.e. why the window is unusable."""
        return tuple(i.message for i in self.issues if i.severity == "fatal")

    def codes(self, signal: str | None = None) -> frozenset[str]:
        """Codes of all issues, optionally only those of one ``signal``."""
        return frozenset(i.code for i in self.issues if signal is None or i.signal == signal)

    def warnings(self) -> tuple[QualityIssue, ...]:
        """Issues of severity ``"warning"``."""
        return tuple(i for i in self.issues if i.severity == "warning")


@dataclass(frozen=True)
class QualityLimits:
    """Thresholds of :func:`assess_quality` (defaults need no per-loop tuning).

    Attributes
    ----------
    min_samples : int
        Fewer finite samples than this is fatal (oscillation and nonlinearity
        tests need several cycles).
    max_nonfinite_fraction : float
        NaN/inf fraction above which a signal is fatal (below: warning).
    gap_factor : float
        A time step larger than ``gap_factor`` times the median step is a gap.
    max_gap_fraction : float
        Gaps totalling more than this fraction of the window are fatal.
    irregular_tolerance : float
        Relative spread ``(p90 - p10) / median`` of the (gap-free) time steps
        above which sampling is reported irregular.
    ts_tolerance : float
        Relative difference between a given ``ts`` and the median time step
        above which ``ts_mismatch`` is reported.
    flat_min_run : int
        Minimum length (samples) of a run of identical values to be a flat
        line; the effective minimum is ``max(flat_min_run, flat_run_fraction*N)``.
    flat_run_fraction : float
        See ``flat_min_run``.
    flat_fatal_fraction : float
        Fraction of the window inside flat-line runs above which it is fatal.
    saturation_fraction : float
        Fraction of samples at an end of the range reported as saturation.
    saturation_fatal_fraction : float
        Saturated fraction above which the loop is treated as open (fatal).
    saturation_tolerance : float
        With known ``ranges``: distance from a limit, as a fraction of the
        range width, still counted as "at the limit".
    quantisation_levels : float
        A signal spanning fewer quantisation steps than this (robust range /
        resolution) is reported as quantised (warning).
    quantisation_fatal_levels : int
        A signal with at most this many distinct values is fatal.
    compression_factor : float
        Estimated historian compression factor above which a warning is given.
        Thornhill, Choudhury & Shah (2004) show spectral, nonlinearity and
        oscillation analyses degrading as the compression factor grows.
    compression_fatal_factor : float
        Compression factor above which the window is fatal.
    """

    min_samples: int = 100
    max_nonfinite_fraction: float = 0.1
    gap_factor: float = 1.5
    max_gap_fraction: float = 0.2
    irregular_tolerance: float = 0.1
    ts_tolerance: float = 0.01
    flat_min_run: int = 20
    flat_run_fraction: float = 0.1
    flat_fatal_fraction: float = 0.5
    saturation_fraction: float = 0.05
    saturation_fatal_fraction: float = 0.5
    saturation_tolerance: float = 0.005
    quantisation_levels: float = 25.0
    quantisation_fatal_levels: int = 3
    compression_factor: float = 3.0
    compression_fatal_factor: float = 10.0


def assess_quality(
    t: ArrayLike | None,
    signals: Mapping[str, ArrayLike],
    ts: float | None = None,
    *,
    ranges: Mapping[str, tuple[float, float]] | None = None,
    limits: QualityLimits | None = None,
) -> QualityReport:
    """Screen a loop data window for problems that defeat loop diagnosis.

    Parameters
    ----------
    t : array_like or None
        Time stamps in seconds, one per sample.  ``None`` means uniformly
        sampled data with interval ``ts``.
    signals : mapping of str to array_like
        The loop signals, e.g. ``{"op": op, "pv": pv}``; any may be missing
        but at least one must be given.  All must have the same length (and
        the length of ``t``).
    ts : float, optional
        Nominal sampling interval in seconds.  Required when ``t`` is None;
        otherwise compared with the median time step.
    ranges : mapping of str to (float, float), optional
        Known instrument / actuator ranges, e.g. ``{"op": (0.0, 100.0)}``;
        saturation is then measured against these limits rather than the
        observed extremes.
    limits : QualityLimits, optional
        Thresholds; the defaults need no per-loop tuning.

    Returns
    -------
    QualityReport
        ``usable`` is False when any issue is fatal; ``reasons()`` says why.

    Raises
    ------
    DataError
        Only for structurally invalid calls: no signals, a signal or ``t``
        that is not one-dimensional / numeric, lengths that differ, a missing
        or non-positive ``ts`` when ``t`` is None.

    Notes
    -----
    Checks and the ``value`` they report:

    ``nonfinite``
        Count of NaN/inf samples; fatal above ``max_nonfinite_fraction``
        (missing values must be handled before any spectral analysis, Jelali
        & Huang 2010).
    ``too_few_samples``
        Number of finite samples, fatal below ``min_samples``.
    ``time_nonfinite`` / ``time_not_increasing`` / ``time_duplicate``
        Index of the first offending step (``t[i+1] <= t[i]``); the message
        lists the first indices.  Backward steps are fatal, duplicates warn.
    ``gaps``
        Largest gap in seconds; a step over ``gap_factor`` times the median
        step is a gap.  ``irregular_sampling``: relative spread of the steps.
    ``constant`` / ``flatline``
        Whole signal constant (fatal) / length of the longest run of
        identical values (a frozen transmitter or a held historian value).
    ``saturation``
        Fraction of samples at the range end (e.g. OP clamped at 0 or 100 %).
        Without known ``ranges``, samples equal to the observed minimum or
        maximum count when that value is far more frequent than its
        neighbouring level (so a quantised signal visiting its extreme level
        is not mistaken for clipping).
    ``quantisation``
        Resolution estimate ``q`` (a low quantile of the non-zero absolute
        first differences, i.e. the smallest step the signal makes); the
        message gives the number of levels ``(p99 - p1) / q`` spanned and the
        count of distinct values.
    ``compression``
        Compression factor estimate ``CF = (N - 1) / (number of slope
        changes + 1)``: a historian that stores only the points triggered by a
        swinging-door or dead-band criterion and is read back with linear
        (or repeated-value) interpolation produces straight-line segments,
        i.e. runs of constant first difference.  Thornhill, Choudhury & Shah
        (2004) detect compression from these straight segments
        and estimate the compression factor as the mean number of samples
        per segment.
    """
    lim = limits if limits is not None else QualityLimits()
    if not signals:
        raise DataError("assess_quality needs at least one signal (e.g. 'op' or 'pv')")

    arrays: dict[str, NDArray[np.float64]] = {}
    for name, raw in signals.items():
        arrays[name] = _as_1d(raw, f"signal '{name}'")
    lengths = {name: a.size for name, a in arrays.items()}
    first_name, n = next(iter(lengths.items()))
    for name, length in lengths.items():
        if length != n:
            raise DataError(
                f"signal '{name}' has {length} samples but signal '{first_name}' has {n}"
            )
    t_arr: NDArray[np.float64] | None = None
    if t is not None:
        t_arr = _as_1d(t, "time stamps 't'")
        if t_arr.size != n:
            raise DataError(
                f"time stamps 't' have {t_arr.size} samples but signal '{first_name}' has {n}"
            )
    if t_arr is None:
        if ts is None or not np.isfinite(ts) or ts <= 0:
            raise DataError("assess_quality needs time stamps 't' or a positive sampling time 'ts'")
    elif ts is not None and (not np.isfinite(ts) or ts <= 0):
        raise DataError(f"sampling time ts must be positive and finite, got {ts!r}")

    issues: list[QualityIssue] = []
    ts_est = _check_time(t_arr, ts, n, lim, issues)

    for name, x in arrays.items():
        rng = None if ranges is None else ranges.get(name)
        _check_signal(name, x, rng, lim, issues)

    if n < lim.min_samples:
        issues.append(
            QualityIssue(
                "too_few_samples",
                None,
                "fatal",
                f"window has {n} samples, fewer than the {lim.min_samples} needed",
                float(n),
            )
        )

    usable = not any(i.severity == "fatal" for i in issues)
    return QualityReport(usable=usable, issues=tuple(issues), ts=ts_est, samples=n)


# ----------------------------------------------------------------------------
# helpers


def _as_1d(raw: ArrayLike, what: str) -> NDArray[np.float64]:
    try:
        a = np.asarray(raw, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise DataError(f"{what} is not numeric: {exc}") from exc
    if a.ndim != 1:
        raise DataError(f"{what} must be one-dimensional, got shape {a.shape}")
    return a


def _fmt_idx(idx: NDArray[np.intp], limit: int = 5) -> str:
    shown = ", ".join(str(int(i)) for i in idx[:limit])
    return shown + (f", ... ({idx.size} in all)" if idx.size > limit else "")


def _check_time(
    t: NDArray[np.float64] | None,
    ts: float | None,
    n: int,
    lim: QualityLimits,
    issues: list[QualityIssue],
) -> float:
    """Time-stamp checks; returns the sampling interval to report."""
    if t is None:
        assert ts is not None
        return float(ts)
    finite = np.isfinite(t)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        issues.append(
            QualityIssue(
                "time_nonfinite",
                "t",
                "fatal",
                f"{bad.size} time stamps are NaN/inf (indices {_fmt_idx(bad)})",
                float(bad[0]),
            )
        )
    tf = t[finite]
    if tf.size < 2:
        return float(ts) if ts is not None else float("nan")
    dt = np.diff(t)
    with np.errstate(invalid="ignore"):
        back = np.flatnonzero(dt < 0)
        dup = np.flatnonzero(dt == 0)
    if back.size:
        issues.append(
            QualityIssue(
                "time_not_increasing",
                "t",
                "fatal",
                f"time stamps go backwards at {back.size} steps t[i+1] < t[i], "
                f"i = {_fmt_idx(back)}",
                float(back[0]),
            )
        )
    if dup.size:
        issues.append(
            QualityIssue(
                "time_duplicate",
                "t",
                "warning",
                f"{dup.size} duplicate time stamps t[i+1] == t[i], i = {_fmt_idx(dup)}",
                float(dup[0]),
            )
        )
    good = dt[np.isfinite(dt) & (dt > 0)]
    if good.size == 0:
        return float(ts) if ts is not None else float("nan")
    med = float(np.median(good))
    if ts is not None and abs(med - ts) > lim.ts_tolerance * ts:
        issues.append(
            QualityIssue(
                "ts_mismatch",
                "t",
                "warning",
                f"median time step {med:g} s differs from the given ts = {ts:g} s",
                med,
            )
        )
    # Gaps relative to the nominal step (given ts, else the median step).
    nominal = float(ts) if ts is not None else med
    gap_mask = good > lim.gap_factor * nominal
    if gap_mask.any():
        gaps = good[gap_mask]
        missing = float(np.sum(gaps - nominal))
        span = float(tf[-1] - tf[0]) if tf.size > 1 else 0.0
        frac = missing / span if span > 0 else 1.0
        gap_idx = np.flatnonzero(np.isfinite(dt) & (dt > lim.gap_factor * nominal))
        sev: Severity = "fatal" if frac > lim.max_gap_fraction else "warning"
        issues.append(
            QualityIssue(
                "gaps",
                "t",
                sev,
                f"{gaps.size} gaps in the time stamps (steps > {lim.gap_factor:g} x "
                f"{nominal:g} s), largest {float(gaps.max()):g} s, missing time "
                f"{100 * frac:.1f}% of the window, at i = {_fmt_idx(gap_idx)}",
                float(gaps.max()),
            )
        )
    regular = good[~gap_mask]
    if regular.size >= 3:
        p10, p90 = np.percentile(regular, [10, 90])
        spread = float((p90 - p10) / med)
        if spread > lim.irregular_tolerance:
            issues.append(
                QualityIssue(
                    "irregular_sampling",
                    "t",
                    "warning",
                    f"irregular sampling: time steps vary by {100 * spread:.0f}% "
                    f"(p10 {p10:g} s, p90 {p90:g} s, median {med:g} s)",
                    spread,
                )
            )
    return float(ts) if ts is not None else med


def _runs(x: NDArray[np.float64]) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Start indices and lengths of runs of identical consecutive values."""
    change = np.flatnonzero(x[1:] != x[:-1]) + 1
    starts = np.concatenate(([0], change)).astype(np.intp)
    ends = np.concatenate((change, [x.size])).astype(np.intp)
    return starts, ends - starts


def _check_signal(
    name: str,
    x_raw: NDArray[np.float64],
    rng: tuple[float, float] | None,
    lim: QualityLimits,
    issues: list[QualityIssue],
) -> None:
    n = x_raw.size
    finite = np.isfinite(x_raw)
    n_bad = int(n - np.count_nonzero(finite))
    if n_bad:
        frac = n_bad / n if n else 1.0
        sev: Severity = "fatal" if frac > lim.max_nonfinite_fraction else "warning"
        first = int(np.flatnonzero(~finite)[0])
        issues.append(
            QualityIssue(
                "nonfinite",
                name,
                sev,
                f"signal '{name}' has {n_bad} NaN/inf samples ({100 * frac:.1f}% of {n}), "
                f"first at index {first}",
                float(n_bad),
            )
        )
    x = x_raw[finite]
    if x.size == 0:
        return
    if x.size < lim.min_samples:
        issues.append(
            QualityIssue(
                "too_few_samples",
                name,
                "fatal",
                f"signal '{name}' has {x.size} finite samples, fewer than {lim.min_samples}",
                float(x.size),
            )
        )
    if name in SET_POINT_SIGNALS:
        return  # constant or stepwise by design: only missing values matter
    lo, hi = float(x.min()), float(x.max())
    if lo == hi:
        issues.append(
            QualityIssue(
                "constant",
                name,
                "fatal",
                f"signal '{name}' is constant at {lo:g} over the whole window",
                lo,
            )
        )
        return
    if x.size < 3:
        return
    scale = hi - lo
    eps = 1e-9 * max(scale, abs(hi), abs(lo))

    values, counts = np.unique(x, return_counts=True)  # sorted, for three of the checks
    sat_values = _check_saturation(name, x, rng, values, counts, lim, issues)
    if name not in HELD_BY_DESIGN_SIGNALS:
        _check_flatline(name, x, sat_values, lim, issues)
    quantised = _check_quantisation(name, x, values.size, eps, lim, issues)
    if name not in HELD_BY_DESIGN_SIGNALS:
        _check_compression(name, x, values, eps, quantised, lim, issues)


def _check_saturation(
    name: str,
    x: NDArray[np.float64],
    rng: tuple[float, float] | None,
    levels: NDArray[np.float64],
    counts: NDArray[np.intp],
    lim: QualityLimits,
    issues: list[QualityIssue],
) -> tuple[float, ...]:
    """Report clipping at the range ends; returns the saturated value(s).  ``levels``
    and ``counts`` are the distinct values of ``x`` and how often each occurs."""
    n = x.size
    found: list[tuple[str, float, float]] = []  # (end, value, fraction)
    if rng is not None:
        r_lo, r_hi = float(rng[0]), float(rng[1])
        tol = lim.saturation_tolerance * abs(r_hi - r_lo)
        for end, value, mask in (
            ("lower", r_lo, x <= r_lo + tol),
            ("upper", r_hi, x >= r_hi - tol),
        ):
            frac = np.count_nonzero(mask) / n
            if frac >= lim.saturation_fraction:
                found.append((end, value, frac))
    elif levels.size >= 3:
        for end, k, nb in (("lower", 0, 1), ("upper", -1, -2)):
            frac = counts[k] / n
            # A clipped signal piles up at the limit; a quantised one visits
            # its extreme level about as often as the neighbouring level.
            if frac >= lim.saturation_fraction and counts[k] >= 3 * counts[nb]:
                found.append((end, float(levels[k]), frac))
    total = sum(f for _, _, f in found)
    if not found:
        return ()
    sev: Severity = "fatal" if total >= lim.saturation_fatal_fraction else "warning"
    detail = ", ".join(f"{100 * f:.1f}% at the {e} end ({v:g})" for e, v, f in found)
    issues.append(
        QualityIssue(
            "saturation",
            name,
            sev,
            f"signal '{name}' saturated: {detail}",
            float(total),
        )
    )
    return tuple(v for _, v, _ in found)


def _check_flatline(
    name: str,
    x: NDArray[np.float64],
    sat_values: tuple[float, ...],
    lim: QualityLimits,
    issues: list[QualityIssue],
) -> None:
    n = x.size
    starts, lengths = _runs(x)
    if sat_values:  # runs at a saturated limit are already reported
        at_sat = np.isin(x[starts], np.asarray(sat_values))
        starts, lengths = starts[~at_sat], lengths[~at_sat]
    if lengths.size == 0:
        return
    min_run = max(lim.flat_min_run, int(np.ceil(lim.flat_run_fraction * n)))
    long = lengths >= min_run
    if not long.any():
        return
    k = int(np.argmax(lengths))
    frac = float(lengths[long].sum()) / n
    sev: Severity = "fatal" if frac >= lim.flat_fatal_fraction else "warning"
    issues.append(
        QualityIssue(
            "flatline",
            name,
            sev,
            f"signal '{name}' frozen: longest run of identical values is {int(lengths[k])} "
            f"samples at {x[starts[k]]:g} from index {int(starts[k])}; runs of >= {min_run} "
            f"samples cover {100 * frac:.1f}% of the window",
            float(lengths[k]),
        )
    )


def _check_quantisation(
    name: str,
    x: NDArray[np.float64],
    n_distinct: int,
    eps: float,
    lim: QualityLimits,
    issues: list[QualityIssue],
) -> bool:
    d = np.abs(np.diff(x))
    nz = d[d > eps]
    if nz.size == 0:
        return False
    q = float(np.percentile(nz, 5))
    p1, p99 = np.percentile(x, [1, 99])
    span = float(p99 - p1) if p99 > p1 else float(x.max() - x.min())
    levels = span / q
    if n_distinct <= lim.quantisation_fatal_levels:
        sev: Severity = "fatal"
    elif levels < lim.quantisation_levels:
        sev = "warning"
    else:
        return False
    issues.append(
        QualityIssue(
            "quantisation",
            name,
            sev,
            f"signal '{name}' is coarsely quantised: resolution about {q:g}, "
            f"{levels:.1f} levels across its range, {n_distinct} distinct values",
            q,
        )
    )
    return True


def _check_compression(
    name: str,
    x: NDArray[np.float64],
    u: NDArray[np.float64],
    eps: float,
    quantised: bool,
    lim: QualityLimits,
    issues: list[QualityIssue],
) -> None:
    n = x.size
    d1 = np.diff(x)
    d2 = np.diff(d1)
    # Tolerance for "same slope": a few round-off units of the stored values.
    # Values read back from an archive are rounded to its resolution; the
    # finest spacing between distinct values estimates that resolution.
    tol = 8.0 * eps
    if u.size > 1:  # u: the distinct values of x, sorted
        lsb = float(np.min(np.diff(u)))
        nz1 = np.abs(d1[np.abs(d1) > eps])
        # Only trust a coarse storage resolution when the signal's own steps
        # are much larger than it (otherwise d2 ~ lsb is genuine movement).
        if nz1.size and float(np.median(nz1)) >= 10.0 * lsb:
            tol = max(tol, 2.01 * lsb)
    straight = np.abs(d2) <= tol
    if quantised:
        # Runs of repeated values are explained by the quantisation; count only
        # straight segments with non-zero slope.
        straight &= np.abs(d1[1:]) > eps
    knots = int(np.count_nonzero(~straight))
    cf = (n - 1) / (knots + 1)
    if cf < lim.compression_factor:
        return
    sev: Severity = "fatal" if cf >= lim.compression_fatal_factor else "warning"
    frac_straight = float(np.count_nonzero(straight)) / max(d2.size, 1)
    issues.append(
        QualityIssue(
            "compression",
            name,
            sev,
            f"signal '{name}' looks reconstructed from a compressed archive: "
            f"{100 * frac_straight:.0f}% of samples lie on straight-line or held segments, "
            f"estimated compression factor {cf:.1f}",
            float(cf),
        )
    )
