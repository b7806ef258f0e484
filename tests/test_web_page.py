"""The web page at ``/`` and the API docs at ``/docs`` and ``/redoc`` work without any other
host: every asset they reference is served by cellcal itself, without the API key (the data
calls still need it). A headless chromium (``tests.support.browser``, the DevTools protocol) clicks
through the page against ``cellcal serve --mock``: key, run, calibration, report, export.

``CELLCAL_SCREENSHOTS=docs pytest tests/test_web_page.py`` refreshes the screenshots in docs/.
"""

from __future__ import annotations

import json
import os
import re
import zipfile
from collections.abc import Iterator
from pathlib import Path

import cv2
import httpx
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.serving.local import LocalService, local_service
from service.web import STATIC_DIR
from tests.support.browser import Browser
from tests.support.helpers import wait_for
from tests.support.service import AUTH, KEY, settings

#: src / href attribute values in HTML.
_REFS = re.compile(r"""(?:src|href)\s*=\s*["']([^"']+)["']""")
#: Anything that would make a browser ask another host.
_REMOTE = re.compile(r"""(?:https?:)?//[A-Za-z0-9.-]+""")


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    with TestClient(create_app(settings(tmp_path))) as c:
        yield c


def local_refs(client: TestClient, path: str) -> list[str]:
    """The references of the HTML page at ``path`` (fetched without the key); each is local
    and loads without the key too."""
    r = client.get(path)
    assert r.status_code == 200, r.text
    assert r.headers["content-type"].startswith("text/html")
    refs = _REFS.findall(r.text)
    assert refs, f"{path} references no asset"
    for ref in refs:
        assert not _REMOTE.match(ref), f"{path} loads {ref} from another host"
        asset = client.get(httpx.URL(str(r.url)).join(ref).path)
        assert asset.status_code == 200, (ref, asset.status_code)
        assert asset.content
    return refs


def test_root_leads_to_the_page(client: TestClient) -> None:
    r = client.get("/", follow_redirects=False)
    assert r.status_code in (302, 307) and r.headers["location"] == "/ui/"
    refs = local_refs(client, "/ui/")
    assert sorted(refs) == ["app.js", "cellwork.js", "favicon.svg", "style.css"]


def test_page_assets_name_no_other_host() -> None:
    files = sorted(p.name for p in STATIC_DIR.iterdir())
    assert files == ["app.js", "cellwork.js", "favicon.svg", "index.html", "style.css"]
    for path in STATIC_DIR.iterdir():
        text = path.read_text().replace('xmlns="http://www.w3.org/2000/svg"', "")  # a name
        assert "http://" not in text and "https://" not in text, path.name
        assert not re.search(r"""["'(]//""", text), path.name  # protocol-relative URLs


@pytest.mark.parametrize(("path", "script"), [("/docs", "swagger-ui-bundle.js"),
                                              ("/redoc", "/redoc/bundle.js")])
def test_docs_work_offline(client: TestClient, path: str, script: str) -> None:
    refs = local_refs(client, path)
    assert any(ref.endswith(script) for ref in refs)
    bundle = next(ref for ref in refs if ref.endswith(script))
    assert len(client.get(bundle).content) > 100_000  # the real bundle, not a stub
    html = client.get(path).text
    assert "fonts.googleapis" not in html and "cdn." not in html


@pytest.mark.parametrize("path", ["/ui/", "/docs", "/redoc"])
def test_html_pages_let_the_browser_load_nothing_from_another_host(client: TestClient,
                                                                    path: str) -> None:
    policy = client.get(path).headers["content-security-policy"]
    directives = dict(d.strip().split(" ", 1) for d in policy.split(";"))
    for directive in ("default-src", "img-src", "connect-src"):
        sources = directives[directive].split()
        assert "'self'" in sources
        assert all(s in ("'self'", "'unsafe-inline'", "data:", "blob:") for s in sources), policy
    assert "content-security-policy" not in client.get("/health").headers  # JSON: no need


def test_favicon_needs_no_key(client: TestClient) -> None:
    """Issue 19: browsers ask every host for /favicon.ico, and got 401."""
    r = client.get("/favicon.ico")
    assert r.status_code == 200 and r.headers["content-type"].startswith("image/svg+xml")
    assert r.content.startswith(b"<svg")


def test_redoc_bundle_names_no_other_host(client: TestClient) -> None:
    bundle = client.get("/redoc/bundle.js")
    assert bundle.status_code == 200 and len(bundle.content) > 100_000
    assert b"cdn.redoc.ly" not in bundle.content


def test_data_still_needs_the_key(client: TestClient) -> None:
    assert client.get("/runs").status_code == 401
    assert client.get("/ui/../runs").status_code in (401, 404)
    assert client.get("/runs", headers=AUTH).status_code == 200


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LocalService]:
    with local_service(tmp_path_factory.mktemp("served") / "data", KEY) as service:
        yield service


@pytest.fixture
def shots(tmp_path: Path) -> Path:
    """Where screenshots go: ``CELLCAL_SCREENSHOTS`` (e.g. docs) or the test's directory."""
    return Path(os.environ.get("CELLCAL_SCREENSHOTS", tmp_path))


def text(browser: Browser, selector: str, session: str | None = None) -> str:
    return browser.js(f"document.querySelector({json.dumps(selector)})?.textContent ?? ''",
                      session)


def left_the_machine(requests: list[str], service: LocalService) -> list[str]:
    """The requested URLs that went anywhere but the service (blob: and data: URLs are
    made in the page itself)."""
    local = (f"{service.url}/", f"blob:{service.url}/", "data:", "about:blank")
    return [u for u in requests if not u.startswith(local)]


@pytest.mark.timeout(600)
def test_click_through_run_calibrate_report_export(served: LocalService, tmp_path: Path,
                                                   shots: Path) -> None:
    with Browser(tmp_path / "chromium") as browser:
        browser.goto(f"{served.url}/")
        browser.type("#key", KEY)
        browser.click("#key-form button")
        browser.wait_for("the page to connect", "document.querySelector('#status')"
                         ".textContent === 'connected'")
        assert "Robot mock://: connected" in text(browser, "#devices")

        browser.type("#stations", "8")
        browser.click("#run-form button")
        browser.wait_for("the run to finish",
                         "document.querySelector('#run-state').textContent === 'done'")
        browser.wait_for("the last station's image", "document.querySelector("
                         "'#latest-caption').textContent.startsWith('Station 7: captured')")
        assert text(browser, "#progress-text") == "8 of 8 stations: 8 captured, 0 skipped"
        assert browser.js("document.querySelectorAll('#stations tbody td.captured').length") == 8
        assert browser.js("[...document.querySelectorAll('[data-action]')]"
                          ".every((b) => b.disabled)")  # nothing to pause, resume or cancel

        # κ chosen on the page; a double click (two clicks in one task) starts one solve
        browser.js("document.querySelector('#kappa').value = 'estimate'")
        browser.js("(() => { const b = document.querySelector('#calibrate');"
                   " b.click(); b.click(); })()")
        assert browser.js("document.querySelector('#calibrate').disabled")
        # and stays so through a refresh of the run, which each event of the followed run
        # makes (one that came late re-enabled it mid-calibration: failed at load ~30)
        assert browser.js("refreshRun().then(() => document.querySelector('#calibrate')"
                          ".disabled)")
        browser.wait_for("the calibration", "document.querySelector('#status').textContent"
                         " === 'calibration finished'")
        run_id = browser.js("currentRun")
        cals = [c for c in httpx.get(f"{served.url}/calibrations?limit=50", headers=AUTH)
                .json()["items"] if c["run_id"] == run_id]
        assert len(cals) == 1, cals
        assert httpx.get(f"{served.url}/calibrations/{cals[0]['id']}", headers=AUTH
                         ).json()["options"]["kappa"] == "estimate"
        row = "#calibrations tbody tr:first-child"
        # the table refreshes on its own event, after the status line (under load it lagged)
        browser.wait_for("the calibration's row to show done",
                         f"document.querySelector('{row} td:nth-child(4)').textContent"
                         " === 'done'")
        verdict = text(browser, f"{row} td:nth-child(5)")
        assert verdict in ("pass", "warn"), verdict
        assert text(browser, "#figures dd.verdict, #figures dd.pass, #figures dd.warn") \
            == verdict
        assert "aspect ratio ν" in text(browser, "#figures")  # not "shear" (issue 19)
        browser.screenshot(shots / "web-page.png")

        activate_asks_first(browser, row, cals[0]["id"])

        whole_calibration(browser, served, run_id)

        report = browser.click_to_open_tab(f"{row} a.report")
        browser.wait_for("the report", "document.readyState === 'complete' && "
                         "location.protocol === 'blob:' && document.querySelector('h1')"
                         "?.textContent === 'Calibration report'", report)
        assert text(browser, ".verdict .word", report) == verdict

        browser.click(f"{row} a[data-format=opencv-yaml]")
        exported = browser.downloaded(after=1)  # the station set came first
        fs = cv2.FileStorage(str(exported), cv2.FILE_STORAGE_READ)
        K = fs.getNode("camera_matrix").mat()
        fs.release()
        assert K.shape == (3, 3) and K[0, 0] > 100 and K[2, 2] == 1.0
        requested = browser.requests
    assert f"{served.url}/ui/app.js" in requested
    assert any(u.startswith(f"{served.url}/calibrations/") and u.endswith("/report")
               for u in requested)
    assert left_the_machine(requested, served) == []


def activate_asks_first(browser: Browser, row: str, cal_id: str) -> None:
    """Issue 19 item 8: Activate opens a dialog naming the calibration and what it replaces;
    Cancel changes nothing, Activate activates; a second time the dialog names it as the
    active one."""
    def dialog(answer: str) -> str:
        browser.click(f"{row} button")
        browser.wait_for("the dialog", "document.querySelector('#activate-dialog').open && "
                         "document.querySelector('#activate-old').textContent !== ''")
        said = text(browser, "#activate-dialog")
        browser.js("document.querySelector('#activate-old').textContent = ''")
        browser.click(f"#activate-dialog button[value={answer}]")
        browser.wait_for("the dialog to close", "!document.querySelector('#activate-dialog')"
                         ".open && document.querySelector('#status').textContent !== ''")
        return said

    first = dialog("cancel")
    assert cal_id[:8] in text(browser, "#activate-new") and "verdict" in first
    assert text(browser, "#status") == "activation cancelled"
    active = httpx.get(f"{browser_url(browser)}/calibrations/active", headers=AUTH)
    before = active.json()["calibration"]["id"] if active.status_code == 200 else None
    assert before != cal_id
    assert (before or "nothing")[:8] in first
    dialog("activate")
    browser.wait_for("the row to say active", f"document.querySelector('{row} "
                     "td:nth-child(7)')?.textContent === 'active'")
    again = dialog("cancel")
    assert f"It replaces {cal_id[:8]}" in again and "nothing changes" in again


def wait_text(browser: Browser, what: str, selector: str, js_test: str) -> str:
    """Wait until the text of ``selector`` passes ``js_test`` (a JS expression of ``t``)."""
    try:
        browser.wait_for(what, f"(t => {js_test})(document.querySelector('{selector}')"
                         ".textContent)")
    except AssertionError as exc:
        raise AssertionError(f"{exc}: {selector} says {text(browser, selector)!r}, the status "
                             f"{text(browser, '#status')!r}") from None
    return text(browser, selector)


def whole_calibration(browser: Browser, served: LocalService, run_id: str) -> None:
    """Issue 19: the page runs a whole calibration. Intrinsics and the board pose in the
    result view; the solve's progress; an older station's image with detected and
    reprojected corners; the station set download; the re-check and the dot-hit validation of
    the active calibration; an external run and a run through a list of poses."""
    figures = text(browser, "#figures")
    for name in ("focal length fx / fy (px)", "principal point", "distortion k1",
                 "board pose (base → board) x / y / z (mm)", "board pose rotation vector"):
        assert name in figures, figures
    assert text(browser, "#solve-progress") not in ("", "started")

    hit = browser.js("(() => { const r = document.querySelector('#stations tbody tr:first-child')"
                     ".getBoundingClientRect(); r && document.querySelector('#stations')"
                     ".scrollIntoView({block: 'center'}); const b = document.querySelector("
                     "'#stations tbody tr:first-child').getBoundingClientRect();"
                     " return document.elementFromPoint(b.left + b.width / 2,"
                     " b.top + b.height / 2)?.closest('#stations') !== null; })()")
    assert hit, "the first station's row is covered"
    browser.click("#stations tbody tr:first-child")
    caption = wait_text(browser, "the first station with both corner sets", "#latest-caption",
                        "t.startsWith('Station 0') && t.includes('reprojected')")
    detected = re.search(r"(\d+) corners detected \(green\), (\d+) reprojected", caption)
    assert detected and detected[1] == detected[2] and int(detected[1]) > 20, caption

    browser.click("#stationset")
    with zipfile.ZipFile(browser.downloaded()) as stationset:
        names = stationset.namelist()
    assert "stations.json" in names and sum(n.endswith(".png") for n in names) == 8, names

    for kind, said in (("check", "cell ok: "), ("dot_hit", "points touched")):
        browser.click(f"[data-validate={kind}]")
        state = wait_text(browser, f"the {kind} to end", "#validation-state",
                          "t === 'done' || t === 'failed'")
        assert state == "done", text(browser, "#validation-result")
        assert said in text(browser, "#validation-result")
        browser.js("document.querySelector('#validation-state').textContent = ''")

    poses = [s["tcp_pose"] for s in httpx.get(f"{served.url}/runs/{run_id}/stations",
                                              headers=AUTH).json()[:3]]
    browser.js("document.querySelector('#run-kind').value = 'external';"
               "document.querySelector('#run-kind').dispatchEvent(new Event('change'))")
    browser.click("#run-form button")
    browser.wait_for("the external run", f"currentRun !== '{run_id}' && document"
                     ".querySelector('#run-state').textContent === 'capturing'")
    external = browser.js("currentRun")
    assert httpx.get(f"{served.url}/runs/{external}", headers=AUTH).json()["mode"] == "external"
    browser.click("[data-action=cancel]")
    wait_text(browser, "the external run to end", "#run-state", "t === 'cancelled'")

    browser.js("document.querySelector('#run-kind').value = 'poses';"
               "document.querySelector('#run-kind').dispatchEvent(new Event('change'))")
    assert not browser.js("document.querySelector('#poses-options').hidden")
    browser.js(f"document.querySelector('#poses').value = {json.dumps(json.dumps(poses))}")
    browser.click("#run-form button")
    browser.wait_for("the pose-list run", f"currentRun !== '{external}' && document"
                     ".querySelector('#run-state').textContent === 'done'")
    assert text(browser, "#progress-text") == "3 of 3 stations: 3 captured, 0 skipped"
    browser.js("document.querySelector('#run-kind').value = 'planned';"
               "document.querySelector('#run-kind').dispatchEvent(new Event('change'))")
    browser.click(f"#runs tbody tr[data-id='{run_id}']")
    browser.wait_for("the first run again", f"currentRun === '{run_id}'")


def browser_url(browser: Browser) -> str:
    return str(browser.js("location.origin"))


@pytest.mark.timeout(300)
@pytest.mark.parametrize(("path", "rendered"), [
    ("/docs", "document.querySelectorAll('.swagger-ui .opblock').length > 20"),
    ("/redoc", "document.querySelectorAll('[data-section-id]').length > 20")])
def test_docs_render_in_chromium_asking_no_other_host(served: LocalService, tmp_path: Path,
                                                      shots: Path, path: str,
                                                      rendered: str) -> None:
    with Browser(tmp_path / "chromium") as browser:
        browser.goto(f"{served.url}{path}")
        browser.wait_for(f"{path} to render the API", rendered)
        assert "/calibrations/active" in browser.js("document.body.innerText")
        if path == "/docs":
            browser.screenshot(shots / "web-docs.png")
        requested, blocked = browser.requests, browser.blocked
    assert any(u.endswith("/openapi.json") for u in requested)
    assert left_the_machine(requested, served) == []
    # nothing even tried elsewhere (ReDoc's bundle asked a CDN for its vendor's logo, which
    # the Content-Security-Policy then blocked)
    assert blocked == []


@pytest.mark.timeout(300)
@pytest.mark.timeout(600)
def test_page_opens_a_run_and_a_calibration_by_short_id(served: LocalService,
                                                         tmp_path: Path) -> None:
    """Issue 19 item 6: the 8-character ids the page shows open a run and a calibration from
    the page's address; the page then works with the full ids the service answers."""
    headers = {"Authorization": f"Bearer {KEY}"}
    run_id = httpx.post(f"{served.url}/runs", json={"stations": 6}, headers=headers).json()["id"]
    wait_for("the run to end", lambda: httpx.get(
        f"{served.url}/runs/{run_id}", headers=headers).json()["state"] != "capturing",
        timeout=300)
    cal_id = httpx.post(f"{served.url}/runs/{run_id[:8]}/calibrations", json={},
                        headers=headers).json()["id"]
    with Browser(tmp_path / "chromium") as browser:
        browser.goto(f"{served.url}/#key={KEY}&run={run_id[:8]}&calibration={cal_id[:8]}")
        browser.wait_for("the run to open", "document.querySelector('#run-state')"
                         ".textContent === 'done'")
        browser.wait_for("the calibration to show", "!document.querySelector("
                         "'#calibration-view').hidden")
        assert browser.js("currentRun") == run_id
        assert (text(browser, "#run-id"), text(browser, "#cal-id")) == (run_id[:8], cal_id[:8])
        assert "state" in text(browser, "#figures")


def test_devices_line_refreshes_itself(tmp_path: Path) -> None:
    """Issue 19 item 1: the devices line was read once, when the page connected. The robot
    moves (a run through the API, not the page); the line follows without a click."""
    with local_service(tmp_path / "data", KEY) as service, \
            Browser(tmp_path / "chromium") as browser:
        browser.goto(f"{service.url}/#key={KEY}")
        browser.wait_for("the page to connect", "document.querySelector('#status')"
                         ".textContent === 'connected'")
        before = text(browser, "#devices")
        assert "Robot mock://: connected" in before and "TCP at" in before
        headers = {"Authorization": f"Bearer {KEY}"}
        run = httpx.post(f"{service.url}/runs", json={"stations": 3}, headers=headers).json()
        while httpx.get(f"{service.url}/runs/{run['id']}",
                        headers=headers).json()["state"] == "capturing":
            browser.wait_for("a moment", "new Promise((r) => setTimeout(() => r(true), 200))")
        x_mm = httpx.get(f"{service.url}/devices", headers=headers).json()["robot"][
            "tcp_pose"][0] * 1000
        browser.wait_for("the devices line to show where the robot went",
                         f"document.querySelector('#devices').textContent"
                         f".includes('TCP at ' + ({x_mm!r}).toFixed(1) + ' ')")
        assert text(browser, "#devices") != before


@pytest.mark.timeout(900)
def test_a_tolerance_run_from_the_page_plots_sigma_against_it(served: LocalService,
                                                              tmp_path: Path,
                                                              shots: Path) -> None:
    """Issue 17 item 3: the page starts a run that stops at a tolerance and shows the
    hand-eye's σ against the tolerance as it goes, with why the run stopped."""
    with Browser(tmp_path / "chromium") as browser:
        browser.goto(f"{served.url}/#key={KEY}")
        browser.wait_for("the page to connect", "document.querySelector('#status')"
                         ".textContent === 'connected'")
        browser.click("#use-tolerance")
        for selector, value in (("#tolerance-mm", "2"), ("#tolerance-deg", "0.2"),
                                ("#max-stations", "8")):
            browser.js(f"document.querySelector('{selector}').value = ''")
            browser.type(selector, value)
        browser.click("#run-form button")
        browser.wait_for("the σ plot", "!document.querySelector('#sigma-view').hidden && "
                         "document.querySelector('#sigma-caption').textContent"
                         ".startsWith('σ ')")
        browser.wait_for("the run to finish",
                         "document.querySelector('#run-state').textContent === 'done'")
        browser.wait_for("the stop reason", "document.querySelector('#sigma-caption')"
                         ".textContent.includes('stopped: ')")
        caption = text(browser, "#sigma-caption")
        # the plot has ink: its non-white pixels
        inked = browser.js(
            "(() => { const c = document.querySelector('#sigma-plot');"
            " const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;"
            " let n = 0; for (let i = 3; i < d.length; i += 4) n += d[i] > 0; return n; })()")
        browser.screenshot(shots / "web-tolerance.png")
    assert "tolerance 0.2° / 2 mm" in caption
    assert re.search(r"stopped: (tolerance_met|max_stations)", caption), caption
    assert inked > 200
    run_id = httpx.get(f"{served.url}/runs?limit=1", headers=AUTH).json()
    run = run_id[0] if isinstance(run_id, list) else run_id["items"][0]
    rule = run["cold_start"]["stop_rule"]
    assert (rule["tolerance_mm"], rule["tolerance_deg"], rule["max_stations"]) == (2.0, 0.2, 8)
    assert "90 % bound" in caption
