"""Ticket and alarm events, delivered by webhook and e-mail from an outbox in the store.

:class:`Outbox` writes one ``notifications`` row per event and channel in the
transaction of the change (a new or changed ticket, an alarm that changed
state), so whatever is stored is delivered at least once, across restarts.
:class:`OutboxDispatcher` delivers the rows that are due, oldest first: a
delivery that fails in a way that may pass (a network error, a timeout, a
5xx answer, an SMTP 4xx) is tried again after a backoff that doubles up to
``max_backoff_s``; one that cannot succeed (a 4xx answer, an SMTP 5xx) or
has used ``max_attempts`` is ``failed``, with the error.  Receivers may see
an event twice (a crash between the delivery and its record): they drop
repeats by ``webhook-id``.

Webhooks are signed as the Standard Webhooks specification has it: headers
``webhook-id``, ``webhook-timestamp`` (UNIX s) and ``webhook-signature: v1,``
the base64 HMAC-SHA256 of ``{id}.{timestamp}.{body}`` with the shared secret
(``whsec_`` and the base64 key bytes).
"""

from __future__ import annotations

import base64
import email.policy
import hashlib
import hmac
import json
import logging
import smtplib
import threading
import time
import urllib.error
import urllib.request
import uuid
from collections.abc import Callable, Mapping, Sequence
from datetime import UTC, datetime
from email.message import EmailMessage
from typing import Any, Protocol

from sqlalchemy import select
from sqlalchemy.orm import Session

from service.store.db import Store
from service.store.models import Notification

__all__ = [
    "Channel",
    "EmailChannel",
    "Outbox",
    "OutboxDispatcher",
    "PermanentDeliveryError",
    "WebhookChannel",
    "sign_webhook",
]

log = logging.getLogger(__name__)


class PermanentDeliveryError(Exception):
    """The receiver refused the event in a way another try cannot change."""


class Channel(Protocol):
    """Delivers one event; raises :class:`PermanentDeliveryError` or another error (tried
    again later)."""

    def deliver(self, event_id: str, event_type: str, payload: dict[str, Any],
                occurred_at: float) -> None:
        """Send the event (of UNIX time ``occurred_at``) now."""


class Outbox:
    """Writes events to deliver on ``channels`` (``webhook``, ``email``) into a session."""

    def __init__(self, channels: Sequence[str]) -> None:
        self.channels = tuple(channels)

    def add(self, session: Session, event_type: str, payload: dict[str, Any],
            now: float) -> None:
        """One pending row per channel, in the caller's transaction."""
        for channel in self.channels:
            session.add(Notification(
                event_id=f"msg_{uuid.uuid4().hex}", channel=channel, event_type=event_type,
                payload=payload, created_at=now, state="pending", attempts=0,
                next_attempt_at=now))


def sign_webhook(secret: str, event_id: str, timestamp: int, body: bytes) -> str:
    """The ``webhook-signature`` of a Standard Webhooks delivery (``v1,<base64>``).

    ``secret`` is ``whsec_`` followed by the base64 of the key bytes.

    >>> sign_webhook("whsec_" + base64.b64encode(b"key").decode(), "msg_1", 1, b"{}")
    'v1,jKGHVBDuJf5ZbCMVrrutoMHDN1OlFFCE9iogVIO9MLQ='
    """
    key = base64.b64decode(secret.removeprefix("whsec_"))
    content = f"{event_id}.{timestamp}.".encode() + body
    digest = hmac.new(key, content, hashlib.sha256).digest()
    return "v1," + base64.b64encode(digest).decode()


class WebhookChannel:
    """POSTs ``{"type", "timestamp", "data"}`` as JSON to ``url``, signed with ``secret``
    (``timestamp``: when the event happened, ISO 8601; ``webhook-timestamp``: when it is
    sent, as receivers check it against their clock)."""

    def __init__(self, url: str, secret: str, *, timeout_s: float = 10.0) -> None:
        if not url.startswith(("http://", "https://")):
            raise ValueError(f"webhook URL must start with http:// or https://, got {url!r}")
        self.url, self.secret, self.timeout_s = url, secret, timeout_s

    def deliver(self, event_id: str, event_type: str, payload: dict[str, Any],
                occurred_at: float) -> None:
        """POST the event; 2xx delivers it, 4xx refuses it for good, anything else may pass.

        Raises
        ------
        PermanentDeliveryError
            The receiver answered 4xx.
        OSError, urllib.error.URLError
            Network error, timeout or 5xx: try again later.
        """
        timestamp = int(time.time())
        occurred = datetime.fromtimestamp(occurred_at, UTC).isoformat()
        body = json.dumps({"type": event_type, "timestamp": occurred, "data": payload}).encode()
        request = urllib.request.Request(self.url, data=body, method="POST", headers={
            "Content-Type": "application/json", "webhook-id": event_id,
            "webhook-timestamp": str(timestamp),
            "webhook-signature": sign_webhook(self.secret, event_id, timestamp, body)})
        try:
            with urllib.request.urlopen(request, timeout=self.timeout_s) as response:
                response.read()
        except urllib.error.HTTPError as exc:
            exc.close()
            if 400 <= exc.code < 500:
                raise PermanentDeliveryError(f"HTTP {exc.code} {exc.reason}") from None
            raise


class EmailChannel:
    """Sends each event as a plain-text e-mail through an SMTP server."""

    def __init__(self, host: str, port: int, sender: str, recipients: Sequence[str], *,
                 timeout_s: float = 10.0) -> None:
        if not recipients:
            raise ValueError("e-mail notifications need at least one recipient")
        self.host, self.port, self.sender = host, port, sender
        self.recipients, self.timeout_s = list(recipients), timeout_s

    def deliver(self, event_id: str, event_type: str, payload: dict[str, Any],
                occurred_at: float) -> None:
        """Send the mail; an SMTP 5xx refuses it for good, anything else may pass.

        Raises
        ------
        PermanentDeliveryError
            The server refused the mail or every recipient with a 5xx code.
        OSError, smtplib.SMTPException
            Try again later.
        """
        # long subjects stay on one line (the 78-column fold puts them on the next one)
        message = EmailMessage(policy=email.policy.SMTP.clone(max_line_length=998))
        message["From"] = self.sender
        message["To"] = ", ".join(self.recipients)
        message["Subject"] = f"loopwatch {event_type}: {_subject(payload)}"
        message["Message-ID"] = f"<{event_id}@loopwatch>"
        message.set_content(json.dumps(payload, indent=2, default=str))
        try:
            with smtplib.SMTP(self.host, self.port, timeout=self.timeout_s) as smtp:
                smtp.send_message(message)
        except smtplib.SMTPRecipientsRefused as exc:
            codes = [code for code, _ in exc.recipients.values()]
            if all(code >= 500 for code in codes):
                raise PermanentDeliveryError(f"SMTP recipients refused: {exc.recipients}") \
                    from None
            raise
        except smtplib.SMTPResponseException as exc:
            if exc.smtp_code >= 500:
                raise PermanentDeliveryError(f"SMTP {exc.smtp_code} {exc.smtp_error!r}") \
                    from None
            raise


def _subject(payload: Mapping[str, Any]) -> str:
    """A one-line summary of a ticket or alarm event."""
    if "ticket" in payload:
        ticket = payload["ticket"]
        return f"ticket {ticket.get('id')} {ticket.get('state')}: {ticket.get('title')}"
    alarm = payload.get("alarm", {})
    return (f"{alarm.get('loop_id')} {alarm.get('kind')} alarm {alarm.get('state')} "
            f"({alarm.get('priority')})")


class OutboxDispatcher:
    """Delivers the due rows of the outbox on their channels, from a background thread.

    :meth:`deliver_due` is one pass (what the thread runs every ``poll_s``).
    """

    def __init__(self, store: Store, channels: Mapping[str, Channel], *,
                 clock: Callable[[], float], backoff_s: float = 1.0,
                 max_backoff_s: float = 300.0, max_attempts: int = 10, poll_s: float = 1.0,
                 batch: int = 100) -> None:
        self.store, self.channels, self.clock = store, dict(channels), clock
        self.backoff_s, self.max_backoff_s = backoff_s, max_backoff_s
        self.max_attempts, self.poll_s, self.batch = max_attempts, poll_s, batch
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def deliver_due(self) -> int:
        """Try every row due now (up to ``batch``); the number tried."""
        now = self.clock()
        with self.store.session() as session:
            due = session.scalars(
                select(Notification.id)
                .where(Notification.state == "pending", Notification.next_attempt_at <= now,
                       Notification.channel.in_(list(self.channels)))
                .order_by(Notification.id).limit(self.batch)).all()
        for row_id in due:  # each outcome is stored as soon as it is known
            with self.store.session() as session:
                row = session.get(Notification, row_id)
                if row is not None and row.state == "pending":
                    self._try(row, now)
        return len(due)

    def _try(self, row: Notification, now: float) -> None:
        row.attempts += 1
        try:
            self.channels[row.channel].deliver(row.event_id, row.event_type, row.payload,
                                               row.created_at)
        except PermanentDeliveryError as exc:
            row.state, row.last_error, row.finished_at = "failed", str(exc), now
            log.warning("%s %s %s refused: %s", row.channel, row.event_type, row.event_id, exc)
        except Exception as exc:  # network, timeout, 5xx: may pass, so try again
            row.last_error = f"{type(exc).__name__}: {exc}"
            if row.attempts >= self.max_attempts:
                row.state, row.finished_at = "failed", now
                log.warning("%s %s %s given up after %d attempts: %s", row.channel,
                            row.event_type, row.event_id, row.attempts, row.last_error)
            else:
                row.next_attempt_at = now + min(self.max_backoff_s,
                                                self.backoff_s * 2 ** (row.attempts - 1))
        else:
            row.state, row.last_error, row.finished_at = "delivered", None, now

    def start(self) -> None:
        """Deliver in a background thread every ``poll_s`` until :meth:`stop`."""
        self._thread = threading.Thread(target=self._run, name="notification-outbox",
                                        daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 10.0) -> None:
        """End the thread after its current pass (what is left is delivered after a restart)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                while self.deliver_due() and not self._stop.is_set():
                    pass
            except Exception:  # the store may be away: the rows wait there
                log.exception("notification outbox: a delivery pass failed")
            self._stop.wait(self.poll_s)
