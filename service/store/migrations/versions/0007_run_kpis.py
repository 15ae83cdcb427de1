"""analysis runs: the KPIs in a column of their own, and an index of the ok runs by loop and time

Revision ID: 0007
Revises: 0006
Create Date: 2026-11-26 08:40:00

* ``analysis_runs.kpis``: ``result["kpis"]`` on its own (filled from the stored
  results here, then written with every result), so the KPI history and the
  bad-actor ranking read about 0.5 kB a run instead of extracting it from the
  whole ~9 kB diagnosis: on PostgreSQL that ``json`` is stored compressed out
  of line (TOAST) and is decompressed and parsed for every run returned.
  The back-fill rewrites every run once.
* ``ix_analysis_runs_ok_loop_started``: ``(loop_id, started_at, id)`` of the
  ``ok`` runs (a partial index), which the history route counts and thins
  by an index-only scan in time order instead of visiting and sorting the
  loop's runs.
"""

import sqlalchemy as sa
from alembic import op

revision = '0007'
down_revision = '0006'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column('analysis_runs', sa.Column('kpis', sa.JSON(), nullable=True))
    if op.get_bind().dialect.name == 'postgresql':
        op.execute("UPDATE analysis_runs SET kpis = result -> 'kpis' WHERE result IS NOT NULL")
    else:
        op.execute("UPDATE analysis_runs SET kpis = json_extract(result, '$.kpis') "
                   "WHERE result IS NOT NULL")
    op.create_index('ix_analysis_runs_ok_loop_started', 'analysis_runs',
                    ['loop_id', 'started_at', 'id'], unique=False,
                    postgresql_where=sa.text("status = 'ok'"),
                    sqlite_where=sa.text("status = 'ok'"))


def downgrade() -> None:
    op.drop_index('ix_analysis_runs_ok_loop_started', table_name='analysis_runs')
    with op.batch_alter_table('analysis_runs', schema=None) as batch_op:
        batch_op.drop_column('kpis')
