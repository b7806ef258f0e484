"""What a report names as calibrated with what: the cell, the robot and camera, the board and
the station set. Built by the service (from the run's rows) and by ``cellcal report
--stations`` (from a station-set directory); read by ``service.results.report``."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ReportIdentity:
    """What was calibrated with what, as a signed report names it (``None``: not known, as
    from a robot driver that reports no serial or a result file without its station set)."""

    cell: str | None = None
    robot: str | None = None
    robot_model: str | None = None
    robot_serial: str | None = None
    controller_version: str | None = None
    camera: str | None = None
    #: the board's JSON description
    board: str | None = None
    #: how many stations, from where
    stations: str | None = None
    #: SHA-256 of the station set (``service.stationsets.format.station_set_sha256``)
    input_sha256: str | None = None
