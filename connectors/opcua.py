"""OPC UA subscriptions: the endpoint configuration and the supervised connector.

One :class:`OpcUaConnector` holds one connection to one endpoint and one
subscription over all its nodes.  Monitored items are created in batches
(one ``CreateMonitoredItems`` call for up to :data:`MONITORED_ITEMS_PER_CALL`
nodes) with the ``StatusValueTimestamp`` trigger, so a sample that repeats
the previous value -- a stuck valve position -- is still delivered, and with
a queue per item, so samples written faster than the publishing interval are
not lost on the server.

Every notification becomes one ingest item (:func:`connectors.base.item`):
stamped with its source timestamp (the server timestamp when the source
gives none), good only when its status code is Good.  A Bad or Uncertain
status, or a value that is not a number, is sent as a bad sample (value
None) and counted in ``bad``.  Items are collected and handed to the
synchronous sink in batches every ``flush_interval_s``, in a worker thread
(the sink writes to a database).

Supervision follows asyncua's own pattern: one supervisor loop per
connection; when the transport is lost, a request fails, or the watchdog
finds the subscription stale (no data and no keep-alive within
``watchdog_s``), the connection is dropped and made again after a capped
exponential backoff, and the subscription is created anew.  The time the
connection was down is recorded as an :class:`~connectors.base.Outage`.  After
a reconnect, the samples missed since the last one of each node (at most
``backfill_max_s`` back) are read with HistoryRead (``read_raw_history``) from
the nodes whose access level allows it, so the buffers have no hole where the
server keeps history; samples the new subscription has already delivered are
not sent twice.

With a security policy (Basic256Sha256, Aes128Sha256RsaOaep or
Aes256Sha256RsaPss) the server's certificate is validated against the trust
store in ``trusted_certificates`` (asyncua's ``CertificateValidator`` and
``TrustStore``: validity, application URI, key usage, trust); a server whose
certificate is not trusted is refused with an error that names the
certificate and the directory to copy it into.

References
----------
OPC Foundation, *OPC 10000-4 Unified Architecture Part 4: Services*, 5.12
(MonitoredItem services, DataChangeFilter), 5.13 (Subscription services,
keep-alive and lifetime counts) and 5.10.3 (HistoryRead); OPC 10000-3, 5.6.2
(AccessLevel: HistoryRead bit); OPC 10000-7 (security policies).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

from asyncua import Client, ua
from asyncua.common.subscription import DataChangeEvent, StatusChangeEvent, Subscription
from asyncua.crypto.security_policies import (
    SecurityPolicy,
    SecurityPolicyAes128Sha256RsaOaep,
    SecurityPolicyAes256Sha256RsaPss,
    SecurityPolicyBasic256Sha256,
)
from asyncua.crypto.truststore import TrustStore
from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions
from asyncua.server.internal_session import ServiceError
from cryptography import x509
from cryptography.hazmat.primitives import hashes
from pydantic import (
    BaseModel,
    ConfigDict,
    DirectoryPath,
    Field,
    FilePath,
    SecretStr,
    field_validator,
    model_validator,
)

from connectors.base import (
    BackgroundConnector,
    Backoff,
    DeliveryCounters,
    SampleSink,
    item,
    raise_if_cancelled,
)

__all__ = [
    "MONITORED_ITEMS_PER_CALL",
    "OpcUaConnector",
    "OpcUaCounters",
    "OpcUaEndpointConfig",
    "OpcUaNodeConfig",
]

log = logging.getLogger(__name__)

MONITORED_ITEMS_PER_CALL = 1000
"""Nodes per CreateMonitoredItems request; many servers cap a call near 1,000 items."""

DISCONNECT_TIMEOUT_S = 2.0
"""How long a clean disconnect may take before the connection is simply dropped."""

SECURITY_POLICIES: dict[str, type[SecurityPolicy]] = {
    "Basic256Sha256": SecurityPolicyBasic256Sha256,
    "Aes128Sha256RsaOaep": SecurityPolicyAes128Sha256RsaOaep,
    "Aes256Sha256RsaPss": SecurityPolicyAes256Sha256RsaPss,
}
"""The security policies a connector may use, by their names in the configuration."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class OpcUaNodeConfig(_Strict):
    """One monitored node and the tag its samples are stored under."""

    tag: str = Field(min_length=1)
    node_id: str = Field(min_length=1, description='OPC UA node id, e.g. "ns=2;s=FIC-101.PV"')

    @field_validator("node_id")
    @classmethod
    def _parsable(cls, node_id: str) -> str:
        try:
            ua.NodeId.from_string(node_id)
        except Exception as exc:  # asyncua raises several types for a malformed id
            raise ValueError(f"not an OPC UA node id ({exc})") from None
        return node_id


class OpcUaEndpointConfig(_Strict):
    """One OPC UA endpoint: how to connect, how to subscribe, and which nodes.

    A ``security_policy`` (one of :data:`SECURITY_POLICIES`) needs
    ``security_mode`` Sign or SignAndEncrypt, the client's ``certificate`` and
    ``private_key`` (PEM or DER), and a way to trust the server: the directory
    ``trusted_certificates`` (the server certificates, or their CAs, that are
    trusted; the server's certificate is validated against it), or the pinned
    ``server_certificate`` itself (then only that certificate is accepted), or
    both.  The server sends a keep-alive three times per ``watchdog_s`` when
    it has no data.

    Examples
    --------
    >>> config = OpcUaEndpointConfig(
    ...     url="opc.tcp://127.0.0.1:4840", publishing_interval_ms=500, watchdog_s=30,
    ...     nodes=[{"tag": "FIC-101.PV", "node_id": "ns=2;s=FIC-101.PV"}])
    >>> config.keepalive_count  # publishing intervals between keep-alives: 10 s
    20
    """

    url: str = Field(pattern=r"^opc\.tcp://", description="opc.tcp://host:port[/path]")
    security_policy: Literal["none", "Basic256Sha256", "Aes128Sha256RsaOaep",
                             "Aes256Sha256RsaPss"] = "none"
    security_mode: Literal["None", "Sign", "SignAndEncrypt"] = "None"
    certificate: FilePath | None = None
    private_key: FilePath | None = None
    server_certificate: FilePath | None = None
    trusted_certificates: DirectoryPath | None = Field(
        default=None, description="directory of trusted server (or CA) certificates, DER or PEM")
    application_uri: str = Field(
        default="urn:loopwatch:connector",
        description="the client's application URI; must match the certificate's SAN URI",
    )
    username: str | None = None
    password: SecretStr | None = None
    sampling_interval_ms: float = Field(default=1000.0, ge=0)
    publishing_interval_ms: float = Field(default=1000.0, gt=0)
    queue_size: int = Field(default=10, ge=1, description="samples kept per node between publishes")
    nodes: list[OpcUaNodeConfig] = Field(min_length=1)
    watchdog_s: float = Field(default=30.0, gt=0)
    flush_interval_s: float = Field(default=1.0, gt=0)
    request_timeout_s: float = Field(default=10.0, gt=0)
    backfill_max_s: float = Field(
        default=86400.0, ge=0,
        description="after a reconnect, missed samples up to this far back are read with "
                    "HistoryRead where the server keeps history, s (0: never)")

    @model_validator(mode="after")
    def _consistent(self) -> OpcUaEndpointConfig:
        if self.security_policy == "none" and self.security_mode != "None":
            raise ValueError(
                f"security_mode {self.security_mode} needs a security_policy "
                f"({', '.join(SECURITY_POLICIES)})"
            )
        if self.security_policy != "none":
            if self.security_mode == "None":
                raise ValueError(
                    f"security_policy {self.security_policy} needs security_mode "
                    "Sign or SignAndEncrypt"
                )
            missing = [k for k in ("certificate", "private_key") if getattr(self, k) is None]
            if missing:
                raise ValueError(
                    f"security_policy {self.security_policy} needs {' and '.join(missing)}"
                )
            if self.trusted_certificates is None and self.server_certificate is None:
                raise ValueError(
                    f"security_policy {self.security_policy} needs trusted_certificates (a "
                    "directory of the server certificates to trust) or the server's own "
                    "server_certificate: the server's certificate is never taken unchecked"
                )
        if (self.username is None) != (self.password is None):
            raise ValueError("username and password go together: give both or neither")
        if self.watchdog_s * 1000.0 < 3.0 * self.publishing_interval_ms:
            raise ValueError(
                f"watchdog_s ({self.watchdog_s} s) must cover at least three publishing "
                f"intervals ({self.publishing_interval_ms} ms each)"
            )
        for what in ("tag", "node_id"):
            seen: set[str] = set()
            for i, node in enumerate(self.nodes):
                value = getattr(node, what)
                if value in seen:
                    raise ValueError(f"nodes[{i}].{what}: duplicate {value!r}")
                seen.add(value)
        return self

    @property
    def keepalive_count(self) -> int:
        """Publishing intervals between keep-alives: three keep-alives per watchdog period."""
        return max(1, math.floor(self.watchdog_s * 1000.0 / self.publishing_interval_ms / 3.0))


@dataclass
class OpcUaCounters(DeliveryCounters):
    """What an :class:`OpcUaConnector` has done, besides the sample counts of its base class.

    ``samples`` are the notifications taken from the subscription, ``bad``
    those sent as bad (status not Good, or not a number).  ``undelivered``
    stays 0: the samples of a flush the sink refused are kept and sent with
    the next one, so they count as ``pending``; once the connector has
    stopped, ``pending`` is 0 unless the sink refused the last flush.

    Attributes
    ----------
    reconnects : int
        Sessions established after a lost one.
    watchdog_timeouts : int
        Times the watchdog found the subscription stale.
    sink_failures : int
        Flushes the sink refused (their samples are kept and sent again).
    backfilled : int
        Samples read with HistoryRead after reconnects (also counted in ``samples``).
    """

    reconnects: int = 0
    watchdog_timeouts: int = 0
    sink_failures: int = 0
    backfilled: int = 0


class _SessionEndedError(Exception):
    """The session is over (transport lost, subscription ended, watchdog); the message says why."""


class OpcUaConnector(BackgroundConnector[OpcUaCounters]):
    """Subscribe to the nodes of one endpoint and deliver their samples to ``sink``.

    Parameters
    ----------
    config : OpcUaEndpointConfig
    sink : SampleSink
        Called (in a worker thread) with ingest batches of the PI Web API shape.
    backoff : Backoff
        Waits between connection attempts; it starts over after every session
        that got as far as subscribing.
    clock : callable
        Wall clock (UNIX seconds) for outages and for samples without timestamps.

    Use ``await connector.run()`` (until cancelled) inside an event loop, or
    :meth:`start` / :meth:`stop` to run it in a thread of its own.
    """

    def __init__(
        self,
        config: OpcUaEndpointConfig,
        sink: SampleSink,
        *,
        backoff: Backoff = Backoff(),  # noqa: B008 -- frozen, so one shared default is safe
        clock: Callable[[], float] = time.time,
    ) -> None:
        super().__init__(f"opcua {config.url}", OpcUaCounters(), clock)
        self.config = config
        self.sink = sink
        self.backoff = backoff
        self.clock = clock
        self._tags = {handle: node.tag for handle, node in enumerate(config.nodes, start=1)}
        self._sessions = 0
        self._connected = False
        self._last_error: str | None = None
        self._failed_nodes: dict[str, str] = {}
        self._pending: dict[str, list[dict[str, Any]]] = {}
        self._warned_tags: set[str] = set()
        self._latest: dict[str, float] = {}  # tag -> time of its latest sample
        # stamps given in this session while back-filling, per tag, to send each sample once;
        # a tag's are dropped at its first live sample newer than the back-fill
        self._recent: dict[str, set[float]] = {}
        self._backfilling = False
        self._backfilled_to = math.inf

    @property
    def connected(self) -> bool:
        """Whether a session is up and subscribed."""
        return self._connected

    @property
    def last_error(self) -> str | None:
        """Why the last session ended or could not begin; None while connected."""
        return self._last_error

    @property
    def failed_nodes(self) -> dict[str, str]:
        """tag -> status name of the nodes the server refused to monitor in the last session."""
        return dict(self._failed_nodes)

    # --- running --------------------------------------------------------------

    async def run(self) -> None:
        """Connect, subscribe and deliver samples until cancelled; reconnect on any loss."""
        stop_flushing = asyncio.Event()
        flusher = asyncio.create_task(self._flush_until(stop_flushing), name="opcua-flush")
        delays = self.backoff.delays()
        try:
            while True:
                sessions_before = self._sessions
                try:
                    await self._session()
                except _SessionEndedError as exc:
                    reason = str(exc)
                except (OSError, ua.UaError, ConnectionError) as exc:  # TimeoutError is an OSError
                    reason = f"{type(exc).__name__}: {exc}"
                except Exception as exc:  # a bug or an unexpected answer: log it, carry on
                    log.exception("opcua %s: session failed unexpectedly", self.config.url)
                    reason = f"{type(exc).__name__}: {exc}"
                raise_if_cancelled()  # a stop that a library call returned through
                self._begin_outage(reason)
                if self._sessions > sessions_before:
                    delays = self.backoff.delays()
                delay = next(delays)
                log.info("opcua %s: reconnecting in %.1f s", self.config.url, delay)
                await asyncio.sleep(delay)
        finally:
            self._connected = False
            stop_flushing.set()
            await flusher

    def _begin_outage(self, reason: str) -> None:
        self._connected = False
        self._last_error = reason
        self._outages.lost(reason)

    def _session_up(self) -> None:
        if self._sessions > 0:
            with self._counters.lock:
                self._counters.reconnects += 1
        self._sessions += 1
        self._connected, self._last_error = True, None
        self._outages.restored()
        log.info("opcua %s: subscribed to %d nodes", self.config.url,
                 len(self._tags) - len(self._failed_nodes))

    # --- one session ------------------------------------------------------------

    async def _connect(self) -> Client:
        config = self.config
        # asyncua's own health probe (a read of the server state) runs at a third of
        # the watchdog period: a busy server is given that long to answer
        client = Client(config.url, timeout=config.request_timeout_s,
                        watchdog_intervall=max(1.0, config.watchdog_s / 3.0))
        client.application_uri = config.application_uri
        if config.security_policy != "none":
            assert config.certificate is not None and config.private_key is not None
            if config.trusted_certificates is not None:
                client.certificate_validator = await self._validator(config.trusted_certificates)
            await client.set_security(
                SECURITY_POLICIES[config.security_policy],
                certificate=str(config.certificate),
                private_key=str(config.private_key),
                server_certificate=(
                    str(config.server_certificate) if config.server_certificate else None
                ),
                mode=getattr(ua.MessageSecurityMode, config.security_mode),
            )
        if config.username is not None and config.password is not None:
            client.set_user(config.username)
            client.set_password(config.password.get_secret_value())
        await client.connect(auto_reconnect=False)
        return client

    async def _validator(self, trusted: Path) -> Callable[
            [x509.Certificate, ua.ApplicationDescription], Any]:
        """asyncua's certificate validator over the trust store ``trusted``, whose refusal
        names the server's certificate and where to put it to trust it."""
        store = TrustStore([trusted], [])
        await store.load()
        validator = CertificateValidator(
            CertificateValidatorOptions.TRUSTED_VALIDATION
            | CertificateValidatorOptions.PEER_SERVER, store)

        async def validate(certificate: x509.Certificate,
                           server: ua.ApplicationDescription) -> None:
            try:
                await validator.validate(certificate, server)
            except ServiceError as exc:
                status = ua.status_codes.get_name_and_doc(exc.code)[0]
                raise _SessionEndedError(
                    f"{status}: the server certificate {certificate.subject.rfc4514_string()} "
                    f"(application {server.ApplicationUri}, SHA-256 "
                    f"{certificate.fingerprint(hashes.SHA256()).hex(':')}, valid until "
                    f"{certificate.not_valid_after_utc:%Y-%m-%d}) is refused; if it is the "
                    f"right server, copy its certificate into {trusted} to trust it"
                ) from None

        return validate

    async def _session(self) -> None:
        """One connection: subscribe, back-fill what was missed, then consume until it
        ends, which it does by raising."""
        missed_since = dict(self._latest) if self._sessions else {}
        client = await self._connect()
        ended: asyncio.Future[str] = asyncio.get_running_loop().create_future()

        def end(reason: str) -> None:
            if not ended.done():
                ended.set_result(reason)

        async def on_connection_lost(exc: Exception) -> None:
            end(f"connection lost: {type(exc).__name__}: {exc}")

        client.connection_lost_callback = on_connection_lost
        subscription: Subscription | None = None
        consumer: asyncio.Task[None] | None = None
        watchdog: asyncio.Task[None] | None = None
        try:
            self._recent, self._backfilling = {}, bool(missed_since)
            subscription = await self._subscribe(client)
            self._session_up()
            consumer = asyncio.create_task(self._consume(subscription, end), name="opcua-consume")
            watchdog = asyncio.create_task(self._watch(subscription, end), name="opcua-watchdog")
            if missed_since and self.config.backfill_max_s > 0:
                self._backfilled_to = await self._backfill(client, missed_since)
            self._backfilling = False
            raise _SessionEndedError(await ended)
        finally:
            self._recent, self._backfilling, self._backfilled_to = {}, False, math.inf
            if watchdog is not None:
                watchdog.cancel()
            if subscription is not None:
                await self._close(subscription, consumer)
            await self._disconnect(client)

    async def _subscribe(self, client: Client) -> Subscription:
        """Create the subscription and its monitored items in batches.

        The subscription is built directly rather than by
        ``Client.create_subscription``, so that asyncua does not re-create it
        behind this connector's back: a stale subscription is this
        connector's watchdog's business, and it records the outage.
        """
        config = self.config
        params = ua.CreateSubscriptionParameters(
            RequestedPublishingInterval=config.publishing_interval_ms,
            RequestedLifetimeCount=10 * config.keepalive_count,
            RequestedMaxKeepAliveCount=config.keepalive_count,
            MaxNotificationsPerPublish=0,
            PublishingEnabled=True,
            Priority=0,
        )
        # queue_maxsize=0: unbounded, so that no notification is ever dropped
        subscription = Subscription(client.uaclient.session, params, None, queue_maxsize=0)
        await subscription.init()
        requests = [self._monitor_request(handle, node)
                    for handle, node in enumerate(config.nodes, start=1)]
        failed: dict[str, str] = {}
        for first in range(0, len(requests), MONITORED_ITEMS_PER_CALL):
            batch = requests[first: first + MONITORED_ITEMS_PER_CALL]
            results = await subscription.create_monitored_items(batch)
            for request, result in zip(batch, results, strict=True):
                if isinstance(result, ua.StatusCode):
                    tag = self._tags[request.RequestedParameters.ClientHandle]
                    failed[tag] = result.name
                    log.error(
                        "opcua %s: the server refused to monitor %s (%s): %s",
                        config.url, tag, request.ItemToMonitor.NodeId.to_string(), result.name,
                    )
        self._failed_nodes = failed
        return subscription

    async def _backfill(self, client: Client, since: dict[str, float]) -> float:
        """Read the samples each node had after ``since[tag]`` (and at most
        ``backfill_max_s`` ago) from the server's history, where its access level
        allows HistoryRead; samples this session has delivered already are skipped.
        The end of the span read (UNIX s).

        A node whose history cannot be read is logged and left with its hole.
        """
        end = datetime.now(UTC)
        nodes = {node.tag: client.get_node(node.node_id) for node in self.config.nodes
                 if node.tag in since and node.tag not in self._failed_nodes}
        levels = await client.read_attributes(list(nodes.values()),
                                              ua.AttributeIds.UserAccessLevel)
        earliest = end.timestamp() - self.config.backfill_max_s
        read = 0
        for (tag, node), level in zip(nodes.items(), levels, strict=True):
            access = level.Value.Value if level.Value is not None else None
            if not isinstance(access, int) or not ua.ua_binary.test_bit(
                    access, ua.AccessLevel.HistoryRead):
                continue
            start = max(since[tag], earliest)
            try:
                history = await node.read_raw_history(
                    datetime.fromtimestamp(start, UTC), end, return_bounds=False)
            except (ua.UaError, OSError) as exc:
                log.warning("opcua %s: the history of %s could not be read after the "
                            "reconnect (%s): its gap stays", self.config.url, tag, exc)
                continue
            for data_value in history:
                timestamp, value = self._sample(tag, data_value)
                if timestamp > start and self._add(tag, timestamp, value):
                    read += 1
        with self._counters.lock:
            self._counters.backfilled += read
        if read:
            log.info("opcua %s: %d missed samples read from the server's history",
                     self.config.url, read)
        return end.timestamp()

    def _monitor_request(self, handle: int, node: OpcUaNodeConfig) -> ua.MonitoredItemCreateRequest:
        parameters = ua.MonitoringParameters(
            ClientHandle=handle,
            SamplingInterval=self.config.sampling_interval_ms,
            QueueSize=self.config.queue_size,
            DiscardOldest=True,
            Filter=ua.DataChangeFilter(Trigger=ua.DataChangeTrigger.StatusValueTimestamp),
        )
        return ua.MonitoredItemCreateRequest(
            ItemToMonitor=ua.ReadValueId(
                NodeId=ua.NodeId.from_string(node.node_id), AttributeId=ua.AttributeIds.Value
            ),
            MonitoringMode=ua.MonitoringMode.Reporting,
            RequestedParameters=parameters,
        )

    async def _consume(self, subscription: Subscription, end: Callable[[str], None]) -> None:
        """Take every notification until the subscription is closed; then end the session."""
        try:
            async for event in subscription:
                if isinstance(event, DataChangeEvent):
                    notification = event.data.monitored_item
                    tag = self._tags[notification.ClientHandle]
                    self._add(tag, *self._sample(tag, notification.Value))
                elif (isinstance(event, StatusChangeEvent)
                      and not event.notification.Status.is_good()):
                    end(f"the server ended the subscription: {event.notification.Status.name}")
        except Exception as exc:  # a bug: end the session rather than lose data quietly
            log.exception("opcua %s: reading notifications failed", self.config.url)
            end(f"reading notifications failed: {type(exc).__name__}: {exc}")
        else:
            end("the subscription was closed")

    def _sample(self, tag: str, data_value: ua.DataValue | None) -> tuple[float, float | None]:
        """(timestamp, value or None when bad) of one notification."""
        if data_value is None:
            return self.clock(), None
        stamp = data_value.SourceTimestamp or data_value.ServerTimestamp
        timestamp = _unix_seconds(stamp) if stamp is not None else self.clock()
        status = data_value.StatusCode
        if status is not None and not status.is_good():
            return timestamp, None
        value = None if data_value.Value is None else data_value.Value.Value
        if isinstance(value, int | float) and math.isfinite(value):
            return timestamp, float(value)
        if tag not in self._warned_tags:
            self._warned_tags.add(tag)
            log.warning("opcua %s: %s sent %r, not a number: stored as bad",
                        self.config.url, tag, value)
        return timestamp, None

    def _add(self, tag: str, timestamp: float, value: float | None) -> bool:
        """Queue one sample for the sink; False (and nothing queued) if it is one the
        subscription and the back-fill of this session both gave."""
        recent = self._recent.setdefault(tag, set()) if self._backfilling \
            else self._recent.get(tag)
        if recent is not None:
            if timestamp in recent:
                return False
            if self._backfilling:
                recent.add(timestamp)
            elif timestamp > self._backfilled_to:
                del self._recent[tag]
        self._pending.setdefault(tag, []).append(item(timestamp, value))
        self._latest[tag] = max(timestamp, self._latest.get(tag, timestamp))
        with self._counters.lock:
            self._counters.samples += 1
            self._counters.bad += value is None
        return True

    async def _watch(self, subscription: Subscription, end: Callable[[str], None]) -> None:
        """End the session when neither data nor a keep-alive came for ``watchdog_s``."""
        watchdog_s = self.config.watchdog_s
        since = time.monotonic()
        while True:
            await asyncio.sleep(min(watchdog_s / 4.0, 1.0))
            heard = max(since, subscription.last_publish_at or since)
            silent = time.monotonic() - heard
            if silent > watchdog_s:
                with self._counters.lock:
                    self._counters.watchdog_timeouts += 1
                end(f"watchdog: no data and no keep-alive for {silent:.1f} s "
                    f"(limit {watchdog_s:g} s)")
                return

    async def _close(self, subscription: Subscription, consumer: asyncio.Task[None] | None) -> None:
        """Delete the subscription, then let the consumer take what is still queued."""
        try:
            await asyncio.wait_for(subscription.delete(), DISCONNECT_TIMEOUT_S)
        except Exception as exc:  # the server is often gone: the local queue closes anyway
            log.debug("opcua %s: deleting the subscription: %r", self.config.url, exc)
        if consumer is not None:
            await asyncio.wait_for(consumer, DISCONNECT_TIMEOUT_S)

    async def _disconnect(self, client: Client) -> None:
        try:
            await asyncio.wait_for(client.disconnect(), DISCONNECT_TIMEOUT_S)
        except Exception as exc:  # the transport is often gone already
            log.debug("opcua %s: disconnect: %r", self.config.url, exc)
        # when asyncua's health probe gives up it marks the client disconnected but
        # leaves the socket open, and disconnect() then skips it: close it here
        protocol = client.uaclient.protocol
        if protocol is not None and protocol.transport is not None:
            protocol.transport.close()

    # --- delivery -------------------------------------------------------------

    async def _flush_until(self, stop: asyncio.Event) -> None:
        """Flush every ``flush_interval_s``, and once more when ``stop`` is set.

        Stopped by the event rather than cancelled: a sink call cannot be
        cancelled half-way, and its samples must be counted either way.  The
        last flush comes after the stop, so samples that arrived while a flush
        was in the sink are delivered too.
        """
        while not stop.is_set():
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), self.config.flush_interval_s)
            await self._flush()
        await self._flush()

    async def _flush(self) -> None:
        """Hand the pending samples to the sink; on failure keep them for the next flush."""
        if not self._pending:
            return
        pending, self._pending = self._pending, {}
        batch = [{"tag": tag, "items": items} for tag, items in pending.items()]
        count = sum(len(items) for items in pending.values())
        try:
            await asyncio.to_thread(self.sink, batch)
        except Exception:
            log.exception(
                "opcua %s: the sink refused %d samples; they are kept for the next flush",
                self.config.url, count,
            )
            for tag, items in self._pending.items():  # arrived during the failed call
                pending.setdefault(tag, []).extend(items)
            self._pending = pending
            with self._counters.lock:
                self._counters.sink_failures += 1
            return
        with self._counters.lock:
            self._counters.delivered += count


def _unix_seconds(stamp: datetime) -> float:
    """UNIX seconds of an OPC UA time stamp (UTC; asyncua may give it without a zone)."""
    if stamp.tzinfo is None:
        stamp = stamp.replace(tzinfo=UTC)
    return stamp.timestamp()

