"""A retry's countdown becomes an absolute ETA on its publisher's clock, which the consuming worker
compares with its own: a webhook retry or a STOW-RS retry published by a worker whose clock is behind
(equivalently: consumed by one whose clock is ahead) came at once instead of after its delay. A retry
with an ETA is made only once it is due on the database's clock (``services.worker.webhook_tasks``,
``services.worker.dicom_tasks``); and a STOW-RS attempt already recorded on the job is not made again.

Real pieces: the database (SQLite, and a PostgreSQL database of each test's own), the embedded broker,
a Celery worker (``celery.contrib.testing.worker.start_worker``, in a thread of this process) as the
consumer, the webhook receiver (an HTTP server on a free loopback port) and a refused TCP connection (a
free loopback port nothing listens on) as the PACS. The fault is injected in the publisher only: its
Celery app's clock (``Celery.now``, from which ``send_task`` computes the ETA of a countdown) is an hour
behind the host's. The consumer, the database and the receiver keep the host's clock, so the times
compared below (the database's clock, the consumer's ``utcnow``) are one clock.
"""

from __future__ import annotations

import contextlib
import uuid
from collections.abc import Iterator
from datetime import datetime, timedelta
from http.server import BaseHTTPRequestHandler
from pathlib import Path
from typing import Any

import pytest
from celery import Celery
from celery.contrib.testing.worker import start_worker
from sqlalchemy import select

from services.core.config import Settings
from services.core.jobqueue import DELIVER_WEBHOOK, STORE_DICOM, make_celery
from services.db import jobs
from services.db.engine import session_scope
from services.db.models import Job, WebhookDelivery
from services.worker import dicom_tasks
from services.worker.dicom_tasks import register_dicom_tasks
from services.worker.tasks import execute_job
from services.worker.webhook_tasks import register_webhook_tasks
from tests.conftest import fresh_settings, spine_payload
from tests.faults import SkewedClock, free_port
from tests.interop_helpers import TEST_WEBHOOK_SECRET, LoopbackReceiver, reply, wait_until

SKEW = timedelta(hours=1)
"""How far the publisher's clock is behind the host's: far more than any retry delay (at most 120 s)."""
DELAY_S = 5.0
"""The retry delay under test (SPINE_WEBHOOK_RETRY_BASE_S, SPINE_DICOMWEB_RETRY_BASE_S): five times the
embedded broker's polling interval (kombu's SQLAlchemy transport, 1 s), so that a retry made at once is
told from one made when due."""
WAIT_S = 20.0
"""The longest wait for the consumer beyond DELAY_S: its start and polling under this 2-core machine's
load (the wait ends as soon as the outcome is there)."""


HOOK = "/hooks/eta"


class Receiver(LoopbackReceiver):
    """A webhook receiver on a free loopback port: 503 to the first request, 204 to the others."""

    def __init__(self) -> None:
        self.requests = 0

        def answer(handler: BaseHTTPRequestHandler, _body: bytes) -> None:
            self.requests += 1
            reply(handler, 503 if self.requests == 1 else 204)

        super().__init__(answer)


@pytest.fixture
def receiver() -> Iterator[Receiver]:
    made = Receiver()
    yield made
    made.close()


@pytest.fixture(params=["sqlite", "postgresql"])
def settings(request: pytest.FixtureRequest, tmp_path: Path, receiver: Receiver) -> Settings:
    pacs = f"http://127.0.0.1:{free_port()}/dicom-web"  # refused: every STOW-RS attempt fails, unavailable
    return fresh_settings(request, tmp_path, dicomweb_url=pacs, dicomweb_store_results=False, dicomweb_timeout_s=2,
                          dicomweb_retry_base_s=DELAY_S, webhook_retry_base_s=DELAY_S,
                          webhook_secret=TEST_WEBHOOK_SECRET, webhook_allowed_urls=receiver.url(HOOK))  # fmt: skip


def _publisher_behind(settings: Settings, monkeypatch: pytest.MonkeyPatch) -> Celery:
    """The publishing worker's app, its clock an hour behind the host's, with both tasks."""
    app = make_celery(settings)
    skewed = SkewedClock()
    skewed.offset = -SKEW
    monkeypatch.setattr(app, "now", skewed)
    register_webhook_tasks(app, settings)
    register_dicom_tasks(app, settings)
    return app


@contextlib.contextmanager
def consumer(settings: Settings) -> Iterator[Celery]:
    """A worker on the host's clock, consuming the webhook and DICOM queues, started once the retry is
    published (so that its due time is read first)."""
    app = make_celery(settings)
    register_webhook_tasks(app, settings)
    register_dicom_tasks(app, settings)
    with start_worker(app, perform_ping_check=False, queues=[settings.webhook_queue, settings.dicom_queue],
                      shutdown_timeout=30.0):  # fmt: skip
        yield app


def _due(settings: Settings, job_id: uuid.UUID) -> datetime:
    """When the retry of the job's webhook is due: attempt 1's ``next_attempt_at``."""
    with session_scope(settings) as session:
        due = session.scalar(
            select(WebhookDelivery.next_attempt_at).where(
                WebhookDelivery.job_id == job_id, WebhookDelivery.attempt == 1
            )
        )
    assert due is not None
    return due


def _attempt_started(settings: Settings, job_id: uuid.UUID, attempt: int) -> datetime | None:
    """When the consumer started attempt ``attempt`` of the job's webhook (its ``utcnow``), once made."""
    with session_scope(settings) as session:
        row = session.scalar(
            select(WebhookDelivery).where(WebhookDelivery.job_id == job_id, WebhookDelivery.attempt == attempt)
        )
        return row.attempted_at if row is not None and row.status_code is not None else None


def test_a_webhook_retry_published_by_a_worker_whose_clock_is_behind_waits_its_delay(
    settings: Settings, receiver: Receiver, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Attempt 1 answered 503: attempt 2 is due DELAY_S later on the database's clock. Published with an
    ETA an hour in the consumer's past, it is made no earlier than then, and made."""
    payload = {**spine_payload(), "callback_url": receiver.url(HOOK)}
    with session_scope(settings) as session:
        job, _ = jobs.create_job(session, payload)
        jobs.cancel_job(session, job.id)
    publisher = _publisher_behind(settings, monkeypatch)
    publisher.tasks[DELIVER_WEBHOOK](str(job.id), "cancelled", 1)  # the worker that made attempt 1
    assert receiver.requests == 1
    due = _due(settings, job.id)  # attempt 2's, as attempt 1 wrote it: DELAY_S after it, the database's clock
    with consumer(settings):
        wait_until(lambda: _attempt_started(settings, job.id, 2) is not None, DELAY_S + WAIT_S, "attempt 2")
    started = _attempt_started(settings, job.id, 2)
    assert started is not None and started >= due
    assert receiver.requests == 2


STOW_STUDY = {"study_instance_uid": "1.2.3", "patient_id": "P-STOW"}
"""The study of a job whose results are stored: only one with a Patient ID is (``results.not_storable``)."""


def _succeeded_job(settings: Settings) -> uuid.UUID:
    """A job run by the engine to success (its result stored), with no STOW-RS published yet."""
    with session_scope(settings) as session:
        job, _ = jobs.create_job(session, {**spine_payload(), "study": STOW_STUDY})
    assert execute_job(settings, job.id) == "succeeded"
    return job.id


def _stores(settings: Settings, job_id: uuid.UUID) -> list[dict[str, Any]]:
    with session_scope(settings) as session:
        job = session.get(Job, job_id)
        assert job is not None
        return list(job.dicom_stores or [])


def test_a_stow_retry_published_by_a_worker_whose_clock_is_behind_waits_its_delay(
    settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Attempt 1 found the PACS unavailable: attempt 2 is due DELAY_S later on the database's clock.
    Published with an ETA an hour in the consumer's past, it is made no earlier than then, and made."""
    stow = settings.model_copy(update={"dicomweb_store_results": True})
    job_id = _succeeded_job(settings)
    publisher = _publisher_behind(stow, monkeypatch)
    publisher.tasks[STORE_DICOM](str(job_id), 1)  # the worker that made attempt 1
    assert [s["attempt"] for s in _stores(stow, job_id)] == [1]
    with session_scope(stow) as session:  # attempt 2's due time as attempt 1 wrote it, the database's clock
        job = session.get(Job, job_id)
        assert job is not None and job.dicom_store_due_at is not None
        due = job.dicom_store_due_at - timedelta(seconds=stow.dicomweb_sweep_after_s)
    with consumer(stow):
        wait_until(lambda: len(_stores(stow, job_id)) >= 2, DELAY_S + WAIT_S, "attempt 2")
    second = _stores(stow, job_id)[1]
    assert second["attempt"] == 2
    assert datetime.fromisoformat(second["attempted_at"]) >= due


def test_a_stow_attempt_already_recorded_is_not_made_again(settings: Settings) -> None:
    """Two messages of one attempt (the sweep's, and the original held late by a consumer whose clock is
    behind): the second, run after the first is recorded, stores nothing again."""
    stow = settings.model_copy(update={"dicomweb_store_results": True})
    job_id = _succeeded_job(settings)
    app = make_celery(stow)
    register_dicom_tasks(app, stow)
    app.tasks[STORE_DICOM](str(job_id), 1)
    app.tasks[STORE_DICOM](str(job_id), 1)
    assert [s["attempt"] for s in _stores(stow, job_id)] == [1]
    assert dicom_tasks.attempt_wait_s(stow, job_id, 1, scheduled=False) is None
    assert dicom_tasks.attempt_wait_s(stow, job_id, 2, scheduled=False) == 0.0
