"""Data access of the ``webhook_deliveries`` table (one row per delivery attempt, shown on the job)
and of what a delivery reads of its job; and the webhook's outbox: ``job_ended`` publishes the first
attempt, or records it as attempt 0 for the reconciler when the broker cannot take it.

``job_ended`` is called where a job reaches a final state (the worker after storing an outcome, the
API after a cancel, the reconciler after failing a lost job); it never raises, and costs nothing for
a job without ``callback_url`` because callers look at the payload first. The message id is derived
from the job and its final status, so every attempt of a message carries the same ``webhook-id`` and a
message that a receiver already accepted is not sent again.
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from celery import Celery
from sqlalchemy import and_, exists, insert, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from services.core.config import Settings
from services.core.jobqueue import publish_webhook
from services.core.status import FINAL_STATUSES
from services.db.engine import session_scope
from services.db.jobs import job_json
from services.db.models import Job, WebhookDelivery, utcnow

log = logging.getLogger(__name__)

_NAMESPACE = uuid.UUID("0b7e3b9e-4f53-5a8e-9c4e-5e1f2a6c9d01")


def message_id(job_id: uuid.UUID | str, status: str) -> str:
    """The Standard Webhooks message id of a job's end (``webhook-id``): the same on every attempt, and
    with the attempt number the key of a row."""
    return "msg_" + uuid.uuid5(_NAMESPACE, f"{job_id}:{status}").hex


@dataclass(frozen=True)
class DeliveryJob:
    """What a delivery of a job's webhook reads of the job."""

    callback_url: str
    owner: str | None
    """The job owner's key id: whose webhook secret signs (``services.webhooks.signing.secret_for``)."""
    data: dict[str, Any]
    """The job as ``GET /v1/jobs/{id}`` shows it (``services.db.jobs.job_json``)."""
    finished_at: datetime | None


def delivery_job(session: Session, job_id: uuid.UUID) -> DeliveryJob | None:
    """The job to deliver, or None when it does not exist or has no callback_url."""
    job = session.get(Job, job_id)
    if job is None or not job.callback_url:
        return None
    return DeliveryJob(callback_url=job.callback_url, owner=job.owner, data=job_json(job), finished_at=job.finished_at)


def job_ended(
    settings: Settings, job_id: uuid.UUID | str, status: str, *, url: str | None = None,
    celery: Celery | None = None,
) -> bool:  # fmt: skip
    """Publish the first delivery of a job's webhook. Never raises; False when publishing failed.

    When it fails and ``url`` (the job's callback_url) is given, an attempt 0 is recorded on the
    job, due now, so that the reconciler's sweep publishes the message later.
    """
    try:
        publish_webhook(settings, job_id, status, 1, celery=celery)
        return True
    except Exception as exc:
        log.warning("could not publish the webhook of job %s (%s): %s", job_id, status, exc)
        if url:
            _record_unpublished(settings, uuid.UUID(str(job_id)), status, url, exc)
        return False


def _record_unpublished(settings: Settings, job_id: uuid.UUID, status: str, url: str, exc: Exception) -> None:
    now = utcnow()
    row = {"job_id": job_id, "message_id": message_id(job_id, status), "event": f"job.{status}", "attempt": 0,
           "url": url, "attempted_at": now}  # fmt: skip
    error = f"not published: {type(exc).__name__}; the reconciler publishes it again"
    try:
        with session_scope(settings) as session:  # a second failure for the same message finds the first row
            claim(session, **row, status_code=None, error=error, duration_ms=None, next_attempt_at=now)
    except Exception as db_exc:  # the database is down too: nothing left to remember it by
        log.error("webhook of job %s (%s) lost: neither published nor recorded: %s", job_id, status, db_exc)


def jobs_ended(session: Session, settings: Settings, job_ids: Iterable[uuid.UUID], celery: Celery) -> int:
    """``job_ended`` for those of ``job_ids`` that have a callback_url (the reconciler's failures)."""
    ids = list(job_ids)
    if not ids:
        return 0
    sent = 0
    for job_id, status, url in session.execute(select(Job.id, Job.status, Job.callback_url).where(Job.id.in_(ids))):
        if url and status in FINAL_STATUSES:
            sent += job_ended(settings, job_id, str(status), url=url, celery=celery)
    return sent


def claim(session: Session, **values: Any) -> int | None:
    """Insert the row of one attempt of a message; None when that attempt already has a row.

    The unique index on (message_id, attempt) makes this the one place where two deliveries of
    the same attempt (a message published twice by a repeated cancel, a sweep, a redelivery
    after a worker died) are told apart: only the first insert succeeds.
    """
    try:
        with session.begin_nested():
            row_id = session.scalar(insert(WebhookDelivery).values(**values).returning(WebhookDelivery.id))
    except IntegrityError:
        return None
    return row_id


def finish(session: Session, row_id: int, **values: Any) -> None:
    """Write an attempt's outcome (status code, error, duration, next attempt) on its claimed row."""
    session.execute(update(WebhookDelivery).where(WebhookDelivery.id == row_id).values(**values))


def delivered(session: Session, message_id: str) -> bool:
    """Whether a receiver already accepted (2xx) this message."""
    query = select(
        exists().where(
            WebhookDelivery.message_id == message_id,
            WebhookDelivery.status_code >= 200,
            WebhookDelivery.status_code < 300,
        )
    )
    return bool(session.scalar(query))


def overdue(session: Session, due_before: datetime, due_after: datetime, limit: int = 500) -> list[WebhookDelivery]:
    """Rows whose next attempt was due between ``due_after`` and ``due_before`` and never came.

    That is: no later attempt of the same message is recorded, and no attempt of it was accepted.
    Row ``attempt = 0`` marks a message that could not be published when its job ended.
    """
    later = WebhookDelivery.__table__.alias("later")
    query = (
        select(WebhookDelivery)
        .where(
            WebhookDelivery.next_attempt_at.is_not(None),
            WebhookDelivery.next_attempt_at > due_after,
            WebhookDelivery.next_attempt_at <= due_before,
            ~exists().where(
                and_(
                    later.c.message_id == WebhookDelivery.message_id,
                    (later.c.attempt > WebhookDelivery.attempt)
                    | and_(later.c.status_code >= 200, later.c.status_code < 300),
                )
            ),
        )
        .order_by(WebhookDelivery.next_attempt_at)
        .limit(limit)
    )
    return list(session.scalars(query))


def postpone(session: Session, row_id: int, until: datetime) -> None:
    """Move a row's next attempt to ``until`` (the reconciler published it again)."""
    session.execute(update(WebhookDelivery).where(WebhookDelivery.id == row_id).values(next_attempt_at=until))


def deliveries(session: Session, job_id: uuid.UUID) -> list[WebhookDelivery]:
    """The job's delivery attempts, oldest first (the ``deliveries`` member of a job)."""
    query = select(WebhookDelivery).where(WebhookDelivery.job_id == job_id).order_by(WebhookDelivery.id)
    return list(session.scalars(query))
