"""End to end over real protocols, as ``make run`` runs it.

The service is built with no plant file and the connectors of the plant file
(``connector_factory=build_connectors``): the simulated plant is served over
OPC UA and Modbus TCP on free loopback ports, the service reads it through
its OPC UA and Modbus connectors, and the last two hours -- the analysis
windows of the ticket rule's two confirmations -- are back-filled at start
through the same ingest.  The scheduler analyses that history, then every
``INTERVAL_S`` the newest window, and finds the sticky valves: the tickets
and alarms are read through the REST API, and every sample received is
accounted for.
"""

import time
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from connectors.modbus import ModbusConnector
from connectors.opcua import OpcUaConnector
from connectors.plant_sim import WATCHED_SIGNALS
from service.config import Settings
from service.connector_setup import build_connectors
from service.server import Service, build_service, running

pytestmark = pytest.mark.serial  # timing-sensitive: run alone, after the parallel tests

ADMIN = "end-to-end-admin-key-0123456789"
INTERVAL_S = 4.0
HEADERS = {"X-API-Key": ADMIN}


def wait_for(what: str, condition: Callable[[], Any], within_s: float,
             state: Callable[[], Any]) -> Any:
    deadline = time.monotonic() + within_s
    while not (result := condition()):
        assert time.monotonic() < deadline, f"no {what} after {within_s} s; now: {state()}"
        time.sleep(0.2)
    return result


def demo_service(tmp_path: Any) -> Service:
    settings = Settings(database_url=f"sqlite:///{tmp_path / 'e2e.db'}", api_key=ADMIN,
                        analysis_interval_s=INTERVAL_S, window_s=3600, buffer_horizon_s=7200,
                        ticket_confirmations=2)
    return build_service(settings, None, connector_factory=build_connectors)


def test_the_demo_plant_over_opcua_and_modbus_gets_its_alarms_and_tickets(tmp_path):
    service = demo_service(tmp_path)
    assert service.feeder is not None
    plant = service.feeder.plant
    opcua, modbus = sorted(service.connectors, key=lambda c: type(c).__name__, reverse=True)
    assert isinstance(opcua, OpcUaConnector) and isinstance(modbus, ModbusConnector)
    client = TestClient(service.app)

    def tickets() -> set[str]:
        answer = client.get("/api/v1/tickets", headers=HEADERS).json()["data"]
        return {t["valve_asset"] for t in answer}

    def verdicts() -> dict[str, tuple[bool | None, str | None]]:
        answer = client.get("/api/v1/loops", headers=HEADERS).json()["data"]
        return {loop["id"]: (loop["oscillating"], loop["verdict"]) for loop in answer}

    with running(service):
        wait_for("ticket for each sticky valve", lambda: {"FV-101", "FV-105", "FV-502"}
                 <= tickets(), within_s=90, state=lambda: (tickets(), verdicts()))
        # the windows run from the back-fill into the live samples without a gap (up to
        # the samples still on their way: the connectors flush every second)
        modbus_polls_per_s = len(modbus.config.groups) / modbus.config.poll_interval_s
        wait_for("10 s of Modbus polls", lambda: modbus.counters.polls > 10 * modbus_polls_per_s,
                 within_s=30, state=lambda: modbus.counters)
        delivered_by = time.time() - 2.5
        over_opcua = service.state.buffers.window("FIC-101", 3600, delivered_by)
        over_modbus = service.state.buffers.window("FIC-105", 3600, delivered_by)
        found = verdicts()
        alarms = client.get("/api/v1/alarms", headers=HEADERS).json()["data"]
        column = client.get("/api/v1/units/column/diagnosis", headers=HEADERS).json()
        # A round stores the loops' runs, then the unit's diagnosis settles their verdicts
        # (a few seconds in which AIC-501 and TIC-503 show their own findings; see the
        # closing note of issue 19): ask for the prediction on settled verdicts.
        def settled_prediction() -> Any:
            answer = client.get("/api/v1/units/column/prediction", headers=HEADERS)
            valves = {v["loop"]: v for v in answer.json().get("valves", [])}
            cleared = all("cleared_by_unit_run" in valves.get(loop, {})
                          for loop in ("AIC-501", "TIC-503"))
            return answer if answer.status_code != 200 or cleared else None

        answers: list[Any] = []
        wait_for("the unit's prediction on settled verdicts",
                 lambda: answers.append(settled_prediction()) or answers[-1] is not None,
                 within_s=30, state=verdicts)
        prediction = answers[-1]
        ticketed = tickets()
        sizes = {loop: client.get(f"/api/v1/loops/{loop}/health", headers=HEADERS)
                 .json()["diagnosis"]["valve"] for loop in ("FIC-101", "FIC-105", "AIC-502")}
        pic_kpis = client.get("/api/v1/loops/PIC-401/kpis", headers=HEADERS).json()["data"]
    assert plant.origin is not None
    # PIC-401 is in manual from 30 to 75 min of plant time: each run's service factor is
    # the share of its window's grid in that stretch (to a grid point: the stored window
    # end is the round's time, the grid ends at the last sample before it)
    ts = plant.sample_interval("PIC-401")
    in_manual = []
    for point in pic_kpis:
        grid = (np.floor(point["window_end"] / ts) - np.arange(int(3600 / ts))) * ts
        plant_s = (grid - plant.origin) * plant.speed
        share = np.mean((plant_s >= 1800) & (plant_s < 4500))
        factor = point["kpis"]["service_factor"]
        assert abs(factor["manual"] - share) <= 1.5 * ts / 3600, (point, share)
        in_manual.append(factor["manual"])
    assert max(in_manual) > 0.2 and any("in manual" in note for point in pic_kpis
                                        for note in point["kpis"]["notes"])
    # OPC UA delivers every sample; Modbus is polled twice per sampling interval, so only
    # a poll loop held up for a whole interval (a loaded CI machine) leaves a point empty
    assert over_opcua.pv is not None and not np.isnan(over_opcua.pv).any()
    assert over_modbus.pv is not None and np.isnan(over_modbus.pv).sum() <= 5
    # OPC UA delivers every sample with its time stamp: the window is the simulation
    served = [plant.value("FIC-101.PV", plant.sample_index("FIC-101", t)) for t in over_opcua.t]
    np.testing.assert_array_equal(over_opcua.pv, served)
    # over Modbus a register holds the latest sample served (float32), stamped when
    # polled: sample k or an earlier one, a few samples back when the simulator's thread
    # was held up on a loaded machine
    polled = 0
    for t, value in zip(over_modbus.t, over_modbus.pv, strict=True):
        k = plant.sample_index("FIC-105", t)
        if not np.isnan(value) and value != plant.value("FIC-105.PV", k):  # not back-filled
            recent = [np.float32(plant.value("FIC-105.PV", j)) for j in range(k - 5, k + 1)]
            assert value in recent, (t, k, value)
            polled += 1
    assert polled >= 5

    assert ticketed == {"FV-101", "FV-105", "FV-502"}  # no healthy valve has a ticket
    # each sticky valve's size is combined over the two windows of the history rounds that
    # do not overlap, with its interval (issue 19).  FV-101 (Kano S 4, J 2) measured
    # 4.00/1.99.  FV-105 (He S 8, J 4, sized with its configured process model's gain)
    # is fitted as a Kano valve and reads J low, -13 % to -18 % over live runs whose
    # windows start a few seconds apart (benchmarks/demo_sizes.py --offsets): not always
    # within 15 %.
    # FV-502 (He S 4, J 2) is sized with the column's process matrix, J 2.03; its S is
    # the second window's (3.7-4.2): the start-up window (1.5-3.2, R^2 0.74-0.97 against
    # 0.99) counts less for its worse fit, whichever interval is the narrower.
    for size in sizes.values():
        assert len(size["size_windows"]) == 2
        assert size["S_interval"][0] <= size["S"] <= size["S_interval"][1]
        assert size["J_interval"][0] <= size["J"] <= size["J_interval"][1]
    assert sizes["FIC-101"]["S"] == pytest.approx(4.0, rel=0.15)
    assert sizes["FIC-101"]["J"] == pytest.approx(2.0, rel=0.15)
    assert sizes["FIC-105"]["S"] == pytest.approx(8.0, rel=0.15)
    assert sizes["FIC-105"]["J"] == pytest.approx(4.0, rel=0.25)  # a guard, not the target
    assert sizes["AIC-502"]["S"] == pytest.approx(4.0, rel=0.15)
    assert sizes["AIC-502"]["J"] == pytest.approx(2.0, rel=0.15)
    assert all(w["gain_given"] for w in sizes["AIC-502"]["size_windows"])
    assert sizes["AIC-502"]["J_note"].startswith("J sized with the process gain from unit column")
    # the unit's prediction takes the sticky valve's estimate, and the cleared valves as healthy
    assert prediction.status_code == 200, prediction.text
    valves = {v["loop"]: v for v in prediction.json()["valves"]}
    # the estimate's valve model at the combined size: FV-502 is simulated as a He valve;
    # in a limit cycle a Kano valve of the same S and J gives nearly the same PV, and the
    # quantification's choice between them turns on the trajectory
    sticky = valves["AIC-502"]["valve"]
    assert sticky["model"] in ("he", "kano")
    stick_band = sticky["fs"] + sticky["fd"] if sticky["model"] == "he" else sticky["S"]
    assert stick_band == pytest.approx(sizes["AIC-502"]["S"])
    # the unit's model cycles as the column does (issue 19): the simulation within 15 % of
    # the measured period and 25 % of its OP amplitude; the harmonic balance predicts no
    # cycle (the loop FV-502 sees lags under 90 degrees) and the answer says why
    answer = prediction.json()
    measured = answer["comparison"]["measured_cycle"]
    assert 150.0 < measured["measured"]["period_s"] < 250.0
    assert abs(measured["period_error"]["simulated"]) <= 0.15, answer["valve_fit"]
    assert measured["reproduces"] and answer["valve_fit"]["reproduces"]
    assert answer["describing_note"].startswith("the harmonic balance cannot give")
    assert answer["comparison"]["agree"] is False
    assert all(valves[loop]["valve"] is None and "cleared_by_unit_run" in valves[loop]
               for loop in ("AIC-501", "TIC-503"))
    assert found == {
        "FIC-101": (True, "stiction"), "FIC-105": (True, "stiction"),  # sticky valves
        "FIC-102": (True, "no_stiction"), "TIC-201": (True, "no_stiction"),  # tuning, disturbance
        # healthy and quiet: their valves hardly move, too little to judge (issue 17)
        "LIC-301": (False, "undecided"), "PIC-401": (False, "undecided"),
        # the column's cycle reaches every loop; its unit diagnosis clears FV-501 and PV-503,
        # and every page reads that final verdict (issue 19)
        "AIC-501": (True, "no_stiction"), "AIC-502": (True, "stiction"),
        "TIC-503": (True, "no_stiction"),
    }
    assert column["source"] == "scheduler"
    assert [valve["loop"] for valve in column["sticky_valves"]] == ["AIC-502"]
    alarmed = {alarm["loop_id"] for alarm in alarms if alarm["kind"] == "oscillation"}
    assert {"FIC-101", "FIC-105", "FIC-102", "TIC-201", "AIC-502"} <= alarmed
    assert not alarmed & {"LIC-301", "PIC-401"}

    books = service.state.accounting()
    assert books.refused == {} and books.spooled == 0
    assert books.received == books.stored + books.already_stored
    opcua_counters, modbus_counters = opcua.counters, modbus.counters
    for counters in (opcua_counters, modbus_counters):
        assert counters.samples == counters.delivered, counters
    live_samples = opcua_counters.delivered + modbus_counters.delivered
    per_second = sum(len(WATCHED_SIGNALS) / plant.sample_interval(loop.id)
                     for loop in plant.loops)
    backfilled_s = (books.received - live_samples) / per_second
    # two hours (the windows of the ticket rule's two confirmations), and the seconds up to
    # the live samples
    assert service.feeder.history_s == 7200
    assert 7200 <= backfilled_s < 7200 + 30
    assert not opcua.outages and not modbus.outages
