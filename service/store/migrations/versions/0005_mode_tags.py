"""mode tags: a loop's controller mode is a signal of its own

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-26 07:00:00

* ``tags.signal`` widens from 2 to 8 characters: besides ``op``, ``pv``,
  ``sp`` and ``mv`` a tag may now be a loop's ``mode`` (issue 24, the
  service factor).  Existing rows are unchanged; going back is refused while
  a ``mode`` tag is stored, as it would not fit.
"""

import sqlalchemy as sa
from alembic import op

revision = '0005'
down_revision = '0004'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('tags', schema=None) as batch_op:
        batch_op.alter_column('signal', existing_type=sa.String(length=2),
                              type_=sa.String(length=8), existing_nullable=False)


def downgrade() -> None:
    tags = sa.table('tags', sa.column('signal', sa.String()))
    if op.get_bind().execute(sa.select(sa.func.count()).select_from(tags)
                             .where(sa.func.length(tags.c.signal) > 2)).scalar():
        raise RuntimeError("0005 cannot be undone while mode tags are stored: remove the "
                           "loops' mode tags first")
    with op.batch_alter_table('tags', schema=None) as batch_op:
        batch_op.alter_column('signal', existing_type=sa.String(length=8),
                              type_=sa.String(length=2), existing_nullable=False)
