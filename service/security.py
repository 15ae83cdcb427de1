"""The API's protections that are not authentication: limits, rate limiting, headers, CORS.

* Request bodies larger than ``settings.max_body_bytes`` are refused with
  413 before the route reads them, whether or not the client announced the
  length (:class:`BodyLimitMiddleware`).
* Each API key may send ``rate_limit_per_s`` requests per second sustained,
  ``rate_limit_burst`` at once (a token bucket, :class:`RateLimiter`); beyond
  that 429 with ``Retry-After``.  Failed authentications are limited the
  same way per client address (``auth_failure_*``), and expensive analyses
  per key (:class:`ConcurrencyLimiter`).  The limits are per process: behind
  a load balancer each replica counts for itself.
* A client that pauses longer than ``settings.body_timeout_s`` while sending
  a request body gets 408 and the connection is closed
  (:class:`BodyTimeoutMiddleware`; the header deadline and the connection
  cap are uvicorn's, see :func:`service.server.uvicorn_config`).
* Every response carries secure headers (:data:`SECURITY_HEADERS`): a
  Content Security Policy that lets the dashboard load only its own
  scripts, styles and images (no inline script or style, no other origin),
  no framing, no MIME sniffing, no referrer; API answers are not cached;
  HSTS when the request came over HTTPS.
* CORS is off unless ``settings.cors_origins`` lists origins: only those may
  call the API from a browser, with the ``X-API-Key`` and ``Content-Type``
  headers and no cookies.
"""

from __future__ import annotations

import asyncio
import json
import math
import threading
import time
from collections.abc import Callable, Hashable
from dataclasses import dataclass

from fastapi import FastAPI
from starlette.middleware.cors import CORSMiddleware
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.config import Settings

__all__ = [
    "CONTENT_SECURITY_POLICY",
    "SECURITY_HEADERS",
    "BodyLimitMiddleware",
    "BodyTimeoutMiddleware",
    "ConcurrencyLimiter",
    "RateLimiter",
    "SecurityHeadersMiddleware",
    "install_protections",
]

CONTENT_SECURITY_POLICY = "; ".join((
    "default-src 'none'",
    "script-src 'self'",
    "style-src 'self'",
    "img-src 'self' data: blob:",
    "connect-src 'self'",
    "font-src 'self'",
    "base-uri 'none'",
    "form-action 'self'",
    "frame-ancestors 'none'",
))
"""Same-origin scripts, styles, images and API calls; nothing inline, nothing else."""

SECURITY_HEADERS: dict[str, str] = {
    "Content-Security-Policy": CONTENT_SECURITY_POLICY,
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
    "Cross-Origin-Opener-Policy": "same-origin",
    "Cross-Origin-Resource-Policy": "same-origin",
    "Permissions-Policy": "camera=(), microphone=(), geolocation=(), payment=(), usb=()",
}
"""Headers added to every response (a header the route set itself is kept)."""

HSTS = "max-age=31536000"
NO_STORE_PREFIXES = ("/api/", "/metrics", "/openapi.json")
"""Paths whose answers hold plant data or keys: ``Cache-Control: no-store`` unless set."""


@dataclass
class _Bucket:
    tokens: float
    updated: float


class RateLimiter:
    """Token buckets, one per key: ``rate_per_s`` sustained, ``burst`` at once.

    Parameters
    ----------
    rate_per_s : float
        Tokens added per second.
    burst : int
        Bucket size: requests a fresh key may send at once.
    clock : callable
        Monotonic seconds (injectable for tests).
    """

    def __init__(self, *, rate_per_s: float, burst: int,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if not (rate_per_s > 0 and burst >= 1):
            raise ValueError(f"need rate_per_s > 0 and burst >= 1, got {rate_per_s}, {burst}")
        self.rate_per_s = rate_per_s
        self.burst = burst
        self.clock = clock
        self._buckets: dict[Hashable, _Bucket] = {}
        self._lock = threading.Lock()

    MAX_BUCKETS = 100_000
    """Past this many keys, buckets that have filled up again are forgotten."""

    def _refill(self, key: Hashable, now: float) -> _Bucket:
        if key not in self._buckets and len(self._buckets) >= self.MAX_BUCKETS:
            full = self.burst / self.rate_per_s
            self._buckets = {k: b for k, b in self._buckets.items() if now - b.updated < full}
        bucket = self._buckets.setdefault(key, _Bucket(float(self.burst), now))
        bucket.tokens = min(float(self.burst),
                            bucket.tokens + (now - bucket.updated) * self.rate_per_s)
        bucket.updated = now
        return bucket

    def acquire(self, key: Hashable) -> float:
        """Take one token for ``key``: 0 if granted, else the seconds until one is free."""
        with self._lock:
            bucket = self._refill(key, self.clock())
            if bucket.tokens >= 1.0:
                bucket.tokens -= 1.0
                return 0.0
            return (1.0 - bucket.tokens) / self.rate_per_s

    def wait(self, key: Hashable) -> float:
        """The seconds until ``key`` has a token (0: it has one now), taking none."""
        with self._lock:
            if key not in self._buckets:
                return 0.0
            bucket = self._refill(key, self.clock())
            return max(0.0, (1.0 - bucket.tokens) / self.rate_per_s)


class ConcurrencyLimiter:
    """At most ``per_key`` tasks at once per key and ``total`` in all (expensive analyses)."""

    def __init__(self, *, per_key: int, total: int) -> None:
        if not (per_key >= 1 and total >= 1):
            raise ValueError(f"need per_key >= 1 and total >= 1, got {per_key}, {total}")
        self.per_key = per_key
        self.total = total
        self._running: dict[Hashable, int] = {}
        self._lock = threading.Lock()

    def acquire(self, key: Hashable) -> str | None:
        """Take a slot of ``key``: None if granted, else what is full, "key" or "total"."""
        with self._lock:
            if self._running.get(key, 0) >= self.per_key:
                return "key"
            if sum(self._running.values()) >= self.total:
                return "total"
            self._running[key] = self._running.get(key, 0) + 1
            return None

    def release(self, key: Hashable) -> None:
        """Give back a slot taken by :meth:`acquire`."""
        with self._lock:
            left = self._running[key] - 1
            if left:
                self._running[key] = left
            else:
                del self._running[key]


def retry_after(seconds: float) -> str:
    """A ``Retry-After`` value: whole seconds, at least 1."""
    return str(max(1, math.ceil(seconds)))


async def _refuse(send: Send, status: int, detail: str) -> None:
    """Answer ``status`` with ``{"detail": ...}`` and close the connection afterwards."""
    body = json.dumps({"detail": detail}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"),
                            (b"content-length", str(len(body)).encode()),
                            (b"connection", b"close")]})
    await send({"type": "http.response.body", "body": body})


class BodyTimeoutMiddleware:
    """Answer 408 to a client that pauses over ``timeout_s`` while sending a body.

    The application then sees a disconnect; whatever it answers to that is
    dropped.  Without this a client sending one byte a minute holds a
    connection and a task for as long as it likes.
    """

    def __init__(self, app: ASGIApp, *, timeout_s: float) -> None:
        self.app = app
        self.timeout_s = timeout_s

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = refused = False

        async def timed_receive() -> Message:
            nonlocal refused
            if refused:
                return {"type": "http.disconnect"}
            try:
                return await asyncio.wait_for(receive(), self.timeout_s)
            except TimeoutError:
                if started:
                    raise
                refused = True
                await _refuse(send, 408, f"Request body not received: the client paused more "
                                         f"than {self.timeout_s:g} s (LOOPWATCH_BODY_TIMEOUT_S)")
                return {"type": "http.disconnect"}

        async def guarded_send(message: Message) -> None:
            nonlocal started
            if refused:
                return  # the client has its 408
            started = started or message["type"] == "http.response.start"
            await send(message)

        await self.app(scope, timed_receive, guarded_send)


class BodyLimitMiddleware:
    """Refuse request bodies above ``max_bytes`` with 413 (ASGI middleware).

    A declared ``Content-Length`` over the limit is refused before anything
    is read.  A body without one is counted as it streams in; at the limit
    the client gets the 413 at once and the application sees a disconnect,
    whatever it answers to that is dropped.
    """

    def __init__(self, app: ASGIApp, *, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def _refuse(self, send: Send) -> None:
        limit = (f"{self.max_bytes / 1024 ** 2:g} MiB" if self.max_bytes >= 1024 ** 2
                 else f"{self.max_bytes} bytes")
        await _refuse(send, 413, f"Request body larger than the limit of {limit} "
                                 "(LOOPWATCH_MAX_BODY_BYTES)")

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope["headers"]).get(b"content-length", b"")
        if declared.isdigit() and int(declared) > self.max_bytes:
            await self._refuse(send)
            return
        seen = 0
        started = refused = False

        async def counted_receive() -> Message:
            nonlocal seen, refused
            if refused:
                return {"type": "http.disconnect"}
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.max_bytes and not started:
                    refused = True
                    await self._refuse(send)
                    return {"type": "http.disconnect"}
            return message

        async def guarded_send(message: Message) -> None:
            nonlocal started
            if refused:
                return  # the client has its 413
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, counted_receive, guarded_send)
        except Exception:
            if not refused:
                raise


class SecurityHeadersMiddleware:
    """Add :data:`SECURITY_HEADERS` (and HSTS over HTTPS, no-store on API answers)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        extra = dict(SECURITY_HEADERS)
        if scope.get("scheme") == "https":
            extra["Strict-Transport-Security"] = HSTS
        if scope["path"].startswith(NO_STORE_PREFIXES):
            extra["Cache-Control"] = "no-store"

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", []))
                present = {name.lower() for name, _ in headers}
                headers += [(name.lower().encode(), value.encode())
                            for name, value in extra.items()
                            if name.lower().encode() not in present]
                message = {**message, "headers": headers}
            await send(message)

        await self.app(scope, receive, send_with_headers)


def install_protections(app: FastAPI, settings: Settings) -> None:
    """Add the body limit and timeout, CORS (if origins are configured) and the secure
    headers.

    The headers middleware is outermost, so refusals by the others carry the
    headers too.
    """
    app.add_middleware(BodyLimitMiddleware, max_bytes=settings.max_body_bytes)
    app.add_middleware(BodyTimeoutMiddleware, timeout_s=settings.body_timeout_s)
    if settings.cors_origins:
        app.add_middleware(
            CORSMiddleware,
            allow_origins=settings.cors_origins,
            allow_methods=["GET", "POST", "PUT", "PATCH", "DELETE"],
            allow_headers=["X-API-Key", "Content-Type"],
            allow_credentials=False,
            max_age=600,
        )
    app.add_middleware(SecurityHeadersMiddleware)
