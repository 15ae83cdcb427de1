"""KPIs in the service: stored with every analysis run, their history, the bad-actor score.

A real store (SQLite and PostgreSQL, ``tests/service/conftest.py``), real
ingest and the real scheduler for the stored KPIs; a loop whose valve
sticks more day by day, analysed by :func:`service.analysis.analyse_window`
and stored run by run, for the history and the ranking.
"""

import csv
import dataclasses
import io
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from fastapi.testclient import TestClient
from pypdf import PdfReader
from sqlalchemy import event, null, update

from analytics.kpi import oscillation_index
from analytics.synthetic_cases import synthetic_library, window_start
from service.analysis import analyse_window
from service.api.routes.loops import KpiHistoryPublic
from service.cli import main
from service.config import PlantConfig, Settings
from service.server import build_service
from service.store.models import AnalysisRun, Ticket
from tests.service.test_api import ADMIN, T0, key, simulated_batch

DAY = 86400.0


def plant() -> PlantConfig:
    """The two loops of ``test_api``; FIC-1 with a process model (dead time 3 s) and PV
    limits, FIC-2 with neither."""
    loop = {"ts": 1.0, "ranges": {"op": [0, 100], "pv": [0, 100]},
            "process_type": "self-regulating", "controller": {"Kc": 0.5, "Ti": 8}}
    return PlantConfig.model_validate({
        "units": [{"id": "u1", "name": "Unit 1"}],
        "loops": [
            {**loop, "id": "FIC-1", "unit": "u1", "valve_asset": "FV-1", "importance": "high",
             "process_model": {"type": "fopdt", "K": 1.0, "tau": 10.0, "theta": 3.0},
             "pv_limits": [20, 80],
             "tags": {"op": "FIC-1.OP", "pv": "FIC-1.PV", "sp": "FIC-1.SP"}},
            {**loop, "id": "FIC-2", "unit": "u1", "valve_asset": "FV-2",
             "tags": {"op": "FIC-2.OP", "pv": "FIC-2.PV", "sp": "FIC-2.SP"}},
        ],
    })


class Clock:
    def __init__(self, now: float) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clock():
    return Clock(T0)


@pytest.fixture
def service(store, clock):
    settings = Settings(database_url=store.url, api_key=ADMIN, window_s=3600,
                        buffer_horizon_s=7200, ticket_confirmations=2)
    svc = build_service(settings, plant(), executor=ThreadPoolExecutor(1), clock=clock)
    yield svc
    svc.executor.shutdown()
    svc.state.store.close()


@pytest.fixture
def client(service):
    return TestClient(service.app)


def test_every_run_stores_its_kpis_and_the_history_returns_them(service, client):
    historian, viewer = key(client, "historian"), key(client, "viewer")
    assert client.post("/api/v1/ingest", json=simulated_batch(7200),
                       headers=historian).status_code == 200
    service.scheduler.run_once(T0 - 3600)
    service.scheduler.run_once(T0)

    with service.state.store.session() as session:
        stored = {r.loop_id: r.result for r in session.query(AnalysisRun)
                  .filter(AnalysisRun.started_at == T0)}
    sticky, healthy = stored["FIC-1"]["kpis"], stored["FIC-2"]["kpis"]
    # The oscillation index is the one of the run's own oscillation result.
    osc = stored["FIC-1"]["oscillation"]
    assert osc["detected"] is True
    assert sticky["oscillation_index"] == oscillation_index(True, osc["regularity"]) > 0
    # Dead time 3 s at 1 s: d = 3 + 1 samples with the hold; FIC-2 has none configured.
    assert sticky["dead_time_source"] == "configured" and sticky["harris"]["dead_time"] == 4
    assert sticky["dead_time_note"] == "configured" and sticky["dead_time_s"] == 3.0
    assert 0 < sticky["harris"]["ratio"] <= 1.0
    # FIC-2's set point holds still in the window and it is never in manual: under
    # feedback alone its dead time cannot be identified (analytics.kpi.identify_dead_time).
    assert healthy["harris"] is None and healthy["dead_time_source"] == "unknown"
    assert healthy["dead_time_note"].startswith("unknown: no set-point moves beyond noise")
    assert any("dead time unknown" in note for note in healthy["notes"])
    assert sticky["error"]["within_limits"] is not None
    assert healthy["error"]["within_limits"] is None
    assert sticky["samples"] == 3600 and sticky["travel_per_day"] > healthy["travel_per_day"]

    history = client.get("/api/v1/loops/FIC-1/kpis", headers=viewer,
                         params={"since": T0 - 2 * 3600, "until": T0})
    assert history.status_code == 200, history.text
    body = history.json()
    assert body["count"] == 2 and body["loop_id"] == "FIC-1"
    assert [p["started_at"] for p in body["data"]] == [T0 - 3600, T0]  # oldest first
    assert body["data"][-1]["kpis"] == sticky
    only_last = client.get("/api/v1/loops/FIC-1/kpis", headers=viewer,
                           params={"since": T0 - 60, "until": T0}).json()
    assert only_last["count"] == 1
    assert client.get("/api/v1/loops/FIC-1/kpis", headers=viewer).json()["count"] == 2


def test_a_loop_without_a_dead_time_has_it_from_its_set_point_steps(service, client):
    """FIC-2 (no process model) with a set point stepped by 5 % every 150 s: the run's KPIs
    take the dead time from the steps, the simulated one (2 s of the process, 1.2 e^{-2 s} /
    (8 s + 1), plus the hold's sample), say so, and the history returns it.  (Steps of
    5 % every 300 s were too weak for this sluggish first response, 12 % of the gain in the
    first sample, in one simulated hour of the two tried: 'unknown', 2 to 4 samples fitting
    alike; weak excitation is tested in tests/analytics/test_kpi.py.)"""
    case = {c.name: c for c in synthetic_library(3600)}["flow-noise-ts1"]
    first = window_start(3600, 1.0)
    loop = service.state.registry.plant.loops[1].model_dump(mode="json")
    assert loop["id"] == "FIC-2" and loop["process_model"] is None
    steps = tuple((first + 150 * (k + 1), 50.0 + 2.5 * (-1) ** k) for k in range(24))
    sim = dataclasses.replace(case, setpoint=((0.0, 50.0), *steps)).simulate()
    kpis = analyse_window(loop, 1.0, T0 - 3600 + 1 + np.arange(3600.0), {
        "op": sim.op[0], "pv": sim.pv[0], "sp": sim.sp[0], "mv": None})["kpis"]
    assert kpis["dead_time_source"] == "identified"
    assert kpis["dead_time_note"] == "identified from set-point steps"
    assert kpis["dead_time_samples"] == int(case.process.delay / case.ts) + 1 == 3
    assert kpis["harris"]["dead_time"] == 3 and 0 < kpis["harris"]["ratio"] <= 1
    with service.state.store.session() as session:
        session.add(AnalysisRun(loop_id="FIC-2", started_at=T0, finished_at=T0,
                                window_start=T0 - 3600, window_end=T0, status="ok",
                                result={"kpis": kpis}, kpis=kpis, round_end=T0))
    body = client.get("/api/v1/loops/FIC-2/kpis", headers=key(client, "viewer"),
                      params={"since": T0 - 60, "until": T0}).json()
    assert body["data"][0]["kpis"] == kpis


def test_the_kpi_history_reads_the_kpis_column_not_the_whole_diagnosis(service, client):
    """The history route reads each run's ``kpis`` (about 0.5 kB), never its ``result``
    (the ~9 kB diagnosis that PostgreSQL would decompress and parse for every run)."""
    historian, viewer = key(client, "historian"), key(client, "viewer")
    assert client.post("/api/v1/ingest", json=simulated_batch(7200),
                       headers=historian).status_code == 200
    service.scheduler.run_once(T0 - 3600)
    service.scheduler.run_once(T0)
    statements: list[str] = []

    def note(_conn, _cursor, statement, *_args) -> None:
        statements.append(statement)

    engine = service.state.store.engine
    event.listen(engine, "before_cursor_execute", note)
    try:
        body = client.get("/api/v1/loops/FIC-1/kpis", headers=viewer,
                          params={"since": T0 - 2 * 3600, "until": T0}).json()
    finally:
        event.remove(engine, "before_cursor_execute", note)
    assert [s for s in statements if "analysis_runs" in s]  # the route did read the runs
    assert not [s for s in statements if "analysis_runs.result" in s]
    with service.state.store.session() as session:
        stored = [r.result["kpis"] for r in session.query(AnalysisRun)
                  .filter(AnalysisRun.loop_id == "FIC-1").order_by(AnalysisRun.started_at)]
    assert [p["kpis"] for p in body["data"]] == stored and len(stored) == 2


def test_the_kpi_history_answers_what_its_response_model_would(service, client):
    """The route writes the stored KPIs' JSON text into its answer instead of validating
    and serialising models: the answer is KpiHistoryPublic's own JSON of it -- for runs
    without KPIs (SQL NULL or JSON null), stored by older versions with fewer or other
    keys, with small and whole numbers, a missing health and window."""
    stored = [
        None, {"i": 1, "notes": ["a \"quoted\" note", "é"]},
        {"harris": {"ratio": 1e-07, "dead_time": 3}, "dead_time_s": 2.0, "travel_per_day": 12,
         "setpoint_responses": [{"step": -5.0, "settling_time_s": None}], "error": None},
        {"harris": None, "dead_time_note": "unknown: no SP or no PV"},
    ]
    with service.state.store.session() as session:
        for i, kpis in enumerate(stored):
            session.add(AnalysisRun(loop_id="FIC-1", started_at=T0 - 60.0 * i - 0.125,
                                    status="ok", health=None if i == 1 else 50.0 + i / 3,
                                    window_start=None if i == 2 else T0 - 3600.0 * (i + 1),
                                    window_end=T0 - 60.0 * i, result={"kpis": kpis},
                                    kpis=kpis, round_end=T0 - 60.0 * i))
        session.add(AnalysisRun(loop_id="FIC-1", started_at=T0 - 1000.0, status="ok",
                                health=1.0, result={}, round_end=T0 - 1000.0))
        session.flush()
        session.execute(update(AnalysisRun).where(AnalysisRun.started_at == T0 - 1000.0)
                        .values(kpis=null()))  # as migration 0007 left a run without KPIs
    answer = client.get("/api/v1/loops/FIC-1/kpis", headers=key(client, "viewer"),
                        params={"since": T0 - 3000.5})
    assert answer.status_code == 200 and answer.headers["content-type"] == "application/json"
    body = answer.json()
    assert body["count"] == body["total"] == 5 and body["since"] == T0 - 3000.5
    assert [p["kpis"] for p in body["data"]] == [None, *reversed(stored)]
    assert KpiHistoryPublic.model_validate(body).model_dump(mode="json",
                                                            exclude_unset=True) == body

@pytest.mark.parametrize("limit", [1, 7, 40, 1000])
def test_the_thinned_history_is_every_kth_run_back_from_the_newest(service, client, limit):
    """Runs written in shuffled order (ids unrelated to time; some started at the same
    second, ordered by id), failed runs and runs outside the range among them: the
    history is every k-th ok run in the range counting back from the newest,
    k = ceil(total / limit), computed here from the runs themselves."""
    rng = np.random.default_rng(limit)
    started = T0 - 10.0 * rng.permutation(np.repeat(np.arange(120), 2)[:230])
    with service.state.store.session() as session:
        for i, t in enumerate(started):
            session.add(AnalysisRun(loop_id="FIC-1", started_at=float(t),
                                    status="failed" if i % 9 == 4 else "ok",
                                    result={"kpis": {"i": i}}, round_end=T0 + i))
    with service.state.store.session() as session:
        ok = sorted(((r.started_at, r.id) for r in session.query(AnalysisRun).filter(
            AnalysisRun.loop_id == "FIC-1", AnalysisRun.status == "ok",
            AnalysisRun.started_at >= T0 - 1000.0)), reverse=True)
    step = -(-len(ok) // limit)
    body = client.get("/api/v1/loops/FIC-1/kpis", headers=key(client, "viewer"),
                      params={"since": T0 - 1000.0, "limit": limit}).json()
    assert body["total"] == len(ok) > 150
    assert [p["run_id"] for p in body["data"]] == [i for _, i in reversed(ok[::step])]

def test_kpi_history_refusals(client):
    viewer, historian = key(client, "viewer"), key(client, "historian")
    url = "/api/v1/loops/FIC-1/kpis"
    missing = client.get("/api/v1/loops/FIC-9/kpis", headers=viewer)
    assert (missing.status_code, missing.json()) == (404, {"detail": "Loop not found"})
    backwards = client.get(url, headers=viewer, params={"since": T0, "until": T0 - 1})
    assert (backwards.status_code, backwards.json()) == (
        422, {"detail": "until must be after since"})
    assert client.get(url, headers=viewer, params={"limit": 0}).status_code == 422
    assert client.get(url, headers=viewer, params={"limit": 10_001}).status_code == 422
    assert client.get(url, headers=viewer, params={"since": -1}).status_code == 422
    assert client.get(url, headers=historian).status_code == 403
    assert client.get(url).status_code == 401
    assert client.get(url, headers=viewer).json() == {
        "loop_id": "FIC-1", "since": T0 - 30 * DAY, "until": T0, "data": [], "count": 0,
        "total": 0}


def degrading_days(service, clock) -> None:
    """Seven days, one analysed hour a day: FIC-2's valve sticks more from day 4
    (Kano S = 2, 4, 8 on days 4-6 and 8 again on day 7); FIC-1 stays healthy."""
    cases = {c.name: c for c in synthetic_library(3600)}
    days = {"FIC-1": ["flow-noise-ts1"] * 7,
            "FIC-2": ["flow-noise-ts1"] * 3 + ["flow-kano-S2-J1-ts1", "flow-kano-S4-J2-ts1",
                                               "flow-kano-S8-J4-ts1", "flow-kano-S8-J4-ts1"]}
    loops = {loop.id: loop.model_dump(mode="json") for loop in service.state.registry.plant.loops}
    start = T0 - 7 * DAY
    for day in range(7):
        end = start + (day + 1) * DAY
        with service.state.store.session() as session:
            for loop_id, names in days.items():
                sim = cases[names[day]].simulate()
                t = end - 3600 + 1 + np.arange(3600.0)
                result = analyse_window(loops[loop_id], 1.0, t, {
                    "op": sim.op[0], "pv": sim.pv[0], "sp": sim.sp[0], "mv": None})
                session.add(AnalysisRun(
                    loop_id=loop_id, started_at=end, finished_at=end, window_start=end - 3600,
                    window_end=end, status="ok", usable=result["quality"]["usable"],
                    oscillating=result["oscillation"]["detected"], health=result["health"],
                    verdict=result["stiction"]["verdict"], result=result, round_end=end))
    clock.now = start + 7 * DAY


def test_a_degrading_loop_shows_its_trend_and_climbs_the_ranking(service, client, clock):
    viewer = key(client, "viewer")
    degrading_days(service, clock)
    history = client.get("/api/v1/loops/FIC-2/kpis", headers=viewer,
                         params={"since": clock.now - 7 * DAY}).json()["data"]
    assert len(history) == 7
    index = [p["kpis"]["oscillation_index"] for p in history]
    assert index[:3] == [0.0, 0.0, 0.0] and min(index[-3:]) > 0.3  # the valve's cycle shows
    travel = [p["kpis"]["travel_per_day"] for p in history]
    assert min(travel[-3:]) > max(travel[:3])  # and the valve travels more

    # Over the first three days both loops are healthy: FIC-1 ranks first by importance
    # and health; over the week FIC-2 is the bad actor, and says why.
    clock.now -= 4 * DAY
    early = client.get("/api/v1/plant/bad-actors", headers=viewer,
                       params={"period": "3d"}).json()
    assert [r["score"] for r in early["data"]] == [0.0, 0.0]
    week_end = clock.now + 4 * DAY
    clock.now = week_end
    week = client.get("/api/v1/plant/bad-actors", headers=viewer,
                      params={"period": "7d"}).json()
    assert week["period"] == "7d" and week["since"] == week_end - 7 * DAY
    first = week["data"][0]
    assert first["id"] == "FIC-2" and first["score"] > 0
    assert first["runs"] == 7 and 3 <= first["bad_runs"] <= 4
    assert first["bad_share"] == first["bad_runs"] / 7
    assert first["score"] == pytest.approx(100 * first["severity"] * 1.0 * first["bad_share"])
    assert first["why"].startswith(f"bad in {first['bad_runs']} of 7 runs")
    assert "importance medium (x1)" in first["why"]
    # The existing keys stay.
    assert {"id", "health", "oscillating", "verdict", "active_alarms"} <= first.keys()
    assert week["data"][1]["id"] == "FIC-1" and week["data"][1]["score"] == 0.0
    # Over the last day only, FIC-2 is bad in its only run.
    day = client.get("/api/v1/plant/bad-actors", headers=viewer,
                     params={"period": "1d"}).json()["data"][0]
    assert (day["id"], day["runs"], day["bad_share"]) == ("FIC-2", 1, 1.0)


def test_bad_actor_period_is_bounded(client):
    viewer = key(client, "viewer")
    assert client.get("/api/v1/plant/bad-actors", headers=viewer,
                      params={"period": "93d"}).json() == {
        "detail": "period must be at most 92 days"}
    assert client.get("/api/v1/plant/bad-actors", headers=viewer,
                      params={"period": "7w"}).status_code == 422


def test_bad_actor_report_csv(service, client, clock):
    viewer = key(client, "viewer")
    degrading_days(service, clock)
    open_ticket(service, clock)
    response = client.get("/api/v1/reports/bad-actors", headers=viewer,
                          params={"period": "7d", "format": "csv"})
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "text/csv; charset=utf-8"
    assert 'filename="bad-actors-7d.csv"' in response.headers["content-disposition"]
    rows = list(csv.DictReader(io.StringIO(response.text)))
    assert [r["loop"] for r in rows] == ["FIC-2", "FIC-1"]
    ranking = client.get("/api/v1/plant/bad-actors", headers=viewer,
                         params={"period": "7d"}).json()["data"]
    assert float(rows[0]["score"]) == pytest.approx(ranking[0]["score"], rel=1e-3)
    assert rows[0]["why"] == ranking[0]["why"] and rows[0]["rank"] == "1"
    assert rows[0]["open_tickets"].endswith(" FV-2") and rows[1]["open_tickets"] == ""
    latest = client.get("/api/v1/loops/FIC-2/kpis", headers=viewer).json()["data"][-1]["kpis"]
    assert float(rows[0]["oscillation_index"]) == pytest.approx(latest["oscillation_index"],
                                                                rel=1e-3)
    assert float(rows[0]["travel_per_day"]) == pytest.approx(latest["travel_per_day"],
                                                             rel=1e-3)
    assert rows[1]["harris_ratio"] != "" and rows[0]["harris_ratio"] == ""  # FIC-1 has theta
    assert rows[1]["harris_dead_time"] == "configured"
    assert rows[0]["harris_dead_time"] == latest["dead_time_note"]
    assert rows[0]["harris_dead_time"].startswith("unknown: ")
    refused = client.get("/api/v1/reports/bad-actors", headers=viewer, params={"format": "xls"})
    assert refused.status_code == 422 and refused.json()["detail"][0]["loc"][-1] == "format"


def open_ticket(service, clock) -> None:
    with service.state.store.session() as session:  # an open ticket on FIC-2's valve
        session.add(Ticket(valve_asset="FV-2", loop_id="FIC-2", state="open", priority=2,
                           title="FV-2 sticks", description="", location=None,
                           malfunction_start=clock.now, evidence={}, created_at=clock.now,
                           updated_at=clock.now))


def test_bad_actor_report_pdf_reads_back_as_the_ranking(service, client, clock):
    """The PDF's text, read back with pypdf, holds the ranking in order with each loop's
    score, KPIs, why, diagnosis and open tickets; FIC-2's sparkline is drawn (a path of
    one point per day of the week)."""
    viewer = key(client, "viewer")
    degrading_days(service, clock)
    open_ticket(service, clock)
    response = client.get("/api/v1/reports/bad-actors", headers=viewer,
                          params={"period": "7d", "format": "pdf"})
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "application/pdf"
    assert 'filename="bad-actors-7d.pdf"' in response.headers["content-disposition"]
    document = PdfReader(io.BytesIO(response.content))
    text = "\n".join(page.extract_text() for page in document.pages)
    ranking = client.get("/api/v1/plant/bad-actors", headers=viewer,
                         params={"period": "7d"}).json()["data"]
    latest = client.get("/api/v1/loops/FIC-2/kpis", headers=viewer).json()["data"][-1]["kpis"]
    assert "Bad-actor report: the worst loops over 7d" in text
    assert text.index("FIC-2") < text.index("FIC-1")
    assert "1 FIC-2" in " ".join(text.split())
    assert f"{ranking[0]['score']:.1f}" in text and ranking[0]["why"] in " ".join(text.split())
    assert f"{latest['oscillation_index']:.2g}" in text
    assert f"{latest['travel_per_day']:.4g}" in text
    fic2 = text.split("FIC-1")[0]
    assert ranking[0]["verdict"] in fic2 and "oscillating" in fic2
    assert "FV-2" in fic2  # FIC-2's open ticket, on its row
    content = document.pages[0].get_contents().get_data().decode("latin-1")
    assert content.count(" l\n") >= 6  # the week's seven points joined by six lines


def test_loopwatch_report_writes_the_same_report_from_the_store(service, client, clock, store,
                                                              tmp_path, monkeypatch, capsys):
    """``loopwatch report`` reads the store the service writes (its URL from the
    environment) and writes the route's CSV, and a PDF whose text holds the ranking."""
    viewer = key(client, "viewer")
    degrading_days(service, clock)
    open_ticket(service, clock)
    monkeypatch.setenv("LOOPWATCH_DATABASE_URL", store.url)
    monkeypatch.setenv("LOOPWATCH_WINDOW_S", "3600")
    until = ["--until", str(clock.now)]
    assert main(["report", "--since", "7d", "--out", str(tmp_path / "w.csv"), *until]) == 0
    route = client.get("/api/v1/reports/bad-actors", headers=viewer,
                       params={"period": "7d", "limit": 20}).text
    assert (tmp_path / "w.csv").read_text() == route
    assert main(["report", "--since", "7d", "--out", str(tmp_path / "w.pdf"), *until]) == 0
    text = PdfReader(tmp_path / "w.pdf").pages[0].extract_text()
    assert text.index("FIC-2") < text.index("FIC-1") and "FV-2" in text
    assert "w.pdf: 2 loops over 7d" in capsys.readouterr().out
    for argv, message in ((["--out", "w.txt"], "must end in .pdf or .csv"),
                          (["--since", "93d", "--out", "w.pdf"], "at most 92 days"),
                          (["--since", "7w", "--out", "w.pdf"], "a period such as 7d")):
        assert main(["report", *argv]) == 2
        assert message in capsys.readouterr().err


def test_runs_a_minute_apart_count_once_per_window(service, client):
    """Sixty runs in the last hour are one observation; one more an hour earlier is another."""
    viewer = key(client, "viewer")
    bad = {"oscillation_index": 0.9}
    with service.state.store.session() as session:
        for i in range(60):
            end = T0 - 60.0 * i
            session.add(AnalysisRun(loop_id="FIC-2", started_at=end, window_start=end - 3600,
                                    window_end=end, status="ok", health=100.0,
                                    result={"kpis": bad}, round_end=end))
        session.add(AnalysisRun(loop_id="FIC-2", started_at=T0 - 5400, status="ok",
                                health=100.0, result={"kpis": {"oscillation_index": 0.0}},
                                round_end=T0 - 5400))
    first = client.get("/api/v1/plant/bad-actors", headers=viewer,
                       params={"period": "1d"}).json()["data"][0]
    assert (first["id"], first["runs"], first["bad_runs"]) == ("FIC-2", 2, 1)
    assert first["score"] == pytest.approx(100 * 0.9 * 1.0 * 0.5)


def test_a_long_history_is_thinned_evenly_to_the_limit(service, client):
    viewer = key(client, "viewer")
    with service.state.store.session() as session:
        for i in range(100):
            end = T0 - 60.0 * i
            session.add(AnalysisRun(loop_id="FIC-1", started_at=end, status="ok",
                                    health=float(i), result={"kpis": {"i": i}}, round_end=end))
    body = client.get("/api/v1/loops/FIC-1/kpis", headers=viewer,
                      params={"since": T0 - 6000, "limit": 10}).json()
    assert (body["count"], body["total"]) == (10, 100)
    started = [p["started_at"] for p in body["data"]]
    assert started[-1] == T0 and started == sorted(started)
    assert [p["kpis"]["i"] for p in body["data"]] == [90, 80, 70, 60, 50, 40, 30, 20, 10, 0]
    body = client.get("/api/v1/loops/FIC-1/kpis", headers=viewer,
                      params={"since": T0 - 6000, "limit": 30}).json()  # every 4th run
    assert (body["count"], body["total"]) == (25, 100)
    assert body["data"][0]["kpis"]["i"] == 96
