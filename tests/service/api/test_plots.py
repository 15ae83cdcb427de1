"""The plot routes (``service/api/routes/plots.py``) on SQLite and PostgreSQL.

The drawn coordinates are read back out of the SVG (the helpers of
:mod:`tests.service.test_plots`) and compared with what the analysis stored and
what the data say: the latest estimate replayed on the window, the ellipse and
period the analysis measured, the samples of ``/data``, the model check's overlay.
"""

from __future__ import annotations

import struct
import xml.etree.ElementTree as ET
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from analytics.lti import TransferFunction
from analytics.quantification import VALVE_MODELS
from analytics.replay import (
    MODEL_CYCLES_KEPT,
    MODEL_LEAD_PERIODS,
    MODEL_POINTS,
    StictionModelPath,
    stiction_model_path,
)
from analytics.stiction.signature import EllipseFit
from service import plots
from service.buffer import LoopBuffers
from service.config import PlantConfig, Settings
from service.server import build_service
from service.store.models import AnalysisRun
from tests.service.api.stored import store_run
from tests.service.test_api import ADMIN, T0, key, plant, simulated_batch
from tests.service.test_plots import HEADERS, SVG, drawn, marker, panels, parse, resolution


@pytest.fixture
def service(make_service):
    """The two-loop test plant; one stiction finding opens a ticket."""
    return make_service(ticket_confirmations=1)


@pytest.fixture
def analysed(service, client):
    """FIC-1 (sticky valve) and FIC-2 (healthy) ingested and analysed twice (the first
    analysis opens FV-1's ticket, the second updates it)."""
    assert client.post("/api/v1/ingest", json=simulated_batch(),
                       headers=HEADERS).status_code == 200
    for _ in range(2):
        service.scheduler.run_once(T0)
    return client


def get_plot(client, loop_id, kind, **params):
    return client.get(f"/api/v1/loops/{loop_id}/plots/{kind}", params=params, headers=HEADERS)


def test_every_kind_renders_as_svg_and_png(analysed):
    for kind in ("trend", "signature", "spectrum", "nyquist", "history"):
        svg = get_plot(analysed, "FIC-1", kind)
        assert svg.status_code == 200, (kind, svg.text)
        assert svg.headers["content-type"].startswith("image/svg+xml")
        assert parse(svg.text).get("data-kind") == kind
        png = get_plot(analysed, "FIC-1", kind, format="png")
        assert png.status_code == 200
        assert png.headers["content-type"] == "image/png"
        assert png.content[:8] == b"\x89PNG\r\n\x1a\n"
        width, _ = struct.unpack(">II", png.content[16:24])
        assert width == round(plots.PLOT_WIDTH * plots.PNG_ZOOM)


def test_the_nyquist_title_says_its_size_is_this_windows(analysed):
    """QA: the title showed the analysed window's S and J unlabelled, beside the valve's
    combined size on the same page."""
    q = analysed.get("/api/v1/loops/FIC-1/health",
                     headers=HEADERS).json()["diagnosis"]["quantification"]
    title = parse(get_plot(analysed, "FIC-1", "nyquist").text).find(
        "{http://www.w3.org/2000/svg}text").text
    assert title.endswith(f"Nyquist plot, identified model; this window: S {q['S']:.2f} %, "
                          f"J {q['J']:.2f} %"), title


def test_signature_draws_the_latest_estimate_replayed_on_the_window(analysed, service):
    diagnosis = analysed.get("/api/v1/loops/FIC-1/health", headers=HEADERS).json()["diagnosis"]
    estimate = diagnosis["quantification"]
    assert estimate["valve_model"] in ("he", "kano")
    signature, valve = panels(parse(get_plot(analysed, "FIC-1", "signature").text))
    window = service.state.buffers.window("FIC-1", 3600, T0)
    x, y = drawn(valve, "model_mv")

    def replay(stretch: slice) -> StictionModelPath:
        return stiction_model_path(
            window.op[stretch], window.pv[stretch], window.ts,
            valve=VALVE_MODELS[estimate["valve_model"]](estimate["S"], estimate["J"]),
            process=TransferFunction.fopdt(estimate["process"]["K"], estimate["process"]["tau"],
                                           estimate["process"]["theta"]),
            period_s=diagnosis["oscillation"]["analysed_period_s"], label="")

    path = replay(slice(None))
    kept = MODEL_CYCLES_KEPT * path.period  # the last cycles, every k-th beyond MODEL_POINTS
    last = slice(-kept, None, -(-kept // MODEL_POINTS))
    np.testing.assert_allclose(x, window.op[last], atol=resolution(valve, "x"))
    np.testing.assert_allclose(y, path.mv[last], atol=resolution(valve, "y"))
    # The analysis replays only the window's end, which the plot draws: the same path as
    # the whole window's replay there, its R2 that of the end's replay.
    stored = diagnosis["model_trace"]
    np.testing.assert_allclose(stored["mv"], path.mv[last], atol=5e-5)
    end_path = replay(slice(-(MODEL_CYCLES_KEPT + MODEL_LEAD_PERIODS) * path.period, None))
    assert stored["r2"] == pytest.approx(end_path.r2, rel=1e-9)
    assert path.r2 > 0.8 and end_path.r2 > 0.8  # the fit explains the measured signature
    assert f"R² {end_path.r2:.2f}" in signature.findtext(f".//{SVG}text[last()]")
    assert f"S = {estimate['S']:.2f} %" in ET.tostring(valve, encoding="unicode")


def test_plots_read_the_window_from_the_store_when_the_buffer_lacks_it(
    analysed, service, monkeypatch
):
    """An API replica of the scale-out has empty rolling buffers: the same plots, from the
    store."""
    from_buffer = {kind: get_plot(analysed, "FIC-1", kind).text
                   for kind in ("signature", "spectrum")}
    monkeypatch.setattr(service.state, "buffers", LoopBuffers(plant(), horizon_s=7200))
    assert not np.isfinite(service.state.buffers.window("FIC-1", 3600, T0).pv).any()
    for kind, svg in from_buffer.items():
        assert get_plot(analysed, "FIC-1", kind).text == svg


def test_model_check_plot_draws_the_answer_of_the_model_check(analysed):
    check = analysed.post("/api/v1/loops/FIC-1/model-check", headers=HEADERS)
    assert check.status_code == 200, check.text
    answer = check.json()
    body = {"overlay": answer["overlay"], "cause": answer["cause"]}
    response = analysed.post("/api/v1/loops/FIC-1/plots/model-check", json=body,
                             headers=HEADERS)
    assert response.status_code == 200, response.text
    root = parse(response.text)
    assert root.get("data-kind") == "model-check"
    effect = answer["cause"]["effect"]
    assert (effect.replace("_", " ") if effect != "none" else "no effect found") \
        in root.get("aria-label")
    overlay, _ = panels(root)
    x, y = drawn(overlay, "pv_extended")
    scored = np.array(answer["overlay"]["scored"])
    np.testing.assert_allclose(x, np.array(answer["overlay"]["t"])[scored],
                               atol=resolution(overlay, "x"))
    np.testing.assert_allclose(y, np.array(answer["overlay"]["pv_extended"])[scored],
                               atol=resolution(overlay, "y"))
    png = analysed.post("/api/v1/loops/FIC-1/plots/model-check", json=body, headers=HEADERS,
                        params={"format": "png"})
    assert png.content[:8] == b"\x89PNG\r\n\x1a\n"
    body["overlay"]["pv"] = body["overlay"]["pv"][1:]
    bad = analysed.post("/api/v1/loops/FIC-1/plots/model-check", json=body, headers=HEADERS)
    assert bad.status_code == 422 and "differ in shape" in bad.json()["detail"]
    missing = analysed.post("/api/v1/loops/NOPE/plots/model-check", json=body, headers=HEADERS)
    assert missing.json() == {"detail": "Loop not found"}


def test_signature_and_spectrum_show_what_the_analysis_measured(analysed):
    diagnosis = analysed.get("/api/v1/loops/FIC-1/health", headers=HEADERS).json()["diagnosis"]
    signature = get_plot(analysed, "FIC-1", "signature").text
    apparent = diagnosis["apparent_stiction"]
    assert (f"apparent stiction {apparent['apparent_stiction']:.2f} % of OP span "
            f"(width ratio {apparent['width_ratio']:.2f}") in signature
    spectrum_panel, acf_panel = panels(parse(get_plot(analysed, "FIC-1", "spectrum").text))
    period = diagnosis["oscillation"]["analysed_period_s"]
    assert marker(spectrum_panel, "period")[0] == pytest.approx(period, rel=1e-3)
    assert marker(acf_panel, "period")[0] == pytest.approx(period, abs=resolution(acf_panel, "x"))
    periods, power = drawn(spectrum_panel, "pv")
    assert periods[np.argmax(power)] == pytest.approx(period, rel=0.1)


def test_signature_draws_the_ellipse_the_analysis_stored(analysed, service):
    """The OP-PV ellipse is the analysis's (issue 25), not fitted a second time; an
    analysis stored before the geometry was kept gets it fitted on the same window."""
    def store(apparent_stiction):
        with service.state.store.session() as session:
            run = session.scalars(select(AnalysisRun).where(AnalysisRun.loop_id == "FIC-1")
                                  .order_by(AnalysisRun.id.desc())).first()
            run.result = {**run.result, "apparent_stiction": apparent_stiction}
            session.commit()

    diagnosis = analysed.get("/api/v1/loops/FIC-1/health", headers=HEADERS).json()["diagnosis"]
    stored = diagnosis["apparent_stiction"]
    pv_panel, _ = panels(parse(get_plot(analysed, "FIC-1", "signature").text))
    x, y = drawn(pv_panel, "ellipse")
    ex, ey = plots.ellipse_points(EllipseFit.from_dict(stored))
    np.testing.assert_allclose(x, ex, atol=resolution(pv_panel, "x"))
    np.testing.assert_allclose(y, ey, atol=resolution(pv_panel, "y"))
    store({**stored, "centre": [stored["centre"][0] + 1.0, stored["centre"][1]]})
    moved, _ = panels(parse(get_plot(analysed, "FIC-1", "signature").text))
    np.testing.assert_allclose(drawn(moved, "ellipse")[0], ex + 1.0, atol=resolution(moved, "x"))
    store({k: v for k, v in stored.items() if k not in ("centre", "semi_axes", "angle")})
    refitted, _ = panels(parse(get_plot(analysed, "FIC-1", "signature").text))
    np.testing.assert_allclose(drawn(refitted, "ellipse")[0], ex, atol=resolution(pv_panel, "x"))
    np.testing.assert_allclose(drawn(refitted, "ellipse")[1], ey, atol=resolution(pv_panel, "y"))


def test_trend_draws_the_samples_of_the_data_endpoint(analysed):
    window = {"start": T0 - 600, "end": T0}
    data = analysed.get("/api/v1/loops/FIC-1/data", params=window, headers=HEADERS).json()
    pv = next(s for s in data["series"] if s["signal"] == "pv")
    upper, _ = panels(parse(get_plot(analysed, "FIC-1", "trend", **window).text))
    x, y = drawn(upper, "pv")
    np.testing.assert_allclose(x, pv["t"], atol=resolution(upper, "x"))
    np.testing.assert_allclose(y, pv["value"], atol=resolution(upper, "y"))


def test_the_plots_a_ticket_links_to_exist(analysed):
    ticket = analysed.get("/api/v1/tickets", headers=HEADERS).json()["data"][0]
    links = ticket["evidence"]["plots"]
    assert links
    for kind, url in links.items():
        response = analysed.get(url, headers=HEADERS)
        assert response.status_code == 200, (kind, response.text)


def test_plot_errors_say_what_is_missing(analysed):
    assert get_plot(analysed, "NOPE", "trend").json() == {"detail": "Loop not found"}
    assert get_plot(analysed, "FIC-1", "bode").status_code == 422
    assert get_plot(analysed, "FIC-1", "trend", format="gif").status_code == 422
    assert analysed.get("/api/v1/loops/FIC-1/plots/trend").status_code == 401
    healthy = get_plot(analysed, "FIC-2", "nyquist")
    assert healthy.status_code == 404
    assert "no stiction estimate" in healthy.json()["detail"]
    empty = get_plot(analysed, "FIC-1", "trend", start=T0 - 9000, end=T0 - 8000)
    assert empty.status_code == 404
    assert empty.json()["detail"].startswith("No samples of loop FIC-1 between")


def test_plots_before_any_analysis_answer_404_with_the_reason(client):
    for kind in ("signature", "spectrum", "nyquist", "history"):
        response = get_plot(client, "FIC-1", kind)
        assert response.status_code == 404
        assert response.json() == {"detail": "No analysis of loop FIC-1 yet"}


def test_the_trend_of_a_loop_with_a_mode_tag_draws_its_signals(store):
    """The demo's loops carry a mode tag (issue 24); the trend drew nothing but a 500
    ("unknown signals ['mode']")."""
    config = plant().model_dump()
    config["loops"][0]["tags"]["mode"] = "FIC-1.MODE"
    config["loops"][0]["mode_map"] = {8: "auto", 16: "manual"}
    settings = Settings(database_url=store.url, api_key=ADMIN, window_s=3600,
                        buffer_horizon_s=7200)
    svc = build_service(settings, PlantConfig.model_validate(config),
                        executor=ThreadPoolExecutor(1), clock=lambda: T0)
    client = TestClient(svc.app)
    mode = {"tag": "FIC-1.MODE", "items": [{"timestamp": T0 - 3000.0, "value": 8.0},
                                           {"timestamp": T0 - 600.0, "value": 16.0}]}
    batch = [*simulated_batch(), mode]
    assert client.post("/api/v1/ingest", json=batch, headers=HEADERS).status_code == 200
    response = get_plot(client, "FIC-1", "trend")
    assert response.status_code == 200, response.text
    assert "Controller output" in response.text
    svc.executor.shutdown()
    svc.state.store.close()


# ----------------------------------------------------------------------------- status codes
# Analyses written into the store (tests.service.api.stored): each refusal's exact detail.

WINDOW = (T0 - 3600.0, T0)


def refusal(client, loop_id, kind, headers=HEADERS, **params):
    answer = client.get(f"/api/v1/loops/{loop_id}/plots/{kind}", params=params,
                        headers=headers)
    return answer.status_code, answer.json()["detail"]


def test_keys_kinds_and_formats(client):
    assert refusal(client, "FIC-1", "trend", {}) == (401, "Missing API key (header X-API-Key)")
    assert refusal(client, "FIC-1", "trend", key(client, "historian")) == (
        403, "Role 'historian' may not read")
    assert refusal(client, "FIC-1", "bode") == (422, [{
        "loc": ["path", "kind"], "type": "literal_error",
        "msg": "Input should be 'trend', 'signature', 'spectrum', 'nyquist' or 'history'"}])
    assert refusal(client, "FIC-1", "trend", format="gif") == (422, [{
        "loc": ["query", "format"], "type": "literal_error",
        "msg": "Input should be 'svg' or 'png'"}])
    assert refusal(client, "FIC-1", "trend", start=T0 - 9000, end=T0 - 8000) == (
        404, f"No samples of loop FIC-1 between {T0 - 9000:.0f} and {T0 - 8000:.0f}")


@pytest.mark.parametrize("kind", ["signature", "spectrum"])
def test_the_window_of_the_analysis_must_still_be_there(client, kind):
    store_run(client, "FIC-1", "no_stiction", window=WINDOW)
    assert refusal(client, "FIC-1", kind) == (
        404, "Samples of the analysed window are no longer stored")
    assert client.post("/api/v1/ingest", json=simulated_batch(200),
                       headers=HEADERS).status_code == 200
    store_run(client, "FIC-1", "no_stiction", window=WINDOW,
              manual={"share": 1.0, "judged_from": None, "judged_to": None})
    assert refusal(client, "FIC-1", kind) == (
        404, "The loop was in manual over the whole analysed window")


def test_the_signature_needs_op_and_pv(client):
    body = {"ts": 1.0, "tags": {"op": "FIC-9.OP"}}
    assert client.put("/api/v1/loops/FIC-9", json=body, headers=HEADERS).status_code == 200
    op = {"tag": "FIC-9.OP", "items": [{"timestamp": T0 - k, "value": 50.0} for k in range(9)]}
    assert client.post("/api/v1/ingest", json=[op], headers=HEADERS).status_code == 200
    store_run(client, "FIC-9", "no_stiction", window=WINDOW)
    assert refusal(client, "FIC-9", "signature") == (
        404, "The valve signature needs both OP and PV tags")


@pytest.mark.parametrize(("estimate", "detail"), [
    (None, "the latest analysis has no stiction estimate (S, J) with an identified process "
           "model"),
    ({"S": 4.0, "J": 2.0, "process": {"K": -1.0, "tau": 10.0, "theta": 2.0,
                                      "integrating": False}},
     "the identified process gain -1 and the controller action 'reverse' make positive "
     "feedback"),
])
def test_the_nyquist_plot_needs_a_model(client, estimate, detail):
    store_run(client, "FIC-1", "stiction", estimate, window=WINDOW)
    assert refusal(client, "FIC-1", "nyquist") == (404, detail)


def test_the_model_check_plot_needs_an_overlay_of_equal_lengths(client):
    url = "/api/v1/loops/FIC-1/plots/model-check"
    empty = {"t": [], "pv": [], "pv_base": [], "pv_extended": [], "scored": []}
    body = {"overlay": empty, "cause": {"effect": "valve_stiction"}}
    answer = client.post(url, json=body, headers=HEADERS)
    assert (answer.status_code, answer.json()) == (422, {"detail": "The overlay has no samples"})
    body["overlay"] = {**empty, "t": [T0, T0 + 1], "pv": [1.0, 2.0], "pv_base": [1.0, 2.0],
                       "pv_extended": [1.0], "scored": [True, True]}
    answer = client.post(url, json=body, headers=HEADERS)
    assert (answer.status_code, answer.json()) == (422, {"detail": (
        "model_check_figure: t, pv, pv_base, pv_extended and scored differ in shape: "
        "[(1,), (2,)]")})
    answer = client.post("/api/v1/loops/NOPE/plots/model-check", json=body, headers=HEADERS)
    assert (answer.status_code, answer.json()) == (404, {"detail": "Loop not found"})


def test_a_model_check_that_finds_nothing_is_not_titled_extended_with_none(client):
    """The model check of a loop its model explains was titled "model check, extended with
    none"."""
    overlay = {"t": [T0, T0 + 1, T0 + 2], "pv": [1.0, 2.0, 1.5], "pv_base": [1.1, 1.9, 1.5],
               "pv_extended": [1.1, 1.9, 1.5], "scored": [False, True, True]}
    answer = client.post("/api/v1/loops/FIC-1/plots/model-check", headers=HEADERS,
                         json={"overlay": overlay, "cause": {"effect": "none"}})
    assert answer.status_code == 200, answer.text
    label = parse(answer.text).get("aria-label")
    assert "model check, no effect found" in label and "extended with none" not in label
    answer = client.post("/api/v1/loops/FIC-1/plots/model-check", headers=HEADERS,
                         json={"overlay": overlay, "cause": {"effect": "gain_mismatch"}})
    assert "model check, extended with gain mismatch" in parse(answer.text).get("aria-label")
