"""The due times that one process writes and another compares are on the database's clock
(services/db/clock.py), as the leases are (tests/db/test_lease_clock.py): a queued job's ``enqueued_at``
(the reconciler's ``SPINE_QUEUED_TIMEOUT_S``), a webhook attempt's ``next_attempt_at`` (the sweep's
``SPINE_WEBHOOK_SWEEP_AFTER_S``) and a job's ``dicom_store_due_at`` (the STOW-RS sweep's
``SPINE_DICOMWEB_SWEEP_AFTER_S``). With a process's own clock an hour off, a writer behind or a comparer
ahead publishes again a message the broker still holds (or an attempt still in flight: the receiver is
called twice), and a writer ahead or a comparer behind recovers a lost message an hour late.

The fault is injected in this test process only: the Python clock (``utcnow``) of the module that acts
(the API's ``services.db.jobs``, the worker's and the reconciler's ``services.db.runs``,
``services.db.deliveries``, ``services.worker.webhook_tasks``, ``services.worker.dicom_tasks``) is moved
an hour away from the host's, as on a host whose clock is wrong; far more than any of the margins
(10 s, 300 s by default). The databases (SQLite, and a PostgreSQL database of each test's own, so that
the reconciler and the sweeps see this test's rows only), the embedded broker and the webhook receiver
(an HTTP server on a free loopback port) are real."""

from __future__ import annotations

import uuid
from collections.abc import Callable, Iterator
from datetime import UTC, datetime, timedelta
from http.server import BaseHTTPRequestHandler
from pathlib import Path
from typing import Any

import pytest
from celery import Celery

from services.core.config import Settings
from services.core.jobqueue import make_celery, queue_depth
from services.db import deliveries, jobs, runs
from services.db.dicom_stores import DicomStoreAttempt
from services.db.engine import session_scope, worker_connection
from services.db.migrate import upgrade
from services.worker import dicom_tasks, webhook_tasks
from tests.conftest import queued_job
from tests.faults import SkewedClock, db_clock
from tests.interop_helpers import TEST_WEBHOOK_SECRET, LoopbackReceiver, reply, wait_until

SKEW = timedelta(hours=1)
"""How far the skewed process's clock is from the host's: far more than any margin (10 s, 300 s)."""
QUEUED_TIMEOUT = timedelta(seconds=60)
"""A queued timeout no test outlasts: a job enqueued in the test is never stale under it."""
SHORT = 1.0
"""A queued timeout or sweep delay (s) that the tests wait out on the database's clock."""
WAIT_S = 10.0
"""The longest wait for the database's clock to pass SHORT: SHORT plus this 2-core machine's slack under
the other helpers' load (the wait ends as soon as the clock has passed it)."""
LOST = {"type": "https://spine.example/problems/worker-lost", "title": "lost", "status": 500, "detail": "x"}
UNREACHABLE = "http://127.0.0.1:9/hooks/due-clock"
"""A callback_url that the sweep publishes for; no test makes its request."""


@pytest.fixture(params=["sqlite", "postgresql"])
def settings(request: pytest.FixtureRequest, tmp_path: Path) -> Settings:
    stow = "http://127.0.0.1:9/dicom-web"  # a PACS that no test reaches: the STOW-RS messages are only queued
    if request.param == "postgresql":
        url = request.getfixturevalue("fresh_postgres_url")
        made = Settings(DATABASE_URL=url, data_dir=tmp_path, dicomweb_url=stow, dicomweb_store_results=True)
    else:
        made = Settings(data_dir=tmp_path, dicomweb_url=stow, dicomweb_store_results=True)
    upgrade(made, quiet=True)
    return made


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> Iterator[SkewedClock]:
    skewed = SkewedClock()
    for module in (jobs, runs, deliveries, webhook_tasks, dicom_tasks):
        monkeypatch.setattr(module, "utcnow", skewed, raising=False)  # where the module reads a clock of its own
    yield skewed


@pytest.fixture
def broker(settings: Settings) -> Celery:
    """The embedded broker (a SQLite file of the test's own)."""
    return make_celery(settings)


def _wait_db_clock_past(settings: Settings, moment: datetime, seconds: float) -> None:
    """Until the database's clock is ``seconds`` past ``moment`` (a time read from it)."""
    wait_until(lambda: db_clock(settings) > moment + timedelta(seconds=seconds), WAIT_S, "the database's clock")


def _republished(settings: Settings, job_id: uuid.UUID, timeout: timedelta = QUEUED_TIMEOUT) -> bool:
    """One reconciler pass; whether it handed ``job_id`` to be published again."""
    with session_scope(settings) as session:
        outcome = runs.reconcile(session, queued_timeout=timeout, max_attempts=3, lost_problem=LOST)
    return job_id in outcome.requeue


# ------------------------------------------------------------------ the queued timeout


def test_a_job_enqueued_by_an_api_whose_clock_is_behind_is_not_published_again_at_once(
    settings: Settings, clock: SkewedClock
) -> None:
    clock.offset = -SKEW
    job_id = queued_job(settings)
    clock.offset = timedelta(0)
    assert not _republished(settings, job_id)


def test_a_reconciler_whose_clock_is_ahead_publishes_no_fresh_job_again(settings: Settings, clock: SkewedClock) -> None:
    job_id = queued_job(settings)
    clock.offset = SKEW
    assert not _republished(settings, job_id)


def test_a_job_enqueued_by_an_api_whose_clock_is_ahead_is_recovered_after_the_timeout(
    settings: Settings, clock: SkewedClock
) -> None:
    """Its message lost, the job is published again once the timeout passed on the database's clock,
    not an hour later."""
    clock.offset = SKEW
    job_id = queued_job(settings)
    clock.offset = timedelta(0)
    _wait_db_clock_past(settings, db_clock(settings), SHORT)
    assert _republished(settings, job_id, timedelta(seconds=SHORT))


def test_a_reconciler_whose_clock_is_behind_recovers_a_job_after_the_timeout(
    settings: Settings, clock: SkewedClock
) -> None:
    job_id = queued_job(settings)
    _wait_db_clock_past(settings, db_clock(settings), SHORT)
    clock.offset = -SKEW
    assert _republished(settings, job_id, timedelta(seconds=SHORT))


def test_a_job_published_again_by_a_reconciler_whose_clock_is_behind_waits_the_timeout_again(
    settings: Settings, clock: SkewedClock
) -> None:
    """The reconciler's own write of ``enqueued_at`` (a job marked unpublished, published again): the
    next pass, on a right clock, does not publish it a second time."""
    job_id = queued_job(settings)
    with session_scope(settings) as session:
        runs.mark_unpublished(session, [job_id])
    clock.offset = -SKEW
    assert _republished(settings, job_id)
    clock.offset = timedelta(0)
    assert not _republished(settings, job_id)


def test_a_run_released_by_a_worker_whose_clock_is_behind_is_not_published_again_at_once(
    settings: Settings, clock: SkewedClock
) -> None:
    """``release_claim`` (the PACS was unavailable) re-enqueues the job: the reconciler leaves it alone."""
    job_id = queued_job(settings)
    clock.offset = -SKEW
    with worker_connection(settings) as connection:
        claim = runs.claim_job(connection, job_id, "1.0")
        assert claim is not None
        assert runs.release_claim(connection, claim, 2.0)  # SPINE_DICOMWEB_RETRY_BASE_S
    clock.offset = timedelta(0)
    assert not _republished(settings, job_id)


# ------------------------------------------------------------------ webhook attempts


def _failed_by_worker(settings: Settings, callback_url: str) -> uuid.UUID:
    """A job with a callback_url claimed and failed by a worker (its outbox row written with its end)."""
    job_id = queued_job(settings, callback_url)
    with worker_connection(settings) as connection:
        claim = runs.claim_job(connection, job_id, "1.0")
        assert claim is not None
        assert runs.finish_job(connection, claim, error={"type": "x", "detail": "failed by the test"})
    return job_id


def _webhook_settings(settings: Settings, **update: Any) -> Settings:
    return settings.model_copy(update={"webhook_secret": TEST_WEBHOOK_SECRET, **update})


def test_an_outbox_row_written_by_a_worker_whose_clock_is_behind_is_not_swept_at_once(
    settings: Settings, clock: SkewedClock, broker: Celery
) -> None:
    """The job's first message waits in the broker: the sweep does not publish it a second time."""
    settings = _webhook_settings(settings)
    clock.offset = -SKEW
    _failed_by_worker(settings, UNREACHABLE)
    clock.offset = timedelta(0)
    assert webhook_tasks.sweep(settings, broker) == 0


def test_a_sweep_whose_clock_is_ahead_publishes_no_fresh_outbox_row(
    settings: Settings, clock: SkewedClock, broker: Celery
) -> None:
    settings = _webhook_settings(settings)
    _failed_by_worker(settings, UNREACHABLE)
    clock.offset = SKEW
    assert webhook_tasks.sweep(settings, broker) == 0


def test_a_sweep_whose_clock_is_behind_publishes_a_lost_first_message_after_its_delay(
    settings: Settings, clock: SkewedClock, broker: Celery
) -> None:
    settings = _webhook_settings(settings, webhook_sweep_after_s=SHORT)
    _failed_by_worker(settings, UNREACHABLE)
    _wait_db_clock_past(settings, db_clock(settings), SHORT)
    clock.offset = -SKEW
    assert webhook_tasks.sweep(settings, broker) == 1
    assert queue_depth(broker, settings.webhook_queue) == 1


def test_a_row_postponed_by_a_sweep_whose_clock_is_behind_is_not_published_again_at_once(
    settings: Settings, clock: SkewedClock, broker: Celery
) -> None:
    """The sweep's own write (the row postponed by SWEEP_AFTER once published again): the next sweep,
    on a right clock, does not publish it a second time."""
    settings = _webhook_settings(settings)
    job_id = queued_job(settings, UNREACHABLE)
    long_ago = datetime.now(UTC) - 2 * SKEW  # an attempt in flight whose worker died: overdue on every clock here
    with session_scope(settings) as session:
        deliveries.claim(session, job_id=job_id, message_id=deliveries.message_id(job_id, "failed"),
                         event="job.failed", attempt=1, url=UNREACHABLE, attempted_at=long_ago,
                         next_attempt_at=long_ago)  # fmt: skip
    clock.offset = -SKEW
    assert webhook_tasks.sweep(settings, broker) == 1
    clock.offset = timedelta(0)
    assert webhook_tasks.sweep(settings, broker) == 0
    assert queue_depth(broker, settings.webhook_queue) == 1


class SweepingReceiver(LoopbackReceiver):
    """A webhook receiver on a free loopback port that, while it holds a request (the attempt in
    flight), runs ``during`` and keeps what it returned; then answers ``status``."""

    def __init__(self, during: Callable[[], int], status: int = 204) -> None:
        self.requests = 0
        self.during_request: list[int] = []

        def answer(handler: BaseHTTPRequestHandler, _body: bytes) -> None:
            self.requests += 1
            self.during_request.append(during())
            reply(handler, status)

        super().__init__(answer)


@pytest.mark.parametrize("sweep_offset", [timedelta(0), SKEW], ids=["sweep-right", "sweep-ahead"])
def test_an_attempt_in_flight_is_not_swept(
    settings: Settings, clock: SkewedClock, broker: Celery, sweep_offset: timedelta
) -> None:
    """A worker whose clock is behind (or a sweep whose clock is ahead) while the request is held: the
    attempt's row is due at its deadline (SPINE_WEBHOOK_TIMEOUT_S, 10 s) on the database's clock, so the
    sweep publishes nothing and the receiver is called once."""

    def sweep_now() -> int:
        clock.offset = sweep_offset  # the reconciler's process, during the worker's request
        return webhook_tasks.sweep(hooks, broker)

    receiver = SweepingReceiver(sweep_now)
    try:
        url = receiver.url("/hooks/in-flight")
        hooks = _webhook_settings(settings, webhook_allowed_urls=url)
        job_id = queued_job(hooks, url)
        with session_scope(hooks) as session:
            jobs.cancel_job(session, job_id)
        clock.offset = -SKEW if sweep_offset == timedelta(0) else timedelta(0)  # the worker's process
        assert webhook_tasks.deliver_once(hooks, job_id, "cancelled", 1) is None
        assert (receiver.requests, receiver.during_request) == (1, [0])
        assert queue_depth(broker, hooks.webhook_queue) == 0
    finally:
        receiver.close()


def test_a_retry_due_from_a_worker_whose_clock_is_behind_is_not_swept_at_once(
    settings: Settings, clock: SkewedClock, broker: Celery
) -> None:
    """The receiver answered 500: the next attempt waits in the broker (its countdown, at most
    ``MAX_RETRY_DELAY_S``, 120 s, below SWEEP_AFTER's 300 s): the sweep does not publish it too."""
    receiver = SweepingReceiver(lambda: 0, status=500)
    try:
        url = receiver.url("/hooks/retry")
        hooks = _webhook_settings(settings, webhook_allowed_urls=url)
        job_id = queued_job(hooks, url)
        with session_scope(hooks) as session:
            jobs.cancel_job(session, job_id)
        clock.offset = -SKEW
        assert webhook_tasks.deliver_once(hooks, job_id, "cancelled", 1) is not None
        clock.offset = timedelta(0)
        assert webhook_tasks.sweep(hooks, broker) == 0
    finally:
        receiver.close()


# ------------------------------------------------------------------ STOW-RS


def test_a_stow_due_from_a_worker_whose_clock_is_behind_is_not_swept_at_once(
    settings: Settings, clock: SkewedClock, broker: Celery
) -> None:
    """``job_succeeded`` published attempt 1, which waits in the broker: the sweep does not publish it too."""
    job_id = queued_job(settings)
    clock.offset = -SKEW
    assert dicom_tasks.job_succeeded(settings, job_id, celery=broker)
    clock.offset = timedelta(0)
    assert dicom_tasks.sweep(settings, broker) == 0
    assert queue_depth(broker, settings.dicom_queue) == 1


def test_a_stow_sweep_whose_clock_is_ahead_publishes_no_fresh_attempt(
    settings: Settings, clock: SkewedClock, broker: Celery
) -> None:
    job_id = queued_job(settings)
    assert dicom_tasks.job_succeeded(settings, job_id, celery=broker)
    clock.offset = SKEW
    assert dicom_tasks.sweep(settings, broker) == 0


def test_a_stow_sweep_whose_clock_is_behind_publishes_a_lost_attempt_after_its_delay(
    settings: Settings, clock: SkewedClock, broker: Celery
) -> None:
    """Then the sweep's own write (the due time moved SWEEP_AFTER, 300 s by default, ahead): the next sweep,
    on a right clock, does not publish it a second time."""
    job_id = queued_job(settings)
    assert dicom_tasks.job_succeeded(settings.model_copy(update={"dicomweb_sweep_after_s": SHORT}), job_id, broker)
    _wait_db_clock_past(settings, db_clock(settings), SHORT)
    clock.offset = -SKEW
    assert dicom_tasks.sweep(settings, broker) == 1
    clock.offset = timedelta(0)
    assert dicom_tasks.sweep(settings, broker) == 0
    assert queue_depth(broker, settings.dicom_queue) == 2  # attempt 1 (lost in real life) and the sweep's


def test_a_failed_stow_attempt_recorded_by_a_worker_whose_clock_is_behind_is_not_swept_at_once(
    settings: Settings, clock: SkewedClock, broker: Celery
) -> None:
    """Attempt 1 failed (the PACS was unavailable): the worker records it as ``store_once`` does, its
    next attempt ``retry_delay_s`` later, and publishes that attempt with the delay; the sweep does not
    publish it too."""
    job_id = queued_job(settings)
    clock.offset = -SKEW
    attempted_at = clock()  # the attempt's times on a clock an hour behind (store_once now reads the database's)
    next_at = attempted_at + timedelta(seconds=dicom_tasks.retry_delay_s(settings, 1))
    failed = DicomStoreAttempt(
        attempt=1, attempted_at=attempted_at, ok=False, problem_type="dicomweb-unavailable", next_attempt_at=next_at
    )
    dicom_tasks._record(settings, job_id, failed)
    clock.offset = timedelta(0)
    assert dicom_tasks.sweep(settings, broker) == 0
