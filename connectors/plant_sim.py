"""The simulated plant: closed loops with known faults, served over OPC UA and Modbus TCP.

The plant has six single loops (:data:`SINGLE_LOOPS`), cases of
:mod:`analytics.synthetic_cases` in no unit: two sticky valves (Kano and He
models), an over-tuned controller, an external oscillating disturbance, and
two healthy loops.  Its one unit, ``column`` (:data:`COLUMN_LOOPS`), is the
3x3 ethanol-water column of thesis Eq. 2.10
(:func:`analytics.scenarios.column3x3`) with ONE sticky valve, the side-draw
valve of loop 2 (He model, fs = 3, fd = 1, thesis Table 2.3): its cycle
spreads to the other loops, and only one valve is to blame.  Column signals
are deviations from the operating point, as in the thesis.

Every loop is simulated ahead for ``horizon_s`` of plant time and its
samples are released as time passes, ``speed`` times faster than real time
(after the horizon the runs start over, with a jump).  Sample ``k`` of a
loop sampled every ``ts`` seconds is stamped ``origin + k ts / speed``: the
time stamps are wall-clock UTC, so in accelerated time the plant is simply a
faster plant, and :meth:`PlantSimulator.plant_config` divides sampling
intervals and integral times by ``speed`` to match.  The origin is the start
of serving unless given earlier: the plant has then been running since, and
:meth:`PlantSimulator.history` gives the samples stamped before the start as
ingest batches, for a back-fill that the served samples continue without a
seam.

OP, PV, SP, MV and MODE of every loop are served

* over OPC UA (asyncua), one Double variable per tag with node id
  ``ns=2;s=<loop>.<SIGNAL>``, every sample written with its source time
  stamp, so a subscriber with a queue gets every sample;
* over Modbus TCP (:class:`connectors.modbus_server.ModbusRegisterServer`),
  one float32 in two holding registers per tag, holding the latest sample.

The plant configuration it writes watches OP, PV, SP and MODE of every loop; MV
(the valve position, which few plants measure) is served but not watched.
MODE is the controller's mode as Foundation Fieldbus function blocks report
it (MODE_BLK.Actual, :data:`MODE_VALUES`: 16 manual, 8 auto); one loop,
PIC-401, is put in manual by its operator for a stretch of each run
(:attr:`PlantLoop.manual`): OP is held there, and the service factor of its
windows shows it.

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
import socket
import threading
import time
from collections.abc import Callable, Collection, Iterator, Mapping
from dataclasses import dataclass, replace
from datetime import UTC
from functools import cached_property
from typing import Any, Literal

import numpy as np
from asyncua import Server, ua

from analytics.lti import TransferFunction
from analytics.scenarios import COLUMN_PROCESS, column3x3
from analytics.simulation import PIDController, SimulationResult, in_stretches
from analytics.synthetic_cases import SyntheticCase, synthetic_library
from connectors.base import ThreadedRunner
from connectors.modbus import REGISTER_COUNT, WordOrder
from connectors.modbus_server import ModbusRegisterServer

__all__ = [
    "COLUMN_LOOPS",
    "DEFAULT_MODBUS_LOOPS",
    "NAMESPACE_URI",
    "PLANT_LOOPS",
    "SIGNALS",
    "SINGLE_LOOPS",
    "WATCHED_SIGNALS",
    "PlantLoop",
    "PlantSimulator",
    "TagAddress",
]

log = logging.getLogger(__name__)

SIGNALS = ("OP", "PV", "SP", "MV", "MODE")
"""The signals served for every loop; tag ``<loop id>.<signal>``."""

WATCHED_SIGNALS = ("OP", "PV", "SP", "MODE")
"""The signals :meth:`PlantSimulator.plant_config` has the service watch (not MV: a sticky
valve's position is held between slips, which data-quality screening takes for a
compressed archive, and few plants measure it)."""

MODE_VALUES = {16.0: "manual", 8.0: "auto", 4.0: "cascade"}
"""The raw MODE values and what they mean: the mode bits of a Foundation Fieldbus
function block's MODE_BLK (FF-891 Function Block Application Process part 2; Man 0x10,
Auto 0x08, Cas 0x04), the plant file's ``mode_map``."""
MANUAL, AUTO = 16.0, 8.0

NAMESPACE_URI = "urn:loopwatch:plant-sim"
NAMESPACE_INDEX = 2
"""The index a fresh asyncua server gives the first namespace registered."""

MODBUS_LOOP_STRIDE = 10
"""Registers reserved per loop: loop ``n`` starts at ``10 n`` (OP, PV, SP, MV, MODE at +0, +2,
+4, +6, +8)."""

DEFAULT_MODBUS_LOOPS = ("FIC-105", "LIC-301")
"""Loops that :meth:`PlantSimulator.plant_config` reads over Modbus -- one sticky, one
healthy, so a fault travels that path too; the others are read over OPC UA."""


@dataclass(frozen=True)
class PlantLoop:
    """One loop of the simulated plant: its configuration entry and what it should show.

    ``source`` is the name of an :mod:`analytics.synthetic_cases` case, or
    ``"column:<i>"`` for loop ``i`` (0-based) of the 3x3 column.  ``unit`` is
    None for a loop that interacts with no other.  ``manual`` lists the
    stretches ``(start, end)`` of plant time (s from the start of each run)
    the loop spends in manual (single loops only).
    """

    id: str
    name: str
    unit: str | None
    source: str
    valve_asset: str
    importance: str
    expected: str
    ranges: tuple[tuple[str, tuple[float, float]], ...] = (
        ("op", (0.0, 100.0)), ("pv", (0.0, 100.0)),
    )
    manual: tuple[tuple[float, float], ...] = ()


SINGLE_LOOPS = (
    PlantLoop("FIC-101", "Feed flow", None, "flow-kano-S4-J2-ts1", "FV-101", "high",
              "sticky valve (Kano S=4 %, J=2 %): alarm and ticket"),
    PlantLoop("FIC-102", "Reflux flow", None, "flow-aggressive-ts1", "FV-102", "medium",
              "over-tuned controller: oscillation alarm, no ticket"),
    PlantLoop("TIC-201", "Reactor temperature", None, "temp-sine200s-ts2", "TV-201", "high",
              "upstream disturbance (200 s, 18 cycles an hour: enough to tell it from its "
              "own tuning): oscillation alarm, no ticket, no detuning"),
    PlantLoop("LIC-301", "Drum level", None, "level-noise-ts1", "LV-301", "medium", "healthy"),
    PlantLoop("FIC-105", "Steam flow", None, "flow-he-S8-J4-ts1", "FV-105", "critical",
              "sticky valve (He fs=6 %, fd=2 %): alarm and ticket"),
    PlantLoop("PIC-401", "Header pressure", None, "flow-noise-ts0.5", "PV-401", "low",
              "healthy; in manual from 30 to 75 min of each run", manual=((1800.0, 4500.0),)),
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

PLANT_LOOPS = SINGLE_LOOPS + COLUMN_LOOPS
"""Every loop of the simulated plant, in address-map order."""

UNITS = (
    {"id": "column", "name": "Ethanol-water column, 3x3 (simulated, thesis Eq. 2.10)"},
)


def _span(loop: PlantLoop, signal: str) -> float:
    low, high = dict(loop.ranges)[signal]
    return high - low


def _matrix_entry(g: TransferFunction, gain: float, speed: float) -> dict[str, Any]:
    """``gain G(speed s)`` in the plant file's ``{"num", "den", "theta"}`` form: the model
    in % of span per % of OP, in the plant's accelerated time."""
    def scaled(coefficients: tuple[float, ...]) -> list[float]:
        order = len(coefficients) - 1
        return [c / speed ** (order - k) for k, c in enumerate(coefficients)]

    return {"num": [gain * c for c in scaled(g.num)], "den": scaled(g.den),
            "theta": g.delay / speed}


def column_process(speed: float = 1.0) -> dict[str, Any]:
    """The column unit's process matrix for the plant file (``units[].process``): thesis
    Eq. 2.10 with each entry scaled from engineering units to % of span (``op`` span of
    the valve's loop over ``pv`` span of the measured loop)."""
    return {
        "loops": [loop.id for loop in COLUMN_LOOPS],
        "matrix": [[_matrix_entry(COLUMN_PROCESS[i][j],
                                  _span(COLUMN_LOOPS[j], "op") / _span(pv_loop, "pv"), speed)
                    for j in range(len(COLUMN_LOOPS))]
                   for i, pv_loop in enumerate(COLUMN_LOOPS)],
    }


@dataclass(frozen=True)
class TagAddress:
    """Where one tag is served: OPC UA node id and Modbus holding registers."""

    tag: str
    node_id: str
    modbus_address: int
    modbus_type: str
    word_order: str


@dataclass(frozen=True)
class _LoopModel:
    """What the configuration needs of a simulated loop: sampling, process type, controller
    and, for a single loop, the process it simulates (a column loop's is its unit's
    matrix)."""

    ts: float
    process_type: str
    controller: PIDController
    process: TransferFunction | None = None


def _case(name: str, samples: int) -> SyntheticCase:
    return next(c for c in synthetic_library(samples) if c.name == name)


def _column_index(loop: PlantLoop) -> int:
    return int(loop.source.split(":")[1])


def _models() -> dict[str, _LoopModel]:
    """The model of every loop of the plant (cheap: nothing is simulated)."""
    models = {}
    for loop in SINGLE_LOOPS:
        case = _case(loop.source, 100)
        models[loop.id] = _LoopModel(case.ts, case.process_type, case.controller, case.process)
    column = column3x3(sticky=(2,))
    for loop in COLUMN_LOOPS:
        controller = column.loops[_column_index(loop)].controller
        models[loop.id] = _LoopModel(column.dt, "self-regulating", controller)
    return models


def _signals(result: SimulationResult, i: int, manual: tuple[tuple[float, float], ...] = ()
             ) -> dict[str, np.ndarray]:
    in_manual = in_stretches(result.t, manual)
    return {"OP": result.op[i], "PV": result.pv[i], "SP": result.sp[i], "MV": result.mv[i],
            "MODE": np.where(in_manual, MANUAL, AUTO)}


def _simulate(horizon_s: float) -> dict[str, dict[str, np.ndarray]]:
    """Every loop's signals over ``horizon_s`` of plant time (``values[loop][signal]``)."""
    values: dict[str, dict[str, np.ndarray]] = {}
    for loop in SINGLE_LOOPS:
        ts = _case(loop.source, 100).ts
        case = replace(_case(loop.source, max(int(horizon_s / ts), 2)), manual=loop.manual)
        values[loop.id] = _signals(case.simulate(), 0, loop.manual)
    result = column3x3(sticky=(2,), duration=horizon_s).run()
    for loop in COLUMN_LOOPS:
        values[loop.id] = _signals(result, _column_index(loop))
    return values


def _watched_tags(loop_id: str) -> list[str]:
    return [f"{loop_id}.{signal}" for signal in WATCHED_SIGNALS]


def _free_port(host: str) -> int:
    """A TCP port free on ``host`` now."""
    with socket.socket() as probe:
        probe.bind((host, 0))
        return int(probe.getsockname()[1])


def _controller_config(controller: PIDController, speed: float, loop: PlantLoop
                       ) -> dict[str, Any]:
    """The DCS view of a simulated PI controller: Kc > 0 in OP % per PV % of span (the
    simulated gain is in engineering units) with an action, Ti in s."""
    action = controller.action
    if controller.kp < 0:  # a negative gain is the other action (thesis Eq. 2.12)
        action = "direct" if action == "reverse" else "reverse"
    return {
        "type": "PI",
        "Kc": abs(controller.kp) * _span(loop, "pv") / _span(loop, "op"),
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
        None serves OPC UA only.  Port 0 takes a port that is free when the
        simulator is made, so :meth:`plant_config` can name it before serving.
    speed : float
        Plant seconds per wall-clock second.
    horizon_s : float
        Plant time simulated ahead; the runs start over after it.
    origin : float or None
        UNIX time of sample 0, at or before the start of serving (None: the
        start).  Samples stamped before the start are not served; they are
        the plant's history (:meth:`history`).
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
        origin: float | None = None,
        word_order: WordOrder = "ABCD",
        clock: Callable[[], float] = time.time,
    ) -> None:
        if not (math.isfinite(speed) and speed > 0):
            raise ValueError(f"speed must be a positive number, got {speed!r}")
        if not horizon_s > 0:
            raise ValueError(f"horizon_s must be positive, got {horizon_s!r}")
        self.host = host
        self.opcua_port = opcua_port or _free_port(host)
        self.modbus_port = None if modbus_port is None else modbus_port or _free_port(host)
        self.speed = float(speed)
        self.horizon_s = horizon_s
        self.word_order = word_order
        self.clock = clock
        self.loops = PLANT_LOOPS
        self._models = _models()
        self._bad: set[str] = set()
        self._opcua: Server | None = None
        self._variables: dict[str, ua.NodeId] = {}
        self._modbus: ModbusRegisterServer | None = None
        self._released: dict[str, int] = {}
        self.origin = origin
        """UNIX time of sample 0; None until the start when not given."""
        self._releaser: asyncio.Task[None] | None = None
        self._serving = threading.Event()
        self._runner = ThreadedRunner(self.run, name="plant-sim")

    @cached_property
    def _values(self) -> dict[str, dict[str, np.ndarray]]:
        """The simulated signals, computed when first needed (the configuration needs none)."""
        return _simulate(self.horizon_s)

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
        plant serves Modbus), the others over OPC UA; every loop's
        :data:`WATCHED_SIGNALS` are watched.  Sampling intervals and integral
        times are divided by ``speed``.  Every single loop's configuration gives the
        process it is simulated with (``process_model``, % of span per % of OP, in the
        accelerated time, as a step test of the loop would give it): the Harris index
        has its dead time and a sticky valve is sized with its gain; a column loop's
        process is its unit's matrix (``units[].process``).
        """
        known = {loop.id for loop in self.loops}
        unknown = sorted(set(modbus_loops) - known)
        if unknown:
            raise ValueError(f"modbus_loops: unknown loops {unknown}; known: {sorted(known)}")
        over_modbus = set(modbus_loops) if self.modbus_port is not None else set()
        loops = []
        for loop in self.loops:
            model = self._models[loop.id]
            loops.append({
                "id": loop.id, "name": loop.name, "unit": loop.unit,
                "tags": {s.lower(): f"{loop.id}.{s}" for s in WATCHED_SIGNALS},
                "mode_map": {f"{raw:g}": name for raw, name in MODE_VALUES.items()},
                "ranges": {signal: list(span) for signal, span in loop.ranges},
                "ts": model.ts / self.speed,
                "process_type": model.process_type,
                "valve_asset": loop.valve_asset,
                "importance": loop.importance,
                "controller": _controller_config(model.controller, self.speed, loop),
                **({} if model.process is None else {"process_model": _matrix_entry(
                    model.process, _span(loop, "op") / _span(loop, "pv"), self.speed)}),
            })
        addresses = {a.tag: a for a in self.address_map()}
        over_opcua = [loop.id for loop in self.loops if loop.id not in over_modbus]
        fastest_ms = min(self.sample_interval(loop_id) for loop_id in over_opcua) * 1000
        connectors: dict[str, Any] = {"opcua": [{
            "url": self.opcua_url,
            "sampling_interval_ms": fastest_ms,
            "publishing_interval_ms": max(fastest_ms, 100.0),
            # ten seconds of samples per node: a publish held up by a busy machine (the
            # server drops a node's oldest samples once its queue is full) loses none
            "queue_size": max(10, math.ceil(10_000.0 / fastest_ms)),
            "watchdog_s": 30.0,
            "nodes": [{"tag": tag, "node_id": addresses[tag].node_id}
                      for loop_id in over_opcua for tag in _watched_tags(loop_id)],
        }]}
        if over_modbus:
            connectors["modbus"] = [self._modbus_section(sorted(over_modbus), addresses)]
        units = [{**unit, "process": column_process(self.speed)} if unit["id"] == "column"
                 else dict(unit) for unit in UNITS]
        return {"units": units, "loops": loops, "connectors": connectors}

    def _modbus_section(
        self, loop_ids: list[str], addresses: dict[str, TagAddress]
    ) -> dict[str, Any]:
        """A :class:`connectors.modbus.ModbusConnectorConfig`: one register group per loop.

        The registers hold the latest sample and the connector stamps a value
        when it polls, so it polls twice per sampling interval: every point of
        an analysis window's grid then has a value polled within half an
        interval of it, also when a poll is late.
        """
        groups = []
        for loop_id in loop_ids:
            tags = _watched_tags(loop_id)
            first = addresses[tags[0]].modbus_address
            last = addresses[tags[-1]].modbus_address
            groups.append({
                "function": "holding",
                "start": first,
                "count": last + REGISTER_COUNT["float32"] - first,
                "tags": [
                    {"tag": tag, "data_type": "float32",
                     "offset": addresses[tag].modbus_address - first,
                     "word_order": self.word_order}
                    for tag in tags
                ],
            })
        return {
            "host": self.host,
            "port": self.modbus_port,
            "poll_interval_s": min(self.sample_interval(loop_id) for loop_id in loop_ids) / 2,
            "groups": groups,
        }

    # --- the simulated signals --------------------------------------------------

    def sample_interval(self, loop_id: str) -> float:
        """Wall-clock seconds between the samples of ``loop_id`` (``ts / speed``)."""
        return self._models[loop_id].ts / self.speed

    def value(self, tag: str, k: int) -> float:
        """Sample ``k`` of ``tag`` (counted from the origin; the runs repeat after the horizon)."""
        loop_id, signal = tag.rsplit(".", 1)
        values = self._values[loop_id][signal]
        return float(values[k % len(values)])

    def sample_index(self, loop_id: str, timestamp: float) -> int:
        """The sample number of ``loop_id`` stamped ``timestamp`` (nearest)."""
        if self.origin is None:
            raise RuntimeError("the plant has not started")
        return round((timestamp - self.origin) / self.sample_interval(loop_id))

    def history(
        self, since: float, until: Mapping[str, float], *, max_samples: int = 100_000
    ) -> Iterator[list[dict[str, Any]]]:
        """The samples of each tag of ``until`` stamped from ``since`` to before ``until[tag]``.

        As ingest batches of the PI Web API shape, of at most ``max_samples``
        items, oldest first; none later than the newest sample released.

        Raises
        ------
        RuntimeError
            The plant has not started.
        KeyError
            A tag the plant does not serve.
        """
        if self.origin is None or not self._released:
            raise RuntimeError("the plant has not started")
        served = set(self.tags)
        batch: list[dict[str, Any]] = []
        room = max_samples
        for tag, before in until.items():
            if tag not in served:
                raise KeyError(f"tag {tag!r} is not served by the plant")
            loop_id, signal = tag.rsplit(".", 1)
            interval = self.sample_interval(loop_id)
            last = min(math.ceil((before - self.origin) / interval - 1e-9) - 1,
                       self._released[loop_id])
            values = self._values[loop_id][signal]
            k = max(math.ceil((since - self.origin) / interval - 1e-9), 0)
            while k <= last:
                numbers = np.arange(k, min(last + 1, k + room))
                stamps = (self.origin + numbers * interval).tolist()
                batch.append({"tag": tag, "items": [
                    {"timestamp": t, "value": v, "good": True}
                    for t, v in zip(stamps, values[numbers % len(values)].tolist(), strict=True)
                ]})
                k += len(numbers)
                room -= len(numbers)
                if room == 0:
                    yield batch
                    batch, room = [], max_samples
        if batch:
            yield batch

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
        """Start the servers and serve the sample of now (earlier ones are history)."""
        if self.origin is not None and self.origin > self.clock():
            raise ValueError(f"the origin {self.origin} is after the start {self.clock()}")
        self._values  # noqa: B018 -- simulate before serving, not in the first release
        self._opcua = await self._start_opcua()
        if self.modbus_port is not None:
            self._modbus = ModbusRegisterServer(
                self.host, self.modbus_port,
                {a.tag: (a.modbus_address, "float32", self.word_order)
                 for a in self.address_map()},
            )
            await self._modbus.start()
        now = self.clock()
        if self.origin is None:
            self.origin = now
        self._released = {loop.id: self._due(loop.id, now) - 1 for loop in self.loops}
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
                latest = max(self._released.get(loop.id, 0), 0)
                node = await folder.add_variable(
                    ua.NodeId.from_string(addresses[tag].node_id), signal,
                    ua.Variant(self.value(tag, latest), ua.VariantType.Double),
                )
                self._variables[tag] = node.nodeid
                if loop.id in self._released:  # brought back: the latest sample as served
                    await server.write_attribute_value(
                        node.nodeid, self._data_value(tag, latest, self._stamp(loop.id, latest)))
        await server.start()
        return server

    def _due(self, loop_id: str, now: float) -> int:
        """The number of the newest sample of ``loop_id`` stamped by ``now``."""
        assert self.origin is not None
        return math.floor((now - self.origin) / self.sample_interval(loop_id) + 1e-9)

    async def release(self) -> int:
        """Serve every sample due by now; returns the number of samples written."""
        assert self.origin is not None
        now = self.clock()
        written = 0
        for loop in self.loops:
            due = self._due(loop.id, now)
            for k in range(self._released[loop.id] + 1, due + 1):
                stamp = self._stamp(loop.id, k)
                for signal in SIGNALS:
                    await self._serve(f"{loop.id}.{signal}", k, stamp)
                    written += 1
            self._released[loop.id] = max(due, self._released[loop.id])
        return written

    def _stamp(self, loop_id: str, k: int) -> ua.DateTime:
        """The time stamp of sample ``k`` of ``loop_id``."""
        assert self.origin is not None
        return ua.DateTime.fromtimestamp(self.origin + k * self.sample_interval(loop_id), UTC)

    def _data_value(self, tag: str, k: int, stamp: ua.DateTime) -> ua.DataValue:
        """Sample ``k`` of ``tag`` as OPC UA serves it: its value, or a failed measurement."""
        now = ua.DateTime.now(UTC)
        if tag in self._bad:
            return ua.DataValue(
                StatusCode=ua.StatusCode(ua.UInt32(ua.StatusCodes.BadSensorFailure)),
                SourceTimestamp=stamp, ServerTimestamp=now,
            )
        return ua.DataValue(ua.Variant(self.value(tag, k), ua.VariantType.Double),
                            SourceTimestamp=stamp, ServerTimestamp=now)

    async def _serve(self, tag: str, k: int, stamp: ua.DateTime) -> None:
        if self._modbus is not None:
            if tag in self._bad:
                self._modbus.set_bad(tag)
            else:
                self._modbus.set(tag, self.value(tag, k))
        if self._opcua is not None:  # None while taken down
            await self._opcua.write_attribute_value(self._variables[tag],
                                                    self._data_value(tag, k, stamp))

    async def stop(self) -> None:
        """Stop both servers."""
        if self._modbus is not None:
            await self._modbus.stop()
            self._modbus = None
        if self._opcua is not None:
            await self._opcua.stop()
            self._opcua = None

    async def take_down(self, server: Literal["opcua", "modbus"]) -> None:
        """Stop one of the servers, as a fault; the plant runs on and the other serves on."""
        if server == "opcua":
            if self._opcua is not None:
                await self._opcua.stop()
                self._opcua = None
        elif self._modbus is not None:
            await self._modbus.stop()  # its registers keep being written

    async def bring_back(self, server: Literal["opcua", "modbus"]) -> None:
        """Start a server taken down again, on its port, serving the latest samples.

        Raises
        ------
        RuntimeError
            The server is up, or the plant serves no Modbus.
        """
        if server == "opcua":
            if self._opcua is not None:
                raise RuntimeError("the OPC UA server is up")
            self._opcua = await self._start_opcua()
        elif self._modbus is None:
            raise RuntimeError("the plant serves no Modbus")
        else:
            await self._modbus.start()  # RuntimeError if it is up

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
        self._serving.set()
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        self._serving.clear()
        if self._releaser is not None:
            self._releaser.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._releaser
            self._releaser = None
        await self.stop()

    def start_in_thread(self, timeout: float = 60.0) -> None:
        """Serve from a background thread with its own event loop; returns once serving.

        Raises
        ------
        RuntimeError
            The servers could not start (a port in use...): the reason is given.
        TimeoutError
            Not serving after ``timeout`` seconds (the thread is stopped).
        """
        self._runner.start()
        deadline = time.monotonic() + timeout
        while not self._serving.wait(0.05):
            if not self._runner.running:
                raise RuntimeError(f"the simulated plant could not start: {self._runner.error}")
            if time.monotonic() > deadline:
                self._runner.stop()
                raise TimeoutError(f"the simulated plant was not serving after {timeout:g} s")

    def stop_thread(self, timeout: float = 10.0) -> None:
        """Stop serving and join the background thread."""
        self._runner.stop(timeout)
