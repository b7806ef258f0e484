"""This service among the others on one database: its ``Instance`` row, the heartbeat that
renews its lease, and the recovery of work whose service died.

A service registers at start-up and renews ``heartbeat_at`` every third of the lease. Work
in flight (a capturing run, a running calibration or validation) names its instance. At
start-up and at every heartbeat a service recovers the work of its own cell whose instance
is dead: its lease ran out, or it ran on this host under a process id that is gone (so a
service restarted after ``kill -9`` need not wait out the lease). A live service's work is
never touched.
"""

from __future__ import annotations

import datetime as dt
import logging
import os
import socket
import threading

from service.settings import Settings
from service.store import queries, writes
from service.store.db import Database
from service.store.records import InstanceRecord, utcnow

log = logging.getLogger("cellcal.service")


class InstanceLease:
    """This service's instance row and its heartbeat thread."""

    def __init__(self, settings: Settings, db: Database) -> None:
        self.db = db
        self.cell = settings.cell
        self.lease = dt.timedelta(seconds=settings.lease_s)
        self.host = socket.gethostname()
        self.row = InstanceRecord(cell=settings.cell, host=self.host, port=settings.port,
                                  pid=os.getpid())
        with db.session() as s:
            writes.add_instance(s, self.row)
        self.id: str = self.row.id
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, name="heartbeat", daemon=True)

    def describe(self) -> str:
        """How a 409 names this instance."""
        return describe(self.row)

    def start(self) -> None:
        """Recover dead services' work now, then keep the lease and recover at every beat."""
        self.recover()
        self._thread.start()

    def recover(self) -> tuple[int, int, int]:
        """Fail or interrupt the work of this cell's dead instances (``writes.recover``);
        forget those instances. How many runs, calibrations and validations."""
        with self.db.session() as s:
            live = self.live_instances(s)
            counts = writes.recover(s, cell=self.cell, live=live)
            writes.forget_instances(s, cell=self.cell, live=live)
        if any(counts):
            log.warning("recovered the work of stopped services of cell %s: %d run(s) "
                        "interrupted, %d calibration(s) and %d validation(s) failed",
                        self.cell, *counts)
        return counts

    def live_instances(self, s: queries.Session) -> set[str]:
        """Ids of this cell's instances that hold their lease (this one always)."""
        now = utcnow()
        live = {self.id}
        for row in queries.instances(s, cell=self.cell):
            on_this_host_and_gone = row.host == self.host and not process_alive(row.pid)
            if row.heartbeat_at + self.lease > now and not on_this_host_and_gone:
                live.add(row.id)
        return live

    def _beat(self) -> None:
        while not self._stop.wait(self.lease.total_seconds() / 3):
            try:
                with self.db.session() as s:
                    if not writes.renew_instance(s, instance_id=self.id):
                        log.error("this service's instance %s was taken for dead by another "
                                  "(no heartbeat for %s); registering again", self.id,
                                  self.lease)
                        writes.restore_instance(s, self.row)
                self.recover()
            except Exception as exc:  # a database outage: try again at the next beat
                log.warning("heartbeat: %s", exc)

    def close(self) -> None:
        """Stop the heartbeat and remove the instance row (its work has ended by now)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(10.0)
        with self.db.session() as s:
            writes.forget_instances(s, cell=self.cell, live=set(), only={self.id})


def describe(row: InstanceRecord) -> str:
    """``instance <id> (<host>:<port>, pid <pid>)``."""
    return f"instance {row.id} ({row.host}:{row.port}, pid {row.pid})"


def process_alive(pid: int) -> bool:
    """True while a process ``pid`` exists on this host (ours or another user's)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
