"""The service's database: show its schema revision, or upgrade it to the one this cellcal
needs. The database is CELLCAL_DATABASE_URL (default sqlite:///<CELLCAL_DATA_DIR>/cellcal.db),
or --url. Back the database up before upgrading it (pg_dump on PostgreSQL, a copy of the file
on SQLite): 'cellcal serve' refuses a database at an older revision.
"""

# ``cellcal db upgrade|current``: Alembic revisions (``service.migrations``) from the command line.

from __future__ import annotations

import argparse
import sys


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``db`` command's arguments."""
    parser.add_argument("action", choices=("upgrade", "current"),
                        help="upgrade: bring the database to this cellcal's schema; current: "
                             "print the database's revision and the newest one")
    parser.add_argument("--url", help="SQLAlchemy database URL (default: the service's)")


def run(args: argparse.Namespace) -> int:
    """Upgrade the database or print its revision."""
    from sqlalchemy import create_engine
    from sqlalchemy.exc import SQLAlchemyError

    from service import migrations
    from service.store.db import with_driver

    url = args.url or _service_database()
    engine = create_engine(with_driver(url))
    where = engine.url.render_as_string(hide_password=True)
    try:
        if args.action == "upgrade":
            before, after = migrations.upgrade(engine)
            said = "already at" if before == after else f"upgraded from {before} to"
            print(f"{where}: {said} schema revision {after}", file=sys.stderr)
        else:
            with engine.connect() as conn:
                current = migrations.current_revision(conn)
            print(f"{current or 'none'} (newest {migrations.head()})")
    except SQLAlchemyError as exc:
        why = str(getattr(exc, "orig", None) or exc).splitlines()[0]
        raise ValueError(f"database {where}: {why}") from None
    finally:
        engine.dispose()
    return 0


def _service_database() -> str:
    """The database the service would open (``CELLCAL_*`` settings)."""
    from pydantic import ValidationError

    from service.settings import Settings

    try:
        return Settings().database
    except ValidationError as exc:
        raise ValueError(f"configuration: {exc.errors()[0]['msg']}") from None
