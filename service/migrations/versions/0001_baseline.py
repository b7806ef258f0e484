"""The schema of cellcal before schema versions (hub commit e2ac272): runs, stations,
calibrations, their events, activations, validations.

On an empty database it creates the tables. On a database an older cellcal made (tables, no
``alembic_version``) it keeps what is there and adds the columns that cellcal lacked, as its
start-up used to, so every later revision starts from the same schema.

Revision ID: 0001
Revises:
Create Date: 2026-11-25
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op
from sqlalchemy.schema import CreateColumn

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None

_ACTIVE = sa.text("state IN ('capturing', 'paused')")


def _tables(meta: sa.MetaData) -> None:
    """The baseline's tables, frozen here (the models move on; this revision must not)."""
    sa.Table(
        "runs", meta,
        sa.Column("id", sa.String(32), primary_key=True),
        sa.Column("robot", sa.String(255), nullable=False),
        sa.Column("state", sa.String(16), nullable=False),
        sa.Column("mode", sa.String(16), nullable=False, server_default="robot"),
        sa.Column("setup", sa.String(16), nullable=False),
        sa.Column("target", sa.JSON, nullable=False),
        sa.Column("poses", sa.JSON, nullable=False),
        sa.Column("owner", sa.String(32)),
        sa.Column("error", sa.Text),
        sa.Column("error_code", sa.String(64)),
        sa.Column("created_at", sa.DateTime, nullable=False),
        sa.Column("updated_at", sa.DateTime, nullable=False),
        sa.Index("uq_runs_one_active_per_robot", "robot", unique=True,
                 sqlite_where=_ACTIVE, postgresql_where=_ACTIVE))
    sa.Table(
        "stations", meta,
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("run_id", sa.String(32), sa.ForeignKey("runs.id", ondelete="CASCADE"),
                  nullable=False),
        sa.Column("index", sa.Integer, nullable=False),
        sa.Column("state", sa.String(16), nullable=False),
        sa.Column("target_pose", sa.JSON, nullable=False),
        sa.Column("tcp_pose", sa.JSON),
        sa.Column("joint_positions", sa.JSON),
        sa.Column("image_path", sa.String(512)),
        sa.Column("image_size", sa.JSON),
        sa.Column("detection", sa.JSON),
        sa.Column("error", sa.Text),
        sa.Column("error_code", sa.String(64)),
        sa.Column("attempts", sa.Integer, nullable=False),
        sa.Column("captured_at", sa.DateTime, nullable=False),
        sa.UniqueConstraint("run_id", "index", name="uq_stations_run_index"))
    sa.Table(
        "calibrations", meta,
        sa.Column("id", sa.String(32), primary_key=True),
        sa.Column("run_id", sa.String(32), sa.ForeignKey("runs.id", ondelete="CASCADE"),
                  nullable=False, index=True),
        sa.Column("state", sa.String(16), nullable=False),
        sa.Column("options", sa.JSON, nullable=False),
        sa.Column("result", sa.JSON),
        sa.Column("error", sa.Text),
        sa.Column("created_at", sa.DateTime, nullable=False),
        sa.Column("finished_at", sa.DateTime))
    sa.Table(
        "run_events", meta,
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("run_id", sa.String(32), sa.ForeignKey("runs.id", ondelete="CASCADE"),
                  nullable=False, index=True),
        sa.Column("type", sa.String(16), nullable=False),
        sa.Column("data", sa.JSON, nullable=False),
        sa.Column("created_at", sa.DateTime, nullable=False),
        sqlite_autoincrement=True)
    sa.Table(
        "job_events", meta,
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("kind", sa.String(16), nullable=False),
        sa.Column("job_id", sa.String(32), nullable=False),
        sa.Column("type", sa.String(16), nullable=False),
        sa.Column("data", sa.JSON, nullable=False),
        sa.Column("created_at", sa.DateTime, nullable=False),
        sa.Index("ix_job_events_job", "kind", "job_id", "id"),
        sqlite_autoincrement=True)
    sa.Table(
        "activations", meta,
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("robot", sa.String(255), nullable=False),
        sa.Column("calibration_id", sa.String(32),
                  sa.ForeignKey("calibrations.id", ondelete="CASCADE"), nullable=False,
                  index=True),
        sa.Column("activated_at", sa.DateTime, nullable=False),
        sa.Index("ix_activations_robot_id", "robot", "id"))
    sa.Table(
        "validations", meta,
        sa.Column("id", sa.String(32), primary_key=True),
        sa.Column("calibration_id", sa.String(32),
                  sa.ForeignKey("calibrations.id", ondelete="CASCADE"), nullable=False,
                  index=True),
        sa.Column("kind", sa.String(32), nullable=False),
        sa.Column("state", sa.String(16), nullable=False),
        sa.Column("result", sa.JSON),
        sa.Column("error", sa.Text),
        sa.Column("created_at", sa.DateTime, nullable=False),
        sa.Column("finished_at", sa.DateTime))


def upgrade() -> None:
    bind = op.get_bind()
    meta = sa.MetaData()
    _tables(meta)
    present = sa.inspect(bind)
    for table in meta.sorted_tables:
        if not present.has_table(table.name):
            table.create(bind)
            continue
        have = {c["name"] for c in present.get_columns(table.name)}
        for column in table.columns:
            if column.name not in have:  # nullable or with a server default, as they were
                ddl = CreateColumn(column).compile(dialect=bind.dialect)
                op.execute(f"ALTER TABLE {table.name} ADD COLUMN {ddl}")


def downgrade() -> None:
    meta = sa.MetaData()
    _tables(meta)
    meta.drop_all(op.get_bind())
