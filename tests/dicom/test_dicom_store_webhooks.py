"""The webhooks of a job's STOW-RS runs (``job.dicom_stored``, ``job.dicom_store_failed``), end to end on the
session's Orthanc, PostgreSQL, Redis, a `spine worker` subprocess of this module's own and a real HTTP
receiver (``tests.interop_helpers.Receiver``, answering 204), each message checked with the Standard
Webhooks reference implementation (``standardwebhooks``).

As in tests/dicom/test_dicom_store_again.py, the service reaches Orthanc through a relay
(``PortRelay``) closed at first: every STOW-RS attempt is refused, as by a PACS that is down, until a test
opens it. The tests run in file order (``--dist loadfile`` keeps a file in one process): the outage's
first, then the working PACS's. Runs are short: ``MAX_ATTEMPTS`` attempts ``RETRY_BASE_S`` apart."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from datetime import datetime
from typing import Any

import pytest
from standardwebhooks import Webhook

from services.db.deliveries import message_id
from services.dicom.uids import job_uids
from tests.conftest import Service
from tests.interop_helpers import TEST_WEBHOOK_SECRET, Received, Receiver, wait_until

from .conftest import STORE_TIMEOUT_S, OrthancServer, PortRelay, complete_payload, relayed_store_service

MAX_ATTEMPTS = 2
"""SPINE_DICOMWEB_MAX_ATTEMPTS of the module's service: a run of two attempts."""
RETRY_BASE_S = 0.5
"""SPINE_DICOMWEB_RETRY_BASE_S of the module's service: the delay before a run's second attempt (s)."""
SECRET = TEST_WEBHOOK_SECRET.get_secret_value()
"""SPINE_WEBHOOK_SECRET of the module's service: the jobs are an admin key's (no owner), signed with it."""


@pytest.fixture(scope="module")
def receiver() -> Iterator[Receiver]:
    made = Receiver()
    yield made
    made.close()


@pytest.fixture(scope="module")
def hooked_service(
    tmp_path_factory: pytest.TempPathFactory, postgres_url: str, redis_url: str, orthanc: OrthancServer,
    relay: PortRelay, receiver: Receiver,
) -> Iterator[Service]:  # fmt: skip
    """A `spine serve` of the module's own (PostgreSQL, Redis, its worker) storing results in the session's
    Orthanc through ``relay``, and calling back ``receiver``."""
    with relayed_store_service(
        "dicom-hooks", tmp_path_factory.mktemp("dicom-hooks"), postgres_url, redis_url, orthanc, relay,
        MAX_ATTEMPTS, RETRY_BASE_S, SPINE_WEBHOOK_ALLOWED_URLS=receiver.url("/hooks/"), SPINE_WEBHOOK_SECRET=SECRET,
    ) as service:  # fmt: skip
        yield service


def _submit(service: Service, receiver: Receiver, study: dict[str, str] | None) -> tuple[str, str]:
    """A job (the service's admin key) calling back a path of its own on ``receiver``: its id and the path."""
    path = f"/hooks/{uuid.uuid4().hex}"
    job = service.submit({**complete_payload(study), "callback_url": receiver.url(path)})
    return job["id"], path


def _messages(service: Service, receiver: Receiver, path: str, count: int) -> list[dict[str, Any]]:
    """The first ``count`` messages ``path`` received (within ``STORE_TIMEOUT_S``), each verified (its
    signature and timestamp, by ``standardwebhooks``) and returned as its body with its ``webhook-id``
    (``id``), in the order of their events' timestamps (deliveries on two worker slots may arrive in
    either order)."""

    def arrived() -> list[Received] | None:
        got = receiver.at(path)
        return got if len(got) >= count else None

    got = wait_until(arrived, STORE_TIMEOUT_S, f"{count} webhooks at {path}:\n{service.worker_log()[-3000:]}")
    bodies = [{**Webhook(SECRET).verify(r.body, r.headers), "id": r.headers["webhook-id"]} for r in got]
    return sorted(bodies, key=lambda b: datetime.fromisoformat(b["timestamp"]))


def _delivered(service: Service, job_id: str, events: int) -> list[tuple[str, str, int, int | None]]:
    """(event, message id, attempt, status) of the job's deliveries (``GET /v1/jobs/{id}``) once ``events``
    messages were accepted."""

    def accepted() -> list[dict[str, Any]] | None:
        found = service.job(job_id)["deliveries"] or []
        return found if sum(d["status_code"] == 204 for d in found) >= events else None

    found = wait_until(accepted, STORE_TIMEOUT_S, f"{events} accepted deliveries of job {job_id}")
    return [(d["event"], d["message_id"], d["attempt"], d["status_code"]) for d in found]


def test_a_run_that_fails_is_told_and_a_new_run_that_stores_is_a_new_message(
    hooked_service: Service, receiver: Receiver, relay: PortRelay
) -> None:
    """PACS down: a job's first run (attempts 1, 2 refused) ends with ``job.dicom_store_failed`` (after
    ``job.succeeded``), its data the job with its ``dicom_stores`` as GET shows them, ending with attempt 2
    (no next attempt, the reason). A job without study gets ``job.dicom_store_failed`` for its one attempt,
    ``dicom-no-patient-identity``. The PACS back, a request (``POST .../dicom-store``) starts run 3, whose
    stored attempt sends ``job.dicom_stored``: a new message (another ``webhook-id``). Every message is
    listed on its job's deliveries, accepted once."""
    storable, path = _submit(hooked_service, receiver, {"study_instance_uid": f"2.25.{uuid.uuid4().int}",
                                                        "patient_id": "P-HOOKS"})  # fmt: skip
    no_study, no_study_path = _submit(hooked_service, receiver, None)

    succeeded, failed = _messages(hooked_service, receiver, path, 2)
    assert [succeeded["type"], failed["type"]] == ["job.succeeded", "job.dicom_store_failed"]
    assert (succeeded["id"], failed["id"]) == (message_id(storable, "succeeded"),
                                               message_id(storable, "dicom_store_failed", 1))  # fmt: skip
    stores = hooked_service.job(storable)["dicom_stores"]
    assert failed["data"]["dicom_stores"] == stores  # the job as GET shows it, up to the run's last attempt
    assert [(s["attempt"], s["ok"], s["problem_type"]) for s in stores] == [
        (n, False, "dicomweb-unavailable") for n in range(1, MAX_ATTEMPTS + 1)]  # fmt: skip
    assert stores[-1]["next_attempt_at"] is None and stores[-1]["error"]
    assert failed["data"]["id"] == storable and failed["data"]["status"] == "succeeded"
    assert datetime.fromisoformat(failed["timestamp"]) == datetime.fromisoformat(stores[-1]["attempted_at"])

    no_study_succeeded, no_identity = _messages(hooked_service, receiver, no_study_path, 2)
    assert [no_study_succeeded["type"], no_identity["type"]] == ["job.succeeded", "job.dicom_store_failed"]
    [entry] = no_identity["data"]["dicom_stores"]
    assert (entry["attempt"], entry["ok"], entry["problem_type"]) == (1, False, "dicom-no-patient-identity")
    assert "the job has no study" in entry["error"] and entry["next_attempt_at"] is None
    assert no_identity["id"] == message_id(no_study, "dicom_store_failed", 1)

    relay.open()  # the PACS is back: asked again
    answer = hooked_service.client.post(f"/v1/jobs/{storable}/dicom-store")
    assert answer.status_code == 202, answer.text
    stored = _messages(hooked_service, receiver, path, 3)[-1]
    assert stored["type"] == "job.dicom_stored"
    assert stored["id"] == message_id(storable, "dicom_stored", MAX_ATTEMPTS + 1) != failed["id"]
    request, attempt = stored["data"]["dicom_stores"][-2:]
    uids = job_uids(storable)
    assert (request["attempt"], request["requested_by"]) == (MAX_ATTEMPTS + 1, f"{hooked_service.name}-admin")
    assert (attempt["attempt"], attempt["ok"], sorted(attempt["stored"])) == (
        MAX_ATTEMPTS + 1, True, sorted([uids["sr"], uids["sc"]]))  # fmt: skip
    assert stored["data"]["dicom_stores"] == hooked_service.job(storable)["dicom_stores"]

    assert sorted(_delivered(hooked_service, storable, 3)) == sorted([
        ("job.succeeded", succeeded["id"], 1, 204), ("job.dicom_store_failed", failed["id"], 1, 204),
        ("job.dicom_stored", stored["id"], 1, 204)])  # fmt: skip
    assert len(receiver.at(path)) == 3
    assert sorted(_delivered(hooked_service, no_study, 2)) == sorted([
        ("job.succeeded", no_study_succeeded["id"], 1, 204),
        ("job.dicom_store_failed", no_identity["id"], 1, 204)])  # fmt: skip


def test_results_stored_at_once_are_told_after_the_jobs_end(
    hooked_service: Service, receiver: Receiver, relay: PortRelay
) -> None:
    """PACS up (the relay open, as the previous test left it): the receiver gets ``job.succeeded`` and
    ``job.dicom_stored``, both signed, the latter's event after the former's (its time, the attempt's, is
    after the job's end) and its data the job with the one successful attempt."""
    if relay._server is None:  # run alone
        relay.open()
    job_id, path = _submit(hooked_service, receiver, {"study_instance_uid": f"2.25.{uuid.uuid4().int}",
                                                      "patient_id": "P-HOOKS-UP"})  # fmt: skip
    succeeded, stored = _messages(hooked_service, receiver, path, 2)
    assert [succeeded["type"], stored["type"]] == ["job.succeeded", "job.dicom_stored"]
    assert datetime.fromisoformat(succeeded["timestamp"]) < datetime.fromisoformat(stored["timestamp"])
    [attempt] = stored["data"]["dicom_stores"]
    uids = job_uids(job_id)
    assert (attempt["attempt"], attempt["ok"], sorted(attempt["stored"])) == (1, True, sorted([uids["sr"], uids["sc"]]))
    assert stored["data"]["result"] == succeeded["data"]["result"] and stored["data"]["study"]["patient_id"]
    assert stored["id"] == message_id(job_id, "dicom_stored", 1)
    assert sorted(_delivered(hooked_service, job_id, 2)) == sorted([
        ("job.succeeded", succeeded["id"], 1, 204), ("job.dicom_stored", stored["id"], 1, 204)])  # fmt: skip
