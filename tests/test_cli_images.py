"""``cellcal calibrate`` on station sets with images: full result, rejected files, errors."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from calib.geometry import pose_error
from calib.result import parse_result
from service.cli.main import main
from tests.support.helpers import undeclared_fields
from tests.support.stations import N_IMAGES, SCENE, write_image_set


def test_image_set_gives_the_full_result(tmp_path, capsys):
    d = write_image_set(tmp_path / "set")
    # a truncated JPEG, a truncated PNG, a file that is no image, a missing file
    (d / "001.jpg").write_bytes((d / "001.jpg").read_bytes()[:5000])
    (d / "002.png").write_bytes((d / "002.png").read_bytes()[:20000])
    (d / "003.png").write_text("not an image")
    (d / "004.png").unlink()
    out = tmp_path / "result.json"
    assert main(["calibrate", str(d), "--out", str(out), "--kappa", "estimate"]) == 0
    doc = json.loads(out.read_text())
    rejected = {r["id"]: r["reason"] for r in doc["rejected"]}
    assert rejected == {
        "001": "image file '001.jpg' is truncated (incomplete copy or interrupted capture?)",
        "002": "image file '002.png' is truncated (incomplete copy or interrupted capture?)",
        "003": "image file '003.png' is not a readable image (PNG or JPEG expected)",
        "004": "cannot read image file '004.png': No such file or directory"}
    assert doc["format"] == "cellcal/result@1" and doc["method"] == "joint"
    assert undeclared_fields(parse_result(doc)) == []  # the schema documents every field
    cam = doc["camera"]
    assert cam["image_size"] == list(SCENE.camera.image_size) and len(cam["dist"]) == 5
    assert np.abs(np.array(cam["K"]) - SCENE.camera.k_matrix).max() < 3.0
    assert 0 < cam["rms_px"] < 0.2
    t = doc["target"]
    assert abs(t["kappa"] - SCENE.target.kappa) < 4 * t["kappa_sigma"]
    assert abs(t["nu"] - SCENE.target.nu) < 4 * t["nu_sigma"]
    rot, trans = pose_error(np.array(doc["hand_eye"]["matrix"]), SCENE.hand_eye_matrix)
    assert rot < np.deg2rad(0.05) and trans < 0.5e-3
    u = doc["uncertainty"]
    assert len(u["hand_eye_trans_m"]) == 3 and len(u["target_pose_rot_rad"]) == 3
    assert u["camera"]["fx"] > 0 and 0.5 < u["variance_factor"] < 2
    assert [s["id"] for s in doc["stations"]] == ["000", *(f"{k:03d}" for k in range(5, N_IMAGES))]
    assert all(s["mahalanobis"] is not None for s in doc["stations"])
    assert {"E_R", "E_t", "loo_trans_m_mean", "chain_rms_px"} <= set(doc["validation"])
    assert doc["options"]["nu_method"] == "images" and doc["software"]["version"]
    assert "wrote" in capsys.readouterr().err


def test_known_intrinsics_and_another_method(tmp_path):
    K, dist = SCENE.camera.k_matrix.tolist(), SCENE.camera.dist
    d = write_image_set(tmp_path / "set", intrinsics={"K": K, "dist": dist})
    out = tmp_path / "r.json"
    assert main(["calibrate", str(d), "--out", str(out), "--method", "sm"]) == 0
    doc = json.loads(out.read_text())
    assert doc["method"] == "sm" and doc["camera"]["K"] == K and doc["rejected"] == []


@pytest.mark.parametrize("inner_corners", [(10, 8), (12, 9), (8, 7)])
def test_wrong_inner_corners_is_told_from_the_first_image(tmp_path, capsys, monkeypatch,
                                                           inner_corners):
    """Issue 19 item 2: a board of another size fails at once, naming the grid it saw (a
    larger configured board took the detector's whole search on every image). The images are
    halved, which keeps what is seen and cuts each search for the absent board (0.8-1.8 CPU s
    on a 1280x1024 image)."""
    d = write_image_set(tmp_path / "set", inner_corners=inner_corners, n=3, half=True)
    solved = []
    monkeypatch.setattr("calib.calibrate",
                        lambda *a, **k: solved.append(1))
    assert main(["calibrate", str(d)]) == 2
    err = capsys.readouterr().err
    cols, rows = inner_corners
    assert err == (f"cellcal: error: {d}: station 000: found an 11x8 grid of inner corners, "
                   f"you configured {cols}x{rows}: correct the target in stations.json\n")
    assert solved == []


def test_square_size_in_millimetres_gets_a_hint(tmp_path, capsys):
    d = write_image_set(tmp_path / "set", n=3)
    doc = json.loads((d / "stations.json").read_text())
    doc["target"]["square_size_m"] = 30
    (d / "stations.json").write_text(json.dumps(doc))
    assert main(["calibrate", str(d)]) == 2
    assert "millimetres? 30 mm is 0.03 m" in capsys.readouterr().err


def test_mixed_pose_and_image_stations_are_refused(tmp_path, capsys):
    d = write_image_set(tmp_path / "set")
    doc = json.loads((d / "stations.json").read_text())
    doc["stations"][0].pop("image")
    doc["stations"][0]["target_pose"] = [0.0, 0.0, 0.5, 0.0, 0.0, 0.0]
    (d / "stations.json").write_text(json.dumps(doc))
    assert main(["calibrate", str(d)]) == 2
    assert "station 000 has a target_pose while others have images" in capsys.readouterr().err


@pytest.mark.parametrize("n_images, bar", [(12, True), (4, False)])
def test_progress_bar_only_for_many_images(tmp_path, capsys, n_images, bar):
    d = write_image_set(tmp_path / "set", n=n_images)
    assert main(["calibrate", str(d), "--method", "sm", "--out", str(tmp_path / "r.json")]) == 0
    err = capsys.readouterr().err
    assert ("detecting corners" in err) == bar
    # images are decoded on several threads while the bar is drawn: the decoders' capture of
    # stderr (their warnings reject an image) must not take the bar's text for a warning
    assert "rejected" not in err


@pytest.mark.parametrize(("out", "message"), [
    ("missing/result.json", "no directory .*missing; create it first"),
    (".", "is a directory; name the result file"),
])
def test_out_is_checked_before_the_solve(tmp_path, capsys, monkeypatch, out, message):
    d = write_image_set(tmp_path / "set", n=3)
    monkeypatch.chdir(tmp_path)
    solved = []
    monkeypatch.setattr("calib.calibrate",
                        lambda *a, **k: solved.append(1))
    assert main(["calibrate", str(d), "--out", out]) == 2
    err = capsys.readouterr().err
    assert re.match(f"cellcal: error: --out {re.escape(out)}: {message}", err), err
    assert solved == []  # refused before any image was read or solved


def test_rejected_stations_are_listed_on_the_terminal(tmp_path, capsys):
    d = write_image_set(tmp_path / "set")
    (d / "003.png").write_text("not an image")
    assert main(["calibrate", str(d), "--out", str(tmp_path / "r.json")]) == 0
    lines = capsys.readouterr().err.splitlines()
    assert "cellcal: station 003 rejected: image file '003.png' is not a readable image " \
           "(PNG or JPEG expected)" in lines
    assert sum("rejected:" in line for line in lines) == 1
