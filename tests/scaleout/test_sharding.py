"""Connectors sharded by endpoint across ingest processes, and what each role runs."""

import math
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from connectors.base import SampleSink
from service.config import PlantConfig, Settings
from service.server import Connector, build_service, ingest_shard
from tests.service.test_api import ADMIN, T0, plant

ROOT = Path(__file__).resolve().parents[2]
ENDPOINTS = [f"opc.tcp://plc-{k:05d}.site-{k % 7}:4840" for k in range(10_000)]


def test_every_process_computes_the_same_shard() -> None:
    """No coordination: a process with another hash seed gets the same assignment."""
    code = ("from service.server import ingest_shard; "
            f"print([ingest_shard(e, 5) for e in {ENDPOINTS[:200]!r}])")
    other = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           env={"PYTHONHASHSEED": "12345", "PYTHONPATH": str(ROOT)},
                           check=True, cwd=ROOT)
    assert other.stdout.strip() == str([ingest_shard(e, 5) for e in ENDPOINTS[:200]])


def test_endpoints_spread_evenly_over_the_shards() -> None:
    shards = 4
    counts = [0] * shards
    for endpoint in ENDPOINTS:
        counts[ingest_shard(endpoint, shards)] += 1
    n, p = len(ENDPOINTS), 1 / shards
    sigma = math.sqrt(n * p * (1 - p))  # binomial: 43 endpoints
    assert all(abs(c - n * p) < 5 * sigma for c in counts), counts


def test_adding_a_process_moves_only_what_the_new_one_takes() -> None:
    before = [ingest_shard(e, 4) for e in ENDPOINTS]
    after = [ingest_shard(e, 5) for e in ENDPOINTS]
    moved = [(b, a) for b, a in zip(before, after, strict=True) if b != a]
    assert {a for _, a in moved} == {4}  # none moves between the old processes
    n, p = len(ENDPOINTS), 1 / 5
    assert abs(len(moved) - n * p) < 5 * math.sqrt(n * p * (1 - p))


def test_the_endpoint_is_compared_as_written_less_case_blanks_and_a_trailing_slash() -> None:
    assert ingest_shard(" OPC.TCP://PLC-1:4840/ ", 7) == ingest_shard("opc.tcp://plc-1:4840", 7)
    assert ingest_shard("anything", 1) == 0
    with pytest.raises(ValueError, match="shards must be at least 1, got 0"):
        ingest_shard("opc.tcp://plc-1:4840", 0)


class RecordingConnector:
    """A connector that only records its lifecycle (the real ones are tested elsewhere)."""

    def __init__(self, endpoint: str, sink: SampleSink) -> None:
        self.endpoint, self.sink = endpoint, sink
        self.calls: list[str] = []

    def start(self) -> None:
        self.calls.append("start")
        self.sink([{"tag": "FIC-1.PV", "items": [{"timestamp": T0, "value": 1.0}]}])

    def stop(self) -> None:
        self.calls.append("stop")


@pytest.mark.parametrize("shard", [0, 1, 2])
def test_an_ingest_process_runs_the_connectors_of_its_shard(tmp_path: Path, shard: int) -> None:
    endpoints = ENDPOINTS[:30]
    made: list[RecordingConnector] = []

    def factory(plant_config: PlantConfig, owns, sink: SampleSink) -> list[Connector]:
        mine = [RecordingConnector(e, sink) for e in endpoints if owns(e)]
        made.extend(mine)
        return list(mine)

    settings = Settings(database_url=f"sqlite:///{tmp_path / 'x.db'}", api_key=ADMIN,
                        role="ingest", ingest_shard=shard, ingest_shards=3)
    svc = build_service(settings, plant(), clock=lambda: T0, connector_factory=factory)
    assert svc.scheduler is None and svc.executor is None and svc.feeder is None
    assert [c.endpoint for c in made] == [e for e in endpoints if ingest_shard(e, 3) == shard]
    svc.start()
    svc.stop()
    assert all(c.calls == ["start", "stop"] for c in made)
    assert svc.state.metrics.value("loopwatch_samples_received_total") == len(made)


@pytest.mark.parametrize(("role", "schedules", "ingests"), [
    ("api", False, False), ("ingest", False, True), ("scheduler", True, False),
    ("all", True, True),
])
def test_each_role_runs_its_part(tmp_path: Path, role: str, schedules: bool,
                                 ingests: bool) -> None:
    calls: list[str] = []

    def factory(plant_config: PlantConfig, owns, sink: SampleSink) -> list[Connector]:
        calls.append("factory")
        return []

    settings = Settings(database_url=f"sqlite:///{tmp_path / 'x.db'}", api_key=ADMIN,
                        role=role)
    executor = ThreadPoolExecutor(1) if schedules else None
    svc = build_service(settings, None, executor=executor, clock=lambda: T0,
                        connector_factory=factory)
    try:
        assert (svc.scheduler is not None, svc.executor is not None) == (schedules, schedules)
        assert (svc.feeder is not None, calls == ["factory"]) == (ingests, ingests)  # demo
        assert bool(svc.state.buffers.tags) == schedules  # only schedulers keep windows
    finally:
        svc.state.store.close()
        if executor is not None:
            executor.shutdown()


def test_shard_settings_are_checked() -> None:
    with pytest.raises(ValueError, match=r"LOOPWATCH_INGEST_SHARD \(3\) must be below "
                                         r"LOOPWATCH_INGEST_SHARDS \(3\)"):
        Settings(ingest_shard=3, ingest_shards=3)
