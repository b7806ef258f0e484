"""Alembic's environment: migrate the connection ``service.migrations`` hands over, or, for
the ``alembic`` command line (alembic.ini at the repository root), the database its
``sqlalchemy.url`` or ``CELLCAL_DATABASE_URL`` names."""

from __future__ import annotations

import os

from alembic import context
from sqlalchemy import Connection, create_engine

from service.store.records import Base


def run() -> None:
    connection = context.config.attributes.get("connection")
    if connection is not None:
        _migrate(connection)
        return
    url = os.environ.get("CELLCAL_DATABASE_URL") or context.config.get_main_option(
        "sqlalchemy.url")
    engine = create_engine(url)
    with engine.connect() as conn:
        _migrate(conn)
    engine.dispose()


def _migrate(connection: Connection) -> None:
    # batch mode: SQLite alters a table by copying it, which is how it renames or retypes
    context.configure(connection=connection, target_metadata=Base.metadata,
                      render_as_batch=True, compare_type=True)
    with context.begin_transaction():
        context.run_migrations()


run()
