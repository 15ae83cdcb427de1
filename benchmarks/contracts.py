"""The service's answers on fixed inputs, recorded to compare a refactoring byte for byte.

Builds the demo plant's service on a fixed clock (a thread pool, SQLite), ingests
three hours of the simulated plant, runs the analysis rounds of its last two
hours, then records:

- every ``GET`` of ``/api/v1`` (and ``/openapi.json``) for every loop, unit,
  alarm, ticket and analysis run, plots included, and the model-check route;
- the CLI's JSON answers: ``analyze --json`` of a real window of
  ``../shared/data/plant_dev``, ``model-check --json`` and ``predict --json`` of
  a demo loop.

Run: ``.venv/bin/python benchmarks/contracts.py OUT_DIR`` writes one file per
answer; ``... OUT_DIR --compare BEFORE_DIR`` also prints the answers that differ
from an earlier recording and exits 1 if any does.  The random parts (the
bootstrap key's id, the metrics' process figures and the temporary directory's
name) are left out.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fastapi.testclient import TestClient  # noqa: E402

from connectors.plant_sim import PlantSimulator  # noqa: E402
from service.config import Settings  # noqa: E402
from service.server import build_service  # noqa: E402

KEY = "contracts-admin-key-0123456789"
T0 = 1_800_000_000.0
HISTORY_S = 3 * 3600.0
ROUND_S = 600.0
WINDOWS = ("FIC-06_w01", "FIC-06_w05", "FIC-01_w01", "LIC-01_w01", "PIC-01_w01")
"""Real windows of plant_dev for ``loopwatch analyze``: sticky (oscillating or not), healthy."""
TEMPERATURE = {
    "dt": 1.0,
    "process": {"type": "fopdt", "K": 0.4346, "tau": 27.58, "theta": 6.0},
    "controllers": [{"Kc": 10, "Ti": 10}],
    "valves": [{"model": "choudhury", "S": 4, "J": 2}],
}
"""The temperature loop of thesis section 5.5.1, for ``loopwatch predict``."""


def _ingest_history(svc: Any, plant: PlantSimulator) -> None:
    for loop in plant.loops:
        interval = plant.sample_interval(loop.id)
        n = int(HISTORY_S / interval)
        for tag in (t for t in plant.tags if t.startswith(f"{loop.id}.")):
            items = [{"timestamp": T0 - HISTORY_S + k * interval,
                      "value": plant.value(tag, k), "good": True} for k in range(n)]
            for start in range(0, n, 20_000):
                svc.state.ingest([{"tag": tag, "items": items[start:start + 20_000]}])


def _answers(client: TestClient) -> dict[str, bytes]:
    got: dict[str, bytes] = {}

    def get(path: str) -> Any:
        response = client.get(path)
        got[f"GET {path}"] = f"{response.status_code}\n".encode() + response.content
        return response.json() if response.headers.get("content-type", "").startswith(
            "application/json") else None

    get("/openapi.json")
    get("/api/v1/me")
    get("/api/v1/plant/bad-actors")
    loops = get("/api/v1/loops?limit=100")["data"]
    units = get("/api/v1/units")["data"]
    for loop in loops:
        base = f"/api/v1/loops/{loop['id']}"
        for suffix in ("", "/config", "/analyses", "/health", "/kpis", "/advice",
                       f"/data?start={T0 - 600}&end={T0}"):
            get(base + suffix)
        for kind in ("signature", "spectrum", "nyquist", "history",
                     f"trend?start={T0 - 600}&end={T0}"):
            get(f"{base}/plots/{kind}")
        response = client.post(base + "/model-check", json={})
        got[f"POST {base}/model-check"] = f"{response.status_code}\n".encode() + response.content
    for unit in units:
        for suffix in ("", "/diagnosis", "/prediction"):
            get(f"/api/v1/units/{unit['id']}{suffix}")
    for alarm in get("/api/v1/alarms")["data"]:
        get(f"/api/v1/alarms/{alarm['id']}")
    for ticket in get("/api/v1/tickets")["data"]:
        get(f"/api/v1/tickets/{ticket['id']}")
        get(f"/api/v1/tickets/{ticket['id']}/cmms")
    metrics = client.get("/api/v1/metrics").text
    got["GET /api/v1/metrics"] = "\n".join(
        line for line in metrics.splitlines()
        if line.startswith("loopwatch_") and "created" not in line).encode()
    return got


def _cli(args: list[str]) -> bytes:
    done = subprocess.run([sys.executable, "-m", "service.cli", *args], cwd=ROOT,
                          capture_output=True, timeout=900, check=False)
    return f"{done.returncode}\n".encode() + done.stdout + b"\n--stderr--\n" + done.stderr


def record() -> dict[str, bytes]:
    """Every answer, by what was asked."""
    with tempfile.TemporaryDirectory() as tmp:
        settings = Settings(database_url=f"sqlite:///{tmp}/contracts.db", api_key=KEY,
                            window_s=3600.0, buffer_horizon_s=HISTORY_S,
                            leader_lease_s=86_400.0)  # held through every round
        svc = build_service(settings, None, executor=ThreadPoolExecutor(1), clock=lambda: T0)
        plant = PlantSimulator(modbus_port=None, origin=T0 - HISTORY_S, clock=lambda: T0,
                               horizon_s=HISTORY_S + 600.0)
        _ingest_history(svc, plant)
        assert svc.scheduler is not None and svc.scheduler.election is not None
        svc.scheduler.election.poll()  # the scheduler's leadership, as its thread takes it
        svc.scheduler.sync_buffers(T0)
        for k in range(int(2 * 3600 / ROUND_S), -1, -1):
            svc.scheduler.run_round(T0 - k * ROUND_S)
        with TestClient(svc.app, headers={"X-API-Key": KEY}) as client:
            got = _answers(client)
        svc.executor.shutdown(wait=True) if svc.executor is not None else None
        svc.state.store.close()
    data = ROOT.parent / "shared" / "data" / "plant_dev"
    with tempfile.TemporaryDirectory() as tmp:
        model = Path(tmp) / "model.json"
        model.write_text(json.dumps(TEMPERATURE))
        column = Path(tmp) / "column.csv"
        runs = [["analyze", "--json", str(data / f"{w}.csv")] for w in WINDOWS]
        runs += [["model-check", "--json", str(data / "FIC-06_w01.csv")],
                 ["model-check", "--json", "--overlay", str(data / "LIC-01_w01.csv")],
                 ["predict", "--json", str(model)],
                 ["simulate", "column-2", "--out", str(column)],
                 ["unit-analyze", "--json", "--skip", "2000", str(column)]]
        for args in runs:
            got["CLI " + " ".join(Path(a).name for a in args)] = _cli(args)
    return got


def _name(question: str) -> str:
    readable = re.sub(r"[^A-Za-z0-9]+", "_", question).strip("_")[:80]
    return f"{readable}-{hashlib.sha256(question.encode()).hexdigest()[:8]}"


def _masked(body: bytes) -> bytes:
    body = re.sub(rb'"key_id":\s*"[^"]*"', b'"key_id":"*"', body)
    return re.sub(rb"/tmp/tmp\w+", b"<tmp>", body)  # the temporary directory's name


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--compare", type=Path)
    options = parser.parse_args()
    options.out.mkdir(parents=True, exist_ok=True)
    got = {question: _masked(body) for question, body in record().items()}
    (options.out / "index.json").write_text(json.dumps(
        {_name(q): q for q in sorted(got)}, indent=1))
    for question, body in got.items():
        (options.out / _name(question)).write_bytes(body)
    print(f"{len(got)} answers written to {options.out}")
    if options.compare is None:
        return 0
    before = json.loads((options.compare / "index.json").read_text())
    differ = [q for name, q in sorted(before.items(), key=lambda item: item[1])
              if q not in got or (options.compare / name).read_bytes() != got[q]]
    new = sorted(set(got) - set(before.values()))
    for question in differ:
        print(f"differs: {question}")
    for question in new:
        print(f"new: {question}")
    print(f"{len(before) - len(differ)} of {len(before)} answers identical")
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
