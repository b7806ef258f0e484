"""The cell's web page (``GET /``): static HTML, CSS and a little plain JavaScript shipped in
the package, calling the same REST API with the same API key (kept in the browser tab's
session storage). No asset comes from another host."""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import RedirectResponse
from fastapi.staticfiles import StaticFiles

#: The page's files, served at ``/ui/``.
STATIC_DIR = Path(__file__).parent / "static"


def mount_page(app: FastAPI) -> None:
    """Serve the page at ``/ui/`` and send ``/`` there."""
    app.mount("/ui", StaticFiles(directory=STATIC_DIR, html=True), name="ui")

    @app.get("/", include_in_schema=False)
    async def root() -> RedirectResponse:
        return RedirectResponse("/ui/")
