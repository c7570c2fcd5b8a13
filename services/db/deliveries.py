"""Data access of the ``webhook_deliveries`` table: one row per delivery attempt, shown on the job."""

from __future__ import annotations

import uuid
from datetime import datetime
from typing import Any

from sqlalchemy import and_, exists, insert, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from services.db.models import WebhookDelivery


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
