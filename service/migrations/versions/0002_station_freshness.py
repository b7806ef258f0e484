"""Stations keep how the camera made sure their image was exposed after the robot settled
(``freshness``, issue 17 item 5).

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-25
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("stations") as batch:
        batch.add_column(sa.Column("freshness", sa.Text))


def downgrade() -> None:
    with op.batch_alter_table("stations") as batch:
        batch.drop_column("freshness")
