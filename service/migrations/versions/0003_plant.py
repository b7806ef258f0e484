"""Many cells on one database: a cell name on runs, calibrations, validations and
activations; the active calibration per cell and setup; service instances with a heartbeat;
one motion claim row per cell and robot.

Rows written before name no cell: they get the cell of the service that upgrades the
database (``CELLCAL_CELL``, default the host name), since a database before this revision
served one cell. Activations get their calibration's setup, validations their robot, and the
newest activation per cell and setup becomes the active one.

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-25
"""

from __future__ import annotations

import os
import socket

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None

_ACTIVE = sa.text("state IN ('capturing', 'paused')")
#: A column of the run whose calibration a row of ``table`` refers to.
_OF_RUN = ("(SELECT runs.{column} FROM calibrations JOIN runs ON runs.id = calibrations.run_id "
           "WHERE calibrations.id = {table}.calibration_id)")


def _add_filled(table: str, column: sa.Column, fill: str, **params: str) -> None:
    """Add a required column to a table with rows: nullable, filled by the ``fill`` SQL
    expression, then required."""
    with op.batch_alter_table(table) as batch:
        batch.add_column(column)
    op.execute(sa.text(f"UPDATE {table} SET {column.name} = {fill}").bindparams(**params))
    with op.batch_alter_table(table) as batch:
        batch.alter_column(column.name, existing_type=column.type, nullable=False)


def upgrade() -> None:
    op.create_table(
        "instances",
        sa.Column("id", sa.String(32), primary_key=True),
        sa.Column("cell", sa.String(255), nullable=False),
        sa.Column("host", sa.String(255), nullable=False),
        sa.Column("port", sa.Integer, nullable=False),
        sa.Column("pid", sa.Integer, nullable=False),
        sa.Column("started_at", sa.DateTime, nullable=False),
        sa.Column("heartbeat_at", sa.DateTime, nullable=False))
    op.create_table(
        "motion_claims",
        sa.Column("cell", sa.String(255), primary_key=True),
        sa.Column("robot", sa.String(255), primary_key=True),
        sa.Column("job", sa.String(64)),
        sa.Column("instance_id", sa.String(32)),
        sa.Column("claimed_at", sa.DateTime))
    cell = os.environ.get("CELLCAL_CELL") or socket.gethostname()
    for table in ("runs", "calibrations", "validations", "activations"):
        _add_filled(table, sa.Column("cell", sa.String(255)), ":cell", cell=cell)
        if table != "activations":
            with op.batch_alter_table(table) as batch:
                batch.add_column(sa.Column("instance_id", sa.String(32)))
    with op.batch_alter_table("runs") as batch:
        batch.drop_index("uq_runs_one_active_per_robot")
        batch.create_index("uq_runs_one_active_per_cell_robot", ["cell", "robot"], unique=True,
                           sqlite_where=_ACTIVE, postgresql_where=_ACTIVE)
        batch.create_index("ix_runs_created", ["created_at", "id"])
    _add_filled("validations", sa.Column("robot", sa.String(255)), _OF_RUN.format(
        column="robot", table="validations"))
    _add_filled("activations", sa.Column("setup", sa.String(16)), _OF_RUN.format(
        column="setup", table="activations"))
    with op.batch_alter_table("activations") as batch:
        batch.create_index("ix_activations_cell_setup_id", ["cell", "setup", "id"])
    with op.batch_alter_table("calibrations") as batch:
        batch.create_index("ix_calibrations_cell_created", ["cell", "created_at", "id"])
        batch.create_index("ix_calibrations_created", ["created_at", "id"])
    op.create_table(
        "active_calibrations",
        sa.Column("cell", sa.String(255), primary_key=True),
        sa.Column("setup", sa.String(16), primary_key=True),
        sa.Column("calibration_id", sa.String(32),
                  sa.ForeignKey("calibrations.id", ondelete="CASCADE"), nullable=False,
                  index=True),
        sa.Column("activation_id", sa.Integer, nullable=False))
    op.execute("INSERT INTO active_calibrations (cell, setup, calibration_id, activation_id) "
               "SELECT cell, setup, calibration_id, id FROM activations WHERE id IN "
               "(SELECT max(id) FROM activations GROUP BY cell, setup)")


def downgrade() -> None:
    op.drop_table("active_calibrations")
    with op.batch_alter_table("calibrations") as batch:
        batch.drop_index("ix_calibrations_created")
        batch.drop_index("ix_calibrations_cell_created")
    with op.batch_alter_table("activations") as batch:
        batch.drop_index("ix_activations_cell_setup_id")
        batch.drop_column("setup")
    with op.batch_alter_table("validations") as batch:
        batch.drop_column("robot")
    with op.batch_alter_table("runs") as batch:
        batch.drop_index("ix_runs_created")
        batch.drop_index("uq_runs_one_active_per_cell_robot")
        batch.create_index("uq_runs_one_active_per_robot", ["robot"], unique=True,
                           sqlite_where=_ACTIVE, postgresql_where=_ACTIVE)
    for table in ("runs", "calibrations", "validations", "activations"):
        with op.batch_alter_table(table) as batch:
            batch.drop_column("cell")
            if table != "activations":
                batch.drop_column("instance_id")
    op.drop_table("motion_claims")
    op.drop_table("instances")
