"""``loopwatch serve``: build the service, start its background work, run the API.

With no plant file the service runs the demo (:mod:`service.demo`): the
simulated plant is served over OPC UA and Modbus TCP on loopback and read
through the connectors, its last hour back-filled at start; the analysis
interval is short and the window one hour, so alarms and a ticket for each
sticky valve appear within about a minute of start.

A process has a role (``--role`` or ``LOOPWATCH_ROLE``); the roles share
nothing but the store, so any number of each can run:

``api``
    The REST API only: stateless, run as many replicas as the load needs.
``ingest``
    The connectors whose endpoint falls in this process's shard
    (:func:`ingest_shard`), plus the API (health, metrics, historian push).
    The demo plant counts as one endpoint: the process that owns it serves
    the plant, reads both its servers and back-fills its history.
``scheduler``
    The analysis scheduler: one process leads (:mod:`service.leader`), the
    others stand by and take over when it dies.
``all``
    All of them in one process: the embedded default.
"""

from __future__ import annotations

import asyncio
import gc
import hashlib
import logging
import socket
import sys
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Executor
from contextlib import asynccontextmanager, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import uvicorn
from fastapi import FastAPI
from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError
from uvicorn.protocols.http.h11_impl import H11Protocol

from connectors.base import SampleSink
from service.api.app import create_app
from service.auth import ensure_bootstrap_key
from service.buffer import LoopBuffers
from service.config import ConfigError, PlantConfig, Settings, load_plant_config
from service.connector_setup import build_connectors
from service.demo import DemoFeeder, demo_plant_config
from service.executors import make_executor
from service.leader import make_election
from service.logs import configure_logging
from service.metrics import Metrics
from service.notifications import (
    Channel,
    EmailChannel,
    Outbox,
    OutboxDispatcher,
    WebhookChannel,
)
from service.plant import PlantRegistry, sync_plant
from service.runtime import AppState, WatchedSource
from service.scheduler import AnalysisScheduler
from service.store.db import Store
from service.store.models import Sample

__all__ = [
    "INGEST_ROLES",
    "ROLES",
    "SCHEDULING_ROLES",
    "Connector",
    "ConnectorFactory",
    "Service",
    "build_service",
    "ingest_shard",
    "serve",
    "uvicorn_config",
]

log = logging.getLogger(__name__)

DEMO_INTERVAL_S = 15.0

DEMO_ENDPOINT = "demo://loopwatch"
"""The demo plant counts as one endpoint: one ingest process serves, reads and back-fills it."""

ROLES = ("api", "ingest", "scheduler", "all")
INGEST_ROLES = frozenset({"ingest", "all"})
SCHEDULING_ROLES = frozenset({"scheduler", "all"})


class Connector(WatchedSource, Protocol):
    """A connector as the service runs it (:class:`connectors.opcua.OpcUaConnector` fits)."""

    def start(self) -> None:
        """Connect and deliver samples in the background."""

    def stop(self) -> None:
        """Disconnect; no sample is delivered afterwards."""


ConnectorFactory = Callable[[PlantConfig, Callable[[str], bool], SampleSink], list[Connector]]
"""The hook through which ingest processes get their connectors.

Called as ``factory(plant, owns, sink)``: build the connectors of
``plant.connectors`` whose endpoint ``owns(endpoint)`` accepts (the
endpoint as written in the plant file: an OPC UA ``url``, ``host:port`` of a
Modbus device), delivering their batches to ``sink``.
"""


def ingest_shard(endpoint: str, shards: int) -> int:
    """The ingest process, ``0 .. shards - 1``, that runs the connector of ``endpoint``.

    Rendezvous (highest random weight) hashing: every process computes the
    same answer with no coordination, the endpoints spread evenly, and going
    from ``n`` to ``n + 1`` processes moves only the endpoints the new process
    takes (about ``1 / (n + 1)`` of them).  Case, surrounding blanks and a
    trailing slash of the endpoint do not matter.

    References
    ----------
    D.G. Thaler and C.V. Ravishankar, "Using name-based mappings to increase
    hit rates", IEEE/ACM Trans. Networking 6(1), 1998.

    Examples
    --------
    >>> ingest_shard("opc.tcp://plc-7:4840", 3) == ingest_shard(" OPC.TCP://PLC-7:4840/ ", 3)
    True
    >>> ingest_shard("opc.tcp://plc-7:4840", 1)
    0
    """
    if shards < 1:
        raise ValueError(f"shards must be at least 1, got {shards}")
    key = endpoint.strip().rstrip("/").lower()
    return max(range(shards),
               key=lambda index: hashlib.sha256(f"{index}|{key}".encode()).digest())


@dataclass
class Service:
    """The parts of a running service and their lifecycle.

    ``scheduler`` and ``executor`` are None in processes that do not schedule
    (roles ``api`` and ``ingest``); ``executor`` is the scheduler's first
    executor (it builds a new one when a worker dies or hangs).  ``feeder`` is
    the demo plant, in the process that serves it.
    """

    state: AppState
    scheduler: AnalysisScheduler | None
    executor: Executor | None
    feeder: DemoFeeder | None
    notifications: OutboxDispatcher | None
    admin_key: str
    key_generated: bool
    app: FastAPI
    role: str = "all"
    connectors: list[Connector] = field(default_factory=list)

    def start(self) -> None:
        """Start the demo plant with its back-fill, the connectors, then scheduling."""
        if self.feeder is not None:
            with self.state.store.session() as session:
                stored_until = session.scalar(
                    select(func.max(Sample.time)).where(Sample.tag.in_(self.feeder.tags)))
            self.feeder.start(self.state.ingest, after=stored_until)
        for connector in self.connectors:
            connector.start()
        if self.feeder is not None:
            self.feeder.close_seam(self.state.ingest)
        if self.scheduler is not None:
            self.scheduler.start()
        if self.notifications is not None:
            self.notifications.start()

    def stop(self) -> None:
        """Stop reading and analysing; release the leadership, the pool and the database."""
        for connector in self.connectors:
            connector.stop()
        if self.feeder is not None:
            self.feeder.stop()
        if self.scheduler is not None:
            self.scheduler.stop()
        if self.notifications is not None:
            self.notifications.stop()
        if self.scheduler is not None:
            self.scheduler.executor.shutdown(wait=False, cancel_futures=True)
        self.state.close_analyses()
        self.state.store.close()


def notification_channels(settings: Settings) -> dict[str, Channel]:
    """The notification channels the settings configure (webhook, e-mail), by name."""
    channels: dict[str, Channel] = {}
    if settings.webhook_url is not None and settings.webhook_secret is not None:
        channels["webhook"] = WebhookChannel(settings.webhook_url,
                                             settings.webhook_secret.get_secret_value())
    if settings.smtp_host is not None:
        channels["email"] = EmailChannel(settings.smtp_host, settings.smtp_port,
                                         settings.email_from, settings.email_to)
    return channels


def _register(store: Store, plant: PlantConfig, admin_key: str, now: float, *,
              generated: bool) -> PlantConfig:
    """Write the plant and the bootstrap key (``generated`` for this run, or from the
    settings); the plant to run, with the loops added through the API
    (:func:`service.plant.sync_plant`).  Replicas starting together may collide once."""
    def register() -> PlantConfig:
        with store.session() as session:
            running_plant = sync_plant(session, plant, now)
            ensure_bootstrap_key(session, admin_key, now, generated=generated)
        return running_plant

    try:
        return register()
    except IntegrityError:
        log.info("another process registered the plant at the same time; updating it")
        return register()


def build_service(
    settings: Settings,
    plant: PlantConfig | None,
    *,
    executor: Executor | None = None,
    executor_factory: Callable[[], Executor] | None = None,
    clock: Any = time.time,
    connector_factory: ConnectorFactory | None = None,
) -> Service:
    """Open the store (migrating it), then wire what ``settings.role`` runs.

    ``plant`` None means the demo plant, served by the ingest process that
    owns :data:`DEMO_ENDPOINT` when there is a ``connector_factory``.  The
    scheduler builds its executor, and a new one after a worker died or hung,
    with ``executor_factory`` (default: :func:`service.executors.make_executor`
    of ``settings``); a fixed ``executor`` (a thread pool in tests) is never
    replaced.  Processes that schedule rebuild their rolling buffers from the
    store here.
    """
    role = settings.role

    def owns(endpoint: str) -> bool:
        return ingest_shard(endpoint, settings.ingest_shards) == settings.ingest_shard

    reads_plant = role in INGEST_ROLES and connector_factory is not None
    feeder = None
    if plant is None and reads_plant and owns(DEMO_ENDPOINT):
        # enough history for the ticket rule's confirmations on windows that do not overlap
        history_s = settings.ticket_confirmations * settings.window_s + settings.analysis_interval_s
        feeder = DemoFeeder(history_s=min(history_s, settings.buffer_horizon_s),
                            max_batch_samples=settings.max_batch_samples, clock=clock)
        plant = feeder.plant_config
    elif plant is None:
        plant = demo_plant_config()
    store = Store(settings.resolved_database_url)
    now = clock()
    admin_key, generated = settings.bootstrap_key()
    plant = _register(store, plant, admin_key, now, generated=generated)
    # only a scheduling process analyses windows: the others keep no rolling buffers (ingest
    # then leaves every sample to the store, and 10,000 loops save 2.4 GiB per process)
    schedules = role in SCHEDULING_ROLES
    buffers = LoopBuffers(plant if schedules else PlantConfig(),
                          horizon_s=settings.buffer_horizon_s)
    metrics = Metrics()
    state = AppState(settings=settings, registry=PlantRegistry(plant), store=store,
                     buffers=buffers, metrics=metrics, clock=clock)
    channels = notification_channels(settings)
    dispatcher = OutboxDispatcher(store, channels, clock=time.time) if channels else None
    state.outbox = Outbox(list(channels)) if channels else None

    scheduler = None
    if schedules:
        given = executor
        scheduler = AnalysisScheduler(
            store=store, registry=state.registry, buffers=buffers, settings=settings,
            executor_factory=executor_factory or (
                lambda: given if given is not None else make_executor(settings)),
            metrics=metrics, clock=clock,
            outbox=state.outbox,
            election=make_election(store, lease_s=settings.leader_lease_s),
        )
        executor = scheduler.executor
        loaded = scheduler.sync_buffers(now)
        log.info("rolling buffers rebuilt from the store: %d samples", loaded)
    connectors: list[Connector] = []
    if reads_plant and connector_factory is not None:
        if feeder is not None:  # the demo plant's servers are this process's
            connectors = connector_factory(plant, lambda _: True, feeder.live_sink(state.ingest))
        else:
            connectors = connector_factory(plant, owns, state.ingest)
    state.sources = list(connectors)
    return Service(state, scheduler, executor, feeder, dispatcher, admin_key, generated,
                   create_app(state), role=role, connectors=connectors)


MAX_HEADER_BYTES = 16 * 1024
"""Largest request head (request line and headers) uvicorn buffers, bytes."""


class DeadlineH11Protocol(H11Protocol):
    """uvicorn's HTTP/1.1 protocol with a deadline for a request's headers.

    uvicorn closes idle keep-alive connections, but a client that sends its
    headers a byte at a time is never cut off; here the connection is closed
    when a request's headers are not complete ``header_timeout_s`` after the
    connection opened or the previous response ended.
    """

    header_timeout_s = 10.0

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._deadline: asyncio.TimerHandle | None = self.loop.call_later(
            self.header_timeout_s, self._headers_too_slow)

    def handle_events(self) -> None:
        cycle = self.cycle
        super().handle_events()
        if self.cycle is not cycle and self._deadline is not None:  # a request head arrived
            self._deadline.cancel()
            self._deadline = None

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if self._deadline is None and not self.transport.is_closing():
            self._deadline = self.loop.call_later(self.header_timeout_s,
                                                  self._headers_too_slow)

    def connection_lost(self, exc: Exception | None) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None
        super().connection_lost(exc)

    def _headers_too_slow(self) -> None:
        self._deadline = None
        if (self.cycle is None or self.cycle.response_complete) \
                and not self.transport.is_closing():
            self.transport.close()


def uvicorn_config(app: FastAPI, settings: Settings) -> uvicorn.Config:
    """How ``loopwatch serve`` runs uvicorn: the header deadline
    (``LOOPWATCH_HEADER_TIMEOUT_S``), idle keep-alive connections closed after
    ``LOOPWATCH_KEEP_ALIVE_S``, at most ``LOOPWATCH_MAX_CONNECTIONS`` connections
    (requests beyond get 503), request heads of at most :data:`MAX_HEADER_BYTES`,
    the client's address from ``X-Forwarded-For`` of the proxies in
    ``LOOPWATCH_FORWARDED_ALLOW_IPS`` only.  The body deadline is
    :class:`service.security.BodyTimeoutMiddleware`'s."""
    protocol = type("ServeH11Protocol", (DeadlineH11Protocol,),
                    {"header_timeout_s": settings.header_timeout_s})
    return uvicorn.Config(
        app, host=settings.host, port=settings.port, log_level="info", http=protocol,
        timeout_keep_alive=max(1, round(settings.keep_alive_s)),
        limit_concurrency=settings.max_connections,
        h11_max_incomplete_event_size=MAX_HEADER_BYTES,
        proxy_headers=True, forwarded_allow_ips=settings.forwarded_allow_ips,
        log_config=None,  # uvicorn's records go to the handler of service.logs
    )


@contextmanager
def running(service: Service) -> Iterator[Service]:
    """Start the service's background work for the duration of a ``with`` block."""
    service.start()
    try:
        yield service
    finally:
        service.stop()


DEMO_SETTINGS = {"analysis_interval_s": DEMO_INTERVAL_S, "window_s": 3600.0,
                 "buffer_horizon_s": 2 * 3600.0}
"""Demo defaults (a variable set in the environment wins)."""


QUIET_LIBRARIES = ("asyncua", "pymodbus")
"""Libraries whose INFO messages would flood the console (asyncua logs every
subscription publish and every standard node it skips); their warnings show."""


YOUNG_OBJECTS_COLLECTED = 20_000
"""Allocations (net) between two collections of the youngest generation; Python's default
is 700."""

SWITCH_INTERVAL_S = 0.001
"""How long a thread waits for the interpreter lock before it asks the holder to let go;
Python's default is 5 ms."""


def tune_interpreter() -> None:
    """Tune the interpreter for many short requests beside a busy ingest (issue 20's load:
    20 dashboards, 4 historians pushing back to back, 2 model checks, 2,000 loops).

    * The objects made at start (modules, the plant's configuration, the store's
      metadata) are left out of the garbage collector's full collections from now
      on, and the youngest generation is collected every
      :data:`YOUNG_OBJECTS_COLLECTED` allocations.  A collection walks its
      generations while it holds the interpreter lock, and every request waits for
      it: the full collection ran about once a second for 0.15-1.6 s, most of the
      dashboard's p99; with the start's objects frozen, 79 full collections in a
      minute took 4.9 s (10-30 ms typically, up to 0.8 s) and 895 middle ones 1.3 s;
      collecting the youngest objects less often left one full and five middle
      collections in a minute.  Garbage is collected as before, a little later.
    * A request thread takes the interpreter lock back after every database call;
      while the ingest thread runs Python code it waited up to the switch interval
      each time, twenty times or more per request.  At :data:`SWITCH_INTERVAL_S`
      instead of 5 ms, four 40 s runs of each (alternating, on a shared machine) gave
      the dashboard p50 89-95 ms against 94-120 ms; p99 225-295 ms against
      199-523 ms (no clear difference) and the ingest rate alike.
    """
    gc.collect()
    gc.freeze()
    gc.set_threshold(YOUNG_OBJECTS_COLLECTED, *gc.get_threshold()[1:])
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    log.info("%d objects made at start left out of full garbage collections; "
             "switch interval %g s", gc.get_freeze_count(), SWITCH_INTERVAL_S)


def serve(config: Path | None, *, host: str | None = None, port: int | None = None,
          role: str | None = None) -> None:
    """Run the service until interrupted (the ``loopwatch serve`` command)."""
    plant = load_plant_config(config) if config is not None else None
    settings = Settings()
    configure_logging(settings.log_format, QUIET_LIBRARIES, settings.access_log)
    updates: dict[str, Any] = {
        k: v for k, v in (("host", host), ("port", port), ("role", role)) if v is not None
    }
    if plant is None:
        updates |= {k: v for k, v in DEMO_SETTINGS.items() if k not in settings.model_fields_set}
    settings = settings.model_copy(update=updates)
    check_port_free(settings.host, settings.port)  # before the plant starts and back-fills
    service = build_service(settings, plant, connector_factory=build_connectors)

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> Any:
        with running(service):
            tune_interpreter()
            service.state.start_analyses()
            yield

    service.app.router.lifespan_context = lifespan
    def announce() -> None:
        url = f"http://{settings.host}:{settings.port}"
        print(f"loopwatch: listening; role {settings.role}; dashboard at {url}/  (API docs "
              f"at {url}/docs, with a key)")
        if service.key_generated:
            print(f"loopwatch: admin API key for this run: {service.admin_key}")
            print(f"loopwatch: signed-in dashboard link: {url}/#key={service.admin_key}")
            print("           (set LOOPWATCH_API_KEY to keep one across restarts)")
        if service.feeder is not None:
            simulated = service.feeder.plant
            print(f"loopwatch: demo plant -- {len(simulated.loops)} simulated loops served over "
                  f"OPC UA ({simulated.opcua_url}) and Modbus TCP ({simulated.host}:"
                  f"{simulated.modbus_port}), {service.feeder.history_text} back-filled; "
                  "sticky valves FV-101, FV-105 and FV-502 (column unit); analyses every "
                  f"{settings.analysis_interval_s:g} s")
        sys.stdout.flush()

    AnnouncingServer(uvicorn_config(service.app, settings), announce).run()


class AnnouncingServer(uvicorn.Server):
    """A uvicorn server that calls ``announce`` once it listens (so the URL and the key
    printed are those of a server that answers)."""

    def __init__(self, config: uvicorn.Config, announce: Callable[[], None]) -> None:
        super().__init__(config)
        self.announce = announce

    async def startup(self, sockets: list[socket.socket] | None = None) -> None:
        """Start listening, then announce (unless the start failed)."""
        await super().startup(sockets)
        if not self.should_exit:
            self.announce()


def check_port_free(host: str, port: int) -> None:
    """Refuse to start when ``host:port`` is taken (port 0: any free port, never taken).

    Raises
    ------
    ConfigError
        The port is in use, with how to choose another.
    """
    if port == 0:
        return
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds
        try:
            probe.bind((host, port))
        except OSError as exc:
            raise ConfigError(
                f"cannot listen on {host}:{port}: {exc.strerror} (another loopwatch or "
                f"another server has it); choose another port with --port P or "
                f"LOOPWATCH_PORT=P, e.g. --port {port + 1}") from None
