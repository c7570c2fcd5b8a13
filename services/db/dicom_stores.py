"""Data access of a job's STOW-RS pushes: the attempts recorded on the job (``jobs.dicom_stores``) and
the time by which the next one is overdue (``jobs.dicom_store_due_at``, what the reconciler's sweep
looks for); and what a push reads of its job.
"""

from __future__ import annotations

import uuid
from dataclasses import dataclass
from datetime import datetime, timedelta

from pydantic import BaseModel, Field
from sqlalchemy import select, update
from sqlalchemy.orm import Session

from services.core.status import JobStatus
from services.db.job_forms import JobForms, job_forms
from services.db.models import Job


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


@dataclass(frozen=True)
class StoreSource:
    """What a push builds the SR and the figure from."""

    forms: JobForms
    finished_at: datetime | None


def store_source(session: Session, job_id: uuid.UUID) -> StoreSource | None:
    """The job's forms when it succeeded with a result; None otherwise (nothing to store)."""
    job = session.get(Job, job_id)
    if job is None or job.status != JobStatus.succeeded.value or job.result is None:
        return None
    return StoreSource(forms=job_forms(job), finished_at=job.finished_at)


def set_due(session: Session, job_id: uuid.UUID, due_at: datetime | None) -> None:
    """The time by which the job's next attempt is overdue (None: no attempt follows)."""
    session.execute(update(Job).where(Job.id == job_id).values(dicom_store_due_at=due_at))


def record(session: Session, job_id: uuid.UUID, attempt: DicomStoreAttempt, sweep_after: timedelta) -> None:
    """Append the attempt to the job (its row locked); the due time is ``sweep_after`` past the next
    attempt (none: cleared), or past this one for attempt 0 (the message was not published)."""
    job = session.execute(select(Job).where(Job.id == job_id).with_for_update()).scalar_one()
    job.dicom_stores = [*(job.dicom_stores or []), attempt.model_dump(mode="json")]
    if attempt.attempt == 0:
        job.dicom_store_due_at = attempt.attempted_at + sweep_after
    else:
        job.dicom_store_due_at = attempt.next_attempt_at + sweep_after if attempt.next_attempt_at else None


def overdue(session: Session, now: datetime, limit: int = 100) -> list[tuple[uuid.UUID, int]]:
    """Jobs whose STOW-RS attempt is overdue (``dicom_store_due_at`` before ``now``: its message was
    never published or was lost), each with the number of its next attempt (the last recorded + 1)."""
    rows = session.execute(select(Job.id, Job.dicom_stores).where(Job.dicom_store_due_at < now).limit(limit)).all()
    return [(job_id, max([int(s.get("attempt", 0)) for s in stores or []] + [0]) + 1) for job_id, stores in rows]
