"""``/api/v1/units/{id}/diagnosis``: the unit's sticky valves computed on demand or read
from the scheduler's run, 404 for an unknown unit, one without loops or without a window,
422 for a failed stored run, with their exact ``detail``."""

from service.buffer import LoopBuffers
from service.store.models import Unit, UnitAnalysisRun
from tests.service.test_api import T0, key, plant, simulated_batch


def test_unit_diagnosis_names_the_sticky_valve_of_the_unit(client):
    historian, viewer = key(client, "historian"), key(client, "viewer")
    empty = client.get("/api/v1/units/u1/diagnosis", headers=viewer)
    assert (empty.status_code, empty.json()) == (404, {
        "detail": "Unit diagnosis not available: no loop of the unit has a complete OP and PV "
                  "window"})
    client.post("/api/v1/ingest", json=simulated_batch(), headers=historian)
    response = client.get("/api/v1/units/u1/diagnosis", headers=viewer)
    assert response.status_code == 200, response.text
    body = response.json()
    assert [v["loop"] for v in body["sticky_valves"]] == ["FIC-1"]
    assert (body["source"], body["loops_without_complete_window"]) == ("on_demand", [])
    assert client.get("/api/v1/units/nope/diagnosis", headers=viewer).json() == {
        "detail": "Unit not found"}
    # an API replica keeps no rolling buffers: the same diagnosis from the store
    client.app.state.loopwatch.buffers = LoopBuffers(plant(), horizon_s=7200)
    assert client.get("/api/v1/units/u1/diagnosis", headers=viewer).json() == body


def test_a_unit_without_loops_is_404(service, client):
    with service.state.store.session() as session:
        session.add(Unit(id="u2", name="Unit 2"))
    answer = client.get("/api/v1/units/u2/diagnosis", headers=key(client, "viewer"))
    assert (answer.status_code, answer.json()) == (404, {
        "detail": "Unit diagnosis not available: the unit has no loops"})


def test_the_schedulers_failed_run_is_422_with_its_error(service, client):
    with service.state.store.session() as session:
        session.add(UnitAnalysisRun(
            unit_id="u1", started_at=T0, finished_at=T0 + 1, window_start=T0 - 3600,
            window_end=T0, status="failed", loops=["FIC-1", "FIC-2"], incomplete_loops=[],
            sticky_loops=[], cleared_loops=[], result=None, error="the windows disagree",
            round_end=T0))
    answer = client.get("/api/v1/units/u1/diagnosis", headers=key(client, "viewer"))
    assert (answer.status_code, answer.json()) == (422, {
        "detail": "Unit diagnosis not available: the scheduler's latest attempt ended "
                  "'failed': the windows disagree"})
