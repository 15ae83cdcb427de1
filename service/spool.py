"""Riding out a store outage: ingest batches wait in a bounded spool until it returns.

When the database cannot be reached (PostgreSQL down or unreachable, a
SQLite file that cannot be written or stays locked), :class:`AppState.ingest
<service.runtime.AppState>` puts each validated batch into an
:class:`IngestSpool` instead of failing, answers with a
:class:`SpooledReport`, and writes the spooled batches, oldest first, once
the store answers again.  New batches join the spool while it holds any, so
the store sees the batches in the order they arrived.

The spool is bounded in samples.  Nothing is lost within the bound; a batch
that does not fit whole is refused whole with :class:`StoreUnavailableError`
(HTTP 503 with ``Retry-After``) and counted as refused for ``spool_full``, so
a historian can send it again and an in-process feeder knows it was lost.
The spool lives in memory: a service killed during an outage loses what it
held (the counters say how much was waiting).
"""

from __future__ import annotations

import math
import threading
from collections import Counter, deque
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from sqlalchemy.exc import DBAPIError, OperationalError

from analytics.types import FloatArray
from service.ingest import IngestReport, TagItems, TagReport, parse_timestamp

__all__ = [
    "IngestSpool",
    "SpooledBatch",
    "SpooledReport",
    "StoreUnavailableError",
    "is_store_outage",
]


class StoreUnavailableError(RuntimeError):
    """The store cannot be reached and the request cannot be held for later (HTTP 503)."""


def is_store_outage(exc: BaseException) -> bool:
    """True for errors that mean "the database cannot be reached or written now".

    Those are the driver's operational errors (connection refused or lost,
    ``database is locked``, ``disk I/O error``, a read-only file) and any
    error that invalidated the connection; integrity and programming errors
    are bugs or bad data and are not retried.
    """
    return isinstance(exc, OperationalError) or (
        isinstance(exc, DBAPIError) and exc.connection_invalidated
    )


BAD_TIME = -1.0
"""Stands for a time stamp that could not be read: refused as ``bad_timestamp`` on flush."""


@dataclass(frozen=True)
class SpooledBatch:
    """A validated ingest batch waiting for the store, packed into arrays.

    17 bytes a sample plus about 2 kB a batch (measured: 17 B a sample for
    batches of 1,000 samples a tag, 39 B for a connector's batch of 100 tags
    with one sample each), where the validated models take about 0.5 kB a
    sample.  Time stamps are parsed on entry with
    the ingest's own :func:`~service.ingest.parse_timestamp` (one that cannot
    be read becomes :data:`BAD_TIME`), a null value becomes NaN and a value
    sent as text is kept as text (refused as ``bad_value`` on flush), so the
    store sees the same samples and the same refusals as if the batch had
    been written at once.
    """

    tags: tuple[str, ...]
    """The batch's entries in order (a tag may appear more than once)."""
    lengths: NDArray[np.int64]
    """Items of each entry."""
    times: FloatArray
    values: FloatArray
    good: NDArray[np.bool_]
    texts: dict[int, str]
    """Values sent as text, by item index (NaN in ``values``)."""

    @property
    def samples(self) -> int:
        """Samples in the batch."""
        return int(self.times.size)

    @classmethod
    def of(cls, batch: list[TagItems]) -> SpooledBatch:
        """The packed form of a validated batch."""
        items = [item for entry in batch for item in entry.items]
        times = [parse_timestamp(item.timestamp) for item in items]
        texts = {k: item.value for k, item in enumerate(items) if isinstance(item.value, str)}
        return cls(
            tags=tuple(entry.tag for entry in batch),
            lengths=np.array([len(entry.items) for entry in batch], dtype=np.int64),
            times=np.array([BAD_TIME if t is None else t for t in times], dtype=np.float64),
            values=np.array([np.nan if item.value is None or k in texts else item.value
                             for k, item in enumerate(items)], dtype=np.float64),
            good=np.array([item.good for item in items], dtype=np.bool_),
            texts=texts,
        )

    def as_batch(self) -> list[dict[str, Any]]:
        """The batch as :func:`~service.ingest.ingest_batch` takes it."""
        bounds = np.concatenate(([0], np.cumsum(self.lengths))).tolist()
        times, values, good = self.times.tolist(), self.values.tolist(), self.good.tolist()
        return [
            {"tag": tag, "items": [
                {"timestamp": times[k],
                 "value": self.texts.get(k, None if math.isnan(values[k]) else values[k]),
                 "good": good[k]}
                for k in range(lo, hi)
            ]}
            for tag, lo, hi in zip(self.tags, bounds[:-1], bounds[1:], strict=True)
        ]


@dataclass(frozen=True)
class SpooledReport(IngestReport):
    """The answer to a batch that the spool holds: received, not stored yet.

    Every tag's items count as received and none as stored; ``spooled`` is
    the number of samples held for this batch and ``spool_samples`` the
    number the spool holds in all after taking it.
    """

    spooled: int = 0
    spool_samples: int = 0

    @classmethod
    def of(cls, held: SpooledBatch, spool_samples: int) -> SpooledReport:
        """The report of ``held``, per tag, as it enters the spool."""
        received: Counter[str] = Counter()
        for tag, length in zip(held.tags, held.lengths.tolist(), strict=True):
            received[tag] += length
        tags = tuple(
            TagReport(tag=tag, received=n, stored=0, already_stored=0, bad=0, out_of_order=0,
                      refused={}, first_timestamp=None, last_timestamp=None)
            for tag, n in received.items()
        )
        return cls(tags=tags, new_samples={}, spooled=held.samples,
                   spool_samples=spool_samples)

    def as_dict(self) -> dict[str, Any]:
        """The ingest response body with ``spooled`` and ``spool_samples`` added."""
        return {**super().as_dict(), "spooled": self.spooled,
                "spool_samples": self.spool_samples}


class IngestSpool:
    """Ingest batches held in memory, oldest first, at most ``max_samples`` samples.

    Thread-safe: the API's worker threads, the connectors and the demo feeder
    all ingest.  A batch is taken whole or not at all.
    """

    def __init__(self, *, max_samples: int) -> None:
        if max_samples < 0:
            raise ValueError(f"max_samples must be >= 0, got {max_samples}")
        self.max_samples = max_samples
        self._batches: deque[SpooledBatch] = deque()
        self._samples = 0
        self._lock = threading.Lock()

    @property
    def samples(self) -> int:
        """Samples held now."""
        return self._samples

    def __len__(self) -> int:
        """Batches held now."""
        return len(self._batches)

    def put(self, held: SpooledBatch) -> bool:
        """Hold ``held`` unless it would take the spool past its bound; True if held."""
        with self._lock:
            if self._samples + held.samples > self.max_samples:
                return False
            self._batches.append(held)
            self._samples += held.samples
            return True

    def oldest(self) -> SpooledBatch | None:
        """The batch that has waited longest (kept until :meth:`discard_oldest`)."""
        with self._lock:
            return self._batches[0] if self._batches else None

    def discard_oldest(self) -> SpooledBatch:
        """Remove the oldest batch once it has been written (or given up)."""
        with self._lock:
            held = self._batches.popleft()
            self._samples -= held.samples
            return held
