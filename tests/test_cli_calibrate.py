import json
import subprocess
import sys

import numpy as np
import pytest

from calib.geometry import pose_error
from mocks.posesim import default_cell, simulate
from service.cli.main import main
from tests.support.stations import write_station_set


@pytest.fixture
def cell_data():
    cell = default_cell("eye_in_hand")
    P, C = simulate(cell, 12, np.random.default_rng(3))
    return cell, P, C


@pytest.mark.parametrize("method", ["refine", "sm", "park", "shah"])
def test_calibrate_writes_a_result(tmp_path, cell_data, method):
    cell, P, C = cell_data
    d = write_station_set(tmp_path / "set", P, C)
    out = tmp_path / "result.json"
    assert main(["calibrate", str(d), "--out", str(out), "--method", method]) == 0
    doc = json.loads(out.read_text())
    assert doc["format"] == "cellcal/result@1" and doc["method"] == method
    X = np.array(doc["hand_eye"]["matrix"])
    dr, dt = pose_error(X, cell.hand_eye)
    assert dr < np.deg2rad(0.1) and dt < 1e-3
    assert len(doc["stations"]) == 12
    assert doc["software"]["version"]
    if method == "refine":
        assert len(doc["uncertainty"]["hand_eye_trans_m"]) == 3


def test_calibrate_to_stdout(tmp_path, cell_data, capsys):
    _, P, C = cell_data
    d = write_station_set(tmp_path / "set", P, C)
    assert main(["calibrate", str(d)]) == 0
    assert json.loads(capsys.readouterr().out)["setup"] == "eye_in_hand"


def _nan(doc):
    doc["stations"][3]["tcp_pose"][1] = float("nan")


def _mm(doc):
    for s in doc["stations"]:
        s["tcp_pose"][:3] = [1000.0 * v for v in s["tcp_pose"][:3]]


def _deg(doc):
    doc["stations"][2]["tcp_pose"][3:] = [float(np.rad2deg(v)) for v in
                                          doc["stations"][2]["tcp_pose"][3:]]


def _two(doc):
    doc["stations"] = doc["stations"][:2]


def _both(doc):
    doc["stations"][0]["image"] = "000.png"


def _dup(doc):
    doc["stations"][1]["id"] = doc["stations"][0]["id"]


def _fmt(doc):
    doc["format"] = "other@1"


@pytest.mark.parametrize("mutate, message", [
    (_nan, r"stations\[3\]\.tcp_pose\[1\]: Input should be a finite number"),
    (_mm, r"stations\[0\]\.tcp_pose: tcp_pose translation is .* m, more than 20 m: "
          r".*millimetres"),
    (_deg, r"stations\[2\]\.tcp_pose: tcp_pose rotation vector has norm 1.*, more than π "
           r"rad: .*radians \(were degrees given\?\)"),
    (_two, r"need at least 3 stations, got 2"),
    (_both, r"stations\[0\]: a station carries either an 'image' or a"),
    (_dup, r"station ids must be unique, repeated: 000"),
    (_fmt, r"format: Input should be 'cellcal/stations@1'"),
])
def test_bad_station_sets_give_one_line(tmp_path, cell_data, capsys, mutate, message):
    _, P, C = cell_data
    d = write_station_set(tmp_path / "set", P, C, mutate=mutate)
    assert main(["calibrate", str(d)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("cellcal: error: ") and err.count("\n") == 1
    assert __import__("re").search(message, err), err


def test_missing_directory_and_bad_json(tmp_path, capsys):
    assert main(["calibrate", str(tmp_path / "nope")]) == 2
    assert "stations.json: no such file" in capsys.readouterr().err
    (tmp_path / "stations.json").write_text("{not json")
    assert main(["calibrate", str(tmp_path)]) == 2
    assert "not valid JSON" in capsys.readouterr().err


def test_unknown_method_is_a_usage_error(tmp_path, cell_data):
    _, P, C = cell_data
    d = write_station_set(tmp_path / "set", P, C)
    proc = subprocess.run([sys.executable, "-m", "service.cli", "calibrate", str(d),
                           "--method", "magic"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert "invalid choice: 'magic'" in proc.stderr and "Traceback" not in proc.stderr


def test_joint_needs_images(tmp_path, cell_data, capsys):
    """``joint`` is the corner-level maximum likelihood; a pose-only set has no corners."""
    _, P, C = cell_data
    d = write_station_set(tmp_path / "set", P, C)
    assert main(["calibrate", str(d), "--method", "joint"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "needs images" in err and "'refine'" in err


def test_degenerate_set_through_the_console_script(tmp_path):
    # all stations rotate about one axis
    rng = np.random.default_rng(0)
    from scipy.spatial.transform import Rotation

    from calib.geometry import invert, make_transform
    R = Rotation.from_rotvec(np.outer(np.deg2rad([0, 30, 60, 90]), [0, 0, 1])).as_matrix()
    P = make_transform(R, rng.normal(0, 0.3, (4, 3)))
    C = invert(P)
    d = write_station_set(tmp_path / "set", P, C)
    proc = subprocess.run([sys.executable, "-m", "service.cli", "calibrate", str(d)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert proc.stderr.strip() == ("cellcal: error: rotation axes of all motions are parallel "
                                   "within 2 deg: add stations tilted about another axis")


def test_demo_runs(capsys):
    assert main(["demo", "--poses-only", "--stations", "8"]) == 0
    out = capsys.readouterr().out
    assert "refine" in out and "hand-eye err" in out


def test_verdict_line_gives_the_honest_figure_and_names_dropped_stations():
    from calib import CrossValidationBlock, QualityBlock
    from service.cli.calibrate import verdict_line
    stations = [{"id": f"{k:02d}"} for k in range(5)]
    cv = {"kind": "k-fold", "folds": 5, "rms_px": 2.07, "rms_mm": 1.1, "kept_rms_px": 0.48,
          "dropped": ["01", "03"], "stations": stations}
    quality = QualityBlock(verdict="warn")
    assert verdict_line(quality, CrossValidationBlock.model_validate(cv)) == (
        "cellcal: verdict warn: cross-validated error 2.07 px (1.10 mm at the board), k-fold "
        "over 5 stations; 0.48 px over the 3 kept stations, dropped as outliers: 01, 03")
    cv.update(dropped=[], kept_rms_px=2.07)
    assert verdict_line(quality, CrossValidationBlock.model_validate(cv)).endswith(
        "k-fold over 5 stations")
