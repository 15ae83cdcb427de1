"""The Prometheus exposition text of service.metrics."""

from service.metrics import Metrics


def test_large_counts_and_fractions_keep_every_digit():
    # ``:g`` formatting printed 1234567 as 1.23457e+06: a counter that lost 33 samples
    metrics = Metrics()
    metrics.inc("loopwatch_samples_total", 1_234_567, tag="FIC-1.PV")
    metrics.inc("loopwatch_rounds_total")
    text = metrics.render({"loopwatch_outage_seconds": 2.5312345678, "loopwatch_loops": 10_000.0})
    assert text.splitlines() == [
        "# TYPE loopwatch_rounds_total counter",
        "loopwatch_rounds_total 1",
        "# TYPE loopwatch_samples_total counter",
        'loopwatch_samples_total{tag="FIC-1.PV"} 1234567',
        "# TYPE loopwatch_loops gauge",
        "loopwatch_loops 10000",
        "# TYPE loopwatch_outage_seconds gauge",
        "loopwatch_outage_seconds 2.5312345678",
    ]
