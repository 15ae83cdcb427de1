"""salted API keys with a key id; where each loop was configured

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-26 05:00:00

* ``api_keys``: ``prefix`` (the key's first 8 characters, half of a short
  key) is dropped; ``key_id`` (not secret, for lists and logs) and ``salt``
  are added, and ``key_hash`` becomes ``SHA-256(salt || SHA-256(key))``.
  The stored unsalted hash is ``SHA-256(key)``, so every existing key is
  rehashed here and keeps working without being re-issued; those keys get an
  ``ext-`` id (they do not carry one, see :mod:`service.auth`).
* ``loops.origin``: ``plant_file`` or ``api`` (``PUT /api/v1/loops/{id}``);
  the service loads the ``api`` loops at start.  Rows stored before this
  revision cannot be told apart, so they are all marked ``api`` (none is
  lost); the next start marks the plant file's loops ``plant_file``.
"""

import hashlib
import secrets

import sqlalchemy as sa
from alembic import op

revision = '0004'
down_revision = '0003'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('api_keys', schema=None) as batch_op:
        batch_op.add_column(sa.Column('key_id', sa.String(length=16), nullable=True))
        batch_op.add_column(sa.Column('salt', sa.String(length=32), nullable=True))
    bind = op.get_bind()
    keys = sa.table('api_keys', sa.column('id', sa.Integer()), sa.column('key_id', sa.String()),
                    sa.column('salt', sa.String()), sa.column('key_hash', sa.String()))
    for row_id, old_hash in bind.execute(sa.select(keys.c.id, keys.c.key_hash)).all():
        salt = secrets.token_hex(16)
        bind.execute(keys.update().where(keys.c.id == row_id).values(
            key_id="ext-" + secrets.token_hex(6), salt=salt,
            key_hash=hashlib.sha256(bytes.fromhex(salt) + bytes.fromhex(old_hash)).hexdigest()))
    with op.batch_alter_table('api_keys', schema=None) as batch_op:
        batch_op.alter_column('key_id', existing_type=sa.String(length=16), nullable=False)
        batch_op.alter_column('salt', existing_type=sa.String(length=32), nullable=False)
        batch_op.create_unique_constraint('uq_api_keys_key_id', ['key_id'])
        batch_op.drop_column('prefix')
    with op.batch_alter_table('loops', schema=None) as batch_op:
        batch_op.add_column(sa.Column('origin', sa.String(length=16), nullable=False,
                                      server_default='api'))


def downgrade() -> None:
    raise NotImplementedError(
        "0004 cannot be undone: the salted key hashes cannot be turned back into "
        "SHA-256(key); restore the database from a backup taken before the upgrade")
