"""The cell's web page (``GET /``): static HTML, CSS and a little plain JavaScript shipped in
the package, calling the same REST API with the same API key (kept in the browser tab's
session storage). No asset comes from another host.

Every HTML answer (the page, ``/docs``, ``/redoc``, reports) carries a Content-Security-Policy
that lets the browser load nothing from another host: ReDoc's bundle, for one, shows a logo
from its vendor's server, which on an air-gapped cell network would hang or leak.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import RedirectResponse
from fastapi.staticfiles import StaticFiles
from starlette.types import ASGIApp, Message, Receive, Scope, Send

#: The page's files, served at ``/ui/``.
STATIC_DIR = Path(__file__).parent / "static"
#: This host only; inline scripts and styles (Swagger UI's and ReDoc's pages have them), data:
#: images (the reports' plots) and blob: URLs (ReDoc's worker, the page's downloads).
CONTENT_SECURITY_POLICY = ("default-src 'self' 'unsafe-inline' data: blob:; "
                           "img-src 'self' data: blob:; connect-src 'self' blob:")


class LocalOnlyPages:
    """ASGI middleware: adds ``CONTENT_SECURITY_POLICY`` to every HTML response."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def send_with_policy(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = message.get("headers", [])
                if any(k == b"content-type" and v.startswith(b"text/html") for k, v in headers):
                    message["headers"] = [*headers, (b"content-security-policy",
                                                     CONTENT_SECURITY_POLICY.encode())]
            await send(message)

        await self.app(scope, receive, send_with_policy)


def mount_page(app: FastAPI) -> None:
    """Serve the page at ``/ui/`` and send ``/`` there; HTML answers load nothing from
    another host (``LocalOnlyPages``)."""
    app.add_middleware(LocalOnlyPages)
    app.mount("/ui", StaticFiles(directory=STATIC_DIR, html=True), name="ui")

    @app.get("/", include_in_schema=False)
    async def root() -> RedirectResponse:
        return RedirectResponse("/ui/")
