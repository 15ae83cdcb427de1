"""Answers read from the store, shared by the requests that ask for them until it changes.

Twenty dashboards polling the loop list and the bad-actor ranking of a plant
of 2,000 loops each second asked the store for the same 2,000 rows twenty
times a second, and ranked them twenty times: more work than one core does,
so every request queued behind the others (issue 20's load benchmark).  A
:class:`ReadCache` computes an answer once and gives it to every request
that asks while

* no transaction of this process that wrote one of the answer's tables has
  committed since it was computed (:meth:`service.store.db.Store.version`:
  an alarm raised, a loop changed or an analysis stored shows at once), and
* it is at most ``max_age_s`` old, the bound on how late a write of another
  process (an API replica, a scheduler elsewhere) shows.

Requests that find the answer missing or stale while another request computes
it wait for that computation instead of repeating it, and take its answer when
it began after they arrived (it saw every write they could have seen), even if
the store was written again meanwhile: while the scheduler stores a round of
2,000 runs, one ranking at a time is computed, not one per request.  An answer
computed from other kept answers (a page of the loop list from the list) is
dated from the oldest of them, so it too is at most ``max_age_s`` old.
:meth:`ReadCache.peek` takes a current answer without waiting for a
computation, for the event loop; :meth:`ReadCache.refresh_ahead` and
:meth:`ReadCache.refresh` compute an answer again in the background once it is
half ``max_age_s`` old, so that no request waits for one that only grew old.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Any, TypeVar

from service.store.db import Store

__all__ = ["ReadCache"]

T = TypeVar("T")

log = logging.getLogger(__name__)


@dataclass
class _Entry:
    value: Any
    version: int
    at: float
    computation: int  # the number of the computation that made it (they count up)


class ReadCache:
    """Answers computed from ``tables`` of ``store``, kept while current (module docstring).

    Parameters
    ----------
    store : Store
        Counts the commits that wrote each table.
    tables : sequence of str
        The tables every answer is read from.
    max_age_s : float
        Longest an answer is given again (0: never; every request computes).
    max_entries : int
        Answers kept (the least recently computed go first).
    clock : callable
        Monotonic seconds (injectable for tests).
    """

    def __init__(self, store: Store, tables: tuple[str, ...], *, max_age_s: float,
                 max_entries: int = 64, clock: Callable[[], float] = time.monotonic) -> None:
        self.store, self.tables, self.max_age_s, self.clock = store, tables, max_age_s, clock
        self.max_entries = max_entries
        self._entries: dict[Hashable, _Entry] = {}
        self._locks: dict[Hashable, threading.Lock] = {}
        self._lock = threading.Lock()
        self._computations = 0
        self._thread = threading.local()
        self._refreshing: set[Hashable] = set()

    def _current(self, key: Hashable, version: int,
                 valid: Callable[[Any], bool] | None) -> _Entry | None:
        entry = self._entries.get(key)
        max_age_s = self.max_age_s / 2 if getattr(self._thread, "ahead", False) else self.max_age_s
        if (entry is None or entry.version != version
                or self.clock() - entry.at > max_age_s
                or (valid is not None and not valid(entry.value))):
            return None
        return entry

    def _computing(self) -> list[float]:
        """The answers this thread is computing, innermost last: when each began, or
        when the oldest kept answer it used was computed, if earlier."""
        stack: list[float] | None = getattr(self._thread, "stack", None)
        if stack is None:
            stack = self._thread.stack = []
        return stack

    def _used(self, at: float) -> None:
        """An answer of ``at`` went into the answer this thread computes, if any: that
        one is as old (an answer made of kept answers is no younger than they are)."""
        outer = self._computing()
        if outer:
            outer[-1] = min(outer[-1], at)

    def peek(self, key: Hashable, valid: Callable[[Any], bool] | None = None) -> Any | None:
        """The answer kept under ``key`` if :meth:`get` would give it now, else None; never
        waits for a computation nor computes (safe on the event loop)."""
        if self.max_age_s <= 0:
            return None
        entry = self._current(key, self.store.version(*self.tables), valid)
        return None if entry is None else entry.value

    def refresh_ahead(self, key: Hashable) -> bool:
        """Whether the caller should :meth:`refresh` the answer kept under ``key`` now: it
        is older than half ``max_age_s`` and nobody refreshes it yet (True claims it)."""
        with self._lock:
            entry = self._entries.get(key)
            if (entry is None or key in self._refreshing
                    or self.clock() - entry.at <= self.max_age_s / 2):
                return False
            self._refreshing.add(key)
            return True

    def refresh(self, key: Hashable, compute: Callable[[], Any],
                valid: Callable[[Any], bool] | None = None) -> None:
        """Compute the answer under ``key`` (claimed by :meth:`refresh_ahead`) again, and
        the kept answers it is made of that are older than half ``max_age_s``, before it
        expires: in a background thread, while the requests still take the kept answer.
        Answers that only grow old are then never waited for (a ranking of 2,000 loops
        expiring every ``max_age_s`` held up every request that came while it was computed
        again: the load benchmark's p99).  A failure is logged; the next request that
        finds the answer expired computes it and gets the error."""
        self._thread.ahead = True
        try:
            self.get(key, compute, valid)
        except Exception as exc:
            log.warning("refreshing the shared answer %r failed: %s: %s", key,
                        type(exc).__name__, exc)
        finally:
            self._thread.ahead = False
            with self._lock:
                self._refreshing.discard(key)

    def get(self, key: Hashable, compute: Callable[[], T],
            valid: Callable[[T], bool] | None = None) -> T:
        """The answer kept under ``key`` if current (and ``valid(answer)``, when given),
        else ``compute()``, kept.  ``compute`` must read the store after it is called."""
        if self.max_age_s <= 0:
            return compute()
        with self._lock:
            lock = self._locks.setdefault(key, threading.Lock())
            arrived = self._computations
        with lock:
            entry = self._entries.get(key)
            if entry is None or entry.computation <= arrived:  # else: computed after it arrived
                entry = self._current(key, self.store.version(*self.tables), valid)
            if entry is not None:
                self._used(entry.at)
                value: T = entry.value
                return value
            version = self.store.version(*self.tables)
            with self._lock:
                self._computations += 1
                computation = self._computations
            outer = self._computing()
            outer.append(self.clock())
            try:
                value = compute()
            finally:
                at = outer.pop()
            self._used(at)
            with self._lock:
                self._entries.pop(key, None)
                self._entries[key] = _Entry(value, version, at, computation)
                while len(self._entries) > self.max_entries:
                    oldest = next(iter(self._entries))
                    del self._entries[oldest]
                    if oldest != key:
                        self._locks.pop(oldest, None)
            return value

    def clear(self) -> None:
        """Forget every answer."""
        with self._lock:
            self._entries.clear()
            self._locks.clear()
            self._refreshing.clear()
