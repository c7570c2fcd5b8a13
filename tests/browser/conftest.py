"""The browser tests' shared fixtures: one `spine serve` (API + worker child, embedded SQLite) on a
free port of 127.0.0.1 and one headless Chromium for every page module of the session (each test
opens its own browser context), instead of one of each per module.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from page_fixtures import CHROMIUM_FLAGS, chromium_path, start_serve, stop_serve

API_KEYS: dict[str, str] = {}
DATA_DIRS: dict[str, Path] = {}


@pytest.fixture(scope="session")
def live_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """`spine serve` on a free port of 127.0.0.1: uvicorn API and its Celery worker child."""
    serve = start_serve(tmp_path_factory.mktemp("page-service"))
    API_KEYS[serve.url] = serve.api_key
    DATA_DIRS[serve.url] = serve.log.parent
    try:
        yield serve.url
    finally:
        stop_serve(serve.proc)


@pytest.fixture(scope="session")
def api_key(live_url: str) -> str:
    return API_KEYS[live_url]


@pytest.fixture(scope="session")
def live_data_dir(live_url: str) -> Path:
    """The data directory of the session's `spine serve` (its embedded SQLite database)."""
    return DATA_DIRS[live_url]


@pytest.fixture(scope="session")
def browser() -> Iterator[Any]:
    from playwright.sync_api import sync_playwright

    executable = chromium_path()
    if executable is None:
        pytest.skip("no Chromium executable ($SPINE_CHROMIUM, /usr/bin/chromium): `make browser` installs Debian's")
    with sync_playwright() as pw:
        chromium = pw.chromium.launch(executable_path=executable, headless=True, args=CHROMIUM_FLAGS)
        try:
            yield chromium
        finally:
            chromium.close()
