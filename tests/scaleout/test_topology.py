"""The deployment of docker-compose.yml without Docker, and a scheduler failover.

A real PostgreSQL, a Dask ``LocalCluster`` of two worker processes and two
``loopwatch serve`` processes on loopback ports: B with ``--role scheduler``
starts first and leads; A with ``--role all`` feeds the demo plant (its
history backfilled, then live), serves the API and stands by.  B is killed
(SIGKILL, as a crash); A takes over.  The store must then hold every round
on the grid, each with exactly one run of every loop, without a gap around
the failover, and the cluster must have computed no analysis twice except
those B had in flight when it died.
"""

import itertools
import os
import signal
import subprocess
import sys
import time
import urllib.request
from collections import defaultdict
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import select

from service.cli import build_parser
from service.demo import DEMO_LOOPS
from service.store.db import Store
from service.store.models import AnalysisRun
from tests.scaleout.test_executors import HAS_DASK, cluster  # noqa: F401  (fixture)
from tests.scaleout.test_leader import pg_store  # noqa: F401  (fresh PostgreSQL database)
from tests.servers import free_port, require

pytestmark = pytest.mark.serial  # timing-sensitive: run alone, after the parallel tests

ROOT = Path(__file__).resolve().parents[2]
KEY = "topology-test-admin-key-0123"
INTERVAL_S = 5
LOOPS = {loop.id for loop in DEMO_LOOPS}


def loopwatch_command() -> list[str]:
    """The ``loopwatch`` console script of this environment (or the module behind it)."""
    script = Path(sys.executable).with_name("loopwatch")
    return [str(script)] if script.is_file() else [sys.executable, "-m", "service.cli"]


class ServiceProcess:
    """``loopwatch serve --role ROLE`` in a subprocess on a free loopback port."""

    def __init__(self, role: str, env: dict[str, str], log: Path) -> None:
        self.role = role
        self.port = free_port()
        self.log = log
        with log.open("w") as out:
            self.process = subprocess.Popen(
                [*loopwatch_command(), "serve", "--role", role, "--host", "127.0.0.1",
                 "--port", str(self.port)],
                env=env, stdout=out, stderr=subprocess.STDOUT, cwd=ROOT,
            )

    def healthy(self) -> bool:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{self.port}/healthz",
                                        timeout=2) as response:
                return response.status == 200
        except OSError:
            return False

    def metrics(self) -> str:
        request = urllib.request.Request(f"http://127.0.0.1:{self.port}/metrics",
                                         headers={"X-API-Key": KEY})
        with urllib.request.urlopen(request, timeout=10) as response:
            return response.read().decode()

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 60) -> int:
        if self.process.poll() is None:
            self.process.send_signal(sig)
            try:
                self.process.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(10)
        return self.process.returncode


def wait_for(what: str, condition: Callable[[], Any], processes: list[ServiceProcess],
             timeout_s: float = 120) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for p in processes:
            if p.process.poll() is not None:
                pytest.fail(f"{p.role} process exited ({p.process.returncode}) while waiting "
                            f"for {what}:\n{p.log.read_text()[-3000:]}")
        if result := condition():
            return result
        time.sleep(0.5)
    logs = "\n".join(f"--- {p.role}\n{p.log.read_text()[-3000:]}" for p in processes)
    pytest.fail(f"timed out waiting for {what}\n{logs}")


def rounds(store: Store) -> dict[float, list[AnalysisRun]]:
    by_round: dict[float, list[AnalysisRun]] = defaultdict(list)
    with store.session() as session:
        for run in session.scalars(select(AnalysisRun).where(AnalysisRun.round_end.is_not(None))):
            assert run.round_end is not None
            by_round[run.round_end].append(run)
    return dict(sorted(by_round.items()))


def complete_ok_rounds(store: Store, pid: int) -> list[float]:
    return [end for end, runs in rounds(store).items()
            if {r.loop_id for r in runs} == LOOPS and all(r.status == "ok" for r in runs)
            and all(r.scheduled_by and r.scheduled_by.split(":")[1] == str(pid) for r in runs)]


@pytest.fixture
def topology_env(pg_store: Store, cluster: Any, tmp_path: Path) -> Iterator[dict[str, str]]:  # noqa: F811
    env = {
        **os.environ,
        "PYTHONPATH": str(ROOT),
        "LOOPWATCH_DATABASE_URL": pg_store.url,
        "LOOPWATCH_API_KEY": KEY,
        "LOOPWATCH_DATA_DIR": str(tmp_path / "data"),
        "LOOPWATCH_EXECUTOR": "dask",
        "LOOPWATCH_DASK_SCHEDULER": cluster.scheduler_address,
        "LOOPWATCH_ANALYSIS_INTERVAL_S": str(INTERVAL_S),
        "LOOPWATCH_WINDOW_S": "600",
        "LOOPWATCH_BUFFER_HORIZON_S": "1200",
        "LOOPWATCH_LEADER_LEASE_S": "3",
    }
    yield env


def test_the_standby_takes_over_and_no_round_is_lost_or_doubled(
    topology_env: dict[str, str], pg_store: Store, cluster: Any, tmp_path: Path,  # noqa: F811
) -> None:
    analyses_before = cluster.scheduler.task_prefixes.get("analyse_window")
    assert analyses_before is None
    b = ServiceProcess("scheduler", topology_env, tmp_path / "b.log")
    a: ServiceProcess | None = None
    try:
        wait_for("B to lead and store a round", lambda: rounds(pg_store), [b])
        a = ServiceProcess("all", topology_env, tmp_path / "a.log")
        wait_for("A to serve", a.healthy, [a, b])
        # B analyses the plant A feeds (it reads A's backfill and live samples from the store)
        wait_for("two complete rounds by B", lambda: len(complete_ok_rounds(
            pg_store, b.process.pid)) >= 2, [a, b])
        killed_at = time.time()
        assert b.stop(signal.SIGKILL) == -signal.SIGKILL
        wait_for("two complete rounds by A", lambda: len(complete_ok_rounds(
            pg_store, a.process.pid)) >= 2, [a])
        metrics = a.metrics()
        # uvicorn shuts down cleanly, then re-raises SIGTERM to exit with it
        assert a.stop() in (0, -signal.SIGTERM)
        assert "Application shutdown complete" in a.log.read_text()
    finally:
        b.stop(signal.SIGKILL)
        if a is not None:
            a.stop(signal.SIGKILL)

    by_round = rounds(pg_store)
    ends = list(by_round)
    assert all(round(end / INTERVAL_S) * INTERVAL_S == end for end in ends)  # on the grid
    assert [later - earlier for earlier, later in itertools.pairwise(ends)] == (
        [INTERVAL_S] * (len(ends) - 1))  # no gap, not even around the failover
    for end, runs in by_round.items():  # every loop once in every round: nothing lost
        assert sorted(r.loop_id for r in runs) == sorted(LOOPS), end
    def pid(run: AnalysisRun) -> str:
        return (run.scheduled_by or "").split(":")[1]

    b_pid, a_pid = str(b.process.pid), str(a.process.pid)
    assert {pid(r) for runs in by_round.values() for r in runs} == {b_pid, a_pid}
    took_over = min(end for end, runs in by_round.items() if any(pid(r) == a_pid for r in runs))
    assert all(pid(r) == b_pid for end, runs in by_round.items() if end < took_over
               for r in runs)
    assert took_over <= killed_at + INTERVAL_S  # A completed or ran the round B left
    assert 'loopwatch_analyses_duplicate_total 0.0' in metrics  # A doubled nothing
    # every analysis that B or A stored ran once on the cluster; only what B had in flight
    # when it died (at most 2 per worker) was computed again
    stored = sum(r.status != "no_data" for runs in by_round.values() for r in runs)
    computed = cluster.scheduler.task_prefixes["analyse_window"].state_counts["memory"]
    assert stored <= computed <= stored + 4


def test_serve_takes_a_role() -> None:
    parser = build_parser()
    assert parser.parse_args(["serve", "--role", "scheduler"]).role == "scheduler"
    assert parser.parse_args(["serve"]).role is None  # LOOPWATCH_ROLE, default all
    with pytest.raises(SystemExit):
        parser.parse_args(["serve", "--role", "worker"])


def test_a_bad_role_setting_is_refused_with_its_name(tmp_path: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "LOOPWATCH_ROLE": "worker",
           "LOOPWATCH_DATA_DIR": str(tmp_path)}
    done = subprocess.run([*loopwatch_command(), "serve"], env=env, capture_output=True,
                          text=True, timeout=120, cwd=ROOT)
    assert done.returncode == 2
    assert "invalid LOOPWATCH_* settings" in done.stderr and "role" in done.stderr


def test_an_unreachable_dask_scheduler_stops_the_start_with_its_address(tmp_path: Path) -> None:
    require(HAS_DASK, "dask.distributed is not installed (pip install 'dask[distributed]')")
    address = f"tcp://127.0.0.1:{free_port()}"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "LOOPWATCH_EXECUTOR": "dask",
           "LOOPWATCH_DASK_SCHEDULER": address, "LOOPWATCH_DATA_DIR": str(tmp_path),
           "LOOPWATCH_ROLE": "scheduler", "LOOPWATCH_DASK_CONNECT_TIMEOUT_S": "3"}
    done = subprocess.run([*loopwatch_command(), "serve"], env=env, capture_output=True,
                          text=True, timeout=180, cwd=ROOT)
    assert done.returncode == 2, done.stderr[-2000:]
    assert "Timed out trying to connect" in done.stderr and "after 3 s" in done.stderr
    assert f"cannot reach the Dask scheduler at {address}" in done.stderr
