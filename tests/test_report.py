"""The HTML report (``service.results.report``) of real results: ``cellcal report`` on a real UR
set and ``GET /calibrations/{id}/report`` after a capture run on the mock cell."""

from __future__ import annotations

import base64
import hashlib
import json
import re
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from html.parser import HTMLParser
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from calib import image_coverage, outlier_limit
from calib.result import parse_result
from service.cli import report as report_cli
from service.cli.main import main
from service.results.report import render_report, report_plots
from tests.support.helpers import wait_for
from tests.support.service import finished, get_report, start_run, wait_calibration, wait_run

#: Plots a hand-eye result from images always has (``model-selection`` needs the block).
IMAGE_PLOTS = ("station-errors", "residuals", "coverage", "uncertainty")


class _Page(HTMLParser):
    """Collects every URL-bearing attribute, figure ids and the visible text."""

    def __init__(self) -> None:
        super().__init__()
        self.urls: list[str] = []
        self.figures: list[str] = []
        self.images: list[str] = []
        self.text: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        self.urls += [v or "" for k, v in attrs if k in ("src", "href", "action", "srcset")]
        if tag == "figure":
            self.figures.append(a.get("id") or "")
        if tag == "img":
            self.images.append(a.get("src") or "")

    def handle_data(self, data: str) -> None:
        self.text.append(data)


def parse(html: str) -> _Page:
    page = _Page()
    page.feed(html)
    page.close()
    return page


def assert_self_contained(html: str) -> _Page:
    """No external reference of any kind; every image an embedded, decodable PNG (plots) or
    JPEG (station thumbnails, 320 px wide)."""
    page = parse(html)
    assert "http://" not in html and "https://" not in html
    assert "<link" not in html and "<script" not in html and "@import" not in html
    assert page.urls and all(u.startswith(("data:image/png;base64,", "data:image/jpeg;base64,"))
                             for u in page.urls)
    for src in page.images:
        data = base64.b64decode(src.split(",", 1)[1], validate=True)
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        width = 320 if src.startswith("data:image/jpeg") else 400
        assert image is not None and image.shape[0] > 150 and image.shape[1] >= width
        assert image.std() > 10  # something is drawn
    return page




def test_report_of_a_real_calibration(ur_result, capsys) -> None:
    path, result = ur_result
    assert main(["report", str(path)]) == 0  # next to the result by default
    out = path.with_suffix(".html")
    assert f"wrote {out}" in capsys.readouterr().err
    html = out.read_text()
    page = assert_self_contained(html)
    text = " ".join(page.text)
    assert page.figures == [f"fig-{p.key}" for p in report_plots(parse_result(result))]
    assert set(IMAGE_PLOTS) <= {f.removeprefix("fig-") for f in page.figures}
    if "model_selection" in result:
        assert "fig-model-selection" in page.figures
    quality = result.get("quality")
    verdict = quality["verdict"] if quality else "no verdict"
    # the verdict comes before the first plot, with every finding's message
    assert html.index(f">{verdict}<") < html.index("<figure")
    for finding in (quality or {}).get("findings", []):
        assert finding["message"] in text
    # every used station has a row; the blank one is listed with the detector's reason
    for s in result["stations"]:
        assert f"<td class=\"l\">{s['id']}</td>" in html
    (rejected,) = result["rejected"]
    assert rejected["id"] == "04" and "blank" in rejected["reason"]
    assert f"rejected: {rejected['reason']}" in text
    # the figures a person reads: κ and the hand-eye translation in mm
    assert f"{result['target']['kappa']:.5f}" in text
    t_mm = np.asarray(result["hand_eye"]["pose"][:3]) * 1e3
    assert all(f"{v:.2f}" in text for v in t_mm)
    # the cross-validated error in the verdict box, then every candidate, why, and the rule
    cv = result["cross_validation"]
    box = html[html.index("class=\"verdict\""):html.index("<h2>Result")]
    assert f"predicted to {cv['rms_px']:.2f} px ({cv['rms_mm']:.2f} mm at the board)" in box
    selection = result["model_selection"]
    table = html[html.index("<h2>Model selection"):html.index("<h2>Stations")]
    for c in selection["candidates"]:
        row = table[table.index(f"<td class=\"l\">{c['name']}</td>"):]
        row = row[:row.index("</tr>")]
        assert f"{c['cv_rms_px']:.3f}" in row and f"{c['cv_range_mm']:.3f}" in row
    chosen = table[table.index("class=\"chosen\""):]
    assert chosen[:chosen.index("</tr>")].count(selection["chosen"]) == 1
    assert all(d in text for d in selection["decisions"]) and selection["rule"] in text


def test_one_coverage_figure_and_a_sign_off(ur_result) -> None:
    """Issue 19: the page (the quality finding) said 89 % and the report 59 %: the report now
    states the one figure of calib.quality.image_coverage; a sign-off block closes it."""
    path, result = ur_result
    html = path.with_suffix(".html").read_text() if path.with_suffix(".html").exists() \
        else render_report(result)
    corners = np.concatenate([np.asarray(s["corners_px"]) for s in result["stations"]])
    fraction, empty = image_coverage(corners, tuple(result["camera"]["image_size"]))
    assert f"Coverage {fraction:.0%}" in html and f"{empty} of 4 image corners empty" in html
    for finding in result["quality"]["findings"]:
        if finding["code"] == "poor_coverage":
            assert f"{100 * fraction:.0f} % of the image" in finding["message"]
    sign_off = html[html.index("<h2>Sign-off</h2>"):]
    for field in ("Name", "Date", "Decision", "Signature", "accepted", "rejected"):
        assert f">{field}<" in sign_off or field in sign_off
    assert "@page { size: A4" in html


def test_stations_against_their_thresholds_and_outliers_marked(ur_result) -> None:
    """Issue 19: per-station residuals in degrees and mm, each against its threshold (the
    verdict's outlier rule), and the outlier stations highlighted."""
    _, result = ur_result
    doc = json.loads(json.dumps(result))
    first, *others = doc["stations"]
    held_out = [s["loo_rot_rad"] for s in others if s.get("loo_rot_rad") is not None]
    assert len(held_out) >= 5
    first["loo_rot_rad"] = 100 * max(held_out)
    doc["quality"]["findings"].append({"code": "outlier_stations", "severity": "warn",
                                       "message": "m", "stations": [first["id"]]})
    html = render_report(doc)
    table = html[html.index("<h2>Stations"):html.index("<h2>Provenance")]
    limit = np.degrees(outlier_limit(np.array([first["loo_rot_rad"], *held_out])))
    assert f"held-out rot. (°, ≤ {limit:.3f})" in table and "held-out trans. (mm, ≤ " in table
    (row,) = [r for r in table.split("<tr")
              if f"<td class=\"l\">{first['id']}</td>" in r]
    assert row.startswith(" class=\"outlier\">") and "over</span>" in row, row
    assert row.endswith("<td>outlier</td></tr>")
    assert table.count("class=\"outlier\"") == 1


def test_report_prints_to_a_pdf_through_chromium(ur_result, tmp_path, capsys,
                                                 monkeypatch) -> None:
    """The report of the real 21-station UR set with its station thumbnails (the blank
    station rejected): one JPEG per used station with the corners drawn, an outlier framed,
    under 3 MB, nothing from another host; printed to an A4 PDF."""
    path, result = ur_result
    out = tmp_path / "report.html"
    assert main(["report", str(path), "--stations", str(path.parent), "--out", str(out),
                 "--pdf"]) == 0
    pdf = out.with_suffix(".pdf")
    assert f"wrote {pdf}" in capsys.readouterr().err
    html = out.read_text()
    assert len(html.encode()) < 3_000_000 and "http://" not in html and "https://" not in html
    thumbs = re.findall(r'<figure class="thumb[^"]*"><img alt="station ([^"]+)" '
                        r'src="data:image/jpeg;base64,([^"]+)"', html)
    assert [sid for sid, _ in thumbs] == [s["id"] for s in result["stations"]]
    for _, data in thumbs:
        image = cv2.imdecode(np.frombuffer(base64.b64decode(data), np.uint8), cv2.IMREAD_COLOR)
        b, g, r = (image[..., k].astype(int) for k in range(3))
        assert image.shape[1] == 320 and ((g - r > 80) & (g - b > 80)).sum() > 20  # green dots
        assert ((r - g > 40) & (r - b > 40)).sum() > 20  # red crosses (JPEG softens them)
    identity = html[html.index("<h2>Cell and inputs</h2>"):html.index("<h2>Sign-off</h2>")]
    digest = hashlib.sha256((path.parent / "stations.json").read_bytes())
    for s in json.loads((path.parent / "stations.json").read_text())["stations"]:
        digest.update((path.parent / s["image"]).read_bytes())
    assert digest.hexdigest() in identity and "inner_corners" in identity
    assert f">{result['software']['version']}<" in identity and "robot serial" in identity
    data = pdf.read_bytes()
    assert data.startswith(b"%PDF-")
    pages = re.findall(rb"/MediaBox \[0 0 ([\d.]+) ([\d.]+)\]", data)
    assert pages and all(abs(float(w) - 595.3) < 1 and abs(float(h) - 841.9) < 1
                         for w, h in pages)  # A4 (210 x 297 mm in points)
    monkeypatch.setattr(report_cli, "chromium", lambda: None)
    pdf.unlink()
    assert main(["report", str(path), "--out", str(out), "--pdf"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--pdf needs chromium" in err and not pdf.exists()


def test_bad_report_input_is_one_line(tmp_path, capsys) -> None:
    (tmp_path / "other.json").write_text(json.dumps({"format": "cellcal/stations@1"}))
    (tmp_path / "broken.json").write_text("{")
    (tmp_path / "deep.json").write_text("[" * 100_000 + "]" * 100_000)  # an internal error before
    for name, message in [("missing.json", "cannot read"), ("other.json", "not a cellcal result"),
                          ("broken.json", "not JSON"), ("deep.json", "not JSON")]:
        assert main(["report", str(tmp_path / name), "--out", str(tmp_path / "r.html")]) == 2
        err = capsys.readouterr().err
        assert err.startswith("cellcal: error: ") and message in err and err.count("\n") == 1
    assert not (tmp_path / "r.html").exists()


def test_intrinsics_only_and_pose_only_results_have_reports(ur_result, tmp_path) -> None:
    """Results without hand-eye or without camera still give a page, with the plots they
    allow."""
    from calib.boards import Checkerboard
    from calib.pipeline import calibrate_stations
    from calib.stations import StationInputs
    from mocks.posesim import default_cell, simulate
    from service.results.document import calibration_result
    from service.results.report import render_report
    from tests.support.stations import write_station_set

    _, result = ur_result
    corners = [np.asarray(s["corners_px"]) for s in result["stations"]]
    intrinsics = calibration_result(calibrate_stations(
        StationInputs(corners, image_size=(1280, 720)), Checkerboard((11, 8), 0.03)))
    page = assert_self_contained(render_report(intrinsics))
    assert page.figures == ["fig-station-errors", "fig-residuals", "fig-coverage"]

    P, C = simulate(default_cell("eye_in_hand"), 12, np.random.default_rng(3))
    out = tmp_path / "pose.json"
    assert main(["calibrate", str(write_station_set(tmp_path / "set", P, C)), "--out",
                 str(out)]) == 0
    pose_only = json.loads(out.read_text())
    html = render_report(pose_only)
    assert parse(html).figures == ["fig-uncertainty"]
    s = pose_only["stations"][5]
    assert (f"<td>{np.rad2deg(s['residual_rot_rad']):.3f}</td>"
            f"<td>{s['residual_trans_m'] * 1e3:.2f}</td>") in html


# only a hang guard: under four CPU burners the nice-10 rendering gets a few % of a core
@pytest.mark.timeout(600)
def test_rest_report_of_a_capture_run(client, monkeypatch) -> None:
    run_id = start_run(client, 8)
    wait_run(client, run_id, finished)
    cal_id = client.post(f"/runs/{run_id}/calibrations", json={}).json()["id"]
    cal = wait_calibration(client, cal_id, 240)
    assert cal["state"] == "done", cal["error"]
    r = get_report(client, cal_id)
    assert r.status_code == 200
    assert r.headers["content-type"].startswith("text/html")
    page = assert_self_contained(r.text)
    assert set(IMAGE_PLOTS) <= {f.removeprefix("fig-") for f in page.figures}
    assert all(f"<td class=\"l\">{s['id']}</td>" in r.text for s in cal["result"]["stations"])
    thumbs = re.findall(r'<figure class="thumb[^"]*"><img alt="station ([^"]+)"', r.text)
    assert thumbs == [s["id"] for s in cal["result"]["stations"]]  # the run's images
    identity = r.text[r.text.index("<h2>Cell and inputs</h2>"):r.text.index("<h2>Sign-off")]
    assert f"8 of run {run_id}" in identity and "mock://" in identity
    assert ("<td>robot model</td><td class=\"code\">cellcal mock (a simulated arm)</td>"
            in identity)  # as the driver told it when capture started
    assert "<td>robot serial</td><td class=\"code\">not known</td>" in identity
    assert re.search(r">[0-9a-f]{64}<", identity)
    missing = client.get("/calibrations/nope/report")
    assert missing.status_code == 404 and missing.json()["code"] == "not_found"
    # rendered once and kept (issue 22, row 7): the cached page is what later requests get,
    # also several at once, and a rendering in flight is shared
    reports = client.app.state.runtime.calibrations.reports
    cached = reports.cached(cal_id)
    wait_for("the page to be kept", cached.is_file)  # written as the rendering ends
    assert cached.read_text() == r.text
    cached.write_text(r.text.replace("Calibration report", "Calibration report (cached)"))
    with ThreadPoolExecutor(8) as pool:
        pages = list(pool.map(lambda _: client.get(f"/calibrations/{cal_id}/report"), range(8)))
    assert all(p.status_code == 200 and "(cached)" in p.text for p in pages)
    # a kept page needs nothing read for a rendering (the stations, their images' hash)
    assert reports.page(cal_id, lambda: pytest.fail("inputs made for a kept page")) == cached
    cached.unlink()
    with ThreadPoolExecutor(8) as pool:
        pages = list(pool.map(lambda _: get_report(client, cal_id), range(8)))
    assert {p.text for p in pages} == {r.text}
    wait_for("the page to be kept again", cached.is_file)
    assert cached.read_text() == r.text
    # a rendering that does not end within report_wait_s: each request is answered 503 with
    # Retry-After at once (it never hangs), and the page is served once the rendering ends
    cached.unlink()
    rendering: Future[str] = Future()
    monkeypatch.setattr(reports, "wait_s", 0.05)
    monkeypatch.setattr(reports, "_pool", SimpleNamespace(submit=lambda *args: rendering,
                                                          shutdown=lambda: None))
    with ThreadPoolExecutor(4) as pool:
        waiting = list(pool.map(lambda _: client.get(f"/calibrations/{cal_id}/report"),
                                range(4)))
    for w in waiting:
        assert w.status_code == 503 and w.headers["Retry-After"] == "5", w.text
        assert w.json()["code"] == "report_rendering" and cal_id in w.json()["detail"]
    assert not cached.exists()
    rendering.set_result("<p>rendered late</p>")
    wait_for("the late page to be kept", cached.is_file)
    assert client.get(f"/calibrations/{cal_id}/report").text == "<p>rendered late</p>"
    # the worker died while rendering (out of memory, killed): 503 at once, saying so, and the
    # next request renders the page again (issue 22, a variant of row 7: before, 500)
    cached.unlink()
    died: Future[str] = Future()
    died.set_exception(BrokenProcessPool("a child process terminated abruptly"))
    again: Future[str] = Future()
    again.set_result("<p>rendered again</p>")
    renderings = iter([died, again])
    monkeypatch.setattr(reports, "_pool", SimpleNamespace(submit=lambda *args: next(renderings),
                                                          shutdown=lambda: None))
    lost = client.get(f"/calibrations/{cal_id}/report")
    assert lost.status_code == 503 and lost.headers["Retry-After"] == "5", lost.text
    assert lost.json()["code"] == "report_worker_died" and cal_id in lost.json()["detail"]
    assert client.get(f"/calibrations/{cal_id}/report").text == "<p>rendered again</p>"
