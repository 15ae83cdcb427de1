"""GET /api/v1/units/{id}/prediction and the unit process matrix of the plant file.

Unit ``u1`` couples the temperature loop of thesis section 5.5.1 (sticky
valve S = 4, J = 2 under Kc = 10, Ti = 10 s) weakly to a healthy flow loop.
The answer is checked against the harmonic balance evaluated here from
``TransferFunction.frequency_response`` and ``choudhury_df`` (thesis Eq. 3.14
with ERRATA items 1 and 9), against the single-loop prediction it must stay
close to, and against a simulation built here with the simulator directly.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from analytics.describing import choudhury_df
from analytics.limit_cycle import predict_limit_cycles, simulate_limit_cycle
from analytics.lti import TransferFunction
from analytics.simulation import ClosedLoopModel, Loop, PIDController
from analytics.valves import ChoudhuryValve, IdealValve
from service.config import ConfigError, PlantConfig, Settings, parse_plant_config
from service.server import build_service
from service.store import models
from service.store.db import Store
from service.store.models import UnitAnalysisRun
from tests.service.api.stored import store_run
from tests.service.test_api import ADMIN, T0, key

TEMPERATURE = TransferFunction.fopdt(0.4346, 27.58, 6.0)  # thesis Eq. 5.42
FLOW = TransferFunction.fopdt(1.0, 5.0, 1.0)
FLOW_TO_TEMPERATURE = TransferFunction.fopdt(0.05, 10.0, 3.0)
TEMPERATURE_TO_FLOW = TransferFunction.fopdt(0.1, 5.0, 2.0)
CONTROLLERS = (PIDController.ideal(10.0, 10.0), PIDController.ideal(0.5, 8.0))
TS = 1.0


def fopdt(g: TransferFunction) -> dict[str, Any]:
    """The model-file entry of a first-order-plus-dead-time ``g``."""
    return {"type": "fopdt", "K": g.num[0], "tau": g.den[0], "theta": g.delay}


def loop(loop_id: str, unit: str, kc: float, ti: float) -> dict[str, Any]:
    return {"id": loop_id, "unit": unit, "ts": TS, "controller": {"Kc": kc, "Ti": ti},
            "tags": {"op": f"{loop_id}.OP", "pv": f"{loop_id}.PV"}}


def plant_data() -> dict[str, Any]:
    """u1: the coupled pair; u2: no process matrix; u3: a loop unstable without stiction."""
    return {
        "units": [
            {"id": "u1", "process": {"loops": ["TIC-1", "FIC-2"], "matrix": [
                [fopdt(TEMPERATURE), fopdt(FLOW_TO_TEMPERATURE)],
                [fopdt(TEMPERATURE_TO_FLOW), fopdt(FLOW)],
            ]}},
            {"id": "u2"},
            {"id": "u3", "process": {"loops": ["TIC-3"], "matrix": [
                [{"type": "fopdt", "K": 1.0, "tau": 10.0, "theta": 5.0}]]}},
        ],
        "loops": [loop("TIC-1", "u1", 10.0, 10.0), loop("FIC-2", "u1", 0.5, 8.0),
                  loop("FIC-4", "u2", 0.5, 8.0), loop("TIC-3", "u3", 5.0, 10.0)],
    }


@pytest.fixture
def client(store: Store) -> Iterator[TestClient]:
    settings = Settings(database_url=store.url, api_key=ADMIN, window_s=3600,
                        buffer_horizon_s=7200)
    svc = build_service(settings, PlantConfig.model_validate(plant_data()),
                        executor=ThreadPoolExecutor(1), clock=lambda: T0)
    yield TestClient(svc.app)
    svc.executor.shutdown()
    svc.state.store.close()


def store_unit_run(client: TestClient, at: float, period_s: float | None,
                   amplitude: float) -> None:
    """A diagnosis of u1 that measured TIC-1 cycling at ``period_s`` with OP amplitude
    ``amplitude`` (no group: no cycle)."""
    groups = [] if period_s is None else [{
        "period_s": period_s, "loops": ["TIC-1", "FIC-2"],
        "members": [{"signal": "pv_TIC-1", "period_s": period_s, "amplitude": 0.5},
                    {"signal": "op_TIC-1", "period_s": period_s, "amplitude": amplitude}]}]
    state = client.app.state.loopwatch  # type: ignore[attr-defined]
    with state.store.session() as session:
        session.add(UnitAnalysisRun(
            unit_id="u1", started_at=at, finished_at=at, window_start=at - 3600.0,
            window_end=at, status="ok", loops=["TIC-1", "FIC-2"], incomplete_loops=[],
            sticky_loops=["TIC-1"], cleared_loops=[],
            result={"groups": groups, "sticky_valves": []}))


def loop_matrix(omega: float, hold_delay: float) -> np.ndarray:
    """``gc_i(jw) e^(-jw hold) g_ij(jw)``, computed directly."""
    rows = ((TEMPERATURE, FLOW_TO_TEMPERATURE), (TEMPERATURE_TO_FLOW, FLOW))
    s = 1j * omega
    return np.array([[(c.kp + c.ki / s) * np.exp(-hold_delay * s)
                      * complex(g.frequency_response(omega)) for g in row]
                     for c, row in zip(CONTROLLERS, rows, strict=True)])


# ----------------------------------------------------------------------------- the route
def test_prediction_of_the_coupled_unit_meets_its_defining_equation_and_the_simulation(
    client: TestClient,
) -> None:
    viewer = key(client, "viewer")
    run_id = store_run(client, "TIC-1", "stiction", {"S": 4.0, "J": 2.0, "fs": 3.0, "fd": 1.0})
    store_run(client, "FIC-2", "no_stiction")
    response = client.get("/api/v1/units/u1/prediction", headers=viewer)
    assert response.status_code == 200, response.text
    body = response.json()
    assert body["loops"] == ["TIC-1", "FIC-2"]
    assert body["valves"][0]["valve"] == {"model": "choudhury", "S": 4.0, "J": 2.0}
    assert body["valves"][0]["run_id"] == run_id
    assert body["valves"][1]["valve"] is None
    assert body["unknown"] == ["unit 'u1' has no diagnosis yet: the prediction is not "
                               "checked against a measured cycle"]
    assert "valve_fit" not in body  # nothing measured to fit the valve to
    (cycle,) = body["limit_cycles"]
    assert cycle["stable"] and cycle["amplitudes"][1] is None

    # Thesis Eq. 3.14 and ERRATA item 9 at the answer: det(I + L N) = 0, and the
    # OP amplitudes are the moduli of the null vector.
    gains = np.array([complex(choudhury_df(cycle["amplitudes"][0], 4.0, 2.0)), 1.0])
    h = np.eye(2) + loop_matrix(cycle["omega"], TS / 2) * gains
    _, singular, vh = np.linalg.svd(h)
    assert singular[-1] < 1e-8
    null = np.abs(vh[-1])
    ops = cycle["op_amplitudes"]
    assert null[1] / null[0] == pytest.approx(ops[1] / ops[0], rel=1e-6)

    # Weak coupling: close to the single loop of section 5.5.1 (36.4 s with the hold).
    (alone,) = predict_limit_cycles(TEMPERATURE, CONTROLLERS[0], ChoudhuryValve(4.0, 2.0),
                                    hold_delay=TS / 2).limit_cycles
    assert cycle["period_s"] == pytest.approx(alone.period_s, rel=0.03)

    # The simulated cycle, against a simulation of the same loops built here.
    loops = (Loop(CONTROLLERS[0], ChoudhuryValve(4.0, 2.0), setpoint=[(10.0, 54.0)]),
             Loop(CONTROLLERS[1], IdealValve(), setpoint=[(10.0, 54.0)]))
    model = ClosedLoopModel(((TEMPERATURE, FLOW_TO_TEMPERATURE), (TEMPERATURE_TO_FLOW, FLOW)),
                            loops, dt=TS, duration=body["simulated"]["window_s"][1])
    independent = simulate_limit_cycle(model)
    simulated = body["simulated"]
    assert simulated["oscillating"] and independent.oscillating
    assert simulated["period_s"] == pytest.approx(independent.period_s, rel=0.01)
    assert simulated["amplitudes"][0] == pytest.approx(independent.amplitudes[0], rel=0.02)
    # The DF error of the method, as reported, and small for this loop (thesis Fig. 5.16).
    error = body["comparison"]["period_error_pct"]
    assert error == pytest.approx(100 * (cycle["period_s"] - simulated["period_s"])
                                  / simulated["period_s"])
    assert abs(error) < 10.0
    assert abs(body["comparison"]["amplitude_error_pct"][0]) < 20.0


def test_agree_needs_the_model_to_reproduce_the_measured_cycle(client: TestClient) -> None:
    """Issue 19: the column predicted no cycle and said ``agree: true`` while the plant
    cycled at 200 s.  Prediction and simulation agreeing with each other is not enough:
    the model must cycle with the period the unit's diagnosis measured (within 15 %)."""
    viewer = key(client, "viewer")
    store_run(client, "TIC-1", "stiction", {"S": 4.0, "J": 2.0})
    store_run(client, "FIC-2", "no_stiction")
    store_unit_run(client, T0, 200.0, 3.0)
    body = client.get("/api/v1/units/u1/prediction", headers=viewer).json()
    (cycle,) = body["limit_cycles"]
    simulated = body["simulated"]
    assert simulated["oscillating"] and cycle["stable"]  # they agree with each other ...
    measured = body["comparison"]["measured_cycle"]
    assert measured["measured"] == {"period_s": 200.0, "amplitude": 3.0}
    assert measured["period_error"]["predicted"] == pytest.approx(
        (cycle["period_s"] - 200.0) / 200.0)
    assert measured["period_error"]["simulated"] == pytest.approx(
        (simulated["period_s"] - 200.0) / 200.0)
    assert measured["amplitude_error"]["simulated"] == pytest.approx(
        (simulated["amplitudes"][0] - 3.0) / 3.0)
    # ... but a 36 s cycle is not the measured 200 s one
    assert not measured["reproduces"] and not measured["agree"]
    assert "disagrees with the measurement (200 s)" in measured["explanation"]
    assert body["comparison"]["agree"] is False
    assert body["unknown"] == []
    # the valve was fitted to the measured cycle first: no He, Kano or Choudhury valve of
    # the estimate's size (no intervals stored) cycles at 200 s in this unit; the model
    # simulated is the fit's closest, and says so
    fit = body["valve_fit"]
    assert fit["measured"] == {"period_s": 200.0, "amplitude": 3.0}
    assert fit["cause"] == "process" and not fit["reproduces"]
    assert fit["chosen"]["period_s"] == pytest.approx(simulated["period_s"])
    assert "the model keeps that error" in fit["explanation"]
    assert (fit["chosen"]["S"], fit["chosen"]["J"]) == (4.0, 2.0)

    # A later diagnosis that measured the model's own cycle: all three agree.  (The
    # simulation runs as many measured periods as the fit's, here 5 % longer, so its
    # period may move by a fraction of a sample.)
    store_unit_run(client, T0 + 60.0, simulated["period_s"] * 1.05,
                   simulated["amplitudes"][0])
    body = client.get("/api/v1/units/u1/prediction", headers=viewer).json()
    measured = body["comparison"]["measured_cycle"]
    assert measured["period_error"]["simulated"] == pytest.approx(1 / 1.05 - 1, abs=0.005)
    assert measured["reproduces"] and measured["agree"] and body["comparison"]["agree"]
    assert body["valve_fit"]["cause"] == "none"
    assert "describing_note" not in body  # the harmonic balance gives this period

    # A diagnosis that measured no cycle of TIC-1, while the model cycles: no agreement.
    store_unit_run(client, T0 + 120.0, None, 0.0)
    body = client.get("/api/v1/units/u1/prediction", headers=viewer).json()
    assert body["comparison"]["measured_cycle"]["measured"]["period_s"] is None
    assert body["comparison"]["agree"] is False


@pytest.mark.parametrize(("model", "valve"), [
    ("kano", {"model": "kano", "S": 4.0, "J": 2.0}),
    ("he", {"model": "he", "fs": 3.0, "fd": 1.0}),  # thesis Eq. 1.2
    (None, {"model": "choudhury", "S": 4.0, "J": 2.0}),  # stored before valve_model
])
def test_the_valve_is_the_estimates_model_at_the_combined_size(
    client: TestClient, model: str | None, valve: dict[str, Any],
) -> None:
    """Issue 19: the unit's model took a Choudhury valve of the latest window's S and J;
    the valve is the model the Hammerstein fit chose, at the size combined over the
    valve's windows (the final verdict's), as the single-loop advice takes it."""
    viewer = key(client, "viewer")
    window = {"S": 3.1, "J": 0.9, "valve_model": model}  # the latest window alone
    combined = {"verdict": "stiction", "decided_by": "loop", "S": 4.0, "J": 2.0,
                "S_interval": [3.5, 4.5], "J_interval": [1.5, 2.5]}
    store_run(client, "TIC-1", "stiction", window, valve=combined)
    store_run(client, "FIC-2", "no_stiction")
    body = client.get("/api/v1/units/u1/prediction", headers=viewer).json()
    assert body["valves"][0]["valve"] == pytest.approx(valve)


def test_missing_configuration_and_estimates_are_named(client: TestClient) -> None:
    viewer = key(client, "viewer")
    missing = client.get("/api/v1/units/nope/prediction", headers=viewer)
    assert missing.status_code == 404
    assert missing.json() == {"detail": "Unit not found"}

    no_matrix = client.get("/api/v1/units/u2/prediction", headers=viewer)
    assert no_matrix.status_code == 409
    assert no_matrix.json()["detail"].startswith(
        "Prediction not available: unit 'u2' has no process matrix; add 'process: {loops: "
        "[...], matrix: [[...]]}' to the unit in the plant file")

    nothing_yet = client.get("/api/v1/units/u1/prediction", headers=viewer).json()
    assert nothing_yet["limit_cycles"] == [] and nothing_yet["simulated"] is None
    assert nothing_yet["unknown"] == [
        "TIC-1: not analysed yet; its valve is taken as healthy",
        "FIC-2: not analysed yet; its valve is taken as healthy",
    ]
    assert "no valve of the unit has a stiction finding" in nothing_yet["note"]

    run_id = store_run(client, "TIC-1", "stiction", None)
    unsized = client.get("/api/v1/units/u1/prediction", headers=viewer)
    assert unsized.status_code == 409
    assert unsized.json() == {"detail": "Prediction not available: loop 'TIC-1' has a "
                                        f"stiction finding (analysis {run_id}) without a size "
                                        "estimate (S, J)"}


def test_a_unit_unstable_without_stiction_is_refused(client: TestClient) -> None:
    store_run(client, "TIC-3", "stiction", {"S": 4.0, "J": 2.0})
    response = client.get("/api/v1/units/u3/prediction", headers=key(client, "viewer"))
    assert (response.status_code, response.json()) == (422, {"detail": (
        "Prediction not available: unit model: unstable without stiction, so no limit "
        "cycle: the loop is unstable with healthy valves (2 right-half-plane roots): "
        "oscillations grow instead of settling on a limit cycle")})


def test_who_may_ask_and_what_the_configuration_lacks(client: TestClient) -> None:
    """401/403 for keys; 409 for a loop of the matrix without a controller, and for one the
    plant file names but the store lacks (another replica's plant file)."""
    url = "/api/v1/units/u3/prediction"
    assert (client.get(url).status_code, client.get(url).json()) == (
        401, {"detail": "Missing API key (header X-API-Key)"})
    refused = client.get(url, headers=key(client, "historian"))
    assert (refused.status_code, refused.json()) == (
        403, {"detail": "Role 'historian' may not read"})
    admin = {"X-API-Key": ADMIN}
    body = {"unit": "u3", "ts": 1.0, "tags": {"op": "TIC-3.OP", "pv": "TIC-3.PV"}}
    assert client.put("/api/v1/loops/TIC-3", json=body, headers=admin).status_code == 200
    answer = client.get(url, headers=admin)
    assert (answer.status_code, answer.json()) == (409, {"detail": (
        "Prediction not available: loop 'TIC-3' has no controller (Kc, Ti) in its "
        "configuration")})
    state = client.app.state.loopwatch  # type: ignore[attr-defined]
    with state.store.session() as session:
        session.delete(session.get(models.Loop, "TIC-3"))
    answer = client.get(url, headers=admin)
    assert (answer.status_code, answer.json()) == (409, {"detail": (
        "Prediction not available: the process matrix of unit 'u3' names loop 'TIC-3', "
        "which is not in the store")})


# ----------------------------------------------------------------------------- the plant file
@pytest.mark.parametrize(("change", "message"), [
    (lambda p: p["units"][0]["process"]["loops"].__setitem__(1, "FIC-4"),
     "units[0].process.loops[1]: 'FIC-4' is not a loop of unit 'u1'"),
    (lambda p: p["units"][0]["process"]["loops"].__setitem__(1, "XIC-9"),
     "units[0].process.loops[1]: 'XIC-9' is not a loop of unit 'u1'"),
    (lambda p: p["units"][0]["process"]["matrix"][1][0].pop("tau"),
     "units[0].process: Value error, matrix[2][1]: missing key 'tau' for model type 'fopdt'"),
    (lambda p: p["units"][0]["process"]["matrix"][1].pop(),
     "units[0].process: Value error, matrix must be square (2 x 2, one row and column per "
     "loop): row 2 has 1 entries"),
    (lambda p: p["units"][0]["process"]["loops"].pop(),
     "units[0].process: Value error, matrix is 2 x 2 but 'loops' names 1 loops"),
    (lambda p: p["units"][0]["process"]["matrix"][0].__setitem__(0, None),
     "units[0].process: Value error, matrix[1][1] is null: loop 1 has no effect on its PV"),
])
def test_a_bad_process_matrix_is_refused_with_its_key_path(
    change: Callable[[dict[str, Any]], object], message: str
) -> None:
    data = plant_data()
    change(data)
    with pytest.raises(ConfigError) as refused:
        parse_plant_config(data, "plant.yaml")
    assert message in str(refused.value)


def test_the_matrix_entries_are_those_of_the_model_file() -> None:
    unit = parse_plant_config(plant_data()).units[0]
    assert unit.process is not None
    first = unit.process.matrix[0][0]
    assert first is not None
    entry = TransferFunction.from_dict(first)
    assert complex(entry.frequency_response(0.1)) == pytest.approx(
        complex(TEMPERATURE.frequency_response(0.1)))
    assert math.isclose(entry.delay, 6.0)
