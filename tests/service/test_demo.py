"""The demo plant's back-fill (:class:`service.demo.DemoFeeder`) against a store that
already holds an earlier run's samples: the two runs' plants must not interleave."""

import pytest

from service.demo import DemoFeeder

NOW = 1_800_000_000.0


@pytest.fixture
def feeder():
    demo = DemoFeeder(history_s=1200.0, max_batch_samples=50_000, clock=lambda: NOW)
    yield demo
    demo.stop()


def stamps(batches):
    return [item["timestamp"] for batch in batches for entry in batch for item in entry["items"]]


def test_a_fresh_store_gets_the_whole_history(feeder):
    batches = []
    assert feeder.start(batches.append) > 0
    times = stamps(batches)
    assert min(times) == pytest.approx(NOW - 1200.0, abs=2.0) and max(times) < NOW
    assert feeder.history_text == "the last 20 min (1200 s)"


def test_a_restart_back_fills_only_after_the_stored_samples(feeder):
    """Restarted 5 minutes after the last stored sample: the new run's plant is simulated
    from another origin, so its back-fill starts after the stored samples (a seam like a
    plant restart) instead of writing a second plant between them."""
    batches = []
    feeder.start(batches.append, after=NOW - 300.0)
    times = stamps(batches)
    assert times and min(times) >= NOW - 300.0 and max(times) < NOW
    assert feeder.history_text == (
        "the last 5 min (300 s), after the samples stored by the run before")
