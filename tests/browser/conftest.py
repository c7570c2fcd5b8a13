"""The browser tests' shared fixtures: one `spine serve` (API + worker child, embedded SQLite) on a
free port of 127.0.0.1 and one headless Chromium for every page module of the session (each test
opens its own browser context), instead of one of each per module.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
from page_fixtures import CHROMIUM_FLAGS, chromium_path, free_port

API_KEYS: dict[str, str] = {}


@pytest.fixture(scope="session")
def live_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """`spine serve` on a free port of 127.0.0.1: uvicorn API and its Celery worker child."""
    data_dir = tmp_path_factory.mktemp("page-service")
    port = free_port()
    env = {
        **os.environ,
        "SPINE_DATA_DIR": str(data_dir),
        "SPINE_QUEUE_NAME": f"spine-page-{uuid.uuid4().hex[:8]}",
        "SPINE_WORKER_CONCURRENCY": "1",
        "SPINE_LOG_LEVEL": "WARNING",
    }
    for key in ("DATABASE_URL", "CELERY_BROKER_URL", "SPINE_SERVE_WORKER"):
        env.pop(key, None)
    log_path = data_dir / "serve.log"
    with log_path.open("wb") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "serve", "--host", "127.0.0.1", "--port", str(port)],
            env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
        )  # fmt: skip
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get(f"{url}/readyz", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"spine serve did not become ready:\n{log_path.read_text(errors='replace')[-4000:]}")
            time.sleep(0.2)
        printed = re.search(r"^(spine_[0-9a-f]{12}_[A-Za-z0-9_-]{43})$", log_path.read_text(errors="replace"), re.M)
        assert printed, f"spine serve printed no API key:\n{log_path.read_text(errors='replace')[-4000:]}"
        API_KEYS[url] = printed.group(1)
        yield url
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()


@pytest.fixture(scope="session")
def api_key(live_url: str) -> str:
    return API_KEYS[live_url]


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
