"""Service metrics for Prometheus, kept and written by ``prometheus_client``.

Every counter and histogram is declared here with its HELP text and labels
(:data:`COUNTERS`, :data:`HISTOGRAMS`), in a registry of the service's own
(tests build many services in one process).  The API, the scheduler thread
and the connectors count through :class:`Metrics`; what the store and the
connectors know is read when ``GET /metrics`` is scraped, by
:class:`ServiceCollector`.  ``prometheus_client`` escapes label values, adds
the ``_total`` suffix of counters and writes the histogram buckets.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING

from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector
from sqlalchemy import func, select

from service.spool import is_store_outage
from service.store.models import Alarm, Loop, Notification, Ticket

if TYPE_CHECKING:
    from service.runtime import WatchedSource
    from service.store.db import Store

__all__ = ["COUNTERS", "HISTOGRAMS", "Metrics", "ServiceCollector"]

log = logging.getLogger(__name__)

COUNTERS: dict[str, tuple[str, tuple[str, ...]]] = {
    "loopwatch_samples_received": ("Samples received by ingest (batches, uploads, connectors)",
                                   ()),
    "loopwatch_samples_stored": ("Samples written to the store", ()),
    "loopwatch_samples_already_stored": ("Samples received that the store already held", ()),
    "loopwatch_samples_refused": ("Samples refused, by reason", ("reason",)),
    "loopwatch_samples_spooled": ("Samples held in memory while the store was unreachable", ()),
    "loopwatch_samples_unspooled": ("Spooled samples taken out of the spool", ()),
    "loopwatch_samples_purged": ("Samples deleted by the retention", ()),
    "loopwatch_rounds_missed": ("Analysis rounds skipped because the scheduler was behind", ()),
    "loopwatch_executor_replacements": ("Analysis executors replaced after a dead or hung "
                                        "worker", ()),
    "loopwatch_analysis_retries": ("Loop analyses tried again, by cause", ("cause",)),
    "loopwatch_analyses": ("Loop analyses finished, by status", ("status",)),
    "loopwatch_analyses_duplicate": ("Analysis results another scheduler had stored first", ()),
    "loopwatch_unit_analyses": ("Unit diagnoses finished, by status", ("status",)),
}
"""Counter name (without ``_total``) -> (HELP text, label names)."""

ANALYSIS_BUCKETS = (0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0)
"""Histogram buckets of analysis times, s (a loop takes 0.1-10 s; the time limit is 60 s)."""

HISTOGRAMS: dict[str, tuple[str, tuple[str, ...]]] = {
    "loopwatch_analysis_duration_seconds": (
        "Time from the submission of an analysis to the executor to its outcome", ("kind",)),
    "loopwatch_analysis_queue_seconds": (
        "Time an analysis of a round waited for a free worker slot before it was submitted",
        ("kind",)),
}
"""Histogram name -> (HELP text, label names); buckets :data:`ANALYSIS_BUCKETS`."""


class Metrics:
    """The service's counters and histograms, rendered for ``GET /metrics``."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self._counters = {name: Counter(name, text, labels, registry=self.registry)
                          for name, (text, labels) in COUNTERS.items()}
        self._histograms = {name: Histogram(name, text, labels, registry=self.registry,
                                            buckets=ANALYSIS_BUCKETS)
                            for name, (text, labels) in HISTOGRAMS.items()}

    def inc(self, name: str, amount: float = 1.0, **labels: str) -> None:
        """Add ``amount`` to counter ``name`` (with or without ``_total``) with ``labels``.

        Raises
        ------
        KeyError
            ``name`` is not in :data:`COUNTERS`.
        """
        counter = self._counters[name.removesuffix("_total")]
        (counter.labels(**labels) if labels else counter).inc(amount)

    def observe(self, name: str, seconds: float, **labels: str) -> None:
        """Record ``seconds`` in histogram ``name`` (one of :data:`HISTOGRAMS`)."""
        histogram = self._histograms[name]
        (histogram.labels(**labels) if labels else histogram).observe(seconds)

    def value(self, name: str, **labels: str) -> float:
        """Current value of a sample of the counters and histograms, as
        ``loopwatch_analyses_total`` (0 if never counted); the store is not read."""
        for metric in (*self._counters.values(), *self._histograms.values()):
            for family in metric.collect():
                for sample in family.samples:
                    if sample.name == name and sample.labels == labels:
                        return float(sample.value)
        return 0.0

    def register(self, collector: Collector) -> None:
        """Read ``collector`` at every scrape too."""
        self.registry.register(collector)

    def render(self) -> bytes:
        """The exposition text (the Prometheus text format)."""
        return generate_latest(self.registry)


class ServiceCollector(Collector):
    """What the store and the connectors know, read at every scrape.

    Gauges: loops, active alarms, open tickets, and per connector whether data
    comes now and its pending samples; counters (``_total``): per connector its
    outages, their length, and its samples made, bad, delivered and given up;
    per notification channel the events delivered and failed (counters) and
    pending (gauge), from the outbox.
    """

    def __init__(self, store: Store, sources: Callable[[], Sequence[WatchedSource]],
                 clock: Callable[[], float]) -> None:
        self.store, self.sources, self.clock = store, sources, clock

    def collect(self) -> Iterator[Metric]:
        """The metric families of this scrape."""
        try:
            yield from self._store_gauges()
        except Exception as exc:
            if not is_store_outage(exc):
                raise
            log.warning("store unreachable (%s): /metrics without the store's gauges",
                        type(exc).__name__)
        yield from self._connectors()

    def _store_gauges(self) -> Iterator[Metric]:
        """Loops, active alarms and open tickets, read in one session."""
        with self.store.session() as session:
            counts = {
                "loopwatch_loops": ("Loops configured", select(func.count()).select_from(Loop)),
                "loopwatch_alarms_active": ("Alarms not in the normal state",
                                            select(func.count()).where(Alarm.state != "normal")),
                "loopwatch_tickets_open": ("Tickets open, acknowledged or scheduled",
                                           select(func.count()).where(Ticket.state.in_(
                                               ("open", "acknowledged", "scheduled")))),
            }
            values = {name: float(session.scalar(query) or 0)
                      for name, (text, query) in counts.items()}
            outbox = session.execute(
                select(Notification.channel, Notification.state, func.count())
                .group_by(Notification.channel, Notification.state)).all()
        for name, (text, _) in counts.items():
            yield GaugeMetricFamily(name, text, value=values[name])
        finished = CounterMetricFamily(
            "loopwatch_notifications", "Ticket and alarm events delivered or given up, by "
            "channel", labels=["channel", "state"])
        pending = GaugeMetricFamily("loopwatch_notifications_pending",
                                    "Events waiting in the outbox, by channel",
                                    labels=["channel"])
        for channel, state, count in outbox:
            if state == "pending":
                pending.add_metric([channel], float(count))
            else:
                finished.add_metric([channel, state], float(count))
        yield finished
        yield pending

    def _connectors(self) -> Iterator[Metric]:
        now = self.clock()
        up = GaugeMetricFamily("loopwatch_connector_up",
                               "1 while the connector's data comes, 0 during an outage",
                               labels=["connector"])
        pending = GaugeMetricFamily("loopwatch_connector_pending",
                                    "Samples made but not yet delivered to ingest",
                                    labels=["connector"])
        totals = {
            "outages": "Outages of the connector since start",
            "outage_seconds": "Time without data from the connector since start, s",
            "samples": "Samples the connector made since start",
            "bad": "Samples made that were bad (status or value) since start",
            "delivered": "Samples delivered to ingest since start",
            "undelivered": "Samples given up since start",
        }
        counters = {key: CounterMetricFamily(f"loopwatch_connector_{key}", text,
                                             labels=["connector"])
                    for key, text in totals.items()}
        for source in self.sources():
            outages = source.outages
            counts = source.counters
            up.add_metric([source.name], float(not outages or outages[-1].end is not None))
            pending.add_metric([source.name], float(counts.pending))
            counters["outages"].add_metric([source.name], float(len(outages)))
            counters["outage_seconds"].add_metric([source.name], sum(
                (now if o.end is None else o.end) - o.start for o in outages))
            for key in ("samples", "bad", "delivered", "undelivered"):
                counters[key].add_metric([source.name], float(getattr(counts, key)))
        yield up
        yield pending
        yield from counters.values()
