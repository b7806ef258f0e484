"""The service's long-lived objects, built once per app (and by the service benchmark):
database, devices, event bus, the robot's motion jobs, runs, calibrations, validations."""

from __future__ import annotations

import logging
from dataclasses import dataclass

from service.cell.devices import DeviceOpener, Devices, settings_opener
from service.cell.motion import Motion
from service.events import EventBus
from service.jobs.calibrations import Calibrations
from service.jobs.outcomes import Outcomes
from service.jobs.validations import Validations
from service.runs import RunManager
from service.settings import Settings
from service.store.db import Database
from service.store.instances import InstanceLease
from service.store.storage import Storage

log = logging.getLogger("cellcal.service")


@dataclass(frozen=True)
class Runtime:
    """Everything a request or a background job works with."""

    settings: Settings
    db: Database
    instance: InstanceLease
    devices: Devices
    events: EventBus
    motion: Motion
    outcomes: Outcomes
    runs: RunManager
    calibrations: Calibrations
    validations: Validations

    @classmethod
    def open(cls, settings: Settings, open_devices: DeviceOpener | None = None) -> Runtime:
        """Open the database, register this instance and recover the work of this cell's
        dead services; devices open on first use (``open_devices`` replaces opening
        ``settings.robot`` / ``camera``)."""
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        db = Database(settings.database, busy_timeout_s=settings.database_busy_timeout_s)
        instance = InstanceLease(settings, db)
        devices = Devices(open_devices or settings_opener(settings))
        events = EventBus(db, instance.id)
        storage = Storage(settings)
        outcomes = Outcomes(settings, db, events, storage)
        if spooled := outcomes.recover():  # before dead services' jobs are marked failed
            log.warning("stored %d outcome(s) spooled during a database outage", spooled)
        instance.start()  # recovers the work of this cell's dead services first
        motion = Motion(settings, db, devices, instance.id, storage)
        return cls(settings=settings, db=db, instance=instance, devices=devices, events=events,
                   motion=motion, outcomes=outcomes, runs=RunManager(motion, events),
                   calibrations=Calibrations(settings, db, events, instance.id, outcomes),
                   validations=Validations(motion, events, outcomes))

    def halt(self) -> None:
        """Stop the robot now; no motion job takes another step (returns at once)."""
        self.motion.halt()

    def stop_jobs(self, timeout: float = 10.0) -> None:
        """Stop the robot and the motion threads (runs become ``interrupted``, validations
        ``failed``), and cancel queued calibrations."""
        self.motion.shutdown(timeout)
        self.calibrations.shutdown()
        self.runs.external.images.shutdown()

    def close(self) -> None:
        """Stop the jobs, close the devices, leave the instances and close the database."""
        self.stop_jobs()
        self.outcomes.close()
        self.devices.close()
        self.events.close()
        self.instance.close()
        self.db.close()
