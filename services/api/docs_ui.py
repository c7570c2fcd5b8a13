"""The API documentation pages, Swagger UI at ``/docs`` and ReDoc at ``/redoc``, served by the
service itself: their scripts and styles come from ``services/api/static/docs/`` (copied by
``make web`` from the pinned npm packages swagger-ui-dist 5.35.0, Apache-2.0, and redoc 3.0.1, MIT;
licences beside them), so the pages work offline and load nothing from a CDN. Neither page has an
inline script (Swagger UI is started by ``swagger-init.js``; ReDoc starts itself on its
``<redoc spec-url>`` element), so a policy of ``script-src 'self'`` serves them.

Mount with ``mount_docs(app)`` on an app made with ``FastAPI(docs_url=None, redoc_url=None)``
(FastAPI's own pages load their assets from a CDN).
"""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import HTMLResponse, PlainTextResponse, Response
from fastapi.staticfiles import StaticFiles

DOCS_DIR = Path(__file__).resolve().parent / "static" / "docs"
ASSETS_URL = "/docs/assets"

SWAGGER_PAGE = f"""<!doctype html>
<html lang="en">
  <head>
    <meta charset="utf-8" />
    <meta name="viewport" content="width=device-width, initial-scale=1" />
    <title>Spine reconstruction service API (Swagger UI)</title>
    <link rel="icon" href="data:," />
    <link rel="stylesheet" href="{ASSETS_URL}/swagger-ui.css" />
  </head>
  <body>
    <div id="swagger-ui"></div>
    <script src="{ASSETS_URL}/swagger-ui-bundle.js"></script>
    <script src="{ASSETS_URL}/swagger-init.js"></script>
  </body>
</html>
"""

REDOC_PAGE = f"""<!doctype html>
<html lang="en">
  <head>
    <meta charset="utf-8" />
    <meta name="viewport" content="width=device-width, initial-scale=1" />
    <title>Spine reconstruction service API (ReDoc)</title>
    <link rel="icon" href="data:," />
  </head>
  <body>
    <redoc spec-url="/openapi.json"></redoc>
    <script type="module" src="{ASSETS_URL}/redoc.standalone.js"></script>
  </body>
</html>
"""


def mount_docs(app: FastAPI, docs_dir: Path = DOCS_DIR) -> None:
    """Serve Swagger UI at ``/docs``, ReDoc at ``/redoc`` and their assets under ``/docs/assets``.

    Without the assets (no ``make web`` build) both pages say how to make them (404).
    """
    built = (docs_dir / "swagger-ui-bundle.js").is_file() and (docs_dir / "redoc.standalone.js").is_file()

    def page(html: str) -> Response:
        if not built:
            return PlainTextResponse(
                "The API documentation pages are not built: run `make web`. The schema is at /openapi.json.",
                status_code=404,
            )
        return HTMLResponse(html, headers={"Cache-Control": "no-cache"})

    def swagger() -> Response:
        return page(SWAGGER_PAGE)

    def redoc() -> Response:
        return page(REDOC_PAGE)

    app.add_api_route("/docs", swagger, methods=["GET", "HEAD"], include_in_schema=False)
    app.add_api_route("/redoc", redoc, methods=["GET", "HEAD"], include_in_schema=False)
    if built:
        app.mount(ASSETS_URL, StaticFiles(directory=docs_dir), name="docs-assets")
