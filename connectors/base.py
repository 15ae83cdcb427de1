"""What every connector shares: where samples go, outages, reconnect waits, the background thread.

A connector turns protocol data into ingest batches of the PI Web API shape
(``[{"tag", "items": [{"timestamp", "value", "good"}]}]``) and hands them to
a :class:`SampleSink` -- in the service that is ``AppState.ingest``, which
stores them (idempotently, counting every refusal) and feeds the rolling
buffers.  While a connection is down nothing is stored, so the window shows
a gap that the data-quality screen reports; the connector records the
:class:`Outage` in an :class:`OutageLog` and reconnects after the waits of a
:class:`Backoff`.  A connector's work is one coroutine, run until cancelled
in an event loop of the caller's or, beside the synchronous service, in a
thread of its own by a :class:`ThreadedRunner`.

The CSV vocabulary (:data:`TIME_NAMES`, :data:`MISSING` and the readers
below them) is shared by the historian replay (:mod:`connectors.replay`) and
the service's loop files (``service.loop_csv``), so both read a file the
same way and refuse it with the same messages.
"""

from __future__ import annotations

import asyncio
import contextlib
import csv
import io
import logging
import math
import random
import re
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Coroutine, Iterator, Mapping
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime, tzinfo
from pathlib import Path
from typing import Any, Generic, Protocol, Self, TypeVar

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "MISSING",
    "TIME_NAMES",
    "BackgroundConnector",
    "Backoff",
    "DeliveryCounters",
    "Outage",
    "OutageLog",
    "SampleSink",
    "ThreadedRunner",
    "column_index",
    "hand_over",
    "item",
    "number_columns",
    "parse_time",
    "raise_if_cancelled",
    "read_csv_rows",
]

log = logging.getLogger(__name__)


class SampleSink(Protocol):
    """Receives ingest batches; returns whatever the receiver reports (ignored here)."""

    def __call__(self, batch: list[dict[str, Any]], /) -> object:
        """Store ``batch``."""
        ...


def item(timestamp: float, value: float | None, good: bool = True) -> dict[str, Any]:
    """One ingest item; a bad or missing value is sent as ``value None, good False``."""
    if value is None or not good:
        return {"timestamp": timestamp, "value": None, "good": False}
    return {"timestamp": timestamp, "value": value, "good": True}


@dataclass
class DeliveryCounters:
    """Samples a connector made and what its sink did with them.

    ``pending`` (``samples - delivered - undelivered``) are the samples still
    on their way to the sink while the connector runs.  Once it has stopped,
    ``pending`` is 0, so ``samples == delivered + undelivered``, unless the
    connector holds samples to send again on its next run (an OPC UA
    connector keeps those of a flush the sink refused).

    A connector updates its counters under :attr:`lock` and hands out
    :meth:`snapshot` copies, so the numbers of one copy belong together,
    whichever thread reads them.

    Attributes
    ----------
    samples, bad : int
        Items made, and how many of them are bad.
    delivered, undelivered : int
        Items the sink took, and items of batches the sink raised on (logged,
        not sent again).
    lock : threading.Lock
        Held by every update and by :meth:`snapshot`.
    """

    samples: int = 0
    bad: int = 0
    delivered: int = 0
    undelivered: int = 0
    lock: threading.Lock = field(
        default_factory=threading.Lock, init=False, repr=False, compare=False
    )

    @property
    def pending(self) -> int:
        """Items neither delivered nor given up (see above)."""
        return self.samples - self.delivered - self.undelivered

    def snapshot(self) -> Self:
        """A copy of the counters now, taken under :attr:`lock`."""
        with self.lock:
            return replace(self)


def raise_if_cancelled() -> None:
    """Raise :class:`asyncio.CancelledError` if the current task has a cancellation pending.

    Python 3.11's ``asyncio.wait_for`` returns the result of an awaitable that completes
    together with a cancellation and drops the cancellation (fixed in 3.12), and the
    client libraries read through it: a connector's poll or reconnect loop checks this
    at each turn, so that a stop ends it.
    """
    task = asyncio.current_task()
    if task is not None and task.cancelling():
        raise asyncio.CancelledError


async def hand_over(
    sink: SampleSink, batch: list[dict[str, Any]], counters: DeliveryCounters, name: str
) -> None:
    """Hand ``batch`` to ``sink`` in a worker thread and count its items delivered or not.

    The sink writes to a database, so it runs off the event loop.  The
    counting is done in the worker thread: a caller cancelled while it waits
    (a stopped connector) still has the call counted, because a sink call
    cannot be stopped half-way and ``asyncio.run`` waits for worker threads.
    """
    count = sum(len(entry["items"]) for entry in batch)

    def call_sink() -> None:
        try:
            sink(batch)
        except Exception:
            with counters.lock:
                counters.undelivered += count
            log.exception("%s: the sink refused a batch of %d samples", name, count)
        else:
            with counters.lock:
                counters.delivered += count

    await asyncio.to_thread(call_sink)


@dataclass(frozen=True)
class Backoff:
    """Capped exponential backoff with jitter (asyncua's reconnect pattern).

    Delays are ``initial * factor**k`` capped at ``maximum``, each multiplied
    by a random factor in ``[1 - jitter, 1]`` so that many clients do not
    reconnect in step.

    Examples
    --------
    >>> [round(d, 2) for d in Backoff(initial=0.5, maximum=4.0, jitter=0.0).delays(6)]
    [0.5, 1.0, 2.0, 4.0, 4.0, 4.0]
    """

    initial: float = 0.5
    maximum: float = 30.0
    factor: float = 2.0
    jitter: float = 0.1

    def delays(self, count: int | None = None, seed: int | None = None) -> Iterator[float]:
        """The successive waits (endless when ``count`` is None)."""
        rng = random.Random(seed)
        delay = self.initial
        k = 0
        while count is None or k < count:
            yield min(delay, self.maximum) * (1.0 - self.jitter * rng.random())
            delay *= self.factor
            k += 1


@dataclass(frozen=True)
class Outage:
    """A time during which no data came from a source: the window has a gap.

    Attributes
    ----------
    start : float
        UNIX time the connection was lost (or the first connect failed).
    end : float or None
        UNIX time data came again; None while the outage lasts.
    reason : str
        What went wrong first.
    failed_attempts : int
        Reconnection attempts that failed.
    """

    start: float
    end: float | None
    reason: str
    failed_attempts: int = 0


class OutageLog:
    """The outages of one connection, oldest first; the last one may still be open.

    Parameters
    ----------
    name : str
        The connection, for the log messages.
    clock : callable
        Wall clock, UNIX seconds.

    Examples
    --------
    >>> outages = OutageLog("demo", clock=iter([10.0, 12.5]).__next__)
    >>> outages.lost("connection refused"), outages.lost("connection refused")
    (True, False)
    >>> outages.restored()
    >>> outages.outages
    (Outage(start=10.0, end=12.5, reason='connection refused', failed_attempts=1),)
    """

    def __init__(self, name: str, clock: Callable[[], float] = time.time) -> None:
        self.name = name
        self.clock = clock
        self._outages: list[Outage] = []

    @property
    def outages(self) -> tuple[Outage, ...]:
        """Every outage so far."""
        return tuple(self._outages)

    def lost(self, reason: str) -> bool:
        """Record that no data comes; True if this begins an outage, False if it goes on."""
        if self._outages and self._outages[-1].end is None:
            last = self._outages[-1]
            self._outages[-1] = replace(last, failed_attempts=last.failed_attempts + 1)
            log.info("%s: still no connection: %s", self.name, reason)
            return False
        self._outages.append(Outage(self.clock(), None, reason))
        log.warning("%s: no data from now on: %s", self.name, reason)
        return True

    def restored(self) -> None:
        """Record that data comes again: the open outage, if any, ends now."""
        if self._outages and self._outages[-1].end is None:
            end = self.clock()
            self._outages[-1] = replace(self._outages[-1], end=end)
            log.warning("%s: data again after %.1f s without",
                        self.name, end - self._outages[-1].start)


class ThreadedRunner:
    """Run a coroutine function in a thread of its own, with its own event loop.

    The service is synchronous apart from FastAPI; connectors and the plant
    simulator run beside it this way.  :meth:`stop` cancels the coroutine,
    waits for its clean-up (its ``finally`` blocks and the worker threads it
    started) and joins the thread; a later :meth:`start` runs it again.

    Attributes
    ----------
    error : Exception or None
        What stopped the last run, when it was an error (also logged).
    """

    def __init__(self, main: Callable[[], Coroutine[Any, Any, None]], *, name: str) -> None:
        self.main = main
        self.name = name
        self.error: Exception | None = None
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._task: asyncio.Task[None] | None = None
        self._ready = threading.Event()

    @property
    def running(self) -> bool:
        """Whether the thread is running (a finite coroutine may end on its own)."""
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> None:
        """Start the thread; returns once the coroutine is scheduled."""
        if self.running:
            raise RuntimeError(f"{self.name}: already running")
        self.error = None
        self._ready.clear()
        self._thread = threading.Thread(target=self._thread_main, name=self.name, daemon=True)
        self._thread.start()
        self._ready.wait()

    def _thread_main(self) -> None:
        async def supervised() -> None:
            self._loop = asyncio.get_running_loop()
            self._task = asyncio.current_task()
            self._ready.set()
            await self.main()

        try:
            asyncio.run(supervised())
        except asyncio.CancelledError:
            pass
        except Exception as exc:
            self.error = exc
            log.exception("%s: stopped by an error", self.name)
        finally:
            self._ready.set()

    def stop(self, timeout: float = 10.0) -> None:
        """Cancel the coroutine and join the thread (at most ``timeout`` seconds).

        Stops only what :meth:`start` started; a coroutine awaited in a loop
        of the caller's is stopped by cancelling its task.
        """
        if self._thread is None:
            return
        if self._loop is not None and self._task is not None and not self._loop.is_closed():
            with contextlib.suppress(RuntimeError):  # the loop closed meanwhile
                self._loop.call_soon_threadsafe(self._task.cancel)
        self._thread.join(timeout)
        if self._thread.is_alive():
            raise TimeoutError(f"{self.name}: did not stop within {timeout} s")


CountersT = TypeVar("CountersT", bound=DeliveryCounters)


class BackgroundConnector(ABC, Generic[CountersT]):
    """A connector whose work is one coroutine, :meth:`run`, stopped by cancelling it.

    ``await connector.run()`` runs it in an event loop of the caller's;
    :meth:`start` and :meth:`stop` run it beside the synchronous service in a
    thread of its own (a :class:`ThreadedRunner`).  :meth:`run` delivers what
    it holds before it ends, also when cancelled.  Every connector reports
    its :attr:`counters` (a :class:`DeliveryCounters` of its own kind) and
    its :attr:`outages`.
    """

    def __init__(
        self, name: str, counters: CountersT, clock: Callable[[], float] = time.time
    ) -> None:
        self.name = name
        self._runner = ThreadedRunner(self.run, name=name)
        self._counters = counters
        self._outages = OutageLog(name, clock)

    @property
    def counters(self) -> CountersT:
        """A consistent copy of the counters now."""
        return self._counters.snapshot()

    @property
    def outages(self) -> list[Outage]:
        """The times no data came from the source, oldest first (the last may be open)."""
        return list(self._outages.outages)

    @abstractmethod
    async def run(self) -> None:
        """Deliver samples until cancelled (or, for a finite source, until done)."""

    @property
    def running(self) -> bool:
        """Whether the thread of :meth:`start` is running."""
        return self._runner.running

    def start(self) -> None:
        """Run :meth:`run` in a background thread with its own event loop."""
        self._runner.start()

    def stop(self, timeout: float = 10.0) -> None:
        """Cancel :meth:`run`, let it deliver what it holds, and join the thread."""
        self._runner.stop(timeout)


# --- CSV files ------------------------------------------------------------------

TIME_NAMES = ("time", "t", "t_s", "timestamp")
"""Header names of a time column, matched case-insensitively, in order of preference."""

MISSING = frozenset({"", "nan", "NaN", "NAN", "null", "NULL", "NA"})
"""Cell texts that mean "no value": read as NaN and sent as bad samples."""


DECIMAL_COMMA = re.compile(r"[+-]?(\d+,\d*|,\d+)([eE][+-]?\d+)?")
"""A number written with a decimal comma (``12,5``, ``-0,25E3``)."""


def read_csv_rows(
    path: Path, error: type[ValueError]
) -> tuple[list[str], list[tuple[int, list[str]]]]:
    """The header and the data rows of a CSV file, each row with its row number.

    The header is row 1; blank rows are skipped; a byte-order mark is dropped.
    A file whose header has more semicolons than commas is read as
    semicolon-separated, and its numbers with a decimal comma (``12,5``) are
    given a decimal point, as spreadsheets in most of Europe write them.

    Raises
    ------
    error
        With the file name: missing, not text, not CSV, empty, no data rows,
        or (with the row) a row whose length differs from the header's.
    """
    try:
        text = path.read_text(encoding="utf-8-sig")
        first = text.split("\n", 1)[0]
        semicolons = first.count(";") > first.count(",")
        table = list(csv.reader(io.StringIO(text, newline=""),
                                delimiter=";" if semicolons else ","))
    except FileNotFoundError:
        raise error(f"{path}: no such file") from None
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not a text file ({exc.reason})") from None
    except csv.Error as exc:
        raise error(f"{path}: not valid CSV: {exc}") from None
    if not table:
        raise error(f"{path}: the file is empty")
    header = table[0]
    body = [(number, row) for number, row in enumerate(table[1:], start=2) if any(row)]
    if not body:
        raise error(f"{path}: no data rows below the header")
    for number, row in body:
        if len(row) != len(header):
            raise error(f"{path}, row {number}: {len(row)} cells, the header has {len(header)}")
    if semicolons:
        body = [(number, [cell.replace(",", ".") if DECIMAL_COMMA.fullmatch(cell.strip())
                          else cell for cell in row]) for number, row in body]
    return header, body


def column_index(header: list[str], name: str, path: Path, error: type[ValueError]) -> int:
    """Where column ``name`` is in ``header`` (case-insensitive); ``error`` if nowhere."""
    lowered = [h.strip().lower() for h in header]
    try:
        return lowered.index(name.strip().lower())
    except ValueError:
        raise error(f"{path}: no column {name!r}; the header has {', '.join(header)}") from None


def number_columns(
    path: Path,
    header: list[str],
    body: list[tuple[int, list[str]]],
    columns: Mapping[str, int],
    error: type[ValueError],
) -> dict[str, NDArray[np.float64]]:
    """The cells of ``columns`` (name -> column index) of every row, as numbers.

    :data:`MISSING` cells are NaN; any other cell that is not a number
    raises ``error`` with the file, row and column.
    """
    values = {name: np.empty(len(body)) for name in columns}
    for k, (number, row) in enumerate(body):
        for name, i in columns.items():
            cell = row[i].strip()
            if cell in MISSING:
                values[name][k] = math.nan
                continue
            try:
                values[name][k] = float(cell)
            except ValueError:
                raise error(
                    f"{path}, row {number}, column {header[i]!r}: {cell!r} is not a number"
                ) from None
    return values


def parse_time(text: str, zone: tzinfo = UTC) -> float:
    """UNIX seconds from UNIX seconds or an ISO 8601 time (one without an offset is in ``zone``).

    Raises
    ------
    ValueError
        Neither.

    Examples
    --------
    >>> parse_time("1700000000.5"), parse_time("2023-11-14T22:13:20Z")
    (1700000000.5, 1700000000.0)
    """
    try:
        return float(text)
    except ValueError:
        stamp = datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
        if stamp.tzinfo is None:
            stamp = stamp.replace(tzinfo=zone)
        return stamp.timestamp()
