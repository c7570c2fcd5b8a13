"""Job leases are written and compared on the database's clock (services/db/clock.py), so that processes
whose own clocks differ by more than a lease neither take back a live run nor leave a dead one.

The fault is injected in this test process only: ``services.db.runs.utcnow`` (the Python clock the run
functions read) is moved an hour away from the host's clock, far beyond any lease (``SPINE_LEASE_S``,
10 s by default), as on a host whose clock is wrong; the databases are real (SQLite, and a PostgreSQL
database of each test's own, so that the reconciler sees this test's jobs only)."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from datetime import timedelta

import pytest
from sqlalchemy import select

from services.core.config import Settings
from services.db import runs
from services.db.clock import db_now
from services.db.engine import session_scope, worker_connection
from services.db.models import Job
from tests.conftest import queued_job
from tests.faults import SkewedClock
from tests.interop_helpers import wait_until

SKEW = timedelta(hours=1)
"""How far the skewed process's clock is from the host's: far more than any lease."""
LEASE = timedelta(seconds=30)
"""A live run's lease: it holds for the whole of a test."""
SHORT_LEASE = timedelta(seconds=1)
"""A dead run's lease, waited out on the database's clock."""
EXPIRY_WAIT_S = 10.0
"""The longest wait for the database's clock to pass SHORT_LEASE: the lease plus this 2-core machine's
slack under the other helpers' load (the wait ends as soon as the clock has passed it)."""
LOST = {"type": "https://spine.example/problems/worker-lost", "title": "lost", "status": 500, "detail": "x"}



@pytest.fixture
def settings(fresh_db_settings: Settings) -> Settings:
    return fresh_db_settings


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> Iterator[SkewedClock]:
    skewed = SkewedClock()
    monkeypatch.setattr(runs, "utcnow", skewed, raising=False)  # where the module reads a clock of its own
    yield skewed


def _claim(settings: Settings, job_id: uuid.UUID, lease: timedelta) -> runs.Claim:
    with worker_connection(settings, durable=False) as connection:  # as the worker claims
        claim = runs.claim_job(connection, job_id, "1.0", lease)
    assert claim is not None
    return claim


def _taken_back(settings: Settings, job_id: uuid.UUID) -> bool:
    """One reconciler pass; whether it handed ``job_id`` back to the queue."""
    with session_scope(settings) as session:
        outcome = runs.reconcile(session, queued_timeout=timedelta(minutes=5), max_attempts=3, lost_problem=LOST)
    with session_scope(settings) as session:
        status = session.scalar(select(Job.status).where(Job.id == job_id))
    assert (job_id in outcome.requeue) == (status == "queued"), (outcome, status)
    return job_id in outcome.requeue


def _wait_for_expiry(settings: Settings, job_id: uuid.UUID) -> None:
    """Until the database's clock is past the job's lease."""

    def expired() -> bool:
        with session_scope(settings) as session:
            return bool(session.scalar(select(Job.lease_expires_at < db_now()).where(Job.id == job_id)))

    wait_until(expired, EXPIRY_WAIT_S, "the lease to expire on the database's clock")


def test_a_worker_whose_clock_is_behind_keeps_its_lease(settings: Settings, clock: SkewedClock) -> None:
    """A worker an hour behind claims and renews: its lease holds for the reconciler on a right clock
    (with the worker's clock, the lease had ended an hour before it was written)."""
    job_id = queued_job(settings)
    clock.offset = -SKEW
    claim = _claim(settings, job_id, LEASE)
    clock.offset = timedelta(0)
    assert not _taken_back(settings, job_id)
    clock.offset = -SKEW
    with worker_connection(settings) as connection:
        assert runs.renew_leases(connection, [claim], LEASE) == [claim]
    clock.offset = timedelta(0)
    assert not _taken_back(settings, job_id)


def test_a_reconciler_whose_clock_is_ahead_takes_back_no_live_run(settings: Settings, clock: SkewedClock) -> None:
    job_id = queued_job(settings)
    _claim(settings, job_id, LEASE)
    clock.offset = SKEW
    assert not _taken_back(settings, job_id)


def test_a_reconciler_whose_clock_is_behind_takes_back_an_expired_run(settings: Settings, clock: SkewedClock) -> None:
    job_id = queued_job(settings)
    _claim(settings, job_id, SHORT_LEASE)
    _wait_for_expiry(settings, job_id)  # its worker died
    clock.offset = -SKEW
    assert _taken_back(settings, job_id)


def test_a_worker_whose_clock_is_ahead_leaves_no_lease_for_hours(settings: Settings, clock: SkewedClock) -> None:
    """A worker an hour ahead claims and dies: the reconciler (right clock) takes the job back once the
    lease has passed on the database's clock, not an hour later."""
    job_id = queued_job(settings)
    clock.offset = SKEW
    _claim(settings, job_id, SHORT_LEASE)
    clock.offset = timedelta(0)
    assert not _taken_back(settings, job_id)  # the lease holds while it lasts
    _wait_for_expiry(settings, job_id)
    assert _taken_back(settings, job_id)
