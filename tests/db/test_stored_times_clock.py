"""Every time the database stores is the database's clock (services/db/clock.py), not only the job's
created, started and finished times (tests/db/test_job_times_clock.py) and the leases and due times
(tests/db/test_lease_clock.py, tests/db/test_due_clock.py): an API key's ``created_at`` and ``revoked_at``,
an audit row's ``at``, a webhook attempt's ``attempted_at`` (the worker's claim, the outbox row the API's
cancel writes, a message the broker refused) and a STOW-RS attempt's ``attempted_at`` and
``next_attempt_at`` (``jobs.dicom_stores``). So they are ordered with the job's times and with one another
whatever the clocks of the hosts that write them: the most recent key of a client is the one made last
(it signs the client's webhooks), and the audit rows of a job are in the order of the actions.

The fault is injected in this test process only: the Python clock (``utcnow``) of the module that acts
(``services.db.keys``, ``services.db.deliveries``, ``services.worker.webhook_tasks``,
``services.worker.dicom_tasks``), where it reads one, is moved an hour away from the host's, as on a host
whose clock is wrong. The databases are real (SQLite, and a PostgreSQL database of each test's own), as
are the embedded broker, the webhook receiver (an HTTP server on a free loopback port) and the PACS (a
free loopback port nothing listens on: every STOW-RS attempt finds it unavailable). Each time written
must lie between two reads of the database's clock taken just before and just after the call that
writes it (on SQLite both are the host's clock read by SQLite, to the millisecond, so the bounds hold
exactly)."""

from __future__ import annotations

import uuid
from collections.abc import Callable, Iterator
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import select

from services.core.config import Settings
from services.core.jobqueue import make_celery
from services.core.webhook_policy import decode_secret
from services.db import deliveries, jobs, keys
from services.db.clock import db_now_plus_s
from services.db.engine import session_scope
from services.db.models import ApiKey, Job, JobAudit, WebhookDelivery
from services.worker import dicom_tasks, webhook_tasks
from services.worker.tasks import execute_job
from tests.conftest import fresh_settings, spine_payload
from tests.faults import SkewedClock, assert_within, free_port, on_db_clock
from tests.interop_helpers import TEST_WEBHOOK_SECRET, Receiver

SKEW = timedelta(hours=1)
"""How far a skewed process's clock is from the host's: far more than any call's duration here (seconds)."""
HOOK = "/hooks/stored-times"
REFUSED_BROKER = "redis://127.0.0.1:1/0"
"""A broker that refuses every connection (port 1): a message published there is "not published"."""


@pytest.fixture(params=["sqlite", "postgresql"])
def settings(request: pytest.FixtureRequest, tmp_path: Path) -> Settings:
    """A migrated database of the test's own, with a PACS that refuses (STOW-RS results stored) and the
    webhook settings of the loopback receiver's tests."""
    return fresh_settings(request, tmp_path, dicomweb_url=f"http://127.0.0.1:{free_port()}/dicom-web",
                          dicomweb_timeout_s=2, dicomweb_store_results=True, webhook_secret=TEST_WEBHOOK_SECRET)


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> Iterator[SkewedClock]:
    skewed = SkewedClock()
    for module in (jobs, keys, deliveries, webhook_tasks, dicom_tasks):
        monkeypatch.setattr(module, "utcnow", skewed, raising=False)  # where the module reads a clock of its own
    yield skewed


@pytest.fixture
def receiver() -> Iterator[Receiver]:
    made = Receiver()
    yield made
    made.close()


# ------------------------------------------------------------------ API keys and the audit trail


def test_keys_are_made_and_revoked_on_the_databases_clock_and_the_last_made_signs(
    settings: Settings, clock: SkewedClock
) -> None:
    """A client's key made on a host an hour ahead, then another on a host an hour behind: each
    ``created_at`` is the database's time of its insert (with the hosts' clocks the second came two hours
    before the first), the key returned carries it, and the second, the most recent, signs the client's
    webhooks. Revoked from a host an hour ahead: ``revoked_at`` is the database's time of the revoke, and
    the first key signs again."""

    def make() -> tuple[str, datetime, str | None]:
        with session_scope(settings) as session:
            row, _ = keys.create_key(session, "clinic", "client")
            return row.id, row.created_at, row.webhook_secret

    (first, first_answered, first_secret), first_window = on_db_clock(settings, clock, SKEW, make)
    (second, second_answered, second_secret), second_window = on_db_clock(settings, clock, -SKEW, make)
    with session_scope(settings) as session:
        stored = {key_id: at for key_id, at in session.execute(select(ApiKey.id, ApiKey.created_at))}
        signer = keys.key_webhook_secret(session, "clinic")
    assert_within(stored[first], first_window, "the first key's created_at")
    assert_within(stored[second], second_window, "the second key's created_at")
    assert (first_answered, second_answered) == (stored[first], stored[second])
    assert second_secret is not None and signer == decode_secret(second_secret)

    def revoke() -> datetime | None:
        with session_scope(settings) as session:
            [revoked] = keys.revoke(session, second)
            return revoked.revoked_at

    answered, window = on_db_clock(settings, clock, SKEW, revoke)
    with session_scope(settings) as session:
        revoked_at = session.scalar(select(ApiKey.revoked_at).where(ApiKey.id == second))
        signer = keys.key_webhook_secret(session, "clinic")
    assert_within(revoked_at, window, "revoked_at")
    assert answered == revoked_at
    assert first_secret is not None and signer == decode_secret(first_secret)


def test_a_jobs_audit_rows_are_on_the_databases_clock_in_the_order_of_the_actions(
    settings: Settings, clock: SkewedClock
) -> None:
    """A job created through an API host an hour ahead (the audit row in the inserting transaction, as
    the API's create hook writes it), read through one an hour behind, cancelled through one an hour
    ahead: each row's ``at`` is the database's time of its insert, and ordered by id (the order of the
    actions) the times never go back (with the hosts' clocks the read came two hours before the create)."""
    caller = keys.Caller(key_id="0123456789ab", name="clinic", role="client")

    def create() -> uuid.UUID:
        def hook(session: Any, ids: list[uuid.UUID]) -> None:
            keys.audit(session, caller, "create", ids, "req-create")

        with session_scope(settings) as session:
            job, _ = jobs.create_job(session, spine_payload(), owner="clinic", on_insert=hook)
        return job.id

    def acted(action: keys.AuditAction, job_id: uuid.UUID) -> Callable[[], None]:
        def act() -> None:
            with session_scope(settings) as session:
                if action == "cancel":
                    jobs.cancel_job(session, job_id, owner="clinic")
                keys.audit(session, caller, action, [job_id], f"req-{action}")
                session.commit()

        return act

    job_id, create_window = on_db_clock(settings, clock, SKEW, create)
    _, read_window = on_db_clock(settings, clock, -SKEW, acted("read", job_id))
    _, cancel_window = on_db_clock(settings, clock, SKEW, acted("cancel", job_id))
    with session_scope(settings) as session:
        trail = [(row.action, row.at) for row in keys.audit_trail(session, job_id)]
        finished = session.scalar(select(Job.finished_at).where(Job.id == job_id))
    assert [action for action, _ in trail] == ["create", "read", "cancel"]
    for (action, at), window in zip(trail, (create_window, read_window, cancel_window), strict=True):
        assert_within(at, window, f"the {action} row's at")
    times = [at for _, at in trail]
    assert times == sorted(times), f"audit rows out of the actions' order: {trail}"
    assert finished is not None and times[1] <= finished <= times[2]  # the cancel's row comes after the cancel


def test_a_batch_of_audit_rows_is_one_time(settings: Settings, clock: SkewedClock) -> None:
    """One INSERT of several rows (a batch's create, a list): every row carries the database's time of
    that insert."""
    caller = keys.Caller(key_id="0123456789ab", name="clinic", role="client")
    ids = [uuid.uuid4(), uuid.uuid4(), uuid.uuid4()]

    def listed() -> None:
        with session_scope(settings) as session:
            keys.audit(session, caller, "list", ids, "req-list")
            session.commit()

    _, window = on_db_clock(settings, clock, -SKEW, listed)
    with session_scope(settings) as session:
        times = list(session.scalars(select(JobAudit.at).where(JobAudit.action == "list")))
    assert len(times) == 3
    for at in times:
        assert_within(at, window, "a listed job's row's at")


# ------------------------------------------------------------------ webhook attempts


def _cancelled_job(settings: Settings, url: str) -> uuid.UUID:
    """A job calling back ``url``, cancelled (its ``finished_at`` the database's clock)."""
    with session_scope(settings) as session:
        job, _ = jobs.create_job(session, {**spine_payload(), "callback_url": url})
        jobs.cancel_job(session, job.id)
    return job.id


def _rows(settings: Settings, job_id: uuid.UUID) -> list[WebhookDelivery]:
    with session_scope(settings) as session:
        query = select(WebhookDelivery).where(WebhookDelivery.job_id == job_id).order_by(WebhookDelivery.attempt)
        return list(session.scalars(query))


def _finished_at(settings: Settings, job_id: uuid.UUID) -> datetime | None:
    with session_scope(settings) as session:
        return session.scalar(select(Job.finished_at).where(Job.id == job_id))


# one direction only: a time off the window fails either way, and the suite has its 10 minutes
@pytest.mark.parametrize("offset", [SKEW], ids=["api-ahead"])
def test_the_outbox_row_of_a_cancel_gives_the_jobs_end_as_stored(
    settings: Settings, clock: SkewedClock, receiver: Receiver, offset: timedelta
) -> None:
    """The API cancels a job and writes its webhook's outbox row (``job_ended``) with its clock an hour
    off: the row's ``attempted_at`` is the job's ``finished_at`` as the database wrote it."""
    url = receiver.url(HOOK)
    job_id = _cancelled_job(settings, url)
    broker = make_celery(settings)  # the embedded broker: the message is published, never consumed here
    clock.offset = offset
    try:
        assert deliveries.job_ended(settings, job_id, "cancelled", url=url, celery=broker)
    finally:
        clock.offset = timedelta(0)
    [outbox] = _rows(settings, job_id)
    assert outbox.attempt == deliveries.OUTBOX_ATTEMPT
    assert outbox.attempted_at == _finished_at(settings, job_id)


# one direction only: a time off the window fails either way, and the suite has its 10 minutes
@pytest.mark.parametrize("offset", [SKEW], ids=["api-ahead"])
def test_a_message_the_broker_refused_is_marked_on_the_databases_clock(
    settings: Settings, clock: SkewedClock, receiver: Receiver, offset: timedelta
) -> None:
    """The broker refuses the message of a cancel made by an API whose clock is an hour off: the outbox
    row says "not published", its ``attempted_at`` the database's time of that call, after the job's end."""
    url = receiver.url(HOOK)
    job_id = _cancelled_job(settings, url)
    refused = make_celery(settings.model_copy(update={"broker_url": REFUSED_BROKER}))

    def end() -> bool:
        return deliveries.job_ended(settings, job_id, "cancelled", url=url, celery=refused)

    published, window = on_db_clock(settings, clock, offset, end)
    assert not published
    [outbox] = _rows(settings, job_id)
    assert outbox.error is not None and outbox.error.startswith(deliveries.NOT_PUBLISHED)
    assert_within(outbox.attempted_at, window, "the unpublished row's attempted_at")
    finished = _finished_at(settings, job_id)
    assert finished is not None and finished <= outbox.attempted_at


def test_webhook_attempts_are_claimed_on_the_databases_clock(
    settings: Settings, clock: SkewedClock, receiver: Receiver
) -> None:
    """Attempt 1 (the receiver answers 503) made by a worker an hour ahead, attempt 2 (204) by one an hour
    behind: each ``attempted_at`` is the database's time of the attempt, after the job's end and in the
    attempts' order (with the workers' clocks attempt 2 came two hours before attempt 1); the outbox row,
    postponed as the sweep does, takes attempt 1's ``attempted_at`` as when its next attempt came."""
    url = receiver.url(HOOK)
    receiver.plan[HOOK] = [503]
    settings = settings.model_copy(update={"webhook_allowed_urls": url})
    job_id = _cancelled_job(settings, url)
    assert deliveries.job_ended(settings, job_id, "cancelled", url=url, celery=make_celery(settings))
    with session_scope(settings) as session:  # the sweep published attempt 1 again: due 300 s ahead
        [outbox] = _rows(settings, job_id)
        deliveries.postpone(session, outbox.id, db_now_plus_s(300.0))

    def attempt(number: int) -> Callable[[], float | None]:
        return lambda: webhook_tasks.deliver_once(settings, job_id, "cancelled", number)

    delay, first_window = on_db_clock(settings, clock, SKEW, attempt(1))
    assert delay is not None  # 503: retried
    none, second_window = on_db_clock(settings, clock, -SKEW, attempt(2))
    assert none is None  # 204: delivered
    outbox, first, second = _rows(settings, job_id)
    assert [r.status_code for r in (first, second)] == [503, 204]
    assert_within(first.attempted_at, first_window, "attempt 1's attempted_at")
    assert_within(second.attempted_at, second_window, "attempt 2's attempted_at")
    finished = _finished_at(settings, job_id)
    assert finished is not None and finished <= first.attempted_at <= second.attempted_at
    assert outbox.next_attempt_at == first.attempted_at


# ------------------------------------------------------------------ STOW-RS attempts


STOW_STUDY = {"study_instance_uid": "1.2.3", "patient_id": "P-STOW"}
"""The study of a job whose results are stored: only one with a Patient ID is (``results.not_storable``)."""


def _succeeded_job(settings: Settings) -> uuid.UUID:
    """A job run by the engine to success (its result stored), with no STOW-RS published yet."""
    with session_scope(settings) as session:
        job, _ = jobs.create_job(session, {**spine_payload(), "study": STOW_STUDY})
    assert execute_job(settings.model_copy(update={"dicomweb_store_results": False}), job.id) == "succeeded"
    return job.id


def _stores(settings: Settings, job_id: uuid.UUID) -> list[dict[str, Any]]:
    with session_scope(settings) as session:
        job = session.get(Job, job_id)
        assert job is not None
        return list(job.dicom_stores or [])


# one direction only: a time off the window fails either way, and the suite has its 10 minutes
@pytest.mark.parametrize("offset", [SKEW], ids=["worker-ahead"])
def test_stow_attempts_are_recorded_on_the_databases_clock(
    settings: Settings, clock: SkewedClock, offset: timedelta
) -> None:
    """A STOW-RS message the broker refused (attempt 0), then attempt 1 (the PACS unavailable), both by a
    worker whose clock is an hour off: each ``attempted_at`` is the database's time of its call, after the
    job's end, and attempt 1's ``next_attempt_at`` is its ``attempted_at`` plus the retry delay."""
    job_id = _succeeded_job(settings)
    refused = make_celery(settings.model_copy(update={"broker_url": REFUSED_BROKER}))
    published, unpublished_window = on_db_clock(settings, clock, offset, lambda: dicom_tasks.job_succeeded(
        settings, job_id, refused))  # fmt: skip
    assert not published
    outcome, attempt_window = on_db_clock(settings, clock, offset, lambda: dicom_tasks.store_once(settings, job_id, 1))
    assert not outcome.ok and outcome.problem_type == "dicomweb-unavailable"
    zero, one = _stores(settings, job_id)
    assert (zero["attempt"], one["attempt"]) == (0, 1)
    zero_at, one_at = datetime.fromisoformat(zero["attempted_at"]), datetime.fromisoformat(one["attempted_at"])
    assert_within(zero_at, unpublished_window, "attempt 0's attempted_at")
    assert_within(one_at, attempt_window, "attempt 1's attempted_at")
    assert one["next_attempt_at"] is not None
    delay = timedelta(seconds=dicom_tasks.retry_delay_s(settings, 1))
    assert datetime.fromisoformat(one["next_attempt_at"]) == one_at + delay
    finished = _finished_at(settings, job_id)
    assert finished is not None and finished <= zero_at <= one_at
