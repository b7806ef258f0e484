"""The station-set file format (``cellcal/stations@1``, product.md): schema and loading.

A station set is a directory with ``stations.json`` and the images it names. Each station carries
a robot pose (``tcp_pose``, T_base_tcp) and either an ``image`` or a measured ``target_pose``
(T_cam_target, pose-only hand-eye). Poses are UR vectors in metres and radians.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
import zipfile
from collections import Counter
from collections.abc import Iterable
from pathlib import Path
from typing import Annotated, Any, Literal

import cv2
import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from calib import FiniteFloat, Station, Stations, Target, TargetAdapter, check_ur_vector
from drivers.config_files import describe_validation_error

STATIONS_FILE = "stations.json"
#: Default largest station count of a set; every stage scales linearly up to it.
DEFAULT_MAX_STATIONS = 50_000
#: ``stations.json`` bytes allowed per station (a pose-only station takes about 250).
FILE_BYTES_PER_STATION = 2048

PoseVector = Annotated[list[FiniteFloat], Field(min_length=6, max_length=6)]


class Intrinsics(BaseModel):
    model_config = ConfigDict(extra="forbid")
    K: Annotated[list[Annotated[list[FiniteFloat], Field(min_length=3, max_length=3)]],
                 Field(min_length=3, max_length=3)]
    dist: Annotated[list[FiniteFloat], Field(min_length=4, max_length=14)]


class StationEntry(BaseModel):
    model_config = ConfigDict(extra="forbid")
    id: str
    tcp_pose: PoseVector | None = None
    image: str | None = None
    target_pose: PoseVector | None = None
    #: How the capture made sure the image was exposed after the robot had settled.
    freshness: str | None = None

    @field_validator("tcp_pose", "target_pose")
    @classmethod
    def _plausible_pose(cls, pose: list[float] | None,
                        info: ValidationInfo) -> list[float] | None:
        """Metres and radians, checked when the file is read (before any image is)."""
        if pose is not None:
            check_ur_vector(pose, str(info.field_name))
        return pose

    @model_validator(mode="after")
    def _one_observation(self) -> StationEntry:
        if (self.image is None) == (self.target_pose is None):
            raise ValueError("a station carries either an 'image' or a 'target_pose'")
        return self


class StationSet(BaseModel):
    model_config = ConfigDict(extra="forbid")
    format: Literal["cellcal/stations@1"]
    setup: Literal["eye_in_hand", "eye_to_hand"] = "eye_in_hand"
    target: Target | None = None
    intrinsics: Intrinsics | None = None
    stations: Annotated[list[StationEntry], Field(min_length=1)]

    @model_validator(mode="after")
    def _consistent(self) -> StationSet:
        dup = sorted(i for i, k in Counter(s.id for s in self.stations).items() if k > 1)
        if dup:
            raise ValueError(f"station ids must be unique, repeated: {', '.join(dup)}")
        if any(s.image for s in self.stations) and self.target is None:
            raise ValueError("stations with images need a 'target' description")
        return self

    def model(self) -> Stations:
        """The file's stations as the one station model (``calib.Stations``); images stay
        references relative to the set's directory."""
        return Stations(
            setup=self.setup, target=self.target,
            intrinsics=None if self.intrinsics is None else (np.asarray(self.intrinsics.K),
                                                             np.asarray(self.intrinsics.dist)),
            stations=tuple(Station(id=s.id, T_base_tcp=_vector(s.tcp_pose), image=s.image,
                                   T_cam_target=_vector(s.target_pose),
                                   freshness=s.freshness)
                           for s in self.stations))


def _vector(pose: list[float] | None) -> np.ndarray | None:
    return None if pose is None else np.asarray(pose, dtype=float)


def load_station_set(directory: str | Path, *,
                     max_stations: int = DEFAULT_MAX_STATIONS) -> StationSet:
    """Read and validate ``DIR/stations.json``; raise ``ValueError`` with one clear line.

    The file size is checked before it is read and the station count before the stations are
    validated, so an oversized set costs neither memory nor time.
    """
    path = Path(directory) / STATIONS_FILE
    if not path.is_file():
        raise ValueError(f"{path}: " + ("not a regular file" if path.exists() else
                                        "no such file (a station set is a directory with "
                                        "stations.json)"))
    max_bytes = FILE_BYTES_PER_STATION * max_stations
    if path.stat().st_size > max_bytes:
        raise ValueError(f"{path}: {path.stat().st_size / 1e6:.0f} MB, more than the "
                         f"{max_bytes / 1e6:.0f} MB allowed for {max_stations} stations")
    try:
        raw = json.loads(path.read_text())
    except (ValueError, RecursionError) as exc:  # also too many digits, nested too deep
        raise ValueError(f"{path}: not valid JSON ({exc})") from None
    n = len(raw["stations"]) if isinstance(raw, dict) and isinstance(raw.get("stations"),
                                                                     list) else 0
    if n > max_stations:
        raise ValueError(f"{path}: {n} stations, more than the {max_stations} allowed "
                         "(--max-stations)")
    try:
        return StationSet.model_validate(raw)
    except ValidationError as exc:
        raise ValueError(f"{path}: {describe_validation_error(exc)}") from None


def station_record(station: Station, image_name: str) -> dict[str, Any]:
    """The ``stations.json`` entry of a station with an image (``tcp_pose`` and
    ``freshness`` when known)."""
    record: dict[str, Any] = {"id": station.id}
    if station.T_base_tcp is not None:
        record["tcp_pose"] = [float(v) for v in station.T_base_tcp]
    record["image"] = image_name
    if station.freshness is not None:
        record["freshness"] = station.freshness
    return record


def station_set_document(stations: Stations) -> tuple[str, list[str]]:
    """The ``stations.json`` text of ``stations`` and its image names (``000.png``, ...
    in station order), validated (``ValueError`` with one clear line)."""
    names = [f"{k:03d}.png" for k in range(len(stations.stations))]
    doc: dict[str, Any] = {"format": "cellcal/stations@1", "setup": stations.setup,
                           "target": None if stations.target is None
                           else TargetAdapter.dump_python(stations.target, mode="json")}
    if stations.intrinsics is not None:
        K, dist = stations.intrinsics
        doc["intrinsics"] = {"K": np.asarray(K).tolist(), "dist": np.asarray(dist).tolist()}
    doc["stations"] = [station_record(s, n)
                       for s, n in zip(stations.stations, names, strict=True)]
    try:
        StationSet.model_validate(doc)
    except ValidationError as exc:
        raise ValueError(f"cannot write a station set: {describe_validation_error(exc)}") \
            from None
    return json.dumps(doc, indent=2) + "\n", names


def station_set_sha256(index: bytes, images: Iterable[Path]) -> str:
    """The input checksum a report carries: SHA-256 of a station set's ``stations.json``
    bytes followed by each image file in the order it names them (a missing file counts as
    ``missing:NAME``). The service computes it of the set it would download, the CLI of the
    directory, so the two agree on the same stations."""
    digest = hashlib.sha256(index)
    for path in images:
        try:
            digest.update(path.read_bytes())
        except OSError:
            digest.update(b"missing:" + path.name.encode())
    return digest.hexdigest()


def captured_set_sha256(stations: Stations, *, source: str | Path) -> str:
    """:func:`station_set_sha256` of the set :func:`write_station_set` would write of
    ``stations``, whose images are PNG files relative to ``source``."""
    text, _ = station_set_document(stations)
    return station_set_sha256(text.encode(), (Path(source) / str(s.image)
                                              for s in stations.stations))


def write_station_set(directory: str | Path, stations: Stations, *,
                      source: str | Path | None = None) -> Path:
    """Write ``stations`` (each with an image) as a station set in ``directory``; return the
    ``stations.json`` path.

    Images are ``000.png``, ``001.png``, ... in station order: a station's ``image`` is either
    its pixels (written as PNG) or a PNG file relative to ``source`` (copied byte for byte, so
    a calibration of the set detects exactly what the service detected). The document is
    validated before anything is written (``ValueError``), an existing ``stations.json`` is
    never overwritten (``FileExistsError``), and ``stations.json`` is written last,
    atomically, so an interrupted write never leaves a readable but incomplete set.
    """
    directory = Path(directory)
    path = directory / STATIONS_FILE
    text, names = station_set_document(stations)
    if path.exists():
        raise FileExistsError(f"{path} already exists; choose a new directory for the capture")
    directory.mkdir(parents=True, exist_ok=True)
    for station, name in zip(stations.stations, names, strict=True):
        _write_image(directory / name, station, source)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)
    return path


def _write_image(path: Path, station: Station, source: str | Path | None) -> None:
    """A station's image at ``path``: its pixels as PNG, or its PNG file copied."""
    if isinstance(station.image, str):
        if source is None:
            raise ValueError(f"station {station.id}: its image is a file, {station.image!r}, "
                             "but no source directory was given")
        shutil.copyfile(Path(source) / station.image, path)
    elif station.image is None or not cv2.imwrite(str(path), station.image):
        raise OSError(f"could not write {path}" + (f": station {station.id} has no image"
                                                    if station.image is None else ""))


def zip_station_set(path: str | Path, stations: Stations, *, source: str | Path) -> Path:
    """Write ``stations`` as a station set into the zip file ``path`` (``stations.json`` and
    the images at its top level; see :func:`write_station_set`); return ``path``."""
    path = Path(path)
    with tempfile.TemporaryDirectory(dir=path.parent) as tmp:
        written = write_station_set(Path(tmp) / "set", stations, source=source).parent
        with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as archive:  # PNGs are compressed
            for file in sorted(written.iterdir()):
                archive.write(file, file.name)
    return path
