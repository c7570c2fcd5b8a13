"""Runs of jobs: the worker's claim and finish, fenced by attempt, and the reconciler's pass
over stranded jobs; publishing job messages and marking those that could not be published.

State changes are guarded by the expected current state (``WHERE status = ...``), so a message
delivered twice, a cancel racing a fit, or a reconciler racing a slow worker never gives a job
two outcomes. A run is fenced by its attempt number: a worker can only finish the run it claimed.
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import Any, cast

import pydantic_core
from celery import Celery
from sqlalchemy import (
    Boolean,
    Connection,
    CursorResult,
    Table,
    bindparam,
    column,
    func,
    insert,
    literal,
    or_,
    select,
    true,
    update,
)
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.dialects.postgresql import JSON
from sqlalchemy.orm import Session

from services.core.jobqueue import enqueue
from services.core.status import JobStatus
from services.db import deliveries
from services.db.clock import db_now, db_now_plus, db_now_plus_s, seconds_param, seconds_until
from services.db.engine import SerializedJSON
from services.db.jobs import study_column_values
from services.db.models import Job, JobMeasures, VertebraStrain, WebhookDelivery
from services.db.results import measures_row, strain_rows
from spine_engine.models import RegistrationResult


@dataclass(frozen=True)
class Claim:
    """A run of a job that this worker owns: fenced by the attempt number."""

    job_id: uuid.UUID
    attempt: int
    payload: dict[str, Any]
    created_at: datetime
    callback_url: str | None = None
    dicom: dict[str, Any] | None = None
    """What was read from the images' headers so far (``jobs.dicom``): the client's, or an earlier run's."""


_JOBS = cast(Table, Job.__table__)
_CLAIM = (
    update(_JOBS)
    .where(
        _JOBS.c.id == bindparam("job_id"),
        _JOBS.c.status == JobStatus.queued.value,
        or_(_JOBS.c.enqueued_at.is_(None), _JOBS.c.enqueued_at <= db_now()),
    )
    .values(
        status=JobStatus.running.value,
        started_at=db_now(),
        attempts=_JOBS.c.attempts + 1,
        engine_version=bindparam("engine_version"),
        lease_expires_at=db_now_plus(seconds_param("lease_s")),
    )
    .returning(_JOBS.c.attempts, _JOBS.c.payload, _JOBS.c.created_at, _JOBS.c.callback_url, _JOBS.c.dicom)
)
_RENEW = (
    update(_JOBS)
    .where(
        _JOBS.c.id == bindparam("job_id"),
        _JOBS.c.status == JobStatus.running.value,
        _JOBS.c.attempts == bindparam("attempt"),
    )
    .values(lease_expires_at=db_now_plus(seconds_param("lease_s")))
)
_FINISH = (
    update(_JOBS)
    .where(
        _JOBS.c.id == bindparam("job_id"),
        _JOBS.c.status == JobStatus.running.value,
        _JOBS.c.attempts == bindparam("attempt"),
    )
    .values(
        status=bindparam("status"),
        finished_at=db_now(),
        result=bindparam("result"),
        error=bindparam("error"),
        engine_version=func.coalesce(bindparam("engine_version"), _JOBS.c.engine_version),
        lease_expires_at=None,
    )
)
_MEASURES = cast(Table, JobMeasures.__table__)
_STRAINS = cast(Table, VertebraStrain.__table__)
_DELIVERIES = cast(Table, WebhookDelivery.__table__)
_INSERT_MEASURES = insert(_MEASURES)
_INSERT_STRAINS = insert(_STRAINS)
_INSERT_OUTBOX = sqlite.insert(_DELIVERIES).values(next_attempt_at=db_now()).on_conflict_do_nothing()
_MEASURE_COLUMNS = [c for c in _MEASURES.c if c.name != "job_id"]
_STRAIN_COLUMNS = [c for c in _STRAINS.c if c.name != "job_id"]
_NO_MEASURES = {c.name: None for c in _MEASURE_COLUMNS}
_OUTBOX_COLUMNS = ["job_id", "message_id", "event", "attempt", "url", "attempted_at", "next_attempt_at"]
_NO_OUTBOX = {"with_webhook": False, "webhook_message_id": None, "webhook_event": None, "webhook_url": None}


def _outbox_cte(done: Any) -> Any:
    """The insert of the webhook's outbox row (``deliveries.outbox_row``, due on the database's clock)
    for the job ``done`` ended, when ``:with_webhook``; nothing when the row is there already. Its
    ``attempted_at`` is the job's ``finished_at`` as ``done`` wrote it."""
    ended_at = done.c.finished_at
    row = select(
        done.c.id,
        bindparam("webhook_message_id", type_=_DELIVERIES.c.message_id.type),
        bindparam("webhook_event", type_=_DELIVERIES.c.event.type),
        literal(deliveries.OUTBOX_ATTEMPT),
        bindparam("webhook_url", type_=_DELIVERIES.c.url.type),
        ended_at,
        db_now(),
    ).where(bindparam("with_webhook", type_=Boolean()))
    return postgresql.insert(_DELIVERIES).from_select(_OUTBOX_COLUMNS, row).on_conflict_do_nothing().cte("w")


def _finish_one_statement() -> Any:
    """PostgreSQL: ``_FINISH``, both measure inserts and the webhook's outbox row as one statement with
    data-modifying CTEs.

    ``WITH done AS (UPDATE jobs … RETURNING id), m AS (INSERT INTO job_measures SELECT … FROM done
    WHERE :with_measures), s AS (INSERT INTO vertebra_strains SELECT done.id, r.* FROM done,
    json_to_recordset(:strains) AS r(level text, u1 float8, …)), w AS (INSERT INTO webhook_deliveries
    SELECT done.id, … FROM done WHERE :with_webhook ON CONFLICT DO NOTHING) SELECT count(*) FROM done``:
    nothing is inserted when the fenced update matched no row, and all of it commits together.
    The strains go as one ``json`` document (``json_to_recordset`` reads the text once; ``jsonb``
    would build a binary document first).
    """
    done = _FINISH.returning(_JOBS.c.id, _JOBS.c.finished_at).cte("done")
    measures = insert(_MEASURES).from_select(
        ["job_id", *[c.name for c in _MEASURE_COLUMNS]],
        select(done.c.id, *[bindparam(c.name, type_=c.type) for c in _MEASURE_COLUMNS]).where(
            bindparam("with_measures", type_=Boolean())
        ),
    )
    record = (
        func.json_to_recordset(bindparam("strains", type_=JSON()))
        .table_valued(*[column(c.name, c.type) for c in _STRAIN_COLUMNS])
        .render_derived(with_types=True)
    )
    strains = insert(_STRAINS).from_select(
        ["job_id", *[c.name for c in _STRAIN_COLUMNS]],
        select(done.c.id, *[record.c[c.name] for c in _STRAIN_COLUMNS]).select_from(done).join(record, true()),
    )
    return select(func.count()).select_from(done).add_cte(measures.cte("m"), strains.cte("s"), _outbox_cte(done))


_FINISH_RETURNING = _FINISH.returning(_JOBS.c.finished_at)
"""``_FINISH`` alone (not PostgreSQL), returning the ``finished_at`` it wrote: none when it stored nothing."""
_FINISH_ONE_STATEMENT = _finish_one_statement()
# Statements are built once and executed on Core tables with bound parameters: the worker's
# per-job cost stays in the database, not in statement construction.

Db = Session | Connection
"""Where the run functions execute: the worker's Core connection (``services.db.engine.
worker_connection``) or an ORM session (the reconciler, the tests)."""


def _dialect_name(db: Db) -> str:
    return db.dialect.name if isinstance(db, Connection) else db.get_bind().dialect.name


def claim_job(
    session: Db, job_id: uuid.UUID, engine_version: str | None, lease: timedelta = timedelta(seconds=10)
) -> Claim | None:
    """queued → running, attempts + 1, leased for ``lease`` from the database's clock
    (``services.db.clock``), ``started_at`` that clock too (the clock of ``created_at``); None when the
    job is not queued (duplicate, cancelled…) or not due yet: ``enqueued_at`` after the database's
    clock, a run handed back until then (``release_claim``; ``due_in_s`` says how long).

    One statement. The worker runs it on ``services.db.engine.worker_connection(settings,
    durable=False)``: on PostgreSQL that commits without waiting for the disk; if the server
    crashes and loses the claim, the job is simply queued again, and the run's final update,
    fenced on running and this attempt, stores nothing.
    """
    params = {"job_id": job_id, "engine_version": engine_version, "lease_s": lease.total_seconds()}
    row = session.execute(_CLAIM, params).first()
    session.commit()
    if row is None:
        return None
    return Claim(job_id, row.attempts, row.payload, row.created_at, row.callback_url, row.dicom)


def renew_leases(session: Db, claims: Sequence[Claim], lease: timedelta) -> list[Claim]:
    """Extend the lease of each claimed run to now + ``lease``, now read from the database's clock
    (``services.db.clock``); return the runs that still own their job (a run whose job was cancelled
    or taken back by the reconciler is not renewed)."""
    lease_s = lease.total_seconds()
    kept = []
    for claim in claims:
        done: CursorResult[Any] = session.execute(  # type: ignore[assignment]
            _RENEW, {"job_id": claim.job_id, "attempt": claim.attempt, "lease_s": lease_s}
        )
        if done.rowcount == 1:
            kept.append(claim)
    session.commit()
    return kept


def finish_job(
    session: Db,
    claim: Claim,
    *,
    result: RegistrationResult | None = None,
    error: dict[str, Any] | None = None,
    engine_version: str | None = None,
) -> bool:
    """running → succeeded (with ``result``) or failed (with ``error``, a problem), only for this run;
    ``finished_at`` is the database's clock (``services.db.clock``, the clock of ``started_at``).

    The job's row, its ``job_measures`` row, its ``vertebra_strains`` rows and, when it has a
    ``callback_url``, its webhook's outbox row (``deliveries.outbox_row``, due at the job's end on the
    database's clock, ``services.db.clock``) are
    written in one transaction: on PostgreSQL as one statement (one round trip), elsewhere as up to four.
    Returns False, storing nothing, when the job was cancelled or handed to another run meanwhile.
    """
    status = JobStatus.succeeded if error is None else JobStatus.failed
    params = {
        "job_id": claim.job_id,
        "attempt": claim.attempt,
        "status": status.value,
        "result": SerializedJSON(result.model_dump_json()) if result is not None else None,
        "error": error,
        "engine_version": engine_version,
    }
    measures = measures_row(result) if result is not None else None
    strains = strain_rows(result) if result is not None else []
    if _dialect_name(session) == "postgresql":
        # the strains' JSON written by pydantic-core (Rust): 30 µs, against 100-170 µs for json.dumps
        document = SerializedJSON(pydantic_core.to_json(strains).decode())
        webhook = _NO_OUTBOX if not claim.callback_url else {
            "with_webhook": True, "webhook_message_id": deliveries.message_id(claim.job_id, status.value),
            "webhook_event": f"job.{status.value}", "webhook_url": claim.callback_url,
        }  # fmt: skip
        values = {**params, **(measures or _NO_MEASURES), "with_measures": measures is not None, "strains": document}
        stored = session.execute(_FINISH_ONE_STATEMENT, {**values, **webhook}).scalar_one()
        session.commit()
        return bool(stored)
    finished_at = session.execute(_FINISH_RETURNING, params).scalar_one_or_none()
    if finished_at is None:
        session.rollback()
        return False
    if measures is not None:
        session.execute(_INSERT_MEASURES, {**measures, "job_id": claim.job_id})
    if strains:
        session.execute(_INSERT_STRAINS, [{**row, "job_id": claim.job_id} for row in strains])
    if claim.callback_url:  # the outbox row's attempted_at: the job's end as the job shows it
        session.execute(_INSERT_OUTBOX, deliveries.outbox_row(claim.job_id, status.value, claim.callback_url,
                                                              finished_at))  # fmt: skip
    session.commit()
    return True


@dataclass(frozen=True)
class Reconciliation:
    requeue: list[uuid.UUID]
    """Jobs to publish again: queued too long since last enqueued, or taken back from a lost run."""
    failed: list[uuid.UUID]
    """Jobs stranded in running after their last allowed attempt, now failed."""
    later: list[tuple[uuid.UUID, float]] = field(default_factory=list)
    """Queued jobs not due yet (runs handed back until later, ``release_claim``) whose messages a broker
    restart lost (``reconcile(not_due=True)``): each with the seconds (s) until it is due on the
    database's clock, the countdown to publish it with (``publish_later``)."""


def reconcile(
    session: Session,
    *,
    queued_timeout: timedelta,
    max_attempts: int,
    lost_problem: dict[str, Any],
    batch: int = 1000,
    republish_queued: int | None = None,
    not_due: bool = False,
) -> Reconciliation:
    """Find jobs a lost message or a dead worker stranded, and hand them back or fail them.

    A running job is stranded when its lease expired (its worker stopped renewing it:
    ``lease_expires_at`` before the database's clock, ``services.db.clock``, as every lease is
    written; every claim sets a lease). A queued job is stranded when it was last enqueued
    (``enqueued_at``, written and compared on the database's clock too; for a released run, when it is
    due again: ``release_claim``) more than ``queued_timeout`` ago or is marked unpublished; with
    ``republish_queued`` set, only that many of the oldest such jobs are taken (the broker is
    missing about that many messages), and ``queued_timeout`` zero takes every queued job that is due
    (the broker lost its messages). With ``not_due`` (the broker lost its messages too), the queued jobs
    not due yet are listed in ``later`` with the seconds until they are due, their ``enqueued_at`` (the
    due time) untouched: their messages, held until their ETA, are gone, and the queued timeout would
    publish them again only that long after they are due.
    """
    requeue: list[uuid.UUID] = []
    failed: list[uuid.UUID] = []
    stale_running = session.execute(
        select(Job.id, Job.attempts, Job.callback_url)
        .where(Job.status == JobStatus.running.value, Job.lease_expires_at < db_now())
        .limit(batch)
    ).all()
    for job_id, attempts, callback_url in stale_running:
        guard = (Job.id == job_id, Job.status == JobStatus.running.value, Job.attempts == attempts)
        if attempts >= max_attempts:  # finished_at on the database's clock, as the run's started_at
            finished_at = session.scalar(
                update(Job)
                .where(*guard)
                .values(status=JobStatus.failed.value, finished_at=db_now(), error=lost_problem, lease_expires_at=None)
                .returning(Job.finished_at)
            )
            if finished_at is not None:
                failed.append(job_id)
                if callback_url:  # the webhook's outbox row, committed with the failure
                    deliveries.record_due(session, job_id, JobStatus.failed.value, callback_url, finished_at)
        else:
            back: CursorResult[Any] = session.execute(  # type: ignore[assignment]
                update(Job)
                .where(*guard)
                .values(status=JobStatus.queued.value, enqueued_at=db_now(), lease_expires_at=None)
            )
            if back.rowcount == 1:
                requeue.append(job_id)
    # Queued too long since last enqueued, or known to have no message (``mark_unpublished``).
    stale = or_(Job.enqueued_at <= db_now_plus_s(-queued_timeout.total_seconds()), Job.enqueued_at.is_(None))
    limit = batch if republish_queued is None else max(0, min(batch, republish_queued))
    unpublished = list(
        session.scalars(
            select(Job.id).where(Job.status == JobStatus.queued.value, Job.enqueued_at.is_(None)).limit(batch)
        )
    )
    oldest = select(Job.id).where(Job.status == JobStatus.queued.value, stale)
    stale_queued = list(
        dict.fromkeys(
            unpublished + list(session.scalars(oldest.order_by(Job.enqueued_at, Job.id).limit(limit)))
        )
    )
    if stale_queued:
        touched = session.scalars(
            update(Job)
            .where(Job.id.in_(stale_queued), Job.status == JobStatus.queued.value, stale)
            .values(enqueued_at=db_now())
            .returning(Job.id)
        ).all()
        requeue.extend(touched)
    later: list[tuple[uuid.UUID, float]] = []
    if not_due:
        waiting = select(Job.id, Job.enqueued_at, db_now()).where(
            Job.status == JobStatus.queued.value, Job.enqueued_at > db_now()
        )
        later = [(job_id, seconds_until(due, now)) for job_id, due, now in session.execute(waiting.limit(batch))]
    session.commit()
    return Reconciliation(requeue, failed, later)


def mark_unpublished(session: Session, job_ids: Sequence[uuid.UUID]) -> None:
    """Mark queued jobs whose message could not be published (``enqueued_at`` NULL), so that the
    reconciler's next pass publishes them instead of waiting ``SPINE_QUEUED_TIMEOUT_S``."""
    if job_ids:
        session.execute(
            update(Job)
            .where(Job.id.in_(list(job_ids)), Job.status == JobStatus.queued.value)
            .values(enqueued_at=None)
        )
        session.commit()


log = logging.getLogger(__name__)


def publish(session: Session, app: Celery, job_ids: Sequence[uuid.UUID]) -> int:
    """``enqueue`` the jobs; mark those whose message could not be published, so that the
    reconciler's next pass (every ``SPINE_RECONCILE_INTERVAL_S``) publishes them. Never raises."""
    sent = enqueue(app, job_ids)
    if sent < len(job_ids):
        try:
            mark_unpublished(session, job_ids[sent:])
        except Exception as exc:  # the database too: the queued timeout still catches them
            log.warning("could not mark %d unpublished jobs: %s", len(job_ids) - sent, exc)
    return sent


def publish_later(app: Celery, later: Sequence[tuple[uuid.UUID, float]]) -> int:
    """``enqueue`` each job with its countdown (s): jobs not due yet whose messages were lost
    (``Reconciliation.later``). A message that comes before its job is due on the database's clock (its
    ETA is on this process's clock) is published again for the time left by the worker. Those that
    cannot be published are not marked (a job marked unpublished could be claimed before it is due): the
    queued timeout past their due time, or the next broker restart, publishes them. Never raises; returns
    how many were published."""
    return enqueue(app, [job_id for job_id, _ in later], [countdown for _, countdown in later])


def release_claim(session: Db, claim: Claim, delay_s: float) -> bool:
    """running → queued for this run (fenced by attempt), to run again ``delay_s`` (s) later: a dependency
    of the run (the PACS) was unavailable. The attempt stays counted, so ``SPINE_MAX_ATTEMPTS`` bounds
    the tries.

    ``enqueued_at`` = the database's now + ``delay_s`` (``services.db.clock``): when the job is due again.
    Until then ``claim_job`` does not take it (a message that came early, its ETA on another host's
    clock, is published again for ``due_in_s``), and the reconciler's queued timeout counts from then:
    the message waits in a worker until its ETA, not in the broker, so the job counts as missing a
    message, and is published again only once ``enqueued_at + SPINE_QUEUED_TIMEOUT_S`` is past. A broker
    restart, which loses that message (the worker drops the messages it holds when its connection is
    lost), has it published again at once with the time left (``reconcile(not_due=True)``)."""
    done: CursorResult[Any] = session.execute(  # type: ignore[assignment]
        update(Job)
        .where(Job.id == claim.job_id, Job.status == JobStatus.running.value, Job.attempts == claim.attempt)
        .values(
            status=JobStatus.queued.value, enqueued_at=db_now_plus_s(delay_s), lease_expires_at=None, started_at=None
        )
    )
    session.commit()
    return done.rowcount == 1


def due_in_s(session: Db, job_id: uuid.UUID) -> float | None:
    """Seconds until the queued job is due on the database's clock: its ``enqueued_at`` (a released run's
    due time, ``release_claim``) minus the database's now, read in one statement; 0 when it is due (or
    marked unpublished), None when the job is not queued (or not there)."""
    row = session.execute(select(Job.status, Job.enqueued_at, db_now()).where(Job.id == job_id)).first()
    if row is None or row.status != JobStatus.queued.value:
        return None
    return seconds_until(row[1], row[2])


def record_dicom(session: Db, claim: Claim, provenance: dict[str, Any], study: dict[str, Any]) -> bool:
    """Store what the DICOM layer read for this run (``jobs.dicom``) and the study's identifiers it
    completed (the list filters' columns), fenced by attempt."""
    values: dict[str, Any] = {"dicom": provenance}
    columns = study_column_values(study)  # without their padding, as the payload's are stored
    values.update({name: value for name, value in columns.items() if isinstance(study.get(name), str)})
    done: CursorResult[Any] = session.execute(  # type: ignore[assignment]
        update(Job)
        .where(Job.id == claim.job_id, Job.status == JobStatus.running.value, Job.attempts == claim.attempt)
        .values(**values)
    )
    session.commit()
    return done.rowcount == 1
