"""Who may call what, and the protections around it: keys, roles, limits, headers, CORS.

The access test is generated from the application's route table: every
route must appear in :data:`ACCESS` with the permission it needs, and is
called with a key of every role (and without a key).  A new route without
an entry fails :func:`test_every_route_is_in_the_access_table`.
"""

from __future__ import annotations

import asyncio
import hashlib
import logging
import re
from collections.abc import Iterable, Iterator
from html.parser import HTMLParser
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import event, select, text

from service.api.deps import RequireKey
from service.api.routes.dashboard import STATIC_FILES
from service.auth import PERMISSIONS, ROLES, salted_hash
from service.config import Settings
from service.security import CONTENT_SECURITY_POLICY, RateLimiter
from service.server import Service
from service.store.models import ApiKey
from tests.service.test_api import ADMIN, T0

PUBLIC = {("GET", "/healthz"), ("GET", "/"), ("GET", "/static/{name:path}"), ("GET", "/docs"),
          ("GET", "/redoc")}
"""Routes without a key: the liveness probe and the dashboard shell (fixed files, no data)."""

ANY_KEY = "any key"
ACCESS: dict[tuple[str, str], str] = {
    ("GET", "/openapi.json"): ANY_KEY,
    ("GET", "/metrics"): "read",
    ("GET", "/api/v1/me"): "read",
    ("GET", "/api/v1/loops"): "read",
    ("GET", "/api/v1/plant/bad-actors"): "read",
    ("GET", "/api/v1/loops/{loop_id}"): "read",
    ("GET", "/api/v1/loops/{loop_id}/config"): "read",
    ("PUT", "/api/v1/loops/{loop_id}"): "admin",
    ("GET", "/api/v1/loops/{loop_id}/analyses"): "read",
    ("GET", "/api/v1/loops/{loop_id}/health"): "read",
    ("GET", "/api/v1/loops/{loop_id}/data"): "read",
    ("GET", "/api/v1/loops/{loop_id}/kpis"): "read",
    ("GET", "/api/v1/reports/bad-actors"): "read",
    ("GET", "/api/v1/loops/{loop_id}/plots/{kind}"): "read",
    ("GET", "/api/v1/loops/{loop_id}/advice"): "read",
    ("POST", "/api/v1/loops/{loop_id}/model-check"): "read",
    ("POST", "/api/v1/loops/{loop_id}/plots/model-check"): "read",
    ("GET", "/api/v1/units/{unit_id}/diagnosis"): "read",
    ("GET", "/api/v1/units/{unit_id}/prediction"): "read",
    ("GET", "/api/v1/units"): "read",
    ("GET", "/api/v1/units/{unit_id}"): "read",
    ("GET", "/api/v1/alarms"): "read",
    ("GET", "/api/v1/alarms/{alarm_id}"): "read",
    ("POST", "/api/v1/alarms/{alarm_id}/acknowledge"): "alarms",
    ("POST", "/api/v1/alarms/{alarm_id}/shelve"): "alarms",
    ("POST", "/api/v1/alarms/{alarm_id}/unshelve"): "alarms",
    ("POST", "/api/v1/alarms/{alarm_id}/out-of-service"): "admin",
    ("POST", "/api/v1/alarms/{alarm_id}/in-service"): "admin",
    ("GET", "/api/v1/tickets"): "read",
    ("GET", "/api/v1/tickets/{ticket_id}"): "read",
    ("GET", "/api/v1/tickets/{ticket_id}/cmms"): "read",
    ("PATCH", "/api/v1/tickets/{ticket_id}"): "tickets",
    ("POST", "/api/v1/ingest"): "ingest",
    ("POST", "/api/v1/ingest/csv"): "ingest",
    ("POST", "/api/v1/keys"): "admin",
    ("GET", "/api/v1/keys"): "admin",
    ("DELETE", "/api/v1/keys/{key_id}"): "admin",
}
"""Every keyed route and the permission it needs (:data:`service.auth.PERMISSIONS`)."""

PATH_VALUES = {"loop_id": "FIC-1", "unit_id": "u1", "alarm_id": "999", "ticket_id": "999",
               "key_id": "999", "kind": "trend", "name": "app.js"}
"""Path parameters for the access test: requests that change nothing (ids that do not
exist, bodies that do not validate), so the calls can run in any order."""


def api_routes(routes: Iterable[Any]) -> Iterator[Any]:
    """The HTTP routes of an app, routers included (whatever FastAPI version nests them)."""
    for route in routes:
        if hasattr(route, "effective_candidates"):
            yield from api_routes(route.effective_candidates())
        elif getattr(route, "methods", None) and hasattr(route, "dependant"):
            yield route


def route_table(service: Service) -> dict[tuple[str, str], Any]:
    return {(method, route.path): route for route in api_routes(service.app.routes)
            for method in route.methods if method != "HEAD"}


def declared_access(dependant: Any) -> list[str]:
    """The permissions the route's key dependencies ask for (ANY_KEY for "any key")."""
    found = []
    for dependency in dependant.dependencies:
        if isinstance(dependency.call, RequireKey):
            found.append(dependency.call.permission or ANY_KEY)
        found.extend(declared_access(dependency))
    return found


def may(role: str, access: str) -> bool:
    return access == ANY_KEY or access in PERMISSIONS[role]  # type: ignore[index]


@pytest.fixture
def service(make_service) -> Service:
    return make_service()


@pytest.fixture
def client(service) -> TestClient:
    return TestClient(service.app)


def new_key(client: TestClient, role: str, name: str | None = None) -> str:
    response = client.post("/api/v1/keys", json={"name": name or f"{role} key", "role": role},
                           headers={"X-API-Key": ADMIN})
    assert response.status_code == 201, response.text
    return str(response.json()["key"])


def call(client: TestClient, method: str, path: str, key: str | None) -> Any:
    path = re.sub(r"\{(\w+):\w+\}", r"{\1}", path)  # {name:path} -> {name}
    url = path.format(**{k: v for k, v in PATH_VALUES.items() if f"{{{k}}}" in path})
    body = {} if method in ("POST", "PUT", "PATCH") else None
    headers = {} if key is None else {"X-API-Key": key}
    return client.request(method, url, json=body, headers=headers)


# ----------------------------------------------------------------------------- access


def test_every_route_is_in_the_access_table(service):
    routes = route_table(service)
    unlisted = sorted(set(routes) - set(ACCESS) - PUBLIC)
    assert not unlisted, f"routes without an entry in ACCESS (add one): {unlisted}"
    gone = sorted((set(ACCESS) | PUBLIC) - set(routes))
    assert not gone, f"ACCESS lists routes the app does not have: {gone}"
    for route_key, route in routes.items():
        expected = [] if route_key in PUBLIC else [ACCESS[route_key]]
        assert declared_access(route.dependant) == expected, route_key


@pytest.mark.parametrize("role", ROLES)
def test_every_route_admits_exactly_the_roles_that_may_use_it(client, role):
    key = new_key(client, role)
    wrong = []
    for (method, path), access in ACCESS.items():
        status = call(client, method, path, key).status_code
        if may(role, access) and status in (401, 403):
            wrong.append(f"{method} {path}: {role} refused with {status}")
        if not may(role, access) and status != 403:
            wrong.append(f"{method} {path}: {role} answered {status}, expected 403")
    assert not wrong, "\n".join(wrong)


def test_every_keyed_route_refuses_a_missing_unknown_or_revoked_key(make_service):
    # every refusal counts against this client's address: let them all through here
    client = TestClient(make_service(auth_failure_burst=10_000).app)
    viewer = new_key(client, "viewer")
    victim = client.get("/api/v1/keys", headers={"X-API-Key": ADMIN}).json()["data"][0]
    assert client.delete(f"/api/v1/keys/{victim['id']}",
                         headers={"X-API-Key": ADMIN}).status_code == 200
    expected = {None: "Missing API key (header X-API-Key)", "lw_not-a-key": "Invalid or "
                "revoked API key", viewer: "Invalid or revoked API key"}
    for method, path in ACCESS:
        for key, detail in expected.items():
            response = call(client, method, path, key)
            assert (response.status_code, response.json()) == (401, {"detail": detail}), \
                (method, path)
    for method, path in PUBLIC:
        assert call(client, method, path, None).status_code == 200, path


def test_a_key_is_refused_at_once_when_revoked_here_and_within_the_cache_time_elsewhere(
        service):
    client = TestClient(service.app)
    now = [0.0]
    service.state.keys.clock = lambda: now[0]
    cache_s = service.state.settings.auth_cache_s
    here, elsewhere = new_key(client, "viewer", "revoked here"), new_key(client, "viewer")
    ids = {k["name"]: k["id"] for k in client.get(
        "/api/v1/keys", headers={"X-API-Key": ADMIN}).json()["data"]}
    for key in (here, elsewhere):  # both confirmed by the store, and kept
        assert client.get("/api/v1/me", headers={"X-API-Key": key}).status_code == 200
    assert client.delete(f"/api/v1/keys/{ids['revoked here']}",
                         headers={"X-API-Key": ADMIN}).status_code == 200
    assert client.get("/api/v1/me", headers={"X-API-Key": here}).status_code == 401
    with service.state.store.session() as session:  # as another API replica revokes it
        session.get(ApiKey, ids["viewer key"]).revoked_at = T0
    now[0] = cache_s  # still kept: admitted
    assert client.get("/api/v1/me", headers={"X-API-Key": elsewhere}).status_code == 200
    now[0] = cache_s + 0.1
    assert client.get("/api/v1/me", headers={"X-API-Key": elsewhere}).status_code == 401


def test_no_route_queries_the_store_on_the_event_loop(make_service):
    """A statement run by the event loop's thread holds up every request meanwhile."""
    service = make_service(auth_failure_burst=10_000)
    client = TestClient(service.app)
    on_loop = []

    def note(_connection: Any, _cursor: Any, statement: str, *_: Any) -> None:
        try:
            asyncio.get_running_loop()
        except RuntimeError:  # a worker thread
            return
        on_loop.append(statement)

    event.listen(service.state.store.engine, "before_cursor_execute", note)
    viewer = new_key(client, "viewer")
    for method, path in ACCESS:
        for key in (ADMIN, viewer, "lw_not-a-key"):
            assert call(client, method, path, key).status_code < 500, (method, path)
    assert not on_loop, on_loop


def test_the_schema_needs_a_key_and_the_docs_pages_load_only_loopwatch_files(client):
    assert client.get("/openapi.json").status_code == 401
    schema = client.get("/openapi.json", headers={"X-API-Key": new_key(client, "historian")})
    assert schema.status_code == 200
    assert "/api/v1/ingest" in schema.json()["paths"]
    for path in ("/docs", "/redoc"):
        page = client.get(path)
        assert page.status_code == 200
        sources = re.findall(r'(?:src|href)="([^"]+)"', page.text)
        assert sources and all(s.startswith("/") for s in sources), sources
        assert all(client.get(s).status_code == 200 for s in sources if s.startswith("/static/"))


def test_keys_are_stored_as_hashes_only(service, client):
    key = new_key(client, "operator", "console 3")
    with service.state.store.session() as session:
        row = session.scalars(select(ApiKey).where(ApiKey.name == "console 3")).one()
        assert row.key_hash == salted_hash(hashlib.sha256(key.encode()).hexdigest(), row.salt)
        dump = " ".join(str(v) for r in session.execute(text("SELECT * FROM api_keys"))
                        for v in r)
    assert key not in dump and ADMIN not in dump
    assert key.startswith(f"lw_{row.key_id}_")


# ----------------------------------------------------------------------------- limits


def test_token_bucket_admits_the_burst_plus_the_rate_over_time():
    """Requests every millisecond for 10 s: the analytic count is burst + rate * T."""
    now = [0.0]
    limiter = RateLimiter(rate_per_s=7.0, burst=25, clock=lambda: now[0])
    granted = 0
    for step in range(10_001):
        now[0] = step * 1e-3
        granted += limiter.acquire("k") == 0.0
    assert granted == 25 + 70
    assert limiter.acquire("other key") == 0.0
    wait = limiter.acquire("k")
    assert 0 < wait <= 1 / 7.0
    now[0] += wait
    assert limiter.acquire("k") == 0.0


def test_a_key_over_its_rate_gets_429_with_retry_after_and_others_go_on(make_service):
    client = TestClient(make_service(rate_limit_per_s=0.5, rate_limit_burst=3).app)
    viewer = new_key(client, "viewer", "wallboard")
    statuses = [client.get("/api/v1/loops", headers={"X-API-Key": viewer}).status_code
                for _ in range(4)]
    assert statuses == [200, 200, 200, 429]
    refused = client.get("/api/v1/loops", headers={"X-API-Key": viewer})
    assert refused.headers["Retry-After"] == "2"
    assert refused.json()["detail"] == ("Rate limit of 0.5 requests/s (burst 3) exceeded for "
                                        "key 'wallboard'; retry later")
    other = new_key(client, "viewer")
    assert client.get("/api/v1/loops", headers={"X-API-Key": other}).status_code == 200


def test_a_body_over_the_limit_is_refused_with_413_announced_or_streamed(make_service):
    svc = make_service(max_body_bytes=1000)
    client = TestClient(svc.app)
    historian = {"X-API-Key": new_key(client, "historian")}
    items = [{"timestamp": T0 - k, "value": 1.0} for k in range(40)]
    batch = [{"tag": "FIC-1.PV", "items": items}]
    announced = client.post("/api/v1/ingest", json=batch, headers=historian)
    assert announced.status_code == 413
    assert announced.json() == {
        "detail": "Request body larger than the limit of 1000 bytes (LOOPWATCH_MAX_BODY_BYTES)"}
    streamed = client.post("/api/v1/ingest/csv", headers=historian,
                           content=(b"time,FIC-1.PV\n%d,1.0\n" % (T0 - k) for k in range(100)))
    assert streamed.status_code == 413
    assert "limit of 1000 bytes" in streamed.json()["detail"]
    assert svc.state.accounting().received == 0
    small = [{"tag": "FIC-1.PV", "items": items[:3]}]
    assert client.post("/api/v1/ingest", json=small, headers=historian).status_code == 200


def test_a_batch_over_the_sample_limit_is_refused_with_422(make_service):
    svc = make_service(max_batch_samples=10)
    client = TestClient(svc.app)
    batch = [{"tag": "FIC-1.PV", "items": [{"timestamp": T0 - k, "value": 1.0}
                                           for k in range(11)]}]
    response = client.post("/api/v1/ingest", json=batch,
                           headers={"X-API-Key": new_key(client, "historian")})
    assert response.status_code == 422
    assert response.json()["detail"] == ("batch of 11 samples is longer than the limit of 10 "
                                         "(LOOPWATCH_MAX_BATCH_SAMPLES); split it")
    assert svc.state.accounting().received == 0


# ----------------------------------------------------------------------------- headers, CORS


class _PageAudit(HTMLParser):
    """Everything in a page that a CSP without 'unsafe-inline' would block."""

    def __init__(self) -> None:
        super().__init__()
        self.blocked: list[str] = []
        self._in_script = False

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        names = dict(attrs)
        if tag == "script" and "src" not in names:
            self._in_script = True
            self.blocked.append("inline <script>")
        if tag == "style":
            self.blocked.append("<style> element")
        self.blocked += [f"{name}= on <{tag}>" for name in names
                         if name == "style" or name.startswith("on")]
        for name in ("src", "href"):
            if (names.get(name) or "").startswith(("http:", "https:", "//", "javascript:")):
                self.blocked.append(f"{name}={names[name]} on <{tag}>")


def test_the_dashboard_needs_nothing_the_content_security_policy_forbids(client):
    page = client.get("/")
    assert page.headers["Content-Security-Policy"] == CONTENT_SECURITY_POLICY
    assert "'unsafe-inline'" not in CONTENT_SECURITY_POLICY
    assert "script-src 'self'" in CONTENT_SECURITY_POLICY
    for path in ("/", "/docs", "/redoc"):
        audit = _PageAudit()
        audit.feed(client.get(path).text)
        assert audit.blocked == [], path
    for name in STATIC_FILES:
        if name.endswith(".js") and not name.startswith("vendor/"):  # ours, not Swagger's
            script = client.get(f"/static/{name}").text
            assert not re.search(r"\beval\(|new Function\(|\.innerHTML\s*=", script), name


@pytest.mark.parametrize("path", ["/", "/healthz", "/api/v1/loops", "/api/v1/nowhere"])
def test_every_answer_carries_the_secure_headers(client, path):
    headers = client.get(path).headers
    assert headers["X-Content-Type-Options"] == "nosniff"
    assert headers["X-Frame-Options"] == "DENY"
    assert headers["Referrer-Policy"] == "no-referrer"
    assert "frame-ancestors 'none'" in headers["Content-Security-Policy"]
    assert "Strict-Transport-Security" not in headers  # plain HTTP: browsers ignore it
    assert (headers.get("Cache-Control") == "no-store") == path.startswith("/api/")


def test_https_answers_carry_hsts(service):
    client = TestClient(service.app, base_url="https://testserver")
    assert client.get("/healthz").headers["Strict-Transport-Security"] == "max-age=31536000"


def test_cors_admits_only_the_configured_origins(make_service):
    closed = TestClient(make_service().app)
    asked = {"Origin": "https://ops.example", "Access-Control-Request-Method": "GET",
             "Access-Control-Request-Headers": "X-API-Key"}
    assert "access-control-allow-origin" not in closed.options("/api/v1/loops",
                                                                headers=asked).headers
    client = TestClient(make_service(cors_origins=["https://ops.example"]).app)
    preflight = client.options("/api/v1/loops", headers=asked)
    assert preflight.status_code == 200
    assert preflight.headers["access-control-allow-origin"] == "https://ops.example"
    assert "x-api-key" in preflight.headers["access-control-allow-headers"].lower()
    assert "access-control-allow-credentials" not in preflight.headers
    foreign = client.options("/api/v1/loops", headers={**asked, "Origin": "https://evil.example"})
    assert foreign.status_code == 400
    assert "access-control-allow-origin" not in foreign.headers
    simple = client.get("/healthz", headers={"Origin": "https://evil.example"})
    assert "access-control-allow-origin" not in simple.headers


# ----------------------------------------------------------------------------- settings


@pytest.mark.parametrize(("changes", "message"), [
    ({"api_key": None}, "LOOPWATCH_API_KEY must be set"),
    ({"api_key": "dev-insecure-key"}, "LOOPWATCH_API_KEY must be set"),
    ({"database_url": "postgresql://loopwatch:loopwatch@db/loopwatch"},
     "LOOPWATCH_DATABASE_URL has a default password for user 'loopwatch'"),
    ({"database_url": "postgresql://plant:postgres@db/loopwatch"},
     "LOOPWATCH_DATABASE_URL has a default password for user 'plant'"),
    ({"cors_origins": "*"}, "LOOPWATCH_CORS_ORIGINS may not be '*' in production"),
])
def test_production_refuses_default_secrets_and_a_cors_wildcard(monkeypatch, changes, message):
    monkeypatch.setenv("LOOPWATCH_API_KEY", "a-long-enough-secret-key")
    for name, value in changes.items():
        if value is None:
            monkeypatch.delenv(f"LOOPWATCH_{name.upper()}")
        else:
            monkeypatch.setenv(f"LOOPWATCH_{name.upper()}", value)
    Settings()  # development takes them
    monkeypatch.setenv("LOOPWATCH_ENVIRONMENT", "production")
    with pytest.raises(ValueError, match=re.escape(message)):
        Settings()


def test_production_takes_real_secrets_and_listed_origins(monkeypatch):
    monkeypatch.setenv("LOOPWATCH_ENVIRONMENT", "production")
    monkeypatch.setenv("LOOPWATCH_API_KEY", "a-long-enough-secret-key")
    monkeypatch.setenv("LOOPWATCH_DATABASE_URL", "postgresql://plant:Xq7-long-pw@db/lw")
    monkeypatch.setenv("LOOPWATCH_CORS_ORIGINS", "https://ops.example, http://hmi-3:8080")
    settings = Settings()
    assert settings.cors_origins == ["https://ops.example", "http://hmi-3:8080"]
    assert settings.resolved_database_url == "postgresql://plant:Xq7-long-pw@db/lw"
    for shown in (repr(settings), str(settings), settings.model_dump_json()):
        assert "Xq7-long-pw" not in shown and "a-long-enough-secret-key" not in shown


def test_a_cors_origin_with_a_path_is_refused():
    with pytest.raises(ValueError, match="must be scheme://host"):
        Settings(cors_origins=["https://ops.example/"])


def test_no_key_reaches_the_logs(make_service, caplog):
    caplog.set_level(logging.DEBUG)
    caplog.set_level(logging.DEBUG, logger="sqlalchemy")  # SQL and its parameters too
    svc = make_service(rate_limit_burst=10, rate_limit_per_s=0.1)
    client = TestClient(svc.app)
    keys = [ADMIN]
    for role in ROLES:
        keys.append(new_key(client, role))
        for _ in range(11):  # the last one over the rate limit
            client.get("/api/v1/loops", headers={"X-API-Key": keys[-1]})
    client.get("/api/v1/loops", headers={"X-API-Key": keys[-1] + "x"})
    listed = client.get("/api/v1/keys", headers={"X-API-Key": ADMIN}).json()["data"]
    client.delete(f"/api/v1/keys/{listed[0]['id']}", headers={"X-API-Key": ADMIN})
    client.get("/api/v1/loops", headers={"X-API-Key": keys[-1]})
    assert "FROM api_keys" in caplog.text  # the capture sees the key look-ups
    logged = caplog.text + "".join(str(r.args) for r in caplog.records)
    for key in keys:
        assert key not in logged
        assert key[16:] not in logged  # not even without the key id the list shows
