"""Who moves the robot, and where it may go.

The robot does one motion job at a time: a capture run (``service.runs``) or a dot-hit
validation (``service.jobs.validations``). A validation is refused while a run is active (capturing
or paused) and a run while a validation is running. ``claim`` makes each check and the row
that claims the robot one transaction that first writes the robot's ``motion_claims`` row, so
it holds across every service on the database (its write lock makes a second claimer wait
for the first one's commit); the one-active-run index backs it for runs. Robots are told
apart by cell and URL: two cells' ``mock://`` robots are two robots. Every commanded pose is
checked against the workspace box.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
from sqlalchemy.orm import Session

from drivers.errors import WorkspaceError
from service.cell.devices import Devices
from service.errors import ConflictError
from service.events import EventBus
from service.settings import Settings
from service.store import queries, writes
from service.store.db import Database
from service.store.instances import describe
from service.store.records import RunRecord, ValidationRecord
from service.store.storage import Storage


class Motion:
    """The robot's motion jobs: their threads, the locks that serialise them, the box."""

    def __init__(self, settings: Settings, db: Database, devices: Devices,
                 instance_id: str, storage: Storage) -> None:
        self.settings = settings
        self.db = db
        self.devices = devices
        #: This service's instance (``service.store.instances``): its jobs' rows name it.
        self.instance_id = instance_id
        #: The data directory's health, checked before each station and each new job.
        self.storage = storage
        #: Held by the one thread that drives the robot.
        self.robot_lock = threading.Lock()
        #: Set at shutdown: motion threads take no new step.
        self.stopping = threading.Event()
        self._threads: dict[str, threading.Thread] = {}  # run owner / validation id -> thread
        self._threads_lock = threading.Lock()
        self._stop_deadline: float | None = None  # when shutdown stops waiting for threads

    # ---- claiming the robot ----------------------------------------------------------------

    @contextlib.contextmanager
    def claim(self, job: str, *, check: bool = True) -> Iterator[Session]:
        """A session whose transaction holds the robot's claim (``writes.claim_robot``) until
        the block, which stores the claiming row ``job`` names, commits; first check that the
        robot is free (409 if not) unless the block makes its own checks (``check=False``)."""
        with self.db.session() as s:
            writes.claim_robot(s, cell=self.settings.cell, robot=self.settings.robot, job=job,
                              instance_id=self.instance_id)
            if check:
                self.check_free(s)
            yield s

    def check_free(self, s: Session | None = None) -> None:
        """409 while a run is active on the robot or a validation moves it."""
        with contextlib.ExitStack() as stack:
            s = s or stack.enter_context(self.db.session())
            if queries.running_validation(s, **self._robot()) is not None or \
                    queries.active_run(s, **self._robot()) is not None:
                raise self.busy(s)

    def busy(self, s: Session | None = None) -> ConflictError:
        """The 409 that says what keeps the robot busy and which service holds it."""
        with contextlib.ExitStack() as stack:
            s = s or stack.enter_context(self.db.session())
            job: RunRecord | ValidationRecord | None = queries.active_run(s, **self._robot())
            what = "already has an active run"
            if job is None:
                job = queries.running_validation(s, **self._robot())
                what = "is running validation"
            holder = queries.get_instance(s, instance_id=job.instance_id if job else None)
        held = f", held by {describe(holder)}" if holder is not None else ""
        advice = ("let it finish first" if isinstance(job, ValidationRecord)
                  else "cancel it or let it finish first")
        return ConflictError(f"The robot {self.settings.robot} of cell {self.settings.cell} "
                             f"{what} {job.id if job else ''}{held}; {advice}.",
                             code="robot_busy")

    def _robot(self) -> dict[str, str]:
        return {"cell": self.settings.cell, "robot": self.settings.robot}

    # ---- motion threads --------------------------------------------------------------------

    def start(self, key: str, job: Callable[..., None], *args: Any, name: str) -> None:
        """Run ``job(*args)`` in a daemon thread known by ``key`` until it returns."""

        def body() -> None:
            try:
                job(*args)
            finally:
                with self._threads_lock:
                    self._threads.pop(key, None)

        thread = threading.Thread(target=body, name=name, daemon=True)
        with self._threads_lock:
            self._threads[key] = thread
        thread.start()

    def idle(self) -> bool:
        """True when no motion thread (capture run, validation) is alive: a paused or
        cancelled run's thread has ended its station in progress and captures nothing more."""
        with self._threads_lock:
            return not self._threads

    def stop_if_moving(self, key: str) -> None:
        """Stop the robot if the thread ``key`` is driving it."""
        with self._threads_lock:
            moving = key in self._threads
        devices = self.devices.current()
        if moving and devices is not None:
            devices[0].stop()

    def halt(self) -> None:
        """Stop the robot now and let no motion thread take another step (shutdown's first
        act; returns at once, the threads end their in-flight station by themselves)."""
        self.stopping.set()
        with self._threads_lock:
            moving = bool(self._threads)
        devices = self.devices.current()
        if moving and devices is not None:
            devices[0].stop()

    def shutdown(self, timeout: float = 10.0) -> None:
        """Stop the robot and wait for the motion threads to end, at most until ``timeout``
        s after the first call (a second call does not wait longer for a stuck thread)."""
        with self._threads_lock:
            if self._stop_deadline is None:
                self._stop_deadline = time.monotonic() + timeout
            deadline = self._stop_deadline
            threads = list(self._threads.values())
        self.halt()
        for thread in threads:
            thread.join(max(0.0, deadline - time.monotonic()))

    # ---- the workspace box -----------------------------------------------------------------

    def outside_workspace(self, pose: Any) -> str | None:
        """Why UR pose ``pose`` (6,) lies outside the workspace box, or None if inside."""
        lo = np.asarray(self.settings.workspace_min)
        hi = np.asarray(self.settings.workspace_max)
        p = np.asarray(pose[:3], dtype=float)
        if np.all(p >= lo) and np.all(p <= hi):
            return None
        mm = ", ".join(f"{v * 1e3:.0f}" for v in p)
        box = " x ".join(f"[{a * 1e3:.0f}, {b * 1e3:.0f}]" for a, b in zip(lo, hi, strict=True))
        return f"position ({mm}) mm is outside the workspace limits {box} mm (base frame)"

    def check_workspace(self, pose: np.ndarray) -> None:
        """Raise ``WorkspaceError`` for a commanded UR pose (6,) outside the workspace box."""
        if (outside := self.outside_workspace(pose)) is not None:
            raise WorkspaceError(f"Target {outside}; the robot was not moved.")


class MotionJobs:
    """Base of the two kinds of motion job (capture runs, validations): what each needs to
    move the robot, report progress and store results."""

    def __init__(self, motion: Motion, events: EventBus) -> None:
        self.motion = motion
        self.events = events
        self.settings = motion.settings
        self.db = motion.db
