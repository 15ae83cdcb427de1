"""The store: SQLAlchemy 2 models, engine set-up and Alembic migrations.

SQLite (WAL mode) by default, PostgreSQL by URL; the schema is created and
upgraded only through the migrations in ``service/store/migrations``.
"""
