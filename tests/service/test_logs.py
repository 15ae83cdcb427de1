"""The console of ``loopwatch serve``: a busy port, the announcement once listening, JSON
log lines with the request id, and the audit records."""

import io
import json
import logging
import socket
import threading
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

import pytest
import uvicorn
from fastapi import FastAPI
from fastapi.testclient import TestClient

from service.cli import main
from service.config import ConfigError, Settings
from service.logs import configure_logging
from service.server import AnnouncingServer, build_service, check_port_free
from tests.servers import free_port
from tests.service.test_api import ADMIN, T0, plant, simulated_batch


@pytest.fixture
def busy_port() -> Iterator[int]:
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        yield listener.getsockname()[1]


def test_a_busy_port_is_refused_before_anything_starts(busy_port, capsys):
    with pytest.raises(ConfigError, match=rf"cannot listen on 127.0.0.1:{busy_port}: .*"
                                          rf"choose another port with --port P or "
                                          rf"LOOPWATCH_PORT=P, e.g. --port {busy_port + 1}"):
        check_port_free("127.0.0.1", busy_port)
    # the demo plant is not started: the command ends at once, with the message
    assert main(["serve", "--port", str(busy_port)]) == 2
    captured = capsys.readouterr()
    assert f"cannot listen on 127.0.0.1:{busy_port}" in captured.err
    assert "demo plant" not in captured.out
    check_port_free("127.0.0.1", 0)  # any free port


def test_the_announcement_comes_once_the_server_listens():
    port = free_port()
    answered: list[bool] = []

    def announce() -> None:  # the URL printed must answer already
        with socket.create_connection(("127.0.0.1", port), timeout=5):
            answered.append(True)
        server.should_exit = True

    server = AnnouncingServer(uvicorn.Config(FastAPI(), host="127.0.0.1", port=port,
                                             log_config=None), announce)
    thread = threading.Thread(target=server.run)
    thread.start()
    thread.join(60)
    assert answered == [True]


@pytest.fixture
def json_logs() -> Iterator[io.StringIO]:
    """What the root logger writes as ``serve`` sets it up with LOOPWATCH_LOG_FORMAT=json
    (put back after)."""
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    configure_logging("json")
    stream = io.StringIO()
    root.handlers[0].setStream(stream)  # type: ignore[attr-defined]
    yield stream
    root.handlers[:] = handlers
    root.setLevel(level)


def test_json_lines_carry_the_request_id_and_actions_leave_audit_records(
        tmp_path, json_logs):
    settings = Settings(database_url=f"sqlite:///{tmp_path / 'lw.db'}", api_key=ADMIN,
                        window_s=3600, buffer_horizon_s=7200, ticket_confirmations=1)
    service = build_service(settings, plant(), executor=ThreadPoolExecutor(1), clock=lambda: T0)
    client = TestClient(service.app)
    admin = {"X-API-Key": ADMIN, "X-Request-ID": "req-42"}
    created = client.post("/api/v1/keys", json={"name": "console 3", "role": "operator"},
                          headers=admin)
    assert created.headers["X-Request-ID"] == "req-42"
    operator = {"X-API-Key": created.json()["key"]}
    assert client.get("/healthz").headers["X-Request-ID"]  # one is made up when not given
    loop = {"ts": 1.0, "tags": {"op": "FIC-9.OP", "pv": "FIC-9.PV"}}
    assert client.put("/api/v1/loops/FIC-9", json=loop, headers=admin).status_code == 200
    client.post("/api/v1/ingest", json=simulated_batch(3600), headers=admin)
    service.scheduler.run_once(T0)
    alarm = client.get("/api/v1/alarms", headers=operator).json()["data"][0]
    client.post(f"/api/v1/alarms/{alarm['id']}/acknowledge", json={"note": "seen"},
                headers=operator)
    ticket = client.get("/api/v1/tickets", headers=operator).json()["data"][0]
    maintenance = client.post("/api/v1/keys", json={"name": "planner", "role": "maintenance"},
                              headers=admin).json()
    client.patch(f"/api/v1/tickets/{ticket['id']}", json={"state": "acknowledged"},
                 headers={"X-API-Key": maintenance["key"]})
    client.delete(f"/api/v1/keys/{created.json()['id']}", headers=admin)

    lines = [json.loads(line) for line in json_logs.getvalue().splitlines()]
    audits = [(r["audit"]["actor"], r["audit"]["action"], r["audit"]["target"])
              for r in lines if r["logger"] == "loopwatch.audit"]
    key_id = created.json()["key_id"]
    assert audits == [
        ("bootstrap (admin)", "created API key", f"{key_id} (console 3)"),
        ("bootstrap (admin)", "added loop", "FIC-9"),
        ("console 3 (operator)", "alarm acknowledged", f"alarm {alarm['id']} (FIC-1 oscillation)"),
        ("bootstrap (admin)", "created API key", f"{maintenance['key_id']} (planner)"),
        ("planner (maintenance)", "ticket state change", f"ticket {ticket['id']} (FV-1)"),
        ("bootstrap (admin)", "revoked API key", f"{key_id} (console 3)"),
    ]
    first = next(r for r in lines if r["logger"] == "loopwatch.audit")
    assert first["request_id"] == "req-42" and first["level"] == "INFO"
    assert first["time"].endswith("+00:00")
    service.executor.shutdown()
    service.state.store.close()


@pytest.mark.parametrize("setting, logged", [("failed", ["/missing"]),
                                             ("all", ["/ok", "/missing"]), ("off", [])])
def test_the_console_logs_failed_requests_only_by_default(setting, logged):
    """A dashboard polls every 15 s: a line per answer would bury the console's
    warnings (LOOPWATCH_ACCESS_LOG; uvicorn serving real requests)."""
    import urllib.error
    import urllib.request

    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    configure_logging("json", access_log=setting)
    stream = io.StringIO()
    root.handlers[0].setStream(stream)  # type: ignore[attr-defined]
    app = FastAPI()
    app.get("/ok")(lambda: {"ok": True})
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_config=None))
    thread = threading.Thread(target=server.run)
    thread.start()
    try:
        while not server.started:
            threading.Event().wait(0.01)
        for path in ("/ok", "/missing"):
            try:
                urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=5).read()
            except urllib.error.HTTPError as error:
                assert error.code == 404
    finally:
        server.should_exit = True
        thread.join(10)
        root.handlers[:] = handlers
        root.setLevel(level)
        logging.getLogger("uvicorn.access").filters[:] = []
        logging.getLogger("uvicorn.access").disabled = False
    lines = [json.loads(line) for line in stream.getvalue().splitlines()]
    paths = [r["message"].split()[3] for r in lines if r["logger"] == "uvicorn.access"]
    assert paths == logged
