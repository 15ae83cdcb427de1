"""Issue 20: no request may stall the API, no input may give a 5xx, no configured loop
may be lost on restart, and no secret is echoed or stored in the clear.

Every test runs the real application: through :class:`TestClient`, or served by
uvicorn on a loopback port with the settings ``loopwatch serve`` uses.
"""

from __future__ import annotations

import asyncio
import hashlib
import inspect
import json
import os
import re
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import uvicorn
from fastapi.dependencies.models import Dependant
from fastapi.testclient import TestClient
from pydantic import ValidationError
from sqlalchemy import create_engine, select, text

from service.api.deps import get_session
from service.auth import authenticate
from service.config import ConfigError, PlantConfig, Settings
from service.server import Service, build_service
from service.store.db import migrate
from service.store.models import ApiKey
from tests.service.api.test_model_check import case_batch
from tests.service.test_api import ADMIN, T0, plant
from tests.service.test_security import api_routes

HEADERS = {"X-API-Key": ADMIN}
NEW_LOOP = {"name": "Added by API", "unit": "u1", "ts": 1.0,
            "tags": {"op": "NEW.OP", "pv": "NEW.PV"}, "ranges": {"op": [0, 100], "pv": [0, 40]},
            "controller": {"type": "PI", "Kc": 0.5, "Ti": 8.0}}


def sqlite_service(tmp_path: Path, **overrides: Any) -> Service:
    """The two-loop test plant on SQLite with ``overrides`` of the settings."""
    settings = Settings(**{"database_url": f"sqlite:///{tmp_path / 'loopwatch.db'}",
                           "api_key": ADMIN, "window_s": 3600, "buffer_horizon_s": 7200,
                           **overrides})
    return build_service(settings, plant(), executor=ThreadPoolExecutor(1), clock=lambda: T0)


@pytest.fixture
def svc(tmp_path) -> Iterator[Service]:
    service = sqlite_service(tmp_path)
    yield service
    service.executor.shutdown()
    service.state.store.close()


@contextmanager
def served(service: Service) -> Iterator[tuple[str, int]]:
    """Serve ``service.app`` with ``loopwatch serve``'s uvicorn settings on a free port."""
    from service.server import uvicorn_config

    config = uvicorn_config(service.app, service.state.settings.model_copy(update={"port": 0}))
    config.log_config = None
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    while not server.started:
        if not thread.is_alive():
            raise RuntimeError("uvicorn did not start")
        threading.Event().wait(0.01)
    port = server.servers[0].sockets[0].getsockname()[1]
    try:
        yield "127.0.0.1", port
    finally:
        server.should_exit = True
        thread.join(10)


def http_response(sock: socket.socket) -> tuple[int, dict[str, str], bytes]:
    """Read one HTTP/1.1 response with a Content-Length from ``sock``."""
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(65536)
        if not chunk:
            raise ConnectionError(f"connection closed after {data!r}")
        data += chunk
    head, body = data.split(b"\r\n\r\n", 1)
    lines = head.decode("latin-1").split("\r\n")
    headers = {k.strip().lower(): v.strip() for k, v in
               (line.split(":", 1) for line in lines[1:])}
    while len(body) < int(headers.get("content-length", 0)):
        body += sock.recv(65536)
    return int(lines[0].split()[1]), headers, body


# ----------------------------------------------------------------------------- 1: stalls


def _uses_session(dependant: Dependant) -> bool:
    return any(d.call is get_session or _uses_session(d) for d in dependant.dependencies)


def test_no_route_on_the_event_loop_waits_for_the_store(svc):
    """A coroutine route runs on the event loop: a store call there (a pool wait, a
    query) stalls every other request, so every route using a session is a plain def
    (run in the thread pool)."""
    on_loop = [route.path for route in api_routes(svc.app.routes)
               if inspect.iscoroutinefunction(route.endpoint) and _uses_session(route.dependant)]
    assert on_loop == []


def test_one_key_runs_one_expensive_analysis_at_a_time(tmp_path):
    from analytics.model_check.cases import hidden_effect_case

    service = sqlite_service(tmp_path)
    service.state.ingest(case_batch(hidden_effect_case("gain_mismatch", 3, samples=3000)))
    client = TestClient(service.app)
    viewer = {"X-API-Key": client.post("/api/v1/keys", json={"name": "v", "role": "viewer"},
                                       headers=HEADERS).json()["key"]}
    url = "/api/v1/loops/FIC-1/model-check"
    with ThreadPoolExecutor(2) as pool:
        answers = list(pool.map(lambda _: client.post(url, headers=viewer), range(2)))
    assert sorted(a.status_code for a in answers) == [200, 429], [a.text for a in answers]
    refused = next(a for a in answers if a.status_code == 429)
    assert int(refused.headers["Retry-After"]) >= 1
    assert "analysis" in refused.json()["detail"]
    assert client.post(url, headers=viewer).status_code == 200  # free again afterwards
    viewers = [{"X-API-Key": client.post("/api/v1/keys", json={"name": f"v{i}", "role": "viewer"},
                                         headers=HEADERS).json()["key"]} for i in range(3)]
    with ThreadPoolExecutor(3) as pool:  # one analysis process admits two at once
        answers = list(pool.map(lambda k: client.post(url, headers=k), viewers))
    assert sorted(a.status_code for a in answers) == [200, 200, 503], [a.text for a in answers]
    assert "Retry-After" in next(a for a in answers if a.status_code == 503).headers
    service.state.close_analyses()
    service.executor.shutdown()
    service.state.store.close()


# ----------------------------------------------------------------------------- 2: integers

TOO_BIG = 2 ** 63
OVERFLOWS = [
    ("GET", f"/api/v1/loops?offset={TOO_BIG}", "offset"),
    ("GET", f"/api/v1/alarms?offset={TOO_BIG}", "offset"),
    ("GET", f"/api/v1/tickets?offset={TOO_BIG}", "offset"),
    ("GET", f"/api/v1/loops/FIC-1/analyses?offset={TOO_BIG}", "offset"),
    ("GET", f"/api/v1/alarms/{TOO_BIG}", "alarm_id"),
    ("POST", f"/api/v1/alarms/{TOO_BIG}/acknowledge", "alarm_id"),
    ("POST", f"/api/v1/alarms/{TOO_BIG}/unshelve", "alarm_id"),
    ("POST", f"/api/v1/alarms/{TOO_BIG}/out-of-service", "alarm_id"),
    ("POST", f"/api/v1/alarms/{TOO_BIG}/in-service", "alarm_id"),
    ("GET", f"/api/v1/tickets/{TOO_BIG}", "ticket_id"),
    ("GET", f"/api/v1/tickets/{TOO_BIG}/cmms", "ticket_id"),
    ("PATCH", f"/api/v1/tickets/{TOO_BIG}", "ticket_id"),
    ("DELETE", f"/api/v1/keys/{TOO_BIG}", "key_id"),
]


@pytest.mark.parametrize(("method", "url", "name"), OVERFLOWS)
def test_integers_the_store_cannot_hold_get_422_naming_the_parameter(svc, method, url, name):
    client = TestClient(svc.app, raise_server_exceptions=False)
    body = {"note": "x"} if method == "POST" else ({"status": "closed"}
                                                   if method == "PATCH" else None)
    response = client.request(method, url, headers=HEADERS, json=body)
    assert response.status_code == 422, response.text
    assert any(e["loc"][-1] == name for e in response.json()["detail"]), response.text


def test_an_unexpected_error_is_a_json_500_logged_once_and_keeps_the_connection(svc, caplog):
    def broken() -> None:
        raise RuntimeError("a bug")

    svc.app.add_api_route("/broken", broken, include_in_schema=False)
    with served(svc) as (host, port), socket.create_connection((host, port), 10) as sock:
        sock.sendall(b"GET /broken HTTP/1.1\r\nHost: x\r\n\r\n")
        status, headers, body = http_response(sock)
        assert status == 500 and json.loads(body) == {"detail": "Internal server error"}
        assert headers.get("connection") != "close"
        sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
        assert http_response(sock)[0] == 200  # the same keep-alive connection
    logged = [r for r in caplog.records if r.exc_info and "a bug" in str(r.exc_info[1])]
    assert len(logged) == 1


# ----------------------------------------------------------------------------- 3: restart


def test_loops_added_through_the_api_keep_taking_data_after_a_restart(make_service):
    first = make_service()
    client = TestClient(first.app)
    assert client.put("/api/v1/loops/NEW-1", json=NEW_LOOP, headers=HEADERS).status_code == 200
    first.state.store.close()

    again = make_service()
    assert "NEW-1" in {loop.id for loop in again.state.registry.plant.loops}
    report = again.state.ingest([{"tag": "NEW.PV", "items": [{"timestamp": T0, "value": 1.0}]}])
    assert report.stored == 1 and not report.refused
    client = TestClient(again.app)
    clash = client.put("/api/v1/loops/NEW-2", json={**NEW_LOOP, "tags": {"pv": "NEW.PV"}},
                       headers=HEADERS)
    assert clash.status_code == 409, clash.text
    assert clash.json()["detail"] == "Tag 'NEW.PV' belongs to loop 'NEW-1'"
    assert client.get("/api/v1/loops/NEW-2", headers=HEADERS).status_code == 404


def test_a_plant_file_claiming_the_tag_of_an_api_loop_is_refused_at_start(tmp_path):
    first = sqlite_service(tmp_path)
    TestClient(first.app).put("/api/v1/loops/NEW-1", json=NEW_LOOP, headers=HEADERS)
    first.state.store.close()
    grown = plant().model_dump()
    grown["loops"].append({**NEW_LOOP, "id": "FILE-3", "tags": {"pv": "NEW.PV"}})
    settings = Settings(database_url=f"sqlite:///{tmp_path / 'loopwatch.db'}", api_key=ADMIN)
    refusal = re.escape("loops.FILE-3: tag 'NEW.PV' belongs to loop 'NEW-1'")
    with pytest.raises(ConfigError, match=refusal):
        build_service(settings, PlantConfig.model_validate(grown),
                      executor=ThreadPoolExecutor(1), clock=lambda: T0)


# ----------------------------------------------------------------------------- 4, 5: ingest


def test_a_huge_malformed_batch_is_refused_with_a_short_report(svc):
    client = TestClient(svc.app)
    huge = client.post("/api/v1/ingest", content=b"[" + b"1," * 999_999 + b"1]",
                       headers={**HEADERS, "Content-Type": "application/json"})
    assert huge.status_code == 422 and len(huge.content) < 2000, huge.content[:300]
    assert "1000000 entries" in huge.json()["detail"]
    many_errors = client.post("/api/v1/ingest", json=[1] * 100_000, headers=HEADERS)
    assert many_errors.status_code == 422 and len(many_errors.content) < 5000
    detail = many_errors.json()["detail"]
    assert detail.startswith("invalid batch: batch[0]: ") and "(and 99990 more)" in detail


def test_a_wide_csv_over_the_column_limit_is_refused(svc):
    client = TestClient(svc.app)
    header = "time," + ",".join(f"T{i}" for i in range(100_000))
    response = client.post("/api/v1/ingest/csv", content=f"{header}\n".encode(),
                           headers={**HEADERS, "Content-Type": "text/csv"})
    assert response.status_code == 422
    assert response.json()["detail"] == ("CSV row 1: 100001 columns, more than the limit of "
                                         "10000; split the upload")
    duplicate = "time," + ",".join(f"T{i}" for i in range(5000)) + ",T17\n1" + ",1" * 5001
    response = client.post("/api/v1/ingest/csv", content=duplicate.encode(),
                           headers={**HEADERS, "Content-Type": "text/csv"})
    assert response.json()["detail"] == "CSV row 1, column 5002: duplicate column 'T17'"


# ----------------------------------------------------------------------------- 6: times


def test_a_time_past_year_9999_gets_422(svc):
    client = TestClient(svc.app, raise_server_exceptions=False)
    for url in ("/api/v1/loops/FIC-1/plots/trend?start=0&end=253402300800",
                "/api/v1/loops/FIC-1/data?start=0&end=253402300800"):
        response = client.get(url, headers=HEADERS)
        assert response.status_code == 422, response.text
        assert response.json()["detail"][0]["loc"] == ["query", "end"]


# ----------------------------------------------------------------------------- 7, 8: secrets

SECRET = "Sup3rS3cretK3y!"


def test_the_production_refusal_never_echoes_the_key():
    with pytest.raises(ValidationError) as refused:
        Settings(environment="production", api_key=SECRET)
    assert SECRET not in str(refused.value) and "LOOPWATCH_API_KEY" in str(refused.value)
    env = {**os.environ, "LOOPWATCH_ENVIRONMENT": "production", "LOOPWATCH_API_KEY": SECRET,
           "PYTHONPATH": str(Path(__file__).parents[2])}
    run = subprocess.run([sys.executable, "-m", "service.cli", "serve"], env=env,
                         capture_output=True, text=True, timeout=120)
    assert run.returncode != 0 and "LOOPWATCH_API_KEY" in run.stderr
    assert SECRET not in run.stderr + run.stdout


def test_whitespace_keys_are_refused_in_production():
    with pytest.raises(ValidationError, match="LOOPWATCH_API_KEY"):
        Settings(environment="production", api_key=" " * 20)
    with pytest.raises(ValidationError, match="LOOPWATCH_API_KEY"):
        Settings(environment="production", api_key="  short-but-padded  ")


def test_keys_are_stored_salted_with_a_key_id_that_is_not_secret(svc):
    client = TestClient(svc.app)
    created = [client.post("/api/v1/keys", json={"name": f"k{i}", "role": "viewer"},
                           headers=HEADERS).json() for i in range(2)]
    with svc.state.store.session() as session:
        rows = {row.name: row for row in session.scalars(select(ApiKey))}
        dump = " ".join(str(v) for r in session.execute(text("SELECT * FROM api_keys"))
                        for v in r)
    for made in created:
        row = rows[made["name"]]
        assert made["key_id"] == row.key_id and made["key"].startswith(f"lw_{row.key_id}_")
        secret = made["key"].removeprefix(f"lw_{row.key_id}_")
        assert row.key_hash != hashlib.sha256(made["key"].encode()).hexdigest()
        assert secret[:4] not in dump
    assert rows["k0"].salt != rows["k1"].salt
    assert rows["bootstrap"].key_hash != hashlib.sha256(ADMIN.encode()).hexdigest()
    assert ADMIN[:6] not in dump


def test_each_start_without_a_configured_key_leaves_one_active_generated_admin_key(tmp_path):
    """Issue 19: a key generated for a run (no LOOPWATCH_API_KEY) revokes the keys generated
    for earlier runs; a configured key and keys made through the API are kept."""
    configured = sqlite_service(tmp_path)
    TestClient(configured.app).post("/api/v1/keys", json={"name": "ops", "role": "admin"},
                                    headers=HEADERS)
    configured.executor.shutdown()
    configured.state.store.close()
    keys = []
    for _ in range(3):
        svc = sqlite_service(tmp_path, api_key=None)
        assert svc.key_generated
        keys.append(svc.admin_key)
        with svc.state.store.session() as session:
            active = sorted(row.name for row in session.scalars(
                select(ApiKey).where(ApiKey.revoked_at.is_(None))))
            assert [authenticate(session, key) is not None for key in keys] == (
                [False] * (len(keys) - 1) + [True])
        svc.executor.shutdown()
        svc.state.store.close()
        assert active == ["bootstrap", "bootstrap, this run only", "ops"]


@pytest.fixture(params=["sqlite", "postgresql"])
def empty_database(request: pytest.FixtureRequest, tmp_path) -> Iterator[str]:
    """The URL of an empty database (no schema) on SQLite or a real PostgreSQL."""
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'old.db'}"
        return
    server_url = request.getfixturevalue("postgres_url")
    admin = create_engine(server_url, isolation_level="AUTOCOMMIT")
    with admin.connect() as connection:
        connection.execute(text("CREATE DATABASE loopwatch_before_0004"))
    yield server_url.rsplit("/", 1)[0] + "/loopwatch_before_0004"
    with admin.connect() as connection:
        connection.execute(text("DROP DATABASE loopwatch_before_0004 WITH (FORCE)"))
    admin.dispose()


def test_keys_and_loops_stored_before_migration_0004_are_kept(empty_database):
    engine = create_engine(empty_database)
    migrate(engine, "0003")
    old_key = "lw_" + "A" * 40
    with engine.begin() as connection:
        connection.execute(text(
            "INSERT INTO api_keys (name, role, key_hash, prefix, created_at) "
            "VALUES ('old', 'viewer', :hash, :prefix, 0)"),
            {"hash": hashlib.sha256(old_key.encode()).hexdigest(), "prefix": old_key[:8]})
        connection.execute(text("INSERT INTO units (id, name) VALUES ('u1', 'Unit 1')"))
        connection.execute(text(
            "INSERT INTO loops (id, name, unit_id, config, created_at, updated_at) "
            "VALUES ('NEW-1', 'old', 'u1', :config, 0, 0)"),
            {"config": json.dumps({**NEW_LOOP, "id": "NEW-1"})})
        connection.execute(text("INSERT INTO tags (name, loop_id, signal) VALUES "
                                "('NEW.OP', 'NEW-1', 'op'), ('NEW.PV', 'NEW-1', 'pv')"))
    engine.dispose()
    service = build_service(Settings(database_url=empty_database, api_key=ADMIN), plant(),
                            executor=ThreadPoolExecutor(1), clock=lambda: T0)
    with service.state.store.session() as session:
        row = authenticate(session, old_key)
        assert row is not None and row.name == "old" and row.key_id.startswith("ext-")
        assert authenticate(session, old_key + "x") is None
    assert "NEW-1" in {loop.id for loop in service.state.registry.plant.loops}
    service.executor.shutdown()
    service.state.store.close()


# ----------------------------------------------------------------------------- 9: slow clients


def test_slow_clients_are_cut_off(tmp_path):
    from service.server import uvicorn_config

    service = sqlite_service(tmp_path, header_timeout_s=0.5, body_timeout_s=0.5)
    config = uvicorn_config(service.app, service.state.settings)
    assert config.limit_concurrency == service.state.settings.max_connections
    assert config.timeout_keep_alive <= 5
    with served(service) as address:
        with socket.create_connection(address, 10) as slow_headers:
            slow_headers.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n")
            slow_headers.settimeout(10)
            assert slow_headers.recv(4096) == b""  # closed, the headers never finished
        with socket.create_connection(address, 10) as slow_body:
            slow_body.sendall(b"POST /api/v1/ingest HTTP/1.1\r\nHost: x\r\nX-API-Key: "
                              + ADMIN.encode() + b"\r\nContent-Type: application/json\r\n"
                              b"Content-Length: 100\r\n\r\n[")
            slow_body.settimeout(10)
            status, headers, body = http_response(slow_body)
            assert status == 408 and headers["connection"] == "close"
            assert "body" in json.loads(body)["detail"]
    service.executor.shutdown()
    service.state.store.close()


# ----------------------------------------------------------------------------- 10, 11: keys


def test_failed_authentication_is_limited_per_client_address(tmp_path):
    service = sqlite_service(tmp_path, auth_failure_burst=5, auth_failure_per_s=0.01)
    client = TestClient(service.app)
    answers = [client.get("/api/v1/loops", headers={"X-API-Key": f"wrong-{i}"})
               for i in range(8)]
    assert [a.status_code for a in answers] == [401] * 5 + [429] * 3
    assert int(answers[-1].headers["Retry-After"]) >= 1
    assert "authentication" in answers[-1].json()["detail"]
    elsewhere = TestClient(service.app, client=("10.0.0.2", 50000))
    assert elsewhere.get("/api/v1/loops", headers={"X-API-Key": "wrong"}).status_code == 401
    assert elsewhere.get("/api/v1/loops", headers=HEADERS).status_code == 200
    service.executor.shutdown()
    service.state.store.close()


def test_the_last_admin_key_cannot_be_revoked(svc):
    client = TestClient(svc.app)
    own = client.get("/api/v1/keys", headers=HEADERS).json()["data"][0]
    refused = client.delete(f"/api/v1/keys/{own['id']}", headers=HEADERS)
    assert refused.status_code == 409
    assert refused.json()["detail"] == ("Key 1 is the last active admin key; create another "
                                        "admin key before revoking it")
    second = client.post("/api/v1/keys", json={"name": "a2", "role": "admin"}, headers=HEADERS)
    assert client.delete(f"/api/v1/keys/{own['id']}", headers=HEADERS).status_code == 200
    assert client.get("/api/v1/loops", headers=HEADERS).status_code == 401
    assert client.get("/api/v1/loops",
                      headers={"X-API-Key": second.json()["key"]}).status_code == 200


# ----------------------------------------------------------------------------- 12: schema


def test_the_schema_documents_every_error_the_api_answers(svc):
    schema = TestClient(svc.app).get("/openapi.json", headers=HEADERS).json()
    error = schema["components"]["schemas"]["Error"]
    assert set(error["properties"]) == {"detail"}
    for path, operations in schema["paths"].items():
        if path == "/healthz":  # no key, no parameters: it answers 200
            continue
        for method, operation in operations.items():
            codes = set(operation["responses"])
            where = f"{method.upper()} {path}"
            assert {"401", "422", "429"} <= codes, where
            if "requestBody" in operation:
                assert "413" in codes, where
            assert "Retry-After" in operation["responses"]["429"]["headers"], where
            ref = operation["responses"]["422"]["content"]["application/json"]["schema"]
            assert ref == {"$ref": "#/components/schemas/Error"}, where


def test_a_detail_string_and_a_validation_list_both_fit_the_error_schema(svc):
    schema = TestClient(svc.app).get("/openapi.json", headers=HEADERS).json()
    detail = schema["components"]["schemas"]["Error"]["properties"]["detail"]
    kinds = [option.get("type") or option.get("$ref") for option in detail["anyOf"]]
    assert "string" in kinds and "array" in kinds


def test_an_analysis_slot_is_free_before_its_answer_is_sent(tmp_path):
    """A client that sends its next model check as soon as it has the answer must find
    its key's slot free (the load benchmark's clients got 429 now and then)."""
    from analytics.model_check.cases import hidden_effect_case

    service = sqlite_service(tmp_path)
    service.state.ingest(case_batch(hidden_effect_case("gain_mismatch", 3, samples=3000)))
    client = TestClient(service.app)
    created = client.post("/api/v1/keys", json={"name": "v", "role": "viewer"},
                          headers=HEADERS).json()
    slot_at_answer: list[tuple[int, str | None]] = []

    async def receive() -> dict[str, Any]:
        return {"type": "http.request", "body": b"", "more_body": False}

    async def send(message: dict[str, Any]) -> None:
        if message["type"] == "http.response.start":
            taken = service.state.analyses.acquire(created["id"])
            if taken is None:
                service.state.analyses.release(created["id"])
            slot_at_answer.append((message["status"], taken))

    path = "/api/v1/loops/FIC-1/model-check"
    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1",
             "method": "POST", "scheme": "http", "path": path, "raw_path": path.encode(),
             "query_string": b"", "root_path": "", "client": ("127.0.0.1", 50000),
             "server": ("127.0.0.1", 8000),
             "headers": [(b"x-api-key", created["key"].encode()), (b"content-length", b"0")]}
    asyncio.run(service.app(scope, receive, send))
    assert slot_at_answer == [(200, None)]
    service.state.close_analyses()
    service.executor.shutdown()
    service.state.store.close()


# ----------------------------------------------------------------------------- commits


def test_a_write_is_answered_only_after_its_commit(svc, monkeypatch):
    """A route's transaction commits before its answer is sent: a client that reads
    right after a 200 sees its write (the dashboard redraws an acknowledged alarm from
    the next GET), and a commit that fails is a 500, never a 200 for a lost write.
    FastAPI's default ends a ``yield`` dependency only after the response is sent."""
    from sqlalchemy import event
    from sqlalchemy.orm import Session

    client = TestClient(svc.app, raise_server_exceptions=False)

    def wrote(session: Session, _context: object) -> None:
        session.info["wrote"] = True

    def refuse(session: Session) -> None:
        if session.info.get("wrote"):  # the key's insert; reads commit nothing
            raise RuntimeError("the disk is full")

    event.listen(Session, "after_flush", wrote)
    event.listen(Session, "before_commit", refuse)
    try:
        answer = client.post("/api/v1/keys", json={"name": "lost", "role": "viewer"},
                             headers=HEADERS)
    finally:
        event.remove(Session, "before_commit", refuse)
        event.remove(Session, "after_flush", wrote)
    assert answer.status_code == 500
    names = [k["name"] for k in client.get("/api/v1/keys", headers=HEADERS).json()["data"]]
    assert "lost" not in names
