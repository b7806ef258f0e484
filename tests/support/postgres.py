"""A throwaway PostgreSQL server for tests, benchmarks and the plant test.

``PostgresServer.start()`` runs Debian's ``initdb`` and ``postgres`` (``/usr/lib/postgresql/*/
bin``) in a fresh directory under /tmp, listening only on a unix socket in that directory, with
durability off (fsync, synchronous commit: nothing here outlives the run). As root it runs the
server as ``nobody``, since ``initdb`` refuses root. The server is the caller's child and gets
SIGQUIT (immediate shutdown) when the caller dies, even by SIGKILL
(``service.serving.parent_death``); a directory left by a killed run is removed by the next
``start()``.
"""

from __future__ import annotations

import contextlib
import glob
import os
import pwd
import shutil
import signal
import subprocess
import tempfile
import time
import uuid
from collections.abc import Callable
from pathlib import Path

from service.serving.parent_death import die_with_parent
from service.store.instances import process_alive

#: Directories of servers made here: /tmp/cellcal-pg-<random>, with the creator's pid inside.
_PREFIX = "cellcal-pg-"
_SUPERUSER = "cellcal"


class PostgresUnavailableError(RuntimeError):
    """No PostgreSQL server binaries on this machine."""


def server_binaries() -> Path:
    """The newest installed PostgreSQL's ``bin`` directory (``initdb``, ``postgres``)."""
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"),
                   key=lambda p: int(Path(p).parts[-3]) if Path(p).parts[-3].isdigit() else 0)
    if found:
        return Path(found[-1]).parent
    initdb = shutil.which("initdb")
    if initdb is None:
        raise PostgresUnavailableError(
            "PostgreSQL is not installed (Debian: apt-get install postgresql)")
    return Path(initdb).parent


class PostgresServer:
    """One running server; ``url(name)`` addresses a database on it by SQLAlchemy URL."""

    def __init__(self) -> None:
        self.bin = server_binaries()
        self.root = Path(tempfile.mkdtemp(prefix=_PREFIX))
        self.port = 5432
        self.process: subprocess.Popen[bytes] | None = None

    @property
    def socket_dir(self) -> Path:
        return self.root

    def url(self, database: str = "postgres") -> str:
        """SQLAlchemy URL of ``database`` on this server (psycopg 3 over the unix socket)."""
        return (f"postgresql+psycopg://{_SUPERUSER}@/{database}"
                f"?host={self.socket_dir}&port={self.port}")

    def start(self, timeout_s: float = 60.0) -> PostgresServer:
        """initdb, start the server and wait until it takes connections."""
        remove_stale_servers()
        (self.root / "owner.pid").write_text(str(os.getpid()))
        data = self.root / "data"
        demote = _demoter(self.root)
        subprocess.run([str(self.bin / "initdb"), "-D", str(data), "-U", _SUPERUSER,
                        "--auth=trust", "-E", "UTF8", "--locale=C.UTF-8", "--no-sync"],
                       check=True, capture_output=True, preexec_fn=demote)
        log = (self.root / "server.log").open("wb")
        self.process = subprocess.Popen(
            [str(self.bin / "postgres"), "-D", str(data), "-k", str(self.socket_dir),
             "-p", str(self.port), "-c", "listen_addresses=", "-c", "fsync=off",
             "-c", "synchronous_commit=off", "-c", "full_page_writes=off",
             "-c", "max_connections=300", "-c", "shared_buffers=64MB"],
            stdout=log, stderr=subprocess.STDOUT, preexec_fn=_and_die_with_parent(demote))
        deadline = time.monotonic() + timeout_s
        while not self._answers():
            if self.process.poll() is not None or time.monotonic() > deadline:
                self.stop()
                raise RuntimeError("PostgreSQL did not start: "
                                   + (self.root / "server.log").read_text()[-2000:])
            time.sleep(0.05)
        return self

    def _answers(self) -> bool:
        import psycopg

        try:
            psycopg.connect(self.dsn("postgres"), connect_timeout=2).close()
        except psycopg.OperationalError:
            return False
        return True

    def dsn(self, database: str) -> str:
        """libpq connection string of ``database`` (for psycopg directly)."""
        return f"host={self.socket_dir} port={self.port} user={_SUPERUSER} dbname={database}"

    def create_database(self, prefix: str = "t") -> str:
        """A new empty database; its name."""
        import psycopg

        name = f"{prefix}_{uuid.uuid4().hex[:12]}"
        with psycopg.connect(self.dsn("postgres"), autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return name

    def drop_database(self, name: str) -> None:
        """Drop ``name``, closing what still connects to it."""
        import psycopg

        with psycopg.connect(self.dsn("postgres"), autocommit=True) as conn:
            conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')

    def stop(self) -> None:
        """Stop the server at once and remove its directory."""
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(signal.SIGQUIT)
            try:
                self.process.wait(20)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        shutil.rmtree(self.root, ignore_errors=True)


def _demoter(root: Path) -> Callable[[], None] | None:
    """As root: hand ``root`` to ``nobody`` and return what makes a child ``nobody``."""
    if os.geteuid() != 0:
        return None
    nobody = pwd.getpwnam("nobody")
    for path in (root, *root.rglob("*")):
        os.chown(path, nobody.pw_uid, nobody.pw_gid)

    def demote() -> None:
        os.setgroups([])
        os.setgid(nobody.pw_gid)
        os.setuid(nobody.pw_uid)

    return demote


def _and_die_with_parent(first: Callable[[], None] | None) -> Callable[[], None]:
    """``first``, then SIGQUIT (immediate shutdown) for the server when its parent dies (armed
    after the uid change, which would clear it)."""
    parent = os.getpid()

    def prepare() -> None:
        if first is not None:
            first()
        die_with_parent(signal.SIGQUIT, parent)

    return prepare


def remove_stale_servers() -> None:
    """Stop and remove the servers of runs that died without stopping them."""
    for root in Path(tempfile.gettempdir()).glob(f"{_PREFIX}*"):
        try:
            owner = int((root / "owner.pid").read_text())
        except (OSError, ValueError):
            continue
        if process_alive(owner):
            continue
        with contextlib.suppress(OSError, ValueError, IndexError):
            postmaster = int((root / "data" / "postmaster.pid").read_text().split()[0])
            os.kill(postmaster, signal.SIGQUIT)
        shutil.rmtree(root, ignore_errors=True)
