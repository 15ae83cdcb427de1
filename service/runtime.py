"""The running service's shared state: configuration, store, buffers, metrics."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from service.buffer import LoopBuffers
from service.config import Settings
from service.ingest import IngestReport, ingest_batch, ingest_csv
from service.metrics import Metrics
from service.plant import PlantRegistry
from service.store.db import Store

__all__ = ["AppState"]


@dataclass
class AppState:
    """Everything the routes, the scheduler and the feeders share."""

    settings: Settings
    registry: PlantRegistry
    store: Store
    buffers: LoopBuffers
    metrics: Metrics = field(default_factory=Metrics)
    clock: Callable[[], float] = time.time

    def _account(self, report: IngestReport) -> None:
        self.buffers.append_new(report.new_samples)
        self.metrics.inc("loopwatch_samples_received_total", report.received)
        self.metrics.inc("loopwatch_samples_stored_total", report.stored)
        for reason, count in report.refused.items():
            self.metrics.inc("loopwatch_samples_refused_total", count, reason=reason)

    def ingest(self, batch: list[dict[str, Any]] | list[Any]) -> IngestReport:
        """Store a batch (one transaction), then feed the rolling buffers."""
        with self.store.session() as session:
            report = ingest_batch(
                session, batch, known_tags=self.registry.tag_index().keys(), now=self.clock()
            )
        self._account(report)
        return report

    def ingest_csv(self, text: str) -> IngestReport:
        """Store an uploaded CSV (long or wide format), then feed the buffers."""
        with self.store.session() as session:
            report = ingest_csv(
                session, text, known_tags=self.registry.tag_index().keys(), now=self.clock()
            )
        self._account(report)
        return report
