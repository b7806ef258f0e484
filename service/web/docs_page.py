"""The ReDoc page (``GET /redoc``) from the ReDoc bundle shipped with fastapi_offline, served
so that it asks no other host for anything.

The bundle shows its vendor's logo from a CDN (``cdn.redoc.ly``); the page's
Content-Security-Policy blocks that request, but the browser still tries it and logs the
refusal. The bundle is served here with that address replaced by an empty ``data:`` image,
whose load fails at once, which hides the logo (the bundle's own fallback).
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

import fastapi_offline
from fastapi import FastAPI
from fastapi.openapi.docs import get_redoc_html
from fastapi.responses import FileResponse, HTMLResponse, Response

#: Where the page, its bundle and the service's icon are served (without the API key).
REDOC_PATH, REDOC_BUNDLE_PATH, FAVICON_PATH = "/redoc", "/redoc/bundle.js", "/favicon.ico"
_BUNDLE = Path(fastapi_offline.__file__).parent / "static" / "redoc.standalone.js"
_VENDOR_LOGO = "https://cdn.redoc.ly/redoc/logo-mini.svg"


@cache
def _bundle() -> bytes:
    """The ReDoc bundle without its vendor's logo address (read once)."""
    return _BUNDLE.read_text(encoding="utf-8").replace(_VENDOR_LOGO, "data:,").encode()


def mount_redoc(app: FastAPI) -> None:
    """Serve ReDoc at ``REDOC_PATH`` (build the app with ``redoc_url=None``) and the icon at
    ``FAVICON_PATH``, the one browsers ask every host for."""

    @app.get(REDOC_PATH, include_in_schema=False)
    async def redoc() -> HTMLResponse:
        return get_redoc_html(openapi_url=app.openapi_url or "/openapi.json",
                              title=f"{app.title} - ReDoc", redoc_js_url=REDOC_BUNDLE_PATH,
                              redoc_favicon_url=FAVICON_PATH, with_google_fonts=False)

    @app.get(FAVICON_PATH, include_in_schema=False)
    async def favicon() -> FileResponse:
        return FileResponse(Path(__file__).parent / "static" / "favicon.svg",
                            media_type="image/svg+xml")

    @app.get(REDOC_BUNDLE_PATH, include_in_schema=False)
    async def redoc_bundle() -> Response:
        return Response(_bundle(), media_type="text/javascript")
