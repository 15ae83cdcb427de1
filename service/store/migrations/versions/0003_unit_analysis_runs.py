"""unit analyses: the scheduler's multi-loop diagnosis of every unit, per round

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-22 03:00:00

* ``unit_analysis_runs``: one row per unit and scheduled round (thesis
  chapter 2, :func:`analytics.plantwide.diagnose_unit`), with the loops it
  names sticky and those it clears; the ticket rule reads the latest one,
  and ``/api/v1/units/{id}/diagnosis`` returns it.  At most one per unit
  and round, as for ``analysis_runs``.
"""

import sqlalchemy as sa
from alembic import op

revision = '0003'
down_revision = '0002'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        'unit_analysis_runs',
        sa.Column('id', sa.Integer(), autoincrement=True, nullable=False),
        sa.Column('unit_id', sa.String(length=64), nullable=False),
        sa.Column('started_at', sa.Float(), nullable=False),
        sa.Column('finished_at', sa.Float(), nullable=True),
        sa.Column('window_start', sa.Float(), nullable=False),
        sa.Column('window_end', sa.Float(), nullable=False),
        sa.Column('status', sa.String(length=16), nullable=False),
        sa.Column('loops', sa.JSON(), nullable=False),
        sa.Column('incomplete_loops', sa.JSON(), nullable=False),
        sa.Column('sticky_loops', sa.JSON(), nullable=False),
        sa.Column('cleared_loops', sa.JSON(), nullable=False),
        sa.Column('result', sa.JSON(), nullable=True),
        sa.Column('error', sa.Text(), nullable=True),
        sa.Column('round_end', sa.Float(), nullable=True),
        sa.Column('scheduled_by', sa.String(length=200), nullable=True),
        sa.ForeignKeyConstraint(['unit_id'], ['units.id'], ondelete='CASCADE'),
        sa.PrimaryKeyConstraint('id'),
        sa.UniqueConstraint('unit_id', 'round_end', name='uq_unit_analysis_runs_unit_round'),
    )
    op.create_index('ix_unit_analysis_runs_unit_started', 'unit_analysis_runs',
                    ['unit_id', 'started_at'], unique=False)


def downgrade() -> None:
    op.drop_index('ix_unit_analysis_runs_unit_started', table_name='unit_analysis_runs')
    op.drop_table('unit_analysis_runs')
