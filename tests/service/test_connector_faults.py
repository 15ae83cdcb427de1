"""Connector faults while the service runs (issues 5 and 10).

The simulated plant serves over real OPC UA and Modbus TCP servers on free
loopback ports; the service reads it through the connectors of its plant
file.  The OPC UA server goes away and comes back, then the Modbus server;
then a tag fails on each protocol (OPC UA status BadSensorFailure, a Modbus
register holding NaN).  The service keeps running and reconnects, each
outage is recorded, nothing served while connected is lost, failed values
are stored as bad, and every sample received is accounted for.
"""

import asyncio
import itertools
import time
from collections.abc import Callable
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from connectors.modbus import ModbusConnector
from connectors.opcua import OpcUaConnector
from connectors.plant_sim import PlantSimulator
from service.config import PlantConfig, Settings
from service.connector_setup import build_connectors
from service.server import build_service
from service.store.db import Store
from service.store.models import Sample

pytestmark = pytest.mark.serial  # timing-sensitive: run alone, after the parallel tests

ADMIN = "connector-faults-admin-key-0123"
DOWN_S = 2.5


async def until(what: str, condition: Callable[[], Any], within_s: float = 20.0) -> None:
    deadline = time.monotonic() + within_s
    while not condition():
        assert time.monotonic() < deadline, f"timed out after {within_s} s waiting for {what}"
        await asyncio.sleep(0.05)


def stored(store: Store, tag: str) -> list[tuple[float, float | None, bool]]:
    with store.session() as session:
        rows = session.execute(select(Sample.time, Sample.value, Sample.good)
                               .where(Sample.tag == tag).order_by(Sample.time)).all()
    return [(t, v, g) for t, v, g in rows]


def test_servers_going_away_and_coming_back_and_failed_tags(tmp_path):
    settings = Settings(database_url=f"sqlite:///{tmp_path / 'faults.db'}", api_key=ADMIN,
                        role="ingest")
    times: dict[str, float] = {}

    async def scenario(plant: PlantSimulator) -> tuple[OpcUaConnector, ModbusConnector, Any]:
        plant_config = PlantConfig.model_validate(plant.plant_config())
        service = build_service(settings, plant_config, connector_factory=build_connectors)
        opcua, modbus = sorted(service.connectors, key=lambda c: type(c).__name__, reverse=True)
        assert isinstance(opcua, OpcUaConnector) and isinstance(modbus, ModbusConnector)
        client = TestClient(service.app)

        async def metrics() -> str:
            """``GET /metrics`` as an operator's monitoring would scrape it."""
            response = await asyncio.to_thread(client.get, "/metrics",
                                               headers={"X-API-Key": ADMIN})
            assert response.status_code == 200, response.text
            return str(response.text)

        await asyncio.to_thread(service.start)
        try:
            await until("samples over both protocols",
                        lambda: opcua.counters.delivered > 50 and modbus.counters.delivered > 20)
            for server, connected, reconnects in (
                ("opcua", lambda: opcua.connected, lambda: opcua.counters.reconnects),
                ("modbus", lambda: not modbus.outages or modbus.outages[-1].end is not None,
                 lambda: modbus.counters.reconnects),
            ):
                times[f"{server} down"] = time.time()
                await plant.take_down(server)
                await until(f"the {server} loss to be noticed", lambda c=connected: not c())
                connector = opcua if server == "opcua" else modbus
                name = connector.name
                assert f'loopwatch_connector_up{{connector="{name}"}} 0.0' in await metrics()
                await asyncio.sleep(DOWN_S)
                times[f"{server} up"] = time.time()
                await plant.bring_back(server)
                await until(f"{server} to reconnect", lambda r=reconnects: r() == 1)
                before = connector.counters
                scraped = await metrics()
                after = connector.counters
                assert f'loopwatch_connector_up{{connector="{name}"}} 1.0' in scraped
                assert f'loopwatch_connector_outages_total{{connector="{name}"}} 1.0' in scraped
                delivered = float(scraped.split(
                    f'loopwatch_connector_delivered_total{{connector="{name}"}} ')[1].split()[0])
                assert before.delivered <= delivered <= after.delivered
            bad_before = (opcua.counters.bad, modbus.counters.bad)
            plant.set_bad("FIC-101.PV")  # over OPC UA
            plant.set_bad("FIC-105.PV")  # over Modbus
            await until("bad samples", lambda: opcua.counters.bad > bad_before[0] + 2
                        and modbus.counters.bad > bad_before[1] + 2)
            plant.set_bad("FIC-101.PV", False)
            plant.set_bad("FIC-105.PV", False)
            received = (opcua.counters.samples, modbus.counters.samples)
            await until("good samples again", lambda: opcua.counters.samples > received[0] + 40
                        and modbus.counters.samples > received[1] + 12)
            # ... and stored after the bad ones for both failed tags (a count of samples
            # alone is reached sooner when the plant serves more tags, e.g. its mode tags)
            watcher = Store(settings.resolved_database_url)
            try:
                await until("good values stored after the failures", lambda: all(
                    (rows := stored(watcher, tag)) and rows[-1][2]
                    and any(not good for *_, good in rows)
                    for tag in ("FIC-101.PV", "FIC-105.PV")))
            finally:
                watcher.close()
        finally:
            await asyncio.to_thread(service.stop)
        return opcua, modbus, service.state.accounting()

    async def main() -> tuple[OpcUaConnector, ModbusConnector, Any, PlantSimulator]:
        async with PlantSimulator(opcua_port=0, modbus_port=0, horizon_s=3600) as plant:
            return (*await scenario(plant), plant)

    opcua, modbus, books, plant = asyncio.run(asyncio.wait_for(main(), 120))

    # every sample received is stored (or was already), none refused, none lost on the way
    assert books.refused == {} and books.spooled == 0
    assert books.received == books.stored + books.already_stored
    opcua_counters, modbus_counters = opcua.counters, modbus.counters
    for counters in (opcua_counters, modbus_counters):
        assert counters.samples == counters.delivered, counters
    assert books.received == opcua_counters.delivered + modbus_counters.delivered

    # each outage is recorded, from the loss to the first data after the server came back
    for server, outages in (("opcua", opcua.outages), ("modbus", modbus.outages)):
        assert len(outages) == 1, (server, outages)
        outage = outages[0]
        assert times[f"{server} down"] <= outage.start < times[f"{server} up"], server
        assert outage.end is not None and times[f"{server} up"] <= outage.end, server
    assert opcua_counters.reconnects == 1 and modbus_counters.reconnects == 1

    store = Store(settings.resolved_database_url)
    try:
        # OPC UA: every sample served while connected is stored, with its value
        opcua_outage = opcua.outages[0]
        assert opcua_outage.end is not None
        samples = stored(store, "FIC-101.OP")
        numbers = [plant.sample_index("FIC-101", t) for t, _, _ in samples]
        assert all(v == plant.value("FIC-101.OP", k)
                   for k, (_, v, _) in zip(numbers, samples, strict=True))
        interval = plant.sample_interval("FIC-101")
        assert plant.origin is not None
        missing = [plant.origin + k * interval
                   for k in sorted(set(range(numbers[0], numbers[-1] + 1)) - set(numbers))]
        assert missing, "the outage left no gap"
        publishing_s = 0.5  # the last publish before the loss may not reach the client
        assert all(opcua_outage.start - publishing_s <= t <= opcua_outage.end
                   for t in missing), (missing, opcua_outage)
        # Modbus: polled twice per sampling interval, so one gap spans the outage; a loaded
        # machine may hold the poll loop up for a few seconds elsewhere (polling then misses
        # those samples, as polling does; it is no outage: there is only one, above)
        modbus_outage = modbus.outages[0]
        assert modbus_outage.end is not None
        stamps = [t for t, _, _ in stored(store, "FIC-105.OP")]
        gaps = [(a, b) for a, b in itertools.pairwise(stamps)
                if b - a > 4 * plant.sample_interval("FIC-105") / 2]
        spanning = [(a, b) for a, b in gaps
                    if a <= modbus_outage.start and b >= modbus_outage.end - 0.5]
        assert len(spanning) == 1, (gaps, modbus_outage)
        # a failed measurement is stored as bad, never as a value; good values follow it
        for tag in ("FIC-101.PV", "FIC-105.PV"):
            quality = [(v is None, g) for _, v, g in stored(store, tag)]
            assert (True, False) in quality and quality[-1] == (False, True), tag
            assert all(is_none == (not good) for is_none, good in quality), tag
    finally:
        store.close()

