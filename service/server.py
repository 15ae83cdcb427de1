"""``loopwatch serve``: build the service, start its background work, run the API.

With no plant file the service runs the demo: the simulated plant of
:mod:`service.demo` is fed in-process, the analysis interval is short and
the window one hour, so alarms and a ticket for each sticky valve appear
within about a minute of start.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from concurrent.futures import Executor, ProcessPoolExecutor
from contextlib import asynccontextmanager, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import uvicorn
from fastapi import FastAPI

from service.api.app import create_app
from service.auth import ensure_bootstrap_key
from service.buffer import LoopBuffers
from service.config import PlantConfig, Settings, load_plant_config
from service.demo import DemoFeeder, DemoPlant, demo_plant_config
from service.metrics import Metrics
from service.plant import PlantRegistry, sync_plant
from service.runtime import AppState
from service.scheduler import AnalysisScheduler
from service.store.db import Store
from service.tickets import TicketWebhook, get_ticket

__all__ = ["Service", "build_service", "serve"]

log = logging.getLogger(__name__)

DEMO_INTERVAL_S = 15.0


@dataclass
class Service:
    """The parts of a running service and their lifecycle."""

    state: AppState
    scheduler: AnalysisScheduler
    executor: Executor
    feeder: DemoFeeder | None
    webhook: TicketWebhook | None
    admin_key: str
    key_generated: bool
    app: FastAPI

    def start(self) -> None:
        """Backfill the demo (if any), then start analysing."""
        if self.feeder is not None:
            self.feeder.start()
        self.scheduler.start()

    def stop(self) -> None:
        """Stop feeding and analysing; release the pool and the database."""
        if self.feeder is not None:
            self.feeder.stop()
        self.scheduler.stop()
        if self.webhook is not None:
            self.webhook.close()
        self.executor.shutdown(wait=False, cancel_futures=True)
        self.state.store.close()


def build_service(
    settings: Settings,
    plant: PlantConfig | None,
    *,
    executor: Executor | None = None,
    clock: Any = time.time,
) -> Service:
    """Open the store (migrating it), rebuild the buffers, wire scheduler and API.

    ``plant`` None means the demo plant.
    """
    demo = plant is None
    plant = demo_plant_config() if plant is None else plant
    store = Store(settings.resolved_database_url)
    now = clock()
    admin_key, generated = settings.bootstrap_key()
    with store.session() as session:
        sync_plant(session, plant, now)
        ensure_bootstrap_key(session, admin_key, now)
    buffers = LoopBuffers(plant, horizon_s=settings.buffer_horizon_s)
    with store.session() as session:
        loaded = buffers.rebuild_from_store(session, now)
    log.info("rolling buffers rebuilt from the store: %d samples", loaded)
    metrics = Metrics()
    state = AppState(settings=settings, registry=PlantRegistry(plant), store=store,
                     buffers=buffers, metrics=metrics, clock=clock)
    executor = executor or ProcessPoolExecutor(max_workers=settings.workers)
    webhook = TicketWebhook(settings.webhook_url) if settings.webhook_url else None

    def post_ticket(ticket_id: int) -> None:
        assert webhook is not None
        with store.session() as session:
            webhook.send(get_ticket(session, ticket_id))

    scheduler = AnalysisScheduler(
        store=store, registry=state.registry, buffers=buffers, settings=settings,
        executor=executor, metrics=metrics, clock=clock,
        on_ticket=post_ticket if webhook is not None else None,
    )
    feeder = DemoFeeder(DemoPlant(start=now), state.ingest, clock=clock) if demo else None
    return Service(state, scheduler, executor, feeder, webhook, admin_key, generated,
                   create_app(state))


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


def serve(config: Path | None, *, host: str | None = None, port: int | None = None) -> None:
    """Run the service until interrupted (the ``loopwatch serve`` command)."""
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    plant = load_plant_config(config) if config is not None else None
    settings = Settings()
    updates: dict[str, Any] = {k: v for k, v in (("host", host), ("port", port)) if v is not None}
    if plant is None:
        updates |= {k: v for k, v in DEMO_SETTINGS.items() if k not in settings.model_fields_set}
    settings = settings.model_copy(update=updates)
    service = build_service(settings, plant)

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> Any:
        with running(service):
            yield

    service.app.router.lifespan_context = lifespan
    url = f"http://{settings.host}:{settings.port}"
    print(f"loopwatch: dashboard at {url}/  (API schema at {url}/openapi.json, with a key)")
    if service.key_generated:
        print(f"loopwatch: admin API key for this run: {service.admin_key}")
        print(f"loopwatch: signed-in dashboard link: {url}/#key={service.admin_key}")
        print("           (set LOOPWATCH_API_KEY to keep one across restarts)")
    if plant is None:
        print("loopwatch: demo plant -- simulated loops, two with sticky valves "
              f"(FIC-101, FIC-105); analyses every {DEMO_INTERVAL_S:g} s")
    uvicorn.run(service.app, host=settings.host, port=settings.port, log_level="info")
