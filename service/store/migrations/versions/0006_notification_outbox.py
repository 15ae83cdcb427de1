"""notification outbox: ticket and alarm events to deliver by webhook and e-mail

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-26 07:40:00

* ``notifications``: one row per event and channel (``webhook``, ``email``),
  written in the transaction of the change; ``pending`` until delivered or
  given up (``delivered``, ``failed``), with its attempts and the time of the
  next one (:mod:`service.notifications`).
"""

import sqlalchemy as sa
from alembic import op

revision = '0006'
down_revision = '0005'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        'notifications',
        sa.Column('id', sa.Integer(), autoincrement=True, nullable=False),
        sa.Column('event_id', sa.String(length=40), nullable=False),
        sa.Column('channel', sa.String(length=16), nullable=False),
        sa.Column('event_type', sa.String(length=40), nullable=False),
        sa.Column('payload', sa.JSON(), nullable=False),
        sa.Column('created_at', sa.Float(), nullable=False),
        sa.Column('state', sa.String(length=16), nullable=False),
        sa.Column('attempts', sa.Integer(), nullable=False),
        sa.Column('next_attempt_at', sa.Float(), nullable=False),
        sa.Column('last_error', sa.Text(), nullable=True),
        sa.Column('finished_at', sa.Float(), nullable=True),
        sa.PrimaryKeyConstraint('id'),
        sa.UniqueConstraint('event_id'),
    )
    op.create_index('ix_notifications_state_due', 'notifications',
                    ['state', 'next_attempt_at'], unique=False)


def downgrade() -> None:
    op.drop_index('ix_notifications_state_due', table_name='notifications')
    op.drop_table('notifications')
