"""The store: migrations on SQLite and PostgreSQL."""

from sqlalchemy import inspect


def test_migrations_create_every_table(store):
    names = set(inspect(store.engine).get_table_names())
    assert {"loops", "samples", "alarms", "tickets", "api_keys", "alembic_version"} <= names
