"""Advice on the demo plant through the real service (issue 19): the model behind each
answer must reproduce the cycle measured on the plant.

The service watches the demo plant (:func:`service.demo.demo_plant_config`) and is fed two
hours of the simulated plant's signals through the ingest API; the scheduler analyses
the two windows, then the advice of each loop is read through the REST API.  The numbers
are checked against the simulated plant itself: the measured period against the
simulated valve's, the detuning's gain margin against the true process and controller of
the simulated over-tuned loop.

Every refusal of ``GET /loops/{id}/advice`` is checked for its status code and exact
``detail`` on the two-loop test plant, with analyses written into the store.
"""

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from fastapi.testclient import TestClient

from analytics.simulation import ClosedLoopModel, Loop, PIDController
from analytics.synthetic_cases import synthetic_library
from analytics.tuning import cycle_origin
from connectors.plant_sim import SINGLE_LOOPS, PlantSimulator
from service.config import PlantConfig, Settings
from service.server import build_service
from tests.service.api.stored import store_run
from tests.service.test_api import ADMIN, T0, key

HEADERS = {"X-API-Key": ADMIN}
HISTORY_S = 7200.0


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """The demo plant analysed on two windows ending at ``T0``: (client, plant simulator)."""
    plant = PlantSimulator(modbus_port=None, origin=T0 - HISTORY_S, horizon_s=HISTORY_S)
    config = plant.plant_config()
    del config["connectors"]
    settings = Settings(database_url=f"sqlite:///{tmp_path_factory.mktemp('advice') / 'a.db'}",
                        api_key=ADMIN, window_s=3600, buffer_horizon_s=HISTORY_S)
    service = build_service(settings, PlantConfig.model_validate(config),
                            executor=ThreadPoolExecutor(1), clock=lambda: T0)
    client = TestClient(service.app)
    for loop in config["loops"]:
        ts = loop["ts"]
        k = np.arange(int(HISTORY_S / ts))
        batch = [{"tag": tag, "items": [{"timestamp": T0 - HISTORY_S + j * ts,
                                         "value": plant.value(tag, int(j))} for j in k]}
                 for signal, tag in loop["tags"].items() ]
        assert client.post("/api/v1/ingest", json=batch, headers=HEADERS).status_code == 200
    service.scheduler.run_once(T0 - 3600)
    service.scheduler.run_once(T0)
    yield client, plant
    service.executor.shutdown()
    service.state.store.close()


def advice(client: TestClient, loop_id: str):
    return client.get(f"/api/v1/loops/{loop_id}/advice", headers=HEADERS)


@pytest.mark.parametrize("loop_id", ["FIC-101", "FIC-105"])
def test_a_sticky_valve_gets_advice_from_a_model_that_cycles_as_the_loop(demo, loop_id):
    client, _ = demo
    answer = advice(client, loop_id)
    assert answer.status_code == 200, answer.text
    body = answer.json()
    assert body["kind"] == "stiction"
    # The valve the advice simulates cycles as the plant does, with the plant's size.
    # FV-105 is a He valve (S 8, J 4), which the estimate takes for a Kano valve that
    # would let the loop settle: the check names the He valve.  FV-101 is a Kano valve
    # (S 4, J 2), which the estimate names; in the identified loop model a Kano valve of
    # that size settles or cycles as the last bits of the identified process fall
    # (Kano's valve follows a slow ramp without sticking), and a He valve of the same
    # size then reproduces the cycle.
    source = next(p.source for p in SINGLE_LOOPS if p.id == loop_id)
    case = next(c for c in synthetic_library(100) if c.name == source)
    fit = body["valve_fit"]
    assert fit["estimated"]["valve_model"] == "kano"
    if loop_id == "FIC-105":
        assert fit["chosen"]["valve_model"] == case.valve.name == "he"
        assert fit["cause"] in ("valve_model", "valve_size")
    else:
        assert fit["cause"] in ("none", "valve_model")
    true_s, true_j = {"FIC-101": (4.0, 2.0), "FIC-105": (8.0, 4.0)}[loop_id]
    assert abs(fit["chosen"]["S"] / true_s - 1) <= 0.15
    assert abs(fit["chosen"]["J"] / true_j - 1) <= 0.15
    assert fit["reproduces"] and fit["chosen"]["reproduces"]
    measured = body["measured_cycle"]
    # the plant cycles at about 100 s (FV-101: 102 s, FV-105: 112 s)
    assert 90 < measured["measured"]["period_s"] < 125
    # the simulated model reproduces it: period within 15 %, amplitude within 25 %
    assert body["current_simulated"]["oscillating"]
    assert abs(measured["period_error"]["simulated"]) <= 0.15
    assert abs(measured["amplitude_error"]["simulated"]) <= 0.25
    assert measured["reproduces"] and measured["explanation"].startswith(
        "the model reproduces the measured cycle")
    # where the describing function misses the period, the answer says so
    predicted = measured["period_error"]["predicted"]
    assert ("describing function's period is" in measured["explanation"]) == (
        predicted is not None and abs(predicted) > 0.15)
    assert body["recommendations"], body["notes"]
    for offer in body["recommendations"]:
        assert offer["outcome"] in ("removed", "reduced")
        assert offer["simulated"]["travel_rate"] < body["current_simulated"]["travel_rate"]


@pytest.mark.parametrize("loop_id", ["FIC-101", "FIC-105"])
def test_the_offered_retunes_make_the_plants_valve_travel_less(demo, loop_id):
    """Checked on the simulated plant itself (its process, valve and measurement noise):
    each offered retune makes the valve travel less than the current tuning does."""
    client, _ = demo
    body = advice(client, loop_id).json()
    source = next(p.source for p in SINGLE_LOOPS if p.id == loop_id)
    case = next(c for c in synthetic_library(100) if c.name == source)
    current = plant_valve_travel(case, **body["current"][0])
    assert body["recommendations"]
    for offer in body["recommendations"]:
        assert plant_valve_travel(case, **offer["tunings"][0]) < 0.95 * current, offer


def plant_valve_travel(case, Kc: float, Ti: float | None) -> float:
    """Valve travel (% of span per s) of the simulated plant loop ``case`` under PI ``Kc``,
    ``Ti``, over three hours after its first hour."""
    loop = Loop(PIDController.ideal(Kc, Ti or np.inf), case.valve, pv_bias=50.0,
                setpoint=[(10.0, 51.0)], disturbances=case.disturbances)
    run = ClosedLoopModel(case.process, (loop,), dt=case.ts, duration=14_400.0).run()
    mv = run.mv[0, int(3600 / case.ts):]
    return float(np.abs(np.diff(mv)).sum() / (mv.size * case.ts))


def test_the_over_tuned_loop_gets_detuning_with_its_gain_margin(demo):
    client, _ = demo
    answer = advice(client, "FIC-102")
    assert answer.status_code == 200, answer.text
    body = answer.json()
    assert body["kind"] == "detuning"
    assert body["current"] == [{"Kc": 3.0, "Ti": 4.0}]
    assert "its amplitude waxes and wanes" in body["notes"][-1]  # its own resonance
    offers = body["recommendations"]
    assert [(o["tunings"][0]["Kc"], o["gain_margin"]) for o in offers] == [(1.5, 2.0), (1.0, 3.0)]
    # checked against the simulated plant's own process, controller and sampling (a
    # half-sample hold): the true gain margin of each detuned controller is at least the
    # one promised, and not far above it (the loop cycles near its stability limit)
    case = next(c for c in synthetic_library(100) if c.name == "flow-aggressive-ts1")
    w = np.geomspace(1e-3, 3.0, 300_001)
    for offer in offers:
        kc, ti = offer["tunings"][0]["Kc"], offer["tunings"][0]["Ti"]
        loop = (kc * (1 + 1 / (1j * w * ti)) * case.process.frequency_response(w)
                * np.exp(-0.5j * w * case.ts))
        crossing = np.argmin(np.abs(np.unwrap(np.angle(loop)) + np.pi))
        true_margin = 1 / abs(loop[crossing])
        assert offer["gain_margin"] <= true_margin <= 1.25 * offer["gain_margin"]
    assert abs(body["ultimate_period_s"] - 2 * np.pi / w[crossing]) <= 0.15 * body[
        "ultimate_period_s"]


def test_loops_the_advice_cannot_serve_get_a_409_with_the_reason(demo):
    client, _ = demo
    for loop_id in ("AIC-501", "TIC-503"):  # cleared by the unit: the cause is FV-502
        answer = advice(client, loop_id)
        assert answer.status_code == 409, answer.text
        assert "cycles because FV-502 sticks" in answer.json()["detail"]
    assert advice(client, "LIC-301").status_code == 409  # healthy and quiet
    # TIC-201 cycles with a healthy valve because a 200 s disturbance enters it: its
    # cycle keeps its amplitude, so it is not the tuning, and detuning is not offered
    answer = advice(client, "TIC-201")
    assert answer.status_code == 409, answer.text
    assert "forced from outside" in answer.json()["detail"]


def test_the_units_sticky_valve_gets_advice(demo):
    """AIC-502's identified process has no lag the data resolve (tau = 0): with a PI
    controller that loop would not roll off; one sampling interval of lag keeps it proper."""
    client, _ = demo
    answer = advice(client, "AIC-502")
    assert answer.status_code == 200, answer.text
    assert answer.json()["kind"] == "stiction"


def test_a_loop_without_a_controller_is_told_what_to_configure(demo):
    client, _ = demo
    body = {"name": "No controller", "ts": 1.0, "tags": {"op": "FIC-109.OP", "pv": "FIC-109.PV"}}
    assert client.put("/api/v1/loops/FIC-109", json=body, headers=HEADERS).status_code == 200
    answer = advice(client, "FIC-109")
    assert answer.status_code == 409
    assert "configure controller: {type: PI, Kc, Ti, action}" in answer.json()["detail"]


# ----------------------------------------------------------------------------- status codes
# The two-loop test plant (conftest ``client``) with analyses written into the store.

CYCLING = {"detected": True, "period_s": 100.0, "amplitude_op": 2.0}
"""A cycle of 100 s in a window of 3600 samples of 1 s: 36 periods."""


def refusal(client: TestClient, loop_id: str, headers: dict[str, str] = HEADERS
            ) -> tuple[int, str]:
    answer = client.get(f"/api/v1/loops/{loop_id}/advice", headers=headers)
    return answer.status_code, answer.json()["detail"]


def test_who_and_which_loop(client) -> None:
    assert refusal(client, "NOPE") == (404, "Loop not found")
    assert refusal(client, "FIC-1", {}) == (401, "Missing API key (header X-API-Key)")
    assert refusal(client, "FIC-1", key(client, "historian")) == (
        403, "Role 'historian' may not read")


def test_no_controller_and_no_analysis_are_409(client) -> None:
    assert refusal(client, "FIC-1") == (
        409, "Advice not available: the loop has not been analysed yet")
    body = {"name": "No controller", "ts": 1.0, "tags": {"op": "FIC-9.OP", "pv": "FIC-9.PV"}}
    assert client.put("/api/v1/loops/FIC-9", json=body, headers=HEADERS).status_code == 200
    assert refusal(client, "FIC-9") == (
        409, "Advice not available: the loop's configuration has no controller; configure "
             "controller: {type: PI, Kc, Ti, action} (plant file or PUT /api/v1/loops/FIC-9)")


@pytest.mark.parametrize(("verdict", "result", "detail"), [
    ("no_stiction", {"oscillation": {"detected": False}},
     "the loop does not cycle and its valve is not sticky; there is nothing to retune"),
    ("no_stiction", {"oscillation": CYCLING, "valve": {
        "verdict": "no_stiction", "decided_by": "unit", "reason": "cycles because FV-2 sticks",
        "unit_id": "u1"}},
     "the loop cycles because FV-2 sticks (unit u1's diagnosis); retuning it would not "
     "remove the cause: see the advice for that valve's loop"),
    ("undecided", {"oscillation": CYCLING},
     "the loop cycles but whether its valve sticks is undecided; no model to advise from"),
    ("stiction", {"oscillation": CYCLING},
     "the latest analysis has no stiction estimate (S, J) with an identified process model"),
    ("stiction", {"oscillation": CYCLING, "quantification": {
        "S": 4.0, "J": 2.0, "process": {"K": -1.0, "tau": 10.0, "theta": 2.0,
                                        "integrating": False}}},
     "the identified process gain -1 and the controller action 'reverse' make positive "
     "feedback"),
])
def test_what_the_analysis_lacks_is_a_409_with_the_reason(client, verdict, result,
                                                          detail) -> None:
    store_run(client, "FIC-1", verdict, **{"stiction": {"verdict": verdict}, **result})
    assert refusal(client, "FIC-1") == (409, f"Advice not available: {detail}")


@pytest.mark.parametrize(("envelope", "origin"), [(0.01, "forced"), (0.4, "own")])
def test_a_healthy_valve_cycling_gets_detuning_unless_the_cycle_is_forced(
    client, envelope, origin
) -> None:
    """A steady amplitude is a cycle forced from outside (409 with why); one that waxes and
    wanes is the loop's own (:func:`analytics.tuning.cycle_origin`): detuning, and why."""
    oscillation = {**CYCLING, "envelope_variation": envelope}
    run_id = store_run(client, "FIC-1", "no_stiction", stiction={"verdict": "no_stiction"},
                       oscillation=oscillation, samples=3600, ts=1.0, kpis={"saturation": 0.0})
    _, why = cycle_origin(envelope, 36.0, 0.0)
    answer = client.get("/api/v1/loops/FIC-1/advice", headers=HEADERS)
    if origin == "forced":
        assert (answer.status_code, answer.json()) == (
            409, {"detail": f"Advice not available: {why}"})
        return
    assert answer.status_code == 200, answer.text
    body = answer.json()
    assert (body["kind"], body["run_id"], body["ultimate_period_s"]) == ("detuning", run_id,
                                                                        100.0)
    assert [r["tunings"] for r in body["recommendations"]] == [
        [{"Kc": 0.25, "Ti": 8.0}], [{"Kc": 0.5 / 3, "Ti": 8.0}]]
    assert body["notes"][-1] == why

