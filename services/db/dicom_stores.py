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

A run of attempts is ``SPINE_DICOMWEB_MAX_ATTEMPTS`` attempts from its first: the one the job's success
publishes (attempt 1), or the one a request to store the results again (``POST
/v1/jobs/{id}/dicom-store``, ``request_run``) makes due. Such a request is an entry of its own in
``jobs.dicom_stores``, marked by ``requested_by``: it sends nothing, its ``attempt`` is the number of
its run's first attempt (the last recorded attempt + 1, numbers go on) and its ``next_attempt_at`` when
that attempt is due. The last request entry is where the budget starts (``first_of_run``).

A run ends with the attempt that stored the SR and SC, or with one that failed and has no next attempt
(the run's last, or results that are not storable: ``dicom-no-patient-identity``). For a job with a
``callback_url``, ``record`` writes that run's webhook outbox row (``job.dicom_stored`` or
``job.dicom_store_failed``, ``services.db.deliveries``) in the transaction that appends the attempt, and
returns what the worker publishes then (``RunEnd``), so that a crash between the two loses nothing.
"""

from __future__ import annotations

import logging
import uuid
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from celery import Celery
from pydantic import BaseModel, Field
from sqlalchemy import ColumnElement, select, update
from sqlalchemy.orm import Session

from services.core.config import Settings
from services.core.jobqueue import publish_dicom_store
from services.core.status import JobStatus
from services.db import deliveries
from services.db.clock import db_now, db_now_plus_s, seconds_until
from services.db.engine import sqlite_write_lock
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
    requested_by: str | None = Field(
        None,
        description="Set on the entry of a request to store the results again (POST /v1/jobs/{id}/dicom-store): "
        "the client (API key name) that asked. That entry is no attempt, nothing was sent (ok false): `attempt` is "
        "the number of the first attempt of the run it starts (numbers go on after the last recorded one), "
        "`attempted_at` when it was asked, `next_attempt_at` when that attempt is due, and `error` says if its "
        "message could not be published (the reconciler publishes it later). The run has SPINE_DICOMWEB_MAX_ATTEMPTS "
        "attempts from that number. Null on an attempt.",
    )


log = logging.getLogger(__name__)


class StorePending(Exception):
    """A STOW-RS attempt of the job is still due or in flight (``dicom_store_due_at`` set): ``attempt``,
    the number of the next attempt, is due in ``wait_s`` seconds (0: now, or being made)."""

    def __init__(self, attempt: int, wait_s: float):
        self.attempt = attempt
        self.wait_s = wait_s
        super().__init__(f"attempt {attempt} is due in {wait_s:.3f} s")


@dataclass(frozen=True)
class StoreSource:
    """What a push builds the SR and the figure from."""

    forms: JobForms
    finished_at: datetime | None
    read_at: datetime
    """The database's clock when the job was read, just before the attempt: its ``attempted_at``."""
    first_of_run: int = 1
    """The number of the first attempt of the attempt's run (``first_of_run``): the run's budget starts there."""


def store_source(session: Session, job_id: uuid.UUID) -> StoreSource | None:
    """The job's forms when it succeeded with a result, with the database's clock read in the same
    statement; None otherwise (nothing to store)."""
    row = session.execute(select(Job, db_now()).where(Job.id == job_id)).first()
    if row is None:
        return None
    job, now = row
    if job.status != JobStatus.succeeded.value or job.result is None:
        return None
    return StoreSource(forms=job_forms(job), finished_at=job.finished_at, read_at=now,
                       first_of_run=first_of_run(job.dicom_stores))  # fmt: skip


def due_in(delay: timedelta) -> ColumnElement[datetime]:
    """The database's clock ``delay`` from now: a due time as ``set_due`` writes it."""
    return db_now_plus_s(delay.total_seconds())


def _locked_job(session: Session, job_id: uuid.UUID) -> tuple[Job, datetime]:
    """The job's row and the database's clock, the row locked until the transaction ends (``FOR UPDATE``
    on PostgreSQL, the database's write lock on SQLite: ``engine.sqlite_write_lock``), read as the lock
    found it (``populate_existing``: not as the session read it earlier, e.g. the API's lookup)."""
    sqlite_write_lock(session)
    locked = select(Job, db_now()).where(Job.id == job_id).with_for_update()
    job, now = session.execute(locked.execution_options(populate_existing=True)).one()
    return job, now


def start_first_run(session: Session, job_id: uuid.UUID, sweep_after: timedelta) -> bool:
    """Mark the first run of a succeeded job's STOW-RS attempts as due (``sweep_after`` from now, as
    ``set_due``), its row locked; False, and nothing written, when a run has started already: a due time
    is set, or the job lists an attempt or a request (a ``POST …/dicom-store`` made as the job succeeded,
    before this: its request published attempt 1, which must not be published twice)."""
    job, _ = _locked_job(session, job_id)
    if job.dicom_store_due_at is not None or job.dicom_stores:
        return False
    set_due(session, job_id, due_in(sweep_after))
    return True


def set_due(session: Session, job_id: uuid.UUID, due_at: datetime | ColumnElement[datetime] | None) -> None:
    """The time by which the job's next attempt is overdue (None: no attempt follows): ``due_in(delay)``,
    on the database's clock as the sweep compares it."""
    session.execute(update(Job).where(Job.id == job_id).values(dicom_store_due_at=due_at))


@dataclass(frozen=True)
class RunEnd:
    """A run of STOW-RS attempts that ended, as ``record`` returns it once it wrote the outbox row of the
    run's webhook: event ``job.<event>`` (``deliveries.RUN_EVENTS``) of run ``run`` (the number of the run's
    first attempt), to ``url`` (the job's callback_url)."""

    event: str
    run: int
    url: str


def ends_run(attempt: DicomStoreAttempt) -> bool:
    """Whether a recorded attempt ends its run: it stored the SR and SC, or it failed with no next attempt
    (attempt 0, the first attempt's message not published, is no attempt; a request entry neither)."""
    return attempt.attempt >= 1 and not attempt.requested_by and (attempt.ok or attempt.next_attempt_at is None)


def record(session: Session, job_id: uuid.UUID, attempt: DicomStoreAttempt, sweep_after: timedelta) -> RunEnd | None:
    """Append the attempt to the job (its row locked); the due time is ``sweep_after`` past the next
    attempt (none: cleared), or past now for attempt 0 (the message was not published), counted on the
    database's clock from when the attempt is recorded (the next attempt is published then, with its
    delay: ``next_attempt_at − attempted_at``).

    An attempt numbered below the current run's first (``first_of_run``: a copy of an earlier run's attempt,
    recorded after a new run was requested) is appended and nothing else.

    When the attempt ends its run (``ends_run``) and the job has a ``callback_url``, the run's webhook
    outbox row is written too, in this transaction (``deliveries.record_due``, due now, its
    ``attempted_at`` the attempt's), and returned for the caller to publish once committed; None otherwise,
    and when the row was there already (the attempt recorded twice)."""
    job = session.execute(select(Job).where(Job.id == job_id).with_for_update()).scalar_one()
    earlier = list(job.dicom_stores or [])
    stores = [*earlier, attempt.model_dump(mode="json")]
    run = first_of_run(earlier)
    if 0 < attempt.attempt < run:
        # a second copy of an attempt of a run that ended before a new one was requested, made as the first
        # was: listed (it reached the PACS), but it neither moves the new run's due time nor ends that run
        session.execute(update(Job).where(Job.id == job_id).values(dicom_stores=stores))
        return None
    if attempt.attempt == 0:
        due: ColumnElement[datetime] | None = due_in(sweep_after)
    elif attempt.next_attempt_at is not None:
        due = due_in(attempt.next_attempt_at - attempt.attempted_at + sweep_after)
    else:
        due = None
    session.execute(update(Job).where(Job.id == job_id).values(dicom_stores=stores, dicom_store_due_at=due))
    if not job.callback_url or not ends_run(attempt):
        return None
    end = RunEnd("dicom_stored" if attempt.ok else "dicom_store_failed", run, job.callback_url)
    written = deliveries.record_due(session, job_id, end.event, end.url, attempt.attempted_at, end.run)
    return end if written else None


def record_unpublished(session: Session, job_id: uuid.UUID, error: str, sweep_after: timedelta) -> DicomStoreAttempt:
    """Record attempt 0 (the first attempt's message could not be published: ``error``), its
    ``attempted_at`` the database's clock when it is recorded, and return it."""
    now = session.execute(select(db_now())).scalar_one()
    attempt = DicomStoreAttempt(attempt=0, attempted_at=now, ok=False, error=error)
    record(session, job_id, attempt, sweep_after)
    return attempt


def _is_request(entry: dict[str, Any]) -> bool:
    """Whether an entry of ``jobs.dicom_stores`` records a request for a new run, not an attempt."""
    return bool(entry.get("requested_by"))


def _next_number(stores: list[dict[str, Any]] | None) -> int:
    """The number of the attempt after the last recorded one (1 when none is); request entries are no
    attempts (their number is the one this gives while their run has made none)."""
    return max([int(s.get("attempt", 0)) for s in stores or [] if not _is_request(s)] + [0]) + 1


def first_of_run(stores: list[dict[str, Any]] | None) -> int:
    """The number of the first attempt of the job's current run of STOW-RS attempts: the last request
    entry's (``request_run``), 1 when there is none (the run the job's success started)."""
    return run_firsts(stores)[-1]


def run_firsts(stores: list[dict[str, Any]] | None) -> list[int]:
    """The number of the first attempt of each run of the job's STOW-RS attempts, oldest first: 1 (the run
    the job's success started) and each request entry's."""
    return [1, *(int(s["attempt"]) for s in stores or [] if _is_request(s))]


def run_stores(stores: list[dict[str, Any]] | None, first: int) -> list[dict[str, Any]]:
    """The job's ``dicom_stores`` up to the attempt that ended the run whose first attempt is ``first``
    (``ends_run``: the first such attempt numbered ``first`` or after), each entry as ``GET /v1/jobs/{id}``
    shows it; all of them when that run has not ended."""
    shown = [DicomStoreAttempt.model_validate(s).model_dump(mode="json") for s in stores or []]
    for index, entry in enumerate(stores or []):
        attempt = DicomStoreAttempt.model_validate(entry)
        if attempt.attempt >= first and ends_run(attempt):
            return shown[: index + 1]
    return shown


def run_of_message(session: Session, job_id: uuid.UUID, event: str, message_id: str) -> int | None:
    """The run (the number of its first attempt) of the job's run event ``event`` (``deliveries.RUN_EVENTS``)
    whose message id is ``message_id`` (``deliveries.message_id``), found among the job's runs; None when
    none matches (or no such job)."""
    stores = session.scalar(select(Job.dicom_stores).where(Job.id == job_id))
    return next((run for run in run_firsts(stores) if deliveries.message_id(job_id, event, run) == message_id), None)


def request_run(session: Session, job_id: uuid.UUID, requested_by: str, sweep_after: timedelta) -> DicomStoreAttempt:
    """Start a new run of STOW-RS attempts of a job (its row locked, in the caller's transaction, which
    commits it before the attempt is published): append the request entry (``requested_by``, the
    number of the run's first attempt, due now) and set the due time the sweep looks for,
    ``sweep_after`` from now, on the database's clock. Raises ``StorePending`` when an attempt is still
    due or in flight (``dicom_store_due_at`` set), with the seconds until it is due. Two requests at once:
    the second waits for the first's lock (``_locked_job``), then finds its due time."""
    job, now = _locked_job(session, job_id)
    stores = list(job.dicom_stores or [])
    if job.dicom_store_due_at is not None:
        raise StorePending(_next_number(stores), seconds_until(job.dicom_store_due_at - sweep_after, now))
    entry = DicomStoreAttempt(attempt=_next_number(stores), attempted_at=now, ok=False, next_attempt_at=now,
                              requested_by=requested_by)  # fmt: skip
    session.execute(update(Job).where(Job.id == job_id).values(
        dicom_stores=[*stores, entry.model_dump(mode="json")], dicom_store_due_at=due_in(sweep_after)))  # fmt: skip
    return entry


def publish_run(settings: Settings, session: Session, job_id: uuid.UUID, attempt: int, celery: Celery) -> bool:
    """Publish the first attempt of a run ``request_run`` recorded (and committed). Never raises; a
    message the broker refuses is written on the run's request entry (``error``: not published), its due
    time set again ``SPINE_DICOMWEB_SWEEP_AFTER_S`` from now, so that the reconciler's sweep publishes it
    then, as for a first attempt that could not be published (``record_unpublished``)."""
    try:
        publish_dicom_store(settings, job_id, attempt, celery=celery)
        return True
    except Exception as exc:
        log.warning("could not publish STOW-RS attempt %d of job %s: %s", attempt, job_id, exc)
        refused = type(exc).__name__
    try:
        locked = select(Job).where(Job.id == job_id).with_for_update().execution_options(populate_existing=True)
        stores = [dict(s) for s in session.execute(locked).scalar_one().dicom_stores or []]
        request = next(s for s in reversed(stores) if _is_request(s))
        request["error"] = f"not published: {refused}"
        due = due_in(timedelta(seconds=settings.dicomweb_sweep_after_s))
        session.execute(update(Job).where(Job.id == job_id).values(dicom_stores=stores, dicom_store_due_at=due))
        session.commit()
    except Exception as db_exc:
        session.rollback()
        log.error("STOW-RS attempt %d of job %s neither published nor recorded: %s", attempt, job_id, db_exc)
    return False


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
) -> list[tuple[uuid.UUID, int, int]]:
    """Jobs whose STOW-RS attempt is overdue (``dicom_store_due_at`` before ``now``, by default the
    database's clock: its message was never published or was lost), each with the number of its next
    attempt (the last recorded + 1) and of the first attempt of its run (``first_of_run``)."""
    before = db_now() if now is None else now
    rows = session.execute(select(Job.id, Job.dicom_stores).where(Job.dicom_store_due_at < before).limit(limit)).all()
    return [(job_id, _next_number(stores), first_of_run(stores)) for job_id, stores in rows]
