"""A job whose PACS is unavailable is handed back to the queue (``runs.release_claim``) to run again after
``dicom_tasks.retry_delay_s`` (SPINE_DICOMWEB_RETRY_BASE_S, doubling): it is due again then, on the
database's clock (its ``enqueued_at``), and that backoff holds against the two things that used to cut it
short. The reconciler, which counts the run's message as missing (a worker holds it until its ETA, it does
not wait in the broker), publishes it again only once ``SPINE_QUEUED_TIMEOUT_S`` past that due time, not
past the hand-back; after a broker restart, which loses the run's message, it publishes it at once for
its due time. A message that comes before the due time (its ETA on its publisher's clock, compared
by the consumer with its own) claims nothing and spends no attempt: it is published again for the time
left.

Real pieces: the database (SQLite, and a PostgreSQL database of each test's own, so that the reconciler
sees this test's jobs only), the embedded broker, a refused TCP connection (a free loopback port nothing
listens on) as the PACS, and for the clock test a Celery worker (``celery.contrib.testing.worker.
start_worker``, in a thread of this process) as the consumer. The only fault injected is the publisher's
Celery clock (``Celery.now``, from which ``send_task`` computes the ETA of a countdown), an hour behind the
host's; the consumer and the database keep the host's clock.
"""

from __future__ import annotations

import logging
import time
import uuid
from datetime import datetime, timedelta
from pathlib import Path

import pytest
from celery.contrib.testing.worker import start_worker

from services.core.config import Settings
from services.core.jobqueue import RUN_JOB, make_celery, queue_depth
from services.db import jobs
from services.db.engine import session_scope
from services.db.migrate import upgrade
from services.db.models import Job
from services.worker.tasks import RunLater, execute_job, reconcile_once, register_tasks
from tests.conftest import fresh_settings, spine_payload
from tests.faults import SkewedClock, db_clock, free_port
from tests.interop_helpers import wait_until
from tools.loadbench import OwnRedis

DUE_S = 6.0
"""The hand-back delay under test (SPINE_DICOMWEB_RETRY_BASE_S): above QUEUED_TIMEOUT_S plus this 2-core
machine's slack, so that a reconciler pass fits between the queued timeout and the due time, and six
times the embedded broker's polling interval (kombu's SQLAlchemy transport, 1 s), so that a run made at
once is told from one made when due."""
QUEUED_TIMEOUT_S = 1.0
"""SPINE_QUEUED_TIMEOUT_S: far below DUE_S, as SPINE_DICOMWEB_RETRY_BASE_S · 2^(n−1) exceeds the default
10 s from the 4th hand-back (16 s) on."""
SKEW = timedelta(hours=1)
"""How far the publisher's clock is behind the host's: far more than any hand-back delay (at most 60 s)."""
WAIT_S = 20.0
"""The longest wait beyond a due time: the worker's start and polling under this machine's load (the wait
ends as soon as the outcome is there)."""


@pytest.fixture(params=["sqlite", "postgresql"])
def settings(request: pytest.FixtureRequest, tmp_path: Path) -> Settings:
    pacs = f"http://127.0.0.1:{free_port()}/dicom-web"  # refused: the PACS is unavailable
    return fresh_settings(request, tmp_path, dicomweb_url=pacs, dicomweb_timeout_s=2, dicomweb_retry_base_s=DUE_S,
                          max_attempts=6, queued_timeout_s=QUEUED_TIMEOUT_S)  # fmt: skip


def _by_reference_job(settings: Settings) -> uuid.UUID:
    """A queued job whose PA spacing must be read from the PACS (in px, its image named by UID)."""
    payload = spine_payload(spacing_mm=0.15)
    payload["study"] = {"study_instance_uid": "1.2.3", "pa_sop_instance_uid": "1.2.3.4"}
    with session_scope(settings) as session:
        job, _ = jobs.create_job(session, payload)
    return job.id


def _job(settings: Settings, job_id: uuid.UUID) -> Job:
    with session_scope(settings) as session:
        job = session.get(Job, job_id)
        assert job is not None
        session.expunge(job)
        return job


def _handed_back(settings: Settings, job_id: uuid.UUID) -> tuple[datetime, datetime]:
    """Run the job as a worker does: the PACS refuses, the job goes back to the queue for DUE_S. The
    database's clock just before and just after."""
    before = db_clock(settings)
    with pytest.raises(RunLater) as later:
        execute_job(settings, job_id)
    assert later.value.countdown == DUE_S  # SPINE_DICOMWEB_RETRY_BASE_S, attempt 1
    return before, db_clock(settings)


# PostgreSQL only (the service's database; the embedded SQLite's due time is the fast test's and
# tests/db/test_due_clock.py's): the waits of a due time cost the suite 7–10 s a database
@pytest.mark.parametrize("settings", ["postgresql"], indirect=True)
def test_the_reconciler_leaves_a_handed_back_job_until_it_is_due(settings: Settings) -> None:
    """No message in the broker (the worker that holds it until its ETA does not count as waiting): past
    the queued timeout but before the due time, the reconciler does not publish the job; past the due
    time plus the queued timeout, with still no message, it does."""
    app = make_celery(settings)
    job_id = _by_reference_job(settings)
    before, after = _handed_back(settings, job_id)
    wait_until(lambda: db_clock(settings) > after + timedelta(seconds=QUEUED_TIMEOUT_S), WAIT_S, "the queued timeout")
    early = reconcile_once(settings, app)
    checked = db_clock(settings)
    assert checked < before + timedelta(seconds=DUE_S), "the machine was too slow: the pass came after the due time"
    assert job_id not in early.requeue
    assert queue_depth(app, settings.queue_name) == 0
    job = _job(settings, job_id)
    assert (job.status, job.attempts) == ("queued", 1)
    due = job.enqueued_at  # when it is due again: the hand-back plus DUE_S, the database's clock
    assert due is not None and before + timedelta(seconds=DUE_S) <= due <= after + timedelta(seconds=DUE_S)

    late = due + timedelta(seconds=QUEUED_TIMEOUT_S)
    wait_until(lambda: db_clock(settings) > late, DUE_S + WAIT_S, "the due time plus the queued timeout")
    assert job_id in reconcile_once(settings, app).requeue
    assert queue_depth(app, settings.queue_name) == 1


def test_a_run_that_comes_before_its_job_is_due_claims_nothing_and_waits_the_time_left(settings: Settings) -> None:
    """The job's message run right after the hand-back (as a consumer whose clock is DUE_S or more ahead of
    its publisher's does): no claim, no attempt spent, the job still queued and due when it was; the run
    is handed back for the time left until then."""
    job_id = _by_reference_job(settings)
    _handed_back(settings, job_id)
    due = _job(settings, job_id).enqueued_at
    assert due is not None
    before = db_clock(settings)
    with pytest.raises(RunLater) as early:
        execute_job(settings, job_id)
    after = db_clock(settings)
    job = _job(settings, job_id)
    assert (job.status, job.attempts, job.started_at, job.enqueued_at) == ("queued", 1, None, due)
    left = early.value.countdown  # the seconds from the database's now to the due time
    assert (due - after).total_seconds() <= left <= (due - before).total_seconds()


# PostgreSQL only (the service's database; the embedded SQLite's due time is the fast test's and
# tests/db/test_due_clock.py's): the waits of a due time cost the suite 7–10 s a database
@pytest.mark.parametrize("settings", ["postgresql"], indirect=True)
def test_a_run_published_by_a_worker_whose_clock_is_behind_waits_until_its_job_is_due(
    settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The worker that made attempt 1 publishes the run again with a countdown of DUE_S, its ETA an hour in
    the consumer's past: the consumer receives it at once, and makes attempt 2 (the last: the job fails
    ``dicomweb-unavailable``) no earlier than the job is due on the database's clock."""
    last = settings.model_copy(update={"max_attempts": 2})
    job_id = _by_reference_job(last)
    publisher = make_celery(last)
    skewed = SkewedClock()
    skewed.offset = -SKEW
    monkeypatch.setattr(publisher, "now", skewed)
    register_tasks(publisher, last)
    before = db_clock(last)
    publisher.tasks[RUN_JOB](str(job_id))  # the worker that made attempt 1: the PACS refused
    handed_back = _job(last, job_id)
    assert (handed_back.status, handed_back.attempts) == ("queued", 1)
    consumer = make_celery(last)
    register_tasks(consumer, last)
    with start_worker(consumer, perform_ping_check=False, queues=[last.queue_name], shutdown_timeout=30.0):
        wait_until(lambda: _job(last, job_id).status == "failed", DUE_S + WAIT_S, "attempt 2")
    job = _job(last, job_id)
    assert job.attempts == 2 and job.error is not None and job.error["type"].endswith("dicomweb-unavailable")
    assert job.started_at is not None and job.started_at >= before + timedelta(seconds=DUE_S)  # not at once
    due = handed_back.enqueued_at  # the hand-back plus DUE_S, on the database's clock
    assert due is not None and before + timedelta(seconds=DUE_S) <= due <= job.started_at


def test_a_handed_back_job_whose_message_a_broker_restart_lost_runs_once_due(
    tmp_path: Path, fresh_postgres_url: str, own_redis: OwnRedis, caplog: pytest.LogCaptureFixture
) -> None:
    """The run's message (a countdown of DUE_S) waits in the broker when the broker restarts and loses it
    (a worker holding it until its ETA drops it too when its connection is lost: Celery's
    ``Consumer.on_close``). The reconciler's pass that finds the restart, before the job is due, publishes
    it for its due time: a real worker makes attempt 2 (the last: the job fails ``dicomweb-unavailable``)
    no earlier than the job is due and before the due time plus the default SPINE_QUEUED_TIMEOUT_S (10 s),
    when the queued timeout alone would publish it. The passes, every second as beat runs them,
    publish nothing twice."""
    pacs = f"http://127.0.0.1:{free_port()}/dicom-web"  # refused: the PACS is unavailable
    settings = Settings(DATABASE_URL=fresh_postgres_url, CELERY_BROKER_URL=own_redis.url, data_dir=tmp_path,
                        dicomweb_url=pacs, dicomweb_timeout_s=2, dicomweb_retry_base_s=DUE_S,
                        max_attempts=2)  # fmt: skip
    upgrade(settings, quiet=True)
    queued_timeout = timedelta(seconds=settings.queued_timeout_s)  # the default
    app = make_celery(settings)
    register_tasks(app, settings)
    reconcile_once(settings, app)  # its first look at the broker: the broker's run id
    job_id = _by_reference_job(settings)
    app.tasks[RUN_JOB](str(job_id))  # attempt 1: the PACS refused; the run published again for DUE_S
    due = _job(settings, job_id).enqueued_at
    assert due is not None and queue_depth(app, settings.queue_name) == 1
    own_redis.stop()  # SIGKILL, then a new run: the message is gone
    own_redis.start()
    assert queue_depth(app, settings.queue_name) == 0
    with caplog.at_level(logging.INFO, logger="services.worker.tasks"):
        restart = reconcile_once(settings, app)
    assert "the broker restarted" in caplog.text
    assert db_clock(settings) < due, "the machine was too slow: the restart's pass came after the due time"
    assert [job for job, _ in restart.later] == [job_id] and job_id not in restart.requeue
    assert queue_depth(app, settings.queue_name) == 1
    consumer = make_celery(settings)
    register_tasks(consumer, settings)
    with start_worker(consumer, perform_ping_check=False, queues=[settings.queue_name], shutdown_timeout=30.0):
        deadline = time.monotonic() + DUE_S + queued_timeout.total_seconds() + WAIT_S
        while _job(settings, job_id).status != "failed" and time.monotonic() < deadline:
            passed = reconcile_once(settings, app)  # as beat runs it, every second
            assert job_id not in passed.requeue and passed.later == []
            time.sleep(1.0)
    job = _job(settings, job_id)
    assert job.status == "failed" and job.attempts == 2
    assert job.error is not None and job.error["type"].endswith("dicomweb-unavailable")
    assert job.started_at is not None and due <= job.started_at < due + queued_timeout
