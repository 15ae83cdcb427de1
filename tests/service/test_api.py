"""The REST API end to end on SQLite and PostgreSQL: ingest, analysis, alarms, tickets, keys.

A small plant of two simulated loops (one sticky valve, one healthy loop) is
pushed through ``POST /api/v1/ingest`` as a historian would, analysed by the
scheduler (in a thread pool: the process pool is exercised by the demo test)
and inspected through the API with keys of every role.  Each router's own answers and
refusals are tested in ``tests/service/api/test_<route>.py``.
"""

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from analytics.synthetic_cases import synthetic_library
from service.config import PlantConfig
from service.server import build_service

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

