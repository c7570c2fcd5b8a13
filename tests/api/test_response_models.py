"""The JSON routes answer through their declared ``response_model``: the handler returns the model,
FastAPI validates and serialises it, and nothing the model does not declare reaches a client.

``test_every_json_route_answers_through_its_response_model`` fails when a handler goes back to
returning a ``Response`` (FastAPI then skips the model); ``test_an_undeclared_member_never_leaks``
fails when a stored result's undeclared member reaches the answer, as it did when the handlers
returned the stored JSON as it was.
"""

from __future__ import annotations

import json
import uuid
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import fastapi.routing
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import insert, update

from services.api import schemas
from services.api.app import create_app
from services.api.schemas import Job
from services.core.config import DicomwebConfig, Settings
from services.core.problems import problem
from services.db.engine import session_scope
from services.db.jobs import get_job, job_json
from services.db.migrate import upgrade
from services.db.models import Job as JobRow
from services.db.models import WebhookDelivery
from services.dicom.dicomweb import Pacs
from spine_engine import register
from tests.api.test_api_jobs import TIMESTAMP
from tests.conftest import make_key, spine_payload


@pytest.fixture(scope="module")
def result() -> dict[str, Any]:
    """A real reconstruction as the worker stores it (``RegistrationResult`` as JSON)."""
    return register(spine_payload())


@pytest.fixture
def app_settings(tmp_path: Path) -> Iterator[tuple[TestClient, Settings]]:
    settings = Settings(data_dir=tmp_path, pacs_clients="test-client")  # make_key's client, to reach /v1/pacs
    upgrade(settings, quiet=True)
    with TestClient(create_app(settings)) as client:
        client.headers["Authorization"] = f"Bearer {make_key(settings)}"
        yield client, settings


def _set(settings: Settings, job_id: str, **values: Any) -> None:
    with session_scope(settings) as session:
        session.execute(update(JobRow).where(JobRow.id == uuid.UUID(job_id)).values(**values))
        session.commit()


def _succeed(settings: Settings, job_id: str, result: dict[str, Any]) -> None:
    started = datetime(2026, 12, 1, 17, 0, 0, tzinfo=UTC)  # a whole second: the fraction is still written
    _set(settings, job_id, status="succeeded", result=result, started_at=started, finished_at=started,
         attempts=1, engine_version="test")  # fmt: skip


def test_every_json_route_answers_through_its_response_model(
    app_settings: tuple[TestClient, Settings], payload: dict[str, Any], result: dict[str, Any],
    monkeypatch: pytest.MonkeyPatch,
) -> None:  # fmt: skip
    api, settings = app_settings
    seen: list[Any] = []
    serialize = fastapi.routing.serialize_response

    async def recording(**kwargs: Any) -> Any:  # FastAPI calls it only for what a handler returned that is no Response
        seen.append(kwargs["response_content"])
        return await serialize(**kwargs)

    monkeypatch.setattr(fastapi.routing, "serialize_response", recording)
    # The PACS routes answer 2xx only with a PACS: one that is configured and lists no image (tests/dicom
    # has them on a real Orthanc).
    monkeypatch.setattr(Settings, "dicomweb", property(lambda _settings: DicomwebConfig("http://127.0.0.1:9/dicom-web")))
    monkeypatch.setattr(Pacs, "study_images", lambda _self, _study: [])
    monkeypatch.setattr(Settings, "stores_dicom_results", property(lambda _settings: True))  # for dicom-store
    job_id = api.post("/v1/jobs", json=payload).json()["id"]
    storable = api.post("/v1/jobs", json={**payload, "study": {"study_instance_uid": "1.2.3", "patient_id": "P-1"}})
    _succeed(settings, stored_id := storable.json()["id"], result)  # a succeeded job with the patient's identity
    calls: dict[tuple[str, str], tuple[str, str, dict[str, Any] | None]] = {
        ("POST", "/v1/jobs"): ("POST", "/v1/jobs", payload),
        ("POST", "/v1/jobs/batch"): ("POST", "/v1/jobs/batch", {"jobs": [payload, {"not": "a payload"}]}),
        ("GET", "/v1/jobs"): ("GET", "/v1/jobs", None),
        ("GET", "/v1/jobs/{job_id}"): ("GET", f"/v1/jobs/{job_id}", None),
        ("POST", "/v1/jobs/{job_id}/cancel"): ("POST", f"/v1/jobs/{job_id}/cancel", None),
        ("POST", "/v1/jobs/{job_id}/dicom-store"): ("POST", f"/v1/jobs/{stored_id}/dicom-store", None),
        ("GET", "/v1/pacs"): ("GET", "/v1/pacs", None),
        ("GET", "/v1/pacs/studies/{study_instance_uid}/images"): ("GET", "/v1/pacs/studies/1.2.3/images", None),
        ("GET", "/healthz"): ("GET", "/healthz", None),
        ("GET", "/readyz"): ("GET", "/readyz", None),
        ("GET", "/v1/patients/{patient_id}/measures"): ("GET", "/v1/patients/P-1/measures", None),
    }
    models = _json_answers(api.app.openapi())  # type: ignore[attr-defined]
    assert models.keys() == calls.keys(), "a JSON route of the contract is missing from this test (or gone)"
    for key, (method, url, body) in calls.items():
        seen.clear()
        response = api.request(method, url, json=body)
        assert response.status_code < 300, (key, response.text)
        assert len(seen) == 1, f"{key}: the handler returned a Response, bypassing its response_model"
        assert isinstance(seen[0], models[key]), (key, type(seen[0]))


def _json_answers(contract: dict[str, Any]) -> dict[tuple[str, str], type[Any]]:
    """(method, path) -> the model of the route's 2xx application/json answer, from the OpenAPI."""
    models: dict[tuple[str, str], type[Any]] = {}
    for path, operations in contract["paths"].items():
        for method, operation in operations.items():
            for code, answer in operation.get("responses", {}).items():
                ref = answer.get("content", {}).get("application/json", {}).get("schema", {}).get("$ref")
                if str(code).startswith("2") and ref:
                    models[(method.upper(), path)] = getattr(schemas, ref.rsplit("/", 1)[1])
    return models


def test_an_undeclared_member_never_leaks(
    app_settings: tuple[TestClient, Settings], payload: dict[str, Any], result: dict[str, Any]
) -> None:
    """A member the model does not declare (say, one an older engine stored) is not in the answer."""
    api, settings = app_settings
    job_id = api.post("/v1/jobs", json=payload).json()["id"]
    stored = json.loads(json.dumps(result))
    stored["internal_note"] = "not part of the contract"
    stored["measures"]["debug_trace"] = [1, 2, 3]
    _succeed(settings, job_id, stored)
    read = api.get(f"/v1/jobs/{job_id}").json()
    listed = api.get("/v1/jobs").json()["jobs"][0]
    for job in (read, listed):
        assert "internal_note" not in job["result"] and "debug_trace" not in job["result"]["measures"]
        assert job["result"]["measures"] == result["measures"]
        assert TIMESTAMP.match(job["started_at"]) and job["started_at"] == "2026-12-01T17:00:00.000000Z"


def test_absent_members_stay_absent(app_settings: tuple[TestClient, Settings], payload: dict[str, Any]) -> None:
    """payload, dicom, dicom_stores and deliveries only in GET by id; a problem's unset members absent."""
    api, settings = app_settings
    posted = api.post("/v1/jobs", json=payload)
    job_id = posted.json()["id"]
    detail_only = {"payload", "dicom", "dicom_stores", "deliveries"}
    summaries = [posted.json(), api.get("/v1/jobs").json()["jobs"][0],
                 api.post("/v1/jobs/batch", json={"jobs": [payload]}).json()["results"][0]["job"]]  # fmt: skip
    for summary in summaries:
        assert not detail_only & summary.keys() and {"result", "error", "study"} <= summary.keys()
    read = api.get(f"/v1/jobs/{job_id}").json()
    assert detail_only <= read.keys() and read["deliveries"] == [] and read["dicom_stores"] == []
    assert read["dicom"] is None
    batch = api.post("/v1/jobs/batch", json={"jobs": [payload, 7]}).json()["results"]
    assert batch[0].keys() == {"index", "status", "job"} and batch[1].keys() == {"index", "status", "problem"}
    _set(settings, job_id, status="failed", error=problem("fit-failed", "no fit", iterations=3))
    assert api.get(f"/v1/jobs/{job_id}").json()["error"] == problem("fit-failed", "no fit", iterations=3)


def test_deliveries_are_read_from_their_rows(
    app_settings: tuple[TestClient, Settings], payload: dict[str, Any]
) -> None:
    api, settings = app_settings
    job_id = api.post("/v1/jobs", json=payload).json()["id"]
    _set(settings, job_id, callback_url="https://hooks.example/cb")
    at = datetime(2026, 12, 1, 17, 0, 0, tzinfo=UTC)
    with session_scope(settings) as session:
        session.execute(insert(WebhookDelivery).values(
            job_id=uuid.UUID(job_id), message_id="msg_1", event="job.cancelled", attempt=1, url="https://hooks.example/cb",
            attempted_at=at, status_code=503, error="HTTP 503", duration_ms=12.5, next_attempt_at=None))  # fmt: skip
        session.commit()
    assert api.get(f"/v1/jobs/{job_id}").json()["deliveries"] == [
        {"event": "job.cancelled", "message_id": "msg_1", "attempt": 1, "url": "https://hooks.example/cb",
         "attempted_at": "2026-12-01T17:00:00.000000Z", "status_code": 503, "error": "HTTP 503",
         "duration_ms": 12.5, "next_attempt_at": None}
    ]  # fmt: skip


def test_the_webhook_data_is_the_jobs_summary(
    app_settings: tuple[TestClient, Settings], payload: dict[str, Any], result: dict[str, Any]
) -> None:
    """``job_json`` (a webhook's ``data``, written in the db layer the API model cannot live in) and
    ``Job.summary``, both built from ``job_members``, write the same JSON: times and ids included."""
    api, settings = app_settings
    done, failed = (api.post("/v1/jobs", json=payload).json()["id"] for _ in range(2))
    _succeed(settings, done, result)
    _set(settings, failed, status="failed", error=problem("fit-failed", "no fit", instance="/x", iterations=3))
    with session_scope(settings) as session:
        for job_id in (done, failed):
            row = get_job(session, uuid.UUID(job_id))
            assert json.loads(Job.summary(row).model_dump_json(exclude_unset=True)) == job_json(row)


def test_a_result_a_newer_engine_stored_is_still_served(
    app_settings: tuple[TestClient, Settings], payload: dict[str, Any], result: dict[str, Any]
) -> None:
    """After a rollback (or with a worker upgraded before the API), a stored result may name an assumption or
    an unreliable quantity this engine does not know: the two lists are extensible enums
    (``spine_engine.models.extensible``), so the job and the jobs list answer with the names kept, where the
    stored name used to make both answer 500 (no job lost to a version's list)."""
    api, settings = app_settings
    job_id = api.post("/v1/jobs", json=payload).json()["id"]
    stored = json.loads(json.dumps(result))
    stored["fit"]["assumed"].append({"name": "a_prior_of_a_later_engine", "view": "pa", "reason": "later"})
    stored["fit"]["unreliable"].append("a_quantity_of_a_later_engine")
    _succeed(settings, job_id, stored)
    read = api.get(f"/v1/jobs/{job_id}")
    listed = api.get("/v1/jobs")
    assert read.status_code == 200 and listed.status_code == 200, (read.text, listed.text)
    for job in (read.json(), listed.json()["jobs"][0]):
        assert job["result"]["fit"]["assumed"][-1]["name"] == "a_prior_of_a_later_engine"
        assert job["result"]["fit"]["unreliable"][-1] == "a_quantity_of_a_later_engine"
