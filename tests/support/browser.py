"""A headless chromium driven over the DevTools protocol, for the web page tests.

Chromium is started with ``--remote-debugging-pipe``: it reads protocol commands on file
descriptor 3 and writes answers and events on 4, each message JSON ended by a NUL byte. No
port, no driver binary, no extra package. One page is attached in flat session mode, and so is
every tab it opens (held until the test has attached, so none of its requests is missed); every
request they make is recorded (``Network.requestWillBeSent``) so a test can check that none
leaves the machine (``requests``; those the browser blocked itself, e.g. by the page's
Content-Security-Policy, never leave it and are in ``blocked``), and downloads land in
``downloads``.

Waits are for conditions (``wait_for``), never fixed sleeps; their deadlines only catch hangs.
"""

from __future__ import annotations

import base64
import fcntl
import json
import os
import shutil
import subprocess
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from tests.support.helpers import ends_with_this_process, wait_for

#: Deadline of one wait (s): a guard against a hang, not a speed requirement.
WAIT_S = 120.0
#: ``send``'s session for commands to the browser itself rather than to a page.
BROWSER = ""


class BrowserError(RuntimeError):
    """Chromium answered a command with an error, or a script on the page threw."""


class Browser:
    """Headless chromium with one page; use as a context manager (the process is always
    ended). ``downloads``: where downloads go."""

    def __init__(self, profile: Path, *, width: int = 1280, height: int = 900) -> None:
        chromium = shutil.which("chromium") or shutil.which("chromium-browser")
        assert chromium, "chromium is needed (Debian package chromium; .ci/run installs it)"
        profile.mkdir(parents=True, exist_ok=True)
        self.downloads = profile / "downloads"
        self.downloads.mkdir(exist_ok=True)
        to_chromium, self._out = _high_pipe()
        self._in, from_chromium = _high_pipe()

        def as_fds_3_and_4() -> None:  # in the child, before exec
            os.dup2(to_chromium, 3)
            os.dup2(from_chromium, 4)

        self._log = (profile / "chromium.log").open("wb")
        self.proc = subprocess.Popen(
            [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--remote-debugging-pipe",
             f"--user-data-dir={profile}", "--no-first-run", "--disable-background-networking",
             "--disable-sync", "--disable-component-update", "--disable-default-apps",
             "--hide-scrollbars", f"--window-size={width},{height}", "about:blank"],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
            stderr=self._log, close_fds=False,
            preexec_fn=ends_with_this_process(then=as_fds_3_and_4))
        os.close(to_chromium)
        os.close(from_chromium)
        self._sent: list[tuple[str, str]] = []  # (request id, URL)
        self._blocked: set[str] = set()  # ids of requests the browser refused to send
        self.events: list[dict[str, Any]] = []
        self._answers: dict[int, dict[str, Any]] = {}
        self._cond = threading.Condition()
        self._next_id = 0
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        try:
            self._attach(width, height)
        except BaseException:
            self.close()
            raise

    # ---- the protocol ----------------------------------------------------------------------

    def send(self, method: str, params: dict[str, Any] | None = None, *,
             session: str | None = None) -> dict[str, Any]:
        """Send one command to a page's ``session`` (default: the first page's; ``BROWSER``:
        the browser itself); its result."""
        return self.answer(self.post(method, params, session=session), method)

    def post(self, method: str, params: dict[str, Any] | None = None, *,
             session: str | None = None) -> int:
        """Send one command without waiting for its answer; its id for ``answer``."""
        with self._cond:
            self._next_id += 1
            msg_id = self._next_id
        message: dict[str, Any] = {"id": msg_id, "method": method, "params": params or {}}
        if session != BROWSER:
            message["sessionId"] = session or self.session
        os.write(self._out, json.dumps(message).encode() + b"\0")
        return msg_id

    def answer(self, msg_id: int, method: str) -> dict[str, Any]:
        """The result of the command ``msg_id`` once it came."""
        with self._cond:
            assert self._cond.wait_for(lambda: msg_id in self._answers or not self._alive(),
                                       WAIT_S), f"no answer to {method}"
            answer = self._answers.pop(msg_id, None)
        if answer is None:
            raise BrowserError(f"chromium exited during {method}")
        if "error" in answer:
            raise BrowserError(f"{method}: {answer['error']}")
        return answer.get("result", {})

    def _alive(self) -> bool:
        return self.proc.poll() is None

    def _read(self) -> None:
        buffer = b""
        while chunk := os.read(self._in, 1 << 16):
            buffer += chunk
            *messages, buffer = buffer.split(b"\0")
            for raw in messages:
                self._dispatch(json.loads(raw))
        with self._cond:
            self._cond.notify_all()

    def _dispatch(self, message: dict[str, Any]) -> None:
        with self._cond:
            if "id" in message:
                self._answers[message["id"]] = message
            else:
                params = message.get("params", {})
                if message.get("method") == "Network.requestWillBeSent":
                    self._sent.append((params["requestId"], params["request"]["url"]))
                elif message.get("method") == "Network.loadingFailed" and \
                        params.get("blockedReason"):
                    self._blocked.add(params["requestId"])
                self.events.append(message)
            self._cond.notify_all()

    def _attach(self, width: int, height: int) -> None:
        targets = self.send("Target.getTargets", session=BROWSER)["targetInfos"]
        page = next(t for t in targets if t["type"] == "page")
        self.session = self.send("Target.attachToTarget",
                                 {"targetId": page["targetId"], "flatten": True},
                                 session=BROWSER)["sessionId"]
        self.page_id = page["targetId"]
        self._watch(self.session)
        self.send("Target.setAutoAttach", {"autoAttach": True, "waitForDebuggerOnStart": True,
                                           "flatten": True}, session=BROWSER)
        self.send("Emulation.setDeviceMetricsOverride",
                  {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False})
        self.send("Browser.setDownloadBehavior",
                  {"behavior": "allow", "downloadPath": str(self.downloads),
                   "eventsEnabled": True}, session=BROWSER)

    def _watch(self, session: str) -> None:
        """Record the page's requests."""
        for domain in ("Page", "Network", "Runtime"):
            self.send(f"{domain}.enable", session=session)

    def popup(self) -> str:
        """The session of the first tab the page opened, watched like the page and let go."""
        attached = wait_for("the page to open a tab", lambda: self._event(
            "Target.attachedToTarget", lambda p: p["targetInfo"]["type"] == "page"
            and p["targetInfo"]["targetId"] != self.page_id), WAIT_S)
        session = attached["sessionId"]
        self._watch(session)
        self.send("Runtime.runIfWaitingForDebugger", session=session)
        return session

    @property
    def requests(self) -> list[str]:
        """The URLs the pages requested that the browser did send."""
        with self._cond:
            return [url for rid, url in self._sent if rid not in self._blocked]

    @property
    def blocked(self) -> list[str]:
        """The URLs the pages asked for that the browser refused to request."""
        with self._cond:
            return [url for rid, url in self._sent if rid in self._blocked]

    # ---- what a test does ------------------------------------------------------------------

    def goto(self, url: str) -> None:
        """Open ``url`` and wait until its document has loaded."""
        self.send("Page.navigate", {"url": url})
        self.wait_for(f"{url} to load", "document.readyState === 'complete'")

    def js(self, expression: str, session: str | None = None) -> Any:
        """The value of a JavaScript expression on the page (promises awaited)."""
        answer = self.send("Runtime.evaluate", {"expression": expression,
                                                "returnByValue": True, "awaitPromise": True},
                           session=session)
        if "exceptionDetails" in answer:
            raise BrowserError(f"{expression}: {answer['exceptionDetails']}")
        return answer["result"].get("value")

    def wait_for(self, what: str, expression: str, session: str | None = None) -> Any:
        """Poll a JavaScript expression until it is truthy; its value."""
        return wait_for(what, lambda: self.js(expression, session), WAIT_S)

    def click(self, selector: str) -> None:
        """A real mouse click (pressed and released) in the middle of the element."""
        self.answer(self._click(selector), "Input.dispatchMouseEvent")

    def click_to_open_tab(self, selector: str) -> str:
        """Click an element that opens a tab; the tab's session (``popup``). The tab is held
        until it is watched, and with it the page's renderer, which may be the tab's too: the
        click's answer comes after that."""
        released = self._click(selector)
        session = self.popup()
        self.answer(released, "Input.dispatchMouseEvent")
        return session

    def _click(self, selector: str) -> int:
        """Press the mouse on the element and post its release; the release's command id."""
        box = self.wait_for(f"{selector} to be shown", f"""(() => {{
            const e = document.querySelector({json.dumps(selector)});
            if (!e || e.offsetParent === null || e.disabled) return null;
            e.scrollIntoView({{block: "center"}});
            const r = e.getBoundingClientRect();
            return [r.left + r.width / 2, r.top + r.height / 2];
        }})()""")
        at = {"x": box[0], "y": box[1], "button": "left", "clickCount": 1}
        self.send("Input.dispatchMouseEvent", {"type": "mousePressed", **at})
        return self.post("Input.dispatchMouseEvent", {"type": "mouseReleased", **at})

    def type(self, selector: str, text: str) -> None:
        """Replace the text of an input field as a person would type it."""
        self.click(selector)
        self.js(f"document.querySelector({json.dumps(selector)}).select()")
        self.send("Input.insertText", {"text": text})

    def downloaded(self, after: int = 0) -> Path:
        """The file of the first download (after the first ``after``), once it has
        completed."""
        def ended() -> dict[str, Any] | None:
            with self._cond:
                done = [e["params"] for e in self.events
                        if e.get("method") == "Browser.downloadProgress"
                        and e["params"]["state"] in ("completed", "canceled")]
            return done[after] if len(done) > after else None

        done = wait_for("a download to complete", ended, WAIT_S)
        assert done["state"] == "completed", done
        begun = self._event("Browser.downloadWillBegin", lambda p: p["guid"] == done["guid"])
        assert begun is not None
        return self.downloads / begun["suggestedFilename"]

    def _event(self, method: str, match: Callable[[dict[str, Any]], bool]
               ) -> dict[str, Any] | None:
        with self._cond:
            return next((e["params"] for e in self.events
                         if e.get("method") == method and match(e["params"])), None)

    def screenshot(self, path: Path, session: str | None = None) -> None:
        """A PNG of the whole page, not just the window."""
        size = self.send("Page.getLayoutMetrics", session=session)["cssContentSize"]
        params = {"format": "png", "captureBeyondViewport": True,
                  "clip": {"x": 0, "y": 0, "width": size["width"], "height": size["height"],
                           "scale": 1}}
        path.write_bytes(base64.b64decode(
            self.send("Page.captureScreenshot", params, session=session)["data"]))

    # ---- the process -----------------------------------------------------------------------

    def close(self) -> None:
        """End chromium (politely, then by force) and its pipes."""
        if self._alive():
            try:
                os.write(self._out, json.dumps({"id": 0, "method": "Browser.close"}).encode()
                         + b"\0")
                self.proc.wait(20)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait(20)
        os.close(self._out)
        self._reader.join(20)
        os.close(self._in)
        self._log.close()

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _high_pipe() -> tuple[int, int]:
    """A pipe whose two ends are numbered above 4 (so putting them at 3 and 4 in the child
    cannot overwrite one with the other); both close on exec."""
    r, w = os.pipe()
    ends = (fcntl.fcntl(r, fcntl.F_DUPFD_CLOEXEC, 10), fcntl.fcntl(w, fcntl.F_DUPFD_CLOEXEC, 10))
    os.close(r)
    os.close(w)
    return ends
