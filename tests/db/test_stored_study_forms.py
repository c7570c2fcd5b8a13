"""A study stored in a form the contract no longer takes (`study_date` as a date-time at midnight or as
Unix seconds, a Patient ID of spaces: pydantic's lax reading took them before `Study` refused them) is read
as the API then read it by every consumer (`services.db.job_forms.stored_study`): the job view, the SR,
the FHIR export and the follow-up answer, where the SR and FHIR export answered 500 and the follow-up
left the visit out of every change. Both databases, through the API."""

from __future__ import annotations

import io
import uuid
from collections.abc import Iterator
from typing import Any

import pydicom
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import update

from services.api.app import create_app
from services.core.config import Settings
from services.db.engine import session_factory
from services.db.job_forms import job_study, stored_study
from services.db.models import Job
from spine_engine import register
from spine_engine.models import Study, read_study_date
from tests.conftest import make_key, spine_payload

BACKENDS = pytest.mark.parametrize("db_settings", ["sqlite", "postgresql"], indirect=True)


@pytest.mark.parametrize(
    ("stored", "day"),
    [("2026-02-10", "2026-02-10"), ("2026-02-10T00:00:00", "2026-02-10"), ("86400", "1970-01-02"), (0, "1970-01-01"),
     ("not a date", None)],
)  # fmt: skip
def test_a_stored_study_date_is_read_as_the_api_read_it(stored: Any, day: str | None) -> None:
    study = stored_study({"study_instance_uid": "1.2.3", "study_date": stored, "patient_id": "   "})
    assert study.get("study_date") == day and "patient_id" not in study
    assert Study.model_validate(study).study_date == (None if day is None else read_study_date(day))


@pytest.fixture(scope="module")
def result() -> dict[str, Any]:
    return register(spine_payload())


@pytest.fixture
def client(db_settings: Settings) -> Iterator[TestClient]:
    with TestClient(create_app(db_settings)) as c:
        c.headers["Authorization"] = f"Bearer {make_key(db_settings, f'stored-{uuid.uuid4().hex[:8]}')}"
        yield c


@BACKENDS
def test_a_job_stored_with_a_lax_study_is_served_with_its_day(
    client: TestClient, db_settings: Settings, result: dict[str, Any]
) -> None:
    patient = f"P-{uuid.uuid4().hex[:8]}"
    ids = []
    for stored in ("2026-02-10T00:00:00", "86400"):
        payload = spine_payload()
        payload["study"] = {"study_instance_uid": f"1.2.826.0.1.3680043.8.498.{uuid.uuid4().int % 10**12}",
                            "patient_id": patient, "study_date": "2026-01-01"}  # fmt: skip
        answer = client.post("/v1/jobs", json=payload)
        assert answer.status_code == 202, answer.text
        job_id = uuid.UUID(answer.json()["id"])
        payload["study"]["study_date"] = stored  # as the API stored it before it took YYYY-MM-DD only
        with session_factory(db_settings)() as session:
            stored_row = update(Job).where(Job.id == job_id)
            session.execute(stored_row.values(payload=payload, status="succeeded", result=result))
            session.commit()
            row = session.get(Job, job_id)
            assert row is not None and (job_study(row) or {})["study_date"] != stored
        ids.append(job_id)
    days = ("2026-02-10", "1970-01-02")
    for job_id, day in zip(ids, days, strict=True):
        view = client.get(f"/v1/jobs/{job_id}")
        assert view.status_code == 200, view.text
        assert view.json()["study"]["study_date"] == day
        sr = client.get(f"/v1/jobs/{job_id}/sr.dcm")
        assert sr.status_code == 200, sr.text
        assert pydicom.dcmread(io.BytesIO(sr.content)).StudyDate == day.replace("-", "")
        fhir = client.get(f"/v1/jobs/{job_id}/fhir")
        assert fhir.status_code == 200, fhir.text
        observations = [e["resource"] for e in fhir.json()["entry"] if e["resource"]["resourceType"] == "Observation"]
        assert observations and all(o["effectiveDateTime"] == day for o in observations)
    follow = client.get(f"/v1/patients/{patient}/measures")
    assert follow.status_code == 200, follow.text
    body = follow.json()
    assert sorted(v["study_date"] for v in body["visits"]) == sorted(days)
    assert body["changes"], "two dated visits of the same measures make changes"
