"""The simulated plant: closed loops with known faults, served over OPC UA and Modbus TCP.

The plant has two units.  Six single loops (:data:`SINGLE_LOOPS`, the
catalogue of the demo) are cases of :mod:`analytics.synthetic_cases`: two
sticky valves (Kano and He models), an over-tuned controller, an external
oscillating disturbance, and two healthy loops.  The multi-loop unit
(:data:`COLUMN_LOOPS`) is the 3x3 ethanol-water column of thesis Eq. 2.10
(:func:`analytics.scenarios.column3x3`) with ONE sticky valve, the side-draw
valve of loop 2 (He model, fs = 3, fd = 1, thesis Table 2.3): its cycle
spreads to the other loops, and only one valve is to blame.  Column signals
are deviations from the operating point, as in the thesis.

Every loop is simulated ahead for ``horizon_s`` of plant time and its
samples are released as time passes, ``speed`` times faster than real time
(after the horizon the runs start over, with a jump).  Sample ``k`` of a
loop sampled every ``ts`` seconds is stamped ``start + k ts / speed``: the
time stamps are wall-clock UTC, so in accelerated time the plant is simply a
faster plant, and :meth:`PlantSimulator.plant_config` divides sampling
intervals and integral times by ``speed`` to match.

OP, PV, SP and MV of every loop are served

* over OPC UA (asyncua), one Double variable per tag with node id
  ``ns=2;s=<loop>.<SIGNAL>``, every sample written with its source time
  stamp, so a subscriber with a queue gets every sample;
* over Modbus TCP (:class:`connectors.modbus_server.ModbusRegisterServer`),
  one float32 in two holding registers per tag, holding the latest sample.

:meth:`PlantSimulator.set_bad` turns a tag into a failed measurement (OPC
UA status BadSensorFailure, Modbus NaN) for fault tests.

References
----------
.. [1] B.A. Ogunnaike, J.P. Lemaire, M. Morari and W.H. Ray, "Advanced
   multivariable control of a pilot-plant distillation column", AIChE J.
   29(4), 1983 -- the column of thesis Eq. 2.10 (ref. [31] there): overhead
   and side-stream ethanol compositions and the tray-19 temperature, driven
   by reflux, side-draw and reboiler steam.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections.abc import Callable, Collection
from dataclasses import dataclass
from datetime import UTC
from typing import Any

import numpy as np
from asyncua import Server, ua

from analytics.scenarios import column3x3
from analytics.simulation import PIDController, SimulationResult
from analytics.synthetic_cases import SyntheticCase, synthetic_library
from connectors.base import ThreadedRunner
from connectors.modbus import REGISTER_COUNT, WordOrder
from connectors.modbus_server import ModbusRegisterServer

__all__ = [
    "COLUMN_LOOPS",
    "DEFAULT_MODBUS_LOOPS",
    "NAMESPACE_URI",
    "SIGNALS",
    "SINGLE_LOOPS",
    "PlantLoop",
    "PlantSimulator",
    "TagAddress",
]

log = logging.getLogger(__name__)

SIGNALS = ("OP", "PV", "SP", "MV")
"""The signals served for every loop; tag ``<loop id>.<signal>``."""

NAMESPACE_URI = "urn:loopwatch:plant-sim"
NAMESPACE_INDEX = 2
"""The index a fresh asyncua server gives the first namespace registered."""

MODBUS_LOOP_STRIDE = 10
"""Registers reserved per loop: loop ``n`` starts at ``10 n`` (OP, PV, SP, MV at +0, +2, +4, +6)."""

DEFAULT_MODBUS_LOOPS = ("FIC-105", "LIC-301")
"""Loops that :meth:`PlantSimulator.plant_config` reads over Modbus -- one sticky, one
healthy, so a fault travels that path too; the others are read over OPC UA."""


@dataclass(frozen=True)
class PlantLoop:
    """One loop of the simulated plant: its configuration entry and what it should show.

    ``source`` is the name of an :mod:`analytics.synthetic_cases` case, or
    ``"column:<i>"`` for loop ``i`` (0-based) of the 3x3 column.
    """

    id: str
    name: str
    unit: str
    source: str
    valve_asset: str
    importance: str
    expected: str
    ranges: tuple[tuple[str, tuple[float, float]], ...] = (
        ("op", (0.0, 100.0)), ("pv", (0.0, 100.0)),
    )


SINGLE_LOOPS = (
    PlantLoop("FIC-101", "Feed flow", "loops", "flow-kano-S4-J2-ts1", "FV-101", "high",
              "sticky valve (Kano S=4 %, J=2 %): alarm and ticket"),
    PlantLoop("FIC-102", "Reflux flow", "loops", "flow-aggressive-ts1", "FV-102", "medium",
              "over-tuned controller: oscillation alarm, no ticket"),
    PlantLoop("TIC-201", "Reactor temperature", "loops", "temp-sine500s-ts2", "TV-201", "high",
              "upstream disturbance (500 s): oscillation alarm, no ticket"),
    PlantLoop("LIC-301", "Drum level", "loops", "level-noise-ts1", "LV-301", "medium", "healthy"),
    PlantLoop("FIC-105", "Steam flow", "loops", "flow-he-S8-J4-ts1", "FV-105", "critical",
              "sticky valve (He fs=6 %, fd=2 %): alarm and ticket"),
    PlantLoop("PIC-401", "Header pressure", "loops", "flow-noise-ts0.5", "PV-401", "low",
              "healthy"),
)
"""The single loops (the demo's catalogue): case names of :mod:`analytics.synthetic_cases`."""

_DEVIATION = (-50.0, 50.0)  # column signals are deviations; a 100-unit span keeps S, J in %
COLUMN_LOOPS = (
    PlantLoop("AIC-501", "Overhead ethanol composition", "column", "column:0", "FV-501", "high",
              "cycles through interaction with loop 2; its own valve is healthy",
              (("op", _DEVIATION), ("pv", _DEVIATION))),
    PlantLoop("AIC-502", "Side-stream ethanol composition", "column", "column:1", "FV-502",
              "critical", "sticky side-draw valve (He fs=3, fd=1): alarm and ticket",
              (("op", _DEVIATION), ("pv", _DEVIATION))),
    PlantLoop("TIC-503", "Tray 19 temperature", "column", "column:2", "PV-503", "medium",
              "disturbed by the loop-2 cycle; its own valve is healthy",
              (("op", (-150.0, 300.0)), ("pv", _DEVIATION))),
)
"""The 3x3 column of thesis Eq. 2.10 [1], valve 2 sticky (thesis Table 2.3)."""

UNITS = (
    {"id": "loops", "name": "Single loops (simulated)"},
    {"id": "column", "name": "Ethanol-water column, 3x3 (simulated, thesis Eq. 2.10)"},
)


@dataclass(frozen=True)
class TagAddress:
    """Where one tag is served: OPC UA node id and Modbus holding registers."""

    tag: str
    node_id: str
    modbus_address: int
    modbus_type: str
    word_order: str


@dataclass(frozen=True)
class _Run:
    """A loop's precomputed samples (``values[signal]`` over ``ts``-spaced plant time)."""

    ts: float
    values: dict[str, np.ndarray]
    process_type: str
    controller: PIDController

    @property
    def samples(self) -> int:
        return len(self.values["OP"])


def _case(name: str, samples: int) -> SyntheticCase:
    return next(c for c in synthetic_library(samples) if c.name == name)


def _signals(result: SimulationResult, i: int) -> dict[str, np.ndarray]:
    return {"OP": result.op[i], "PV": result.pv[i], "SP": result.sp[i], "MV": result.mv[i]}


def _simulate(horizon_s: float) -> dict[str, _Run]:
    """Simulate every loop of the plant for ``horizon_s`` of plant time."""
    runs: dict[str, _Run] = {}
    for loop in SINGLE_LOOPS:
        case = _case(loop.source, 100)
        result = _case(loop.source, max(int(horizon_s / case.ts), 2)).simulate()
        runs[loop.id] = _Run(case.ts, _signals(result, 0), case.process_type, case.controller)
    column = column3x3(sticky=(2,), duration=horizon_s)
    result = column.run()
    for loop in COLUMN_LOOPS:
        i = int(loop.source.split(":")[1])
        runs[loop.id] = _Run(
            column.dt, _signals(result, i), "self-regulating", column.loops[i].controller
        )
    return runs


def _controller_config(controller: PIDController, speed: float) -> dict[str, Any]:
    """The DCS view of a simulated PI controller: Kc > 0 with an action, Ti in s."""
    action = controller.action
    if controller.kp < 0:  # a negative gain is the other action (thesis Eq. 2.12)
        action = "direct" if action == "reverse" else "reverse"
    return {
        "type": "PI",
        "Kc": abs(controller.kp),
        "Ti": controller.kp / controller.ki / speed,
        "action": action,
    }


class PlantSimulator:
    """Serve the simulated plant over OPC UA and (optionally) Modbus TCP.

    Parameters
    ----------
    host : str
        Address both servers listen on.
    opcua_port : int
    modbus_port : int or None
        None serves OPC UA only.
    speed : float
        Plant seconds per wall-clock second.
    horizon_s : float
        Plant time simulated ahead; the runs start over after it.
    word_order : {"ABCD", "CDAB", "BADC", "DCBA"}
        Word order of the Modbus float32 registers.
    clock : callable
        Wall clock, UNIX seconds.

    Use ``async with PlantSimulator(...) as plant:`` (serving while inside),
    ``await plant.run()`` until cancelled, or :meth:`start_in_thread`.
    """

    def __init__(
        self,
        *,
        host: str = "127.0.0.1",
        opcua_port: int = 4840,
        modbus_port: int | None = 5020,
        speed: float = 1.0,
        horizon_s: float = 12 * 3600.0,
        word_order: WordOrder = "ABCD",
        clock: Callable[[], float] = time.time,
    ) -> None:
        if not (math.isfinite(speed) and speed > 0):
            raise ValueError(f"speed must be a positive number, got {speed!r}")
        if not horizon_s > 0:
            raise ValueError(f"horizon_s must be positive, got {horizon_s!r}")
        self.host = host
        self.opcua_port = opcua_port
        self.modbus_port = modbus_port
        self.speed = float(speed)
        self.word_order = word_order
        self.clock = clock
        self.loops = SINGLE_LOOPS + COLUMN_LOOPS
        self._runs = _simulate(horizon_s)
        self._bad: set[str] = set()
        self._opcua: Server | None = None
        self._variables: dict[str, ua.NodeId] = {}
        self._modbus: ModbusRegisterServer | None = None
        self._released: dict[str, int] = {}
        self.start_time: float | None = None
        self._releaser: asyncio.Task[None] | None = None
        self._runner = ThreadedRunner(self.run, name="plant-sim")

    # --- what is served where -------------------------------------------------

    @property
    def opcua_url(self) -> str:
        """The OPC UA endpoint URL."""
        return f"opc.tcp://{self.host}:{self.opcua_port}"

    @property
    def tags(self) -> list[str]:
        """Every served tag, loop by loop."""
        return [f"{loop.id}.{signal}" for loop in self.loops for signal in SIGNALS]

    def address_map(self) -> list[TagAddress]:
        """Where every tag is served (OPC UA node id, Modbus float32 registers)."""
        rows = []
        for n, loop in enumerate(self.loops):
            for j, signal in enumerate(SIGNALS):
                tag = f"{loop.id}.{signal}"
                rows.append(TagAddress(
                    tag, f"ns={NAMESPACE_INDEX};s={tag}",
                    MODBUS_LOOP_STRIDE * n + REGISTER_COUNT["float32"] * j,
                    "float32", self.word_order,
                ))
        return rows

    def format_address_map(self) -> str:
        """The address map as a table for people."""
        modbus = f"modbus://{self.host}:{self.modbus_port}" if self.modbus_port else "no Modbus"
        lines = [
            f"OPC UA {self.opcua_url} (namespace {NAMESPACE_URI}), {modbus} "
            "(holding registers, unit id any)",
            f"{'tag':14s} {'OPC UA node id':22s} {'Modbus':>6s}  type     order",
        ]
        lines += [
            f"{a.tag:14s} {a.node_id:22s} {a.modbus_address:6d}  {a.modbus_type:8s} {a.word_order}"
            for a in self.address_map()
        ]
        return "\n".join(lines)

    def plant_config(
        self, *, modbus_loops: Collection[str] = DEFAULT_MODBUS_LOOPS
    ) -> dict[str, Any]:
        """The plant configuration the service needs to watch this plant.

        Loops with ids in ``modbus_loops`` are read over Modbus (when this
        plant serves Modbus), the others over OPC UA; sampling intervals and
        integral times are divided by ``speed``.
        """
        known = {loop.id for loop in self.loops}
        unknown = sorted(set(modbus_loops) - known)
        if unknown:
            raise ValueError(f"modbus_loops: unknown loops {unknown}; known: {sorted(known)}")
        over_modbus = set(modbus_loops) if self.modbus_port is not None else set()
        loops = []
        for loop in self.loops:
            run = self._runs[loop.id]
            loops.append({
                "id": loop.id, "name": loop.name, "unit": loop.unit,
                "tags": {s.lower(): f"{loop.id}.{s}" for s in SIGNALS},
                "ranges": {signal: list(span) for signal, span in loop.ranges},
                "ts": run.ts / self.speed,
                "process_type": run.process_type,
                "valve_asset": loop.valve_asset,
                "importance": loop.importance,
                "controller": _controller_config(run.controller, self.speed),
            })
        addresses = {a.tag: a for a in self.address_map()}
        opcua_tags = [t for t in self.tags if t.split(".")[0] not in over_modbus]
        fastest_ms = min(self._runs[t.split(".")[0]].ts for t in opcua_tags) / self.speed * 1000
        connectors: dict[str, Any] = {"opcua": [{
            "url": self.opcua_url,
            "sampling_interval_ms": fastest_ms,
            "publishing_interval_ms": max(fastest_ms, 100.0),
            # the samples one publishing interval can hold, with room for a late publish
            "queue_size": max(10, math.ceil(4 * max(fastest_ms, 100.0) / fastest_ms)),
            "watchdog_s": 30.0,
            "nodes": [{"tag": t, "node_id": addresses[t].node_id} for t in opcua_tags],
        }]}
        if over_modbus:
            connectors["modbus"] = [self._modbus_section(sorted(over_modbus), addresses)]
        return {"units": [dict(u) for u in UNITS], "loops": loops, "connectors": connectors}

    def _modbus_section(
        self, loop_ids: list[str], addresses: dict[str, TagAddress]
    ) -> dict[str, Any]:
        """A :class:`connectors.modbus.ModbusConnectorConfig`: one register group per loop."""
        groups = []
        for loop_id in loop_ids:
            first = addresses[f"{loop_id}.{SIGNALS[0]}"].modbus_address
            groups.append({
                "function": "holding",
                "start": first,
                "count": REGISTER_COUNT["float32"] * len(SIGNALS),
                "tags": [
                    {"tag": f"{loop_id}.{s}", "data_type": "float32",
                     "offset": addresses[f"{loop_id}.{s}"].modbus_address - first,
                     "word_order": self.word_order}
                    for s in SIGNALS
                ],
            })
        return {
            "host": self.host,
            "port": self.modbus_port,
            "poll_interval_s": min(self._runs[loop_id].ts for loop_id in loop_ids) / self.speed,
            "groups": groups,
        }

    # --- the simulated signals --------------------------------------------------

    def sample_interval(self, loop_id: str) -> float:
        """Wall-clock seconds between the samples of ``loop_id`` (``ts / speed``)."""
        return self._runs[loop_id].ts / self.speed

    def value(self, tag: str, k: int) -> float:
        """Sample ``k`` of ``tag`` (counted from the start; the runs repeat after the horizon)."""
        loop_id, signal = tag.rsplit(".", 1)
        run = self._runs[loop_id]
        return float(run.values[signal][k % run.samples])

    def sample_index(self, loop_id: str, timestamp: float) -> int:
        """The sample number of ``loop_id`` stamped ``timestamp`` (nearest)."""
        if self.start_time is None:
            raise RuntimeError("the plant has not started")
        return round((timestamp - self.start_time) / self.sample_interval(loop_id))

    def set_bad(self, tag: str, bad: bool = True) -> None:
        """Serve ``tag`` as a failed measurement from its next sample on (or again as good)."""
        if tag not in set(self.tags):
            raise KeyError(f"tag {tag!r} is not served by the plant")
        if bad:
            self._bad.add(tag)
        else:
            self._bad.discard(tag)

    # --- serving ----------------------------------------------------------------

    async def start(self) -> None:
        """Start the servers and release the first samples."""
        self._opcua = await self._start_opcua()
        if self.modbus_port is not None:
            self._modbus = ModbusRegisterServer(
                self.host, self.modbus_port,
                {a.tag: (a.modbus_address, "float32", self.word_order)
                 for a in self.address_map()},
            )
            await self._modbus.start()
        self.start_time = self.clock()
        self._released = {loop.id: -1 for loop in self.loops}
        await self.release()
        log.info("plant-sim: serving %d tags on %s%s at %g x real time", len(self.tags),
                 self.opcua_url, f" and modbus port {self.modbus_port}" if self._modbus else "",
                 self.speed)

    async def _start_opcua(self) -> Server:
        server = Server()
        await server.init()
        server.set_endpoint(self.opcua_url)
        server.set_server_name("loopwatch simulated plant")
        server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
        index = await server.register_namespace(NAMESPACE_URI)
        if index != NAMESPACE_INDEX:  # pragma: no cover -- fixed by asyncua's fresh address space
            raise RuntimeError(f"namespace {NAMESPACE_URI} got index {index}")
        addresses = {a.tag: a for a in self.address_map()}
        plant = await server.nodes.objects.add_folder(index, "Plant")
        for loop in self.loops:
            folder = await plant.add_object(index, loop.id)
            for signal in SIGNALS:
                tag = f"{loop.id}.{signal}"
                node = await folder.add_variable(
                    ua.NodeId.from_string(addresses[tag].node_id), signal,
                    ua.Variant(self.value(tag, 0), ua.VariantType.Double),
                )
                self._variables[tag] = node.nodeid
        await server.start()
        return server

    async def release(self) -> int:
        """Serve every sample due by now; returns the number of samples written."""
        assert self._opcua is not None and self.start_time is not None
        elapsed = self.clock() - self.start_time
        written = 0
        for loop in self.loops:
            interval = self.sample_interval(loop.id)
            due = math.floor(elapsed / interval + 1e-9)
            for k in range(self._released[loop.id] + 1, due + 1):
                stamp = ua.DateTime.fromtimestamp(self.start_time + k * interval, UTC)
                for signal in SIGNALS:
                    await self._serve(f"{loop.id}.{signal}", k, stamp)
                    written += 1
            self._released[loop.id] = max(due, self._released[loop.id])
        return written

    async def _serve(self, tag: str, k: int, stamp: ua.DateTime) -> None:
        assert self._opcua is not None
        now = ua.DateTime.now(UTC)
        if tag in self._bad:
            data_value = ua.DataValue(
                StatusCode=ua.StatusCode(ua.UInt32(ua.StatusCodes.BadSensorFailure)),
                SourceTimestamp=stamp, ServerTimestamp=now,
            )
            if self._modbus is not None:
                self._modbus.set_bad(tag)
        else:
            value = self.value(tag, k)
            data_value = ua.DataValue(
                ua.Variant(value, ua.VariantType.Double),
                SourceTimestamp=stamp, ServerTimestamp=now,
            )
            if self._modbus is not None:
                self._modbus.set(tag, value)
        await self._opcua.write_attribute_value(self._variables[tag], data_value)

    async def stop(self) -> None:
        """Stop both servers."""
        if self._modbus is not None:
            await self._modbus.stop()
            self._modbus = None
        if self._opcua is not None:
            await self._opcua.stop()
            self._opcua = None

    async def _release_forever(self) -> None:
        tick = min(min(self.sample_interval(loop.id) for loop in self.loops) / 2, 0.5)
        while True:
            await asyncio.sleep(tick)
            try:
                await self.release()
            except Exception:  # what failed is served again with the next release
                log.exception("plant-sim: releasing samples failed")

    async def run(self, duration_s: float | None = None) -> None:
        """Serve until cancelled (or for ``duration_s`` wall-clock seconds)."""
        async with self:
            if duration_s is None:
                await asyncio.Event().wait()
            else:
                await asyncio.sleep(duration_s)

    async def __aenter__(self) -> PlantSimulator:
        await self.start()
        self._releaser = asyncio.create_task(self._release_forever(), name="plant-sim-release")
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        if self._releaser is not None:
            self._releaser.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._releaser
            self._releaser = None
        await self.stop()

    def start_in_thread(self) -> None:
        """Serve from a background thread with its own event loop."""
        self._runner.start()

    def stop_thread(self, timeout: float = 10.0) -> None:
        """Stop serving and join the background thread."""
        self._runner.stop(timeout)
