"""GET /metrics, read back with prometheus_client's own parser.

The scrape must parse as a whole whatever the label values hold (a
connector named after a file with a ``"`` in its name), every family has
its HELP line, cumulative counts are counters with ``_total``, and the
analysis times are histograms.
"""

from concurrent.futures import ThreadPoolExecutor

import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

from connectors.replay import ReplayConnector
from service.config import Settings
from service.metrics import Metrics
from service.server import build_service
from tests.service.test_api import ADMIN, T0, plant, simulated_batch


def test_large_counts_keep_every_digit_and_unknown_counters_are_refused():
    # ``:g`` formatting once printed 1234567 as 1.23457e+06: a counter that lost 33 samples
    metrics = Metrics()
    metrics.inc("loopwatch_samples_received_total", 1_234_567)
    families = {f.name: f for f in text_string_to_metric_families(metrics.render().decode())}
    assert families["loopwatch_samples_received"].samples[0].value == 1_234_567
    assert metrics.value("loopwatch_samples_received_total") == 1_234_567
    with pytest.raises(KeyError):
        metrics.inc("loopwatch_no_such_total")


@pytest.fixture
def service(tmp_path):
    settings = Settings(database_url=f"sqlite:///{tmp_path / 'loopwatch.db'}", api_key=ADMIN,
                        window_s=3600, buffer_horizon_s=7200)
    svc = build_service(settings, plant(), executor=ThreadPoolExecutor(1), clock=lambda: T0)
    yield svc
    svc.executor.shutdown()
    svc.state.store.close()


def test_the_scrape_parses_with_help_counters_and_histograms(service, tmp_path):
    export = tmp_path / 'FIC "7" \\ export.csv'  # a quote and a backslash in the label
    export.write_text("time,x\n0,1\n1,2\n")
    replay = ReplayConnector(export, service.state.ingest, columns={"x": "FIC-1.PV"})
    service.state.sources.append(replay)
    client = TestClient(service.app)
    assert client.post("/api/v1/ingest", json=simulated_batch(3600),
                       headers={"X-API-Key": ADMIN}).status_code == 200
    service.scheduler.run_once(T0)

    response = client.get("/metrics", headers={"X-API-Key": ADMIN})
    assert response.headers["content-type"].startswith("text/plain; version=")
    families = {f.name: f for f in text_string_to_metric_families(response.text)}

    assert all(f.documentation for f in families.values()), "every family has its HELP"
    assert [line for line in response.text.splitlines() if line.startswith("# HELP")]
    up = families["loopwatch_connector_up"]
    assert [(s.labels, s.value) for s in up.samples] == [({"connector": replay.name}, 1.0)]
    assert replay.name == 'replay FIC "7" \\ export.csv'
    for name in ("samples", "bad", "delivered", "undelivered", "outages", "outage_seconds"):
        family = families[f"loopwatch_connector_{name}"]
        assert family.type == "counter" and family.samples[0].name.endswith("_total")
    assert families["loopwatch_samples_stored"].type == "counter"
    stored = families["loopwatch_samples_stored"].samples[0].value
    assert stored == 6 * 3600  # OP, PV and SP of two loops
    assert families["loopwatch_analyses"].samples[0].labels == {"status": "ok"}
    assert families["loopwatch_loops"].type == "gauge"
    assert families["loopwatch_loops"].samples[0].value == 2

    for name in ("loopwatch_analysis_duration_seconds", "loopwatch_analysis_queue_seconds"):
        histogram = families[name]
        assert histogram.type == "histogram"
        counts = {s.labels["le"]: s.value for s in histogram.samples
                  if s.name == f"{name}_bucket" and s.labels["kind"] == "loop"}
        assert counts["+Inf"] == 2  # both loops of the round
        assert list(counts.values()) == sorted(counts.values())  # cumulative
