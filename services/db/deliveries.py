"""Data access of the ``webhook_deliveries`` table (one row per delivery attempt, shown on the job)
and of what a delivery reads of its job; and the webhook's outbox.

Outbox: before the first attempt of a message is published, its row ``attempt`` 0 is written, due
(``next_attempt_at``) when the job ended, on the database's clock: in the transaction that ends the
job where the job ends in this layer (the worker's ``runs.finish_job``, the reconciler's
``runs.reconcile``), else just before publishing (``job_ended`` after the API's cancel). Once
attempt 1 is claimed the row is no longer overdue; if its message never comes (the broker refused
it, or lost it in a restart), the reconciler's sweep finds the row ``SPINE_WEBHOOK_SWEEP_AFTER_S``
after the job ended and publishes attempt 1 again.
The row is listed on the job (``deliveries``) only when the broker refused the message ("not
published"), as an attempt 0 that made no request; otherwise the job lists its attempts alone.

Every ``next_attempt_at`` the sweep compares is written and compared on the database's clock
(``services.db.clock``), never a process's own: a worker or API host whose clock is off would
otherwise write a row already overdue for the sweep (a message still in the broker, or an attempt
still in flight, published again) or one that a lost message leaves unswept for as long as the skew.
Every ``attempted_at`` is the database's clock too, only shown but ordered with the job's times and the
other rows' whatever the hosts' clocks: an attempt's is its claim's (``claim`` with ``db_now()``), the
outbox row's the job's ``finished_at`` as the job shows it, or when the broker refused the message.

``job_ended`` is called where a job reaches a final state; it never raises, and costs nothing for a
job without ``callback_url`` because callers look at the payload first. The message id is derived
from the job and its final status, so every attempt of a message carries the same ``webhook-id`` and a
message that a receiver already accepted is not sent again.

The events of a run of STOW-RS attempts (``RUN_EVENTS``: ``job.dicom_stored``, ``job.dicom_store_failed``)
go the same way, one message per run: their outbox row is written with the attempt that ended the run
(``services.db.dicom_stores.record``, due at that attempt's ``attempted_at`` as the job shows it), then
``job_ended`` publishes it with ``recorded`` and the run (``run``: the number of the run's first attempt,
``dicom_stores.first_of_run``), which is part of their message id: a retried delivery keeps its
``webhook-id``, a new run's event is a new message.
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import datetime
from typing import Any, NamedTuple, TypeAlias

from celery import Celery
from sqlalchemy import ColumnElement, CursorResult, and_, case, exists, func, insert, or_, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from services.core.config import Settings
from services.core.jobqueue import publish_webhook
from services.core.status import FINAL_STATUSES
from services.db.clock import db_now, seconds_until
from services.db.engine import session_scope
from services.db.jobs import job_json
from services.db.models import Job, WebhookDelivery

log = logging.getLogger(__name__)

Moment: TypeAlias = datetime | ColumnElement[datetime]
"""A time, or an SQL expression of one (``services.db.clock.db_now``, ``db_now_plus_s``)."""

_NAMESPACE = uuid.UUID("0b7e3b9e-4f53-5a8e-9c4e-5e1f2a6c9d01")


RUN_EVENTS = frozenset({"dicom_stored", "dicom_store_failed"})
"""The events (after ``job.``) that end a run of STOW-RS attempts, one message per run: the attempt that
ended it stored the SR and SC (``dicom_stored``), or it failed with no attempt after it or the results are
not storable (``dicom_store_failed``). Any other event is the job's end (its final status)."""


def message_id(job_id: uuid.UUID | str, status: str, run: int | None = None) -> str:
    """The Standard Webhooks message id (``webhook-id``) of event ``job.<status>``: the same on every
    attempt, and with the attempt number the key of a row. The job's end (``run`` None): UUIDv5 of
    ``"{job_id}:{status}"``, as ever (receivers drop duplicates by it); an event of a run of STOW-RS
    attempts (``RUN_EVENTS``): of ``"{job_id}:{status}:{run}"``, ``run`` the number of the run's first
    attempt, so that each run's event is a message of its own."""
    key = f"{job_id}:{status}" if run is None else f"{job_id}:{status}:{run}"
    return "msg_" + uuid.uuid5(_NAMESPACE, key).hex


@dataclass(frozen=True)
class DeliveryJob:
    """What a delivery of a job's webhook reads of the job."""

    callback_url: str
    owner: str | None
    """The job owner's key id: whose webhook secret signs (``services.webhooks.signing.secret_for``)."""
    data: dict[str, Any]
    """The job as ``GET /v1/jobs`` lists it (``services.db.jobs.job_json``)."""
    finished_at: datetime | None
    dicom_stores: list[dict[str, Any]] | None = None
    """The job's STOW-RS attempts (``jobs.dicom_stores``) as stored."""


def delivery_job(session: Session, job_id: uuid.UUID) -> DeliveryJob | None:
    """The job to deliver, or None when it does not exist or has no callback_url."""
    job = session.get(Job, job_id)
    if job is None or not job.callback_url:
        return None
    return DeliveryJob(callback_url=job.callback_url, owner=job.owner, data=job_json(job), finished_at=job.finished_at,
                       dicom_stores=job.dicom_stores)  # fmt: skip


OUTBOX_ATTEMPT = 0
"""The ``attempt`` of a message's outbox row (see the module's docstring): no request is made under it."""
NOT_PUBLISHED = "not published: "
"""How the ``error`` of an outbox row whose message the broker refused begins."""


def outbox_row(job_id: uuid.UUID, status: str, url: str, ended_at: Moment, run: int | None = None) -> dict[str, Any]:
    """The values of the outbox row of the message a job that ended in ``status`` at ``ended_at`` (as
    the job shows it) sends, or of event ``job.<status>`` of the run of STOW-RS attempts ``run`` that
    ended at ``ended_at`` (the last attempt's ``attempted_at``): attempt 0, no outcome. Its due time is not
    among them: the statement that writes the row sets ``next_attempt_at`` to the database's clock
    (``db_now()``), the event's time as the sweep compares it."""
    return {"job_id": job_id, "message_id": message_id(job_id, status, run), "event": f"job.{status}",
            "attempt": OUTBOX_ATTEMPT, "url": url, "attempted_at": ended_at, "status_code": None, "error": None,
            "duration_ms": None}  # fmt: skip


def record_due(
    session: Session, job_id: uuid.UUID, status: str, url: str, ended_at: Moment, run: int | None = None
) -> bool:
    """Write the message's outbox row in ``session``'s transaction, due now on the database's clock;
    ``ended_at``: the job's ``finished_at`` as stored, or an SQL expression of it (``_stored_end``), or
    for an event of run ``run`` of STOW-RS attempts the time of the attempt that ended it. False (nothing
    written) when the row is there already."""
    return claim(session, **outbox_row(job_id, status, url, ended_at, run), next_attempt_at=db_now()) is not None


def job_ended(
    settings: Settings, job_id: uuid.UUID | str, status: str, *, url: str | None = None,
    celery: Celery | None = None, recorded: bool = False, run: int | None = None,
) -> bool:  # fmt: skip
    """Publish the first delivery of a job's webhook: of its end (``status`` its final status), or of the
    end of its run ``run`` of STOW-RS attempts (``status`` one of ``RUN_EVENTS``). Never raises; False
    when publishing failed.

    With ``url`` (the job's callback_url), the message's outbox row is written first unless the caller
    wrote it with the job's end or the run's (``recorded``); when publishing fails, the row says so ("not
    published"). Either way the reconciler's sweep publishes the message if no attempt comes.
    """
    job_uuid = uuid.UUID(str(job_id))
    if url and not recorded:
        _record_due(settings, job_uuid, status, url)
    try:
        publish_webhook(settings, job_uuid, status, 1, run=run, celery=celery)
        return True
    except Exception as exc:
        log.warning("could not publish the webhook of job %s (%s): %s", job_id, status, exc)
        if url:
            _record_unpublished(settings, job_uuid, status, url, exc, run)
        return False


def _stored_end(job_id: uuid.UUID) -> ColumnElement[datetime]:
    """The job's ``finished_at`` as its row holds it (the database's clock: the cancel wrote it), read in
    the statement that uses it; the database's now if the row has none."""
    finished = select(Job.finished_at).where(Job.id == job_id).scalar_subquery()
    return func.coalesce(finished, db_now(), type_=Job.finished_at.type)


def _record_due(settings: Settings, job_id: uuid.UUID, status: str, url: str) -> None:
    try:
        with session_scope(settings) as session:
            record_due(session, job_id, status, url, _stored_end(job_id))
    except Exception as exc:  # published all the same: only a lost message would go unnoticed
        log.warning("webhook of job %s (%s): its outbox row could not be written: %s", job_id, status, exc)


def _record_unpublished(
    settings: Settings, job_id: uuid.UUID, status: str, url: str, exc: Exception, run: int | None = None
) -> None:
    """Mark the message's outbox row "not published" (writing it if it is not there), its ``attempted_at``
    when the broker refused, on the database's clock.

    The refusal may come after the reconciler's sweep already published the message again: a publish to a
    broker that refuses or does not answer is retried (``task_publish_retry_policy``) for longer than
    ``SPINE_WEBHOOK_SWEEP_AFTER_S`` may be, while the row written before it is due. The sweep's own note
    ("no attempt within …") is then replaced, so that the job shows the refusal all the same (only a
    "not published" row is listed), and the row's due time, which the sweep moved ahead, is kept: the
    message is not published a second time for it. A second refusal of the same message keeps the first."""
    error = f"{NOT_PUBLISHED}{type(exc).__name__}; the reconciler publishes it again"
    mid = message_id(job_id, status, run)
    noted = WebhookDelivery.error
    try:
        with session_scope(settings) as session:
            outbox = (WebhookDelivery.message_id == mid, WebhookDelivery.attempt == OUTBOX_ATTEMPT)
            marked: CursorResult[Any] = session.execute(  # type: ignore[assignment]
                update(WebhookDelivery)
                .where(*outbox, or_(noted.is_(None), ~noted.startswith(NOT_PUBLISHED)))
                .values(error=error, attempted_at=db_now(),
                        next_attempt_at=case((noted.is_(None), db_now()), else_=WebhookDelivery.next_attempt_at))
            )  # fmt: skip
            if marked.rowcount == 0:
                row = {**outbox_row(job_id, status, url, db_now(), run), "error": error, "next_attempt_at": db_now()}
                claim(session, **row)
    except Exception as db_exc:  # the database is down too: nothing left to remember it by
        log.error("webhook of job %s (%s) lost: neither published nor recorded: %s", job_id, status, db_exc)


def jobs_ended(
    session: Session, settings: Settings, job_ids: Iterable[uuid.UUID], celery: Celery, *, recorded: bool = False
) -> int:
    """``job_ended`` for those of ``job_ids`` that have a callback_url (the reconciler's failures, whose
    outbox rows ``runs.reconcile`` wrote: ``recorded``)."""
    ids = list(job_ids)
    if not ids:
        return 0
    sent = 0
    for job_id, status, url in session.execute(select(Job.id, Job.status, Job.callback_url).where(Job.id.in_(ids))):
        if url and status in FINAL_STATUSES:
            sent += job_ended(settings, job_id, str(status), url=url, celery=celery, recorded=recorded)
    return sent


class Claimed(NamedTuple):
    """The row ``claim`` inserted: its id and its ``attempted_at`` as stored (given as ``db_now()``: the
    database's clock of the insert)."""

    id: int
    attempted_at: datetime


def claim(session: Session, **values: Any) -> Claimed | None:
    """Insert the row of one attempt of a message; None when that attempt already has a row.

    The unique index on (message_id, attempt) makes this the one place where two deliveries of
    the same attempt (a message published twice by a repeated cancel, a sweep, a redelivery
    after a worker died) are told apart: only the first insert succeeds.
    """
    try:
        with session.begin_nested():
            inserted = insert(WebhookDelivery).values(**values)
            row = session.execute(inserted.returning(WebhookDelivery.id, WebhookDelivery.attempted_at)).one()
    except IntegrityError:
        return None
    return Claimed(row.id, row.attempted_at)


def finish(session: Session, row_id: int, **values: Any) -> None:
    """Write an attempt's outcome (status code, error, duration, next attempt: a ``Moment`` on the
    database's clock, e.g. ``db_now_plus_s(delay)``) on its claimed row."""
    session.execute(update(WebhookDelivery).where(WebhookDelivery.id == row_id).values(**values))


def note(session: Session, row_id: int, error: str) -> None:
    """Write ``error`` on a row that has none yet: the sweep's note on an outbox row it published again
    leaves a refusal recorded meanwhile ("not published", ``job_ended``) as it is."""
    session.execute(
        update(WebhookDelivery).where(WebhookDelivery.id == row_id, WebhookDelivery.error.is_(None)).values(error=error)
    )


def settle_earlier(session: Session, message_id: str, attempt: int, attempted_at: datetime) -> None:
    """Attempt ``attempt`` of the message started at ``attempted_at`` (as its row shows it): an earlier
    row whose next attempt is due later than now on the database's clock (the sweep's postponement of
    a row it published again) gets that time, when its next attempt really came, instead of a time at
    which nothing will happen. Once a later attempt is recorded the sweep no longer looks at the earlier
    row (``overdue``), so the time written is only shown."""
    earlier = (WebhookDelivery.message_id == message_id, WebhookDelivery.attempt < attempt)
    session.execute(
        update(WebhookDelivery)
        .where(*earlier, WebhookDelivery.next_attempt_at > db_now())
        .values(next_attempt_at=attempted_at)
    )


def wait_s(session: Session, message_id: str, attempt: int) -> float:
    """Seconds until attempt ``attempt`` of the message is due on the database's clock: the
    ``next_attempt_at`` of the attempt before it (as ``services.worker.webhook_tasks.deliver_once``
    wrote it, ``db_now_plus_s(delay)``) minus the database's now, read in one statement; 0 when it is due,
    or when that row or its due time is missing (nothing to wait for)."""
    earlier = (WebhookDelivery.message_id == message_id, WebhookDelivery.attempt == attempt - 1)
    row = session.execute(select(WebhookDelivery.next_attempt_at, db_now()).where(*earlier)).first()
    return 0.0 if row is None else seconds_until(row[0], row[1])


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


def overdue(session: Session, due_before: Moment, due_after: Moment, limit: int = 500) -> list[WebhookDelivery]:
    """Rows whose next attempt was due between ``due_after`` and ``due_before`` and never came (the
    sweep gives both on the database's clock: ``db_now_plus_s(-seconds)``).

    That is: no later attempt of the same message is recorded, and no attempt of it was accepted.
    Row ``attempt = 0`` is the message's outbox row: its attempt 1 never came.
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


def postpone(session: Session, row_id: int, until: Moment) -> None:
    """Move a row's next attempt to ``until`` (the reconciler published it again; on the database's
    clock: ``db_now_plus_s(seconds)``)."""
    session.execute(update(WebhookDelivery).where(WebhookDelivery.id == row_id).values(next_attempt_at=until))


def deliveries(session: Session, job_id: uuid.UUID) -> list[WebhookDelivery]:
    """The job's delivery attempts, oldest first (the ``deliveries`` member of a job), and its outbox row
    when the broker refused the message (attempt 0, "not published")."""
    shown = or_(WebhookDelivery.attempt != OUTBOX_ATTEMPT, WebhookDelivery.error.startswith(NOT_PUBLISHED))
    query = select(WebhookDelivery).where(WebhookDelivery.job_id == job_id, shown).order_by(WebhookDelivery.id)
    return list(session.scalars(query))
