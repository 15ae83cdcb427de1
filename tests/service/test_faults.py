"""Faults: the store goes away and comes back, the service is killed, a worker dies or hangs.

The store outage is real: on PostgreSQL the test database stops accepting
connections and its sessions are terminated (what a server restart or a
failover does to the service); on SQLite the database and WAL files are made
immutable (``chattr +i``), so every write fails with ``disk I/O error`` while
reads go on.  After every fault the books are checked: each sample received
is stored, was already stored, is refused with a reason, or waits in the
spool (:meth:`service.runtime.AppState.accounting`), and the store holds
exactly the samples the books say.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from fastapi.testclient import TestClient
from sqlalchemy import create_engine, func, select, text
from sqlalchemy.engine import make_url

from service.analysis import analyse_window
from service.config import Settings
from service.executors import end_executor
from service.server import Service, build_service
from service.store.db import Store
from service.store.models import AnalysisRun, Sample, UnitAnalysisRun
from tests.servers import free_port, require
from tests.service.test_api import ADMIN, T0, plant, simulated_batch

pytestmark = pytest.mark.serial  # timing-sensitive: run alone, after the parallel tests

TAGS = ("FIC-1.OP", "FIC-1.PV", "FIC-2.PV")


def batch(first: float, count: int, value: float = 0.0) -> list[dict[str, Any]]:
    """``count`` samples of each of :data:`TAGS`, one a second from ``first``."""
    return [{"tag": tag, "items": [{"timestamp": first + k, "value": value + k + i}
                                   for k in range(count)]}
            for i, tag in enumerate(TAGS)]


def stored_samples(store: Store) -> dict[tuple[str, float], float | None]:
    with store.session() as session:
        return {(tag, t): v for tag, t, v in session.execute(
            select(Sample.tag, Sample.time, Sample.value))}


def assert_books_balance(svc: Service, store: Store) -> None:
    """received = stored + already stored + refused + spooled, and the store agrees."""
    books = svc.state.accounting()
    assert books.balanced, books
    assert books.spooled == svc.state.spool.samples
    with store.session() as session:
        assert session.scalar(select(func.count()).select_from(Sample)) == books.stored


@contextmanager
def store_outage(store: Store, request: pytest.FixtureRequest) -> Iterator[None]:
    """Make the store unreachable (PostgreSQL) or unwritable (SQLite) until the block ends."""
    url = make_url(store.url)
    if store.dialect == "postgresql":
        admin = create_engine(url.set(database="postgres"), isolation_level="AUTOCOMMIT")
        database = url.database

        def allow(allowed: bool) -> None:
            with admin.connect() as connection:
                connection.execute(text(
                    f'ALTER DATABASE "{database}" ALLOW_CONNECTIONS {str(allowed).lower()}'))
                if not allowed:
                    connection.execute(text(
                        "SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
                        "WHERE datname = :name"), {"name": database})

        allow(False)
        try:
            yield
        finally:
            allow(True)
            admin.dispose()
        return
    assert url.database is not None
    files = [p for p in (Path(url.database), Path(url.database + "-wal")) if p.exists()]
    made = subprocess.run(["chattr", "+i", *map(str, files)], capture_output=True, text=True)
    require(made.returncode == 0, f"chattr +i cannot make the SQLite file unwritable here: "
                                  f"{made.stderr.strip()}")
    try:
        yield
    finally:
        subprocess.run(["chattr", "-i", *map(str, files)], check=True)


def new_key(client: TestClient, role: str) -> dict[str, str]:
    response = client.post("/api/v1/keys", json={"name": role, "role": role},
                           headers={"X-API-Key": ADMIN})
    assert response.status_code == 201, response.text
    return {"X-API-Key": response.json()["key"]}


def test_ingest_rides_out_a_store_outage_and_loses_nothing(make_service, store, request):
    svc = make_service(spool_retry_s=0.2)
    client = TestClient(svc.app)
    historian, viewer = new_key(client, "historian"), new_key(client, "viewer")
    assert client.post("/api/v1/ingest", json=batch(T0 - 600, 50),
                       headers=historian).json()["stored"] == 150
    unconfirmed = new_key(client, "historian")
    with store_outage(store, request):
        during = [client.post("/api/v1/ingest", json=batch(T0 - 500 + 100 * i, 60),
                              headers=historian) for i in range(3)]
        assert [r.status_code for r in during] == [200, 200, 200]
        assert [(r.json()["spooled"], r.json()["stored"]) for r in during] == [(180, 0)] * 3
        assert during[-1].json()["spool_samples"] == 540
        csv = client.post("/api/v1/ingest/csv", content=f"time,FIC-1.PV\n{T0 - 1},1.0\n",
                          headers=historian)
        assert (csv.status_code, csv.headers["Retry-After"]) == (503, "1")
        assert csv.json()["detail"] == ("The store is unreachable: CSV uploads are not "
                                        "spooled, send the file again later")
        if store.dialect == "postgresql":  # reads fail too; SQLite still reads
            page = client.get("/api/v1/loops", headers=viewer)
            assert (page.status_code, page.json()) == (503, {
                "detail": "The store is unreachable, so the API key cannot be checked; "
                          "try again later"})
            refused = client.post("/api/v1/ingest", json=batch(T0, 1), headers=unconfirmed)
            assert refused.status_code == 503
        assert svc.state.accounting().spooled == 540
    time.sleep(0.3)  # the spool's retry interval
    after = client.post("/api/v1/ingest", json=batch(T0 - 100, 10), headers=historian)
    assert (after.status_code, after.json()["stored"]) == (200, 30)
    assert len(svc.state.spool) == 0
    again = client.post("/api/v1/ingest", json=batch(T0 - 500, 60), headers=historian).json()
    assert (again["stored"], again["already_stored"]) == (0, 180)
    expected = {}
    for first, count in ((T0 - 600, 50), (T0 - 500, 60), (T0 - 400, 60), (T0 - 300, 60),
                         (T0 - 100, 10)):
        expected |= {(e["tag"], i["timestamp"]): i["value"]
                     for e in batch(first, count) for i in e["items"]}
    assert stored_samples(store) == expected
    window = svc.state.buffers.window("FIC-1", 600, T0)
    spooled_then = np.isin(window.t, T0 - 500 + np.arange(60))
    np.testing.assert_array_equal(window.pv[spooled_then], 1.0 + np.arange(60))
    assert_books_balance(svc, store)
    assert svc.state.accounting().received == 150 + 540 + 30 + 180


def test_beyond_the_spool_bound_batches_are_refused_and_counted(make_service, store,
                                                                request):
    svc = make_service(spool_max_samples=400)
    client = TestClient(svc.app)
    historian = new_key(client, "historian")
    client.post("/api/v1/ingest", json=batch(T0 - 900, 5), headers=historian)
    with store_outage(store, request):
        first = client.post("/api/v1/ingest", json=batch(T0 - 800, 60), headers=historian)
        second = client.post("/api/v1/ingest", json=batch(T0 - 700, 60), headers=historian)
        third = client.post("/api/v1/ingest", json=batch(T0 - 600, 60), headers=historian)
        # the one path of the connectors: in order, the first value of a time stamp wins
        svc.state.ingest([{"tag": "FIC-2.PV", "items": [{"timestamp": T0 - 10, "value": 1.0}]}])
        svc.state.ingest([{"tag": "FIC-2.PV", "items": [{"timestamp": T0 - 10, "value": 2.0}]}])
    assert [first.status_code, second.status_code, third.status_code] == [200, 200, 503]
    assert third.headers["Retry-After"] == "5"
    assert third.json()["detail"] == (
        "The store is unreachable and the ingest spool is full (360 of 400 samples held): "
        "the batch of 180 samples was not accepted; send it again later")
    assert svc.state.flush_spool() == 362
    books = svc.state.accounting()
    assert books.refused == {"spool_full": 180, "conflict": 1}
    assert (books.received, books.stored, books.spooled) == (15 + 542, 15 + 361, 0)
    assert stored_samples(store)[("FIC-2.PV", T0 - 10)] == 1.0
    metrics = client.get("/metrics", headers={"X-API-Key": ADMIN}).text
    assert 'loopwatch_samples_refused_total{reason="spool_full"} 180.0' in metrics
    assert_books_balance(svc, store)


def test_a_malformed_batch_is_refused_during_an_outage_too(make_service, store, request):
    svc = make_service()
    client = TestClient(svc.app)
    historian = new_key(client, "historian")
    assert client.post("/api/v1/ingest", json=[], headers=historian).status_code == 200
    with store_outage(store, request):
        held = client.post("/api/v1/ingest", json=batch(T0 - 100, 3), headers=historian)
        assert held.json()["spooled"] == 9
        bad = svc.state.ingest
        with pytest.raises(ValueError, match=r"batch\[0\]\.items\[0\]\.value\.float: "
                                             r"Input should be a valid number"):
            bad([{"tag": "FIC-1.PV", "items": [{"timestamp": T0, "value": [1.0]}]}])
    assert svc.state.accounting().spooled == 9
    assert svc.state.flush_spool() == 9
    assert_books_balance(svc, store)


def test_a_spooled_batch_is_stored_and_refused_as_if_written_at_once(make_service, store,
                                                                    request):
    """The spool keeps batches packed in arrays; the store must not see the difference."""
    svc = make_service()
    mixed = [
        {"tag": "FIC-1.PV", "items": [
            {"timestamp": "2023-11-14T22:10:00Z", "value": 1.0},  # T0 - 200 s
            {"timestamp": T0 - 199, "value": None},  # bad sample
            {"timestamp": T0 - 198, "value": 3.0, "good": False},  # bad sample
            {"timestamp": "yesterday", "value": 4.0},  # bad_timestamp
            {"timestamp": T0 + 3600, "value": 5.0},  # future_timestamp
            {"timestamp": T0 - 199, "value": 6.0},  # duplicate_in_batch
            {"timestamp": "-0", "value": 7.0},  # the epoch
            {"timestamp": T0 - 197, "value": "high"},  # bad_value: text, refused alone
        ]},
        {"tag": "NOPE", "items": [{"timestamp": T0, "value": 1.0}]},  # unknown_tag
    ]
    with store_outage(store, request):
        assert svc.state.ingest(mixed).as_dict()["spooled"] == 9
    assert svc.state.flush_spool() == 9
    books = svc.state.accounting()
    assert books.refused == {"unknown_tag": 1, "bad_timestamp": 1, "future_timestamp": 1,
                             "bad_value": 1, "duplicate_in_batch": 1}
    assert stored_samples(store) == {("FIC-1.PV", T0 - 200): 1.0, ("FIC-1.PV", T0 - 199): None,
                                     ("FIC-1.PV", T0 - 198): None, ("FIC-1.PV", 0.0): 7.0}
    assert_books_balance(svc, store)


# ----------------------------------------------------------------------------- killed service


def _post(url: str, body: Any, key: str) -> int:
    request = urllib.request.Request(url, data=json.dumps(body).encode(), method="POST",
                                     headers={"X-API-Key": key,
                                              "Content-Type": "application/json"})
    with urllib.request.urlopen(request, timeout=30) as response:
        return int(response.status)


def test_a_killed_service_keeps_every_acknowledged_sample_and_its_window(store, tmp_path):
    """``kill -9`` while a historian pushes: what was acknowledged is in the store and in
    the rolling window of the restarted service."""
    config = tmp_path / "plant.yaml"
    config.write_text(yaml.safe_dump(plant().model_dump(mode="json")))
    port = free_port()
    env = {**os.environ, "LOOPWATCH_DATABASE_URL": store.url, "LOOPWATCH_API_KEY": ADMIN,
           "LOOPWATCH_ANALYSIS_INTERVAL_S": "3600", "LOOPWATCH_WORKERS": "1",
           "LOOPWATCH_WINDOW_S": "3600", "LOOPWATCH_BUFFER_HORIZON_S": "7200"}
    server = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "serve", "--config", str(config),
         "--port", str(port)],
        env=env, cwd=Path(__file__).resolve().parents[2],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    base = f"http://127.0.0.1:{port}"
    now = float(int(time.time()))
    acknowledged: list[list[dict[str, Any]]] = []
    try:
        for _ in range(300):
            try:
                urllib.request.urlopen(f"{base}/healthz", timeout=1)
                break
            except OSError:
                time.sleep(0.1)
        for k in range(20):
            sent = batch(now - 1200 + 50 * k, 50)
            if _post(f"{base}/api/v1/ingest", sent, ADMIN) == 200:
                acknowledged.append(sent)
    finally:
        server.send_signal(signal.SIGKILL)
        server.wait(timeout=30)
    assert len(acknowledged) == 20
    settings = Settings(database_url=store.url, api_key=ADMIN, window_s=3600,
                        buffer_horizon_s=7200)
    restarted = build_service(settings, plant(), executor=ThreadPoolExecutor(1))
    try:
        in_store = stored_samples(restarted.state.store)
        for sent in acknowledged:
            for entry in sent:
                for item in entry["items"]:
                    assert in_store[(entry["tag"], item["timestamp"])] == item["value"]
        window = restarted.state.buffers.window("FIC-1", 1000, now - 201)
        expected = [item["value"] for sent in acknowledged for e in sent
                    if e["tag"] == "FIC-1.PV" for item in e["items"]]
        assert window.pv.tolist() == expected
    finally:
        restarted.executor.shutdown()
        restarted.state.store.close()


# ----------------------------------------------------------------------------- worker death


def analyse_or_fail(fault: str, marker: str, loop: dict[str, Any], *args: Any
                    ) -> dict[str, Any]:
    """:func:`analyse_window`, except that FIC-2's first analysis kills its worker process
    (``fault`` "die") or hangs for a minute ("hang"), and every one of them dies with
    "die-always"; the sabotaged worker writes its process id to ``marker``."""
    if loop["id"] == "FIC-2" and (fault == "die-always" or not os.path.exists(marker)):
        Path(marker).write_text(str(os.getpid()))
        if fault == "hang":
            time.sleep(60)
        os._exit(1)
    return analyse_window(loop, *args)


class SabotagedPool(ProcessPoolExecutor):
    """A real process pool of one worker whose analyses of FIC-2 die or hang."""

    def __init__(self, fault: str, marker: Path) -> None:
        super().__init__(max_workers=1)
        self.fault, self.marker = fault, str(marker)

    def submit(self, fn: Any, /, *args: Any, **kwargs: Any) -> Any:
        if fn is analyse_window:
            return super().submit(analyse_or_fail, self.fault, self.marker, *args, **kwargs)
        return super().submit(fn, *args, **kwargs)


def process_ended(pid: int) -> bool:
    """True once the process is gone or a zombie (killed, not yet reaped)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except FileNotFoundError:
        return True


@pytest.mark.parametrize(("fault", "fic2"), [
    pytest.param("die", ("ok", None), id="dies-once"),
    pytest.param("hang", ("ok", None), id="hangs-once"),
    pytest.param("die-always", ("failed", "its worker process died, on its retry too"),
                 id="dies-every-time"),
])
def test_a_dead_or_hung_worker_costs_one_loop_one_round_and_the_others_go_on(
        store, tmp_path, fault, fic2):
    settings = Settings(database_url=store.url, api_key=ADMIN, window_s=3600,
                        buffer_horizon_s=7200, analysis_timeout_s=8 if fault == "hang" else 30)
    marker = tmp_path / "sabotaged"
    pools: list[SabotagedPool] = []

    def new_pool() -> SabotagedPool:
        pools.append(SabotagedPool(fault, marker))
        return pools[-1]

    svc = build_service(settings, plant(), executor_factory=new_pool, clock=lambda: T0)
    try:
        svc.state.ingest(simulated_batch())
        assert svc.scheduler is not None
        first = svc.scheduler.run_once(T0)
        sabotaged_worker = int(marker.read_text())
        assert [(r.loop_id, r.status) for r in first] == [("FIC-1", "ok"), ("FIC-2", fic2[0])]
        with svc.state.store.session() as session:
            assert session.get(AnalysisRun, first[1].run_id).error == fic2[1]
            unit_run = session.scalars(select(UnitAnalysisRun)).one()  # the unit goes on too
            assert (unit_run.status, unit_run.sticky_loops) == ("ok", ["FIC-1"])
        # the broken or hung pool was replaced, its worker killed
        assert len(pools) == (3 if fault == "die-always" else 2)
        assert svc.scheduler.executor is pools[-1]
        for _ in range(50):
            if process_ended(sabotaged_worker):
                break
            time.sleep(0.1)
        assert process_ended(sabotaged_worker)
        metrics = svc.state.metrics
        assert metrics.value("loopwatch_analysis_retries_total",
                             cause="timeout" if fault == "hang" else "worker_died") == 1
        assert metrics.value("loopwatch_executor_replacements_total") == len(pools) - 1
        second = {r.loop_id: r.status for r in svc.scheduler.run_once(T0)}
        assert second == {"FIC-1": "ok", "FIC-2": fic2[0]}
    finally:
        for pool in pools:
            end_executor(pool)
        svc.state.store.close()
