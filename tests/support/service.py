"""The service under test: an app with an API key on a temporary data directory and
database, mock devices (optionally with a camera held at a grab), runs started and
waited for, event streams and calibrations read back."""

from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from functools import cache
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from calib.geometry import ur_pose_from_matrix
from drivers.base import Camera, Robot
from mocks.scene import default_scene, sample_station_poses
from service.app import create_app
from service.cell.devices import DeviceOpener, settings_opener
from service.settings import Settings
from tests.support.helpers import wait_for

KEY = "test-key-0123456789abcdef"
#: The cell of the services here (the default CELLCAL_CELL).
CELL = socket.gethostname()
AUTH = {"Authorization": f"Bearer {KEY}"}


@cache
def _poses(n: int) -> tuple[tuple[float, ...], ...]:
    T = sample_station_poses(default_scene(), n, np.random.default_rng(3))
    return tuple(tuple(p) for p in ur_pose_from_matrix(T).tolist())


def poses(n: int) -> list[list[float]]:
    """``n`` valid stations of the default mock cell (the board is in view in each)."""
    return [list(p) for p in _poses(n)]


def settings(tmp_path: Path, **overrides: Any) -> Settings:
    return Settings(data_dir=tmp_path, api_key=KEY, **overrides)


@contextmanager
def service(tmp_path: Path, open_devices: DeviceOpener | None = None) -> Iterator[TestClient]:
    """An authorised client of a service on ``tmp_path`` (its database and images), with the
    mock devices of ``settings(tmp_path)`` unless ``open_devices`` says otherwise."""
    with TestClient(create_app(settings(tmp_path), open_devices=open_devices)) as c:
        c.headers.update(AUTH)
        yield c


def finished(doc: dict[str, Any]) -> bool:
    """A run no longer capturing, a calibration or validation no longer running."""
    return doc["state"] not in ("capturing", "running")


def wait_doc(client: httpx.Client, path: str,
             until: Callable[[dict[str, Any]], bool] = finished, timeout: float = 120.0, *,
             first: float = 0.05) -> dict[str, Any]:
    """Poll ``GET path`` until ``until(doc)`` (by default: ``finished``) and return the
    document; ``timeout`` only catches a stuck run or job (generous: a loaded machine
    captures and solves several times slower)."""
    return wait_for(path, lambda: client.get(path).json(), timeout, until=until, first=first)


def wait_run(client: httpx.Client, run_id: str, until: Callable[[dict[str, Any]], bool],
             timeout: float = 60.0) -> dict[str, Any]:
    """Poll ``GET /runs/{id}`` until ``until(run)``."""
    return wait_doc(client, f"/runs/{run_id}", until, timeout)


def start_run(client: TestClient, n: int) -> str:
    r = client.post("/runs", json={"poses": poses(n)})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def gated_opener(tmp_path: Path, index: int, gate: threading.Event) -> DeviceOpener:
    """The mock devices of ``settings(tmp_path)`` with the camera held at grab ``index``."""
    mocks = settings_opener(settings(tmp_path))

    def gated() -> tuple[Robot, Camera]:
        robot, camera = mocks()
        return robot, GatedCamera(camera, index, gate)  # type: ignore[return-value]

    return gated


class GatedCamera:
    """A camera whose grabs after the first ``free`` wait for ``gate`` (a hung device)."""

    def __init__(self, camera: Camera, free: int, gate: threading.Event) -> None:
        self.camera, self.free, self.gate = camera, free, gate

    def grab(self, *, timeout: float = 2.0) -> np.ndarray:
        self.free -= 1
        if self.free < 0:
            assert self.gate.wait(20.0)
        return self.camera.grab(timeout=timeout)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.camera, name)


Event = tuple[int, str, dict[str, Any]]


def read_events(client: TestClient, run_id: str, *,
                last_event_id: str | bytes | None = None,
                until: Callable[[list[Event]], bool] = lambda events: False,
                path: str = "/runs/{}/events") -> list[Event]:
    """Events ``(id, type, data)`` of the stream at ``path`` (a run's by default) until it
    ends or ``until(events)``, then disconnect."""
    headers = {} if last_event_id is None else {"Last-Event-ID": last_event_id}
    events: list[Event] = []
    fields: dict[str, str] = {}
    with client.stream("GET", path.format(run_id), headers=headers) as r:
        assert r.status_code == 200
        for line in r.iter_lines():
            if line.startswith(":"):
                continue
            if line:
                key, _, value = line.partition(": ")
                fields[key] = value
                continue
            if not fields:  # the blank line that ends a keep-alive comment
                continue
            events.append((int(fields["id"]), fields["event"], json.loads(fields["data"])))
            fields = {}
            if until(events):
                break
    return events


def external_run(client: TestClient, **body: Any) -> str:
    r = client.post("/runs", json={"mode": "external", **body})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def post(client: TestClient, run_id: str, *, pose: Any = None, joints: Any = None,
         image: bytes | None = None) -> Any:
    """POST a station; form fields only for what is given (a bare POST for nothing)."""
    data = {k: json.dumps(v) for k, v in (("pose", pose), ("joints", joints)) if v is not None}
    files = None if image is None else {"image": ("station.png", image, "image/png")}
    return client.post(f"/runs/{run_id}/stations", data=data or None, files=files)


def robot_pose(client: TestClient) -> list[float]:
    return client.get("/devices").json()["robot"]["tcp_pose"]


def wait_calibration(client: httpx.Client, cal_id: str, timeout: float = 120.0
                     ) -> dict[str, Any]:
    """The calibration once it has left ``running``."""
    return wait_doc(client, f"/calibrations/{cal_id}", finished, timeout, first=0.1)


def get_report(client: TestClient, cal_id: str, timeout: float = 240.0) -> Any:
    """``GET /calibrations/{id}/report`` as a client should ask: a 503 ``report_rendering``
    (the page still being rendered) is asked again after its ``Retry-After``; ``timeout``
    only catches a rendering that never ends."""
    deadline = time.monotonic() + timeout
    while (r := client.get(f"/calibrations/{cal_id}/report")).status_code == 503 \
            and r.json()["code"] == "report_rendering":
        assert time.monotonic() < deadline, f"the report is still being rendered: {r.text}"
        time.sleep(int(r.headers["Retry-After"]))
    return r


def assert_same_calibration(a: dict[str, Any], b: dict[str, Any], atol: float = 1e-9) -> None:
    """Two result documents agree on the camera, κ, ν, the hand-eye and the target pose."""
    for key in ("K", "dist"):
        np.testing.assert_allclose(a["camera"][key], b["camera"][key], rtol=0, atol=atol)
    for key in ("kappa", "nu"):
        assert a["target"][key] == pytest.approx(b["target"][key], rel=0, abs=atol)
    for key in ("hand_eye", "target_pose"):
        np.testing.assert_allclose(a[key]["matrix"], b[key]["matrix"], rtol=0, atol=atol)
