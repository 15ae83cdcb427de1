"""What the connectors share: the background runner, the outage log, the hand-over to the sink."""

from __future__ import annotations

import asyncio
import threading
from typing import Any

import pytest

from connectors.base import DeliveryCounters, Outage, OutageLog, ThreadedRunner, hand_over

WAIT_S = 20.0
"""Upper bound on waiting for another thread: against hanging, not a speed check."""


def test_the_runner_cancels_waits_for_clean_up_and_runs_again() -> None:
    events: list[str] = []
    started = threading.Event()

    async def serve() -> None:
        events.append("started")
        started.set()
        try:
            await asyncio.Event().wait()
        finally:
            await asyncio.sleep(0.05)  # an asynchronous clean-up is awaited too
            events.append("cleaned up")

    runner = ThreadedRunner(serve, name="test-runner")
    for _ in range(2):
        started.clear()
        runner.start()
        assert started.wait(WAIT_S) and runner.running
        with pytest.raises(RuntimeError, match="test-runner: already running"):
            runner.start()
        runner.stop()
        assert not runner.running and runner.error is None
    assert events == ["started", "cleaned up"] * 2


def test_the_runner_keeps_the_error_that_ended_the_coroutine() -> None:
    async def fail() -> None:
        raise ValueError("no such endpoint")

    runner = ThreadedRunner(fail, name="failing")
    runner.start()
    runner.stop()  # it fails before its first await, so before a cancel can arrive
    assert isinstance(runner.error, ValueError) and str(runner.error) == "no such endpoint"


def test_a_sink_call_cut_short_by_a_stop_is_still_counted() -> None:
    in_sink, release, cancelled = threading.Event(), threading.Event(), threading.Event()
    taken: list[list[dict[str, Any]]] = []

    def slow_sink(batch: list[dict[str, Any]]) -> None:
        in_sink.set()
        assert release.wait(WAIT_S)
        taken.append(batch)

    batch = [{"tag": "A", "items": [{"timestamp": 0.0, "value": 1.0, "good": True}] * 3}]
    counters = DeliveryCounters(samples=3)

    async def deliver() -> None:
        try:
            await hand_over(slow_sink, batch, counters, "test")
        except asyncio.CancelledError:
            cancelled.set()
            raise

    runner = ThreadedRunner(deliver, name="delivery")
    runner.start()
    assert in_sink.wait(WAIT_S)
    stopper = threading.Thread(target=runner.stop)
    stopper.start()
    assert cancelled.wait(WAIT_S)  # the caller has given up; the sink call goes on
    release.set()
    stopper.join(WAIT_S)
    assert not runner.running
    assert taken == [batch]
    assert (counters.delivered, counters.undelivered) == (3, 0)


def test_a_snapshot_of_the_counters_is_a_copy_that_waits_for_an_update_in_progress() -> None:
    counters = DeliveryCounters(samples=5, bad=1, delivered=3)
    taken: list[DeliveryCounters] = []
    reader = threading.Thread(target=lambda: taken.append(counters.snapshot()))
    with counters.lock:  # an update in progress holds the reader back
        reader.start()
        reader.join(0.2)
        assert reader.is_alive()
        counters.delivered += 2
    reader.join(WAIT_S)
    (snapshot,) = taken
    assert snapshot == counters and snapshot.pending == 0
    assert snapshot is not counters and snapshot.lock is not counters.lock
    counters.samples += 1
    assert (snapshot.samples, snapshot.pending, counters.pending) == (5, 0, 1)


def test_the_outage_log_counts_failed_attempts_and_opens_a_new_outage_after_a_recovery() -> None:
    times = iter([100.0, 104.0, 200.0])
    outages = OutageLog("device", clock=lambda: next(times))
    assert outages.lost("connection refused")  # 100 s: the outage begins
    assert not outages.lost("connection refused")
    assert not outages.lost("timed out")
    outages.restored()  # 104 s
    outages.restored()  # nothing open: nothing to end
    assert outages.lost("connection reset")  # 200 s
    assert outages.outages == (
        Outage(start=100.0, end=104.0, reason="connection refused", failed_attempts=2),
        Outage(start=200.0, end=None, reason="connection reset"),
    )
