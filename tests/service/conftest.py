"""Store fixtures: every store test runs on SQLite and on a real PostgreSQL."""

from collections.abc import Iterator
from itertools import count

import pytest
from sqlalchemy import create_engine, text

from service.store.db import Store

_databases = count()


@pytest.fixture(params=["sqlite", "postgresql"])
def store(request: pytest.FixtureRequest, tmp_path) -> Iterator[Store]:
    """A migrated, empty store on SQLite (a WAL file) or PostgreSQL (a fresh database)."""
    if request.param == "sqlite":
        s = Store(f"sqlite:///{tmp_path / 'loopwatch.db'}")
        yield s
        s.close()
        return
    server_url = request.getfixturevalue("postgres_url")
    name = f"loopwatch_test_{next(_databases)}"
    admin = create_engine(server_url, isolation_level="AUTOCOMMIT")
    with admin.connect() as connection:
        connection.execute(text(f"CREATE DATABASE {name}"))
    s = Store(server_url.rsplit("/", 1)[0] + f"/{name}")
    yield s
    s.close()
    with admin.connect() as connection:
        connection.execute(text(f"DROP DATABASE {name} WITH (FORCE)"))
    admin.dispose()
