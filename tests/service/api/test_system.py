"""``/healthz`` (no key) and ``/metrics`` (a key that may read)."""

from tests.service.test_api import key


def test_liveness_needs_no_key(client):
    answer = client.get("/healthz")
    assert (answer.status_code, answer.json()) == (200, {"status": "ok"})


def test_metrics_need_a_key_that_may_read(client):
    assert client.get("/metrics").json() == {"detail": "Missing API key (header X-API-Key)"}
    refused = client.get("/metrics", headers=key(client, "historian"))
    assert (refused.status_code, refused.json()) == (403, {
        "detail": "Role 'historian' may not read"})
    answer = client.get("/metrics", headers=key(client, "viewer"))
    assert answer.status_code == 200
    assert answer.headers["content-type"].startswith("text/plain")
    assert "loopwatch_tickets_open 0.0" in answer.text
