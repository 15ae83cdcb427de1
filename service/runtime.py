"""The running service's shared state: configuration, store, buffers, metrics.

:meth:`AppState.ingest` is the one path every sample takes into the store
(historian push, CSV upload, connectors, the demo feeder).  It keeps the
books of :class:`SampleAccounting`: every sample received is stored, was
already stored, is refused with a reason, or waits in the spool while the
store is unreachable (:mod:`service.spool`).
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Hashable, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeoutError
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from importlib import import_module
from multiprocessing import get_context
from typing import Any, Protocol, TypeVar, cast

from sqlalchemy.orm import Session

from connectors.base import DeliveryCounters, Outage
from service.auth import KeyVerifier
from service.buffer import LoopBuffers
from service.config import LoopConfig, Settings
from service.executors import ANALYSIS_NICENESS, end_executor
from service.ingest import (
    REFUSAL_REASONS,
    IngestError,
    IngestReport,
    TagItems,
    _validate,
    ingest_batch,
    ingest_csv,
    parse_batch,
)
from service.metrics import Metrics, ServiceCollector
from service.notifications import Outbox
from service.plant import PlantRegistry
from service.read_cache import ReadCache
from service.security import ConcurrencyLimiter, RateLimiter
from service.spool import (
    IngestSpool,
    SpooledBatch,
    SpooledReport,
    StoreUnavailableError,
    is_store_outage,
)
from service.store.db import Store

__all__ = ["SPOOL_REFUSAL_REASONS", "AnalysisUnavailableError", "AppState", "SampleAccounting"]

log = logging.getLogger(__name__)

T = TypeVar("T")

LOOP_VIEW_TABLES = ("loops", "analysis_runs", "alarms")
"""The tables the loop list, the bad-actor ranking and the alarm list are read from."""


class AnalysisUnavailableError(RuntimeError):
    """An expensive analysis of a request could not run: its process died or it ran
    longer than ``settings.analysis_timeout_s`` (HTTP 503)."""

SPOOL_REFUSAL_REASONS = ("spool_full", "spool_write_error")
"""Refusals of the spool: full during an outage; a spooled batch the store then refused
with an error that is not an outage (logged with the error)."""


@dataclass(frozen=True)
class SampleAccounting:
    """Where every sample received since start went (the ``loopwatch_samples_*`` counters).

    ``received == stored + already_stored + sum(refused.values()) + spooled``
    holds whenever no ingest is in progress (:attr:`balanced`).
    """

    received: int
    stored: int
    already_stored: int
    refused: dict[str, int]
    spooled: int
    """Samples waiting in the spool now."""

    @property
    def balanced(self) -> bool:
        """True when every received sample is accounted for."""
        return self.received == (self.stored + self.already_stored
                                 + sum(self.refused.values()) + self.spooled)


class WatchedSource(Protocol):
    """What the service reports of a connector: its name, its counters and its outages."""

    name: str

    @property
    def counters(self) -> DeliveryCounters:
        """A consistent copy of the samples it made and what the sink did with them."""

    @property
    def outages(self) -> list[Outage]:
        """The times no data came, oldest first (the last one may still be open)."""


@dataclass
class AppState:
    """Everything the routes, the scheduler and the feeders share."""

    settings: Settings
    registry: PlantRegistry
    store: Store
    buffers: LoopBuffers
    metrics: Metrics = field(default_factory=Metrics)
    clock: Callable[[], float] = time.time
    sources: list[WatchedSource] = field(default_factory=list)
    outbox: Outbox | None = None
    """Where the routes write the events of operators' alarm and ticket actions
    (:mod:`service.notifications`); None without a notification channel."""
    spool: IngestSpool = field(init=False)
    keys: KeyVerifier = field(init=False)
    limiter: RateLimiter = field(init=False)
    auth_failures: RateLimiter = field(init=False)
    analyses: ConcurrencyLimiter = field(init=False)
    loop_views: ReadCache = field(init=False)
    """The loop states and bad-actor rankings the requests share (:mod:`service.read_cache`)."""

    def buffers_for(self, session: Session, loops: Sequence[LoopConfig], window_s: float,
                    now: float) -> LoopBuffers:
        """The rolling buffers when this process keeps samples of ``loops``; else (an API
        replica) buffers of ``loops`` rebuilt from the store for the window ending ``now``."""
        if any(self.buffers.holds_samples(loop.id) for loop in loops):
            return self.buffers
        return LoopBuffers.from_store(session, loops, since=now - window_s, now=now)

    def __post_init__(self) -> None:
        self.metrics.register(ServiceCollector(self.store, lambda: self.sources, self.clock))
        self.spool = IngestSpool(max_samples=self.settings.spool_max_samples)
        self.keys = KeyVerifier(self.store, grace_s=self.settings.auth_outage_grace_s,
                                cache_s=self.settings.auth_cache_s)
        self.limiter = RateLimiter(rate_per_s=self.settings.rate_limit_per_s,
                                   burst=self.settings.rate_limit_burst)
        self.auth_failures = RateLimiter(rate_per_s=self.settings.auth_failure_per_s,
                                         burst=self.settings.auth_failure_burst)
        self.loop_views = ReadCache(self.store, LOOP_VIEW_TABLES,
                                    max_age_s=self.settings.read_cache_s)
        self.analyses = ConcurrencyLimiter(per_key=self.settings.analyses_per_key,
                                           total=2 * self.settings.analysis_processes)
        self._ingest_slots = threading.BoundedSemaphore(self.settings.ingest_concurrency)
        self._analysis_pool: ProcessPoolExecutor | None = None
        self._pool_lock = threading.Lock()
        self._answers: OrderedDict[Hashable, Any] = OrderedDict()
        self._flushing = threading.Lock()
        self._next_flush = -math.inf  # time.monotonic() of the next attempt to write the spool

    def _pool(self) -> ProcessPoolExecutor:
        with self._pool_lock:
            if self._analysis_pool is None:
                # spawned, not forked: a fork would inherit this process's sockets and
                # pipes and hold them open (a client's connection, a child's stdin)
                self._analysis_pool = ProcessPoolExecutor(
                    self.settings.analysis_processes, mp_context=get_context("spawn"),
                    initializer=os.nice, initargs=(ANALYSIS_NICENESS,))
            return self._analysis_pool

    def start_analyses(self) -> None:
        """Start the analysis process(es) now, each importing the API's modules (whose
        functions the analyses run), without waiting for them: else the first analysis
        waits while a process at :data:`ANALYSIS_NICENESS` starts and imports, which on
        a busy machine took the load benchmark's first model check 34-58 s of its
        LOOPWATCH_ANALYSIS_TIMEOUT_S (60 s).  ``loopwatch serve`` calls it at start."""
        pool = self._pool()
        for _ in range(self.settings.analysis_processes):
            pool.submit(import_module, "service.api.app")

    def analyse(self, function: Callable[..., T], *args: Any) -> T:
        """``function(*args)`` in the API's analysis process(es), waited for here.

        Compiled kernels hold the interpreter lock while they run; in a
        separate process (at a lower CPU priority, :data:`ANALYSIS_NICENESS`)
        they cannot hold up the other requests.  The
        caller holds a slot of :attr:`analyses`, so at most two analyses per
        process are submitted at once.

        Raises
        ------
        AnalysisUnavailableError
            The process died, or the analysis outlived ``analysis_timeout_s``
            (its process is then killed; the next analysis starts a new one).
        """
        pool = self._pool()
        try:
            return pool.submit(function, *args).result(timeout=self.settings.analysis_timeout_s)
        except (BrokenProcessPool, FutureTimeoutError) as exc:
            with self._pool_lock:
                if self._analysis_pool is pool:
                    self._analysis_pool = None
            end_executor(pool)
            reason = ("took longer than LOOPWATCH_ANALYSIS_TIMEOUT_S "
                      f"({self.settings.analysis_timeout_s:g} s)"
                      if isinstance(exc, FutureTimeoutError) else "its process died")
            raise AnalysisUnavailableError(f"The analysis {reason}; try again later") from None

    ANSWERS_KEPT = 256
    """Answers of pure analyses kept by :meth:`analyse_cached`."""

    def analyse_cached(self, function: Callable[..., T], *args: Hashable) -> T:
        """:meth:`analyse` for a pure function of hashable arguments (JSON text, ids):
        the last :attr:`ANSWERS_KEPT` answers are kept and given again."""
        key = (function.__module__, function.__qualname__, args)
        with self._pool_lock:
            if key in self._answers:
                self._answers.move_to_end(key)
                return cast(T, self._answers[key])
        answer = self.analyse(function, *args)
        with self._pool_lock:
            self._answers[key] = answer
            if len(self._answers) > self.ANSWERS_KEPT:
                self._answers.popitem(last=False)
        return answer

    def close_analyses(self) -> None:
        """End the analysis process(es), if any were started."""
        with self._pool_lock:
            pool, self._analysis_pool = self._analysis_pool, None
        if pool is not None:
            end_executor(pool)

    def _account(self, report: IngestReport, *, received: bool = True) -> None:
        """Feed the buffers and count; ``received`` False for a batch counted on entering
        the spool."""
        self.buffers.append_new(report.new_samples)
        if received:
            self.metrics.inc("loopwatch_samples_received_total", report.received)
        self.metrics.inc("loopwatch_samples_stored_total", report.stored)
        self.metrics.inc("loopwatch_samples_already_stored_total", report.already_stored)
        for reason, count in report.refused.items():
            self.metrics.inc("loopwatch_samples_refused_total", count, reason=reason)

    def _write(self, batch: list[TagItems] | list[dict[str, Any]]) -> IngestReport:
        with self.store.session() as session:
            return ingest_batch(
                session, batch, known_tags=self.registry.tag_index().keys(), now=self.clock()
            )

    def ingest(self, batch: list[dict[str, Any]] | list[Any]) -> IngestReport:
        """Store a batch (one transaction), then feed the rolling buffers.

        At most ``settings.ingest_concurrency`` batches (and CSV uploads) are
        validated and written at once: on SQLite they would only queue for
        the write lock, and in the meantime hold the interpreter lock that
        the other requests need.

        While the store is unreachable, or the spool still holds batches, the
        batch is spooled instead and a :class:`~service.spool.SpooledReport`
        returned.

        Raises
        ------
        IngestError
            The batch is malformed or longer than ``settings.max_batch_samples``;
            nothing is stored.
        StoreUnavailableError
            The store is unreachable and the batch does not fit in the spool;
            it is counted as refused (``spool_full``).
        """
        with self._ingest_slots:
            return self._ingest(_validate(batch))

    def ingest_json(self, body: bytes) -> IngestReport:
        """:meth:`ingest` of a request body, parsed in the same slot
        (:func:`service.ingest.parse_batch`: refused in bounded time)."""
        with self._ingest_slots:
            return self._ingest(parse_batch(body, max_samples=self.settings.max_batch_samples,
                                            pi_points=self.registry.plant.pi_points))

    def _ingest(self, items: list[TagItems]) -> IngestReport:
        samples = sum(len(entry.items) for entry in items)
        if samples > self.settings.max_batch_samples:
            raise IngestError(
                f"batch of {samples} samples is longer than the limit of "
                f"{self.settings.max_batch_samples} (LOOPWATCH_MAX_BATCH_SAMPLES); split it"
            )
        if len(self.spool) and time.monotonic() >= self._next_flush:
            self.flush_spool()
        if len(self.spool):
            return self._hold(SpooledBatch.of(items))
        try:
            report = self._write(items)
        except Exception as exc:
            if not is_store_outage(exc):
                raise
            log.warning("store unreachable (%s): spooling ingest batches", type(exc).__name__)
            self._next_flush = time.monotonic() + self.settings.spool_retry_s
            return self._hold(SpooledBatch.of(items))
        self._account(report)
        return report

    def _hold(self, held: SpooledBatch) -> SpooledReport:
        self.metrics.inc("loopwatch_samples_received_total", held.samples)
        if not self.spool.put(held):
            self.metrics.inc("loopwatch_samples_refused_total", held.samples, reason="spool_full")
            log.warning("store unreachable and spool full: refused a batch of %d samples",
                        held.samples)
            raise StoreUnavailableError(
                f"The store is unreachable and the ingest spool is full ({self.spool.samples} "
                f"of {self.spool.max_samples} samples held): the batch of {held.samples} "
                "samples was not accepted; send it again later"
            )
        self.metrics.inc("loopwatch_samples_spooled_total", held.samples)
        return SpooledReport.of(held, self.spool.samples)

    def flush_spool(self) -> int:
        """Write the spooled batches, oldest first, until the spool is empty or the store
        fails again; the number of samples taken out of the spool.

        Called by :meth:`ingest` at most every ``settings.spool_retry_s`` while
        the spool holds batches; the scheduler may call it too.  Only one
        thread writes the spool at a time (others return 0 at once).
        """
        if not self._flushing.acquire(blocking=False):
            return 0
        written = 0
        try:
            while (held := self.spool.oldest()) is not None:
                try:
                    report = self._write(held.as_batch())
                except Exception as exc:
                    if is_store_outage(exc):
                        self._next_flush = time.monotonic() + self.settings.spool_retry_s
                        break
                    log.exception("a spooled batch of %d samples could not be stored",
                                  held.samples)
                    self.metrics.inc("loopwatch_samples_refused_total", held.samples,
                                     reason="spool_write_error")
                else:
                    self._account(report, received=False)
                self.spool.discard_oldest()
                self.metrics.inc("loopwatch_samples_unspooled_total", held.samples)
                written += held.samples
        finally:
            self._flushing.release()
        if written and not len(self.spool):
            log.info("store reachable again: %d spooled samples written", written)
        return written

    def ingest_csv(self, text: str) -> IngestReport:
        """Store an uploaded CSV (long or wide format), then feed the buffers.

        Raises
        ------
        StoreUnavailableError
            The store is unreachable (CSV uploads are not spooled: send the
            file again later).
        """
        with self._ingest_slots:
            return self._ingest_csv(text)

    def _ingest_csv(self, text: str) -> IngestReport:
        if len(self.spool) and time.monotonic() >= self._next_flush:
            self.flush_spool()
        try:
            with self.store.session() as session:
                report = ingest_csv(
                    session, text, known_tags=self.registry.tag_index().keys(), now=self.clock()
                )
        except Exception as exc:
            if not is_store_outage(exc):
                raise
            raise StoreUnavailableError(
                "The store is unreachable: CSV uploads are not spooled, send the file again "
                "later"
            ) from None
        self._account(report)
        return report

    def accounting(self) -> SampleAccounting:
        """The sample counters now (see :class:`SampleAccounting`)."""
        count = self.metrics.value
        return SampleAccounting(
            received=int(count("loopwatch_samples_received_total")),
            stored=int(count("loopwatch_samples_stored_total")),
            already_stored=int(count("loopwatch_samples_already_stored_total")),
            refused={reason: n for reason in (*REFUSAL_REASONS, *SPOOL_REFUSAL_REASONS)
                     if (n := int(count("loopwatch_samples_refused_total", reason=reason)))},
            spooled=int(count("loopwatch_samples_spooled_total")
                        - count("loopwatch_samples_unspooled_total")),
        )
