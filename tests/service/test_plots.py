"""Plots: the figures of ``service/plots.py`` checked against known answers (the routes:
``tests/service/api/test_plots.py``).

The drawn coordinates are read back out of the SVG (each panel records its
plot box and data ranges) and compared with what the data say: an analytic
ellipse for a quadrature cycle, the injected period of a sine, the thesis's
Table 5.1 end points of ``-1/N(A)``.  PNG output is decoded here and its
coloured pixels compared with the SVG's geometry.
"""

from __future__ import annotations

import math
import re
import struct
import xml.etree.ElementTree as ET
import zlib

import numpy as np
import pytest

from analytics.limit_cycle import nyquist_curves, predict_limit_cycles
from analytics.lti import TransferFunction
from analytics.replay import MODEL_CYCLES_KEPT, stiction_model_path
from analytics.simulation import PIDController
from analytics.stiction.signature import fit_signature_ellipse
from analytics.valves import ChoudhuryValve, KanoValve
from service import plots
from tests.analytics.test_replay import TRUE_FLOW_PROCESS, sticky_flow_loop
from tests.service.test_api import ADMIN, T0

SVG = "{http://www.w3.org/2000/svg}"
HEADERS = {"X-API-Key": ADMIN}


# ---------------------------------------------------------------------------- reading SVG


def parse(svg: str) -> ET.Element:
    return ET.fromstring(svg)


def panels(root: ET.Element) -> list[ET.Element]:
    return [g for g in root.iter(f"{SVG}g") if g.get("class") == "panel"]


def to_data(panel: ET.Element, px: np.ndarray, py: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Invert the panel's mapping from data to SVG coordinates."""
    left, top = float(panel.get("data-left")), float(panel.get("data-top"))
    width, height = float(panel.get("data-width")), float(panel.get("data-height"))

    def invert(u: np.ndarray, lo: float, hi: float, log: bool) -> np.ndarray:
        if log:
            return 10 ** (math.log10(lo) + u * (math.log10(hi) - math.log10(lo)))
        return lo + u * (hi - lo)

    x = invert((px - left) / width, float(panel.get("data-x-min")),
               float(panel.get("data-x-max")), panel.get("data-x-log") == "true")
    y = invert(1 - (py - top) / height, float(panel.get("data-y-min")),
               float(panel.get("data-y-max")), panel.get("data-y-log") == "true")
    return x, y


def series_path(panel: ET.Element, name: str) -> str:
    found = [p for p in panel.iter(f"{SVG}path") if p.get("data-series") == name]
    assert len(found) == 1, f"one path for series {name!r}"
    return found[0].get("d") or ""


def drawn(panel: ET.Element, name: str) -> tuple[np.ndarray, np.ndarray]:
    """Data coordinates of every point of a series' path."""
    points = re.findall(r"[ML](-?[\d.]+) (-?[\d.]+)", series_path(panel, name))
    xy = np.array(points, dtype=float).reshape(-1, 2)
    return to_data(panel, xy[:, 0], xy[:, 1])


def marker(panel: ET.Element, name: str) -> tuple[float, float]:
    element = next(e for e in panel.iter() if e.get("data-marker") == name)
    if element.tag == f"{SVG}line":
        x, _ = to_data(panel, np.array([float(element.get("x1"))]), np.array([0.0]))
        return float(x[0]), math.nan
    x, y = to_data(panel, np.array([float(element.get("cx"))]),
                   np.array([float(element.get("cy"))]))
    return float(x[0]), float(y[0])


def resolution(panel: ET.Element, axis: str) -> float:
    """One hundredth of an SVG unit in data units (the path precision) times a margin."""
    span = float(panel.get(f"data-{axis}-max")) - float(panel.get(f"data-{axis}-min"))
    return 2 * 0.01 * span / float(panel.get("data-width" if axis == "x" else "data-height"))


# ---------------------------------------------------------------------------- figures


def quadrature_cycle(phase: float = math.pi / 2) -> tuple[np.ndarray, np.ndarray]:
    k = np.arange(2000)
    return 50 + 2 * np.sin(2 * np.pi * k / 100), 30 + np.sin(2 * np.pi * k / 100 - phase)


def test_svg_is_accessible_xml_with_title_and_description():
    op, pv = quadrature_cycle()
    root = parse(plots.render_svg(plots.signature_figure(op, pv, title="FIC-1 & <signature>")))
    assert root.get("role") == "img"
    assert root.get("aria-label") == "FIC-1 & <signature>"
    assert root.find(f"{SVG}title").text == "FIC-1 & <signature>"
    assert "no ellipse" in root.find(f"{SVG}desc").text
    assert root.get("data-kind") == "signature"


def test_trend_draws_every_sample_and_breaks_the_line_at_a_gap():
    t = T0 + np.arange(300.0)
    pv = 40 + 5 * np.sin(t / 20)
    pv[100:110] = np.nan
    op = 60 - 3 * np.cos(t / 20)
    root = parse(plots.render_svg(plots.trend_figure(
        {"pv": (t, pv), "op": (t, op), "sp": (t, np.full(t.size, 40.0))}, title="trend")))
    upper, lower = panels(root)
    x, y = drawn(upper, "pv")
    ok = np.isfinite(pv)
    np.testing.assert_allclose(x, t[ok], atol=resolution(upper, "x"))
    np.testing.assert_allclose(y, pv[ok], atol=resolution(upper, "y"))
    assert series_path(upper, "pv").count("M") == 2  # the gap starts a new line
    _, y_op = drawn(lower, "op")
    np.testing.assert_allclose(y_op, op, atol=resolution(lower, "y"))


@pytest.mark.parametrize(("phase", "width"), [(math.pi / 2, 4.0), (math.pi / 4, 4 * math.sin(
    math.pi / 4))])
def test_signature_ellipse_matches_the_analytic_cycle(phase, width):
    """OP = 50 + 2 sin(wt), PV = 30 + sin(wt - phi): the ellipse through them is known in
    closed form; its width along OP through the centre is 2 * 2 |sin phi| (the apparent
    stiction of Choudhury et al. 2006, section 6)."""
    op, pv = quadrature_cycle(phase)
    fit = fit_signature_ellipse(op, pv, 100)
    root = parse(plots.render_svg(plots.signature_figure(op, pv, pv_fit=fit, title="s")))
    (panel,) = panels(root)
    ex, ey = drawn(panel, "ellipse")
    assert ex.max() - ex.min() == pytest.approx(4.0, abs=0.02)  # OP swing 2 * 2
    assert ey.max() - ey.min() == pytest.approx(2.0, abs=0.02)  # PV swing 2 * 1
    bar_x, bar_y = drawn(panel, "apparent_stiction")
    assert bar_x[1] - bar_x[0] == pytest.approx(width, rel=0.01)
    np.testing.assert_allclose(bar_y, 30.0, atol=0.01)
    dots_x, dots_y = drawn(panel, "pv")
    np.testing.assert_allclose(dots_x, op, atol=resolution(panel, "x"))
    np.testing.assert_allclose(dots_y, pv, atol=resolution(panel, "y"))
    assert f"apparent stiction {fit.apparent_stiction:.2f}" in ET.tostring(root, encoding="unicode")


def test_signature_with_mv_has_a_second_panel():
    op, pv = quadrature_cycle()
    root = parse(plots.render_svg(plots.signature_figure(op, pv, mv=op, title="s")))
    assert [p.get("data-title") for p in panels(root)] == [
        "Valve signature: OP against PV", "Valve signature: OP against MV"]


def test_signature_draws_the_fitted_model_over_pv_and_in_a_valve_panel():
    op, _, pv, ts = sticky_flow_loop()
    path = stiction_model_path(op, pv, ts, valve=KanoValve(4.0, 2.0),
                                     process=TRUE_FLOW_PROCESS, period_s=100.0,
                                     label="fitted kano valve, S = 4.00 %, J = 2.00 %")
    root = parse(plots.render_svg(plots.signature_figure(op, pv, model=path.trace(op),
                                                         title="s")))
    signature, valve = panels(root)
    assert valve.get("data-title") == "Fitted valve model: OP against the model's MV"
    last = slice(-MODEL_CYCLES_KEPT * path.period, None)  # the last cycles only
    x, y = drawn(signature, "model_pv")
    np.testing.assert_allclose(x, op[last], atol=resolution(signature, "x"))
    np.testing.assert_allclose(y, path.pv[last], atol=resolution(signature, "y"))
    x, y = drawn(valve, "model_mv")
    np.testing.assert_allclose(y, path.mv[last], atol=resolution(valve, "y"))
    assert y.max() - y.min() == pytest.approx(np.ptp(op[last]) - 2.0, abs=0.3)  # OP - (S-J)
    description = root.find(f"{SVG}desc").text
    assert f"fitted model predicts PV with R² {path.r2:.2f}" in description
    assert "S = 4.00 %, J = 2.00 %" in description


def test_signature_with_measured_mv_draws_the_model_over_it():
    op, mv, pv, ts = sticky_flow_loop()
    path = stiction_model_path(op, pv, ts, valve=KanoValve(4.0, 2.0),
                                     process=TRUE_FLOW_PROCESS, period_s=100.0, label="m")
    root = parse(plots.render_svg(plots.signature_figure(op, pv, mv=mv, model=path.trace(op),
                                                         title="s")))
    _, valve = panels(root)
    assert valve.get("data-title") == "Valve signature: OP against MV"
    assert series_path(valve, "mv") and series_path(valve, "model_mv")


def test_model_check_draws_measured_and_scored_simulations_and_their_errors():
    t = T0 + np.arange(400.0)
    pv = 50 + np.sin(t / 30)
    base, extended = pv + 0.5, pv - 0.1
    scored = t >= T0 + 100
    root = parse(plots.render_svg(plots.model_check_figure(t, pv, base, extended, scored,
                                                           title="check")))
    overlay, errors = panels(root)
    x, y = drawn(overlay, "pv")
    np.testing.assert_allclose(y, pv, atol=resolution(overlay, "y"))
    x, y = drawn(overlay, "pv_base")
    np.testing.assert_allclose(x, t[scored], atol=resolution(overlay, "x"))  # no warm-up
    np.testing.assert_allclose(y, base[scored], atol=resolution(overlay, "y"))
    _, y = drawn(errors, "error_base")
    np.testing.assert_allclose(y, -0.5, atol=resolution(errors, "y"))
    _, y = drawn(errors, "error_extended")
    np.testing.assert_allclose(y, 0.1, atol=resolution(errors, "y"))
    assert "300 scored samples; RMS error 0.5 (base) and 0.1 (extended)" in \
        root.find(f"{SVG}desc").text
    with pytest.raises(ValueError, match="differ in shape"):
        plots.model_check_figure(t, pv[1:], base, extended, scored, title="x")


def test_spectrum_and_acf_show_the_injected_period():
    ts, period = 0.5, 40.0
    k = np.arange(4000)
    rng = np.random.default_rng(7)
    pv = np.sin(2 * np.pi * k * ts / period) + 0.3 * rng.standard_normal(k.size)
    root = parse(plots.render_svg(plots.spectrum_figure(None, pv, ts, period_s=period,
                                                        title="spectrum")))
    spectrum, acf = panels(root)
    periods, power = drawn(spectrum, "pv")
    bin_width = period**2 / (k.size * ts)  # period resolution of the periodogram at 40 s
    assert periods[np.argmax(power)] == pytest.approx(period, abs=bin_width)
    lags, correlation = drawn(acf, "pv")
    after_first_trough = lags > period / 2
    assert lags[after_first_trough][np.argmax(correlation[after_first_trough])] == \
        pytest.approx(period, abs=1.0)
    assert marker(spectrum, "period")[0] == pytest.approx(period, rel=1e-3)
    assert marker(acf, "period")[0] == pytest.approx(period, abs=resolution(acf, "x"))


def test_nyquist_plot_draws_table_5_1_limits_and_the_cycle_on_both_curves():
    """Thesis Table 5.1: -1/N(A) runs from -j pi/2 (A -> S/2, for J = S/2) to -1
    (A -> inf); a limit cycle sits where G Gc meets it (Eq. 3.16)."""
    g = TransferFunction.fopdt(0.4346, 27.58, 6.0)
    gc = PIDController.ideal(10.0, 10.0)
    valve = ChoudhuryValve(4.0, 2.0)
    prediction = predict_limit_cycles(g, gc, valve)
    assert prediction.limit_cycles
    curves = nyquist_curves(g, gc, valve)
    root = parse(plots.render_svg(plots.nyquist_figure(curves, prediction=prediction,
                                                       title="nyquist")))
    (panel,) = panels(root)
    re_df, im_df = drawn(panel, "df")
    tolerance = resolution(panel, "x") + resolution(panel, "y")
    assert (re_df[0], im_df[0]) == pytest.approx((0.0, -math.pi / 2), abs=tolerance)
    assert (re_df[-1], im_df[-1]) == pytest.approx((-1.0, 0.0), abs=tolerance)
    cx, cy = marker(panel, "limit_cycle")
    re_loop, im_loop = drawn(panel, "loop")
    span = float(panel.get("data-x-max")) - float(panel.get("data-x-min"))
    for xs, ys in ((re_df, im_df), (re_loop, im_loop)):
        assert np.min(np.hypot(xs - cx, ys - cy)) < 0.01 * span


def pixel_points(path: str) -> np.ndarray:
    """The vertices of an SVG path of M/L commands, each segment sampled 20 times."""
    points: list[np.ndarray] = []
    last = None
    for command, x, y in re.findall(r"([ML])(-?[\d.]+) (-?[\d.]+)", path):
        here = np.array([float(x), float(y)])
        if command == "L" and last is not None:
            points.extend(last + (here - last) * f for f in np.linspace(0, 1, 20))
        points.append(here)
        last = here
    return np.array(points)


@pytest.mark.parametrize(("process", "controller", "valve"), [
    (TransferFunction.fopdt(0.4346, 27.58, 6.0), PIDController.ideal(10.0, 10.0),
     ChoudhuryValve(4.0, 2.0)),  # thesis Table 5.1
    # the demo's FIC-101 as identified (QA: its cycle's label sat under G Gc)
    (TransferFunction.fopdt(1.074, 6.4, 3.0), PIDController.ideal(0.5, 8.0),
     KanoValve(4.0, 2.38)),
])
def test_the_limit_cycle_label_crosses_no_curve(process, controller, valve):
    prediction = predict_limit_cycles(process, controller, valve)
    assert prediction.limit_cycles
    curves = nyquist_curves(process, controller, valve, limit_cycle=prediction.stable_cycles[0])
    svg = plots.render_svg(plots.nyquist_figure(curves, prediction=prediction, title="nyquist"))
    root = parse(svg)
    (panel,) = panels(root)
    drawn_points = np.concatenate([pixel_points(p.get("d")) for p in panel.iter(f"{SVG}path")
                                   if p.get("class") == "series"])
    for text in panel.iter(f"{SVG}text"):
        if "cycle" not in (text.text or ""):
            continue
        x, baseline = float(text.get("x")), float(text.get("y"))
        width = len(text.text) * 11 * plots.CHAR_WIDTH["normal"]
        x0 = x if text.get("text-anchor") == "start" else x - width
        inside = ((drawn_points[:, 0] >= x0) & (drawn_points[:, 0] <= x0 + width)
                  & (drawn_points[:, 1] >= baseline - 9) & (drawn_points[:, 1] <= baseline))
        assert not inside.any(), (text.text, drawn_points[inside][:3])


def test_history_draws_only_the_runs_that_have_an_estimate():
    t = T0 + 60.0 * np.arange(6)
    s = np.array([np.nan, np.nan, 3.8, 4.1, 4.0, np.nan])
    root = parse(plots.render_svg(plots.history_figure(
        t, np.array([100, 90, 20, 18, 16, 100.0]), s, s / 2, title="history")))
    health, estimate = panels(root)
    assert series_path(health, "health").count("M") == 6
    x, y = drawn(estimate, "S")
    np.testing.assert_allclose(y, s[np.isfinite(s)], atol=resolution(estimate, "y"))
    np.testing.assert_allclose(x, t[np.isfinite(s)], atol=resolution(estimate, "x"))


def test_bad_input_is_refused_with_the_reason():
    t = np.arange(10.0)
    with pytest.raises(ValueError, match=r"unknown signals \['flow'\]"):
        plots.trend_figure({"flow": (t, t)}, title="x")
    with pytest.raises(ValueError, match=r"op and pv differ in shape, \(10,\) and \(9,\)"):
        plots.signature_figure(t, t[:9], title="x")
    with pytest.raises(ValueError, match="neither op nor pv"):
        plots.spectrum_figure(None, None, 1.0, title="x")


# ---------------------------------------------------------------------------- PNG


def decode_png(data: bytes) -> np.ndarray:
    """RGBA pixels of an 8-bit, non-interlaced RGBA PNG (the five row filters of RFC 2083)."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat = 8, b""
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos: pos + 4])
        kind, body = data[pos + 4: pos + 8], data[pos + 8: pos + 8 + length]
        if kind == b"IHDR":
            width, height, depth, colour, _, _, interlace = struct.unpack(">IIBBBBB", body)
            assert (depth, colour, interlace) == (8, 6, 0)
        elif kind == b"IDAT":
            idat += body
        pos += 12 + length
    raw = zlib.decompress(idat)
    stride = 4 * width
    image = np.zeros((height, stride), dtype=np.int64)
    previous = np.zeros(stride, dtype=np.int64)
    for row in range(height):
        line = raw[row * (stride + 1): (row + 1) * (stride + 1)]
        kind, scan = line[0], np.frombuffer(line[1:], dtype=np.uint8).astype(np.int64)
        if kind == 0:
            out = scan
        elif kind == 1:
            out = np.cumsum(scan.reshape(-1, 4), axis=0).ravel() % 256
        elif kind == 2:
            out = (scan + previous) % 256
        else:
            values, up = scan.tolist(), previous.tolist()
            out_list = [0] * stride
            for i in range(stride):
                a = out_list[i - 4] if i >= 4 else 0
                b, c = up[i], up[i - 4] if i >= 4 else 0
                if kind == 3:
                    predicted = (a + b) // 2
                else:
                    p = a + b - c
                    pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                    predicted = a if pa <= pb and pa <= pc else b if pb <= pc else c
                out_list[i] = (values[i] + predicted) % 256
            out = np.array(out_list, dtype=np.int64)
        image[row] = previous = out
    return image.reshape(height, width, 4)


def test_png_is_the_svg_rasterised():
    op, pv = quadrature_cycle()
    figure = plots.signature_figure(op, pv, title="s")  # no ellipse over the dots
    root = parse(plots.render_svg(figure))
    (panel,) = panels(root)
    zoom = 0.5
    image = decode_png(plots.render_png(figure, zoom=zoom))
    view_width, view_height = (float(v) for v in root.get("viewBox").split()[2:])
    assert image.shape[:2] == (round(view_height * zoom), round(view_width * zoom))
    r, g, b = (image[..., i] for i in range(3))
    blue = (b > r + 80) & (b > g + 30)  # the PV dots, #0072B2
    rows, cols = np.nonzero(blue)
    assert rows.size > 100
    dots_x, _ = drawn(panel, "pv")
    left, top = float(panel.get("data-left")), float(panel.get("data-top"))
    width, height = float(panel.get("data-width")), float(panel.get("data-height"))
    box = np.array([left, left + width, top, top + height])
    inside = ((cols / zoom >= box[0]) & (cols / zoom <= box[1])
              & (rows / zoom >= box[2]) & (rows / zoom <= box[3]))
    # Blue outside the plot box is the legend swatch only; inside, the dots' extent.
    assert inside.sum() > 0.9 * rows.size
    px = left + width * (dots_x - float(panel.get("data-x-min"))) / (
        float(panel.get("data-x-max")) - float(panel.get("data-x-min")))
    assert cols[inside].min() / zoom == pytest.approx(px.min(), abs=4)
    assert cols[inside].max() / zoom == pytest.approx(px.max(), abs=4)
