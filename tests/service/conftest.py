"""Store and service fixtures: every store test runs on SQLite and on a real PostgreSQL.

``service`` and ``client`` are the two-loop test plant of :func:`tests.service.test_api.plant`
on ``store``; a test module that needs other settings overrides ``service`` with
``make_service(...)``."""

from collections.abc import Iterator
from concurrent.futures import Executor, ThreadPoolExecutor
from itertools import count
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import create_engine, text

from service.config import Settings
from service.server import Service, build_service
from service.store.db import Store
from tests.service.test_api import ADMIN, T0, plant

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


@pytest.fixture
def make_service(store):
    """Build services on ``store`` with the two-loop test plant; they are closed after the test.

    ``make_service(executor=None, **settings)``: a one-thread pool unless an
    executor is given; keyword arguments override the settings.
    """
    made: list[Service] = []

    def make(executor: Executor | None = None, **overrides: Any) -> Service:
        settings = Settings(**{"database_url": store.url, "api_key": ADMIN, "window_s": 3600,
                               "buffer_horizon_s": 7200, **overrides})
        svc = build_service(settings, plant(), executor=executor or ThreadPoolExecutor(1),
                            clock=lambda: T0)
        made.append(svc)
        return svc

    yield make
    for svc in made:
        release = getattr(svc.executor, "release", None)  # ends a deliberately hung job
        if release is not None:
            release.set()
        svc.executor.shutdown(wait=False, cancel_futures=True)
        svc.state.store.close()


@pytest.fixture
def service(make_service) -> Service:
    """The two-loop test plant on ``store`` (tickets after two confirmations)."""
    return make_service(ticket_confirmations=2)


@pytest.fixture
def client(service: Service) -> TestClient:
    """A client of ``service`` (send a key: ``tests.service.test_api.ADMIN`` or ``key(...)``)."""
    return TestClient(service.app)
