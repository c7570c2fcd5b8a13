"""The worker's side of DICOM storage: the STOW-RS push of a succeeded job's SR and figure, with every
attempt recorded on the job (``jobs.dicom_stores``), retried with backoff on the
``<SPINE_QUEUE_NAME>.dicom`` queue.

Push: ``job_succeeded`` publishes attempt 1 of ``spine.dicom_store``; the task builds the SR and the
SC and stores both in one STOW-RS request (``services.dicom.results.store_job_results``), appends the
attempt to the job, and when the PACS was unavailable or refused, publishes the next attempt after
``SPINE_DICOMWEB_RETRY_BASE_S`` doubling at each attempt (2, 4, 8 … s by default), at most
``SPINE_DICOMWEB_RETRY_MAX_S`` (60 s), up to ``SPINE_DICOMWEB_MAX_ATTEMPTS``. The instances' UIDs
derive from the job, so a repeated attempt stores the same instances again (PACS replace or ignore
them; none is duplicated).

Again: ``POST /v1/jobs/{id}/dicom-store`` (``services.db.dicom_stores.request_run``) records a request
and publishes the next attempt number, which starts a new run of ``SPINE_DICOMWEB_MAX_ATTEMPTS``
attempts: this task, its retries and the sweep count the budget, and the backoff its delays, from the
run's first attempt (``dicom_stores.first_of_run``), not from attempt 1.

The end of a run, for a job with a ``callback_url``: the attempt that stored the SR and SC, or the one
that failed with no next attempt (the run's last, or results that are not storable), is recorded with
the outbox row of its webhook (``job.dicom_stored``, ``job.dicom_store_failed``:
``dicom_stores.record``), which is then published (``deliveries.job_ended`` with the run), delivered
as the job's end's webhook is, and published by the webhook sweep if its message is lost.

Only a job with the patient's identity is stored (``services.dicom.results.not_storable``, checked by
``store_job_results`` before anything is built or sent, so on every path: the first attempt, a retry,
the sweep's): a job without ``study``, or whose study has no Patient ID, gets one attempt recorded with
``ok`` false, ``problem_type`` ``dicom-no-patient-identity``, the reason in ``error`` and no next attempt;
nothing reaches the PACS, and the job stays succeeded.

The due time the reconciler's sweep looks for (``jobs.dicom_store_due_at``) is written and compared on
the database's clock (``services.db.dicom_stores``), never this process's own; so are the times of an
attempt shown on the job (``attempted_at``, ``next_attempt_at``).

A retry's countdown becomes an absolute ETA on the publishing worker's clock, which the consuming worker
compares with its own: a consumer whose clock is ahead receives the retry early by the difference. So a
message with an ETA is made only once its attempt is due on the database's clock (``attempt_wait_s``);
one that came early is published again with the time left. A consumer whose clock is behind holds it
late by the difference; beyond ``SPINE_DICOMWEB_SWEEP_AFTER_S`` the sweep publishes the attempt again,
and a message of an attempt already recorded on the job is dropped, so that the same instances are not
stored twice in a row.
"""

from __future__ import annotations

import logging
import time
import uuid
from datetime import datetime, timedelta

from celery import Celery, Task
from sqlalchemy import ColumnElement

from services.core.config import Settings
from services.core.jobqueue import STORE_DICOM, publish_dicom_store
from services.core.retry import TRANSIENT
from services.db import deliveries, dicom_stores
from services.db.dicom_stores import DicomStoreAttempt
from services.db.engine import session_scope
from services.dicom.errors import DicomwebError
from services.dicom.results import NoPatientIdentity, store_job_results
from spine_client.dicom.errors import DicomError

log = logging.getLogger(__name__)


def retry_delay_s(settings: Settings, attempt: int) -> float:
    """Seconds before attempt ``attempt + 1`` of a STOW-RS push, ``attempt`` counted within its run (1: the
    run's first; and before a job whose PACS was unavailable runs again, ``attempt`` its run number):
    ``SPINE_DICOMWEB_RETRY_BASE_S`` · 2^(attempt − 1), at most ``SPINE_DICOMWEB_RETRY_MAX_S``."""
    return float(min(settings.dicomweb_retry_max_s, settings.dicomweb_retry_base_s * 2 ** (attempt - 1)))


def job_succeeded(settings: Settings, job_id: uuid.UUID, celery: Celery | None = None) -> bool:
    """Publish the first STOW-RS attempt of a succeeded job when results are to be stored. Never
    raises; a message that cannot be published is recorded as attempt 0 on the job, and the
    reconciler's ``sweep`` publishes it once ``SPINE_DICOMWEB_SWEEP_AFTER_S`` overdue. Nothing is published
    when a run has started already (``dicom_stores.start_first_run``)."""
    if not settings.stores_dicom_results:
        return False
    sweep_after = timedelta(seconds=settings.dicomweb_sweep_after_s)
    try:
        with session_scope(settings) as session:
            if not dicom_stores.start_first_run(session, job_id, sweep_after):
                log.info("STOW-RS of job %s: a run has started already (a request as the job succeeded)", job_id)
                return False
    except Exception as exc:
        log.warning("could not mark the STOW-RS of job %s as due: %s", job_id, exc)
    try:
        publish_dicom_store(settings, job_id, 1, celery=celery)
        return True
    except Exception as exc:
        log.warning("could not publish the STOW-RS of job %s: %s", job_id, exc)
        try:
            with session_scope(settings) as session:  # attempt 0, at the database's clock
                dicom_stores.record_unpublished(session, job_id, f"not published: {type(exc).__name__}", sweep_after)
        except Exception as db_exc:
            log.error("STOW-RS of job %s neither published nor recorded: %s", job_id, db_exc)
        return False


def _record(settings: Settings, job_id: uuid.UUID, attempt: DicomStoreAttempt) -> None:
    """Record the attempt on the job; when it ends its run, publish the run's webhook, whose outbox row
    was written with the attempt (``dicom_stores.record``)."""
    with session_scope(settings) as session:
        end = dicom_stores.record(session, job_id, attempt, timedelta(seconds=settings.dicomweb_sweep_after_s))
    if end is not None:
        deliveries.job_ended(settings, job_id, end.event, url=end.url, recorded=True, run=end.run)


def sweep(settings: Settings, app: Celery, batch: int = 100) -> int:
    """Publish the STOW-RS attempt of every job whose attempt is overdue (``dicom_store_due_at`` past:
    its message was never published or was lost), as the next attempt number, and push its due time
    on by ``SPINE_DICOMWEB_SWEEP_AFTER_S``; a job out of attempts (``SPINE_DICOMWEB_MAX_ATTEMPTS`` from its
    run's first, ``dicom_stores.first_of_run``) is cleared. Both times are the
    database's clock's (``services.db.clock``). Returns how many."""
    if not settings.stores_dicom_results:
        return 0
    sent = 0
    sweep_after = timedelta(seconds=settings.dicomweb_sweep_after_s)
    with session_scope(settings) as session:
        for job_id, attempt, first in dicom_stores.overdue(session, limit=batch):
            due: ColumnElement[datetime] | None = dicom_stores.due_in(sweep_after)
            if attempt > first + settings.dicomweb_max_attempts - 1:  # past its run's budget
                due = None
            else:
                publish_dicom_store(settings, job_id, attempt, celery=app)
                sent += 1
            dicom_stores.set_due(session, job_id, due)
    if sent:
        log.info("STOW-RS sweep: published %d overdue attempts", sent)
    return sent


def attempt_wait_s(settings: Settings, job_id: uuid.UUID, attempt: int, *, scheduled: bool) -> float | None:
    """Whether attempt ``attempt`` of the job's STOW-RS is to be made now: None when it is already
    recorded on the job (a second message of it, e.g. the sweep's and one held late by its consumer),
    else the seconds until it is due on the database's clock (``dicom_stores.next_attempt``) for a
    message published with a countdown (``scheduled``), 0 for one published to run at once."""
    with session_scope(settings) as session:
        number, wait = dicom_stores.next_attempt(session, job_id, timedelta(seconds=settings.dicomweb_sweep_after_s))
    if attempt < number:
        return None
    return wait if scheduled else 0.0


def store_once(settings: Settings, job_id: uuid.UUID, attempt: int) -> DicomStoreAttempt:
    """One STOW-RS attempt of the job's SR and SC; recorded on the job, with the next attempt's time while
    the run has attempts left (``SPINE_DICOMWEB_MAX_ATTEMPTS`` from its first, ``source.first_of_run``).
    Raises nothing from the PACS. A job without the patient's identity (``NoPatientIdentity``) is
    recorded as not stored, with its reason, and not retried."""
    config = settings.dicomweb
    with session_scope(settings) as session:
        source = dicom_stores.store_source(session, job_id)
    if source is None or config is None:
        raise LookupError(f"job {job_id} has no result to store (or no SPINE_DICOMWEB_URL)")
    if attempt < source.first_of_run:  # recorded before the request that started the current run
        raise LookupError(f"job {job_id}'s attempt {attempt} is of a run before the one requested from attempt "
                          f"{source.first_of_run}: a second copy of its message, not made")  # fmt: skip
    started = time.perf_counter()
    outcome = DicomStoreAttempt(attempt=attempt, attempted_at=source.read_at, ok=False)  # the database's clock
    retried = True
    try:
        outcome.stored = store_job_results(config, job_id, source.forms, source.finished_at)
        outcome.ok = True
    except DicomwebError as exc:
        outcome.problem_type, outcome.error = exc.problem, str(exc)
    except NoPatientIdentity as exc:  # nothing sent: not a failure of the PACS nor of the job, not retried
        outcome.problem_type, outcome.error = exc.problem, str(exc)
        retried = False
    except DicomError as exc:  # a result that cannot be put in DICOM: not retried
        outcome.problem_type, outcome.error = exc.problem, str(exc)
        retried = False
    outcome.duration_ms = (time.perf_counter() - started) * 1000.0
    in_run = attempt - source.first_of_run + 1  # the attempt's place in its run: the budget and the backoff
    if not outcome.ok and retried and in_run < settings.dicomweb_max_attempts:
        outcome.next_attempt_at = outcome.attempted_at + timedelta(seconds=retry_delay_s(settings, in_run))
    _record(settings, job_id, outcome)
    return outcome


def register_dicom_tasks(app: Celery, settings: Settings) -> None:
    """The ``spine.dicom_store`` task on ``app``."""

    @app.task(name=STORE_DICOM, bind=True, shared=False, ignore_result=True, acks_late=True,
              autoretry_for=TRANSIENT, retry_backoff=True, max_retries=10)  # fmt: skip
    def dicom_store(task: Task, job_id: str, attempt: int) -> None:
        parsed = uuid.UUID(job_id)
        attempt = int(attempt)
        wait = attempt_wait_s(settings, parsed, attempt, scheduled=task.request.eta is not None)
        if wait is None:
            log.info("STOW-RS of job %s attempt %d: already made (a second message of it), dropped", parsed, attempt)
            return
        if wait > 0:
            log.info("STOW-RS of job %s attempt %d came %.3f s before it is due on the database's clock "
                     "(this worker's clock and its publisher's differ): published again for then",
                     parsed, attempt, wait)  # fmt: skip
            publish_dicom_store(settings, parsed, attempt, countdown=wait, celery=app)
            return
        try:
            outcome = store_once(settings, parsed, attempt)
        except LookupError as exc:
            log.warning("STOW-RS skipped: %s", exc)
            return
        if outcome.next_attempt_at is not None:
            delay = (outcome.next_attempt_at - outcome.attempted_at).total_seconds()  # the run's backoff (store_once)
            publish_dicom_store(settings, parsed, outcome.attempt + 1, countdown=delay, celery=app)
        log.info("STOW-RS of job %s attempt %d: %s", job_id, outcome.attempt, "stored" if outcome.ok else outcome.error)
