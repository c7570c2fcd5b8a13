"""Swagger UI and ReDoc served by the service itself (services/api/docs_ui.py): offline, no CDN,
under a policy without inline scripts; rendered in Debian's Chromium."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import uvicorn
from fastapi import FastAPI
from fastapi.testclient import TestClient
from page_fixtures import PageWatch, free_port
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from services.api.docs_ui import DOCS_DIR, mount_docs
from services.api.security import DOCS_POLICY

pytestmark = pytest.mark.browser

STRICT_DOCS_POLICY = DOCS_POLICY  # the policy the service sends on /docs and /redoc


class Policy:
    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        async def with_policy(message: Message) -> None:
            if message["type"] == "http.response.start":
                message.setdefault("headers", []).append((b"content-security-policy", STRICT_DOCS_POLICY.encode()))
            await send(message)

        await self.app(scope, receive, with_policy)


def docs_app() -> FastAPI:
    app = FastAPI(title="Docs test", docs_url=None, redoc_url=None)

    @app.get("/v1/ping", summary="Answers pong")
    def ping() -> dict[str, str]:
        return {"ping": "pong"}

    mount_docs(app)
    app.add_middleware(Policy)
    return app


@pytest.fixture(scope="module")
def docs_url() -> Iterator[str]:
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(docs_app(), host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 20
    while True:
        try:
            httpx.get(url + "/openapi.json", timeout=1)
            break
        except httpx.TransportError:
            assert time.monotonic() < deadline, "the docs test server did not start"
            time.sleep(0.1)
    yield url
    server.should_exit = True
    thread.join(10)


def test_the_pages_and_assets_are_served_from_the_service() -> None:
    client = TestClient(docs_app())
    for path in ("/docs", "/redoc"):
        html = client.get(path).text
        assert "https://" not in html and "<script>" not in html  # no CDN, no inline script
    for asset in ("swagger-ui-bundle.js", "swagger-ui.css", "swagger-init.js", "redoc.standalone.js"):
        response = client.get(f"/docs/assets/{asset}")
        assert response.status_code == 200 and len(response.content) > 100, asset
    assert (DOCS_DIR / "swagger-ui.LICENSE.txt").is_file() and (DOCS_DIR / "redoc.LICENSE.txt").is_file()


def test_without_the_build_the_pages_say_how_to_make_it(tmp_path: Path) -> None:
    app = FastAPI(docs_url=None, redoc_url=None)
    mount_docs(app, tmp_path)
    response = TestClient(app).get("/docs")
    assert response.status_code == 404 and "make web" in response.text


def test_swagger_ui_and_redoc_render_offline(browser: Any, docs_url: str, tmp_path: Path) -> None:
    context = browser.new_context(viewport={"width": 1280, "height": 900})
    page = context.new_page()
    watch = PageWatch(page, docs_url)
    blocked: list[str] = []
    page.on("requestfailed", lambda r: blocked.append(r.url) if r.failure == "csp" else None)
    page.goto(docs_url + "/docs")
    page.wait_for_selector(".opblock", timeout=30_000)
    assert "Answers pong" in (page.text_content("#swagger-ui") or "")
    page.screenshot(path=str(tmp_path / "swagger.png"))
    page.goto(docs_url + "/redoc")
    page.get_by_text("Answers pong").first.wait_for(timeout=30_000)
    page.screenshot(path=str(tmp_path / "redoc.png"))
    # ReDoc 3 draws its maker's logo from its CDN (hard-coded in redoc.standalone.js, hidden when it
    # fails to load): the page's policy (img-src 'self' data:) stops it in the browser, so nothing leaves
    page.wait_for_timeout(500)
    assert all(url in blocked for url in watch.foreign), (watch.foreign, blocked)
    assert not [e for e in watch.errors if "Content Security Policy" not in e and "ERR_BLOCKED_BY_CSP" not in e], (
        watch.errors
    )
    context.close()
