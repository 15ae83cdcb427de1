"""scale-out: scheduled rounds, the leader lease, a time index on samples, TimescaleDB

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-22 00:10:00

* ``analysis_runs.round_end`` and ``scheduled_by``, with at most one run per
  loop and scheduled round: a scheduler that takes over after a failover can
  neither store a round twice nor miss one unnoticed (service.scheduler).
* ``ingest_log``: one row per ingest transaction (when, and the time span of
  the samples it stored), from which a scheduler in another process learns
  which samples to read, late ones and backfills included.
* ``leader_leases``: the lease row that elects the active scheduler where
  the database has no advisory locks (SQLite; service.leader).
* ``samples``: a time index (purging old samples and the scheduler's sync
  of the newest samples of every tag are range scans on time), and no
  foreign key to ``tags`` any more: its check on every inserted row halved
  the PostgreSQL insert rate (benchmarks/scale.py), and ingest already
  refuses samples of unknown tags.  SQLite cannot drop a constraint, so
  there the table is copied once.  The downgrade restores the key and fails
  if samples of removed tags are left.
* On PostgreSQL with the TimescaleDB extension installed and preloaded,
  ``samples`` becomes a hypertable in chunks of one day.  Its time column is
  UNIX seconds (float), which TimescaleDB cannot partition directly, so an
  immutable function maps it to integer microseconds for partitioning only;
  queries and the schema stay the same.  Without the extension nothing
  changes.  The downgrade keeps the hypertable (it behaves as a table).
"""

import logging

import sqlalchemy as sa
from alembic import op

revision = '0002'
down_revision = '0001'
branch_labels = None
depends_on = None

log = logging.getLogger("alembic.runtime.migration")

CHUNK_US = 86_400 * 1_000_000
"""One day of samples per TimescaleDB chunk, in the partitioning unit (microseconds)."""


SAMPLES_WITHOUT_TAG_KEY = sa.Table(
    'samples', sa.MetaData(),
    sa.Column('tag', sa.String(length=200), nullable=False),
    sa.Column('time', sa.Float(), nullable=False),
    sa.Column('value', sa.Float(), nullable=True),
    sa.Column('good', sa.Boolean(), nullable=False),
    sa.PrimaryKeyConstraint('tag', 'time'),
)
"""The samples table of 0001 without its foreign key (SQLite copies the table into it)."""


def timescaledb_ready(bind: sa.Connection) -> bool:
    """True on PostgreSQL when the TimescaleDB extension is installed and preloaded."""
    if bind.dialect.name != "postgresql":
        return False
    available = bind.execute(
        sa.text("SELECT 1 FROM pg_available_extensions WHERE name = 'timescaledb'")
    ).first()
    if available is None:
        return False
    preloaded = bind.execute(sa.text("SHOW shared_preload_libraries")).scalar() or ""
    if "timescaledb" not in preloaded:
        log.warning("TimescaleDB is installed but not in shared_preload_libraries: "
                    "samples stay a plain table")
        return False
    return True


def upgrade() -> None:
    with op.batch_alter_table('analysis_runs', schema=None) as batch_op:
        batch_op.add_column(sa.Column('round_end', sa.Float(), nullable=True))
        batch_op.add_column(sa.Column('scheduled_by', sa.String(length=200), nullable=True))
        batch_op.create_index('ix_analysis_runs_round_end', ['round_end'], unique=False)
        batch_op.create_unique_constraint(
            'uq_analysis_runs_loop_round', ['loop_id', 'round_end']
        )
    op.create_table(
        'ingest_log',
        sa.Column('id', sa.Integer(), autoincrement=True, nullable=False),
        sa.Column('received_at', sa.Float(), nullable=False),
        sa.Column('first_time', sa.Float(), nullable=False),
        sa.Column('last_time', sa.Float(), nullable=False),
        sa.Column('samples', sa.Integer(), nullable=False),
        sa.PrimaryKeyConstraint('id'),
    )
    op.create_index('ix_ingest_log_received_at', 'ingest_log', ['received_at'], unique=False)
    op.create_table(
        'leader_leases',
        sa.Column('name', sa.String(length=64), nullable=False),
        sa.Column('holder', sa.String(length=200), nullable=False),
        sa.Column('acquired_at', sa.Float(), nullable=False),
        sa.Column('expires_at', sa.Float(), nullable=False),
        sa.PrimaryKeyConstraint('name'),
    )
    bind = op.get_bind()
    if bind.dialect.name == "sqlite":
        with op.batch_alter_table('samples', copy_from=SAMPLES_WITHOUT_TAG_KEY,
                                  recreate='always') as batch_op:
            batch_op.create_index('ix_samples_time', ['time'], unique=False)
    else:
        for key in sa.inspect(bind).get_foreign_keys('samples'):
            if name := key['name']:
                op.drop_constraint(name, 'samples', type_='foreignkey')
        op.create_index('ix_samples_time', 'samples', ['time'], unique=False)
    if timescaledb_ready(bind):
        op.execute("CREATE EXTENSION IF NOT EXISTS timescaledb")
        op.execute(
            "CREATE OR REPLACE FUNCTION loopwatch_unix_us(t double precision) RETURNS bigint "
            "LANGUAGE sql IMMUTABLE PARALLEL SAFE AS $$ SELECT (t * 1000000)::bigint $$"
        )
        op.execute(
            "SELECT create_hypertable('samples', 'time', "
            f"chunk_time_interval => {CHUNK_US}, "
            "time_partitioning_func => 'loopwatch_unix_us', "
            "create_default_indexes => false, migrate_data => true)"
        )
        log.info("samples is a TimescaleDB hypertable (chunks of one day)")


def downgrade() -> None:
    with op.batch_alter_table('samples', schema=None) as batch_op:
        batch_op.drop_index('ix_samples_time')
        batch_op.create_foreign_key('samples_tag_fkey', 'tags', ['tag'], ['name'],
                                    ondelete='CASCADE')
    op.drop_table('leader_leases')
    op.drop_index('ix_ingest_log_received_at', table_name='ingest_log')
    op.drop_table('ingest_log')
    with op.batch_alter_table('analysis_runs', schema=None) as batch_op:
        batch_op.drop_constraint('uq_analysis_runs_loop_round', type_='unique')
        batch_op.drop_index('ix_analysis_runs_round_end')
        batch_op.drop_column('scheduled_by')
        batch_op.drop_column('round_end')
