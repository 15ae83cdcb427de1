"""Service core: ingest rate, API latency under concurrent clients, analysis throughput.

Prints, in one run:

1. samples per second pushed through ``POST /api/v1/ingest`` (a real uvicorn
   server on loopback, batches of 20 tags x 500 samples) into SQLite and into
   PostgreSQL (a throw-away cluster, as in the tests);
2. latency of ``GET /api/v1/loops?limit=100`` with 2,000 configured loops
   (each with an analysis run) under 20 concurrent clients: median and p99;
3. analyses per second of one-hour windows (3,600 samples) with the local
   process pool of 2 workers.

Run: ``.venv/bin/python benchmarks/service.py`` (needs PostgreSQL's initdb
for the second figure of 1; skipped with a note otherwise).
"""

from __future__ import annotations

import sys
import tempfile
import threading
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from pathlib import Path

import httpx2 as httpx
import numpy as np
import uvicorn

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from analytics.synthetic_cases import synthetic_library  # noqa: E402
from service.analysis import analyse_window  # noqa: E402
from service.config import PlantConfig, Settings  # noqa: E402
from service.server import build_service  # noqa: E402
from service.store.models import AnalysisRun  # noqa: E402
from tests.servers import free_port, postgres_server  # noqa: E402

KEY = "benchmark-admin-key-0123456789"
T0 = 1_700_000_000.0


def plant(n_loops: int) -> PlantConfig:
    return PlantConfig.model_validate({"loops": [
        {"id": f"L{i:05d}", "ts": 1.0, "tags": {"op": f"L{i:05d}.OP", "pv": f"L{i:05d}.PV"}}
        for i in range(n_loops)
    ]})


class Server:
    """The service's app on a real uvicorn server in a thread."""

    def __init__(self, app: object) -> None:
        self.port = free_port()
        config = uvicorn.Config(app, host="127.0.0.1", port=self.port, log_level="warning")
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, daemon=True)

    def __enter__(self) -> str:
        self.thread.start()
        while not self.server.started:
            time.sleep(0.05)
        return f"http://127.0.0.1:{self.port}"

    def __exit__(self, *_: object) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=10)


def ingest_rate(database_url: str, label: str, batches: int = 20) -> None:
    settings = Settings(database_url=database_url, api_key=KEY)
    svc = build_service(settings, plant(10), executor=ThreadPoolExecutor(1), clock=lambda: T0)
    tags = [tag for loop in svc.state.registry.plant.loops for _, tag in loop.tags.items()]
    samples = 0
    with Server(svc.app) as url, httpx.Client(base_url=url, headers={"X-API-Key": KEY},
                                              timeout=60) as client:
        t0 = time.perf_counter()
        for b in range(batches):
            times = T0 - 86_400 + b * 500 + np.arange(500)
            batch = [{"tag": tag, "items": [{"timestamp": float(t), "value": float(k % 17)}
                                            for k, t in enumerate(times)]} for tag in tags]
            response = client.post("/api/v1/ingest", json=batch)
            assert response.status_code == 200, response.text
            samples += response.json()["stored"]
        elapsed = time.perf_counter() - t0
    svc.state.store.close()
    print(f"  {label:11s} {samples / elapsed:9.0f} samples/s "
          f"({samples} samples in {batches} batches of {len(tags)} tags x 500)")


def api_latency(n_loops: int = 2000, clients: int = 20, requests_each: int = 25) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        # one key for all clients: the per-key rate limit (20/s, burst 100) would answer 429
        settings = Settings(database_url=f"sqlite:///{tmp}/bench.db", api_key=KEY,
                            rate_limit_per_s=1e6, rate_limit_burst=1_000_000)
        svc = build_service(settings, plant(n_loops), executor=ThreadPoolExecutor(1),
                            clock=lambda: T0)
        with svc.state.store.session() as session:
            session.add_all(AnalysisRun(loop_id=f"L{i:05d}", started_at=T0, status="ok",
                                        oscillating=bool(i % 3 == 0), verdict="no_stiction",
                                        confidence=0.5, health=float(i % 100))
                            for i in range(n_loops))
        latencies: list[float] = []
        lock = threading.Lock()

        def client_run(url: str) -> None:
            with httpx.Client(base_url=url, headers={"X-API-Key": KEY}, timeout=60) as client:
                for _ in range(requests_each):
                    t0 = time.perf_counter()
                    response = client.get("/api/v1/loops", params={"limit": 100})
                    elapsed = time.perf_counter() - t0
                    assert response.status_code == 200, response.text
                    with lock:
                        latencies.append(elapsed)

        with Server(svc.app) as url:
            threads = [threading.Thread(target=client_run, args=(url,)) for _ in range(clients)]
            t0 = time.perf_counter()
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            wall = time.perf_counter() - t0
        svc.state.store.close()
    ms = np.array(latencies) * 1e3
    print(f"  {n_loops} loops, {clients} clients x {requests_each} requests: median "
          f"{np.median(ms):.0f} ms, p99 {np.percentile(ms, 99):.0f} ms, "
          f"{len(ms) / wall:.1f} requests/s")


def analysis_throughput(n_windows: int = 24, workers: int = 2) -> None:
    cases = [c for c in synthetic_library(3600) if c.name.startswith("flow-")]
    windows = []
    for case in cases:
        r = case.simulate()
        windows.append(({"id": case.name, "process_type": case.process_type}, case.ts, r.t,
                        {"op": r.op[0], "pv": r.pv[0], "sp": r.sp[0], "mv": None}))
    jobs = [windows[k % len(windows)] for k in range(n_windows)]
    with ProcessPoolExecutor(workers) as pool:
        list(pool.map(analyse_window, *zip(*jobs[:workers], strict=True)))  # warm up (numba)
        t0 = time.perf_counter()
        list(pool.map(analyse_window, *zip(*jobs, strict=True)))
        elapsed = time.perf_counter() - t0
    print(f"  {n_windows} one-hour windows (3,600 samples, a mix of sticky and healthy flow "
          f"loops) on {workers} worker processes: {n_windows / elapsed:.1f} loops/s")


if __name__ == "__main__":
    print("== Ingest through POST /api/v1/ingest ==")
    with tempfile.TemporaryDirectory() as tmp:
        ingest_rate(f"sqlite:///{tmp}/bench.db", "SQLite")
    try:
        with postgres_server() as url:
            ingest_rate(url, "PostgreSQL")
    except BaseException as exc:  # pytest.skip raises a BaseException subclass
        print(f"  PostgreSQL  skipped: {exc}")
    print("== API latency ==")
    api_latency()
    print("== Analysis throughput ==")
    analysis_throughput()
