"""``cellcal export`` and ``cellcal --version``: the files are the ones the service exports,
and what cannot be exported fails with one line on stderr and a non-zero status."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from service.cli.exit_codes import EXIT_FAILED, EXIT_USAGE
from service.cli.main import main
from service.exports import FORMATS, ExportNames, export
from service.version import software_version
from tests.support.results import full_result, intrinsics_only_result


def write(tmp_path: Path, doc: Any, name: str = "result.json") -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.parametrize("fmt", FORMATS)
def test_each_format_is_the_service_export(tmp_path: Path, fmt: str) -> None:
    result = full_result()
    out = tmp_path / "out"
    assert main(["export", str(write(tmp_path, result)), "--format", fmt, "--out",
                 str(out)]) == 0
    assert out.read_text() == export(result, fmt)[0]


def test_names_and_stdout(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write(tmp_path, full_result())
    assert main(["export", str(path), "--format", "ros2-static-tf", "--camera-name", "cam2",
                 "--parent-frame", "flange", "--child-frame", "cam2_optical"]) == 0
    names = ExportNames("cam2", parent_frame="flange", child_frame="cam2_optical")
    assert capsys.readouterr().out == export(full_result(), "ros2-static-tf", names)[0]


def test_intrinsics_only_result_exports_what_it_has(tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    path = write(tmp_path, intrinsics_only_result())
    assert main(["export", str(path), "--format", "ros-camera-info"]) == 0
    assert capsys.readouterr().out.startswith("image_width: 1280\n")
    assert main(["export", str(path), "--format", "urdf", "--out",
                 str(tmp_path / "x.urdf")]) == EXIT_USAGE
    err = capsys.readouterr().err
    assert err == ("cellcal: error: format 'urdf' needs a hand-eye transform, but this result "
                   "has none (intrinsics-only calibration): export it as json, opencv-yaml, "
                   "ros-camera-info\n")
    assert not (tmp_path / "x.urdf").exists()


@pytest.mark.parametrize(("content", "status", "message"), [
    ("{not json", EXIT_USAGE, "not JSON"),
    # issue 22, variants of its bad inputs (an internal error before): nested too deep for
    # the parser, an integer of more digits than Python converts
    ("[" * 100_000 + "]" * 100_000, EXIT_USAGE, "not JSON (maximum recursion depth"),
    ('{"format": ' + "9" * 5000 + "}", EXIT_USAGE, "not JSON (Exceeds the limit"),
    ('{"format": "cellcal/stations@1"}', EXIT_USAGE, "not a cellcal result"),
    ("[1, 2]", EXIT_USAGE, "not a cellcal result"),
    (None, EXIT_FAILED, "No such file"),
])
def test_bad_result_files_fail_with_one_line(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str],
                                             content: str | None, status: int,
                                             message: str) -> None:
    path = tmp_path / "result.json"
    if content is not None:
        path.write_text(content)
    assert main(["export", str(path), "--format", "json"]) == status
    err = capsys.readouterr().err
    assert err.startswith("cellcal: error: ") and message in err and err.count("\n") == 1


def test_bad_frame_name_is_a_usage_error(tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    path = write(tmp_path, full_result())
    assert main(["export", str(path), "--format", "urdf", "--child-frame", "a b"]) == EXIT_USAGE
    assert "child frame 'a b'" in capsys.readouterr().err


def test_version() -> None:
    r = subprocess.run([sys.executable, "-m", "service.cli", "--version"], capture_output=True,
                       text=True, timeout=60, check=False)
    assert r.returncode == 0, r.stderr
    assert r.stdout == f"cellcal {software_version()}\n"
    assert software_version() not in ("", "unknown")
