"""Jobs made with an Idempotency-Key, on both databases the service runs on: a batch sent with a key
stores its jobs as every other path does (the study's identifier columns that the DICOM filters and the
follow-up read included), an empty key is refused, and the answers carry the headers openapi.yaml
documents for them."""

from __future__ import annotations

import uuid
from pathlib import Path
from typing import Any

import pytest
import yaml
from fastapi.testclient import TestClient
from sqlalchemy import select

from services.core.config import Settings
from services.db.engine import session_factory
from services.db.models import Job
from tests.conftest import problem_of, spine_payload

ROOT = Path(__file__).resolve().parents[2]
BACKENDS = pytest.mark.parametrize("db_settings", ["sqlite", "postgresql"], indirect=True)
ROW_OWN = {"id", "created_at", "enqueued_at", "idempotency_key", "idempotency_kind", "request_hash"}
"""Columns that differ between two jobs of one payload whatever path made them."""


@pytest.fixture
def client(own_client: TestClient) -> TestClient:
    return own_client


def _with_study(patient_id: str) -> dict[str, Any]:
    payload = spine_payload()
    payload["study"] = {"study_instance_uid": f"1.2.826.0.1.{uuid.uuid4().int % 10**12}",
                        "patient_id": patient_id, "accession_number": "ACC-7", "study_date": "2026-01-12"}  # fmt: skip
    return payload


def _row(settings: Settings, job_id: str) -> dict[str, Any]:
    with session_factory(settings)() as session:
        job = session.scalars(select(Job).where(Job.id == uuid.UUID(job_id))).one()
        return {c.key: getattr(job, c.key) for c in Job.__table__.columns if c.key not in ROW_OWN}


@BACKENDS
def test_every_way_of_submitting_stores_the_same_row_and_the_dicom_filters_find_it(
    client: TestClient, db_settings: Settings
) -> None:
    """A batch sent with an Idempotency-Key stored its jobs without the study's identifier columns, so
    ?patient_id=, ?study_instance_uid=, ?accession_number= and the follow-up missed them."""
    patient = f"P-{uuid.uuid4().hex[:8]}"
    payload = _with_study(patient)
    answers = {
        "single": client.post("/v1/jobs", json=payload),
        "single with a key": client.post("/v1/jobs", json=payload, headers={"Idempotency-Key": "s1"}),
        "batch": client.post("/v1/jobs/batch", json={"jobs": [payload]}),
        "batch with a key": client.post("/v1/jobs/batch", json={"jobs": [payload]}, headers={"Idempotency-Key": "b1"}),
    }
    ids = {}
    for way, answer in answers.items():
        assert answer.status_code in (200, 202), (way, answer.text)
        body = answer.json()
        ids[way] = body["results"][0]["job"]["id"] if "results" in body else body["id"]
    rows = {way: _row(db_settings, job_id) for way, job_id in ids.items()}
    assert rows["batch with a key"]["patient_id"] == patient
    for way, row in rows.items():
        assert row == rows["single"], way
    study = payload["study"]
    for name in ("patient_id", "study_instance_uid", "accession_number"):
        listed = {j["id"] for j in client.get("/v1/jobs", params={name: study[name]}).json()["jobs"]}
        assert listed >= set(ids.values()), (name, {w for w, i in ids.items() if i not in listed})


@BACKENDS
@pytest.mark.parametrize("path", ["/v1/jobs", "/v1/jobs/batch"])
def test_an_empty_idempotency_key_is_a_422_naming_the_header(client: TestClient, path: str) -> None:
    """``Idempotency-Key:`` with no value was taken as a key: two different bodies sent with it were a 409."""
    body = spine_payload() if path == "/v1/jobs" else {"jobs": [spine_payload()]}
    problem = problem_of(client.post(path, json=body, headers={"Idempotency-Key": ""}))
    assert problem["status"] == 422
    assert [(e["path"], e["msg"]) for e in problem["errors"]] == [
        ("header.idempotency-key", "the Idempotency-Key header is empty; give it a value or leave the header out")
    ]
    assert client.get("/v1/jobs").json()["jobs"] == []
    assert client.post(path, json=body, headers={"Idempotency-Key": "k"}).status_code in (200, 202)


def _documented(path: str, status: str) -> dict[str, Any]:
    spec = yaml.safe_load((ROOT / "openapi.yaml").read_text(encoding="utf-8"))
    headers: dict[str, Any] = spec["paths"][path]["post"]["responses"][status].get("headers", {})
    return headers


def test_the_submit_answers_carry_the_headers_the_contract_documents(api: TestClient) -> None:
    """openapi.yaml's 202 of POST /v1/jobs and 200 of POST /v1/jobs/batch listed no headers, though
    the service sends Location and Idempotent-Replayed."""
    single = _documented("/v1/jobs", "202")
    assert set(single) == {"Location", "Idempotent-Replayed"} and single["Location"]["required"] is True
    assert single["Idempotent-Replayed"]["schema"]["enum"] == ["true"]
    payload = spine_payload()
    first = api.post("/v1/jobs", json=payload, headers={"Idempotency-Key": "h1"})
    again = api.post("/v1/jobs", json=payload, headers={"Idempotency-Key": "h1"})
    assert first.status_code == again.status_code == 202
    assert first.headers["Location"] == again.headers["Location"] == f"/v1/jobs/{first.json()['id']}"
    assert "Idempotent-Replayed" not in first.headers and again.headers["Idempotent-Replayed"] == "true"

    batch = _documented("/v1/jobs/batch", "200")
    assert set(batch) == {"Idempotent-Replayed"} and batch["Idempotent-Replayed"]["schema"]["enum"] == ["true"]
    first = api.post("/v1/jobs/batch", json={"jobs": [payload]}, headers={"Idempotency-Key": "h2"})
    again = api.post("/v1/jobs/batch", json={"jobs": [payload]}, headers={"Idempotency-Key": "h2"})
    assert first.status_code == again.status_code == 200
    assert "Idempotent-Replayed" not in first.headers and again.headers["Idempotent-Replayed"] == "true"
    assert first.json()["results"][0]["job"]["id"] == again.json()["results"][0]["job"]["id"]


@BACKENDS
def test_a_single_key_and_a_batch_entry_never_answer_for_each_other(client: TestClient) -> None:
    """A batch keyed ``abc`` stored entry 0 under ``abc#0``, in the namespace of single keys: a single
    POST keyed ``abc#0`` got the batch's job back as its replay (or a 409 for another body), and a batch
    whose entry key a single POST had used got a 409 entry. The draft's Idempotency-Key is any sf-string
    (``#`` included), so the two are kept apart instead; each still replays its own request."""
    payload, other = spine_payload(), spine_payload(curve_mm=25.0)
    batch = client.post("/v1/jobs/batch", json={"jobs": [payload]}, headers={"Idempotency-Key": "abc"})
    assert batch.status_code == 200 and batch.json()["accepted"] == 1
    entry = batch.json()["results"][0]["job"]["id"]
    same = client.post("/v1/jobs", json=payload, headers={"Idempotency-Key": "abc#0"})
    assert same.status_code == 202 and "Idempotent-Replayed" not in same.headers, same.text
    assert same.json()["id"] != entry  # a new job, not the batch's
    another = client.post("/v1/jobs", json=other, headers={"Idempotency-Key": "abc#1"})
    single = client.post("/v1/jobs", json=other, headers={"Idempotency-Key": "xyz#0"})
    assert another.status_code == single.status_code == 202, (another.text, single.text)
    later = client.post("/v1/jobs/batch", json={"jobs": [payload]}, headers={"Idempotency-Key": "xyz"})
    assert later.status_code == 200 and later.json()["results"][0]["status"] == 202, later.text
    assert later.json()["results"][0]["job"]["id"] != single.json()["id"]
    # each request replays as itself
    again = client.post("/v1/jobs/batch", json={"jobs": [payload]}, headers={"Idempotency-Key": "abc"})
    assert again.json()["results"][0]["job"]["id"] == entry and again.headers["Idempotent-Replayed"] == "true"
    resent = client.post("/v1/jobs", json=payload, headers={"Idempotency-Key": "abc#0"})
    assert resent.json()["id"] == same.json()["id"] and resent.headers["Idempotent-Replayed"] == "true"
    changed = client.post("/v1/jobs", json=other, headers={"Idempotency-Key": "abc#0"})
    assert changed.status_code == 409 and problem_of(changed)["job"] == f"/v1/jobs/{same.json()['id']}"
    assert len(client.get("/v1/jobs").json()["jobs"]) == 5
