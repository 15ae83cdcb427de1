"""Connectors from the plant file's ``connectors`` section.

::

    connectors:
      opcua:  [{url: opc.tcp://..., nodes: [{tag, node_id}], ...}]   # connectors.opcua
      modbus: [{host, port, groups: [...]}]                          # connectors.modbus
      replay: [{path, columns: {file column: tag}, speed}]           # connectors.replay

Every entry is validated when the service starts: an invalid one is refused
with its key path (``connectors.opcua[0].nodes[1].tag: ...``).  Each
connector sends its samples to the service's ingest, the one path into the
store; an ingest process only runs the connectors of its shard (``owns``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from pydantic import BaseModel, ValidationError

from connectors.base import SampleSink
from connectors.modbus import ModbusConnector, ModbusConnectorConfig
from connectors.opcua import OpcUaConnector, OpcUaEndpointConfig
from connectors.replay import ReplayConnector, ReplayConnectorConfig
from service.config import ConfigError, PlantConfig, _key_path

__all__ = ["build_connectors", "endpoint_of"]

SECTIONS = ("opcua", "modbus", "replay")


def _validated(section: str, index: int, spec: Any, model: type[BaseModel]) -> Any:
    try:
        return model.model_validate(spec)
    except ValidationError as exc:
        lines = [f"connectors.{section}[{index}].{_key_path(tuple(e['loc']))}: {e['msg']}"
                 for e in exc.errors()]
        raise ConfigError("invalid connector configuration:\n  " + "\n  ".join(lines)) from None


def endpoint_of(section: str, config: Any) -> str:
    """The endpoint a connector talks to: what ingest shards are split by."""
    if section == "opcua":
        return str(config.url)
    if section == "modbus":
        return f"{config.host}:{config.port}"
    return str(config.path)


def build_connectors(plant: PlantConfig, owns: Callable[[str], bool],
                     sink: SampleSink) -> list[Any]:
    """The connectors of ``plant`` whose endpoint this process ``owns``, feeding ``sink``.

    Raises
    ------
    ConfigError
        An unknown section or an invalid entry, with its key path.
    """
    unknown = sorted(set(plant.connectors) - set(SECTIONS))
    if unknown:
        raise ConfigError(f"connectors: unknown section(s) {', '.join(unknown)}; "
                          f"known: {', '.join(SECTIONS)}")
    built: list[Any] = []
    for section, model, make in (
        ("opcua", OpcUaEndpointConfig, OpcUaConnector),
        ("modbus", ModbusConnectorConfig, ModbusConnector),
        ("replay", ReplayConnectorConfig, ReplayConnector.from_config),
    ):
        entries = plant.connectors.get(section) or []
        if not isinstance(entries, list):
            raise ConfigError(f"connectors.{section}: must be a list of connector entries")
        for index, spec in enumerate(entries):
            config = _validated(section, index, spec, model)
            if owns(endpoint_of(section, config)):
                built.append(make(config, sink))
    return built
