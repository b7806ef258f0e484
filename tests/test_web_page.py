"""The web page at ``/`` and the API docs at ``/docs`` and ``/redoc`` work without any other
host: every asset they reference is served by cellcal itself, without the API key (the data
calls still need it). A headless chromium renders the page against ``cellcal serve --mock``.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.local import local_service
from service.web import STATIC_DIR
from tests.test_service_api import AUTH, KEY, settings

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
    assert sorted(refs) == ["app.js", "style.css"]


def test_page_assets_name_no_other_host() -> None:
    files = sorted(p.name for p in STATIC_DIR.iterdir())
    assert files == ["app.js", "index.html", "style.css"]
    for path in STATIC_DIR.iterdir():
        text = path.read_text()
        assert "http://" not in text and "https://" not in text, path.name
        assert not re.search(r"""["'(]//""", text), path.name  # protocol-relative URLs


@pytest.mark.parametrize(("path", "script"), [("/docs", "swagger-ui-bundle.js"),
                                              ("/redoc", "redoc.standalone.js")])
def test_docs_work_offline(client: TestClient, path: str, script: str) -> None:
    refs = local_refs(client, path)
    assert any(ref.endswith(script) for ref in refs)
    bundle = next(ref for ref in refs if ref.endswith(script))
    assert len(client.get(bundle).content) > 100_000  # the real bundle, not a stub
    html = client.get(path).text
    assert "fonts.googleapis" not in html and "cdn." not in html


def test_data_still_needs_the_key(client: TestClient) -> None:
    assert client.get("/runs").status_code == 401
    assert client.get("/ui/../runs").status_code in (401, 404)
    assert client.get("/runs", headers=AUTH).status_code == 200


def chromium_dom(url: str, profile: Path) -> tuple[str, set[str]]:
    """The page's DOM after its scripts ran (headless chromium), and every URL the page
    requested (from the browser's net log)."""
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    assert chromium, "chromium is needed (Debian package chromium; .ci/run installs it)"
    net_log = profile / "net-log.json"
    dom = subprocess.run(
        [chromium, "--headless", "--no-sandbox", "--disable-gpu", f"--user-data-dir={profile}",
         "--no-first-run", "--disable-background-networking", "--disable-sync",
         "--disable-component-update", "--virtual-time-budget=15000",
         f"--log-net-log={net_log}", "--dump-dom", url],
        capture_output=True, text=True, timeout=90, check=False)
    assert dom.returncode == 0, dom.stderr[-2000:]
    return dom.stdout, page_requests(net_log.read_text())


#: Chromium's network traffic annotations of what a page loads: navigations, and the
#: subresources and fetches of its documents (the browser's own services use others).
_PAGE_TRAFFIC = (63171670, 101845102)


def page_requests(net_log: str) -> set[str]:
    """URLs the pages requested, from a chromium net log."""
    annotations = "|".join(map(str, _PAGE_TRAFFIC))
    return set(re.findall(rf'"traffic_annotation":(?:{annotations}),"url":"([^"]+)"', net_log))


def wait_done(url: str, run_id: str) -> None:
    auth = {"Authorization": f"Bearer {KEY}"}
    deadline = time.monotonic() + 60
    while httpx.get(f"{url}/runs/{run_id}", headers=auth).json()["state"] == "capturing":
        assert time.monotonic() < deadline, "run did not finish"
        time.sleep(0.2)


@pytest.mark.timeout(180)
def test_page_and_docs_in_headless_chromium_ask_no_other_host(tmp_path: Path) -> None:
    with local_service(tmp_path / "data", KEY) as service:
        run_id = httpx.post(f"{service.url}/runs", json={"stations": 3},
                            headers={"Authorization": f"Bearer {KEY}"}, timeout=30).json()["id"]
        wait_done(service.url, run_id)
        html, requested = chromium_dom(f"{service.url}/ui/#key={KEY}", tmp_path / "page")
        docs, docs_requested = chromium_dom(f"{service.url}/docs", tmp_path / "docs")
    assert f"<td>{run_id[:8]}</td>" in html, html[-3000:]
    assert '<td class="done">done</td>' in html
    assert "Robot mock://: connected" in html
    assert 'id="status" role="status">connected<' in html
    assert 'class="swagger-ui"' in docs and "/calibrations/active" in docs
    local = service.url + "/"
    assert {f"{local}ui/app.js", f"{local}devices", f"{local}runs?limit=20"} <= requested
    assert any(u.endswith("/swagger-ui-bundle.js") for u in docs_requested)
    assert [u for u in requested | docs_requested if not u.startswith(local)] == []
