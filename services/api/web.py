"""The web front end: the built single page (``web/`` → ``services/api/static/``) served at ``/``.

Only ``/`` (and ``/index.html``) and ``/assets/*`` are taken, so nothing under ``/v1``,
``/healthz``, ``/readyz``, ``/metrics`` or ``/docs`` is shadowed. The page talks only to this
service (its Content-Security-Policy allows nothing else). When the build is missing (``make web``
makes it), ``/`` says so.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import FileResponse, PlainTextResponse, Response
from fastapi.staticfiles import StaticFiles

STATIC_DIR = Path(__file__).resolve().parent / "static"

# Inline styles are allowed for the 3D view's SVG fallback (three's SVGRenderer styles each face);
# scripts only from this service, and nothing is fetched from anywhere else.
CONTENT_SECURITY_POLICY = (
    "default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' blob: data:; "
    "connect-src 'self'; font-src 'self'; object-src 'none'; base-uri 'none'; frame-ancestors 'none'; "
    "form-action 'none'"
)
PAGE_HEADERS = {
    "Content-Security-Policy": CONTENT_SECURITY_POLICY,
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-cache",
}


def mount_web(app: FastAPI, static_dir: Path = STATIC_DIR) -> None:
    """Serve the built page at ``/`` and its hashed assets under ``/assets``."""
    index = static_dir / "index.html"

    def page() -> Response:
        if not index.is_file():
            return PlainTextResponse(
                "The web front end is not built: run `make web` (npm ci && npm run build in web/).",
                status_code=404,
                headers={"Cache-Control": "no-cache"},
            )
        return FileResponse(index, media_type="text/html; charset=utf-8", headers=PAGE_HEADERS)

    app.add_api_route("/", page, methods=["GET", "HEAD"], include_in_schema=False)
    app.add_api_route("/index.html", page, methods=["GET", "HEAD"], include_in_schema=False)
    assets = static_dir / "assets"
    if assets.is_dir():
        app.mount("/assets", StaticFiles(directory=assets), name="web-assets")
