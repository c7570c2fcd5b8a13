"""A job's shown times, ``created_at`` (the API's insert), ``started_at`` (the worker's claim) and
``finished_at`` (the worker's finish, the API's cancel, the reconciler's failure), are written with the
database's clock (services/db/clock.py), as the leases and due times are (tests/db/test_lease_clock.py,
tests/db/test_due_clock.py): so they are ordered and their differences are durations whatever the clocks
of the processes that write them.

The fault is injected in this test process only: the Python clock (``utcnow``) of the module that acts
(the API's ``services.db.jobs``, the worker's and the reconciler's ``services.db.runs``), where it reads
one, is moved an hour away from the host's, as on a host whose clock is wrong. The databases are real
(SQLite, and a PostgreSQL database of each test's own). Each time written must lie between two reads of
the database's clock taken just before and just after the statement that writes it (on SQLite both are
the host's clock read by SQLite, to the millisecond, so the bounds hold exactly)."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from datetime import datetime, timedelta

import pytest
from sqlalchemy import select

from services.core.config import Settings
from services.core.problems import problem
from services.db import jobs, runs
from services.db.engine import session_scope, worker_connection
from services.db.models import Job, WebhookDelivery
from tests.conftest import queued_job, spine_payload
from tests.faults import SkewedClock, assert_within, db_clock, on_db_clock
from tests.interop_helpers import wait_until

SKEW = timedelta(hours=1)
"""How far a skewed process's clock is from the host's: far more than any job's run here (seconds)."""
LEASE = timedelta(seconds=30)
"""A live run's lease: it holds for the whole of a test."""
EXPIRY_WAIT_S = 10.0
"""The longest wait for the database's clock to pass a lease of 0 s: this 2-core machine's slack under the
other helpers' load, as in tests/db/test_lease_clock.py (the wait ends as soon as the clock has passed it)."""
LOST = {"type": "https://spine.example/problems/worker-lost", "title": "lost", "status": 500, "detail": "x"}
UNREACHABLE = "http://127.0.0.1:9/hooks/job-times"
"""A callback_url whose outbox row is written; no test publishes or sends its webhook."""


@pytest.fixture
def settings(fresh_db_settings: Settings) -> Settings:
    return fresh_db_settings


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> Iterator[SkewedClock]:
    skewed = SkewedClock()
    for module in (jobs, runs):
        monkeypatch.setattr(module, "utcnow", skewed, raising=False)  # where the module reads a clock of its own
    yield skewed


def times(settings: Settings, job_id: uuid.UUID) -> tuple[datetime, datetime | None, datetime | None]:
    with session_scope(settings) as session:
        row = session.execute(select(Job.created_at, Job.started_at, Job.finished_at).where(Job.id == job_id)).one()
    return row.created_at, row.started_at, row.finished_at


def claim(settings: Settings, job_id: uuid.UUID, lease: timedelta = LEASE) -> runs.Claim:
    with worker_connection(settings, durable=False) as connection:  # as the worker claims
        made = runs.claim_job(connection, job_id, "1.0", lease)
    assert made is not None
    return made


@pytest.mark.parametrize("api_offset", [SKEW, -SKEW], ids=["api-ahead-worker-behind", "api-behind-worker-ahead"])
def test_a_runs_times_follow_the_databases_clock_and_stay_ordered(
    settings: Settings, clock: SkewedClock, api_offset: timedelta
) -> None:
    """The API stores the job with its clock an hour one way, a worker whose clock is an hour the other way
    claims and finishes it: created_at ≤ started_at ≤ finished_at, each the database's time of its write
    (with the processes' clocks, started_at came an hour before or after created_at), and the job the API
    answers with carries the created_at stored."""
    worker_offset = -api_offset

    def create() -> tuple[uuid.UUID, datetime]:
        with session_scope(settings) as session:
            job, _ = jobs.create_job(session, {**spine_payload(), "callback_url": UNREACHABLE})
        return job.id, job.created_at

    (job_id, answered), created_window = on_db_clock(settings, clock, api_offset, create)
    made, started_window = on_db_clock(settings, clock, worker_offset, lambda: claim(settings, job_id))

    def finish() -> bool:
        with worker_connection(settings) as connection:  # as the worker stores its outcome
            return runs.finish_job(connection, made, error=problem("fit-failed", "refused by the test"))

    stored, finished_window = on_db_clock(settings, clock, worker_offset, finish)
    assert stored
    created, started, finished = times(settings, job_id)
    assert answered == created == made.created_at
    assert_within(created, created_window, "created_at")
    assert_within(started, started_window, "started_at")
    assert_within(finished, finished_window, "finished_at")
    assert started is not None and finished is not None and created <= started <= finished
    with session_scope(settings) as session:  # the webhook's outbox row: the job's end as the job shows it
        attempted = session.scalar(select(WebhookDelivery.attempted_at).where(WebhookDelivery.job_id == job_id))
    assert attempted == finished


def test_a_batchs_created_at_follows_the_databases_clock(settings: Settings, clock: SkewedClock) -> None:
    """Both batch inserts (with and without an Idempotency-Key): every job's created_at is the database's
    time of the insert, and the jobs answered carry the created_at stored."""

    def create_batch() -> list[Job]:
        with session_scope(settings) as session:
            return jobs.create_jobs(session, [spine_payload(), spine_payload()])

    def create_keyed_batch() -> list[Job]:
        with session_scope(settings) as session:
            outcomes = jobs.create_jobs_idempotent(session, [(0, spine_payload()), (1, spine_payload())],
                                                   owner=None, key="times")  # fmt: skip
        made = [outcome[0] for outcome in outcomes if isinstance(outcome, tuple)]
        assert len(made) == 2
        return made

    for create, offset in ((create_batch, SKEW), (create_keyed_batch, -SKEW)):
        answered, window = on_db_clock(settings, clock, offset, create)
        for job in answered:
            created, _, _ = times(settings, job.id)
            assert job.created_at == created
            assert_within(created, window, f"{create.__name__}: created_at")


# one direction only: a time off the window fails either way, and the suite has its 10 minutes
@pytest.mark.parametrize("api_offset", [SKEW], ids=["api-ahead"])
def test_a_cancel_writes_finished_at_with_the_databases_clock(
    settings: Settings, clock: SkewedClock, api_offset: timedelta
) -> None:
    """A running job cancelled by an API whose clock is an hour off: finished_at is the database's time of
    the cancel, after the worker's started_at (with the API's clock an hour behind, it came before it)."""
    job_id = queued_job(settings)
    claim(settings, job_id)

    def cancel() -> str:
        with session_scope(settings) as session:
            job, cancelled = jobs.cancel_job(session, job_id)
        assert cancelled
        return job.status

    status, window = on_db_clock(settings, clock, api_offset, cancel)
    created, started, finished = times(settings, job_id)
    assert status == "cancelled"
    assert_within(finished, window, "finished_at")
    assert started is not None and finished is not None and created <= started <= finished


# one direction only: a time off the window fails either way, and the suite has its 10 minutes
@pytest.mark.parametrize("offset", [SKEW], ids=["reconciler-ahead"])
def test_the_reconcilers_failure_writes_finished_at_with_the_databases_clock(
    settings: Settings, clock: SkewedClock, offset: timedelta
) -> None:
    """A run whose worker died on its last allowed attempt, failed by a reconciler whose clock is an hour
    off: finished_at is the database's time of that pass, and its webhook's outbox row gives that time."""
    job_id = queued_job(settings, UNREACHABLE)
    claim(settings, job_id, lease=timedelta(0))  # its lease over at once
    with session_scope(settings) as session:  # past it on the database's clock (SQLite: to the millisecond)
        expires = session.scalar(select(Job.lease_expires_at).where(Job.id == job_id))
    assert expires is not None
    wait_until(lambda: db_clock(settings) > expires, EXPIRY_WAIT_S, "the database's clock to pass the lease")

    def fail() -> list[uuid.UUID]:
        with session_scope(settings) as session:
            return runs.reconcile(session, queued_timeout=timedelta(minutes=5), max_attempts=1,
                                  lost_problem=LOST).failed  # fmt: skip

    failed, window = on_db_clock(settings, clock, offset, fail)
    assert failed == [job_id]
    created, started, finished = times(settings, job_id)
    assert_within(finished, window, "finished_at")
    assert started is not None and finished is not None and created <= started <= finished
    with session_scope(settings) as session:
        attempted = session.scalar(select(WebhookDelivery.attempted_at).where(WebhookDelivery.job_id == job_id))
    assert attempted == finished
