"""Ticket and alarm events through the outbox, to a real HTTP receiver and a real SMTP server.

The receiver runs on a free loopback port and checks every signature with the
Standard Webhooks reference library (``standardwebhooks``); the SMTP server is
``aiosmtpd`` on loopback.  The service's scheduler writes the events in the
transaction of its analysis; a dispatcher with a clock of the test's delivers
them, so the backoff is checked without waiting.
"""

import base64
import json
import threading
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from email import message_from_bytes, policy
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import pytest
from aiosmtpd.controller import Controller
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families
from sqlalchemy import func, select
from standardwebhooks.webhooks import Webhook, WebhookVerificationError

from service.config import Settings
from service.notifications import (
    EmailChannel,
    OutboxDispatcher,
    PermanentDeliveryError,
    WebhookChannel,
)
from service.server import Service, build_service, notification_channels
from service.store.models import Notification
from tests.servers import free_port
from tests.service.test_api import ADMIN, T0, plant, simulated_batch

SECRET = "whsec_" + base64.b64encode(b"loopwatch test secret, 32 bytes!").decode()


class Receiver(ThreadingHTTPServer):
    """A webhook endpoint that answers each POST with the next of ``statuses`` (then 204)
    and keeps the events whose signature the reference library accepts."""

    def __init__(self, statuses: list[int]) -> None:
        super().__init__(("127.0.0.1", 0), _Handler)
        self.statuses = statuses
        self.events: list[dict[str, Any]] = []
        self.ids: list[str] = []
        self.forged = 0

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.server_address[1]}/loopwatch"


class _Handler(BaseHTTPRequestHandler):
    server: Receiver

    def do_POST(self) -> None:
        body = self.rfile.read(int(self.headers["Content-Length"]))
        try:
            event = Webhook(SECRET).verify(body, dict(self.headers.items()))
        except WebhookVerificationError:
            self.server.forged += 1
            status = 401
        else:
            status = self.server.statuses.pop(0) if self.server.statuses else 204
            self.server.ids.append(self.headers["webhook-id"])
            if status < 300:
                self.server.events.append(event)
        self.send_response(status)
        self.send_header("Content-Length", "0")
        self.end_headers()

    def log_message(self, *args: object) -> None:
        """Quiet."""


@pytest.fixture
def receiver(request: pytest.FixtureRequest) -> Iterator[Receiver]:
    server = Receiver(list(getattr(request, "param", [])))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield server
    server.shutdown()
    server.server_close()
    thread.join()


class Mailbox:
    """aiosmtpd handler: keeps every message it is given."""

    def __init__(self) -> None:
        self.messages: list[Any] = []

    async def handle_DATA(self, server: Any, session: Any, envelope: Any) -> str:
        self.messages.append(message_from_bytes(envelope.content, policy=policy.default))
        return "250 OK"


@pytest.fixture
def mailbox() -> Iterator[tuple[Mailbox, int]]:
    box, port = Mailbox(), free_port()
    controller = Controller(box, hostname="127.0.0.1", port=port)
    controller.start()
    yield box, port
    controller.stop()


def make_service(tmp_path, **settings: Any) -> Service:
    config = Settings(database_url=f"sqlite:///{tmp_path / 'loopwatch.db'}", api_key=ADMIN,
                      window_s=3600, buffer_horizon_s=7200, **settings)
    return build_service(config, plant(), executor=ThreadPoolExecutor(1), clock=lambda: T0)


def close(service: Service) -> None:
    service.executor.shutdown()  # type: ignore[union-attr]
    service.state.store.close()


def analyse_two_hours(service: Service) -> None:
    """FIC-1's sticky valve: an oscillation alarm, then a ticket after two findings."""
    client = TestClient(service.app)
    assert client.post("/api/v1/ingest", json=simulated_batch(7200),
                       headers={"X-API-Key": ADMIN}).status_code == 200
    assert service.scheduler is not None
    service.scheduler.run_once(T0 - 3600)
    service.scheduler.run_once(T0)


def rows(service: Service) -> list[tuple[str, str, str, int]]:
    with service.state.store.session() as session:
        return [(n.channel, n.event_type, n.state, n.attempts)
                for n in session.scalars(select(Notification).order_by(Notification.id))]


class Clock:
    """The dispatcher's time, moved by the test."""

    def __init__(self, now: float) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


@pytest.mark.parametrize("receiver", [[503]], indirect=True)
def test_events_survive_a_restart_are_signed_retried_after_5xx_and_counted(
        tmp_path, receiver, mailbox):
    box, smtp_port = mailbox
    settings = {"webhook_url": receiver.url, "webhook_secret": SECRET,
                "smtp_host": "127.0.0.1", "smtp_port": smtp_port,
                "email_to": "maintenance@plant.example"}
    first = make_service(tmp_path, **settings)
    analyse_two_hours(first)
    written = rows(first)
    assert ("webhook", "alarm.changed", "pending", 0) in written
    assert ("webhook", "ticket.changed", "pending", 0) in written
    assert {channel for channel, *_ in written} == {"webhook", "email"}
    close(first)  # nothing delivered yet: the events wait in the store

    again = make_service(tmp_path, **settings)  # a restart
    clock = Clock(T0)
    dispatcher = OutboxDispatcher(again.state.store, notification_channels(again.state.settings),
                                  clock=clock, backoff_s=30.0)
    dispatcher.deliver_due()
    after_503 = rows(again)
    assert len(receiver.ids) == len(written) // 2  # one try each
    assert after_503[0][2:] == ("pending", 1)  # the 503: tried again later ...
    assert dispatcher.deliver_due() == 0  # ... not before its backoff
    clock.now += 30.0
    assert dispatcher.deliver_due() == 1
    assert {state for *_, state, _ in rows(again)} == {"delivered"}
    assert receiver.forged == 0
    assert len(receiver.events) == len(written) // 2
    assert receiver.ids[0] == receiver.ids[len(written) // 2]  # the retry keeps its id
    ticket = next(e for e in receiver.events if e["type"] == "ticket.changed")
    assert ticket["data"]["ticket"]["valve_asset"] == "FV-1"
    alarm = next(e for e in receiver.events if e["type"] == "alarm.changed")
    assert alarm["data"]["alarm"]["loop_id"] == "FIC-1"
    assert alarm["data"]["change"]["event"] == "activated"

    subjects = sorted(m["Subject"] for m in box.messages)
    assert len(subjects) == len(written) // 2
    assert any(s.startswith("loopwatch ticket.changed: ticket ") for s in subjects)
    assert any(s.startswith("loopwatch alarm.changed: FIC-1 oscillation alarm") for s in subjects)
    assert json.loads(box.messages[0].get_content())  # the event, as JSON

    metrics = TestClient(again.app).get("/metrics", headers={"X-API-Key": ADMIN}).text
    families = {f.name: f for f in text_string_to_metric_families(metrics)}
    delivered = {(s.labels["channel"], s.labels["state"]): s.value
                 for s in families["loopwatch_notifications"].samples}
    assert delivered == {("webhook", "delivered"): len(written) // 2,
                         ("email", "delivered"): len(written) // 2}
    close(again)


@pytest.mark.parametrize("receiver", [[400, 410]], indirect=True)
def test_a_4xx_is_not_tried_again(tmp_path, receiver):
    service = make_service(tmp_path, webhook_url=receiver.url, webhook_secret=SECRET)
    with service.state.store.session() as session:
        service.scheduler.outbox.add(session, "ticket.changed", {"ticket": {"id": 1}}, T0)
    dispatcher = OutboxDispatcher(service.state.store,
                                  {"webhook": WebhookChannel(receiver.url, SECRET)},
                                  clock=Clock(T0 + 1e6))
    dispatcher.deliver_due()
    assert dispatcher.deliver_due() == 0
    assert rows(service) == [("webhook", "ticket.changed", "failed", 1)]
    with service.state.store.session() as session:
        assert session.scalars(select(Notification.last_error)).one() == "HTTP 400 Bad Request"
    close(service)


def test_an_unreachable_receiver_is_tried_with_a_doubling_backoff_then_given_up(tmp_path):
    closed = f"http://127.0.0.1:{free_port()}/nobody"
    service = make_service(tmp_path, webhook_url=closed, webhook_secret=SECRET)
    with service.state.store.session() as session:
        service.scheduler.outbox.add(session, "alarm.changed", {"alarm": {}}, T0)
    clock = Clock(T0)
    dispatcher = OutboxDispatcher(service.state.store,
                                  {"webhook": WebhookChannel(closed, SECRET)},
                                  clock=clock, backoff_s=10.0, max_attempts=3)
    due = []
    for _ in range(3):
        dispatcher.deliver_due()
        with service.state.store.session() as session:
            due.append(session.scalars(select(Notification.next_attempt_at)).one() - clock.now)
        clock.now += 1000.0
    assert due[:2] == [10.0, 20.0]
    assert rows(service) == [("webhook", "alarm.changed", "failed", 3)]
    close(service)


@pytest.mark.parametrize(("settings", "message"), [
    ({"webhook_url": "http://127.0.0.1:1/x"}, "needs LOOPWATCH_WEBHOOK_SECRET"),
    ({"webhook_url": "http://127.0.0.1:1/x", "webhook_secret": "whsec_c2hvcnQ="},
     "at least 16 random bytes"),
    ({"webhook_url": "ftp://x", "webhook_secret": SECRET}, "must start with http://"),
    ({"smtp_host": "mail"}, "needs LOOPWATCH_EMAIL_TO"),
])
def test_channel_settings_are_checked(settings, message):
    with pytest.raises(ValueError, match=message):
        Settings(**settings)


def test_an_email_refused_for_good_is_not_tried_again():
    class Refusing:
        async def handle_RCPT(self, server, session, envelope, address, options):
            return "550 no such mailbox"

    controller = Controller(Refusing(), hostname="127.0.0.1", port=free_port())
    controller.start()
    try:
        channel = EmailChannel("127.0.0.1", controller.port, "lw@plant", ["nobody@plant"])
        with pytest.raises(PermanentDeliveryError, match="recipients refused"):
            channel.deliver("msg_1", "alarm.changed", {"alarm": {}}, T0)
    finally:
        controller.stop()


def test_operators_alarm_and_ticket_actions_are_notified_too(tmp_path):
    """Issue 23: "send alarm events as well as tickets" -- an operator's acknowledge and a
    planner's ticket change are events like the analysis's, written with the action."""
    service = make_service(tmp_path, webhook_url="http://127.0.0.1:1/hook",
                           webhook_secret=SECRET)
    analyse_two_hours(service)
    client = TestClient(service.app)
    headers = {"X-API-Key": ADMIN}
    alarm = client.get("/api/v1/alarms", headers=headers).json()["data"][0]
    ticket = client.get("/api/v1/tickets", headers=headers).json()["data"][0]
    with service.state.store.session() as session:
        before = session.scalar(select(func.count()).select_from(Notification))
    assert client.post(f"/api/v1/alarms/{alarm['id']}/acknowledge",
                       headers=headers).status_code == 200
    assert client.patch(f"/api/v1/tickets/{ticket['id']}", json={"state": "acknowledged"},
                        headers=headers).status_code == 200
    with service.state.store.session() as session:
        added = session.scalars(select(Notification).order_by(Notification.id)
                                .offset(before)).all()
        events = [(n.event_type, n.payload) for n in added]
    assert [kind for kind, _ in events] == ["alarm.changed", "ticket.changed"]
    assert events[0][1]["alarm"]["id"] == alarm["id"]
    assert events[0][1]["change"]["event"] == "acknowledged"
    assert events[1][1]["ticket"]["state"] == "acknowledged"
    close(service)
