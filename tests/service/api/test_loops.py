"""``/api/v1/loops``, ``/api/v1/plant/bad-actors`` and ``/api/v1/units``: the answers of a
loop's routes, 404 for an unknown loop or unit, 409 and 422 for a loop that cannot be
stored, with their exact ``detail`` (the KPI history's refusals: ``tests/service/test_kpis``)."""

import pytest

from service.store.models import AnalysisRun
from tests.service.test_api import ADMIN, T0, key

HEADERS = {"X-API-Key": ADMIN}


@pytest.mark.parametrize("suffix", ["", "/config", "/analyses", "/health", "/kpis", "/data"])
def test_an_unknown_loop_is_404(client, suffix):
    answer = client.get(f"/api/v1/loops/FIC-9{suffix}", headers=HEADERS)
    assert (answer.status_code, answer.json()) == (404, {"detail": "Loop not found"})
    assert client.get(f"/api/v1/loops/FIC-1{suffix}", headers=HEADERS).status_code == 200


def test_units_list_their_loops_and_an_unknown_unit_is_404(client):
    units = client.get("/api/v1/units", headers=HEADERS).json()
    assert units == {"data": [{"id": "u1", "name": "Unit 1", "loops": ["FIC-1", "FIC-2"]}],
                     "count": 1}
    loops = client.get("/api/v1/units/u1", headers=HEADERS).json()
    assert [loop["id"] for loop in loops["data"]] == ["FIC-1", "FIC-2"]
    unknown = client.get("/api/v1/units/nope", headers=HEADERS)
    assert (unknown.status_code, unknown.json()) == (404, {"detail": "Unit not found"})


def test_the_bad_actor_period_is_bounded(client):
    answer = client.get("/api/v1/plant/bad-actors", headers=HEADERS, params={"period": "93d"})
    assert (answer.status_code, answer.json()) == (422, {
        "detail": "period must be at most 92 days"})


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
            result={"ts": 1.0, "first_sample_at": first_sample, "stiction": {
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


def test_only_an_admin_may_add_a_loop(client):
    refused = client.put("/api/v1/loops/X-1", json={"ts": 1.0, "tags": {"pv": "X.PV"}},
                         headers=key(client, "operator"))
    assert (refused.status_code, refused.json()) == (403, {
        "detail": "Role 'operator' may not admin"})
