"""Modbus polling benchmarks: registers per second, and the delay from a register change
to the sink (issue 5, "Speed").

The register server (:class:`connectors.modbus_server.ModbusRegisterServer`)
runs on 127.0.0.1 in a thread of its own; the connector polls it from
another thread, as it would in the service.  Both share this process (and
the GIL), so the figures are a lower bound for a device on the network
that answers at once.  Run with ``.venv/bin/python benchmarks/connectors_modbus.py``;
the machine is shared: quote medians from one run.
"""

from __future__ import annotations

import asyncio
import random
import statistics
import threading
import time
from collections.abc import Coroutine
from typing import Any

from pymodbus.client import AsyncModbusTcpClient

from connectors.modbus import ModbusConnector, ModbusConnectorConfig
from connectors.modbus_server import ModbusRegisterServer

REPEATS = 5
THROUGHPUT_SECONDS = 2.0
CHANGES = 200


class ServerThread:
    """A register server on a free loopback port, serving from its own event loop."""

    def __init__(self, server: ModbusRegisterServer) -> None:
        self.server = server
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)

    def call(self, coroutine: Coroutine[Any, Any, None]) -> None:
        asyncio.run_coroutine_threadsafe(coroutine, self.loop).result()

    def __enter__(self) -> ModbusRegisterServer:
        self.thread.start()
        self.call(self.server.start())
        return self.server

    def __exit__(self, *exc_info: object) -> None:
        self.call(self.server.stop())
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join()


def float_tags(
    groups: int, registers_per_group: int
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """An address map of float32 tags filling ``groups`` blocks, and the matching groups."""
    address_map: dict[str, Any] = {}
    config_groups = []
    for g in range(groups):
        start = g * registers_per_group
        tags = []
        for offset in range(0, registers_per_group, 2):
            tag = f"T{g:03d}.{offset // 2:03d}"
            address_map[tag] = (start + offset, "float32", "ABCD")
            tags.append({"tag": tag, "offset": offset})
        config_groups.append({"start": start, "count": registers_per_group, "tags": tags})
    return address_map, config_groups


async def bare_client_rate(port: int, groups: list[dict[str, Any]]) -> float:
    """Registers per second of a bare pymodbus client reading ``groups`` back to back: the
    reference for what the connector adds (decoding, stamping, queueing, the sink thread)."""
    client = AsyncModbusTcpClient("127.0.0.1", port=port, reconnect_delay=0, retries=0)
    await client.connect()
    registers, start = 0, time.perf_counter()
    while time.perf_counter() - start < THROUGHPUT_SECONDS:
        for group in groups:
            response = await client.read_holding_registers(group["start"], count=group["count"])
            registers += len(response.registers)
    client.close()
    return registers / (time.perf_counter() - start)


def throughput(groups: int, registers_per_group: int) -> None:
    address_map, config_groups = float_tags(groups, registers_per_group)
    if registers_per_group % 2:
        raise ValueError("float32 tags fill an even number of registers")
    rates, requests, cpu, bare = [], [], [], []
    with ServerThread(ModbusRegisterServer("127.0.0.1", 0, address_map)) as server:
        config = ModbusConnectorConfig.model_validate({
            "host": "127.0.0.1", "port": server.port, "poll_interval_s": 1e-4,
            "groups": config_groups,
        })
        for _ in range(REPEATS):
            connector = ModbusConnector(config, lambda batch: None)
            connector.start()
            time.sleep(0.3)  # connected and polling
            before, start, cpu_start = connector.counters, time.perf_counter(), time.process_time()
            time.sleep(THROUGHPUT_SECONDS)
            after, elapsed = connector.counters, time.perf_counter() - start
            cpu.append((time.process_time() - cpu_start) / elapsed)
            connector.stop()
            if after.error_responses or after.outages:
                raise RuntimeError(f"the benchmark polled badly: {after}")
            rates.append((after.registers_read - before.registers_read) / elapsed)
            requests.append((after.polls - before.polls) / elapsed)
            bare.append(asyncio.run(bare_client_rate(server.port, config_groups)))
    print(
        f"  {groups:3d} group(s) x {registers_per_group:3d} registers: "
        f"median {statistics.median(rates):10,.0f} registers/s "
        f"({statistics.median(requests):6,.0f} requests/s; min {min(rates):,.0f}, "
        f"max {max(rates):,.0f}; client and server use {statistics.median(cpu):.2f} cores)\n"
        f"{'':36s}bare pymodbus client: median {statistics.median(bare):10,.0f} registers/s"
    )


class ChangeWatcher:
    """A sink that notes when each new value of one tag arrives."""

    def __init__(self, tag: str) -> None:
        self.tag = tag
        self.arrivals: dict[float, float] = {}

    def __call__(self, batch: list[dict[str, Any]]) -> None:
        now = time.time()
        for entry in batch:
            if entry["tag"] == self.tag:
                for sample in entry["items"]:
                    self.arrivals.setdefault(sample["value"], now)


def change_delay(poll_interval_s: float) -> None:
    tag = "FIC-101.PV"
    watcher = ChangeWatcher(tag)
    rng = random.Random(1)
    delays = []
    with ServerThread(ModbusRegisterServer("127.0.0.1", 0, {tag: (0, "float32", "ABCD")})) as srv:
        config = ModbusConnectorConfig.model_validate({
            "host": "127.0.0.1", "port": srv.port, "poll_interval_s": poll_interval_s,
            "groups": [{"start": 0, "count": 2, "tags": [{"tag": tag, "offset": 0}]}],
        })
        connector = ModbusConnector(config, watcher)
        connector.start()
        time.sleep(0.3)
        for k in range(1, CHANGES + 1):
            time.sleep(rng.uniform(0, poll_interval_s))  # a random phase against the polls
            changed = time.time()
            srv.set(tag, float(k))
            while float(k) not in watcher.arrivals:
                time.sleep(poll_interval_s / 20)
            delays.append(watcher.arrivals[float(k)] - changed)
        connector.stop()
    delays.sort()
    p99 = delays[int(0.99 * (len(delays) - 1))]
    median = statistics.median(delays)
    print(
        f"  poll every {poll_interval_s * 1e3:5.0f} ms: median {median * 1e3:6.1f} ms, "
        f"p99 {p99 * 1e3:6.1f} ms, max {delays[-1] * 1e3:6.1f} ms over {len(delays)} changes"
        f"  (the poll phase alone: median {poll_interval_s / 2 * 1e3:.1f} ms, "
        f"p99 {poll_interval_s * 0.99 * 1e3:.1f} ms)"
    )


def main() -> None:
    print(f"Modbus polling throughput ({REPEATS} runs of {THROUGHPUT_SECONDS:g} s, "
          "float32 tags, polls back to back):")
    throughput(1, 2)
    throughput(1, 124)
    throughput(10, 124)
    print("delay from a register change on the server to the sink:")
    for interval in (0.1, 0.01):
        change_delay(interval)


if __name__ == "__main__":
    main()
