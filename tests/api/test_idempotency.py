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
from sqlalchemy import create_engine, insert, select

from services.api.app import create_app
from services.core.config import Settings
from services.db import jobs as repo
from services.db.engine import session_factory
from services.db.keys import key_id_of
from services.db.migrate import downgrade, upgrade
from services.db.models import Job, JobAudit, utcnow
from tests.conftest import make_key, problem_of, spine_payload

ROOT = Path(__file__).resolve().parents[2]
BACKENDS = pytest.mark.parametrize("db_settings", ["sqlite", "postgresql"], indirect=True)
ROW_OWN = {"id", "created_at", "enqueued_at", "request_hash", *(f"idempotency_{c}" for c in ("key", "kind", "client"))}
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


def _bearer(key: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {key}"}


@BACKENDS
def test_two_admin_clients_keys_are_apart_and_each_replays_its_own(db_settings: Settings) -> None:
    """Idempotency keys are per client (docs/security.md), admin clients included. An admin key's jobs
    have no owner, and keys were per owner: an admin reusing a key another admin had sent got that
    admin's job replayed (same body) or a 409 naming it (another body). Admins still see every job."""
    tag = uuid.uuid4().hex[:8]
    ops1, ops2 = (_bearer(make_key(db_settings, f"{who}-{tag}", "admin")) for who in ("ops1", "ops2"))
    key, p, q = f"k-{tag}", spine_payload(), spine_payload(curve_mm=25.0)
    with TestClient(create_app(db_settings)) as c:
        first = c.post("/v1/jobs", json=p, headers={**ops1, "Idempotency-Key": key})
        other = c.post("/v1/jobs", json=p, headers={**ops2, "Idempotency-Key": key})
        assert first.status_code == other.status_code == 202, other.text
        assert "Idempotent-Replayed" not in other.headers and other.json()["id"] != first.json()["id"]
        changed = c.post("/v1/jobs", json=q, headers={**ops2, "Idempotency-Key": key})
        assert changed.status_code == 409 and problem_of(changed)["job"] == f"/v1/jobs/{other.json()['id']}"
        for who, made in ((ops1, first), (ops2, other)):
            again = c.post("/v1/jobs", json=p, headers={**who, "Idempotency-Key": key})
            assert again.json()["id"] == made.json()["id"] and again.headers["Idempotent-Replayed"] == "true"
        seen = c.get(f"/v1/jobs/{other.json()['id']}", headers=ops1)  # every admin sees every job
        assert seen.status_code == 200 and seen.json()["owner"] is None
        batches = [c.post("/v1/jobs/batch", json={"jobs": [p]}, headers={**who, "Idempotency-Key": key})
                   for who in (ops1, ops2, ops2)]  # fmt: skip
        entries = [b.json()["results"][0]["job"]["id"] for b in batches]
        assert entries[0] != entries[1] == entries[2], [b.text for b in batches]
        assert "Idempotent-Replayed" not in batches[1].headers and batches[2].headers["Idempotent-Replayed"] == "true"


@pytest.fixture(params=["sqlite", "postgresql"])
def empty_db(request: pytest.FixtureRequest, tmp_path: Path) -> Settings:
    """Settings of an empty database of the test's own (nothing migrated)."""
    if request.param == "postgresql":
        return Settings(DATABASE_URL=request.getfixturevalue("fresh_postgres_url"), data_dir=tmp_path)
    return Settings(data_dir=tmp_path)


def test_an_admins_request_retried_across_the_upgrade_replays_its_job(empty_db: Settings) -> None:
    """Keys stored before revision 0013 (owner NULL for every admin's job) are given their client: the
    owner of a client's job, the name of the key that created an admin's job (its audit row), so that
    a request retried after the upgrade replays its job and another admin's key is apart; an admin's
    job no audit row names (made before keys existed) is replayed to every admin key, as before. Going
    down, where two admins stored one key, the first stored keeps it (the older index holds one)."""
    upgrade(empty_db, "0012_idempotency_kind", quiet=True)
    names = {"ops1": "admin", "ops2": "admin", "clinic": "client"}
    keys = {name: make_key(empty_db, name, role) for name, role in names.items()}
    p, q = spine_payload(), spine_payload(curve_mm=25.0)
    legacy = {"named": (None, "k1"), "unnamed": (None, "k2"), "client's": ("clinic", "k1")}
    ids = {what: uuid.uuid4() for what in legacy}
    now = utcnow()
    engine = create_engine(empty_db.sqlalchemy_url)
    try:
        with engine.begin() as conn:  # the columns of 0012: no idempotency_client
            conn.execute(insert(Job), [
                {"id": ids[what], "owner": owner, "status": "queued", "created_at": now, "enqueued_at": now,
                 "attempts": 0, "payload": p, "idempotency_key": key, "request_hash": repo.request_hash(p)}
                for what, (owner, key) in legacy.items()
            ])  # fmt: skip
            conn.execute(insert(JobAudit), [
                {"at": now, "key_id": key_id_of(keys[name]), "action": "create", "job_id": ids[what]}
                for what, name in (("named", "ops1"), ("client's", "clinic"))
            ])  # fmt: skip
        upgrade(empty_db, quiet=True)
        with engine.connect() as conn:
            clients = dict(conn.execute(select(Job.id, Job.idempotency_client)).all())
        assert clients == {ids["named"]: "ops1", ids["unnamed"]: None, ids["client's"]: "clinic"}

        def post(name: str, key: str, body: dict[str, Any]) -> Any:
            return c.post("/v1/jobs", json=body, headers={**_bearer(keys[name]), "Idempotency-Key": key})

        with TestClient(create_app(empty_db)) as c:
            for name, key, what in (("ops1", "k1", "named"), ("ops1", "k2", "unnamed"), ("ops2", "k2", "unnamed"),
                                    ("clinic", "k1", "client's")):  # fmt: skip
                retried = post(name, key, p)
                assert retried.status_code == 202 and retried.headers.get("Idempotent-Replayed") == "true", (name, key)
                assert retried.json()["id"] == str(ids[what]), (name, key)
            apart = post("ops2", "k1", p)  # ops1's key, not ops2's
            assert apart.status_code == 202 and "Idempotent-Replayed" not in apart.headers
            assert problem_of(post("ops2", "k2", q))["job"] == f"/v1/jobs/{ids['unnamed']}"
        downgrade(empty_db, "0012_idempotency_kind")
        with engine.connect() as conn:
            kept = dict(conn.execute(select(Job.id, Job.idempotency_key)).all())
        assert kept[ids["named"]] == "k1" and kept[uuid.UUID(apart.json()["id"])] is None
        assert kept[ids["unnamed"]] == "k2" and kept[ids["client's"]] == "k1"
    finally:
        engine.dispose()
