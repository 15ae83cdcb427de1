"""Engine, sessions and migrations of the store."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from alembic import command
from alembic.config import Config
from sqlalchemy import Engine, create_engine, event, text
from sqlalchemy.engine import make_url
from sqlalchemy.orm import ORMExecuteState, Session, sessionmaker

MIGRATIONS = Path(__file__).resolve().parent / "migrations"

__all__ = ["MIGRATIONS", "MIGRATION_LOCK", "Store", "make_engine", "migrate"]


def _sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
    cursor = dbapi_connection.cursor()
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.execute("PRAGMA foreign_keys=ON")
    cursor.execute("PRAGMA synchronous=NORMAL")
    cursor.execute("PRAGMA busy_timeout=5000")
    cursor.close()


def make_engine(url: str) -> Engine:
    """An engine for ``url``; SQLite gets WAL mode and foreign keys, and its directory."""
    parsed = make_url(url)
    if parsed.get_backend_name() == "sqlite":
        if parsed.database and parsed.database != ":memory:":
            Path(parsed.database).parent.mkdir(parents=True, exist_ok=True)
        # as many connections as FastAPI's thread pool has threads (40): a request never
        # waits for a connection, only for SQLite's write lock
        engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": 30},
                               pool_size=10, max_overflow=30)
        event.listen(engine, "connect", _sqlite_pragmas)
        return engine
    if parsed.get_backend_name() == "postgresql" and parsed.drivername == "postgresql":
        url = parsed.set(drivername="postgresql+psycopg").render_as_string(hide_password=False)
    return create_engine(url, pool_pre_ping=True, pool_size=10, max_overflow=20)


MIGRATION_LOCK = 0x6C6F6F7077617463  # "loopwatc": the advisory lock that serialises migrations


def migrate(engine: Engine, revision: str = "head") -> None:
    """Upgrade the schema to ``revision`` with the Alembic migrations.

    On PostgreSQL the upgrade holds a transaction-level advisory lock, so
    replicas started together migrate one after the other: the first
    upgrades, the others then find the schema current.
    """
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS))
    with engine.begin() as connection:
        if connection.dialect.name == "postgresql":
            connection.execute(text("SELECT pg_advisory_xact_lock(:key)"),
                               {"key": MIGRATION_LOCK})
        config.attributes["connection"] = connection
        command.upgrade(config, revision)


def _written_tables(session: Session) -> set[str]:
    written: set[str] = session.info.setdefault("written_tables", set())
    return written


def _note_flush(session: Session, _context: Any) -> None:
    written = _written_tables(session)
    for obj in session.new:
        if hasattr(obj, "__table__") and not getattr(obj, "unread_when_new", False):
            written.add(obj.__table__.name)
    for obj in session.dirty:
        if hasattr(obj, "__table__") and session.is_modified(obj):
            written.add(obj.__table__.name)
    for obj in session.deleted:
        if hasattr(obj, "__table__"):
            written.add(obj.__table__.name)


def _note_statement(state: ORMExecuteState) -> None:
    table = getattr(state.statement, "table", None)
    if (state.is_insert or state.is_update or state.is_delete) and table is not None:
        _written_tables(state.session).add(table.name)


class Store:
    """The engine and a session factory; ``with store.session() as s`` commits or rolls back.

    The store counts the committed transactions of its sessions that wrote each table
    (:meth:`version`): a copy of what was read from those tables is current while the
    count has not moved.  Only this process's writes through its sessions are counted,
    and not the new rows that say ``unread_when_new`` (an analysis run that is not
    ``ok``: no shared view reads it), nor objects that were touched but not changed.
    """

    def __init__(self, url: str, *, run_migrations: bool = True) -> None:
        self.url = url
        self.engine = make_engine(url)
        if run_migrations:
            migrate(self.engine)
        self._sessions = sessionmaker(self.engine, expire_on_commit=False)
        self._writes: dict[str, int] = {}
        self._writes_lock = threading.Lock()
        event.listen(self._sessions, "after_flush", _note_flush)
        event.listen(self._sessions, "do_orm_execute", _note_statement)
        event.listen(self._sessions, "after_commit", self._count_commit)

    def _count_commit(self, session: Session) -> None:
        written = session.info.pop("written_tables", None)
        if written:
            with self._writes_lock:
                for table in written:
                    self._writes[table] = self._writes.get(table, 0) + 1

    def version(self, *tables: str) -> int:
        """How many committed transactions of this process wrote any of ``tables``
        (counted after the commit: a read that starts after the count moved sees the
        write)."""
        with self._writes_lock:
            return sum(self._writes.get(table, 0) for table in tables)

    @contextmanager
    def session(self) -> Iterator[Session]:
        """A transaction: committed on success, rolled back on error."""
        with self._sessions() as session, session.begin():
            yield session

    @property
    def dialect(self) -> str:
        """``"sqlite"`` or ``"postgresql"``."""
        return self.engine.dialect.name

    def close(self) -> None:
        """Release the connections."""
        self.engine.dispose()
