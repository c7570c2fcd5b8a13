"""The service's side of DICOM: the PACS from the settings, a job's payload resolved by reference in
the worker, and the STOW-RS push of a succeeded job's SR and figure with every attempt recorded on
the job (``jobs.dicom_stores``), retried with backoff on the ``<SPINE_QUEUE_NAME>.dicom`` queue.

Push: ``job_succeeded`` publishes attempt 1 of ``spine.dicom_store``; the task builds the SR and the
SC (``results``), stores both in one STOW-RS request, appends the attempt to the job, and when the
PACS was unavailable or refused, publishes the next attempt after 2, 4, 8 … s (at most 60 s), up to
``SPINE_DICOMWEB_MAX_ATTEMPTS``. The instances' UIDs derive from the job, so a repeated attempt
stores the same instances again (PACS replace or ignore them; none is duplicated).
"""

from __future__ import annotations

import logging
import time
import uuid
from datetime import datetime, timedelta
from typing import Any

from celery import Celery
from pydantic import BaseModel, Field
from sqlalchemy import select, update

from services.core.config import Settings
from services.core.jobqueue import make_celery
from services.core.retry import TRANSIENT
from services.db.engine import session_scope
from services.db.job_forms import job_forms
from services.db.models import Job, utcnow
from spine_client.dicom.errors import DicomError

from .dicomweb import DicomwebConfig, Pacs
from .errors import DicomwebError
from .results import job_figure_sc_dataset, job_sr_dataset

log = logging.getLogger(__name__)

STORE = "spine.dicom_store"
RETRY_BASE_S = 2.0
RETRY_MAX_S = 60.0
"""Backoff between STOW-RS attempts: 2 s doubling, capped at 60 s (5 attempts span about 30 s: a PACS
restart; longer outages are SPINE_DICOMWEB_MAX_ATTEMPTS' business)."""


class DicomStoreAttempt(BaseModel):
    """One STOW-RS attempt of a job's SR and figure."""

    attempt: int
    attempted_at: datetime
    ok: bool
    stored: list[str] = Field(default_factory=list, description="SOP Instance UIDs the PACS stored.")
    problem_type: str | None = Field(None, description="dicomweb-unavailable, dicomweb-store-refused, ...")
    error: str | None = None
    duration_ms: float | None = None
    next_attempt_at: datetime | None = Field(None, description="When the next attempt is due; null: none.")


def dicomweb_config(settings: Settings) -> DicomwebConfig | None:
    """The PACS of the settings, or None without ``SPINE_DICOMWEB_URL``."""
    if not settings.dicomweb_url:
        return None
    return DicomwebConfig(
        url=settings.dicomweb_url,
        username=settings.dicomweb_username,
        password=settings.dicomweb_password.get_secret_value() if settings.dicomweb_password else None,
        token=settings.dicomweb_token.get_secret_value() if settings.dicomweb_token else None,
        timeout_s=settings.dicomweb_timeout_s,
    )


def retry_delay_s(attempt: int) -> float:
    """Seconds before attempt ``attempt + 1``: 2 s doubling, at most 60 s."""
    return float(min(RETRY_MAX_S, RETRY_BASE_S * 2 ** (attempt - 1)))


def publish_store(settings: Settings, job_id: uuid.UUID | str, attempt: int, *, countdown: float = 0.0,
                  celery: Celery | None = None) -> None:  # fmt: skip
    app = celery or make_celery(settings)
    app.send_task(STORE, args=[str(job_id), attempt], countdown=countdown or None, queue=settings.dicom_queue)


def job_succeeded(settings: Settings, job_id: uuid.UUID, celery: Celery | None = None) -> bool:
    """Publish the first STOW-RS attempt of a succeeded job when results are to be stored. Never
    raises; a message that cannot be published is recorded as attempt 0 on the job, and the
    reconciler's ``sweep`` publishes it once ``SPINE_DICOMWEB_SWEEP_AFTER_S`` overdue."""
    if not (settings.dicomweb_store_results and settings.dicomweb_url):
        return False
    try:
        with session_scope(settings) as session:
            session.execute(update(Job).where(Job.id == job_id).values(
                dicom_store_due_at=utcnow() + timedelta(seconds=settings.dicomweb_sweep_after_s)))  # fmt: skip
    except Exception as exc:
        log.warning("could not mark the STOW-RS of job %s as due: %s", job_id, exc)
    try:
        publish_store(settings, job_id, 1, celery=celery)
        return True
    except Exception as exc:
        log.warning("could not publish the STOW-RS of job %s: %s", job_id, exc)
        try:
            _record(settings, job_id, DicomStoreAttempt(attempt=0, attempted_at=utcnow(), ok=False,
                                                        error=f"not published: {type(exc).__name__}"))  # fmt: skip
        except Exception as db_exc:
            log.error("STOW-RS of job %s neither published nor recorded: %s", job_id, db_exc)
        return False


def _record(settings: Settings, job_id: uuid.UUID, attempt: DicomStoreAttempt) -> None:
    """Append the attempt to the job; the sweep's due time follows the next attempt (none: cleared)."""
    with session_scope(settings) as session:
        job = session.execute(select(Job).where(Job.id == job_id).with_for_update()).scalar_one()
        job.dicom_stores = [*(job.dicom_stores or []), attempt.model_dump(mode="json")]
        sweep = timedelta(seconds=settings.dicomweb_sweep_after_s)
        if attempt.attempt == 0:
            job.dicom_store_due_at = attempt.attempted_at + sweep
        else:
            job.dicom_store_due_at = attempt.next_attempt_at + sweep if attempt.next_attempt_at else None


def sweep(settings: Settings, app: Celery, batch: int = 100) -> int:
    """Publish the STOW-RS attempt of every job whose attempt is overdue (``dicom_store_due_at`` past:
    its message was never published or was lost), as the next attempt number, and push its due time
    on by ``SPINE_DICOMWEB_SWEEP_AFTER_S``; a job out of attempts is cleared. Returns how many."""
    if not (settings.dicomweb_store_results and settings.dicomweb_url):
        return 0
    now = utcnow()
    sent = 0
    with session_scope(settings) as session:
        rows = session.execute(
            select(Job.id, Job.dicom_stores).where(Job.dicom_store_due_at < now).limit(batch)
        ).all()
        for job_id, stores in rows:
            attempt = max([int(s.get("attempt", 0)) for s in stores or []] + [0]) + 1
            due: datetime | None = now + timedelta(seconds=settings.dicomweb_sweep_after_s)
            if attempt > settings.dicomweb_max_attempts:
                due = None
            else:
                publish_store(settings, job_id, attempt, celery=app)
                sent += 1
            session.execute(update(Job).where(Job.id == job_id).values(dicom_store_due_at=due))
    if sent:
        log.info("STOW-RS sweep: published %d overdue attempts", sent)
    return sent


def store_once(settings: Settings, job_id: uuid.UUID, attempt: int) -> DicomStoreAttempt:
    """One STOW-RS attempt of the job's SR and SC; recorded on the job. Raises nothing from the PACS."""
    config = dicomweb_config(settings)
    with session_scope(settings) as session:
        job = session.get(Job, job_id)
        if job is None or job.status != "succeeded" or job.result is None or config is None:
            raise LookupError(f"job {job_id} has no result to store (or no SPINE_DICOMWEB_URL)")
        forms, finished = job_forms(job), job.finished_at
    started = time.perf_counter()
    outcome = DicomStoreAttempt(attempt=attempt, attempted_at=utcnow(), ok=False)
    try:
        sr = job_sr_dataset(job_id, forms, finished)
        sc = job_figure_sc_dataset(job_id, forms, finished)
        with Pacs(config) as pacs:
            stored = pacs.store([sr, sc])
        outcome.ok, outcome.stored = True, list(stored.stored)
    except DicomwebError as exc:
        outcome.problem_type, outcome.error = exc.problem, str(exc)
    except DicomError as exc:  # a result that cannot be put in DICOM: not retried
        outcome.problem_type, outcome.error = exc.problem, str(exc)
        attempt = settings.dicomweb_max_attempts
    outcome.duration_ms = (time.perf_counter() - started) * 1000.0
    if not outcome.ok and attempt < settings.dicomweb_max_attempts:
        outcome.next_attempt_at = outcome.attempted_at + timedelta(seconds=retry_delay_s(attempt))
    _record(settings, job_id, outcome)
    return outcome


def register_dicom_tasks(app: Celery, settings: Settings) -> None:
    """The ``spine.dicom_store`` task on ``app``."""

    @app.task(name=STORE, ignore_result=True, acks_late=True, autoretry_for=TRANSIENT, retry_backoff=True,
              max_retries=10)  # fmt: skip
    def dicom_store(job_id: str, attempt: int) -> None:
        parsed = uuid.UUID(job_id)
        try:
            outcome = store_once(settings, parsed, int(attempt))
        except LookupError as exc:
            log.warning("STOW-RS skipped: %s", exc)
            return
        if outcome.next_attempt_at is not None:
            publish_store(settings, parsed, outcome.attempt + 1, countdown=retry_delay_s(outcome.attempt), celery=app)
        log.info("STOW-RS of job %s attempt %d: %s", job_id, outcome.attempt, "stored" if outcome.ok else outcome.error)


def as_problem_fields(exc: DicomError) -> dict[str, Any]:
    """Extension members of a DICOM problem: the attributes by keyword and tag, and the payload field."""
    fields: dict[str, Any] = {"attributes": exc.labels}
    if exc.field:
        fields["field"] = exc.field
    return fields
