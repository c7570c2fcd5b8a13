"""The webhook outbox on real SQLite and PostgreSQL stores and a real broker: a message's row (attempt 0,
due at the job's end) is written with the job's end, before its first attempt is published, so that a
message lost before any worker took it (a broker restart) is published again by the sweep, and a
message consumed normally is never sent twice. A row the sweep published again says, once the next
attempt came, when it came (not the sweep's own re-check time)."""

from __future__ import annotations

import time
import uuid
from datetime import timedelta
from typing import Any

import pytest
from sqlalchemy import select, update

from services.core.config import Settings
from services.core.jobqueue import make_celery, queue_depth
from services.core.problems import problem
from services.db import deliveries as store
from services.db import jobs as repo
from services.db import runs
from services.db.engine import session_scope, worker_connection
from services.db.models import Job, WebhookDelivery, utcnow
from services.worker import webhook_tasks
from tests.conftest import queued_job
from tests.faults import db_clock
from tests.interop_helpers import TEST_WEBHOOK_SECRET, Receiver

BACKENDS = pytest.mark.parametrize("db_settings", ["sqlite", "postgresql"], indirect=True)
UNREACHABLE = "http://127.0.0.1:9/hooks/outbox"


def settle_earlier_tests(settings: Settings) -> None:
    """The PostgreSQL store is shared by this session's tests: nothing of theirs is due any more."""
    with session_scope(settings) as session:
        session.execute(update(WebhookDelivery).values(next_attempt_at=None))


def rows(settings: Settings, job_id: uuid.UUID) -> list[WebhookDelivery]:
    with session_scope(settings) as session:
        query = select(WebhookDelivery).where(WebhookDelivery.job_id == job_id).order_by(WebhookDelivery.id)
        return list(session.scalars(query))


def listed(settings: Settings, job_id: uuid.UUID) -> list[tuple[int, int | None]]:
    """(attempt, status) of the deliveries ``GET /v1/jobs/{id}`` lists."""
    with session_scope(settings) as session:
        return [(row.attempt, row.status_code) for row in store.deliveries(session, job_id)]


def cancelled_job(settings: Settings, url: str) -> uuid.UUID:
    job_id = queued_job(settings, url)
    with session_scope(settings) as session:
        repo.cancel_job(session, job_id)
    return job_id


def wait_past(moment: Any, seconds: float) -> None:
    while utcnow() < moment + timedelta(seconds=seconds):
        time.sleep(0.02)


@BACKENDS
def test_a_job_ending_writes_its_webhooks_outbox_row_with_its_outcome(db_settings: Settings) -> None:
    """The worker's finish writes the row in the same transaction as the outcome: due at the job's end,
    not listed on the job (no attempt was made under it); nothing for a job without callback_url or
    for a run that no longer owns its job."""
    hooked, plain, superseded = (queued_job(db_settings, url) for url in (UNREACHABLE, None, UNREACHABLE))
    before = db_clock(db_settings)
    with worker_connection(db_settings) as connection:
        claims = {job_id: runs.claim_job(connection, job_id, None) for job_id in (hooked, plain, superseded)}
    with worker_connection(db_settings) as connection:
        for job_id, claim in claims.items():
            assert claim is not None
            if job_id == superseded:  # the reconciler took the job back: this run's finish stores nothing
                claim = runs.Claim(claim.job_id, claim.attempt + 1, {}, claim.created_at, claim.callback_url)
            stored = runs.finish_job(connection, claim, error=problem("fit-failed", "refused by the test"))
            assert stored is (job_id != superseded)
    after = db_clock(db_settings)
    [row] = rows(db_settings, hooked)
    with session_scope(db_settings) as session:
        finished_at = session.scalar(select(Job.finished_at).where(Job.id == hooked))
    assert (row.attempt, row.event, row.url, row.status_code, row.error) == (0, "job.failed", UNREACHABLE, None, None)
    assert row.message_id == store.message_id(hooked, "failed")
    assert row.attempted_at == finished_at  # the job's end as the job shows it: the database's clock
    assert row.next_attempt_at is not None and before <= row.next_attempt_at <= after  # the database's clock
    assert rows(db_settings, plain) == [] and rows(db_settings, superseded) == []
    assert listed(db_settings, hooked) == []  # no attempt yet


@BACKENDS
def test_the_reconciler_writes_the_outbox_row_of_a_job_it_fails(db_settings: Settings) -> None:
    job_id = queued_job(db_settings, UNREACHABLE)
    with worker_connection(db_settings) as connection:  # a run whose worker died: its lease is over at once
        assert runs.claim_job(connection, job_id, None, lease=timedelta(0)) is not None
    with session_scope(db_settings) as session:
        outcome = runs.reconcile(session, queued_timeout=timedelta(seconds=60), max_attempts=1,
                                 lost_problem=problem("worker-lost", "lost in the test"))  # fmt: skip
    assert job_id in outcome.failed
    [row] = rows(db_settings, job_id)
    assert (row.attempt, row.event, row.error) == (0, "job.failed", None) and row.next_attempt_at is not None


@BACKENDS
def test_a_first_message_lost_is_swept_and_one_consumed_is_not(db_settings: Settings) -> None:
    """Two cancelled jobs' webhooks published (``job_ended``, as the API's cancel does) to a real broker
    (the embedded one: a queue in SQLite). One message is lost (the queue purged, as a Redis restart
    loses it), the other is delivered to a real receiver. Once SWEEP_AFTER past the jobs' end, the sweep
    publishes the lost one, and only it; its delivery is one request, and the outbox row then gives the
    time its attempt came. SWEEP_AFTER is 3 s: the sweep postpones the row by it, and the row takes the
    attempt's time only while that postponement lasts (``deliveries.settle_earlier``), so the steps from
    the sweep to the delivery must fit in it; on a loaded machine the attempt once came 0.24 s after a
    0.2 s postponement ended, and once 0.86 s after a 1 s one."""
    sweep_after = 3.0
    receiver = Receiver()
    try:
        settings = db_settings.model_copy(update={"webhook_allowed_urls": receiver.url("/hooks/"),
                                                  "webhook_secret": TEST_WEBHOOK_SECRET,
                                                  "webhook_sweep_after_s": sweep_after})  # fmt: skip
        settle_earlier_tests(settings)
        broker = make_celery(settings)
        urls = {name: receiver.url(f"/hooks/{name}") for name in ("lost", "consumed")}
        lost, consumed = (cancelled_job(settings, url) for url in urls.values())
        for job_id, url in zip((lost, consumed), urls.values(), strict=True):
            assert store.job_ended(settings, job_id, "cancelled", url=url, celery=broker)
        assert queue_depth(broker, settings.webhook_queue) == 2
        with broker.connection_for_write() as conn:
            conn.default_channel.queue_purge(settings.webhook_queue)  # both messages gone...
        assert webhook_tasks.deliver_once(settings, consumed, "cancelled", 1) is None  # ...one of them consumed first
        assert listed(settings, lost) == [] and listed(settings, consumed) == [(1, 204)]

        [outbox] = rows(settings, lost)
        wait_past(outbox.next_attempt_at, sweep_after + 0.05)
        assert webhook_tasks.sweep(settings, broker) == 1
        assert queue_depth(broker, settings.webhook_queue) == 1
        assert webhook_tasks.sweep(settings, broker) == 0  # postponed: published once
        [outbox] = rows(settings, lost)
        assert outbox.error is not None
        assert outbox.error.startswith(f"no attempt within {sweep_after:g} s of the job's end")
        assert listed(settings, lost) == []  # the job lists attempts (and a message the broker refused) only

        assert webhook_tasks.deliver_once(settings, lost, "cancelled", 1) is None
        assert sorted(r.path for r in receiver.received) == ["/hooks/consumed", "/hooks/lost"]
        outbox, first = rows(settings, lost)
        assert (first.attempt, first.status_code) == (1, 204)
        assert outbox.next_attempt_at == first.attempted_at  # when it came, not the sweep's re-check time
        assert listed(settings, lost) == [(1, 204)]
        wait_past(utcnow(), sweep_after + 0.05)
        assert webhook_tasks.sweep(settings, broker) == 0
    finally:
        receiver.close()


@BACKENDS
def test_a_swept_rows_next_attempt_is_when_the_next_attempt_came(db_settings: Settings) -> None:
    """An attempt whose worker stopped mid-request is swept: published again, its row postponed by
    SWEEP_AFTER (60 s here). Once attempt 2 came and was accepted, attempt 1's row gives attempt 2's start
    as its next attempt, not a time 60 s ahead at which nothing will happen."""
    receiver = Receiver()
    try:
        url = receiver.url(f"/hooks/{uuid.uuid4().hex}")
        settings = db_settings.model_copy(update={"webhook_allowed_urls": url, "webhook_secret": TEST_WEBHOOK_SECRET,
                                                  "webhook_sweep_after_s": 60.0})  # fmt: skip
        settle_earlier_tests(settings)
        job_id = cancelled_job(settings, url)
        dead = utcnow() - timedelta(seconds=120)  # claimed 2 minutes ago, never finished
        with session_scope(settings) as session:
            store.claim(session, job_id=job_id, message_id=store.message_id(job_id, "cancelled"),
                        event="job.cancelled", attempt=1, url=url, attempted_at=dead, next_attempt_at=dead)  # fmt: skip
        broker = make_celery(settings)
        assert webhook_tasks.sweep(settings, broker) == 1
        [swept] = rows(settings, job_id)
        assert swept.next_attempt_at is not None and swept.next_attempt_at > utcnow() + timedelta(seconds=50)
        assert webhook_tasks.deliver_once(settings, job_id, "cancelled", 2) is None
        swept, accepted = rows(settings, job_id)
        assert (accepted.attempt, accepted.status_code, accepted.next_attempt_at) == (2, 204, None)
        assert swept.error is not None and swept.error.startswith("no outcome recorded")
        assert swept.next_attempt_at == accepted.attempted_at
    finally:
        receiver.close()
