"""Connectors built from the plant file: every section, shards, and precise errors."""

import pytest

from connectors.modbus import ModbusConnector
from connectors.opcua import OpcUaConnector
from connectors.plant_sim import PlantSimulator
from connectors.replay import ReplayConnector
from service.config import ConfigError, PlantConfig, Settings
from service.connector_setup import build_connectors, endpoint_of
from service.demo import DEMO_LOOPS, demo_plant_config
from service.server import DEMO_ENDPOINT, build_service, ingest_shard
from tests.shared_data import SHARED_DATA, require_file


def plant_with_connectors() -> PlantConfig:
    simulator = PlantSimulator(host="127.0.0.1", opcua_port=48400, modbus_port=50200)
    spec = simulator.plant_config()
    export = require_file(SHARED_DATA / "plant_unlabelled" / "FIC-211_20241121-27.csv")
    spec["connectors"]["replay"] = [{"path": str(export), "columns": {"FT_211": "X.PV"},
                                     "date_column": "date", "time_column": "time"}]
    return PlantConfig.model_validate(spec)


def test_every_section_becomes_its_connector_feeding_the_sink():
    received = []
    built = build_connectors(plant_with_connectors(), lambda _: True, received.append)
    kinds = sorted(type(c).__name__ for c in built)
    assert kinds == ["ModbusConnector", "OpcUaConnector", "ReplayConnector"]
    assert all(hasattr(c, "start") and hasattr(c, "stop") for c in built)


def test_an_ingest_shard_runs_only_the_endpoints_it_owns():
    plant = plant_with_connectors()
    built = build_connectors(plant, lambda endpoint: endpoint == "127.0.0.1:50200", print)
    assert [type(c) for c in built] == [ModbusConnector]
    assert not isinstance(built[0], OpcUaConnector | ReplayConnector)


@pytest.mark.parametrize(("connectors", "message"), [
    ({"opc": []}, "connectors: unknown section(s) opc; known: opcua, modbus, replay"),
    ({"opcua": {"url": "opc.tcp://x"}}, "connectors.opcua: must be a list"),
    ({"opcua": [{"url": "opc.tcp://127.0.0.1:4840", "nodes": [{"tag": "A"}]}]},
     "connectors.opcua[0].nodes[0].node_id: Field required"),
    ({"modbus": [{"host": "127.0.0.1", "port": 502, "groups": [], "bogus": 1}]},
     "connectors.modbus[0].bogus: Extra inputs are not permitted"),
])
def test_invalid_entries_are_refused_with_their_key_path(connectors, message):
    plant = PlantConfig.model_validate({"connectors": connectors})
    with pytest.raises(ConfigError) as info:
        build_connectors(plant, lambda _: True, print)
    assert message in str(info.value)


def test_endpoints_name_what_a_connector_talks_to():
    plant = plant_with_connectors()
    opcua = plant.connectors["opcua"][0]
    assert opcua["url"].startswith("opc.tcp://127.0.0.1:48400")
    from connectors.opcua import OpcUaEndpointConfig

    assert endpoint_of("opcua", OpcUaEndpointConfig.model_validate(opcua)) == opcua["url"]


# --- the demo plant (``loopwatch serve`` without a plant file) ----------------------------


def demo_settings(tmp_path, **changes) -> Settings:
    return Settings(database_url=f"sqlite:///{tmp_path / 'demo.db'}",
                    api_key="connector-setup-admin-0123", **changes)


def test_the_demo_is_read_over_the_servers_of_the_plant_this_process_serves(tmp_path):
    svc = build_service(demo_settings(tmp_path, role="ingest"), None,
                        connector_factory=build_connectors)
    try:
        assert svc.feeder is not None
        served = svc.feeder.plant
        opcua, modbus = sorted(svc.connectors, key=lambda c: type(c).__name__, reverse=True)
        assert isinstance(opcua, OpcUaConnector) and opcua.config.url == served.opcua_url
        assert isinstance(modbus, ModbusConnector)
        assert (modbus.config.host, modbus.config.port) == (served.host, served.modbus_port)
        registered = svc.state.registry.plant
        assert registered == svc.feeder.plant_config
        assert registered.model_dump(exclude={"connectors"}) == demo_plant_config().model_dump(
            exclude={"connectors"})  # what processes that do not serve the demo watch
        assert {loop.id for loop in registered.loops} == {loop.id for loop in DEMO_LOOPS}
    finally:
        svc.state.store.close()


def test_only_the_ingest_process_owning_the_demo_serves_it(tmp_path):
    owner = ingest_shard(DEMO_ENDPOINT, 2)
    for shard in (0, 1):
        svc = build_service(demo_settings(tmp_path, role="ingest", ingest_shard=shard,
                                          ingest_shards=2), None,
                            connector_factory=build_connectors)
        try:
            assert (svc.feeder is not None) == (shard == owner)
            assert bool(svc.connectors) == (shard == owner)
        finally:
            svc.state.store.close()


def test_without_a_connector_factory_the_demo_is_not_served(tmp_path):
    svc = build_service(demo_settings(tmp_path, role="ingest"), None)
    try:
        assert svc.feeder is None and svc.connectors == []
    finally:
        svc.state.store.close()
