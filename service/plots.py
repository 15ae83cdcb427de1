"""Plots of a loop's data and diagnosis, drawn as SVG by hand and rasterised to PNG.

Compute and draw are separate (STYLE.md): the analytics return arrays and
result objects, the ``*_figure`` functions here turn them into a
:class:`Figure` (panels of series and markers in data units), and
:func:`render_svg` / :func:`render_png` draw it.  The SVG is written by hand
rather than by a plotting library so that it is small, accessible (``role="img"``
with a ``<title>`` and a ``<desc>`` that says what the plot shows in words) and
can be checked: every panel carries its data ranges and plot box as
``data-*`` attributes and every series its signal name, so a test or a
script can map the drawn coordinates back to data.  PNG is the same SVG
rasterised by resvg (``resvg_py``: one self-contained wheel, no system
libraries), so the two formats never disagree.

Figures
-------
* :func:`trend_figure`: SP, PV, OP (and MV) against time.
* :func:`signature_figure`: the valve signature, OP against PV (and against
  MV when measured), with the ellipse fitted by
  :func:`analytics.stiction.signature.fit_signature_ellipse` and its width
  along OP, the apparent stiction (Choudhury, Shah, Thornhill & Shook 2006,
  Control Eng. Practice 14:1395-1412, section 6), and the fitted stiction
  model's trace (:class:`analytics.replay.ModelTrace`: the Hammerstein fit of
  :func:`analytics.quantification.quantify_stiction` replayed on the
  measured OP, its last periods): OP against its predicted PV and against its MV.
* :func:`spectrum_figure`: power spectrum and autocorrelation of OP and PV
  with the detected period (Thornhill, Huang & Zhang 2003, J. Process
  Control 13:91-100, read the period off the ACF).
* :func:`nyquist_figure`: ``G Gc`` and ``-1/N(A)`` with the predicted limit
  cycles (thesis Figs. 3.1, 5.16; Eq. 3.16) from
  :class:`analytics.limit_cycle.NyquistCurves`.
* :func:`history_figure`: health, S and J of the past analyses.
* :func:`model_check_figure`: measured PV against the base and the extended
  model driven by the measured OP, and their errors
  (:class:`analytics.model_check.check.Overlay`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Literal
from xml.sax.saxutils import escape, quoteattr

import numpy as np
import resvg_py
from numpy.typing import ArrayLike

from analytics.limit_cycle import NyquistCurves, Prediction
from analytics.replay import ModelTrace
from analytics.signals import autocorrelation, power_spectrum
from analytics.stiction.signature import EllipseFit
from analytics.types import FloatArray

__all__ = [
    "COLOURS",
    "PLOT_WIDTH",
    "PNG_ZOOM",
    "Figure",
    "Marker",
    "Panel",
    "Series",
    "ellipse_points",
    "format_utc",
    "history_figure",
    "model_check_figure",
    "nyquist_figure",
    "render_png",
    "render_svg",
    "signature_figure",
    "spectrum_figure",
    "trend_figure",
]

AxisFormat = Literal["number", "time"]

PLOT_WIDTH = 760
"""Width of every figure, px (the height follows from the number of panels)."""
PANEL_HEIGHT = 300
MARGIN_LEFT, MARGIN_RIGHT, MARGIN_TOP, MARGIN_BOTTOM = 70, 20, 34, 64
TITLE_WIDTH = PLOT_WIDTH - 2 * MARGIN_RIGHT
"""Room for a figure's title, which starts at the right margin's distance from the left."""
PNG_ZOOM = 1.5
"""PNG pixels per SVG unit: 1140 px wide, sharp in an e-mail or a printed ticket."""
FONT = "DejaVu Sans, Liberation Sans, Arial, Helvetica, sans-serif"

COLOURS = {
    "sp": "#000000",
    "pv": "#0072B2",
    "op": "#D55E00",
    "mv": "#009E73",
    "fit": "#CC79A7",
    "model": "#E69F00",
    "marker": "#6a3d9a",
    "health": "#0072B2",
    "S": "#D55E00",
    "J": "#009E73",
    "loop": "#0072B2",
    "df": "#D55E00",
    "pv_base": "#D55E00",
    "pv_extended": "#009E73",
}
"""Okabe-Ito colours: told apart with the common colour-vision deficiencies."""


@dataclass(frozen=True)
class Series:
    """One curve or point cloud of a panel, in data units.

    ``name`` is the signal (``pv``, ``op``...): the ``data-series`` attribute
    of its SVG path.  ``style`` "line" joins the points (a non-finite value
    breaks the line), "points" draws a dot of diameter ``2 width`` per point.
    """

    name: str
    label: str
    x: FloatArray
    y: FloatArray
    colour: str
    style: Literal["line", "points"] = "line"
    dashed: bool = False
    width: float = 1.5


@dataclass(frozen=True)
class Marker:
    """A vertical line at ``x`` (``y`` None) or a labelled point at ``(x, y)``."""

    name: str
    label: str
    x: float
    y: float | None = None


@dataclass(frozen=True)
class Panel:
    """One set of axes."""

    title: str
    x_label: str
    y_label: str
    series: tuple[Series, ...]
    markers: tuple[Marker, ...] = ()
    x_log: bool = False
    y_log: bool = False
    x_format: AxisFormat = "number"
    x_range: tuple[float, float] | None = None
    y_range: tuple[float, float] | None = None
    note: str = ""


@dataclass(frozen=True)
class Figure:
    """Panels stacked vertically, with a title and a description in words."""

    kind: str
    title: str
    description: str
    panels: tuple[Panel, ...] = field(default_factory=tuple)


# ---------------------------------------------------------------------------- computations


def format_utc(t: float) -> str:
    """``2023-11-14 22:13 UTC`` for a UNIX time."""
    return datetime.fromtimestamp(t, UTC).strftime("%Y-%m-%d %H:%M UTC")


def ellipse_points(fit: EllipseFit, points: int = 181) -> tuple[FloatArray, FloatArray]:
    """OP and PV coordinates of the fitted ellipse, closed (first point repeated).

    ``x = cx + m cos t cos a - n sin t sin a``, ``y = cy + m cos t sin a + n sin t cos a``
    with the centre ``(cx, cy)``, semi-axes ``m, n`` and angle ``a`` of
    :class:`~analytics.stiction.signature.EllipseFit` (all in signal units).
    """
    t = np.linspace(0.0, 2.0 * math.pi, points)
    (cx, cy), (m, n), a = fit.centre, fit.semi_axes, fit.angle
    x = cx + m * np.cos(t) * math.cos(a) - n * np.sin(t) * math.sin(a)
    y = cy + m * np.cos(t) * math.sin(a) + n * np.sin(t) * math.cos(a)
    return x, y


# ---------------------------------------------------------------------------- figures


def _array(x: ArrayLike) -> FloatArray:
    return np.asarray(x, dtype=np.float64)


SIGNAL_LABELS = {"sp": "SP", "pv": "PV", "op": "OP", "mv": "MV"}


def trend_figure(
    series: Mapping[str, tuple[ArrayLike, ArrayLike]], *, title: str, unit: str = "% of span"
) -> Figure:
    """SP, PV, OP and MV against time (UNIX s, drawn as UTC clock time).

    ``series`` maps a signal name (``sp``, ``pv``, ``op``, ``mv``) to its
    times and values; NaN marks a bad or missing sample and breaks the line.
    PV and SP share the upper panel, OP and MV the lower one.
    """
    unknown = sorted(set(series) - set(SIGNAL_LABELS))
    if unknown:
        raise ValueError(f"trend_figure: unknown signals {unknown} (expected sp, pv, op, mv)")

    def drawn(names: Sequence[str]) -> tuple[Series, ...]:
        return tuple(
            Series(name, SIGNAL_LABELS[name], _array(series[name][0]), _array(series[name][1]),
                   COLOURS[name], dashed=name == "sp")
            for name in names if name in series
        )

    panels = []
    upper, lower = drawn(("sp", "pv")), drawn(("op", "mv"))
    if upper:
        panels.append(Panel("Process variable and set point", "time (UTC)", f"PV ({unit})",
                            upper, x_format="time"))
    if lower:
        panels.append(Panel("Controller output and valve position", "time (UTC)",
                            f"OP ({unit})", lower, x_format="time"))
    if not panels:
        raise ValueError("trend_figure: no signals to draw")
    counts = ", ".join(
        f"{SIGNAL_LABELS[k]} {np.count_nonzero(np.isfinite(_array(v[1])))} samples"
        for k, v in series.items()
    )
    return Figure("trend", title, f"Trend of the loop's signals over time: {counts}.",
                  tuple(panels))


def _signature_panel(
    op: FloatArray, valve: FloatArray, valve_name: str, fit: EllipseFit | None, unit: str,
    model: ModelTrace | None,
) -> Panel:
    label = SIGNAL_LABELS[valve_name]
    drawn = [Series(valve_name, "samples", op, valve, COLOURS[valve_name],
                    style="points")]
    notes = ["no ellipse: no oscillation period to filter at"]
    if fit is not None:
        ex, ey = ellipse_points(fit)
        half = fit.apparent_stiction / 2.0
        cx, cy = fit.centre
        drawn += [
            Series("ellipse", "ellipse", ex, ey, COLOURS["fit"], width=2.5),
            Series("apparent_stiction", "apparent stiction", np.array([cx - half, cx + half]),
                   np.array([cy, cy]), COLOURS["sp"], width=2.5),
        ]
        notes = [f"apparent stiction {fit.apparent_stiction:.2f} % of OP span (width ratio "
                 f"{fit.width_ratio:.2f}, fit residual {fit.residual:.2f})"]
    if model is not None:
        drawn += _model_series(model, valve_name)
        notes.append(f"fitted model predicts PV with R² {model.r2:.2f}" if valve_name == "pv"
                     else model.label)
    return Panel(f"Valve signature: OP against {label}", f"OP ({unit})", f"{label} ({unit})",
                 tuple(drawn), note="; ".join(notes))


def _model_series(model: ModelTrace, signal: str) -> list[Series]:
    """The fitted model's path from OP to its ``pv`` or ``mv`` over the last cycles, a line."""
    return [Series(f"model_{signal}", f"model {SIGNAL_LABELS[signal]}", _array(model.op),
                   _array(model.pv if signal == "pv" else model.mv), COLOURS["model"],
                   width=2.0)]


def _model_valve_panel(model: ModelTrace, unit: str) -> Panel:
    """OP against the model's MV when MV is not measured: the fitted valve's stick-slip."""
    return Panel("Fitted valve model: OP against the model's MV", f"OP ({unit})",
                 f"model MV ({unit})", tuple(_model_series(model, "mv")),
                 note=model.label)


def signature_figure(
    op: ArrayLike,
    pv: ArrayLike,
    *,
    title: str,
    pv_fit: EllipseFit | None = None,
    mv: ArrayLike | None = None,
    mv_fit: EllipseFit | None = None,
    model: ModelTrace | None = None,
    unit: str = "% of span",
) -> Figure:
    """The valve signature: OP against PV (and MV), with the fitted ellipse and model.

    The ellipse is the direct least-squares fit to the band-passed signature
    (:func:`analytics.stiction.signature.fit_signature_ellipse`); the black
    bar through its centre is its width along the OP axis, the apparent
    stiction of Choudhury et al. (2006, section 6).  The fitted stiction
    ``model`` (:class:`analytics.replay.ModelTrace`, as the diagnosis stored it) is drawn as
    its path from OP to the predicted PV over the OP-PV signature and from OP to its MV:
    over the measured OP-MV signature, or in a panel of its own when MV is not
    measured.  Only pairs where both signals are finite are drawn.
    """
    op_values, pv_values = _array(op), _array(pv)
    if op_values.shape != pv_values.shape:
        raise ValueError(f"signature_figure: op and pv differ in shape, "
                         f"{op_values.shape} and {pv_values.shape}")
    panels = [_signature_panel(op_values, pv_values, "pv", pv_fit, unit, model)]
    if mv is not None:
        mv_values = _array(mv)
        if mv_values.shape != op_values.shape:
            raise ValueError(f"signature_figure: op and mv differ in shape, "
                             f"{op_values.shape} and {mv_values.shape}")
        panels.append(_signature_panel(op_values, mv_values, "mv", mv_fit, unit, model))
    elif model is not None:
        panels.append(_model_valve_panel(model, unit))
    words = "; ".join(f"{p.title}: {p.note}" for p in panels)
    return Figure("signature", title, f"Valve signature. {words}.", tuple(panels))


def spectrum_figure(
    op: ArrayLike | None, pv: ArrayLike | None, ts: float, *, title: str,
    period_s: float | None = None,
) -> Figure:
    """Power spectrum (against period) and autocorrelation of OP and PV.

    The detected period, when given, is marked in both panels: a regular
    oscillation shows as a spectral peak there and as an ACF that crosses
    zero every half period and peaks again at one period (Thornhill et al. 2003).
    """
    signals = {name: _array(x) for name, x in (("pv", pv), ("op", op)) if x is not None}
    if not signals:
        raise ValueError("spectrum_figure: neither op nor pv given")
    spectra, acfs = [], []
    longest = max(x.size for x in signals.values())
    max_lag = longest // 2 if period_s is None else min(longest // 2,
                                                        math.ceil(4 * period_s / ts))
    for name, x in signals.items():
        periods, power = power_spectrum(x, ts)
        spectra.append(Series(name, SIGNAL_LABELS[name], periods, power, COLOURS[name]))
        acf = autocorrelation(x, max_lag)
        acfs.append(Series(name, SIGNAL_LABELS[name], ts * np.arange(acf.size, dtype=float), acf,
                           COLOURS[name]))
    markers: tuple[Marker, ...] = ()
    words = "no regular oscillation detected"
    if period_s is not None:
        markers = (Marker("period", f"period {period_s:.0f} s", period_s),)
        words = f"detected period {period_s:.1f} s"
    shortest = 2.0 * ts
    panels = (
        Panel("Power spectrum", "period (s)", "power (relative to the peak)", tuple(spectra),
              markers, x_log=True, x_range=(shortest, float(max(s.x[0] for s in spectra)))),
        Panel("Autocorrelation", "lag (s)", "ACF", tuple(acfs), markers, y_range=(-1.0, 1.0)),
    )
    return Figure("spectrum", title, f"Power spectrum and autocorrelation; {words}.", panels)


def nyquist_figure(
    curves: NyquistCurves, *, title: str, prediction: Prediction | None = None
) -> Figure:
    """``G Gc`` (or the equivalent loop of thesis Eq. 3.20) and ``-1/N(A)`` per sticky valve.

    A limit cycle sits where the two curves meet (harmonic balance, thesis
    Eq. 3.16: ``G(jw) Gc(jw) = -1/N(A)``); the predicted cycles of
    ``prediction`` are marked there with their period, stable or not.
    """
    panels = []
    cycles = () if prediction is None else prediction.limit_cycles
    for row, loop in enumerate(curves.loops):
        response = curves.loop_response[row]
        inverse = curves.negative_inverse_df[row]
        shown = np.abs(response) <= 4.0 * max(1.0, float(np.max(np.abs(inverse))))
        markers = tuple(
            Marker("limit_cycle",
                   f"{'stable' if c.stable else 'unstable'} cycle, {c.period_s:.1f} s",
                   float(point.real), float(point.imag))
            for c in cycles
            for point in (_loop_value(curves, row, c.omega),)
        )
        panels.append(Panel(
            f"Loop {loop + 1}: G Gc and -1/N(A)", "real part", "imaginary part",
            (Series("loop", "G Gc (jw)", response.real[shown], response.imag[shown],
                    COLOURS["loop"]),
             Series("df", "-1/N(A)", inverse.real, inverse.imag, COLOURS["df"], width=2.5)),
            markers,
        ))
    if not cycles:
        words = "no limit cycle predicted"
    else:
        words = "; ".join(f"{'stable' if c.stable else 'unstable'} limit cycle of period "
                          f"{c.period_s:.1f} s" for c in cycles)
    return Figure("nyquist", title, f"Nyquist and describing-function plot: {words}.",
                  tuple(panels))


def _loop_value(curves: NyquistCurves, row: int, omega: float) -> complex:
    """``L(jw)`` at ``omega`` by interpolation along the sampled frequency grid."""
    log_omega = np.log(curves.omega)
    response = curves.loop_response[row]
    re = np.interp(math.log(omega), log_omega, response.real)
    im = np.interp(math.log(omega), log_omega, response.imag)
    return complex(re, im)


def history_figure(
    times: ArrayLike, health: ArrayLike, S: ArrayLike, J: ArrayLike, *, title: str
) -> Figure:
    """Health (0-100) and the stiction estimate S, J (% of span) of past analyses.

    Missing values (a loop without a stiction verdict has no S and J) are NaN.
    """
    t = _array(times)
    panels = (
        Panel("Loop health", "time (UTC)", "health (0-100)",
              (Series("health", "health", t, _array(health), COLOURS["health"],
                      style="points", width=3.0),),
              x_format="time", y_range=(0.0, 100.0)),
        Panel("Stiction estimate", "time (UTC)", "% of span",
              (Series("S", "S (stick band + deadband)", t, _array(S), COLOURS["S"],
                      style="points", width=3.0),
               Series("J", "J (slip jump)", t, _array(J), COLOURS["J"], style="points",
                      width=3.0)),
              x_format="time"),
    )
    return Figure("history", title, f"Health and stiction estimate over {t.size} analyses.",
                  panels)


def model_check_figure(
    t: ArrayLike, pv: ArrayLike, pv_base: ArrayLike, pv_extended: ArrayLike,
    scored: ArrayLike, *, title: str,
) -> Figure:
    """Measured PV against the replay of the base and the extended model, and their errors.

    The inputs are the overlay of :func:`analytics.model_check.check_model`:
    each model is driven by the measured OP and each scored sample predicted
    by the model fitted on the other half of the data; the warm-up
    (``scored`` False) is not drawn for the models.  The lower panel shows
    measured minus simulated PV, where each model goes wrong.
    """
    times, measured = _array(t), _array(pv)
    keep = np.asarray(scored, dtype=bool)
    shapes = {a.shape for a in (times, measured, _array(pv_base), _array(pv_extended), keep)}
    if len(shapes) != 1:
        raise ValueError(f"model_check_figure: t, pv, pv_base, pv_extended and scored differ "
                         f"in shape: {sorted(shapes)}")
    base, extended = (np.where(keep, _array(x), np.nan) for x in (pv_base, pv_extended))
    panels = (
        Panel("Measured and simulated PV", "time (UTC)", "PV (% of span)", (
            Series("pv", "measured", times, measured, COLOURS["pv"]),
            Series("pv_base", "base model", times, base, COLOURS["pv_base"], dashed=True),
            Series("pv_extended", "extended model", times, extended, COLOURS["pv_extended"]),
        ), x_format="time"),
        Panel("Simulation error: measured minus simulated PV", "time (UTC)", "% of span", (
            Series("error_base", "base model", times, measured - base, COLOURS["pv_base"],
                   dashed=True),
            Series("error_extended", "extended model", times, measured - extended,
                   COLOURS["pv_extended"]),
        ), x_format="time"),
    )

    def rms(error: FloatArray) -> float:
        return float(np.sqrt(np.nanmean(error**2))) if np.isfinite(error).any() else math.nan

    return Figure("model-check", title, (
        f"Measured PV against the simulated PV of the base and the extended model, "
        f"{int(keep.sum())} scored samples; RMS error {rms(measured - base):.3g} (base) and "
        f"{rms(measured - extended):.3g} (extended) % of span."), panels)


# ---------------------------------------------------------------------------- drawing


def _nice_step(span: float, target: int) -> float:
    """A 1-2-5 step that cuts ``span`` into about ``target`` intervals."""
    raw = span / max(target, 1)
    magnitude = 10.0 ** math.floor(math.log10(raw))
    for factor in (1.0, 2.0, 5.0, 10.0):
        if raw <= factor * magnitude:
            return factor * magnitude
    return 10.0 * magnitude


TIME_STEPS_S = (1, 2, 5, 10, 15, 30, 60, 120, 300, 600, 900, 1800, 3600, 7200, 10800,
                21600, 43200, 86400, 2 * 86400, 7 * 86400)


def _ticks(lo: float, hi: float, *, log: bool, time: bool) -> list[float]:
    if log:
        first, last = math.floor(math.log10(lo)), math.ceil(math.log10(hi))
        decades = [10.0 ** k for k in range(first, last + 1)]
        if len(decades) <= 3:
            decades = [d * m for d in decades for m in (1.0, 2.0, 5.0)]
        return [d for d in decades if lo <= d <= hi]
    span = hi - lo
    if time:
        step = float(next((s for s in TIME_STEPS_S if span / s <= 6), 0.0)
                     or 86400.0 * _nice_step(span / 86400.0, 5))
    else:
        step = _nice_step(span, 5)
    start = math.ceil(lo / step) * step
    return [start + k * step for k in range(int((hi - start) / step + 1e-9) + 1)]


def _format_tick(value: float, *, time: bool, span: float) -> str:
    if time:
        moment = datetime.fromtimestamp(value, UTC)
        if span > 2 * 86400:
            return moment.strftime("%m-%d %H:%M")
        return moment.strftime("%H:%M:%S" if span < 300 else "%H:%M")
    if value == 0:
        return "0"
    return f"{value:.6g}" if 1e-3 <= abs(value) < 1e6 else f"{value:.1e}"


def _data_range(values: list[FloatArray], *, log: bool, time: bool = False
                ) -> tuple[float, float]:
    finite = np.concatenate([v[np.isfinite(v) & ((v > 0) if log else True)] for v in values])
    if finite.size == 0:
        return (1.0, 10.0) if log else (0.0, 1.0)
    lo, hi = float(finite.min()), float(finite.max())
    if log:
        return (lo, hi) if hi > lo else (lo / 2, hi * 2)
    if hi == lo:
        pad = 60.0 if time else abs(lo) * 0.05 or 1.0
        return lo - pad, hi + pad
    pad = 0.04 * (hi - lo)
    return lo - pad, hi + pad


@dataclass(frozen=True)
class _Axes:
    """Map data to SVG coordinates inside one panel's plot box."""

    left: float
    top: float
    width: float
    height: float
    x_range: tuple[float, float]
    y_range: tuple[float, float]
    x_log: bool
    y_log: bool

    @staticmethod
    def _unit(v: FloatArray, span: tuple[float, float], log: bool) -> FloatArray:
        lo, hi = span
        if log:
            with np.errstate(divide="ignore", invalid="ignore"):
                return (np.log10(v) - math.log10(lo)) / (math.log10(hi) - math.log10(lo))
        return (v - lo) / (hi - lo)

    def x(self, v: ArrayLike) -> FloatArray:
        return self.left + self.width * self._unit(_array(v), self.x_range, self.x_log)

    def y(self, v: ArrayLike) -> FloatArray:
        return self.top + self.height * (1.0 - self._unit(_array(v), self.y_range, self.y_log))


def _path(xs: FloatArray, ys: FloatArray, *, dots: bool) -> str:
    """SVG path data; a non-finite point breaks a line (and is not drawn as a dot)."""
    parts: list[str] = []
    pen_down = False
    for x, y in zip(xs.tolist(), ys.tolist(), strict=True):
        if not (math.isfinite(x) and math.isfinite(y)):
            pen_down = False
            continue
        if dots:
            parts.append(f"M{x:.2f} {y:.2f}h0")
        else:
            parts.append(f"{'L' if pen_down else 'M'}{x:.2f} {y:.2f}")
            pen_down = True
    return "".join(parts)


CHAR_WIDTH = {"normal": 0.62, "bold": 0.7}
"""Widest mean advance of a character, in font sizes, of the fonts of :data:`FONT`
(DejaVu Sans is the widest: 0.61 em for its regular text, 0.69 em bold)."""


def _text(x: float, y: float, content: str, *, size: int = 12, anchor: str = "start",
          weight: str = "normal", rotate: bool = False, colour: str = "#222222",
          fit: float | None = None) -> str:
    """An SVG ``<text>``; with ``fit``, a text that could be wider than ``fit`` units is
    squeezed to that width (``textLength``), so that no title is cut at the plot's edge."""
    transform = f' transform="rotate(-90 {x:.1f} {y:.1f})"' if rotate else ""
    if fit is not None and len(content) * size * CHAR_WIDTH[weight] > fit:
        transform += f' textLength="{fit:.1f}" lengthAdjust="spacingAndGlyphs"'
    return (f'<text x="{x:.1f}" y="{y:.1f}" font-size="{size}" text-anchor="{anchor}" '
            f'font-weight="{weight}" fill="{colour}"{transform}>{escape(content)}</text>')


def _label_place(panel: Panel, axes: _Axes, label: str, x: float, y: float,
                 box: tuple[float, float, float, float]) -> tuple[float, float, str]:
    """Where a point marker's label goes: of the four corners around the point, the one
    whose text crosses the fewest drawn samples (the lines sampled 8 times a segment),
    the upper ones first on a tie; ``(x, baseline y, text-anchor)`` in pixels."""
    left, top, width, height = box
    px, py = [], []
    for s in panel.series:
        xs, ys = np.asarray(axes.x(s.x), float), np.asarray(axes.y(s.y), float)
        if s.style != "points" and xs.size > 1:
            fine = np.linspace(0.0, xs.size - 1.0, 8 * (xs.size - 1) + 1)
            xs, ys = (np.interp(fine, np.arange(xs.size), v) for v in (xs, ys))
        px.append(xs)
        py.append(ys)
    xs_all, ys_all = np.concatenate(px or [np.empty(0)]), np.concatenate(py or [np.empty(0)])
    text_width = len(label) * 11 * CHAR_WIDTH["normal"] + 4
    best: tuple[int, float, float, str] | None = None
    for dy in (-8.0, 19.0):  # baseline above the point, or below it
        for anchor in ("start", "end") if x <= left + width * 0.7 else ("end", "start"):
            x0 = x if anchor == "start" else x - text_width
            baseline = float(np.clip(y + dy, top + 11, top + height))
            if x0 < left or x0 + text_width > left + width:
                continue
            inside = ((xs_all >= x0) & (xs_all <= x0 + text_width)
                      & (ys_all >= baseline - 11) & (ys_all <= baseline + 2))
            hits = int(np.count_nonzero(inside))
            if best is None or hits < best[0]:
                best = (hits, x, baseline, anchor)
    if best is None:
        return x, y - 8, "end" if x > left + width * 0.7 else "start"
    return best[1], best[2], best[3]


def _panel_svg(panel: Panel, top: float) -> str:
    left, width = MARGIN_LEFT, PLOT_WIDTH - MARGIN_LEFT - MARGIN_RIGHT
    box_top, height = top + MARGIN_TOP, PANEL_HEIGHT - MARGIN_TOP - MARGIN_BOTTOM
    xs = [s.x for s in panel.series] + [np.array([m.x]) for m in panel.markers]
    ys = [s.y for s in panel.series] + [np.array([m.y]) for m in panel.markers
                                        if m.y is not None]
    time = panel.x_format == "time"
    x_range = panel.x_range or _data_range(xs, log=panel.x_log, time=time)
    y_range = panel.y_range or _data_range(ys, log=panel.y_log)
    axes = _Axes(left, box_top, width, height, x_range, y_range, panel.x_log, panel.y_log)
    out = [
        f'<g class="panel" data-title={quoteattr(panel.title)} '
        f'data-left="{left}" data-top="{box_top}" data-width="{width}" data-height="{height}" '
        f'data-x-min="{x_range[0]!r}" data-x-max="{x_range[1]!r}" '
        f'data-y-min="{y_range[0]!r}" data-y-max="{y_range[1]!r}" '
        f'data-x-log="{str(panel.x_log).lower()}" data-y-log="{str(panel.y_log).lower()}">',
        _text(left, top + 18, panel.title, size=14, weight="bold"),
        f'<rect x="{left}" y="{box_top}" width="{width}" height="{height}" fill="none" '
        'stroke="#555555"/>',
    ]
    for value in _ticks(*x_range, log=panel.x_log, time=time):
        x = float(axes.x(value))
        out.append(f'<line x1="{x:.1f}" y1="{box_top}" x2="{x:.1f}" y2="{box_top + height}" '
                   'stroke="#dddddd"/>')
        out.append(_text(x, box_top + height + 16, _format_tick(
            value, time=time, span=x_range[1] - x_range[0]), anchor="middle"))
    for value in _ticks(*y_range, log=panel.y_log, time=False):
        y = float(axes.y(value))
        out.append(f'<line x1="{left}" y1="{y:.1f}" x2="{left + width}" y2="{y:.1f}" '
                   'stroke="#dddddd"/>')
        out.append(_text(left - 6, y + 4, _format_tick(value, time=False, span=0.0),
                         anchor="end"))
    out.append(_text(left + width / 2, box_top + height + 36, panel.x_label, anchor="middle"))
    out.append(_text(16, box_top + height / 2, panel.y_label, anchor="middle", rotate=True))
    out.append(f'<svg x="{left}" y="{box_top}" width="{width}" height="{height}" '
               f'viewBox="{left} {box_top} {width} {height}" overflow="hidden">')
    for s in panel.series:
        dots = s.style == "points"
        stroke = f'stroke="{s.colour}" stroke-width="{2 * s.width if dots else s.width}"'
        extra = ' stroke-dasharray="6 4"' if s.dashed else ""
        extra += ' stroke-linecap="round"' if dots else ' stroke-linejoin="round"'
        out.append(f'<path class="series" data-series="{escape(s.name)}" '
                   f'd="{_path(axes.x(s.x), axes.y(s.y), dots=dots)}" fill="none" '
                   f'{stroke}{extra}><title>{escape(s.label)}</title></path>')
    for m in panel.markers:
        x = float(axes.x(m.x))
        if m.y is None:
            out.append(f'<line class="marker" data-marker="{escape(m.name)}" x1="{x:.2f}" '
                       f'y1="{box_top}" x2="{x:.2f}" y2="{box_top + height}" '
                       f'stroke="{COLOURS["marker"]}" stroke-width="1.5" '
                       'stroke-dasharray="3 3"/>')
        else:
            y = float(axes.y(m.y))
            out.append(f'<circle class="marker" data-marker="{escape(m.name)}" cx="{x:.2f}" '
                       f'cy="{y:.2f}" r="5" fill="none" stroke="{COLOURS["marker"]}" '
                       'stroke-width="2"/>')
    out.append("</svg>")
    for m in panel.markers:  # labels outside the clip so they are never cut
        x = float(np.clip(axes.x(m.x), left + 4, left + width - 4))
        if m.y is None:
            anchor = "end" if x > left + width * 0.7 else "start"
            y = box_top + 14
        else:
            y_point = float(np.clip(axes.y(m.y), box_top, box_top + height))
            x, y, anchor = _label_place(panel, axes, m.label, x, y_point,
                                        (left, box_top, width, height))
        out.append(_text(x + (-4 if anchor == "end" else 4), y, m.label, size=11,
                         anchor=anchor, colour=COLOURS["marker"]))
    legend_x = left + width
    for s in reversed(panel.series):
        label_width = 7 * len(s.label) + 26
        legend_x -= label_width
        dash = ' stroke-dasharray="6 4"' if s.dashed else ""
        out.append(f'<line x1="{legend_x:.1f}" y1="{top + 14}" x2="{legend_x + 16:.1f}" '
                   f'y2="{top + 14}" stroke="{s.colour}" stroke-width="3"{dash}/>')
        out.append(_text(legend_x + 20, top + 18, s.label, size=11))
    if panel.note:
        out.append(_text(left, box_top + height + 54, panel.note, size=11))
    out.append("</g>")
    return "\n".join(out)


def render_svg(figure: Figure) -> str:
    """The figure as a standalone, accessible SVG document (a string).

    The root element has ``role="img"``, the figure's title as ``<title>`` and
    ``aria-label`` and its description as ``<desc>``; each series is a
    ``<path class="series" data-series=NAME>``.
    """
    height = PANEL_HEIGHT * len(figure.panels) + 30
    panels = "\n".join(_panel_svg(p, 30 + PANEL_HEIGHT * i) for i, p in enumerate(figure.panels))
    return (
        f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {PLOT_WIDTH} {height}" '
        f'width="{PLOT_WIDTH}" height="{height}" role="img" class="lw-plot" '
        f'data-kind="{escape(figure.kind)}" aria-label={quoteattr(figure.title)} '
        f'font-family="{FONT}">\n'
        f"<title>{escape(figure.title)}</title>\n<desc>{escape(figure.description)}</desc>\n"
        f'<rect width="{PLOT_WIDTH}" height="{height}" fill="#ffffff"/>\n'
        f"{_text(MARGIN_RIGHT, 20, figure.title, size=15, weight='bold', fit=TITLE_WIDTH)}\n"
        f"{panels}\n</svg>\n"
    )


def render_png(figure: Figure, *, zoom: float = PNG_ZOOM) -> bytes:
    """The figure as PNG: :func:`render_svg` rasterised by resvg at ``zoom`` px per unit."""
    return bytes(resvg_py.svg_to_bytes(svg_string=render_svg(figure), zoom=zoom))
