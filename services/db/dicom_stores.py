"""Data access of a job's STOW-RS pushes: the attempts recorded on the job (``jobs.dicom_stores``) and
the time by which the next one is overdue (``jobs.dicom_store_due_at``, what the reconciler's sweep
looks for); and what a push reads of its job.

The due time is written and compared on the database's clock (``services.db.clock``), never a
process's own: the worker that writes it and the reconciler that sweeps may run on hosts whose clocks
differ by more than ``SPINE_DICOMWEB_SWEEP_AFTER_S``. The times of an attempt, shown on the job
(``attempted_at``, ``next_attempt_at`` in ``jobs.dicom_stores``), are the database's clock too, so that
they are ordered with the job's times and one another whatever the workers' clocks: ``attempted_at``
is the database's time read with the job the attempt stores (``store_source``), or when attempt 0 is
recorded (``record_unpublished``); ``next_attempt_at`` is ``attempted_at`` plus the retry delay.
"""

from __future__ import annotations

import uuid
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from pydantic import BaseModel, Field
from sqlalchemy import ColumnElement, select, update
from sqlalchemy.orm import Session

from services.core.status import JobStatus
from services.db.clock import db_now, db_now_plus_s, seconds_until
from services.db.job_forms import JobForms, job_forms
from services.db.models import Job


class DicomStoreAttempt(BaseModel):
    """One STOW-RS attempt of a job's SR and figure."""

    attempt: int
    attempted_at: datetime
    ok: bool
    stored: list[str] = Field(default_factory=list, description="SOP Instance UIDs the PACS stored.")
    problem_type: str | None = Field(
        None,
        description="dicomweb-unavailable, dicomweb-store-refused, dicom-no-patient-identity (not stored: no study "
        "or no Patient ID), ...",
    )
    error: str | None = None
    duration_ms: float | None = None
    next_attempt_at: datetime | None = Field(None, description="When the next attempt is due; null: none.")


@dataclass(frozen=True)
class StoreSource:
    """What a push builds the SR and the figure from."""

    forms: JobForms
    finished_at: datetime | None
    read_at: datetime
    """The database's clock when the job was read, just before the attempt: its ``attempted_at``."""


def store_source(session: Session, job_id: uuid.UUID) -> StoreSource | None:
    """The job's forms when it succeeded with a result, with the database's clock read in the same
    statement; None otherwise (nothing to store)."""
    row = session.execute(select(Job, db_now()).where(Job.id == job_id)).first()
    if row is None:
        return None
    job, now = row
    if job.status != JobStatus.succeeded.value or job.result is None:
        return None
    return StoreSource(forms=job_forms(job), finished_at=job.finished_at, read_at=now)


def due_in(delay: timedelta) -> ColumnElement[datetime]:
    """The database's clock ``delay`` from now: a due time as ``set_due`` writes it."""
    return db_now_plus_s(delay.total_seconds())


def set_due(session: Session, job_id: uuid.UUID, due_at: datetime | ColumnElement[datetime] | None) -> None:
    """The time by which the job's next attempt is overdue (None: no attempt follows): ``due_in(delay)``,
    on the database's clock as the sweep compares it."""
    session.execute(update(Job).where(Job.id == job_id).values(dicom_store_due_at=due_at))


def record(session: Session, job_id: uuid.UUID, attempt: DicomStoreAttempt, sweep_after: timedelta) -> None:
    """Append the attempt to the job (its row locked); the due time is ``sweep_after`` past the next
    attempt (none: cleared), or past now for attempt 0 (the message was not published), counted on the
    database's clock from when the attempt is recorded (the next attempt is published then, with its
    delay: ``next_attempt_at − attempted_at``)."""
    job = session.execute(select(Job).where(Job.id == job_id).with_for_update()).scalar_one()
    stores = [*(job.dicom_stores or []), attempt.model_dump(mode="json")]
    if attempt.attempt == 0:
        due: ColumnElement[datetime] | None = due_in(sweep_after)
    elif attempt.next_attempt_at is not None:
        due = due_in(attempt.next_attempt_at - attempt.attempted_at + sweep_after)
    else:
        due = None
    session.execute(update(Job).where(Job.id == job_id).values(dicom_stores=stores, dicom_store_due_at=due))


def record_unpublished(session: Session, job_id: uuid.UUID, error: str, sweep_after: timedelta) -> DicomStoreAttempt:
    """Record attempt 0 (the first attempt's message could not be published: ``error``), its
    ``attempted_at`` the database's clock when it is recorded, and return it."""
    now = session.execute(select(db_now())).scalar_one()
    attempt = DicomStoreAttempt(attempt=0, attempted_at=now, ok=False, error=error)
    record(session, job_id, attempt, sweep_after)
    return attempt


def _next_number(stores: list[dict[str, Any]] | None) -> int:
    """The number of the attempt after the last recorded one (1 when none is)."""
    return max([int(s.get("attempt", 0)) for s in stores or []] + [0]) + 1


def next_attempt(session: Session, job_id: uuid.UUID, sweep_after: timedelta) -> tuple[int, float]:
    """The number of the job's next STOW-RS attempt (the last recorded + 1) and the seconds until it is
    due on the database's clock: ``dicom_store_due_at`` (written by ``record`` as the next attempt's
    time plus ``sweep_after``, or by the sweep and ``set_due`` as now plus ``sweep_after``) minus
    ``sweep_after`` minus the database's now, read in one statement; at least 0, and 0 without a due time
    or a job."""
    row = session.execute(select(Job.dicom_stores, Job.dicom_store_due_at, db_now()).where(Job.id == job_id)).first()
    if row is None:
        return 1, 0.0
    stores, due, now = row
    return _next_number(stores), seconds_until(None if due is None else due - sweep_after, now)


def overdue(
    session: Session, now: datetime | ColumnElement[datetime] | None = None, limit: int = 100
) -> list[tuple[uuid.UUID, int]]:
    """Jobs whose STOW-RS attempt is overdue (``dicom_store_due_at`` before ``now``, by default the
    database's clock: its message was never published or was lost), each with the number of its next
    attempt (the last recorded + 1)."""
    before = db_now() if now is None else now
    rows = session.execute(select(Job.id, Job.dicom_stores).where(Job.dicom_store_due_at < before).limit(limit)).all()
    return [(job_id, _next_number(stores)) for job_id, stores in rows]
