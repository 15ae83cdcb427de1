"""Load: historians push while dashboards poll; rate, latency, memory, errors, lost samples.

A real ``loopwatch serve`` process runs on a free loopback port with a plant
of ``--loops`` loops (OP, PV, SP tags).  For ``--duration`` seconds:

* ``--historians`` clients (one API key each) push batches back to back
  through ``POST /api/v1/ingest``: ``--tags`` tags x ``--samples`` samples,
  every sample new (each client owns its tags and advances its own clock);
* ``--dashboards`` clients (one viewer key each) poll every
  ``--poll-s`` what the dashboard asks for: the loop list, the bad actors,
  the alarms and one loop's data;
* ``--model-checks`` clients (one viewer key each) run model checks back to
  back (``POST /api/v1/loops/{id}/model-check``) on the first
  :data:`CHECKED_LOOPS` loops, which get an hour of a simulated loop (a
  first-order process under PI control, ending now) before the clock starts.

Issue 20's scenario, 2,000 loops with 20 dashboards while historians push and
2 clients run model checks::

    .venv/bin/python benchmarks/load.py --loops 2000 --dashboards 20 --model-checks 2 \
        --repeat 1 --duration 60

Printed per run and as the median of ``--repeat`` runs: the sustained
ingest rate (samples acknowledged per second), the latency of ingest
batches, of dashboard requests and of model checks (p50 and p99), the server's memory
growth from the end of the warm-up to the end (RSS), and the errors: non-2xx
answers by status, 5xx, and lost samples (acknowledged as stored but not in
the store; the service's own books must also balance).  Everything runs on
127.0.0.1 and stops by itself.

Run: ``.venv/bin/python benchmarks/load.py`` (SQLite), add ``--store
postgresql`` for a throw-away PostgreSQL cluster (needs initdb).
"""

from __future__ import annotations

import argparse
import http.client
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from sqlalchemy import create_engine, func, select

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.store.db import make_engine  # noqa: E402
from service.store.models import Sample  # noqa: E402
from tests.servers import free_port, postgres_server  # noqa: E402

ADMIN = "load-benchmark-admin-key-0123456789"
WARM_UP_S = 2.0
CHECKED_LOOPS = 4
"""Loops with an hour of recent data for the model-check clients."""
BACKGROUND = ("ingest", "model check")
"""Request kinds that are not the dashboard's."""


@dataclass
class Tally:
    """What the clients saw (each thread has its own; merged at the end)."""

    latencies: dict[str, list[float]] = field(default_factory=dict)
    ends: dict[str, list[float]] = field(default_factory=dict)  # time.monotonic() of each
    statuses: Counter[int] = field(default_factory=Counter)
    stored: int = 0  # samples the service said it stored
    accepted: int = 0  # stored + already stored + spooled
    failures: Counter[str] = field(default_factory=Counter)

    def add(self, other: Tally) -> None:
        for kind, values in other.latencies.items():
            self.latencies.setdefault(kind, []).extend(values)
            self.ends.setdefault(kind, []).extend(other.ends.get(kind, []))
        self.statuses.update(other.statuses)
        self.stored += other.stored
        self.accepted += other.accepted
        self.failures.update(other.failures)


class Client:
    """One keep-alive HTTP connection with a key, timing every request."""

    def __init__(self, port: int, key: str, tally: Tally) -> None:
        self.port, self.key, self.tally = port, key, tally
        self.connection = http.client.HTTPConnection("127.0.0.1", port, timeout=60)

    def request(self, kind: str, method: str, path: str, body: Any = None) -> Any:
        data = None if body is None else json.dumps(body).encode()
        headers = {"X-API-Key": self.key, "Content-Type": "application/json"}
        start = time.perf_counter()
        try:
            self.connection.request(method, path, body=data, headers=headers)
            response = self.connection.getresponse()
            payload = response.read()
        except (OSError, http.client.HTTPException) as exc:
            self.tally.failures[type(exc).__name__] += 1
            self.connection.close()
            self.connection = http.client.HTTPConnection("127.0.0.1", self.port, timeout=60)
            return None
        self.tally.latencies.setdefault(kind, []).append(time.perf_counter() - start)
        self.tally.ends.setdefault(kind, []).append(time.monotonic())
        self.tally.statuses[response.status] += 1
        return json.loads(payload) if response.status < 300 and payload else None


def plant_file(path: Path, loops: int) -> list[str]:
    """A plant of ``loops`` loops; the tags, in order."""
    entries = [{"id": f"L{i:04d}", "unit": "u1", "ts": 1.0,
                "ranges": {"op": [0, 100], "pv": [0, 100]},
                "tags": {s: f"L{i:04d}.{s.upper()}" for s in ("op", "pv", "sp")}}
               for i in range(loops)]
    path.write_text(yaml.safe_dump({"units": [{"id": "u1", "name": "load"}], "loops": entries}))
    return [tag for e in entries for tag in e["tags"].values()]


def rss_mib(pid: int) -> float:
    """Resident memory of a process, MiB."""
    status = Path(f"/proc/{pid}/status").read_text()
    match = re.search(r"VmRSS:\s+(\d+) kB", status)
    return int(match.group(1)) / 1024 if match else float("nan")


@contextmanager
def server(database_url: str, config: Path, analysis_interval_s: float
           ) -> Iterator[tuple[subprocess.Popen[bytes], int]]:
    """``loopwatch serve`` on a free loopback port: the process and its port."""
    port = free_port()
    env = {**os.environ, "LOOPWATCH_DATABASE_URL": database_url, "LOOPWATCH_API_KEY": ADMIN,
           "LOOPWATCH_ANALYSIS_INTERVAL_S": str(analysis_interval_s),
           "LOOPWATCH_RATE_LIMIT_PER_S": "100000", "LOOPWATCH_RATE_LIMIT_BURST": "100000"}
    process = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "serve", "--config", str(config),
         "--port", str(port)],
        env=env, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                connection = http.client.HTTPConnection("127.0.0.1", port, timeout=2)
                connection.request("GET", "/healthz")
                if connection.getresponse().status == 200:
                    break
            except OSError:
                pass
            if time.monotonic() > deadline or process.poll() is not None:
                raise RuntimeError("loopwatch serve did not start")
            time.sleep(0.2)
        yield process, port
    finally:
        process.terminate()
        process.wait(timeout=30)


def make_key(port: int, role: str, name: str) -> str:
    tally = Tally()
    answer = Client(port, ADMIN, tally).request("keys", "POST", "/api/v1/keys",
                                                {"name": name, "role": role})
    return str(answer["key"])


def historian(port: int, key: str, tags: list[str], samples: int, start: float,
              stop: threading.Event, tally: Tally) -> None:
    client = Client(port, key, tally)
    t = start
    while not stop.is_set():
        batch = [{"tag": tag, "items": [{"timestamp": t + k, "value": float(k % 97)}
                                        for k in range(samples)]} for tag in tags]
        report = client.request("ingest", "POST", "/api/v1/ingest", batch)
        if report is not None:
            tally.stored += report["stored"]
            tally.accepted += (report["stored"] + report["already_stored"]
                               + report.get("spooled", 0))
        t += samples


def recent_hour(loop: int, end: float) -> list[dict[str, Any]]:
    """An hour of a first-order process (K 1.5, tau 30 s) under PI control, ending at
    ``end``, with set-point steps every 10 min and measurement noise: an ingest batch."""
    rng = np.random.default_rng(loop)
    n = 3600
    sp = 50.0 + 10.0 * np.sign(np.sin(2 * np.pi * np.arange(n) / 1200.0))
    op, pv = np.empty(n), np.empty(n)
    x, integral = 50.0, 0.0
    for k in range(n):
        pv[k] = x + rng.normal(0.0, 0.2)
        error = sp[k] - pv[k]
        integral += error
        op[k] = float(np.clip(50.0 + 0.6 * error + 0.6 * integral / 20.0, 0.0, 100.0))
        x += (1.5 * (op[k] - 50.0) + 50.0 - x) / 30.0
    t = end - n + np.arange(n)
    return [{"tag": f"L{loop:04d}.{name}",
             "items": [{"timestamp": float(a), "value": float(b)}
                       for a, b in zip(t, v, strict=True)]}
            for name, v in (("OP", op), ("PV", pv), ("SP", sp))]


def model_checker(port: int, key: str, seed: int, stop: threading.Event,
                  tally: Tally) -> None:
    client = Client(port, key, tally)
    loop = seed
    while not stop.is_set():
        client.request("model check", "POST",
                       f"/api/v1/loops/L{loop % CHECKED_LOOPS:04d}/model-check")
        loop += 1


def dashboard(port: int, key: str, loops: int, poll_s: float, seed: int,
              stop: threading.Event, tally: Tally) -> None:
    client = Client(port, key, tally)
    rng = np.random.default_rng(seed)
    while not stop.is_set():
        began = time.monotonic()
        client.request("loops", "GET", "/api/v1/loops?limit=100")
        client.request("bad-actors", "GET", "/api/v1/plant/bad-actors")
        client.request("alarms", "GET", "/api/v1/alarms")
        loop = f"L{int(rng.integers(loops)):04d}"
        client.request("loop data", "GET", f"/api/v1/loops/{loop}/data?max_points=500")
        stop.wait(max(0.0, poll_s - (time.monotonic() - began)))


def metric(port: int, name: str) -> float:
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    connection.request("GET", "/metrics", headers={"X-API-Key": ADMIN})
    text = connection.getresponse().read().decode()
    return sum(float(v) for v in re.findall(rf"^{name}(?:{{[^}}]*}})? (\S+)$", text, re.M))


def one_run(args: argparse.Namespace, database_url: str, workdir: Path) -> dict[str, float]:
    config = workdir / "plant.yaml"
    tags = plant_file(config, args.loops)
    with server(database_url, config, args.analysis_interval) as (process, port):
        keys_h = [make_key(port, "historian", f"historian {i}") for i in range(args.historians)]
        keys_d = [make_key(port, "viewer", f"dashboard {i}") for i in range(args.dashboards)]
        keys_m = [make_key(port, "viewer", f"model check {i}")
                  for i in range(args.model_checks)]
        prefilled = 0
        if keys_m:
            now = time.time()
            prefill = Client(port, ADMIN, Tally()).request(
                "prefill", "POST", "/api/v1/ingest",
                [entry for loop in range(min(CHECKED_LOOPS, args.loops))
                 for entry in recent_hour(loop, now)])
            prefilled = prefill["stored"]
        stop = threading.Event()
        clients = args.historians + args.dashboards
        tallies = [Tally() for _ in range(clients + args.model_checks)]
        start = time.time() - 7 * 86400
        threads = [
            threading.Thread(target=historian, args=(
                port, key, tags[i::args.historians][:args.tags], args.samples,
                start, stop, tallies[i]))
            for i, key in enumerate(keys_h)
        ] + [
            threading.Thread(target=dashboard, args=(
                port, key, args.loops, args.poll_s, i, stop, tallies[args.historians + i]))
            for i, key in enumerate(keys_d)
        ] + [
            threading.Thread(target=model_checker, args=(port, key, i, stop, tallies[clients + i]))
            for i, key in enumerate(keys_m)
        ]
        began = time.monotonic()
        for thread in threads:
            thread.start()
        time.sleep(WARM_UP_S)
        rss_start = rss_mib(process.pid)
        accepted_at_warm_up = sum(t.accepted for t in tallies)
        time.sleep(max(0.0, args.duration - WARM_UP_S))
        rss_end = rss_mib(process.pid)
        accepted_at_end = sum(t.accepted for t in tallies)
        stop.set()
        for thread in threads:
            thread.join(timeout=120)
        elapsed = time.monotonic() - began
        total = Tally()
        for tally in tallies:
            total.add(tally)
        received = metric(port, "loopwatch_samples_received_total")
        books = (metric(port, "loopwatch_samples_stored_total")
                 + metric(port, "loopwatch_samples_already_stored_total")
                 + metric(port, "loopwatch_samples_refused_total")
                 + metric(port, "loopwatch_samples_spooled_total")
                 - metric(port, "loopwatch_samples_unspooled_total"))
    engine = make_engine(database_url) if database_url.startswith("sqlite") else create_engine(
        database_url)
    with engine.connect() as connection:
        in_store = int(connection.scalar(select(func.count()).select_from(Sample)) or 0)
    engine.dispose()
    ingest = np.array(total.latencies.get("ingest", [np.nan]))
    reads = np.concatenate([np.array(v) for k, v in total.latencies.items()
                            if k not in BACKGROUND] or [np.array([np.nan])])
    checks = np.array(total.latencies.get("model check", [np.nan]))
    errors = {status: n for status, n in total.statuses.items() if status >= 300}
    result = {
        "ingest samples/s": (accepted_at_end - accepted_at_warm_up)
                            / max(args.duration - WARM_UP_S, 1e-9),
        "batches": float(ingest.size),
        "ingest p50 ms": float(np.median(ingest) * 1e3),
        "ingest p99 ms": float(np.percentile(ingest, 99) * 1e3),
        "dashboard requests": float(reads.size),
        "dashboard p50 ms": float(np.median(reads) * 1e3),
        "dashboard p99 ms": float(np.percentile(reads, 99) * 1e3),
        "model checks": float(np.isfinite(checks).sum()),
        "model check p50 ms": float(np.median(checks) * 1e3),
        "RSS growth MiB": rss_end - rss_start,
        "RSS end MiB": rss_end,
        "non-2xx": float(sum(errors.values())),
        "5xx": float(sum(n for s, n in errors.items() if s >= 500)),
        "connection errors": float(sum(total.failures.values())),
        "lost samples": float(total.stored + prefilled - in_store),
        "books off by": received - books,
    }
    print(f"  run: {elapsed:.1f} s, statuses {dict(sorted(total.statuses.items()))}, "
          f"failures {dict(total.failures)}")
    for kind, values in sorted(total.latencies.items()):
        print(f"    {kind:<11} n={len(values):6d}  p50 {np.median(values) * 1e3:7.1f} ms"
              f"  p99 {np.percentile(values, 99) * 1e3:7.1f} ms")
    if args.timeline:
        print_timeline(total, began, args.timeline)
    return result


def print_timeline(total: Tally, began: float, slice_s: float) -> None:
    """The dashboard's requests answered in each ``slice_s`` of the run: count, p50, p99."""
    kinds = [k for k in total.latencies if k not in BACKGROUND]
    ends = np.concatenate([np.array(total.ends[k]) for k in kinds]) - began
    values = np.concatenate([np.array(total.latencies[k]) for k in kinds]) * 1e3
    print("    dashboard by time (s from the clients' start: n, p50, p99 ms):")
    for lo in np.arange(0.0, float(ends.max(initial=0.0)) + slice_s, slice_s):
        inside = values[(ends >= lo) & (ends < lo + slice_s)]
        if inside.size:
            print(f"      {lo:5.0f}-{lo + slice_s:<5.0f} n={inside.size:5d}  "
                  f"p50 {np.median(inside):7.1f}  p99 {np.percentile(inside, 99):7.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--historians", type=int, default=4)
    parser.add_argument("--dashboards", type=int, default=8)
    parser.add_argument("--duration", type=float, default=20.0, help="seconds per run")
    parser.add_argument("--loops", type=int, default=100)
    parser.add_argument("--tags", type=int, default=50, help="tags per batch")
    parser.add_argument("--samples", type=int, default=20, help="samples per tag per batch")
    parser.add_argument("--poll-s", type=float, default=1.0, help="dashboard poll interval")
    parser.add_argument("--model-checks", type=int, default=0,
                        help="clients running model checks back to back")
    parser.add_argument("--analysis-interval", type=float, default=3600.0)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--timeline", type=float, default=0.0, metavar="S",
                        help="also print the dashboard's latency per S seconds of each run")
    parser.add_argument("--store", choices=("sqlite", "postgresql"), default="sqlite")
    args = parser.parse_args()
    if not (0 < args.duration <= 600
            and args.historians + args.dashboards + args.model_checks <= 200):
        parser.error("keep the load bounded: --duration up to 600 s, at most 200 clients")
    print(f"load: {args.historians} historians x {args.tags} tags x {args.samples} samples, "
          f"{args.dashboards} dashboards polling every {args.poll_s:g} s, "
          f"{args.model_checks} model-check clients, {args.loops} loops, "
          f"{args.duration:g} s x {args.repeat}, {args.store}")
    runs = []
    with ExitStack() as stack:
        server_url = (stack.enter_context(postgres_server()) if args.store == "postgresql"
                      else None)
        for run in range(args.repeat):
            workdir = Path(stack.enter_context(tempfile.TemporaryDirectory()))
            if server_url is None:
                url = f"sqlite:///{workdir / 'load.db'}"
            else:
                admin = create_engine(server_url, isolation_level="AUTOCOMMIT")
                with admin.connect() as connection:
                    connection.exec_driver_sql(f"CREATE DATABASE load_{run}")
                admin.dispose()
                url = server_url.rsplit("/", 1)[0] + f"/load_{run}"
            runs.append(one_run(args, url, workdir))
    print(f"median of {len(runs)} runs:")
    for name in runs[0]:
        print(f"  {name:<20} {statistics.median(r[name] for r in runs):12.1f}")


if __name__ == "__main__":
    main()
