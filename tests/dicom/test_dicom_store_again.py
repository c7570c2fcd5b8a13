"""Storing a job's results in the PACS again (``POST /v1/jobs/{id}/dicom-store``, ``spine store``), end to
end on the session's Orthanc, PostgreSQL, Redis and a `spine worker` subprocess of this module's own.

The service reaches Orthanc through a TCP relay on a port of its own (``PortRelay``): until the relay
opens, nothing listens on that port, so every STOW-RS attempt is refused as by a PACS that is down; once
it opens, the PACS is back. The runs are short: ``MAX_ATTEMPTS`` attempts ``RETRY_BASE_S`` apart."""

from __future__ import annotations

import json
import uuid
from collections.abc import Iterator
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
import redis
from fastapi.testclient import TestClient
from sqlalchemy import select, update

from services.api.app import create_app
from services.core.config import Settings
from services.core.jobqueue import make_celery
from services.db import dicom_stores
from services.db.clock import db_now_plus_s
from services.db.engine import session_scope
from services.db.jobs import cancel_job, create_job
from services.db.keys import audit_trail
from services.db.migrate import upgrade
from services.db.models import ApiKey, Job, utcnow
from services.dicom.uids import job_uids
from services.worker import dicom_tasks
from services.worker.tasks import execute_job
from tests.conftest import Service, _purge_queue, make_key, problem_of, spine_payload
from tests.interop_helpers import wait_until

from .conftest import (
    STORE_TIMEOUT_S,
    OrthancServer,
    PortRelay,
    complete_payload,
    free_port,
    pacs_of,
    relayed_store_service,
)

MAX_ATTEMPTS = 2
"""SPINE_DICOMWEB_MAX_ATTEMPTS of the module's service: a run of two attempts."""
RETRY_BASE_S = 0.5
"""SPINE_DICOMWEB_RETRY_BASE_S of the module's service: the delay before a run's second attempt (s)."""
PENDING_S = 30
"""How far ahead the pending refusal's attempt is put (s): its Retry-After counts down from it."""


@pytest.fixture(scope="module")
def store_service(
    tmp_path_factory: pytest.TempPathFactory, postgres_url: str, redis_url: str, orthanc: OrthancServer,
    relay: PortRelay,
) -> Iterator[Service]:  # fmt: skip
    """A `spine serve` of the module's own (PostgreSQL, Redis, its worker) storing results in the session's
    Orthanc through ``relay``, closed until a test opens it."""
    with relayed_store_service("dicom-again", tmp_path_factory.mktemp("dicom-again"), postgres_url, redis_url,
                               orthanc, relay, MAX_ATTEMPTS, RETRY_BASE_S) as service:  # fmt: skip
        yield service


def _auth(key: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {key}"}


def _stores(service: Service, job_id: str) -> list[dict[str, Any]]:
    return list(service.job(job_id)["dicom_stores"] or [])


def _run_ended(service: Service, job_id: str, count: int) -> list[dict[str, Any]]:
    """The job's ``dicom_stores`` once its run ended (within ``STORE_TIMEOUT_S``): the last entry an attempt
    with no next one (not a request); it must then hold ``count`` entries."""

    def ended() -> bool:
        stores = _stores(service, job_id)
        return bool(stores) and not stores[-1].get("requested_by") and stores[-1]["next_attempt_at"] is None

    wait_until(ended, STORE_TIMEOUT_S, f"the STOW-RS run of job {job_id} ending:\n{service.worker_log()[-3000:]}")
    stores = _stores(service, job_id)
    assert len(stores) == count, stores
    return stores


@pytest.fixture(scope="module")
def jobs(store_service: Service) -> dict[str, Any]:
    """Two succeeded jobs of the client ``clinic-a``, their first runs ended while the PACS is down: one with
    the patient's study (``storable``: its ``MAX_ATTEMPTS`` attempts refused), one without a study
    (``no_study``: its one attempt not stored for want of the patient's identity). Also the keys of
    ``clinic-a`` and of another client, ``clinic-b``."""
    keys = {name: make_key(store_service.settings, name) for name in ("clinic-a", "clinic-b")}
    study_uid = f"2.25.{uuid.uuid4().int}"
    ids = {}
    for name, study in (("storable", {"study_instance_uid": study_uid, "patient_id": "P-AGAIN"}), ("no_study", None)):
        answer = store_service.client.post("/v1/jobs", json=complete_payload(study), headers=_auth(keys["clinic-a"]))
        assert answer.status_code == 202, answer.text
        ids[name] = answer.json()["id"]
    for job in store_service.wait_all(list(ids.values()), timeout=120):
        assert job["status"] == "succeeded", job.get("error")
    first = _run_ended(store_service, ids["storable"], MAX_ATTEMPTS)
    assert [(s["attempt"], s["ok"], s["problem_type"]) for s in first] == [
        (n, False, "dicomweb-unavailable") for n in range(1, MAX_ATTEMPTS + 1)]  # fmt: skip
    assert [s["problem_type"] for s in _run_ended(store_service, ids["no_study"], 1)] == ["dicom-no-patient-identity"]
    return {**ids, "study_uid": study_uid, "keys": keys}


def _store_cli(
    service: Service, key: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], *args: str
) -> tuple[int, str, str]:
    """``spine store ARGS`` (``spine_client.cli``) with ``key``, through the client's own HTTP code to the
    module's API in process: exit code, stdout, stderr."""
    from spine_client import SpineClient
    from spine_client import cli as spine_cli

    transport = service.client._transport
    monkeypatch.setattr(spine_cli, "_client", lambda _: SpineClient("http://testserver", key, transport=transport,
                                                                    retries=0))  # fmt: skip
    capsys.readouterr()
    code = spine_cli.main(["store", *args])
    out = capsys.readouterr()
    return code, out.out, out.err


def _store_audits(service: Service, job_ids: list[str]) -> dict[str, int]:
    """How many ``store`` audit rows each job has."""
    with session_scope(service.settings) as session:
        return {j: sum(row.action == "store" for row in audit_trail(session, uuid.UUID(j))) for j in job_ids}


def _request_entry(entry: dict[str, Any], attempt: int, client: str) -> None:
    """``entry`` is the request of a run whose first attempt is ``attempt``, asked by ``client``, due then."""
    expected: tuple[int, str, bool, list[str]] = (attempt, client, False, [])
    assert (entry["attempt"], entry["requested_by"], entry["ok"], entry["stored"]) == expected, entry
    assert entry["next_attempt_at"] == entry["attempted_at"], entry


def test_results_a_pacs_outage_kept_out_are_stored_again_on_request(
    store_service: Service, jobs: dict[str, Any], orthanc: OrthancServer, relay: PortRelay,
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    """The first run (attempts 1, 2) found the PACS down. Asked again (``spine store``, an admin key) with the
    PACS still down, a new run makes ``MAX_ATTEMPTS`` more attempts (3, 4: the budget starts again, the
    backoff too) and ends. With the PACS back, the owner's POST stores the SR and SC in the patient's study
    (attempt 5); asked again once stored (``spine store --format json``, the owner), the same two instances
    are stored again (attempt 6), none duplicated. Each request is audited as ``store`` in its key's name."""
    job_id, keys = jobs["storable"], jobs["keys"]
    first = _stores(store_service, job_id)
    admin_name = f"{store_service.name}-admin"  # the name of the service's admin key (tests.conftest.Service)

    # PACS still down: a run of MAX_ATTEMPTS attempts more, numbered on
    code, out, err = _store_cli(store_service, store_service.api_key, monkeypatch, capsys, job_id)
    assert code == 0, err
    assert out.startswith(f"job {job_id}: STOW-RS attempt 3 due at ") and out.endswith(f"requested by {admin_name}\n")
    stores = _run_ended(store_service, job_id, len(first) + 1 + MAX_ATTEMPTS)
    assert stores[: len(first)] == first
    _request_entry(stores[2], 3, admin_name)
    assert [(s["attempt"], s["ok"], s["problem_type"]) for s in stores[3:]] == [
        (3, False, "dicomweb-unavailable"), (4, False, "dicomweb-unavailable")]  # fmt: skip
    assert stores[4]["next_attempt_at"] is None
    # the backoff starts again with the run: RETRY_BASE_S before its second attempt (attempt 4), not the
    # RETRY_BASE_S · 2^2 that attempt 3 of one long run would wait
    delay = datetime.fromisoformat(stores[3]["next_attempt_at"]) - datetime.fromisoformat(stores[3]["attempted_at"])
    assert delay == timedelta(seconds=RETRY_BASE_S)
    with pacs_of(orthanc) as pacs:
        assert pacs.search_instances(jobs["study_uid"]) == []

    # the PACS is back: the owner asks
    relay.open()
    answer = store_service.client.post(f"/v1/jobs/{job_id}/dicom-store", headers=_auth(keys["clinic-a"]))
    assert answer.status_code == 202, answer.text
    assert answer.headers["location"] == f"/v1/jobs/{job_id}"
    body = answer.json()
    assert body["id"] == job_id and body["status"] == "succeeded" and body["payload"] is not None  # GET's detail
    assert body["dicom_stores"][:-1] == stores
    _request_entry(body["dicom_stores"][-1], 5, "clinic-a")
    stored = _run_ended(store_service, job_id, len(stores) + 2)[-1]
    uids = job_uids(job_id)
    assert (stored["attempt"], stored["ok"], sorted(stored["stored"])) == (5, True, sorted([uids["sr"], uids["sc"]]))
    with pacs_of(orthanc) as pacs:
        held = pacs.search_instances(jobs["study_uid"])
        assert sorted(i["00080018"]["Value"][0] for i in held) == sorted([uids["sr"], uids["sc"]])
        sr = pacs.retrieve_explicit_le(jobs["study_uid"], uids["sr-series"], uids["sr"])
        assert (sr.Modality, sr.PatientID) == ("SR", "P-AGAIN")

    # once stored, stored again: the same instances
    code, out, err = _store_cli(store_service, keys["clinic-a"], monkeypatch, capsys, job_id, "--format", "json")
    assert code == 0, err
    printed = json.loads(out)
    assert printed["job_id"] == job_id
    _request_entry(printed["dicom_store"], 6, "clinic-a")
    again = _run_ended(store_service, job_id, len(stores) + 4)[-1]
    assert (again["attempt"], again["ok"], sorted(again["stored"])) == (6, True, sorted([uids["sr"], uids["sc"]]))
    with pacs_of(orthanc) as pacs:
        assert len(pacs.search_instances(jobs["study_uid"])) == 2  # the SR and SC, once each

    with session_scope(store_service.settings) as session:
        names = dict(session.execute(select(ApiKey.id, ApiKey.name)).all())
        trail = [(row.action, names[row.key_id]) for row in audit_trail(session, uuid.UUID(job_id))]
    assert [entry for entry in trail if entry[0] == "store"] == [
        ("store", admin_name), ("store", "clinic-a"), ("store", "clinic-a")]  # fmt: skip


def test_each_refusal_names_its_reason(
    store_service: Service, jobs: dict[str, Any], monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """As problem+json: 404 ``not-found`` for no such job and for another client's; 404
    ``dicomweb-not-configured`` without SPINE_DICOMWEB_URL and ``dicomweb-store-disabled`` with
    SPINE_DICOMWEB_STORE_RESULTS off; 409 ``job-has-no-result`` for a queued and a cancelled job; 409
    ``dicom-no-patient-identity`` for a job without a study; 409 ``dicom-store-pending`` with Retry-After
    while an attempt is due. None is audited, nothing is recorded on the job. ``spine store`` exits 5 and 7."""
    keys, client = jobs["keys"], store_service.client
    storable, no_study = jobs["storable"], jobs["no_study"]
    owner = _auth(keys["clinic-a"])

    def refused(job_id: str, status: int, kind: str, headers: dict[str, str] = owner, app: Any = client) -> Any:
        answer = app.post(f"/v1/jobs/{job_id}/dicom-store", headers=headers)
        body = problem_of(answer)
        assert (answer.status_code, body["type"]) == (status, f"https://spine.example/problems/{kind}"), body
        return answer

    before = {j: _stores(store_service, j) for j in (storable, no_study)}
    audited = _store_audits(store_service, [storable, no_study])
    refused(str(uuid.uuid4()), 404, "not-found")
    assert "there is no job" in refused(storable, 404, "not-found", _auth(keys["clinic-b"])).json()["detail"]
    for update_, kind, variable in ((dict(dicomweb_url=None), "dicomweb-not-configured", "SPINE_DICOMWEB_URL"),
                                    (dict(dicomweb_store_results=False), "dicomweb-store-disabled",
                                     "SPINE_DICOMWEB_STORE_RESULTS")):  # fmt: skip
        other = TestClient(create_app(store_service.settings.model_copy(update=update_)))
        assert variable in refused(storable, 404, kind, app=other).json()["detail"]

    with session_scope(store_service.settings) as session:  # not published: it stays queued
        queued, _ = create_job(session, complete_payload(None), owner="clinic-a")
    assert refused(str(queued.id), 409, "job-has-no-result").json()["job_status"] == "queued"
    with session_scope(store_service.settings) as session:
        cancel_job(session, queued.id)
    assert refused(str(queued.id), 409, "job-has-no-result").json()["job_status"] == "cancelled"

    assert "the job has no study" in refused(no_study, 409, "dicom-no-patient-identity").json()["detail"]

    sweep_after = store_service.settings.dicomweb_sweep_after_s  # the due time is the attempt's plus this
    with session_scope(store_service.settings) as session:
        session.execute(update(Job).where(Job.id == uuid.UUID(storable)).values(
            dicom_store_due_at=db_now_plus_s(sweep_after + PENDING_S)))  # fmt: skip
    try:
        pending = refused(storable, 409, "dicom-store-pending")
        # the attempt is due PENDING_S after the update, whole seconds rounded up: less by the time since then
        assert PENDING_S - 1 <= int(pending.headers["retry-after"]) <= PENDING_S, pending.headers
        assert pending.json()["attempt"] == before[storable][-1]["attempt"] + 1
    finally:
        with session_scope(store_service.settings) as session:
            session.execute(update(Job).where(Job.id == uuid.UUID(storable)).values(dicom_store_due_at=None))

    code, _, err = _store_cli(store_service, keys["clinic-a"], monkeypatch, capsys, no_study)
    assert code == 7 and "the job has no study" in err, err  # docs/client.md: 7, conflict with the job's state
    code, _, err = _store_cli(store_service, keys["clinic-a"], monkeypatch, capsys, str(uuid.uuid4()))
    assert code == 5 and "there is no job" in err, err  # 5: not found

    assert {j: _stores(store_service, j) for j in before} == before
    assert _store_audits(store_service, [storable, no_study, str(queued.id)]) == {**audited, str(queued.id): 0}


def test_a_request_the_broker_refuses_is_recorded_and_published_by_the_sweep(tmp_path: Path, redis_url: str) -> None:
    """A request whose message the broker refuses (nothing listens on its port) is still accepted (202): the
    request's entry says it was not published, and the job is due for the reconciler's sweep, which (on a
    broker that answers, real Redis) publishes the run's first attempt by its number once overdue, where
    the first run's budget is spent; past the new run's ``MAX_ATTEMPTS`` the sweep clears the job.
    Real SQLite database and a job run in process."""
    queue = f"spine-test-{uuid.uuid4().hex[:8]}"
    base = Settings(data_dir=tmp_path, queue_name=queue, dicomweb_url="http://127.0.0.1:9/dicom-web",
                    dicomweb_max_attempts=MAX_ATTEMPTS)  # fmt: skip
    upgrade(base, quiet=True)
    with session_scope(base) as session:
        job, _ = create_job(session, complete_payload({"study_instance_uid": "1.2.3", "patient_id": "P-1"}),
                            owner="clinic-a")  # fmt: skip
    assert execute_job(base, job.id) == "succeeded"  # results not stored by this run: no message published
    failed = {"attempted_at": utcnow().isoformat(), "ok": False, "problem_type": "dicomweb-unavailable"}
    first = [{**failed, "attempt": n} for n in range(1, MAX_ATTEMPTS + 1)]  # a first run whose budget is spent
    with session_scope(base) as session:
        session.execute(update(Job).where(Job.id == job.id).values(dicom_stores=first))

    refusing = base.model_copy(update={"dicomweb_store_results": True,
                                       "broker_url": f"redis://127.0.0.1:{free_port()}/0"})  # fmt: skip
    with TestClient(create_app(refusing)) as api:
        answer = api.post(f"/v1/jobs/{job.id}/dicom-store", headers=_auth(make_key(base, "clinic-a")))
    assert answer.status_code == 202, answer.text
    request = answer.json()["dicom_stores"][-1]
    _request_entry(request, MAX_ATTEMPTS + 1, "clinic-a")
    assert request["error"].startswith("not published: "), request

    sweeping = refusing.model_copy(update={"broker_url": redis_url})
    app = make_celery(sweeping)
    past = utcnow() - timedelta(seconds=1)
    try:
        assert dicom_tasks.sweep(sweeping, app) == 0  # due SPINE_DICOMWEB_SWEEP_AFTER_S after the request
        with session_scope(base) as session:
            session.execute(update(Job).where(Job.id == job.id).values(dicom_store_due_at=past))
        assert dicom_tasks.sweep(sweeping, app) == 1
        broker = redis.Redis.from_url(redis_url)
        message = json.loads(broker.lindex(sweeping.dicom_queue, 0))  # type: ignore[arg-type]
        assert message["headers"]["argsrepr"] == f"['{job.id}', {MAX_ATTEMPTS + 1}]"
        # the new run's MAX_ATTEMPTS attempts made and failed, overdue: cleared, not published
        run = [{**failed, "attempt": n} for n in range(MAX_ATTEMPTS + 1, 2 * MAX_ATTEMPTS + 1)]
        with session_scope(base) as session:
            session.execute(update(Job).where(Job.id == job.id).values(
                dicom_stores=[*first, request, *run], dicom_store_due_at=past))  # fmt: skip
        assert dicom_tasks.sweep(sweeping, app) == 0
        with session_scope(base) as session:
            assert session.get(Job, job.id).dicom_store_due_at is None  # type: ignore[union-attr]
        assert broker.llen(sweeping.dicom_queue) == 1
    finally:
        _purge_queue(redis_url, queue)


@pytest.mark.parametrize("db_settings", ["postgresql"], indirect=True)
def test_of_two_requests_at_once_one_starts_a_run(db_settings: Settings) -> None:
    """Two requests for one job (PostgreSQL, two sessions): the second read the job (as the route's lookup
    does, and holds it) before the first committed its request; locking the row, it finds the attempt due
    (``StorePending``), not the job as it read it, and one request entry is recorded."""
    with session_scope(db_settings) as session:
        job, _ = create_job(session, spine_payload())
    sweep_after = timedelta(seconds=db_settings.dicomweb_sweep_after_s)
    with session_scope(db_settings) as late, session_scope(db_settings) as first:
        read = late.get(Job, job.id)  # held, as the route holds the job it looked up
        assert read is not None and read.dicom_store_due_at is None
        dicom_stores.request_run(first, job.id, "clinic-a", sweep_after)
        first.commit()
        with pytest.raises(dicom_stores.StorePending) as pending:
            dicom_stores.request_run(late, job.id, "clinic-b", sweep_after)
    assert pending.value.attempt == 1 and 0 <= pending.value.wait_s <= 1  # due at once (1 s: this test's time)
    with session_scope(db_settings) as session:
        stores = session.get(Job, job.id).dicom_stores  # type: ignore[union-attr]
    assert [(s["attempt"], s["requested_by"]) for s in stores or []] == [(1, "clinic-a")]
