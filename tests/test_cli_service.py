"""``cellcal runs`` and ``cellcal calibrations`` through the real command line (subprocesses)
against a real ``cellcal serve --mock``: start a run and follow it, calibrate it and follow
that, list, show, activate, export (the file the REST export gives), cancel; errors are one
line on stderr with a non-zero exit (service down, wrong key, unknown id)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from service.cli.answers import StateEvent
from service.cli.client import Event, parse_events
from service.cli.exit_codes import EXIT_FAILED
from service.serving.local import LocalService, listening_socket, local_service
from tests.support.cli import assert_one_line_error
from tests.support.helpers import ends_with_this_process

KEY = "cli-key-0123456789abcdef"

pytestmark = pytest.mark.timeout(600)


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LocalService]:
    with local_service(tmp_path_factory.mktemp("cli") / "data", KEY) as service:
        yield service


def cellcal(*args: str, url: str | None = None,
            key: str | None = KEY) -> subprocess.CompletedProcess[str]:
    """``cellcal ARGS`` in a subprocess; the service from CELLCAL_URL / CELLCAL_API_KEY."""
    env = {k: v for k, v in os.environ.items() if k not in ("CELLCAL_URL", "CELLCAL_API_KEY")}
    env |= {"CELLCAL_URL": url} if url else {}
    env |= {"CELLCAL_API_KEY": key} if key else {}
    return subprocess.run([sys.executable, "-m", "service.cli", *args], env=env,
                          capture_output=True, text=True, timeout=540, check=False,
                          preexec_fn=ends_with_this_process())


def rest(service: LocalService, path: str, **params: str) -> httpx.Response:
    r = httpx.get(service.url + path, params=params, timeout=60,
                  headers={"Authorization": f"Bearer {KEY}"})
    r.raise_for_status()
    return r


def test_run_calibrate_activate_export(served: LocalService, tmp_path: Path) -> None:
    url = served.url
    started = cellcal("runs", "start", "--stations", "6", "--wait", url=url)
    assert started.returncode == 0, started.stderr
    run_id = started.stdout.strip()
    run = rest(served, f"/runs/{run_id}").json()
    assert run["state"] == "done" and run["stations_planned"] == 6
    assert f"run {run_id}: done, {run['stations_captured']} captured" in started.stderr
    assert "6/6" in started.stderr  # the progress bar reached the planned stations

    shown = cellcal("runs", "show", run_id[:8], url=url)  # the short id the page shows
    assert shown.returncode == 0 and json.loads(shown.stdout) == run
    listed = cellcal("runs", "list", url=url)
    assert listed.stdout.splitlines()[0].split()[:3] == ["id", "state", "mode"]
    assert any(line.split()[:2] == [run_id, "done"] for line in listed.stdout.splitlines())

    calibrated = cellcal("calibrations", "start", run_id, "--wait", url=url)
    assert calibrated.returncode == 0, calibrated.stderr
    cal_id = calibrated.stdout.strip()
    cal = rest(served, f"/calibrations/{cal_id}").json()
    assert cal["state"] == "done"
    verdict = cal["result"]["quality"]["verdict"]
    assert f"calibration {cal_id}: done, verdict {verdict}" in calibrated.stderr

    assert json.loads(cellcal("calibrations", "show", cal_id[:8], url=url).stdout) == cal
    listed = cellcal("calibrations", "list", "--run", run_id, url=url).stdout.splitlines()
    assert [line.split()[:3] for line in listed[1:]] == [[cal_id, run_id, "done"]]
    rms = listed[1].split()[4]  # rounded, not 17 digits (issue 19)
    assert rms == f"{cal['result']['camera']['rms_px']:.3f}", listed

    activated = cellcal("calibrations", "activate", cal_id[:8], url=url)
    active = json.loads(cellcal("calibrations", "active", url=url).stdout)
    assert active["calibration"]["id"] == cal_id and active["robot"] == "mock://"
    assert activated.stdout == (f"calibration {cal_id} is the active {active['setup']} "
                                f"calibration of cell {active['cell']} (robot mock://)\n")
    elsewhere = cellcal("calibrations", "active", "--cell", "press-7", url=url)
    assert elsewhere.returncode != 0 and "press-7" in elsewhere.stderr  # 404: not this cell's
    assert len(json.loads(cellcal("calibrations", "active", "--history", "1",
                                  url=url).stdout)["history"]) == 1

    out = tmp_path / "camera.urdf"
    exported = cellcal("calibrations", "export", cal_id, "--format", "urdf", "--camera-name",
                       "cam", "--out", str(out), url=url)
    assert exported.returncode == 0, exported.stderr
    assert out.read_text() == rest(served, f"/calibrations/{cal_id}/export", format="urdf",
                                   camera_name="cam").text


def test_cancel_an_external_run(served: LocalService) -> None:
    started = cellcal("runs", "start", "--external", url=served.url)
    run_id = started.stdout.strip()
    assert rest(served, f"/runs/{run_id}").json()["mode"] == "external"
    cancelled = cellcal("runs", "cancel", run_id, url=served.url)
    assert cancelled.stdout == f"run {run_id}: cancelled\n"
    assert rest(served, f"/runs/{run_id}").json()["state"] == "cancelled"


def test_start_with_a_target(served: LocalService, tmp_path) -> None:
    """``cellcal runs start --target``, inline or from a file (issue 19)."""
    board = {"type": "checkerboard", "inner_corners": [9, 6], "square_size_m": 0.025}
    inline = cellcal("runs", "start", "--external", "--target", json.dumps(board),
                     url=served.url)
    assert inline.returncode == 0, inline.stderr
    run_id = inline.stdout.strip()
    assert rest(served, f"/runs/{run_id}").json()["target"]["inner_corners"] == [9, 6]
    cellcal("runs", "cancel", run_id, url=served.url)
    (tmp_path / "board.json").write_text(json.dumps(board | {"square_size_m": 30}))
    refused = cellcal("runs", "start", "--external", "--target", str(tmp_path / "board.json"),
                      url=served.url)
    assert refused.returncode == EXIT_FAILED
    assert_one_line_error(refused.stderr, "millimetres? 30 mm is 0.03 m")
    unreadable = cellcal("runs", "start", "--external", "--target", "{9, 6}", url=served.url)
    assert unreadable.returncode == 2
    assert_one_line_error(unreadable.stderr, "--target: not JSON")


def test_service_down_is_one_line() -> None:
    with listening_socket() as sock:
        url = f"http://127.0.0.1:{sock.getsockname()[1]}"
    done = cellcal("runs", "list", "--url", url)  # the flag, not CELLCAL_URL
    assert done.returncode == EXIT_FAILED
    assert_one_line_error(done.stderr, f"cannot reach the service at {url}")


def test_wrong_key_is_one_line(served: LocalService) -> None:
    done = cellcal("calibrations", "list", "--url", served.url, "--api-key", "wrong", key=None)
    assert done.returncode == EXIT_FAILED
    assert_one_line_error(done.stderr, "Invalid API key. (HTTP 401 invalid_api_key); give the "
                                       "service's key with "
                                       "--api-key or CELLCAL_API_KEY")


@pytest.mark.parametrize("args", [("runs", "show", "nope"), ("runs", "cancel", "nope"),
                                  ("calibrations", "export", "nope", "--format", "json")])
def test_unknown_id_is_one_line(served: LocalService, args: tuple[str, ...]) -> None:
    done = cellcal(*args, url=served.url)
    assert done.returncode == EXIT_FAILED and done.stdout == ""
    assert_one_line_error(done.stderr, "nope")
    assert "(HTTP 404 not_found)" in done.stderr


def test_a_failed_state_says_its_error_code() -> None:
    """A calibration's ``state`` event gives its error and code side by side, a run's as one
    ``{"detail", "code"}``: the line ``--wait`` prints names the code either way."""
    calibration = StateEvent.model_validate({"state": "failed", "error": "Disk full.",
                                             "error_code": "storage_unavailable"})
    run = StateEvent.model_validate({"state": "failed", "error": {
        "detail": "The robot stopped.", "code": "robot_disconnected"}})
    assert str(calibration.error) == "Disk full. (storage_unavailable)"
    assert str(run.error) == "The robot stopped. (robot_disconnected)"
    assert StateEvent.model_validate({"state": "done", "error": None}).error is None


def test_event_stream_lines_are_parsed() -> None:
    lines = ["id: 3", "event: state", 'data: {"state": "capturing"}', "", ": keep-alive", "",
             "id: 4", "event: station", 'data: {"index": 0}', ""]
    assert list(parse_events(iter(lines))) == [Event(3, "state", {"state": "capturing"}),
                                              Event(4, "station", {"index": 0})]


def test_a_tolerance_run_from_the_command_line(served: LocalService) -> None:
    """``runs start --tolerance-mm --tolerance-deg --wait``: the run plans from a cold start
    until the hand-eye's σ meets the tolerance or its station limit; the bar shows the σ."""
    started = cellcal("runs", "start", "--tolerance-mm", "2", "--tolerance-deg", "0.2",
                      "--max-stations", "8", "--wait", url=served.url)
    assert started.returncode == 0, started.stderr
    run = rest(served, f"/runs/{started.stdout.strip()}").json()
    cold = run["cold_start"]
    rule = cold["stop_rule"]
    assert (rule["tolerance_mm"], rule["tolerance_deg"], rule["max_stations"]) == (2.0, 0.2, 8)
    assert cold["stop_reason"] in ("tolerance_met", "max_stations")
    assert f"stopped: {cold['stop_reason']}" in started.stderr
    assert "tolerance 0.2° / 2 mm" in started.stderr  # the σ against the tolerance, live
    assert "90 % bound" in started.stderr
    half = cellcal("runs", "start", "--tolerance-mm", "2", url=served.url)
    assert half.returncode != 0
    assert_one_line_error(half.stderr, "--tolerance-mm and --tolerance-deg together")
