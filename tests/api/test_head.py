"""HEAD on every GET route (RFC 9110 §9.1: a general-purpose server MUST support GET and HEAD; §9.3.2:
HEAD's answer has GET's status and header fields, and no content), ``services.api.security.HeadAsGet``:
the real app in process on a fresh embedded database, as a client would ask it. Each HEAD is compared
with the GET of the same request: the operations' 200s, an artifact's ETag and its 304, the 401 of a
missing key, the 403 of a permission and the 404 of another client's job."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import update

from services.api.app import create_app
from services.core.config import Settings
from services.db.engine import session_scope
from services.db.migrate import upgrade
from services.db.models import Job as JobRow
from spine_engine import register
from tests.conftest import make_key, spine_payload

PER_ANSWER = {"date", "x-request-id"}
"""Header fields that differ between two answers to the same request."""


class Api:
    """The API on a fresh embedded database, with the keys of two clients and of an admin."""

    def __init__(self, tmp_path: Path):
        self.settings = Settings(data_dir=tmp_path, api_key_cache_s=0)
        upgrade(self.settings, quiet=True)
        self.client = TestClient(create_app(self.settings))
        self.a = {"Authorization": f"Bearer {make_key(self.settings, 'clinic-a')}"}
        self.b = {"Authorization": f"Bearer {make_key(self.settings, 'clinic-b')}"}
        self.admin = {"Authorization": f"Bearer {make_key(self.settings, 'ops', 'admin')}"}

    def succeeded_job(self, result: dict[str, Any]) -> str:
        """A job of clinic a made succeeded with ``result`` on its row, as the worker leaves it."""
        job_id = str(self.client.post("/v1/jobs", json=spine_payload(curve_mm=25.0), headers=self.a).json()["id"])
        finished = datetime(2026, 12, 5, 9, 30, tzinfo=UTC)
        with session_scope(self.settings) as session:
            session.execute(update(JobRow).where(JobRow.id == uuid.UUID(job_id)).values(
                status="succeeded", result=result, started_at=finished, finished_at=finished, attempts=1,
                engine_version="test"))  # fmt: skip
        return job_id

    def head_as_get(self, path: str, headers: dict[str, str] | None = None) -> tuple[Any, Any]:
        """(GET, HEAD) of ``path``: HEAD has GET's status and header fields, but those of ``PER_ANSWER``,
        and no content; GET's Content-Length, when it has one, is the length of its content."""
        got = self.client.get(path, headers=headers)
        head = self.client.head(path, headers=headers)
        assert head.status_code == got.status_code, (path, head.status_code, got.status_code)
        assert head.content == b"", path
        assert {k: v for k, v in head.headers.items() if k not in PER_ANSWER} == {
            k: v for k, v in got.headers.items() if k not in PER_ANSWER
        }, path
        if "content-length" in got.headers:
            assert int(got.headers["content-length"]) == len(got.content), path
        return got, head


@pytest.fixture
def api(tmp_path: Path) -> Iterator[Api]:
    made = Api(tmp_path)
    with made.client:
        yield made


@pytest.fixture(scope="module")
def result() -> dict[str, Any]:
    """A real reconstruction as the worker stores it."""
    return register(spine_payload(curve_mm=25.0))


def test_head_answers_every_get_route_as_get_without_the_content(api: Api, result: dict[str, Any]) -> None:
    """Each HEAD was a 405 ``Allow: GET``: now GET's status and header fields, no content."""
    job_id = api.succeeded_job(result)
    paths = ["/healthz", "/readyz", "/v1/jobs", f"/v1/jobs/{job_id}", f"/v1/jobs/{job_id}/figure.png",
             f"/v1/jobs/{job_id}/figure.svg", f"/v1/jobs/{job_id}/fhir", "/openapi.json", "/"]  # fmt: skip
    for path in paths:
        got, _ = api.head_as_get(path, api.a)
        assert got.status_code == 200 and got.content, (path, got.status_code)
        assert "content-length" in got.headers, path
    got, _ = api.head_as_get(f"/v1/jobs/{job_id}/figure.png", api.a)
    assert got.headers["content-type"] == "image/png" and got.headers["etag"]
    assert got.headers["cache-control"] == "no-store"


def test_head_of_an_artifact_with_its_etag_is_a_304_as_get(api: Api, result: dict[str, Any]) -> None:
    """If-None-Match on HEAD: the 304 of GET (RFC 9110 §13.1.2 applies to GET and HEAD), with its ETag."""
    job_id = api.succeeded_job(result)
    tag = api.client.head(f"/v1/jobs/{job_id}/figure.png", headers=api.a).headers["etag"]
    _, head = api.head_as_get(f"/v1/jobs/{job_id}/figure.png", {**api.a, "If-None-Match": tag})
    assert head.status_code == 304 and head.headers["etag"] == tag
    other, _ = api.head_as_get(f"/v1/jobs/{job_id}/figure.png", {**api.a, "If-None-Match": '"png-0"'})
    assert other.status_code == 200


def test_head_is_refused_as_get_is(api: Api, result: dict[str, Any]) -> None:
    """HEAD needs what GET needs: a key (401 with WWW-Authenticate), a permission (403 of /v1/pacs
    for a client key), the client's own job (404 for another's), each with GET's header fields."""
    job_id = api.succeeded_job(result)
    unauthorized, _ = api.head_as_get("/v1/jobs")
    assert unauthorized.status_code == 401 and unauthorized.headers["www-authenticate"].startswith("Bearer")
    forbidden, _ = api.head_as_get("/v1/pacs", api.a)
    assert forbidden.status_code == 403
    for kind in ("", "/figure.png"):
        hidden, _ = api.head_as_get(f"/v1/jobs/{job_id}{kind}", api.b)
        assert hidden.status_code == 404
        seen, _ = api.head_as_get(f"/v1/jobs/{job_id}{kind}", api.admin)
        assert seen.status_code == 200


def test_head_where_there_is_no_get_is_a_405_naming_the_methods(api: Api) -> None:
    """A POST-only path answers HEAD as it answers GET: 405 with the path's methods, no content; and
    where GET is, a 405 lists HEAD beside it."""
    for path, allow in (("/v1/jobs/batch", "POST"), (f"/v1/jobs/{uuid.uuid4()}/cancel", "POST")):
        refused, _ = api.head_as_get(path, api.a)
        assert refused.status_code == 405 and refused.headers["allow"] == allow, path
    assert api.client.put("/healthz").headers["allow"] == "GET, HEAD"
