"""Logging of ``loopwatch serve``: text or JSON lines, request ids, audit records.

``LOOPWATCH_LOG_FORMAT=json`` writes one JSON object per line (``time``,
``level``, ``logger``, ``message``, ``request_id`` while a request is served,
and an ``audit`` object for audit records), for a log collector; the default
is plain text.  Every HTTP request gets an id (the client's ``X-Request-ID``
when it is a short token, a new one otherwise), answered in ``X-Request-ID``
and added to every record logged while the request is served.

Audit records (logger ``loopwatch.audit``, :func:`audit`) say who did what
to which object, and when: API keys created and revoked, loops configured
through the API, alarm and ticket actions.
"""

from __future__ import annotations

import json
import logging
import re
import uuid
from collections.abc import Iterable
from contextvars import ContextVar
from datetime import UTC, datetime
from typing import Any, Literal

from starlette.types import ASGIApp, Message, Receive, Scope, Send

__all__ = [
    "AUDIT_LOGGER",
    "JsonFormatter",
    "RequestIdMiddleware",
    "audit",
    "configure_logging",
]

AUDIT_LOGGER = "loopwatch.audit"

REQUEST_ID: ContextVar[str | None] = ContextVar("loopwatch_request_id", default=None)
_TOKEN = re.compile(r"[A-Za-z0-9._-]{1,64}")


class RequestIdMiddleware:
    """Give each HTTP request an id: in the log records of the request and in the
    ``X-Request-ID`` answer header."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        given = dict(scope["headers"]).get(b"x-request-id", b"").decode("latin-1")
        request_id = given if _TOKEN.fullmatch(given) else uuid.uuid4().hex[:16]
        token = REQUEST_ID.set(request_id)

        async def send_with_id(message: Message) -> None:
            if message["type"] == "http.response.start":
                message["headers"] = [*message.get("headers", []),
                                      (b"x-request-id", request_id.encode())]
            await send(message)

        try:
            await self.app(scope, receive, send_with_id)
        finally:
            REQUEST_ID.reset(token)


class _RequestIdFilter(logging.Filter):
    """Adds ``request_id`` (None outside a request) to every record."""

    def filter(self, record: logging.LogRecord) -> bool:
        record.request_id = REQUEST_ID.get()
        return True


class JsonFormatter(logging.Formatter):
    """One JSON object per record."""

    def format(self, record: logging.LogRecord) -> str:
        """The record as a JSON line."""
        entry: dict[str, Any] = {
            "time": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds"),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        request_id = getattr(record, "request_id", None)
        if request_id is not None:
            entry["request_id"] = request_id
        if hasattr(record, "audit"):
            entry["audit"] = record.audit
        if record.exc_info:
            entry["exception"] = self.formatException(record.exc_info)
        return json.dumps(entry, default=str)


ACCESS_LOGGER = "uvicorn.access"
UVICORN_LOGGERS = ("uvicorn", "uvicorn.error", ACCESS_LOGGER)


class _FailedRequestsFilter(logging.Filter):
    """Keeps uvicorn's access records of requests answered 400 or above: a dashboard
    polls a few routes every 15 s, and a line for each answer would bury the
    console's warnings (its args are client, method, path, HTTP version, status)."""

    def filter(self, record: logging.LogRecord) -> bool:
        args = record.args if isinstance(record.args, tuple) else ()
        return len(args) != 5 or not isinstance(args[4], int) or args[4] >= 400


def configure_logging(log_format: Literal["text", "json"], quiet: Iterable[str] = (),
                      access_log: Literal["failed", "all", "off"] = "failed") -> None:
    """Log to stderr at INFO in ``log_format``; the loggers ``quiet`` at WARNING;
    uvicorn's access records as ``access_log`` says (requests answered 400 or above,
    every request, or none)."""
    handler = logging.StreamHandler()
    handler.addFilter(_RequestIdFilter())
    handler.setFormatter(JsonFormatter() if log_format == "json" else logging.Formatter(
        "%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(logging.INFO)
    for library in quiet:
        logging.getLogger(library).setLevel(logging.WARNING)
    for name in UVICORN_LOGGERS:  # to the root's handler at its level, even after uvicorn
        uvicorn_logger = logging.getLogger(name)  # configured them in this process
        uvicorn_logger.handlers[:], uvicorn_logger.propagate = [], True
        uvicorn_logger.setLevel(logging.NOTSET)
    access = logging.getLogger(ACCESS_LOGGER)
    access.filters[:] = [_FailedRequestsFilter()] if access_log == "failed" else []
    access.disabled = access_log == "off"


def audit(actor: str, action: str, target: str, **details: Any) -> None:
    """An audit record: ``actor`` (the key's name and role) did ``action`` to ``target``."""
    record = {"actor": actor, "action": action, "target": target, **details}
    logging.getLogger(AUDIT_LOGGER).info(
        "%s: %s %s%s", actor, action, target,
        "".join(f" {k}={v!r}" for k, v in details.items()), extra={"audit": record})
