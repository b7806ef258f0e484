"""The service's long-lived objects, built once per app (and by the service benchmark):
database, devices, event bus, the robot's motion jobs, runs, calibrations, validations."""

from __future__ import annotations

import logging
from dataclasses import dataclass

from service import store
from service.calibrations import Calibrations
from service.db import Database
from service.devices import DeviceOpener, Devices, settings_opener
from service.events import EventBus
from service.motion import Motion
from service.runs import RunManager
from service.settings import Settings
from service.validations import Validations

log = logging.getLogger("cellcal.service")


@dataclass(frozen=True)
class Runtime:
    """Everything a request or a background job works with."""

    settings: Settings
    db: Database
    devices: Devices
    events: EventBus
    motion: Motion
    runs: RunManager
    calibrations: Calibrations
    validations: Validations

    @classmethod
    def open(cls, settings: Settings, open_devices: DeviceOpener | None = None) -> Runtime:
        """Open the database and recover from a previous service's death; devices open on
        first use (``open_devices`` replaces opening ``settings.robot`` / ``camera``)."""
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        db = Database(settings.database, busy_timeout_s=settings.database_busy_timeout_s)
        devices = Devices(open_devices or settings_opener(settings))
        events = EventBus(db)
        motion = Motion(settings, db, devices)
        with db.session() as s:
            runs, cals, vals = store.recover(s)
        if runs or cals or vals:
            log.warning("recovered after restart: %d run(s) interrupted, %d calibration(s) "
                        "and %d validation(s) failed", runs, cals, vals)
        return cls(settings=settings, db=db, devices=devices, events=events, motion=motion,
                   runs=RunManager(motion, events), calibrations=Calibrations(settings, db, events),
                   validations=Validations(motion, events))

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
        """Stop the jobs, close the devices and the database."""
        self.stop_jobs()
        self.devices.close()
        self.db.close()
