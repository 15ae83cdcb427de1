"""The REST API end to end on SQLite and PostgreSQL: ingest, analysis, alarms, tickets, keys.

A small plant of two simulated loops (one sticky valve, one healthy loop) is
pushed through ``POST /api/v1/ingest`` as a historian would, analysed by the
scheduler (in a thread pool: the process pool is exercised by the demo test)
and inspected through the API with keys of every role.
"""

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from analytics.synthetic_cases import synthetic_library
from service.buffer import LoopBuffers
from service.config import PlantConfig
from service.server import build_service
from service.store.models import AnalysisRun

ADMIN = "test-admin-key-0123456789"
T0 = 1_700_000_000.0  # window end used by the tests (UNIX s)


def plant() -> PlantConfig:
    loop = {"ts": 1.0, "ranges": {"op": [0, 100], "pv": [0, 100]},
            "process_type": "self-regulating", "controller": {"Kc": 0.5, "Ti": 8}}
    return PlantConfig.model_validate({
        "units": [{"id": "u1", "name": "Unit 1"}],
        "loops": [
            {**loop, "id": "FIC-1", "unit": "u1", "valve_asset": "FV-1", "importance": "high",
             "tags": {"op": "FIC-1.OP", "pv": "FIC-1.PV", "sp": "FIC-1.SP"}},
            {**loop, "id": "FIC-2", "unit": "u1", "valve_asset": "FV-2",
             "tags": {"op": "FIC-2.OP", "pv": "FIC-2.PV", "sp": "FIC-2.SP"}},
        ],
    })


def simulated_batch(samples: int = 3600) -> list[dict]:
    """One hour of FIC-1 (Kano valve S=4, J=2) and FIC-2 (healthy), ending at T0."""
    cases = {c.name: c for c in synthetic_library(samples)}
    batch = []
    for loop_id, case in (("FIC-1", "flow-kano-S4-J2-ts1"), ("FIC-2", "flow-noise-ts1")):
        result = cases[case].simulate()
        t = T0 - samples + 1 + np.arange(samples)
        for signal, values in (("OP", result.op[0]), ("PV", result.pv[0]), ("SP", result.sp[0])):
            batch.append({"tag": f"{loop_id}.{signal}",
                          "items": [{"timestamp": float(a), "value": float(b)}
                                    for a, b in zip(t, values, strict=True)]})
    return batch


def key(client, role):
    response = client.post("/api/v1/keys", json={"name": f"{role} key", "role": role},
                           headers={"X-API-Key": ADMIN})
    assert response.status_code == 201, response.text
    return {"X-API-Key": response.json()["key"]}


def test_missing_wrong_and_insufficient_keys(client):
    assert client.get("/healthz").status_code == 200
    assert client.get("/api/v1/loops").status_code == 401
    assert client.get("/api/v1/loops", headers={"X-API-Key": "nope"}).json() == {
        "detail": "Invalid or revoked API key"}
    viewer, historian = key(client, "viewer"), key(client, "historian")
    assert client.get("/api/v1/loops", headers=viewer).status_code == 200
    assert client.get("/api/v1/loops", headers=historian).status_code == 403
    assert client.post("/api/v1/ingest", json=[], headers=viewer).status_code == 403
    assert client.post("/api/v1/keys", json={"name": "x", "role": "admin"},
                       headers=viewer).status_code == 403


def test_keys_are_shown_once_and_revocation_locks_out(client):
    viewer = key(client, "viewer")
    listed = client.get("/api/v1/keys", headers={"X-API-Key": ADMIN}).json()
    assert listed["count"] == 2
    assert all("key" not in k and "key_hash" not in k for k in listed["data"])
    victim = next(k for k in listed["data"] if k["role"] == "viewer")
    assert viewer["X-API-Key"].startswith(f"lw_{victim['key_id']}_")
    assert client.delete(f"/api/v1/keys/{victim['id']}",
                         headers={"X-API-Key": ADMIN}).status_code == 200
    assert client.get("/api/v1/loops", headers=viewer).status_code == 401
    assert client.delete("/api/v1/keys/999", headers={"X-API-Key": ADMIN}).status_code == 404


def test_ingest_is_idempotent_and_reports_refusals(client):
    historian = key(client, "historian")
    batch = simulated_batch(200)
    first = client.post("/api/v1/ingest", json=batch, headers=historian)
    assert first.status_code == 200, first.text
    assert first.json()["stored"] == 6 * 200
    again = client.post("/api/v1/ingest", json=batch, headers=historian)
    assert again.status_code == 200
    assert again.json()["stored"] == 0 and again.json()["already_stored"] == 6 * 200
    mixed = [{"tag": "NOPE", "items": [{"timestamp": T0, "value": 1.0}]},
             {"tag": "FIC-1.OP", "items": [{"timestamp": T0 + 1, "value": 50.0}]}]
    partial = client.post("/api/v1/ingest", json=mixed, headers=historian)
    assert partial.status_code == 207
    assert partial.json()["refused"] == {"unknown_tag": 1}
    assert partial.json()["stored"] == 1
    # QA: a value sent as text ("NaN") is refused alone, with its tag and time stamp
    text = [{"tag": "FIC-1.OP", "items": [{"timestamp": T0 + 2, "value": 51.0},
                                          {"timestamp": T0 + 3, "value": "NaN"}]}]
    partial = client.post("/api/v1/ingest", json=text, headers=historian)
    assert partial.status_code == 207, partial.text
    answer = partial.json()
    assert (answer["stored"], answer["refused"]) == (1, {"bad_value": 1})
    assert answer["tags"][0]["tag"] == "FIC-1.OP"
    assert answer["tags"][0]["refused_items"] == [{"timestamp": T0 + 3, "reason": "bad_value"}]
    bad = client.post("/api/v1/ingest", json=[{"items": []}], headers=historian)
    assert bad.status_code == 422


def test_analysis_alarm_and_ticket_lifecycle(service, client):
    historian, viewer = key(client, "historian"), key(client, "viewer")
    operator, maintenance = key(client, "operator"), key(client, "maintenance")
    # two hours: tickets need stiction found on windows that do not overlap
    assert client.post("/api/v1/ingest", json=simulated_batch(7200),
                       headers=historian).status_code == 200
    first = service.scheduler.run_once(T0 - 3600)
    assert {r.loop_id: r.status for r in first} == {"FIC-1": "ok", "FIC-2": "ok"}
    loops = {x["id"]: x for x in client.get("/api/v1/loops", headers=viewer).json()["data"]}
    assert loops["FIC-1"]["oscillating"] is True
    assert loops["FIC-1"]["verdict"] == "stiction"
    assert loops["FIC-2"]["oscillating"] is False
    assert client.get("/api/v1/tickets", headers=viewer).json()["count"] == 0  # 1 of 2 runs

    second = service.scheduler.run_once(T0)
    ticket_id = next(r.ticket_id for r in second if r.loop_id == "FIC-1")
    assert ticket_id is not None
    ticket = client.get(f"/api/v1/tickets/{ticket_id}", headers=viewer).json()
    assert ticket["valve_asset"] == "FV-1" and ticket["state"] == "open"
    assert ticket["evidence"]["S"] is not None and ticket["evidence"]["period_s"] > 0
    assert ticket["evidence"]["pattern"] == "limit_cycle"
    assert "\nPattern: limit cycle.\n" in ticket["description"]
    assert client.get(f"/api/v1/tickets/{ticket_id}/cmms",
                      headers=viewer).json()["sap_pm"]["NOTIF_TYPE"] == "M2"
    bad_actors = client.get("/api/v1/plant/bad-actors", headers=viewer).json()["data"]
    assert bad_actors[0]["id"] == "FIC-1"

    alarms = client.get("/api/v1/alarms", headers=viewer).json()["data"]
    assert [(a["loop_id"], a["kind"], a["state"]) for a in alarms] == [
        ("FIC-1", "oscillation", "unacknowledged")]
    assert alarms[0]["message"].endswith("; valve: stiction (limit cycle)")
    alarm_id = alarms[0]["id"]
    url = f"/api/v1/alarms/{alarm_id}/acknowledge"
    assert client.post(url, json={}, headers=viewer).status_code == 403
    acked = client.post(url, headers=operator)  # no body: no note (issue 19)
    assert acked.status_code == 200 and acked.json()["state"] == "acknowledged"
    assert acked.json()["events"][-1]["actor"] == "operator key (operator)"
    again = client.post(url, json={}, headers=operator)
    assert again.status_code == 409
    assert client.post("/api/v1/alarms/999/acknowledge", json={},
                       headers=operator).status_code == 404

    patch = f"/api/v1/tickets/{ticket_id}"
    assert client.patch(patch, json={"state": "acknowledged"},
                        headers=operator).status_code == 403
    assert client.patch(patch, json={"state": "done"}, headers=maintenance).status_code == 409
    moved = client.patch(patch, json={"state": "acknowledged"}, headers=maintenance)
    assert moved.status_code == 200 and moved.json()["state"] == "acknowledged"

    health = client.get("/api/v1/loops/FIC-1/health", headers=viewer).json()
    assert health["diagnosis"]["stiction"]["verdict"] == "stiction"
    assert health["stiction_pattern"] == "limit cycle"
    assert health["diagnosis"]["first_sample_at"] == T0 - 3600 + 1  # the buffer grid
    assert len(health["trend"]) == 2
    data = client.get("/api/v1/loops/FIC-1/data", params={"start": T0 - 600, "end": T0,
                                                          "max_points": 100},
                      headers=viewer).json()
    assert {s["signal"] for s in data["series"]} == {"op", "pv", "sp"}
    assert all(0 < len(s["t"]) <= 100 for s in data["series"])
    advice = client.get("/api/v1/loops/FIC-1/advice", headers=viewer)
    assert advice.status_code == 200, advice.text
    body = advice.json()
    assert body["current"] == [{"Kc": 0.5, "Ti": 8.0}]  # the configured tuning
    assert {"recommendations", "rejected", "notes", "current_simulated"} <= body.keys()
    for offer in body["recommendations"] + body["rejected"]:  # each checked in simulation
        assert {"predicted", "simulated", "outcome"} <= offer.keys()
    unavailable = client.get("/api/v1/loops/FIC-2/advice", headers=viewer)
    assert (unavailable.status_code, unavailable.json()) == (409, {
        "detail": "Advice not available: the loop does not cycle and its valve is not sticky; "
                  "there is nothing to retune"})
    assert client.get("/api/v1/loops/FIC-9/advice", headers=viewer).status_code == 404
    metrics = client.get("/metrics", headers=viewer).text
    assert 'loopwatch_analyses_total{status="ok"} 4.0' in metrics
    assert "loopwatch_tickets_open 1.0" in metrics


def test_health_names_the_pattern_and_lists_the_episodes_at_utc_times(service, client):
    """A stored stick-jump finding: the episodes, seconds from the window's first sample in
    the diagnosis, come back at UNIX times."""
    viewer = key(client, "viewer")
    first_sample = T0 - 3600 + 1
    with service.state.store.session() as session:
        session.add(AnalysisRun(
            loop_id="FIC-1", started_at=T0, finished_at=T0 + 3, window_start=T0 - 3600,
            window_end=T0, status="ok", usable=True, oscillating=False, verdict="stiction",
            confidence=0.7, health=72.0,
            result={"first_sample_at": first_sample, "stiction": {
                "verdict": "stiction", "pattern": "stick_jump", "op_travel": 14.0,
                "episode_stick_band": 2.5,
                "episodes": [{"start_s": 120.0, "jump_s": 190.0, "end_s": 215.0,
                              "op_travel": 2.5, "pv_jump": 1.1, "op_during_jump": 0.3}]}},
        ))
    health = client.get("/api/v1/loops/FIC-1/health", headers=viewer).json()
    assert health["stiction_pattern"] == ("stick-jump: the valve holds while OP ramps, then "
                                          "jumps; no sustained cycle")
    assert health["episodes"] == [{"start": first_sample + 120.0, "jump": first_sample + 190.0,
                                   "end": first_sample + 215.0, "op_travel": 2.5,
                                   "pv_jump": 1.1}]
    quiet = client.get("/api/v1/loops/FIC-2/health", headers=viewer).json()
    assert (quiet["stiction_pattern"], quiet["episodes"]) == (None, [])


def test_restart_rebuilds_the_rolling_window_from_the_store(service, client, store):
    historian = key(client, "historian")
    client.post("/api/v1/ingest", json=simulated_batch(600), headers=historian)
    before = service.state.buffers.window("FIC-1", 600, T0)
    settings = service.state.settings
    restarted = build_service(settings, plant(), executor=ThreadPoolExecutor(1),
                              clock=lambda: T0)
    after = restarted.state.buffers.window("FIC-1", 600, T0)
    np.testing.assert_array_equal(before.op, after.op)
    assert np.isfinite(after.pv).all()
    restarted.executor.shutdown()
    restarted.state.store.close()


@pytest.mark.parametrize(("process_model", "message"), [
    ({"type": "fopdt", "tau": 5.0, "theta": 1.0}, "missing key 'K' for model type 'fopdt'"),
    ({"type": "fopdt", "K": "big", "tau": 5.0}, "K must be a number, got 'big'"),
    ({"theta": -2.0}, "theta (the dead time, s) must be a finite number >= 0, got -2.0"),
])
def test_a_loops_process_model_must_be_whole(client, process_model, message):
    """QA: a fopdt without its gain K was stored silently (no gain to size J with, and
    nothing said so).  It is a 422 naming process_model; the dead time alone stays."""
    body = {"ts": 1.0, "tags": {"pv": "PM.PV"}, "process_model": process_model}
    answer = client.put("/api/v1/loops/PM-1", json=body, headers={"X-API-Key": ADMIN})
    assert answer.status_code == 422, answer.text
    (error,) = answer.json()["detail"]
    assert error["loc"] == ["process_model"] and message in error["msg"]
    assert client.get("/api/v1/loops/PM-1", headers={"X-API-Key": ADMIN}).status_code == 404
    dead_time = {**body, "process_model": {"theta": 2.0}}
    assert client.put("/api/v1/loops/PM-1", json=dead_time,
                      headers={"X-API-Key": ADMIN}).status_code == 200


def test_a_stored_loop_that_no_longer_validates_is_not_run_and_the_service_starts(
        store, caplog):
    """A loop added through the API before its process_model was checked (a fopdt without
    K) must not stop the next start: it is left out with a warning naming the field."""
    from service.plant import sync_plant
    from service.store.models import Loop

    old = {"id": "OLD-1", "ts": 1.0, "tags": {"pv": "OLD.PV"},
           "process_model": {"type": "fopdt", "tau": 5.0}}
    with store.session() as session:
        session.add(Loop(id="OLD-1", name="", config=old, created_at=T0, updated_at=T0,
                         origin="api"))
    with store.session() as session:
        running = sync_plant(session, plant(), T0)
    assert "OLD-1" not in {loop.id for loop in running.loops}
    assert "FIC-1" in {loop.id for loop in running.loops}
    assert "loop OLD-1, added through the API, is not run" in caplog.text
    assert "process_model: Value error, missing key 'K'" in caplog.text


def test_loops_can_be_added_by_an_admin(client):
    body = {"name": "New", "unit": "u1", "ts": 2.0, "tags": {"pv": "NEW.PV"}}
    created = client.put("/api/v1/loops/NEW-1", json=body, headers={"X-API-Key": ADMIN})
    assert created.status_code == 200, created.text
    assert created.json()["id"] == "NEW-1"
    wrong = client.put("/api/v1/loops/NEW-2",
                       json={**body, "tags": {"pv": "NEW2.PV"}, "unit": "nowhere"},
                       headers={"X-API-Key": ADMIN})
    assert wrong.status_code == 422
    assert "unknown unit 'nowhere'" in wrong.text
    taken = client.put("/api/v1/loops/NEW-3", json=body, headers={"X-API-Key": ADMIN})
    assert (taken.status_code, taken.json()) == (
        409, {"detail": "Tag 'NEW.PV' belongs to loop 'NEW-1'"})
    assert client.get("/api/v1/loops/NEW-2",
                      headers={"X-API-Key": ADMIN}).status_code == 404


def test_unit_diagnosis_names_the_sticky_valve_of_the_unit(client):
    historian, viewer = key(client, "historian"), key(client, "viewer")
    assert client.get("/api/v1/units/u1/diagnosis", headers=viewer).status_code == 404
    client.post("/api/v1/ingest", json=simulated_batch(), headers=historian)
    response = client.get("/api/v1/units/u1/diagnosis", headers=viewer)
    assert response.status_code == 200, response.text
    body = response.json()
    assert [v["loop"] for v in body["sticky_valves"]] == ["FIC-1"]
    assert body["loops_without_complete_window"] == []
    assert client.get("/api/v1/units/nope/diagnosis", headers=viewer).json() == {
        "detail": "Unit not found"}
    # an API replica keeps no rolling buffers: the same diagnosis from the store
    client.app.state.loopwatch.buffers = LoopBuffers(plant(), horizon_s=7200)
    assert client.get("/api/v1/units/u1/diagnosis", headers=viewer).json() == body
