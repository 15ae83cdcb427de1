"""Leadership of the scheduler: one leader at a time, a standby takes over when it goes.

The lease row runs on SQLite and PostgreSQL (the ``store`` fixture) with a
clock the test moves; the advisory lock runs on a real PostgreSQL, whose
server releases the lock when the holder's session ends.
"""

import time
from collections.abc import Iterator
from itertools import count

import pytest
from sqlalchemy import create_engine, select, text

from service.leader import AdvisoryLockElection, LeaseElection, advisory_key, make_election
from service.store.db import Store
from service.store.models import LeaderLease
from tests.service.conftest import store  # noqa: F401  (the fixture: SQLite and PostgreSQL)

pytestmark = pytest.mark.serial  # timing-sensitive: run alone, after the parallel tests

LEASE_S = 9.0
_databases = count()


class Clock:
    """UNIX time that moves only when the test says so."""

    def __init__(self, now: float = 1_700_000_000.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def pg_store(postgres_url: str) -> Iterator[Store]:
    """A migrated store in a fresh database of the session's PostgreSQL server."""
    name = f"loopwatch_scaleout_{next(_databases)}"
    admin = create_engine(postgres_url, isolation_level="AUTOCOMMIT")
    with admin.connect() as connection:
        connection.execute(text(f"CREATE DATABASE {name}"))
    s = Store(postgres_url.rsplit("/", 1)[0] + f"/{name}")
    yield s
    s.close()
    with admin.connect() as connection:
        connection.execute(text(f"DROP DATABASE {name} WITH (FORCE)"))
    admin.dispose()


def lease_pair(database: Store, clock: Clock) -> tuple[LeaseElection, LeaseElection]:
    return tuple(LeaseElection(database, name="scheduler", holder=holder, lease_s=LEASE_S,
                               clock=clock) for holder in ("host-a:1", "host-b:2"))


def test_a_lease_has_one_holder_until_it_runs_out(store: Store) -> None:  # noqa: F811
    clock = Clock()
    a, b = lease_pair(store, clock)
    assert a.poll() and a.is_leader
    assert not b.poll() and not b.is_leader
    for _ in range(5):  # renewing every period keeps the lease, however long
        clock.now += a.period_s
        assert a.poll() and not b.poll()
    clock.now += LEASE_S - 0.01  # a stops renewing (it died): still its lease
    assert a.is_leader and not b.poll()
    clock.now += 0.02
    assert not a.is_leader  # it knows its lease ran out, whatever the database says
    assert b.poll() and b.is_leader
    assert not a.poll()  # back from the dead, it stands by
    with store.session() as session:
        row = session.scalars(select(LeaderLease)).one()
        assert (row.holder, row.expires_at) == ("host-b:2", clock.now + LEASE_S)
        assert row.acquired_at == clock.now


def test_a_clean_stop_hands_the_lease_over_at_once(store: Store) -> None:  # noqa: F811
    clock = Clock()
    a, b = lease_pair(store, clock)
    assert a.poll()
    a.stop()
    assert not a.is_leader
    assert b.poll()  # no wait for the lease to run out


def test_an_unreachable_database_means_no_leadership(tmp_path) -> None:
    database = Store(f"sqlite:///{tmp_path / 'x.db'}")
    clock = Clock()
    election = LeaseElection(database, name="scheduler", holder="h", lease_s=LEASE_S,
                             clock=clock)
    assert election.poll()
    with database.engine.begin() as connection:
        connection.execute(text("DROP TABLE leader_leases"))
    clock.now += election.period_s
    assert not election.poll()  # the failed renewal is logged, not raised
    database.close()


def test_the_advisory_lock_is_exclusive_and_freed_when_its_session_ends(
    pg_store: Store,
) -> None:
    a = AdvisoryLockElection(pg_store, name="scheduler", holder="a", lease_s=LEASE_S)
    b = AdvisoryLockElection(pg_store, name="scheduler", holder="b", lease_s=LEASE_S)
    other = AdvisoryLockElection(pg_store, name="other", holder="c", lease_s=LEASE_S)
    assert a.poll() and not b.poll()
    assert other.poll()  # another leadership, another key
    assert a.poll() and not b.poll()  # still held
    with pg_store.engine.connect() as admin:
        held = admin.execute(
            text("SELECT pid FROM pg_locks WHERE locktype = 'advisory' AND objid = :low"),
            {"low": a.key & 0xFFFFFFFF},
        ).scalars().all()
        assert len(held) == 1
        # the leader's session ends as it would when its process is killed; the backend
        # exits after pg_terminate_backend returns, so wait until it has gone
        admin.execute(text("SELECT pg_terminate_backend(:pid)"), {"pid": held[0]})
        admin.commit()
        for _ in range(200):
            if not admin.execute(text("SELECT 1 FROM pg_stat_activity WHERE pid = :pid"),
                                 {"pid": held[0]}).first():
                break
            admin.rollback()  # a fresh snapshot of pg_stat_activity
            time.sleep(0.05)
    assert b.poll()  # the server released the lock with the session
    assert not a.poll() and not a.is_leader  # a finds its session gone and stands by
    b.stop()
    assert a.poll()  # handed over on a clean stop
    a.stop()
    other.stop()


def test_advisory_keys_are_stable_signed_64_bit_integers() -> None:
    assert advisory_key("scheduler") != advisory_key("ingest")
    assert -(2**63) <= advisory_key("scheduler") < 2**63


def test_make_election_fits_the_dialect(store: Store) -> None:  # noqa: F811
    election = make_election(store, lease_s=LEASE_S)
    expected = AdvisoryLockElection if store.dialect == "postgresql" else LeaseElection
    assert type(election) is expected
    election.start()
    try:
        for _ in range(100):
            if election.is_leader:
                break
            time.sleep(0.05)
        assert election.is_leader
    finally:
        election.stop()
    assert not election.is_leader
