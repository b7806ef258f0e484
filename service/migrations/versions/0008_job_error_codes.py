"""A failed calibration or validation names its reason by a code (``error_code``), as a run
does: a client told storage_unavailable, disk_full, a device fault or an interrupted job apart
only by parsing the ``error`` text.

Revision ID: 0008
Revises: 0007
Create Date: 2026-11-26
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0008"
down_revision = "0007"
branch_labels = None
depends_on = None

_TABLES = ("calibrations", "validations")


def upgrade() -> None:
    for table in _TABLES:
        op.add_column(table, sa.Column("error_code", sa.String(64)))


def downgrade() -> None:
    for table in _TABLES:
        with op.batch_alter_table(table) as batch:
            batch.drop_column("error_code")
