"""OPC UA ingest: sustained rate through one connection, and the delay to the sink.

Prints, for each setting:

1. sustained ingest of 5,000 tags changing once a second through one
   :class:`connectors.opcua.OpcUaConnector` (publishing and flushing every
   second): the CPU time of the client process per sample, and what that
   makes per second of data of 5,000 tags at 1 Hz (target: under 0.5 s,
   half of one core; median over slices of the run), with the share of one
   core used and the samples per second that reached the sink over the run;
2. the delay from a value change on the server (its source time stamp) to
   the sink call that delivers it: median and p99, for that setting, for
   1,000 tags (which the Python test server writes on time even on a busy
   machine) and for a low-latency setting (100 tags at 10 Hz, publishing and
   flushing every 100 ms).

The server is a real asyncua server in a separate process (its CPU is not
counted); the sink only records the delays, so the figures are the
connector's own cost, not the store's.

Run: ``.venv/bin/python benchmarks/connectors_opcua.py [--tags N] [--seconds S]``.
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing
import statistics
import sys
import threading
import time
from datetime import UTC, datetime
from multiprocessing.synchronize import Event
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from connectors.opcua import OpcUaConnector, OpcUaEndpointConfig  # noqa: E402
from tests.servers import free_port  # noqa: E402


def serve(port: int, n_tags: int, rate_hz: float, ready: Event, stop: Event) -> None:
    """Server process: ``n_tags`` Double variables, each written ``rate_hz`` times a second."""
    from asyncua import Server, ua

    async def main() -> None:
        server = Server()
        await server.init()
        server.set_endpoint(f"opc.tcp://127.0.0.1:{port}")
        index = await server.register_namespace("urn:loopwatch:bench")
        nodes = [
            (await server.nodes.objects.add_variable(ua.NodeId(f"T{i:05d}", index), f"T{i}", 0.0))
            .nodeid for i in range(n_tags)
        ]
        await server.start()
        ready.set()
        period, k = 1.0 / rate_hz, 0
        next_tick = time.monotonic()
        while not stop.is_set():
            k += 1
            for i, node in enumerate(nodes):
                await server.write_attribute_value(node, ua.DataValue(
                    ua.Variant(float(k + i), ua.VariantType.Double),
                    SourceTimestamp=datetime.now(UTC),
                ))
            next_tick += period
            await asyncio.sleep(max(next_tick - time.monotonic(), 0.0))
        await server.stop()

    asyncio.run(main())


class DelaySink:
    """Records, per delivered sample, the delay from its source time stamp to now."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.delays: list[np.ndarray] = []
        self.samples = 0

    def __call__(self, batch: list[dict[str, Any]]) -> None:
        now = time.time()
        stamps = np.fromiter(
            (i["timestamp"] for entry in batch for i in entry["items"]), dtype=float
        )
        with self.lock:
            self.delays.append(now - stamps)
            self.samples += stamps.size

    def take(self) -> tuple[int, np.ndarray]:
        with self.lock:
            delays, samples = self.delays, self.samples
            self.delays, self.samples = [], 0
        return samples, np.concatenate(delays) if delays else np.empty(0)


def measure(n_tags: int, rate_hz: float, interval_ms: float, seconds: float,
            slices: int) -> dict[str, float]:
    """Run server and connector; CPU per sample and core share (medians of slices), delays."""
    port = free_port()
    context = multiprocessing.get_context("spawn")
    ready, stop = context.Event(), context.Event()
    server = context.Process(target=serve, args=(port, n_tags, rate_hz, ready, stop))
    server.start()
    if not ready.wait(300):
        raise RuntimeError("the benchmark server did not start")
    sink = DelaySink()
    config = OpcUaEndpointConfig(
        url=f"opc.tcp://127.0.0.1:{port}",
        nodes=[{"tag": f"T{i:05d}", "node_id": f"ns=2;s=T{i:05d}"} for i in range(n_tags)],
        sampling_interval_ms=interval_ms, publishing_interval_ms=interval_ms,
        queue_size=max(10, int(4 * rate_hz * interval_ms / 1000)),
        flush_interval_s=interval_ms / 1000, watchdog_s=60,
    )
    connector = OpcUaConnector(config, sink)
    connector.start()
    try:
        deadline = time.monotonic() + 120
        while connector.counters.samples < n_tags:  # subscribed, initial values in
            if time.monotonic() > deadline:
                raise RuntimeError(f"no data: {connector.counters}, {connector.last_error}")
            time.sleep(0.2)
        time.sleep(3.0)  # warm up
        sink.take()
        cpu_per_sample, delays = [], []
        total_cpu = total_wall = total_samples = 0.0
        for _ in range(slices):
            cpu0, wall0 = time.process_time(), time.monotonic()
            time.sleep(seconds / slices)
            cpu, wall = time.process_time() - cpu0, time.monotonic() - wall0
            samples, slice_delays = sink.take()
            cpu_per_sample.append(cpu / samples if samples else float("inf"))
            delays.append(slice_delays)
            total_cpu, total_wall, total_samples = (
                total_cpu + cpu, total_wall + wall, total_samples + samples
            )
    finally:
        connector.stop()
        stop.set()
        server.join(60)
    counters = connector.counters  # after the stop: every sample is delivered
    all_delays = np.concatenate(delays)
    return {
        "cpu_per_sample_s": statistics.median(cpu_per_sample),
        "core_share": total_cpu / total_wall,
        "samples_per_s": total_samples / total_wall,
        "expected_per_s": n_tags * rate_hz,
        "delay_median_s": float(np.median(all_delays)),
        "delay_p99_s": float(np.percentile(all_delays, 99)),
        "samples": counters.samples,
        "delivered": counters.delivered,
        "outages": len(connector.outages),
    }


def report(title: str, result: dict[str, float]) -> None:
    print(title)
    per_sample = result["cpu_per_sample_s"]
    print(f"  client CPU per sample: {per_sample * 1e6:.1f} us, so {per_sample * 5000:.3f} s "
          f"per second of 5,000 tags at 1 Hz (target < 0.5; median of slices)")
    print(f"  share of one core used over the run: {result['core_share']:.3f}")
    print(f"  samples reaching the sink: {result['samples_per_s']:,.0f}/s "
          f"(the server is asked to write {result['expected_per_s']:,.0f}/s)")
    behind = result["samples_per_s"] < 0.95 * result["expected_per_s"]
    print(f"  delay server change -> sink call: median {result['delay_median_s'] * 1000:.0f} ms, "
          f"p99 {result['delay_p99_s'] * 1000:.0f} ms"
          + ("  [the server fell behind: its backlog dominates the delay]" if behind else ""))
    print(f"  samples {result['samples']:,}, delivered {result['delivered']:,}, "
          f"outages {result['outages']}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tags", type=int, default=5000)
    parser.add_argument("--seconds", type=float, default=30.0, help="measured time per setting")
    args = parser.parse_args()
    report(f"{args.tags} tags at 1 Hz, publishing and flushing every 1,000 ms:",
           measure(args.tags, 1.0, 1000.0, args.seconds, slices=5))
    report("1000 tags at 1 Hz, publishing and flushing every 1,000 ms:",
           measure(1000, 1.0, 1000.0, args.seconds / 2, slices=5))
    report("100 tags at 10 Hz, publishing and flushing every 100 ms:",
           measure(100, 10.0, 100.0, args.seconds / 2, slices=5))


if __name__ == "__main__":
    main()
