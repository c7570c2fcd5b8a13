"""Review findings on storing a job's results in the PACS again (``POST /v1/jobs/{id}/dicom-store``) and the
webhooks of a run of STOW-RS attempts (``job.dicom_stored``, ``job.dicom_store_failed``), each reproduced on
the real databases (PostgreSQL; SQLite, the embedded mode), Redis broker and the service's own functions
(``services.worker.dicom_tasks``, ``services.db.dicom_stores``, the API in process) in an order that two
worker slots, or two API threads, can run them.

Two messages of one STOW-RS attempt (the original held late by its consumer and the reconciler's, or a
redelivery) can both pass the task's "already made?" check (``attempt_wait_s``) before either records its
outcome: both make the attempt. When the slower one reads or records it after the integrator, told by the
first one's ``job.dicom_store_failed``, asked for a new run, the old attempt is taken as one of the new
run's. On SQLite two requests at once both start a run. A request just as the job succeeds publishes
the first attempt a second time.
"""

from __future__ import annotations

import contextlib
import json
import socket
import threading
import uuid
from collections.abc import Iterator
from datetime import timedelta
from typing import Any

import pytest
import redis
from fastapi.testclient import TestClient
from sqlalchemy import select

from services.api.app import create_app
from services.core.config import Settings
from services.core.jobqueue import make_celery
from services.db import deliveries, dicom_stores
from services.db import jobs as repo
from services.db.engine import session_scope
from services.db.models import Job, WebhookDelivery
from services.worker import dicom_tasks
from services.worker.tasks import execute_job
from tests.conftest import _purge_queue, make_key
from tests.dicom.conftest import complete_payload
from tests.interop_helpers import TEST_WEBHOOK_SECRET, Receiver

REFUSED_PACS = "http://127.0.0.1:9/dicom-web"
"""A PACS nobody listens at: an attempt is refused at once (dicomweb-unavailable)."""
HOLD_TIMEOUT_S = 10.0
"""Longest wait for the held attempt's connection (s): it builds the SR and SC first (about a second)."""


class HeldPacs:
    """A loopback port that accepts a connection and holds it, unanswered, until ``release`` closes it: a PACS
    that hangs during an attempt (the attempt then fails, dicomweb-unavailable). ``accepted`` is set once a
    connection came: the attempt has read its job and sent its request."""

    def __init__(self) -> None:
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.accepted = threading.Event()
        self._released = threading.Event()
        self._held: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self.server.accept()
            except OSError:
                return
            self._held.append(conn)
            self.accepted.set()
            if self._released.is_set():
                conn.close()

    def release(self) -> None:
        self._released.set()
        for conn in self._held:
            with contextlib.suppress(OSError):
                conn.close()

    def close(self) -> None:
        self.release()
        with contextlib.suppress(OSError):
            self.server.close()


@pytest.fixture
def settings(db_settings: Settings, redis_url: str, receiver: Receiver) -> Iterator[Settings]:
    """``db_settings`` storing results (a run of one attempt: the boundary SPINE_DICOMWEB_MAX_ATTEMPTS=1) in a
    PACS nobody listens at, on a Redis queue of the test's own, calling back ``receiver``."""
    queue = f"spine-test-{uuid.uuid4().hex[:8]}"
    made = db_settings.model_copy(update={
        "queue_name": queue, "broker_url": redis_url, "dicomweb_url": REFUSED_PACS, "dicomweb_store_results": True,
        "dicomweb_max_attempts": 1, "dicomweb_timeout_s": HOLD_TIMEOUT_S,
        "webhook_allowed_urls": receiver.url("/hooks/"), "webhook_secret": TEST_WEBHOOK_SECRET,
    })  # fmt: skip
    yield made
    _purge_queue(redis_url, queue)


def _storable_job(settings: Settings, receiver: Receiver, owner: str) -> uuid.UUID:
    """A succeeded job of ``owner`` with the patient's study, calling back ``receiver``, its first STOW-RS run
    started as a worker starts it (``job_succeeded``: due, attempt 1 published)."""
    study = {"study_instance_uid": f"2.25.{uuid.uuid4().int}", "patient_id": "P-REVIEW"}
    payload: dict[str, Any] = {**complete_payload(study), "callback_url": receiver.url(f"/hooks/{uuid.uuid4().hex}")}
    with session_scope(settings) as session:
        job, _ = repo.create_job(session, payload, owner=owner)
    assert execute_job(settings.model_copy(update={"dicomweb_store_results": False}), job.id) == "succeeded"
    assert dicom_tasks.job_succeeded(settings, job.id, make_celery(settings))
    return job.id


@pytest.mark.parametrize("db_settings", ["postgresql"], indirect=True)
def test_an_old_runs_attempt_recorded_after_a_request_does_not_end_the_new_run(
    settings: Settings, receiver: Receiver
) -> None:
    """Two messages of attempt 1 pass the task's check (``attempt_wait_s``: not made yet). One (B) reads the
    job and hangs on the PACS; the other (A) is refused, ends run 1 (MAX_ATTEMPTS 1) and its
    ``job.dicom_store_failed`` is written; the owner then asks again (202: run 2, first attempt 2, due).
    B's attempt then fails and is recorded. Run 2 has made no attempt, so: its attempt stays due (the sweep
    still covers it), no ``job.dicom_store_failed`` of run 2 exists, and a second request is refused
    (``dicom-store-pending``) rather than starting another run numbered 2."""
    owner = f"clinic-{uuid.uuid4().hex[:8]}"
    job_id = _storable_job(settings, receiver, owner)
    key = {"Authorization": f"Bearer {make_key(settings, owner)}"}
    assert dicom_tasks.attempt_wait_s(settings, job_id, 1, scheduled=False) == 0.0  # message A: to be made
    assert dicom_tasks.attempt_wait_s(settings, job_id, 1, scheduled=False) == 0.0  # message B: to be made too

    held = HeldPacs()
    outcomes: list[Any] = []
    held_settings = settings.model_copy(update={"dicomweb_url": f"http://127.0.0.1:{held.port}/dicom-web"})
    slot_b = threading.Thread(target=lambda: outcomes.append(dicom_tasks.store_once(held_settings, job_id, 1)))
    try:
        slot_b.start()
        assert held.accepted.wait(HOLD_TIMEOUT_S), "attempt B never reached the PACS"
        first = dicom_tasks.store_once(settings, job_id, 1)  # A: refused, the run's last attempt
        assert (first.ok, first.next_attempt_at) == (False, None)
        with TestClient(create_app(settings)) as api:
            asked = api.post(f"/v1/jobs/{job_id}/dicom-store", headers=key)
            assert asked.status_code == 202, asked.text
            assert asked.json()["dicom_stores"][-1]["attempt"] == 2
            held.release()
            slot_b.join(HOLD_TIMEOUT_S)
            assert len(outcomes) == 1 and not outcomes[0].ok  # B recorded its attempt 1
            with session_scope(settings) as session:
                due = session.scalar(select(Job.dicom_store_due_at).where(Job.id == job_id))
                run2_failed = session.scalars(
                    select(WebhookDelivery.attempt).where(
                        WebhookDelivery.message_id == deliveries.message_id(job_id, "dicom_store_failed", 2)
                    )
                ).all()
            again = api.post(f"/v1/jobs/{job_id}/dicom-store", headers=key)
    finally:
        held.close()
        slot_b.join(HOLD_TIMEOUT_S)
    observed = {
        "run 2 still due": due is not None,
        "job.dicom_store_failed rows of run 2": list(run2_failed),
        "second request": (again.status_code, again.json().get("type", "").rsplit("/", 1)[-1]),
    }
    assert observed == {"run 2 still due": True, "job.dicom_store_failed rows of run 2": [],
                        "second request": (409, "dicom-store-pending")}  # fmt: skip


@pytest.mark.parametrize("db_settings", ["postgresql"], indirect=True)
def test_an_old_runs_attempt_made_after_a_request_is_not_retried_in_the_new_run(
    settings: Settings, receiver: Receiver
) -> None:
    """Two messages of attempt 1 pass the task's check; A is refused and ends run 1 (MAX_ATTEMPTS 1); the owner
    asks again (run 2, first attempt 2); then B reads the job and makes its attempt 1, refused too. Attempt 1
    is run 1's, whose budget (one attempt) is spent: no next attempt. The code reckons it from run 2's first
    (``in_run`` = 1 − 2 + 1 = 0 < MAX_ATTEMPTS), gave it a next attempt ``retry_delay_s(0)`` (half of
    SPINE_DICOMWEB_RETRY_BASE_S) later, for which the task published attempt 2, run 2's first, a second time.
    B is a second copy of an attempt already recorded: it is not made (``store_once`` raises LookupError, which
    the task logs and drops), and run 2 stays as the request left it."""
    owner = f"clinic-{uuid.uuid4().hex[:8]}"
    job_id = _storable_job(settings, receiver, owner)
    assert dicom_tasks.attempt_wait_s(settings, job_id, 1, scheduled=False) == 0.0  # message A: to be made
    assert dicom_tasks.attempt_wait_s(settings, job_id, 1, scheduled=False) == 0.0  # message B: to be made too
    first = dicom_tasks.store_once(settings, job_id, 1)  # A
    assert (first.ok, first.next_attempt_at) == (False, None)
    with TestClient(create_app(settings)) as api:
        asked = api.post(
            f"/v1/jobs/{job_id}/dicom-store", headers={"Authorization": f"Bearer {make_key(settings, owner)}"}
        )
    assert asked.status_code == 202, asked.text
    with pytest.raises(LookupError, match="of a run before"):  # B: a copy of run 1's attempt, not made again
        dicom_tasks.store_once(settings, job_id, 1)
    with session_scope(settings) as session:  # run 2 untouched: still due, its request the last entry
        job = session.get(Job, job_id)
        assert job is not None and job.dicom_store_due_at is not None
        assert (job.dicom_stores or [])[-1].get("requested_by") == owner


RENDEZVOUS_S = 1.0
"""How long a request waits for the other to reach the same point before it writes (s): both get there in
milliseconds unless one is held by a lock."""


@pytest.mark.parametrize("db_settings", ["sqlite"], indirect=True)
def test_of_two_requests_at_once_on_sqlite_one_starts_a_run(
    db_settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The embedded mode (SQLite) serves requests on several threads. Two requests for one job (two sessions,
    as two API threads): each reads the job, then waits up to ``RENDEZVOUS_S`` for the other to have read it
    too (a hook on ``due_in``, which ``request_run`` calls between its read and its write, calling the real
    one) before writing. ``SELECT … FOR UPDATE`` locks nothing on SQLite (its dialect leaves ``FOR UPDATE``
    out) and the sqlite3 driver opens no transaction before a read, so both read "no attempt due": both are
    accepted (two runs asked, two messages of attempt 1 published by the route), and the second write
    replaces the first's entry. One must be refused (``StorePending``) and one request entry recorded, as
    on PostgreSQL (tests/dicom/test_dicom_store_again.py); SQLite's own lock is ``BEGIN IMMEDIATE``, which
    the queued-job cap takes (``services.db.stats.lock_submissions``)."""
    with session_scope(db_settings) as session:
        job, _ = repo.create_job(session, complete_payload(None))
    real_due_in = dicom_stores.due_in
    arrived = threading.Condition()
    count = [0]

    def rendezvous(delay: Any) -> Any:
        with arrived:
            count[0] += 1
            arrived.notify_all()
            arrived.wait_for(lambda: count[0] >= 2, timeout=RENDEZVOUS_S)
        return real_due_in(delay)

    monkeypatch.setattr(dicom_stores, "due_in", rendezvous)
    outcomes: list[str] = []

    def ask(client: str) -> None:
        try:
            with session_scope(db_settings) as session:
                dicom_stores.request_run(session, job.id, client, timedelta(seconds=db_settings.dicomweb_sweep_after_s))
            outcomes.append("accepted")
        except dicom_stores.StorePending:
            outcomes.append("StorePending")

    threads = [threading.Thread(target=ask, args=(client,)) for client in ("clinic-a", "clinic-b")]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(30)
    with session_scope(db_settings) as session:
        stores = session.scalar(select(Job.dicom_stores).where(Job.id == job.id)) or []
    assert (sorted(outcomes), len(stores)) == (["StorePending", "accepted"], 1)


@pytest.mark.parametrize("db_settings", ["postgresql"], indirect=True)
def test_a_request_as_the_job_succeeds_does_not_publish_its_first_attempt_twice(
    settings: Settings, receiver: Receiver
) -> None:
    """A worker stores a job's success, publishes ``job.succeeded`` (a broker round trip; seconds when the
    broker is slow), then marks the first STOW-RS attempt due and publishes it (``job_succeeded``). A request
    between the two (the integrator saw ``succeeded`` with no ``dicom_stores``) is accepted as run 1 and
    publishes attempt 1; ``job_succeeded`` then publishes attempt 1 again: two messages of one attempt, which
    two worker slots make at once (both STOW-RS, both recorded; the task's check cannot tell them apart until
    one is recorded). One message of attempt 1 must be queued: the request refused as pending (the due time
    written with the success), or the run it started not published again."""
    owner = f"clinic-{uuid.uuid4().hex[:8]}"
    with session_scope(settings) as session:
        job, _ = repo.create_job(session, complete_payload({"study_instance_uid": "2.25.1", "patient_id": "P-1"}),
                                 owner=owner)  # fmt: skip
    assert execute_job(settings.model_copy(update={"dicomweb_store_results": False}), job.id) == "succeeded"
    with TestClient(create_app(settings)) as api:  # before the worker's job_succeeded
        asked = api.post(
            f"/v1/jobs/{job.id}/dicom-store", headers={"Authorization": f"Bearer {make_key(settings, owner)}"}
        )
    assert asked.status_code in (202, 409), asked.text
    dicom_tasks.job_succeeded(settings, job.id, make_celery(settings))
    queued = redis.Redis.from_url(settings.celery_broker_url).lrange(settings.dicom_queue, 0, -1)
    firsts = [m for m in queued if json.loads(m)["headers"]["argsrepr"] == f"['{job.id}', 1]"]
    assert len(firsts) == 1, [json.loads(m)["headers"]["argsrepr"] for m in queued]
