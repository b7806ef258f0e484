"""Schema versions (Alembic): which revision a database is at, creating a new database at
the newest one, and upgrading an older one (``cellcal db upgrade``).

The revisions are in ``versions/``; ``0001`` is the schema as it was before versions were
recorded, so a database made then upgrades like any other. A service opens only a database at
the newest revision (``prepare``): an empty one is created there, an older one is refused
with the command that upgrades it, so a plant upgrades its shared database once, explicitly,
after a backup.
"""

from __future__ import annotations

from pathlib import Path

from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import Connection, Engine, inspect, text

from service.store.records import Base

#: The table where Alembic records the revision.
VERSION_TABLE = "alembic_version"
UPGRADE_COMMAND = "cellcal db upgrade"
#: Key of the PostgreSQL advisory lock held while a new database is created.
_CREATE_LOCK = 0x63656C6C


class SchemaOutdatedError(ValueError):
    """The database is at an older (or unknown) revision than this cellcal needs."""

    code = "schema_outdated"


def _config(connection: Connection | None = None) -> Config:
    """Alembic's configuration: these revisions, run on ``connection``."""
    cfg = Config()
    cfg.set_main_option("script_location", str(Path(__file__).parent))
    cfg.attributes["connection"] = connection
    return cfg


def head() -> str:
    """The newest revision this cellcal knows."""
    revision = ScriptDirectory.from_config(_config()).get_current_head()
    assert revision is not None
    return revision


def current_revision(connection: Connection) -> str | None:
    """The database's recorded revision; None for an empty database or one made before
    revisions were recorded."""
    return MigrationContext.configure(connection).get_current_revision()


def _is_empty(connection: Connection) -> bool:
    return not (set(inspect(connection).get_table_names()) - {VERSION_TABLE})


def prepare(engine: Engine) -> None:
    """Create an empty database at the newest revision; accept one already there; refuse any
    other with ``SchemaOutdatedError`` naming the upgrade command."""
    with engine.begin() as conn:
        if engine.dialect.name == "postgresql":  # two services creating one new database
            conn.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": _CREATE_LOCK})
        if _is_empty(conn):
            Base.metadata.create_all(conn)
            command.stamp(_config(conn), "head")
            return
        current = current_revision(conn)
    newest = head()
    if current == newest:
        return
    where = engine.url.render_as_string(hide_password=True)
    if current is None:
        state = "was made by a cellcal from before schema revisions"
    elif current not in _known_revisions():
        raise SchemaOutdatedError(
            f"the database {where} is at schema revision {current}, which this cellcal "
            f"(newest {newest}) does not know: it was upgraded by a newer cellcal")
    else:
        state = f"is at schema revision {current}"
    raise SchemaOutdatedError(f"the database {where} {state}; this cellcal needs {newest}: "
                              f"back it up, then run `{UPGRADE_COMMAND}`")


def _known_revisions() -> set[str]:
    return {script.revision for script in ScriptDirectory.from_config(_config()).walk_revisions()}


def upgrade(engine: Engine) -> tuple[str, str]:
    """Bring the database to the newest revision (creating it if empty); the revisions before
    and after (``empty``, ``unversioned`` for a database from before revisions)."""
    with engine.begin() as conn:
        before = "empty" if _is_empty(conn) else current_revision(conn) or "unversioned"
        command.upgrade(_config(conn), "head")
        after = current_revision(conn)
    assert after is not None
    return before, after
