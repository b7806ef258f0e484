"""``cellcal demo`` end to end, as a user runs it: a subprocess that starts the service in its
own subprocess; afterwards neither the service nor its data may be left behind."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.support.helpers import ends_with_this_process

REPO = Path(__file__).resolve().parents[1]
DEMO = [sys.executable, "-m", "service.cli", "demo"]
SERVICE_LINE = re.compile(r"^service: (http://127\.0\.0\.1:\d+) .*data in (\S+), removed on exit",
                          re.MULTILINE)


@pytest.fixture
def reaped() -> Iterator[list[subprocess.Popen[str]]]:
    """Demo processes started by a test; killed if a test leaves one running."""
    procs: list[subprocess.Popen[str]] = []
    yield procs
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)  # the demo stops its service on SIGTERM
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def _ctrl_c_reaches_it() -> None:
    """Default SIGINT in the demo, as in a terminal: a shell that runs the test suite in the
    background starts it with SIGINT ignored, and the demo would inherit that."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def start(reaped: list[subprocess.Popen[str]], *args: str) -> subprocess.Popen[str]:
    proc = subprocess.Popen([*DEMO, *args], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "COLUMNS": "100"},
                            preexec_fn=ends_with_this_process(signal.SIGTERM,
                                                              then=_ctrl_c_reaches_it))
    reaped.append(proc)
    return proc


def assert_gone(url: str, data: str) -> None:
    """The service no longer answers and its data directory is removed."""
    with pytest.raises(httpx.TransportError):
        httpx.get(f"{url}/health", timeout=2)
    assert not Path(data).exists()


# The timeouts only catch a hang: under load the demo runs several times slower than idle.
@pytest.mark.timeout(600)
def test_demo_runs_the_service_flow(tmp_path: Path,
                                    reaped: list[subprocess.Popen[str]]) -> None:
    proc = start(reaped, "--out", str(tmp_path / "out"))
    out, err = proc.communicate(timeout=540)
    assert proc.returncode == 0, err
    url, data = SERVICE_LINE.search(err).groups()  # type: ignore[union-attr]
    assert_gone(url, data)
    assert "capturing: 100%" in err and "15/15" in err
    assert "15 stations captured" in out
    for line in ("hand-eye", "intrinsics", "board scale     κ", "board aspect    ν",
                 "Dot-hit validation (SM eq. 24)", "Wall time"):
        assert line in out, out
    mm = [float(v) for v in re.findall(r"^    (?:corner_\d+_\d+|centre) +([\d.]+) mm$", out,
                                       re.MULTILINE)]
    assert len(mm) == 5 and max(mm) < 1.0, out
    result = json.loads((tmp_path / "out" / "calibration.json").read_text())
    assert result["format"] == "cellcal/result@1"
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        "calibration.json", "camera_calibration.yaml", "camera_info.yaml",
        "camera_joint.urdf", "camera_static_tf.launch.py", "hand_eye_ur_pose.txt"]
    assert f"Result: {tmp_path / 'out' / 'calibration.json'}" in out
    # the last line says the verdict and, for a warn, what was found (issue 19)
    quality = result["quality"]
    last = out.rstrip().splitlines()[-1]
    assert last.startswith(f"Verdict {quality['verdict']}"), last
    for finding in quality["findings"] if quality["verdict"] != "pass" else []:
        if finding["severity"] != "info":
            assert f"[{finding['code']}]" in last, last


@pytest.mark.timeout(300)
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_interrupted_demo_stops_the_service_and_removes_its_data(
        tmp_path: Path, reaped: list[subprocess.Popen[str]], sig: signal.Signals) -> None:
    proc = start(reaped, "--out", str(tmp_path / "out"))
    assert proc.stderr is not None
    first = proc.stderr.readline()  # printed once the service answers
    match = SERVICE_LINE.match(first)
    assert match, first
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=180)
    assert proc.returncode == 130, err
    assert err.rstrip().endswith("cellcal: interrupted")
    assert_gone(*match.groups())


@pytest.mark.timeout(300)
def test_a_bad_scene_is_one_error_line(tmp_path: Path,
                                       reaped: list[subprocess.Popen[str]]) -> None:
    scene = tmp_path / "scene.json"
    scene.write_text('{"format": "cellcal/scene@1"}')
    proc = start(reaped, "--scene", str(scene), "--out", str(tmp_path / "out"))
    out, err = proc.communicate(timeout=240)
    assert proc.returncode == 1
    assert out == ""
    assert err.startswith("cellcal: error: demo: the service exited at startup: configuration: "
                          f"CELLCAL_SCENE: scene {scene}: camera: Field required")
    assert err.count("\n") == 1
