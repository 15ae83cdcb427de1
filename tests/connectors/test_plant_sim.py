"""The simulated plant: what it serves over real OPC UA and Modbus servers, its
configuration, and the ``loopwatch plant-sim`` command."""

import argparse
import asyncio
import math
import socket
import subprocess
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from asyncua import Client
from pymodbus.client import AsyncModbusTcpClient

from analytics.lti import TransferFunction
from analytics.scenarios import COLUMN_PROCESS
from analytics.synthetic_cases import synthetic_library
from connectors.modbus import ModbusConnectorConfig, decode
from connectors.opcua import OpcUaConnector, OpcUaEndpointConfig
from connectors.plant_sim import COLUMN_LOOPS, SIGNALS, SINGLE_LOOPS, PlantSimulator
from service.analysis import analyse_window
from service.buffer import LoopBuffers
from service.commands import CliError
from service.commands.plant_sim import register
from service.config import load_plant_config, parse_plant_config
from tests.servers import free_port

pytestmark = pytest.mark.serial  # timing-sensitive: run alone, after the parallel tests

HORIZON_S = 900.0


class Clock:
    """A wall clock the test moves by hand."""

    def __init__(self, now: float) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


class Sink:
    def __init__(self) -> None:
        self.items: dict[str, list[dict[str, Any]]] = defaultdict(list)
        self.lock = threading.Lock()

    def __call__(self, batch: list[dict[str, Any]]) -> None:
        with self.lock:
            for entry in batch:
                self.items[entry["tag"]].extend(entry["items"])


def plant(**options: Any) -> PlantSimulator:
    return PlantSimulator(opcua_port=0, modbus_port=0, horizon_s=HORIZON_S, **options)


def opcua_connector(sim: PlantSimulator, sink: Sink) -> OpcUaConnector:
    section = sim.plant_config()["connectors"]["opcua"][0]
    return OpcUaConnector(OpcUaEndpointConfig.model_validate({**section, "flush_interval_s": 0.1}),
                          sink)


async def until(condition: Any, within_s: float = 15.0) -> None:
    deadline = time.monotonic() + within_s
    while not condition():
        assert time.monotonic() < deadline, "condition not met in time"
        await asyncio.sleep(0.05)


# --- the catalogue ---------------------------------------------------------------


def test_every_single_loop_is_a_labelled_case_of_the_analytics_library():
    cases = {c.name: c for c in synthetic_library(100)}
    for loop in SINGLE_LOOPS:
        case = cases[loop.source]
        assert (case.label == "stiction") == ("sticky valve" in loop.expected), loop.id


def test_in_the_column_only_the_side_draw_valve_sticks():
    sim = plant()

    def movement(tag: str) -> np.ndarray:
        return np.array([sim.value(tag, k) for k in range(600, 1800)])

    for loop in COLUMN_LOOPS:
        op, mv = movement(f"{loop.id}.OP"), movement(f"{loop.id}.MV")
        if loop.id == "AIC-502":
            # stuck most of the time while OP moves on; slips in jumps (He fs=3, fd=1)
            assert np.mean(np.diff(mv) == 0) > 0.8
            assert np.max(np.abs(np.diff(mv))) > 1.0
        else:
            np.testing.assert_array_equal(mv, op)  # a healthy valve follows OP exactly


# --- served over OPC UA ------------------------------------------------------------


def test_every_sample_arrives_over_opcua_with_its_time_stamp_and_value():
    sim = plant(speed=20.0)
    sink = Sink()
    sim.start_in_thread()  # plant and connector in threads of their own, as beside the service
    try:
        connector = opcua_connector(sim, sink)
        connector.start()
        asyncio.run(until(lambda: connector.counters.samples > 0, within_s=30))
        time.sleep(3.0)
        connector.stop()
    finally:
        sim.stop_thread()
    counters = connector.counters
    assert counters.samples == counters.delivered
    over_opcua = {n["tag"] for n in sim.plant_config()["connectors"]["opcua"][0]["nodes"]}
    assert set(sink.items) == over_opcua
    for tag, items in sink.items.items():
        loop_id = tag.split(".")[0]
        interval = sim.sample_interval(loop_id)
        numbers = [sim.sample_index(loop_id, i["timestamp"]) for i in items]
        assert sim.origin is not None
        for k, i in zip(numbers, items, strict=True):
            assert i["timestamp"] == pytest.approx(sim.origin + k * interval, abs=1e-6)
            assert i["value"] == sim.value(tag, k) and i["good"]
        # one sample per interval, none missing, from the first to the last received
        assert numbers == list(range(numbers[0], numbers[0] + len(numbers))), tag
        assert len(numbers) >= 2.5 / interval, tag


def test_the_mode_tag_over_opcua_gives_the_service_factor_exactly():
    """PIC-401 goes to manual 1800 s into the run (plant time).  Served 10 x faster from
    plant time 1740 s, its samples come through the OPC UA connector into the service's
    buffers; the analysis of a window from the first samples received to 50 s of plant
    time after the switch finds the share of its grid points whose plant time lies in
    manual, counted here from the schedule, and OP held there."""
    speed, loop_id = 10.0, "PIC-401"
    start = time.time()
    sim = PlantSimulator(opcua_port=0, modbus_port=0, horizon_s=2400.0, speed=speed,
                         origin=start - 1740.0 / speed)
    switch = start + 60.0 / speed  # wall time of plant time 1800 s
    tags = [f"{loop_id}.{s}" for s in ("OP", "PV", "SP", "MODE")]
    sink = Sink()
    sim.start_in_thread()
    try:
        connector = opcua_connector(sim, sink)
        connector.start()

        def past_the_switch() -> bool:
            with sink.lock:
                return all(any(i["timestamp"] > switch + 5.5 for i in sink.items[tag])
                           for tag in tags)

        asyncio.run(until(past_the_switch, within_s=90))
        connector.stop()
    finally:
        sim.stop_thread()
    window_start = max(min(i["timestamp"] for i in sink.items[tag]) for tag in tags) + 0.5
    assert window_start < switch - 1.0, "the connector's first samples came after the switch"
    loop = parse_plant_config(sim.plant_config()).loop(loop_id)
    assert loop.tags.mode == f"{loop_id}.MODE" and loop.mode_map is not None
    buffers = LoopBuffers(parse_plant_config({"loops": [loop.model_dump()]}), horizon_s=600)
    for tag, items in sink.items.items():
        if tag.startswith(loop_id + "."):
            buffers.append(tag, [i["timestamp"] for i in items], [i["value"] for i in items])
    window = buffers.window(loop_id, switch + 5.0 - window_start, switch + 5.0)
    assert window.mode is not None and not np.isnan(window.mode).any()
    plant_time = np.array([sim.sample_index(loop_id, t) for t in window.t]) * 0.5
    in_manual = (plant_time >= 1800.0) & (plant_time < 4500.0)
    assert 0.05 < in_manual.mean() < 0.95
    assert window.op is not None and np.ptp(window.op[in_manual]) == 0.0  # OP held
    result = analyse_window(loop.model_dump(mode="json"), window.ts, window.t, {
        "op": window.op, "pv": window.pv, "sp": window.sp, "mv": None, "mode": window.mode})
    factor = result["kpis"]["service_factor"]
    assert factor["manual"] == np.count_nonzero(in_manual) / window.t.size
    assert factor["normal"] == np.count_nonzero(~in_manual) / window.t.size
    assert any("in manual" in note for note in result["kpis"]["notes"])


def test_modbus_registers_hold_the_latest_sample_and_bad_tags_go_bad_on_both():
    start = round(time.time())
    clock = Clock(start)
    sim = plant(clock=clock, word_order="CDAB")
    sink = Sink()
    addresses = {a.tag: a.modbus_address for a in sim.address_map()}

    async def read(client: AsyncModbusTcpClient, tag: str) -> float:
        answer = await client.read_holding_registers(addresses[tag], count=2)
        return decode(answer.registers, "float32", "CDAB")

    async def scenario() -> None:
        await sim.start()
        connector = opcua_connector(sim, sink)
        task = asyncio.create_task(connector.run())
        client = AsyncModbusTcpClient("127.0.0.1", port=sim.modbus_port)
        try:
            await until(lambda: connector.counters.samples >= 21)  # subscribed: initial values
            await client.connect()
            clock.now = start + 5.2
            await sim.release()
            for signal in SIGNALS:
                tag = f"FIC-105.{signal}"  # one sample a second: the latest is number 5
                assert await read(client, tag) == np.float32(sim.value(tag, 5))
            sim.set_bad("FIC-101.PV")
            sim.set_bad("FIC-105.PV")
            clock.now = start + 7.2
            await sim.release()
            assert math.isnan(await read(client, "FIC-105.PV"))
            await until(lambda: any(i["timestamp"] == start + 7 for i in sink.items["FIC-101.PV"]))
        finally:
            client.close()
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
            await sim.stop()

    asyncio.run(scenario())
    quality = {i["timestamp"] - start: (i["value"], i["good"]) for i in sink.items["FIC-101.PV"]}
    assert quality[5.0] == (sim.value("FIC-101.PV", 5), True)
    assert quality[6.0] == quality[7.0] == (None, False)


def test_history_is_the_samples_before_the_start_and_serving_goes_on_from_it():
    start = round(time.time())
    clock = Clock(start)
    sim = plant(clock=clock, origin=start - 100)
    sink = Sink()

    async def scenario() -> list[list[dict[str, Any]]]:
        await sim.start()
        connector = opcua_connector(sim, sink)
        task = asyncio.create_task(connector.run())
        try:
            await until(lambda: connector.counters.samples >= 21)  # the initial values
            clock.now = start + 3.2
            await sim.release()
            await until(lambda: len(sink.items["FIC-101.PV"]) >= 4)
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
            await sim.stop()
        # later samples are not history: nothing stamped after the latest release
        return list(sim.history(start - 50.5, {"FIC-101.PV": start + 60, "AIC-502.OP": start},
                                max_samples=40))

    batches = asyncio.run(scenario())
    assert [sum(len(e["items"]) for e in batch) for batch in batches] == [40, 40, 40, 35]
    history: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for batch in batches:
        for entry in batch:
            history[entry["tag"]].extend(entry["items"])
    # FIC-101 (1 s): samples 50..103, to the latest released; AIC-502 (0.5 s): 99..199
    for tag, first, last in (("FIC-101.PV", 50, 103), ("AIC-502.OP", 99, 199)):
        interval = sim.sample_interval(tag.split(".")[0])
        assert [(i["timestamp"], i["value"], i["good"]) for i in history[tag]] == [
            (start - 100 + k * interval, sim.value(tag, k), True) for k in range(first, last + 1)]
    # over OPC UA the plant goes on from the sample of the start (number 100): no seam
    live = [sim.sample_index("FIC-101", i["timestamp"]) for i in sink.items["FIC-101.PV"]]
    assert live == [100, 101, 102, 103]


def test_a_server_brought_back_serves_the_latest_sample_with_its_own_time_stamp():
    # The nodes of a restarted OPC UA server start at the latest sample, stamped as that
    # sample (not the restart's time: a subscription's first notification would then store
    # an old value at a new time), and a failed measurement starts bad.
    start = round(time.time())
    clock = Clock(start)
    sim = plant(clock=clock)
    addresses = {a.tag: a.node_id for a in sim.address_map()}

    async def scenario() -> dict[str, Any]:
        await sim.start()
        try:
            await sim.take_down("opcua")
            sim.set_bad("FIC-101.PV")
            clock.now = start + 4.2  # the plant runs on: samples 1-4 released while down
            await sim.release()
            clock.now = start + 9.7  # the restart's time, after sample 9 is due
            await sim.bring_back("opcua")
            async with Client(sim.opcua_url) as client:
                return {tag: await client.get_node(addresses[tag]).read_data_value(False)
                        for tag in ("FIC-101.OP", "FIC-101.PV")}
        finally:
            await sim.stop()

    served = asyncio.run(scenario())
    op, pv = served["FIC-101.OP"], served["FIC-101.PV"]
    assert op.SourceTimestamp.timestamp() == start + 4.0  # one sample a second: number 4
    assert op.Value.Value == sim.value("FIC-101.OP", 4)
    assert pv.StatusCode.is_bad() and pv.SourceTimestamp.timestamp() == start + 4.0


def test_start_in_thread_reports_a_port_in_use():
    sim = plant()
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", sim.opcua_port))
        taken.listen()
        with pytest.raises(RuntimeError, match="the simulated plant could not start"):
            sim.start_in_thread()


def test_an_origin_after_the_start_and_a_server_up_are_refused():
    async def scenario() -> None:
        with pytest.raises(ValueError, match=r"the origin .* is after the start"):
            await plant(origin=time.time() + 60).start()
        async with plant() as sim:
            for server in ("opcua", "modbus"):
                with pytest.raises(RuntimeError, match=r"is up|already running"):
                    await sim.bring_back(server)

    asyncio.run(scenario())


# --- configuration and address map ---------------------------------------------------


def test_the_plant_configuration_is_one_the_service_and_the_connectors_accept():
    sim = plant(speed=10.0)
    config = sim.plant_config()
    plant_config = parse_plant_config(config)
    opcua = OpcUaEndpointConfig.model_validate(config["connectors"]["opcua"][0])
    modbus = ModbusConnectorConfig.model_validate(config["connectors"]["modbus"][0])
    opcua_tags = {node.tag for node in opcua.nodes}
    modbus_tags = {tag.tag for tag in modbus.tags()}
    loop_tags = {tag for loop in plant_config.loops for _, tag in loop.tags.items()}
    assert not opcua_tags & modbus_tags and opcua_tags | modbus_tags == loop_tags
    assert {t.split(".")[1] for t in loop_tags} == {"OP", "PV", "SP", "MODE"}  # not MV
    assert {t.split(".")[0] for t in modbus_tags} == {"FIC-105", "LIC-301"}
    assert modbus.poll_interval_s == pytest.approx(0.05)  # twice per sampling interval
    assert [u.id for u in plant_config.units] == ["column"]  # the single loops interact not
    assert {loop.id for loop in plant_config.loops if loop.unit == "column"} == {
        "AIC-501", "AIC-502", "TIC-503"}
    assert plant_config.loop("FIC-101").ts == pytest.approx(0.1)  # ts 1 s, 10 x faster
    assert plant_config.loop("AIC-502").controller is not None
    assert plant_config.loop("AIC-502").controller.action == "direct"  # Kp < 0, Eq. 2.12
    # Kc in OP % per PV % of span: TIC-503 moves its valve (span 450) by 0.675 units per unit
    # of PV (span 100), i.e. 0.15 % of travel per % of PV (Eq. 2.13)
    assert plant_config.loop("TIC-503").controller.Kc == pytest.approx(0.15)
    assert opcua.sampling_interval_ms == pytest.approx(50.0)  # the column: 0.5 s / 10
    for group in modbus.groups:  # each group's registers are the loop's in the map
        for tag in group.tags:
            assert group.start + tag.offset == next(
                a.modbus_address for a in sim.address_map() if a.tag == tag.tag)


def test_the_column_process_matrix_is_thesis_eq_2_10_in_percent_of_span_and_plant_time():
    speed = 10.0
    unit = parse_plant_config(plant(speed=speed).plant_config()).units[0]
    assert unit.process is not None and unit.process.loops == [loop.id for loop in COLUMN_LOOPS]
    omega = np.array([0.01, 0.1, 1.0])  # rad/s of the accelerated plant: G(j omega / speed)
    op_span = [dict(loop.ranges)["op"][1] - dict(loop.ranges)["op"][0] for loop in COLUMN_LOOPS]
    for i, row in enumerate(unit.process.matrix):
        for j, entry in enumerate(row):
            assert entry is not None
            served = TransferFunction(tuple(entry["num"]), tuple(entry["den"]), entry["theta"])
            # % of PV span (100) per % of OP span: the engineering gain times span_op / 100
            np.testing.assert_allclose(
                served.frequency_response(omega),
                op_span[j] / 100.0 * COLUMN_PROCESS[i][j].frequency_response(omega / speed),
                rtol=1e-12)


def test_the_address_map_gives_every_tag_its_own_node_and_registers():
    sim = plant()
    rows = sim.address_map()
    assert [r.tag for r in rows] == sim.tags and len(rows) == 5 * 9
    assert len({r.node_id for r in rows}) == len(rows)
    registers = [reg for r in rows for reg in (r.modbus_address, r.modbus_address + 1)]
    assert len(set(registers)) == len(registers)
    text = sim.format_address_map()
    assert "AIC-502.MV     ns=2;s=AIC-502.MV" in text


def test_port_0_takes_free_ports_the_configuration_names():
    sim = plant()
    assert 0 not in (sim.opcua_port, sim.modbus_port) and sim.opcua_port != sim.modbus_port
    config = sim.plant_config()["connectors"]
    assert config["opcua"][0]["url"] == f"opc.tcp://127.0.0.1:{sim.opcua_port}"
    assert config["modbus"][0]["port"] == sim.modbus_port


def test_unknown_loops_for_modbus_are_refused():
    with pytest.raises(ValueError, match=r"modbus_loops: unknown loops \['XIC-9'\]"):
        plant().plant_config(modbus_loops=["XIC-9"])


# --- loopwatch plant-sim ----------------------------------------------------------


def command(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="loopwatch")
    register(parser.add_subparsers(dest="command"))
    return parser.parse_args(["plant-sim", *argv])


def test_print_the_map_and_write_the_configuration(tmp_path, capsys):
    out = tmp_path / "plant.yaml"
    args = command(["--print-map", "--config-out", str(out), "--duration", "0",
                    "--horizon", "600", "--speed", "5", "--opcua-port", "4841"])
    assert args.handler(args) == 0
    printed = capsys.readouterr().out
    assert "opc.tcp://127.0.0.1:4841" in printed and "FIC-101.PV" in printed
    config = load_plant_config(out)
    assert len(config.loops) == 9 and config.loop("FIC-101").ts == pytest.approx(0.2)
    assert config.connectors["opcua"][0]["url"] == "opc.tcp://127.0.0.1:4841"


@pytest.mark.parametrize(("argv", "message"), [
    (["--speed", "0"], "--speed must be a positive number, got 0.0"),
    (["--speed", "nan"], "--speed must be a positive number"),
    (["--opcua-port", "70000"], "--opcua-port must be a TCP port 1-65535, got 70000"),
    (["--duration", "-1"], "--duration must be 0 or more seconds"),
    (["--config-out", "/no/such/dir/plant.yaml", "--duration", "0", "--horizon", "600"],
     "/no/such/dir/plant.yaml: cannot write"),
])
def test_bad_options_are_user_errors(argv, message):
    args = command(argv)
    with pytest.raises(CliError, match=message):
        args.handler(args)


def test_the_command_serves_until_its_duration_is_over():
    port = free_port()
    args = command(["--opcua-port", str(port), "--modbus-port", "0", "--horizon", "600",
                    "--duration", "4"])
    serving = threading.Thread(target=args.handler, args=(args,))
    serving.start()

    async def read_a_value() -> float:
        deadline = time.monotonic() + 10
        while True:
            try:
                async with Client(f"opc.tcp://127.0.0.1:{port}") as client:
                    return float(await client.get_node("ns=2;s=FIC-101.PV").read_value())
            except OSError:
                assert time.monotonic() < deadline, "the plant never came up"
                await asyncio.sleep(0.3)

    value = asyncio.run(read_a_value())
    serving.join(30)
    assert not serving.is_alive()
    assert 40.0 < value < 60.0  # the feed flow around its 51 % set point


def test_the_command_imports_nothing_else_of_the_service():
    code = (
        "import sys, service.commands.plant_sim\n"
        "extra = sorted(m for m in sys.modules if m.startswith('service.')"
        " and m not in ('service.commands', 'service.commands.plant_sim'))\n"
        "assert not extra, extra\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=Path(__file__).parents[2])
