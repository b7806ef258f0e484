"""The data directory's health: loud about a directory that is gone, read-only or full.

A deleted data directory used to go unnoticed (the capture recreated the run's folder; SQLite
wrote on into a database file that no longer had a name, and a restart showed 0 runs), and a
full disk showed as ``capturing`` for 145 s, then ``internal_error`` (issue 22). Now:

* :meth:`Storage.problem` checks the directory (still the one the service opened, same inode),
  that it takes a new file, that the database file is still there, and the free space
  (``Settings.min_free_mb``); each capture step and each new job checks it first, so the
  affected run fails within a station with ``storage_unavailable`` or ``disk_full``, new runs
  are refused 503, and ``/health`` answers ``degraded`` with the reason;
* a space reserve (``.space-reserve``, ``RESERVE_BYTES``) is kept in the directory and given
  back when the disk is full, so the writes that end a run or cancel it still find room;
* :func:`storage_error` turns an ``OSError`` from a write into the same two errors.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import tempfile
import threading
from pathlib import Path

from sqlalchemy.engine import make_url

from service.errors import ServiceError
from service.settings import Settings

log = logging.getLogger("cellcal.service")

#: Space kept in the data directory and freed when the disk fills, bytes.
RESERVE_BYTES = 16 * 2**20
_RESERVE = ".space-reserve"
_MARKER = ".cellcal-data-dir"
_FULL = (errno.ENOSPC, errno.EDQUOT)
#: ``OSError`` numbers that mean the data directory cannot take a write.
STORAGE_ERRNOS = frozenset({*_FULL, errno.EROFS, errno.EACCES, errno.EPERM, errno.ENOENT,
                            errno.EIO})


class StorageError(ServiceError, code="storage_unavailable"):
    """The data directory cannot take writes: gone, read-only, or (``disk_full``) full (503)."""


def storage_error(exc: OSError, what: str) -> StorageError:
    """The ``StorageError`` an ``OSError`` of ``what`` means."""
    full = exc.errno in _FULL
    return StorageError(f"{what}: {exc.strerror or exc}"
                        + ("; free space in the data directory" if full else
                           "; check that the data directory exists and is writable"),
                        code="disk_full" if full else "storage_unavailable")


class Storage:
    """Watches the data directory (and the SQLite file in it, if any)."""

    def __init__(self, settings: Settings) -> None:
        self.dir = Path(settings.data_dir).resolve()
        self.min_free = settings.min_free_mb * 2**20
        self.database = sqlite_file(settings.database)
        self._identity = _identity(self.dir)
        self._lock = threading.Lock()
        # A directory deleted and made again may get the same inode number: the marker,
        # written once into the directory the service opened, tells them apart.
        self._marker = self.dir / _MARKER
        with contextlib.suppress(OSError):
            self._marker.touch()
        self._keep_reserve()

    def problem(self) -> StorageError | None:
        """Why the data directory cannot take the service's writes now, or None."""
        with self._lock:
            if (error := self.gone()) is not None:
                return error
            try:
                with tempfile.TemporaryFile(dir=self.dir):
                    pass
            except OSError as exc:
                if exc.errno not in _FULL:
                    return storage_error(exc, f"The data directory {self.dir} takes no new "
                                              "file")
            free = _free_bytes(self.dir)
            if free < self.min_free:
                self._give_back_reserve()
                return StorageError(f"The disk of the data directory {self.dir} is full "
                                    f"({free / 2**20:.0f} MB free, CELLCAL_MIN_FREE_MB "
                                    f"{self.min_free / 2**20:g}); free space.",
                                    code="disk_full")
            self._keep_reserve()
            return None

    def gone(self) -> StorageError | None:
        """Why what the service wrote is no longer where it was (the data directory deleted
        or replaced, the database file gone), or None: a job's ``done`` is stored only
        without it (``service.jobs.outcomes``)."""
        if _identity(self.dir) != self._identity or not self._marker.is_file():
            return StorageError(f"The data directory {self.dir} was deleted or replaced "
                                "while the service ran; restore it and restart the service.")
        if self.database is not None and not self.database.is_file():
            return StorageError(f"The database file {self.database} is gone; restore it and "
                                "restart the service.")
        return None

    def check(self) -> None:
        """Raise the ``StorageError`` of :meth:`problem`, if any."""
        if (error := self.problem()) is not None:
            raise error

    def _keep_reserve(self) -> None:
        path = self.dir / _RESERVE
        try:
            if path.is_file() and path.stat().st_size >= RESERVE_BYTES:
                return
            with path.open("wb") as f:
                os.posix_fallocate(f.fileno(), 0, RESERVE_BYTES)
        except OSError:  # no room for it: the check reports the full disk
            with contextlib.suppress(OSError):
                path.unlink(missing_ok=True)

    def _give_back_reserve(self) -> None:
        path = self.dir / _RESERVE
        if path.exists():
            log.error("data directory %s: disk full; the %d MB reserve is given back so runs "
                      "can end and be cancelled", self.dir, RESERVE_BYTES // 2**20)
            path.unlink(missing_ok=True)


def sqlite_file(url: str) -> Path | None:
    """The database file of a SQLite ``url`` in any spelling SQLAlchemy takes
    (``sqlite:///``, ``sqlite+pysqlite:///``), absolute; None for another database."""
    parsed = make_url(url)
    if parsed.get_backend_name() != "sqlite" or parsed.database in (None, "", ":memory:"):
        return None
    return Path(parsed.database).resolve()


def _identity(path: Path) -> tuple[int, int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


def _free_bytes(path: Path) -> int:
    st = os.statvfs(path)
    return st.f_bavail * st.f_frsize
