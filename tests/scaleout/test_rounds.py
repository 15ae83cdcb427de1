"""Scheduled rounds across a failover: completed, caught up, never stored twice.

Two services share one store (SQLite and PostgreSQL), as two scheduler
processes would; their clocks stand at T0 and the rounds sit on a 500 s grid.
"""

import threading
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import numpy as np
import pytest
from sqlalchemy import func, select

from service.config import PlantConfig, Settings
from service.leader import LeaseElection
from service.scheduling.rounds import SYNC_OVERLAP_S
from service.server import SCHEDULING_ROLES, Service, build_service
from service.store.db import Store
from service.store.models import AnalysisRun, Ticket
from tests.service.conftest import store  # noqa: F401  (the fixture: SQLite and PostgreSQL)
from tests.service.test_api import ADMIN, T0, plant, simulated_batch

INTERVAL = 500.0  # T0 is a multiple: round ends T0, T0 - 500, ...


@pytest.fixture
def make_service(store: Store) -> Iterator[Callable[..., Service]]:  # noqa: F811
    made: list[Service] = []

    def make(role: str = "all", executor: Any = None, plant_config: PlantConfig | None = None,
             clock: Callable[[], float] = lambda: T0, **overrides: Any) -> Service:
        settings = Settings(**{
            "database_url": store.url, "api_key": ADMIN, "window_s": 3600,
            "buffer_horizon_s": 7200, "analysis_interval_s": INTERVAL, "role": role,
            **overrides,
        })
        if executor is None and role in SCHEDULING_ROLES:
            executor = ThreadPoolExecutor(2)
        svc = build_service(settings, plant_config or plant(), executor=executor, clock=clock)
        made.append(svc)
        return svc

    yield make
    for svc in made:
        svc.stop()  # also hands back a leadership (and its connection) taken in a test


def runs(svc: Service) -> list[tuple[str, float | None, str | None]]:
    with svc.state.store.session() as session:
        rows = session.execute(
            select(AnalysisRun.loop_id, AnalysisRun.round_end, AnalysisRun.scheduled_by)
        )
        return sorted(((loop, end, by) for loop, end, by in rows),
                      key=lambda r: (r[1] or 0, r[0]))


def test_a_new_leader_completes_the_interrupted_round_and_runs_the_missed_ones(
    make_service: Callable[..., Service],
) -> None:
    svc = make_service()
    svc.state.ingest(simulated_batch())
    with svc.state.store.session() as session:  # the old leader died after FIC-1 of this round
        session.add(AnalysisRun(loop_id="FIC-1", started_at=T0 - 1000, status="ok",
                                round_end=T0 - 1000, scheduled_by="dead:1:0"))
    assert svc.scheduler is not None and svc.scheduler.election is not None
    assert svc.scheduler.election.poll()
    done = svc.scheduler.run_due()
    assert [(s.loop_id, s.status) for s in done] == [
        ("FIC-2", "ok"), ("FIC-1", "ok"), ("FIC-2", "ok"), ("FIC-1", "ok"), ("FIC-2", "ok")]
    me = svc.scheduler.instance
    assert runs(svc) == [
        ("FIC-1", T0 - 1000, "dead:1:0"), ("FIC-2", T0 - 1000, me),
        ("FIC-1", T0 - 500, me), ("FIC-2", T0 - 500, me),
        ("FIC-1", T0, me), ("FIC-2", T0, me),
    ]
    assert svc.scheduler.run_due() == []  # nothing is due twice
    assert len(runs(svc)) == 6


def test_rounds_whose_window_left_the_buffer_are_counted_as_missed(
    make_service: Callable[..., Service],
) -> None:
    svc = make_service(buffer_horizon_s=4000)  # a window of 3600 s fits 400 s back
    with svc.state.store.session() as session:
        session.add_all(AnalysisRun(loop_id=loop, started_at=T0 - 2000, status="ok",
                                    round_end=T0 - 2000) for loop in ("FIC-1", "FIC-2"))
    assert svc.scheduler is not None
    assert svc.scheduler.due_rounds(T0 + 10) == [T0]
    assert svc.state.metrics.value("loopwatch_rounds_missed_total") == 3  # T0-1500..T0-500


def test_a_result_another_scheduler_stored_first_is_dropped_whole(
    make_service: Callable[..., Service],
) -> None:
    """Split brain: B computes a round A is storing; B's results never reach the store, so
    they neither double the runs nor count as a second confirmation of the ticket."""
    a = make_service(ticket_confirmations=2)
    assert a.scheduler is not None and a.scheduler.election is not None
    assert a.scheduler.election.poll()
    a.state.ingest(simulated_batch())

    class RacingExecutor(ThreadPoolExecutor):
        """B's pool: while B's first analysis runs, A runs and stores the whole round."""

        def submit(self, fn: Any, /, *args: Any, **kwargs: Any) -> Future[Any]:
            if not a_stored:
                assert a.scheduler is not None
                a_stored.extend(a.scheduler.run_round(T0))
            return super().submit(fn, *args, **kwargs)

    a_stored: list[Any] = []
    b = make_service(executor=RacingExecutor(2))
    assert b.scheduler is not None
    b.scheduler.election = None  # B believes it leads
    b.scheduler.sync_buffers(T0)
    assert b.scheduler.run_round(T0) == []
    assert [(s.loop_id, s.verdict) for s in a_stored] == [
        ("FIC-1", "stiction"), ("FIC-2", "undecided")]  # FIC-2 hardly moves
    assert b.state.metrics.value("loopwatch_analyses_duplicate_total") == 2
    assert [(loop, end) for loop, end, _ in runs(a)] == [("FIC-1", T0), ("FIC-2", T0)]
    with a.state.store.session() as session:
        assert session.scalar(select(func.count()).select_from(Ticket)) == 0


def test_a_scheduler_that_does_not_lead_stores_nothing(
    make_service: Callable[..., Service],
) -> None:
    svc = make_service()
    svc.state.ingest(simulated_batch())
    assert svc.scheduler is not None
    holder = LeaseElection(svc.state.store, name="scheduler", holder="the-leader",
                           lease_s=600)
    assert holder.poll()
    svc.scheduler.election = LeaseElection(svc.state.store, name="scheduler",
                                           holder="standby", lease_s=600)
    assert not svc.scheduler.election.poll()
    assert svc.scheduler.run_round(T0) == []
    assert runs(svc) == []


def test_the_scheduler_reads_what_ingest_processes_stored(
    make_service: Callable[..., Service],
) -> None:
    # a standby started long ago, before any sample: its first sync rebuilds the horizon
    scheduler = make_service(role="scheduler", clock=lambda: T0 - 10_000)
    received = [T0]
    ingest = make_service(role="ingest", clock=lambda: received[0])
    assert ingest.scheduler is None and ingest.executor is None
    assert scheduler.scheduler is not None and scheduler.feeder is None
    assert ingest.state.buffers.tags == frozenset()  # ingest leaves samples to the store
    batch = simulated_batch(1000)
    op, pv = ([item["value"] for item in batch[k]["items"]] for k in (0, 1))
    late = batch[0]["items"].pop(-101)  # FIC-1.OP at T0 - 100 arrives late
    assert (batch[0]["tag"], late["timestamp"]) == ("FIC-1.OP", T0 - 100)
    ingest.state.ingest(batch)
    assert scheduler.scheduler.sync_buffers(T0) == 6 * 1000 - 1
    window = scheduler.state.buffers.window("FIC-1", 1000, T0)
    np.testing.assert_array_equal(window.pv, pv)
    np.testing.assert_array_equal(np.delete(window.op, -101), np.delete(op, -101))
    assert np.isnan(window.op[-101])
    # five minutes later the late sample comes: the next sync reads from its time stamp
    # on, and again the batch received within SYNC_OVERLAP_S before the last sync
    received[0] = T0 + 300
    ingest.state.ingest([{"tag": "FIC-1.OP", "items": [late]}])
    assert scheduler.scheduler.sync_buffers(T0 + 300) == 6 * 1000
    window = scheduler.state.buffers.window("FIC-1", 1000, T0)
    assert window.op[-101] == late["value"] and np.isfinite(window.op).all()
    # a sync with nothing newly received reads only the overlap: the late batch's span
    assert scheduler.scheduler.sync_buffers(T0 + 301) == 6 * 101
    assert SYNC_OVERLAP_S < 300


def test_no_more_than_two_analyses_per_worker_are_in_flight(
    make_service: Callable[..., Service],
) -> None:
    loops = [{**plant().loops[1].model_dump(), "id": f"FIC-{k}", "unit": None,
              "tags": {"op": f"FIC-{k}.OP", "pv": f"FIC-{k}.PV", "sp": f"FIC-{k}.SP"}}
             for k in range(2, 8)]
    six = PlantConfig.model_validate({"loops": loops})

    class CountingExecutor(ThreadPoolExecutor):
        def __init__(self) -> None:
            super().__init__(1)
            self.futures: list[Future[Any]] = []
            self.most_in_flight = 0
            self.second_submitted = threading.Event()

        def submit(self, fn: Any, /, *args: Any, **kwargs: Any) -> Future[Any]:
            in_flight = sum(not f.done() for f in self.futures) + 1
            self.most_in_flight = max(self.most_in_flight, in_flight)
            if self.futures:
                self.second_submitted.set()
                future = super().submit(fn, *args, **kwargs)
            else:  # the first job waits for the second submission, however slow the machine
                future = super().submit(self.after_second_submission, fn, *args, **kwargs)
            self.futures.append(future)
            return future

        def after_second_submission(self, fn: Any, *args: Any, **kwargs: Any) -> Any:
            self.second_submitted.wait(60)
            return fn(*args, **kwargs)

    executor = CountingExecutor()
    svc = make_service(executor=executor, plant_config=six, workers=1)
    healthy = [entry for entry in simulated_batch(1200) if entry["tag"].startswith("FIC-2.")]
    svc.state.ingest([{**entry, "tag": entry["tag"].replace("FIC-2", f"FIC-{k}")}
                      for k in range(2, 8) for entry in healthy])
    assert svc.scheduler is not None
    done = svc.scheduler.run_once(T0)
    assert [s.loop_id for s in done] == [f"FIC-{k}" for k in range(2, 8)]
    assert {s.status for s in done} == {"ok"}
    assert len(executor.futures) == 6 and executor.most_in_flight == 2
