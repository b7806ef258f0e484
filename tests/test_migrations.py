"""Schema revisions (``service.migrations``, ``cellcal db``) on SQLite and PostgreSQL.

``data/schema-e2ac272.db`` was written by the service as it was at hub commit e2ac272, before
schema revisions: a planned 8-station run captured, calibrated, activated and validated at the
centre point, a cancelled run and an external run still open, with their events (3 runs, 8
stations, 1 calibration, 1 activation, 1 validation, 10 run events, 15 job events). On
PostgreSQL the same rows are copied into tables made by the first revision, with no revision
recorded, as that cellcal's ``create_all`` left them.
"""

from __future__ import annotations

import datetime as dt
import shutil
from pathlib import Path
from typing import Any

import pytest
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from sqlalchemy import Engine, MetaData, create_engine, select, text

from service import migrations
from service.cli.main import main
from service.migrations import SchemaOutdatedError
from service.store.db import Database
from service.store.records import Base
from tests.support.cli import assert_one_line_error

pytestmark = [pytest.mark.usefixtures("database"), pytest.mark.pg_fast]

OLD_DB = Path(__file__).parent / "data" / "schema-e2ac272.db"
OLD_COUNTS = {"runs": 3, "stations": 8, "calibrations": 1, "activations": 1,
              "validations": 1, "run_events": 10, "job_events": 15}


@pytest.fixture
def url(tmp_path: Path, database: str | None) -> str:
    """The test's database: a new SQLite file or the fixture's PostgreSQL database."""
    return database or f"sqlite:///{tmp_path / 'cellcal.db'}"


def rows(engine: Engine, tables: list[str] | None = None) -> dict[str, dict[Any, dict]]:
    """Every row of ``tables`` (default all), by table and primary key, datetimes naive."""
    meta = MetaData()
    meta.reflect(engine, only=tables)
    out: dict[str, dict[Any, dict]] = {}
    with engine.connect() as conn:
        for table in meta.sorted_tables:
            if table.name in (migrations.VERSION_TABLE, "sqlite_sequence"):
                continue
            key = [c.name for c in table.primary_key.columns]
            out[table.name] = {tuple(r[k] for k in key): dict(r)
                               for r in conn.execute(select(table)).mappings()}
    return out


def old_database(url: str) -> None:
    """Put the pre-revision fixture's rows at ``url`` (a copy of the file on SQLite)."""
    if url.startswith("sqlite"):
        shutil.copy(OLD_DB, url.removeprefix("sqlite:///"))
        return
    engine = create_engine(url)
    with engine.begin() as conn:
        migrations.command.upgrade(migrations._config(conn), "0001")
        conn.execute(text(f"DROP TABLE {migrations.VERSION_TABLE}"))
    source = create_engine(f"sqlite:///{OLD_DB}")
    meta = MetaData()
    meta.reflect(engine)
    with source.connect() as src, engine.begin() as dst:
        for table in meta.sorted_tables:
            found = [dict(r) for r in src.execute(text(f'SELECT * FROM "{table.name}"'))
                     .mappings()]
            for row in found:
                for column in ("created_at", "updated_at", "captured_at", "finished_at",
                               "activated_at"):
                    if isinstance(row.get(column), str):
                        row[column] = dt.datetime.fromisoformat(row[column])
            if found:
                dst.execute(table.insert(), found)
            if "id" in table.c and str(table.c.id.type) == "INTEGER":
                dst.execute(text(f"SELECT setval(pg_get_serial_sequence('{table.name}', 'id'),"
                                 f" (SELECT max(id) FROM {table.name}))"))
    source.dispose()
    engine.dispose()


def test_a_new_database_is_created_at_the_newest_revision(url: str) -> None:
    Database(url).close()
    engine = create_engine(url)
    with engine.connect() as conn:
        assert migrations.current_revision(conn) == migrations.head()
    engine.dispose()
    Database(url).close()  # and opens again


def test_the_revisions_build_what_the_models_describe(url: str) -> None:
    """Upgrading an empty database through every revision gives the models' schema, so a
    database created new (from the models) and one upgraded are the same."""
    engine = create_engine(url)
    assert migrations.upgrade(engine) == ("empty", migrations.head())
    with engine.connect() as conn:
        diff = compare_metadata(MigrationContext.configure(conn), Base.metadata)
    engine.dispose()
    assert diff == []


def test_an_upgrade_keeps_every_row(url: str) -> None:
    old_database(url)
    engine = create_engine(url)
    before = rows(engine)
    assert {name: len(found) for name, found in before.items()} == OLD_COUNTS
    with pytest.raises(SchemaOutdatedError, match="cellcal db upgrade"):
        Database(url)
    assert migrations.upgrade(engine) == ("unversioned", migrations.head())
    after = rows(engine, list(before))
    for name, found in before.items():
        assert set(after[name]) == set(found), name
        for key, row in found.items():
            assert {k: after[name][key][k] for k in row} == row, (name, key)
    engine.dispose()
    db = Database(url)  # opens now; and new rows still get fresh ids
    with db.session() as s:
        s.execute(text("INSERT INTO job_events (kind, job_id, type, data, created_at) VALUES "
                       "('validation', 'x', 'state', '{}', '2026-11-25 00:00:00')"))
        s.commit()
    db.close()


def test_serve_refuses_an_old_database_and_names_the_upgrade(
        url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    old_database(url)
    for name, value in (("DATABASE_URL", url), ("DATA_DIR", str(tmp_path)),
                        ("API_KEY", "k" * 24)):
        monkeypatch.setenv(f"CELLCAL_{name}", value)
    assert main(["serve", "--mock", "--port", "1"]) != 0
    served = capsys.readouterr()
    assert_one_line_error(served.err, f"needs {migrations.head()}: back it up, then run "
                                      "`cellcal db upgrade`")
    assert main(["db", "upgrade"]) == 0
    assert f"upgraded from unversioned to schema revision {migrations.head()}" in \
        capsys.readouterr().err
    assert main(["db", "current"]) == 0
    assert capsys.readouterr().out.split()[0] == migrations.head()
    assert main(["db", "upgrade"]) == 0
    assert f"already at schema revision {migrations.head()}" in capsys.readouterr().err


def test_a_url_as_libpq_writes_it_opens(url: str, capsys: pytest.CaptureFixture[str]) -> None:
    """``postgresql://...`` (no driver named, as pg_dump and psql take it) means psycopg 3."""
    plain = url.replace("postgresql+psycopg://", "postgresql://")
    Database(plain).close()
    assert main(["db", "current", "--url", plain]) == 0
    assert capsys.readouterr().out.split()[0] == migrations.head()
