"""Database engine and sessions: one ``Database`` per app, shared by requests and job threads."""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

from sqlalchemy import URL, Engine, create_engine, event, make_url
from sqlalchemy.exc import DisconnectionError, InterfaceError, OperationalError
from sqlalchemy.orm import Session, sessionmaker

from service import migrations

log = logging.getLogger("cellcal.service")
T = TypeVar("T")

#: Errors a later attempt of the same transaction can get past: a lock held beyond the busy
#: timeout, a database server restarting, a dropped connection.
TRANSIENT_ERRORS = (OperationalError, InterfaceError)
#: First pause between attempts (s); doubled after each failure up to ``_MAX_DELAY_S``.
_FIRST_DELAY_S = 0.1
_MAX_DELAY_S = 2.0
#: Connections a service keeps open once it needed them (at most twice as many at a peak).
#: With SQLAlchemy's 5, 20 clients made PostgreSQL connections open and close 3-5 times a
#: second, and a GET that opened one took 3-4x as long (issue 21, benchmarks/README.md).
POOL_SIZE = 20
#: A pooled PostgreSQL connection unused for longer than this (s) is pinged before it is handed
#: out, and replaced if the server dropped it (a restart, an idle timeout). A connection used
#: more recently is not: under load each would otherwise cost every request one more round
#: trip (issue 21). One that died within this time fails its statement once; SQLAlchemy then
#: replaces every pooled connection older than the failure.
IDLE_PING_S = 5.0


class DatabaseUnavailableError(Exception):
    """The database kept failing (``TRANSIENT_ERRORS``) for a whole retry budget."""

    code = "database_unavailable"


def retry_transient(transaction: Callable[[], T], *, budget_s: float, what: str,
                    stopping: threading.Event | None = None) -> T:
    """Run ``transaction`` (a whole session's work), again after transient errors.

    Pauses grow from 0.1 s to 2 s (exponential backoff). After ``budget_s`` seconds of failures,
    or when ``stopping`` is set, ``DatabaseUnavailableError`` names ``what`` failed and why.
    """
    deadline = time.monotonic() + budget_s
    delay = _FIRST_DELAY_S
    while True:
        try:
            return transaction()
        except TRANSIENT_ERRORS as exc:
            why = str(getattr(exc, "orig", None) or exc).splitlines()[0]
            if time.monotonic() + delay > deadline or (stopping and stopping.is_set()):
                raise DatabaseUnavailableError(
                    f"{what}: the database did not answer for {budget_s:g} s ({why})") from exc
            log.warning("%s: %s; retrying in %.1f s", what, why, delay)
        if stopping is not None:
            stopping.wait(delay)
        else:
            time.sleep(delay)
        delay = min(2.0 * delay, _MAX_DELAY_S)


def with_driver(url: str) -> URL:
    """The URL with the PostgreSQL driver cellcal ships (psycopg 3) when it names none:
    ``postgresql://...`` as libpq and ``pg_dump`` write it works as it is."""
    parsed = make_url(url)
    return parsed.set(drivername="postgresql+psycopg") if parsed.drivername in (
        "postgresql", "postgres") else parsed


class Database:
    """Engine plus session factory. Opens a database at the newest schema revision, creating
    an empty one there; refuses an older one (``migrations.SchemaOutdatedError``: run
    ``cellcal db upgrade``).

    SQLite gets a busy timeout and write-ahead logging so the capture threads can commit a
    station while requests read, and foreign keys are enforced as on other databases.
    """

    def __init__(self, url: str, *, busy_timeout_s: float = 30.0) -> None:
        is_sqlite = url.startswith("sqlite")
        connect_args: dict[str, Any] = (
            {"check_same_thread": False, "timeout": busy_timeout_s} if is_sqlite else {})
        self.engine: Engine = create_engine(with_driver(url), connect_args=connect_args,
                                            pool_size=POOL_SIZE, max_overflow=POOL_SIZE)
        self._sessions = sessionmaker(self.engine, expire_on_commit=False)
        if is_sqlite:
            event.listen(self.engine, "connect", _sqlite_pragmas)
            # pysqlite begins no transaction for a SELECT: reads already cost no BEGIN
            self._reads = self._sessions
        else:  # a SQLite file has no server that could drop a connection
            _ping_when_idle(self.engine)
            # no BEGIN before and no ROLLBACK after a request's reads: two round trips of a
            # GET's 3-4. Under READ COMMITTED each statement sees its own snapshot anyway.
            self._reads = sessionmaker(self.engine.execution_options(
                isolation_level="AUTOCOMMIT"), expire_on_commit=False)
        try:
            migrations.prepare(self.engine)
        except BaseException:
            self.engine.dispose()
            raise

    @contextmanager
    def session(self) -> Iterator[Session]:
        """A session that is closed (and rolled back if uncommitted) on exit."""
        with self._sessions() as session:
            yield session

    def new_session(self, *, read_only: bool = False) -> Session:
        """A session the caller closes (no I/O until it is first used); ``read_only``: one for
        reads only, whose statements run outside a transaction (each commits at once)."""
        return self._reads() if read_only else self._sessions()

    def close(self) -> None:
        self.engine.dispose()


def _ping_when_idle(engine: Engine) -> None:
    """Ping a pooled connection on checkout only if it sat unused for ``IDLE_PING_S``
    (SQLAlchemy's ``pool_pre_ping`` pings on every checkout). A dead one is replaced: raising
    ``DisconnectionError`` in ``checkout`` makes the pool discard it and connect again."""

    @event.listens_for(engine, "checkin")
    def returned(_dbapi_connection: Any, record: Any) -> None:
        record.info["returned_at"] = time.monotonic()

    @event.listens_for(engine, "checkout")
    def ping_if_idle(dbapi_connection: Any, record: Any, _proxy: Any) -> None:
        if time.monotonic() - record.info.get("returned_at", math.inf) <= IDLE_PING_S:
            return
        try:
            engine.dialect.do_ping(dbapi_connection)
        except engine.dialect.loaded_dbapi.Error as exc:
            raise DisconnectionError(f"a pooled connection was dropped: {exc}") from exc


def _sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
    cursor = dbapi_connection.cursor()
    cursor.execute("PRAGMA foreign_keys=ON")
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.close()
