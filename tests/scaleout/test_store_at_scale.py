"""The store at scale: migrations 0002 and 0007, replicas migrating together, the PostgreSQL
ingest path.

Every test runs on SQLite and on a real PostgreSQL unless it is about
PostgreSQL only.
"""

import importlib.util
import json
import threading
from collections.abc import Iterator
from itertools import count
from typing import Any

import pytest
from alembic import command
from alembic.config import Config
from alembic.script import ScriptDirectory
from sqlalchemy import create_engine, event, inspect, select, text
from sqlalchemy.exc import IntegrityError

from service.ingest import ingest_batch
from service.plant import sync_plant
from service.store.db import MIGRATIONS, Store, make_engine, migrate
from service.store.models import AnalysisRun, IngestLog, Loop
from tests.service.test_ingest import KNOWN, NOW, PLANT, items, stored

_databases = count()
VERSIONS = MIGRATIONS / "versions"


def load_migration(name: str) -> Any:
    spec = importlib.util.spec_from_file_location(name, VERSIONS / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(params=["sqlite", "postgresql"])
def empty_url(request: pytest.FixtureRequest, tmp_path) -> Iterator[str]:
    """The URL of an empty database: a SQLite file, or a new PostgreSQL database."""
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'loopwatch.db'}"
        return
    server_url = request.getfixturevalue("postgres_url")
    name = f"loopwatch_scale_{next(_databases)}"
    admin = create_engine(server_url, isolation_level="AUTOCOMMIT")
    with admin.connect() as connection:
        connection.execute(text(f"CREATE DATABASE {name}"))
    yield server_url.rsplit("/", 1)[0] + f"/{name}"
    with admin.connect() as connection:
        connection.execute(text(f"DROP DATABASE {name} WITH (FORCE)"))
    admin.dispose()


def downgrade(url: str, revision: str) -> None:
    engine = make_engine(url)
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS))
    with engine.begin() as connection:
        config.attributes["connection"] = connection
        command.downgrade(config, revision)
    engine.dispose()


def test_0002_keeps_the_data_of_0001_and_adds_the_scale_out_schema(empty_url: str) -> None:
    engine = make_engine(empty_url)
    migrate(engine, "0001")
    with engine.begin() as connection:
        connection.execute(text(
            "INSERT INTO loops (id, name, config, created_at, updated_at) "
            "VALUES ('FIC-101', '', '{}', 0, 0)"))
        connection.execute(text(
            "INSERT INTO tags (name, loop_id, signal) VALUES ('FIC101.PV', 'FIC-101', 'pv')"))
        connection.execute(text(
            "INSERT INTO samples (tag, time, value, good) VALUES ('FIC101.PV', 1.5, 2.5, true)"))
        connection.execute(text(
            "INSERT INTO analysis_runs (loop_id, started_at, status) VALUES ('FIC-101', 1, 'ok')"))
    migrate(engine, "0003")  # 0004 salts the key hashes and cannot be undone (its own test)
    schema = inspect(engine)
    assert {"leader_leases", "ingest_log"} <= set(schema.get_table_names())
    assert schema.get_foreign_keys("samples") == []
    assert "ix_samples_time" in {i["name"] for i in schema.get_indexes("samples")}
    with engine.connect() as connection:
        assert connection.execute(text("SELECT tag, time, value FROM samples")).all() == [
            ("FIC101.PV", 1.5, 2.5)]
        assert connection.execute(
            text("SELECT loop_id, round_end, scheduled_by FROM analysis_runs")).all() == [
            ("FIC-101", None, None)]
    engine.dispose()
    downgrade(empty_url, "0001")
    engine = make_engine(empty_url)
    schema = inspect(engine)
    assert "leader_leases" not in schema.get_table_names()
    assert [k["referred_table"] for k in schema.get_foreign_keys("samples")] == ["tags"]
    engine.dispose()


def test_0007_moves_the_kpis_of_the_stored_runs_into_their_column(empty_url: str) -> None:
    """Runs stored before 0007 get their ``result["kpis"]`` in the ``kpis`` column, and
    the ok runs an index by loop and time; a run stored after it keeps the two equal."""
    engine = make_engine(empty_url)
    migrate(engine, "0006")
    kpis = {"oscillation_index": 0.4, "harris": {"normalised": 0.75}}
    with engine.begin() as connection:
        connection.execute(text(
            "INSERT INTO loops (id, name, config, created_at, updated_at) "
            "VALUES ('FIC-101', '', '{}', 0, 0)"))
        connection.execute(text(
            "INSERT INTO analysis_runs (loop_id, started_at, status, result) VALUES "
            "('FIC-101', 1, 'ok', :with_kpis), ('FIC-101', 2, 'ok', '{\"quality\": {}}'), "
            "('FIC-101', 3, 'failed', NULL)"),
            {"with_kpis": json.dumps({"quality": {}, "kpis": kpis})})
    migrate(engine)
    schema = inspect(engine)
    index = {i["name"]: i for i in schema.get_indexes("analysis_runs")}[
        "ix_analysis_runs_ok_loop_started"]
    assert index["column_names"] == ["loop_id", "started_at", "id"]
    store = Store(empty_url)
    with store.session() as session:
        runs = session.scalars(select(AnalysisRun).order_by(AnalysisRun.started_at)).all()
        assert [r.kpis for r in runs] == [kpis, None, None]
        runs[1].result = {"quality": {}, "kpis": {"saturation": 0.1}}
        session.add(AnalysisRun(loop_id="FIC-101", started_at=4, status="ok",
                                result={"kpis": {"saturation": 0.2}}))
    with store.session() as session:
        assert [r.kpis for r in session.scalars(
            select(AnalysisRun).order_by(AnalysisRun.started_at))] == [
            kpis, {"saturation": 0.1}, None, {"saturation": 0.2}]
    store.close()
    engine.dispose()
    downgrade(empty_url, "0006")
    engine = make_engine(empty_url)
    assert "kpis" not in {c["name"] for c in inspect(engine).get_columns("analysis_runs")}
    engine.dispose()


def test_one_run_per_loop_and_round_but_any_number_on_demand(empty_url: str) -> None:
    store = Store(empty_url)
    with store.session() as session:
        session.add(Loop(id="L1", name="", config={}, created_at=0, updated_at=0))
    with store.session() as session:
        session.add_all([AnalysisRun(loop_id="L1", started_at=1, status="ok"),
                         AnalysisRun(loop_id="L1", started_at=1, status="ok"),
                         AnalysisRun(loop_id="L1", started_at=1, status="ok", round_end=60.0)])
    with pytest.raises(IntegrityError), store.session() as session:
        session.add(AnalysisRun(loop_id="L1", started_at=2, status="ok", round_end=60.0))
    with store.session() as session:
        assert len(session.scalars(select(AnalysisRun)).all()) == 3
    store.close()


def test_replicas_starting_together_migrate_one_after_the_other(postgres_url: str) -> None:
    name = f"loopwatch_scale_{next(_databases)}"
    admin = create_engine(postgres_url, isolation_level="AUTOCOMMIT")
    with admin.connect() as connection:
        connection.execute(text(f"CREATE DATABASE {name}"))
    url = postgres_url.rsplit("/", 1)[0] + f"/{name}"
    start = threading.Barrier(4)
    errors: list[BaseException] = []

    def replica() -> None:
        engine = make_engine(url)
        try:
            start.wait()
            migrate(engine)
        except BaseException as exc:
            errors.append(exc)
        finally:
            engine.dispose()

    threads = [threading.Thread(target=replica) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert errors == []
    engine = make_engine(url)
    head = ScriptDirectory(str(MIGRATIONS)).get_current_head()
    with engine.connect() as connection:
        assert connection.execute(text("SELECT version_num FROM alembic_version")).all() == [
            (head,)]
    engine.dispose()
    with admin.connect() as connection:
        connection.execute(text(f"DROP DATABASE {name} WITH (FORCE)"))
    admin.dispose()


def test_samples_become_a_hypertable_only_with_timescaledb(postgres_url: str) -> None:
    migration = load_migration("0002_scale_out")
    engine = create_engine(postgres_url)
    with engine.connect() as connection:
        ready = migration.timescaledb_ready(connection)
        available = connection.execute(text(
            "SELECT 1 FROM pg_available_extensions WHERE name = 'timescaledb'")).first()
        assert ready == (available is not None and "timescaledb" in str(
            connection.execute(text("SHOW shared_preload_libraries")).scalar()))
    engine.dispose()
    store = Store(postgres_url.rsplit("/", 1)[0] + "/postgres")
    with store.engine.connect() as connection:
        if ready:
            assert connection.execute(text(
                "SELECT hypertable_name FROM timescaledb_information.hypertables"
            )).scalars().all() == ["samples"]
        else:  # Debian has no TimescaleDB package: samples stays an ordinary table
            assert connection.execute(text(
                "SELECT relkind FROM pg_class WHERE relname = 'samples'")).scalar() == "r"
    store.close()


# ------------------------------------------------------------- the ingest paths


def plant_store_at(url: str) -> Store:
    store = Store(url)
    with store.session() as session:
        sync_plant(session, PLANT, NOW)
    return store


def test_postgresql_and_sqlite_account_for_every_item_alike(
    postgres_url: str, tmp_path
) -> None:
    """The COPY path of PostgreSQL and the multi-row INSERTs of SQLite give the same reports."""
    batches = [
        [{"tag": "FIC101.PV", "items": items((NOW - 2, 1.0), (NOW - 1, None), (NOW, 3.0))}],
        [{"tag": "FIC101.PV", "items": items((NOW - 2, 1.0), (NOW - 1, 9.0), (NOW - 3, 0.5),
                                             (NOW - 3, 0.7), ("soon", 1.0))},
         {"tag": "FIC101.OP", "items": items((NOW + 3600, 1.0), (NOW, float("nan")))},
         {"tag": "NOPE", "items": items((NOW, 1.0))}],
        [{"tag": "FIC101.OP", "items": items(*((NOW - k, float(k)) for k in range(2500)))}],
    ]
    reports: dict[str, list[dict[str, Any]]] = {}
    contents = {}
    name = f"loopwatch_scale_{next(_databases)}"
    admin = create_engine(postgres_url, isolation_level="AUTOCOMMIT")
    with admin.connect() as connection:
        connection.execute(text(f"CREATE DATABASE {name}"))
    for dialect, url in (("sqlite", f"sqlite:///{tmp_path / 'x.db'}"),
                         ("postgresql", postgres_url.rsplit("/", 1)[0] + f"/{name}")):
        store = plant_store_at(url)
        statements: list[str] = []

        def record(conn: Any, cursor: Any, statement: str, *_: Any,
                   into: list[str] = statements) -> None:
            into.append(statement)

        event.listen(store.engine, "before_cursor_execute", record)
        with store.session() as session:
            reports[dialect] = [
                ingest_batch(session, b, known_tags=KNOWN, now=NOW).as_dict() for b in batches
            ]  # three batches in one transaction: the stage table is reused
        if dialect == "postgresql":  # one INSERT ... SELECT per batch, its rows by COPY
            inserts = [s for s in statements if s.startswith("INSERT INTO samples")]
            assert len(inserts) == 3 and all("SELECT" in s for s in inserts), inserts
        contents[dialect] = stored(store)
        with store.session() as session:
            assert [(log.first_time, log.last_time, log.samples) for log in session.scalars(
                select(IngestLog).order_by(IngestLog.id))] == [
                (NOW - 2, NOW, 3), (NOW - 3, NOW, 2), (NOW - 2499, NOW - 1, 2499)]
        store.close()
    assert reports["postgresql"] == reports["sqlite"]
    assert contents["postgresql"] == contents["sqlite"]
    second = reports["sqlite"][1]
    assert (second["stored"], second["already_stored"], second["refused"]) == (
        2, 1, {"unknown_tag": 1, "bad_timestamp": 1, "future_timestamp": 1,
               "duplicate_in_batch": 1, "conflict": 1})
    with admin.connect() as connection:
        connection.execute(text(f"DROP DATABASE {name} WITH (FORCE)"))
    admin.dispose()
