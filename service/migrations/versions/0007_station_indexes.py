"""Indexes for a run's station counts and errors (issue 21, history that stays fast):
``GET /runs`` counts the stations of 50 runs by state and lists their errors. Through the
``(run_id, index)`` key both read every station row, and a station's error column lies behind
its detection (88 corners, a few kB), so SQLite read ~1,000 rows with their overflow pages per
page (7 ms). ``(run_id, state)`` answers the counts from the index alone; the partial index
over the stations that have an error finds those without touching the others.

Revision ID: 0007
Revises: 0006
Create Date: 2026-11-26
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0007"
down_revision = "0006"
branch_labels = None
depends_on = None

_HAS_ERROR = sa.text("error IS NOT NULL")


def upgrade() -> None:
    op.create_index("ix_stations_run_state", "stations", ["run_id", "state"])
    op.create_index("ix_stations_run_errors", "stations", ["run_id", "index"],
                    sqlite_where=_HAS_ERROR, postgresql_where=_HAS_ERROR)


def downgrade() -> None:
    op.drop_index("ix_stations_run_errors", "stations")
    op.drop_index("ix_stations_run_state", "stations")
