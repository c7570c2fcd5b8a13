"""The web front end as the API serves it: the page at /, its assets, nothing shadowed, and the
committed build (services/api/static/) matching web/'s sources."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from services.api.web import STATIC_DIR, mount_web
from services.core.problems import PROBLEM_BASE

ROOT = Path(__file__).resolve().parents[2]
WEB = ROOT / "web"
SOURCE_FILES = ["index.html", "package.json", "package-lock.json", "tsconfig.json", "vite.config.ts"]


def test_the_page_is_served_at_the_root_with_a_strict_policy(api: TestClient) -> None:
    response = api.get("/")
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("text/html")
    policy = response.headers["content-security-policy"]
    assert "default-src 'self'" in policy and "script-src 'self';" in policy and "connect-src 'self'" in policy
    assert "<title>Spine reconstruction</title>" in response.text
    assert api.head("/").status_code == 200
    assert api.get("/index.html").text == response.text


def test_the_page_loads_only_its_own_assets(api: TestClient) -> None:
    html = api.get("/").text
    refs = re.findall(r'(?:src|href)="([^"]+)"', html)
    assets = [r for r in refs if r.startswith("/assets/")]
    assert any(a.endswith(".js") for a in assets) and any(a.endswith(".css") for a in assets)
    for ref in refs:
        assert ref.startswith(("/assets/", "/docs", "#", "data:")), f"{ref} is not served by the service"
    for asset in assets:
        response = api.get(asset)
        assert response.status_code == 200, asset
        assert len(response.content) > 100
    assert "https://" not in api.get(next(a for a in assets if a.endswith(".css"))).text  # no web fonts


def test_nothing_of_the_api_is_shadowed(api: TestClient) -> None:
    assert api.get("/healthz").json()["status"] == "ok"
    assert api.get("/readyz").status_code == 200
    assert api.get("/metrics").status_code == 200
    assert api.get("/docs").status_code == 200
    assert api.get("/openapi.json").status_code == 200
    assert api.get("/v1/jobs").status_code == 200
    missing = api.get("/v1/nothing-here")
    assert missing.status_code == 404 and missing.json()["type"] == PROBLEM_BASE + "route-not-found"
    assert api.get("/assets/no-such-file.js").status_code == 404
    assert api.post("/").status_code == 405
    assert "/" not in api.get("/openapi.json").json()["paths"]


def test_without_a_build_the_root_says_how_to_make_it(tmp_path: Path) -> None:
    app = FastAPI()
    mount_web(app, tmp_path)
    response = TestClient(app).get("/")
    assert response.status_code == 404 and "make web" in response.text


def sources_sha256() -> str:
    """What web/vite.config.ts's sourcesHash() computes."""
    files = sorted(
        [f for f in SOURCE_FILES] + [p.relative_to(WEB).as_posix() for p in (WEB / "src").rglob("*") if p.is_file()]
    )
    digest = hashlib.sha256()
    for name in files:
        digest.update(f"{name}\n{hashlib.sha256((WEB / name).read_bytes()).hexdigest()}\n".encode())
    return digest.hexdigest()


@pytest.mark.skipif(not (WEB / "package.json").exists(), reason="no web/ sources beside this install")
def test_the_committed_build_matches_the_sources() -> None:
    info = json.loads((STATIC_DIR / "build-info.json").read_text())
    assert info["sources_sha256"] == sources_sha256(), (
        "services/api/static/ is stale: run `make web` and commit services/api/static/"
    )


def test_the_service_serves_its_own_api_docs(api: TestClient) -> None:
    """/docs and /redoc come from the service: every script and style they load is one of
    its own assets, so the pages work offline (FastAPI's defaults load both from a CDN)."""
    for path in ("/docs", "/redoc"):
        answer = api.get(path)
        assert answer.status_code == 200, path
        sources = re.findall(r'(?:src|href|spec-url)="([^"]+)"', answer.text)
        assert sources, path
        for source in sources:
            assert (source.startswith("/") and not source.startswith("//")) or source == "data:,", (path, source)
            if source.startswith("/docs/assets/"):
                assert api.get(source).status_code == 200, source
