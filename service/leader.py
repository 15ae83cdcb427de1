"""Exactly one active scheduler: leadership held through the database every process shares.

Every process that may schedule (role ``scheduler`` or ``all``) runs an
election in a background thread; the one that holds the leadership analyses,
the others stand by and try again every ``period_s``.

* On PostgreSQL the leadership is a session-level advisory lock
  (``pg_try_advisory_lock``) held on a connection of its own.  When the
  holder dies its connection closes and the server releases the lock at
  once; TCP keep-alives set on that connection make the server notice a
  vanished host too (about ``lease_s``).  The holder checks its connection
  every period and steps down when it is lost.
* Elsewhere (SQLite) it is a lease row in ``leader_leases``: the holder
  renews ``expires_at = now + lease_s`` every period (a third of the lease);
  a standby takes the row over once it has expired.  A holder that could not
  renew in time considers itself deposed when its lease runs out, whether or
  not the database answers.

Leadership only decides who schedules.  That no analysis is stored twice is
guaranteed by the store itself (one run per loop and round, see
:mod:`service.scheduler`), so a deposed leader that has not noticed yet
cannot double a result.
"""

from __future__ import annotations

import hashlib
import logging
import os
import socket
import threading
import time
import uuid
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Any, cast

from sqlalchemy import Connection, CursorResult, case, func, select, update
from sqlalchemy.dialects import postgresql, sqlite

from service.store.db import Store
from service.store.models import LeaderLease

__all__ = [
    "SCHEDULER_LEADERSHIP",
    "AdvisoryLockElection",
    "Election",
    "LeaseElection",
    "advisory_key",
    "instance_name",
    "make_election",
]

log = logging.getLogger(__name__)

SCHEDULER_LEADERSHIP = "scheduler"
"""Name of the leadership of the analysis scheduler."""

LOCK_KEEPALIVES = (("tcp_keepalives_idle", 5), ("tcp_keepalives_interval", 2),
                   ("tcp_keepalives_count", 3))
"""Server-side TCP keep-alives of the lock's connection: a vanished host frees it in ~11 s."""


def instance_name() -> str:
    """``host:pid:nonce``: names this process in leases and analysis runs."""
    return f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:8]}"


def advisory_key(name: str) -> int:
    """A stable signed 64-bit advisory-lock key for ``name`` (the same in every process).

    >>> advisory_key("scheduler") == advisory_key("scheduler") != advisory_key("other")
    True
    """
    digest = hashlib.sha256(f"loopwatch:{name}".encode()).digest()
    return int.from_bytes(digest[:8], "big", signed=True)


class Election(ABC):
    """The background thread common to both elections; subclasses hold or release.

    Parameters
    ----------
    name : str
        The leadership contended for.
    holder : str
        This process (:func:`instance_name`).
    lease_s : float
        How long a silent leader keeps the leadership; the thread tries to
        take or keep it every ``lease_s / 3``.
    clock : callable
        UNIX time; processes on different hosts must agree on it within a
        small fraction of ``lease_s`` (NTP).
    """

    def __init__(self, *, name: str, holder: str, lease_s: float,
                 clock: Callable[[], float] = time.time) -> None:
        if not lease_s > 0:
            raise ValueError(f"lease_s must be positive, got {lease_s}")
        self.name = name
        self.holder = holder
        self.lease_s = lease_s
        self.period_s = lease_s / 3.0
        self.clock = clock
        self._valid_until = -float("inf")
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def is_leader(self) -> bool:
        """True while the leadership is held (and, for a lease, not run out)."""
        return self.clock() < self._valid_until

    @abstractmethod
    def _hold(self) -> float | None:
        """Take or keep the leadership; the time it is held until, or None if not held."""

    @abstractmethod
    def _let_go(self) -> None:
        """Give up the leadership (on a clean stop)."""

    def poll(self) -> bool:
        """One attempt to take or keep the leadership; True if held afterwards."""
        was = self.is_leader
        try:
            until = self._hold()
        except Exception as exc:  # the database is unreachable: not leader, retry later
            log.warning("leadership %r: %s: %s", self.name, type(exc).__name__, exc)
            until = None
        self._valid_until = -float("inf") if until is None else until
        now_leader = self.is_leader
        if now_leader != was:
            log.info("%s %s the %r leadership", self.holder, "took" if now_leader else "lost",
                     self.name)
        return now_leader

    def start(self) -> None:
        """Poll once now, then every ``period_s`` in a daemon thread until :meth:`stop`."""
        def run() -> None:
            while not self._stop.wait(self.period_s):
                self.poll()

        self._stop.clear()
        self.poll()
        self._thread = threading.Thread(target=run, name=f"loopwatch-election-{self.name}",
                                        daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop polling and hand the leadership back, so a standby takes over at once."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=self.period_s + 5)
        self._valid_until = -float("inf")
        try:
            self._let_go()
        except Exception as exc:  # the standby takes over when the lease runs out instead
            log.warning("leadership %r not released: %s", self.name, exc)


class LeaseElection(Election):
    """Leadership as a row of ``leader_leases`` renewed by its holder (any database)."""

    def __init__(self, store: Store, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.store = store

    def _hold(self) -> float | None:
        now = self.clock()
        until = now + self.lease_s
        table = LeaderLease.__table__
        with self.store.session() as session:
            dialect = {"postgresql": postgresql, "sqlite": sqlite}[self.store.dialect]
            session.execute(
                dialect.insert(table)
                .values(name=self.name, holder=self.holder, acquired_at=now, expires_at=until)
                .on_conflict_do_nothing()
            )
            renewed = session.execute(
                update(LeaderLease)
                .where(LeaderLease.name == self.name,
                       (LeaderLease.holder == self.holder) | (LeaderLease.expires_at < now))
                .values(
                    holder=self.holder,
                    expires_at=until,
                    acquired_at=case(
                        (LeaderLease.holder == self.holder, LeaderLease.acquired_at), else_=now
                    ),
                )
            )
            held = cast(CursorResult[Any], renewed).rowcount == 1
        return until if held else None

    def _let_go(self) -> None:
        with self.store.session() as session:
            session.execute(
                update(LeaderLease)
                .where(LeaderLease.name == self.name, LeaderLease.holder == self.holder)
                .values(expires_at=0.0)
            )


class AdvisoryLockElection(Election):
    """Leadership as a PostgreSQL session advisory lock on a connection of its own."""

    def __init__(self, store: Store, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        if store.dialect != "postgresql":
            raise ValueError(f"advisory locks need PostgreSQL, not {store.dialect}")
        self.store = store
        self.key = advisory_key(self.name)
        self._connection: Connection | None = None

    def _hold(self) -> float | None:
        until = self.clock() + self.lease_s
        if self._connection is not None:
            try:  # still our session, so still our lock
                self._connection.execute(select(1))
                return until
            except Exception:
                self._drop_connection()
                raise
        connection = self.store.engine.connect().execution_options(isolation_level="AUTOCOMMIT")
        try:
            for setting, value in LOCK_KEEPALIVES:
                connection.exec_driver_sql(f"SET {setting} = {value}")
            got = connection.execute(select(func.pg_try_advisory_lock(self.key))).scalar()
        except Exception:
            connection.close()
            raise
        if not got:
            connection.close()
            return None
        self._connection = connection
        return until

    def _drop_connection(self) -> None:
        if self._connection is not None:
            try:
                self._connection.invalidate()  # never back to the pool: the lock would travel
                self._connection.close()
            finally:
                self._connection = None

    def _let_go(self) -> None:
        if self._connection is None:
            return
        try:
            self._connection.execute(select(func.pg_advisory_unlock(self.key)))
        finally:
            self._drop_connection()


def make_election(store: Store, *, lease_s: float, name: str = SCHEDULER_LEADERSHIP,
                  holder: str | None = None) -> Election:
    """The election that fits the store: an advisory lock on PostgreSQL, a lease elsewhere."""
    holder = holder or instance_name()
    if store.dialect == "postgresql":
        return AdvisoryLockElection(store, name=name, holder=holder, lease_s=lease_s)
    return LeaseElection(store, name=name, holder=holder, lease_s=lease_s)
