"""The job repository: every read and state change of a job, as conditional SQL statements.

State changes are guarded by the expected current state (``WHERE status = ...``), so a message
delivered twice, a cancel racing a fit, or a reconciler racing a slow worker never gives a job
two outcomes. A run is fenced by its attempt number: a worker can only finish the run it claimed.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import json
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any, cast

from sqlalchemy import (
    Boolean,
    CursorResult,
    Table,
    and_,
    bindparam,
    column,
    func,
    insert,
    or_,
    select,
    true,
    update,
)
from sqlalchemy.dialects.postgresql import JSONB
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from services.db.models import FINAL_STATUSES, Job, JobMeasures, JobStatus, VertebraStrain, utcnow

FINISHED = [s.value for s in FINAL_STATUSES]

InsertHook = Callable[[Session, list[uuid.UUID]], None]
"""Called with the ids of jobs just inserted, in their transaction (the API's audit rows)."""


class IdempotencyConflict(Exception):
    """The Idempotency-Key was already used with a different body."""

    def __init__(self, job_id: uuid.UUID):
        self.job_id = job_id
        super().__init__(str(job_id))


class JobNotFound(Exception):
    pass


class JobFinished(Exception):
    """The job has already reached succeeded or failed."""

    def __init__(self, job: Job):
        self.job = job
        super().__init__(job.status)


class BadCursor(ValueError):
    pass


def request_hash(payload: Any) -> str:
    """A digest of a JSON body, independent of key order and whitespace."""
    canonical = json.dumps(payload, sort_keys=True, separators=(",", ":"), ensure_ascii=False)
    return hashlib.sha256(canonical.encode()).hexdigest()


def _new_job(payload: dict[str, Any], owner: str | None, now: datetime, **extra: Any) -> dict[str, Any]:
    return {
        "id": uuid.uuid4(),
        "owner": owner,
        "status": JobStatus.queued.value,
        "created_at": now,
        "enqueued_at": now,
        "attempts": 0,
        "payload": payload,
        **extra,
    }


def create_job(
    session: Session,
    payload: dict[str, Any],
    *,
    owner: str | None = None,
    idempotency_key: str | None = None,
    on_insert: InsertHook | None = None,
) -> tuple[Job, bool]:
    """Store a queued job; return it and whether it is new (False: an idempotent replay).

    Raises ``IdempotencyConflict`` when ``idempotency_key`` was used by this owner with another body.
    ``on_insert(session, [job id])`` runs in the inserting transaction (the API's audit row).
    """
    digest = request_hash(payload) if idempotency_key is not None else None
    if idempotency_key is not None:
        existing = _by_idempotency_key(session, owner, idempotency_key)
        if existing is not None:
            return _replay(existing, digest)
    values = _new_job(payload, owner, utcnow(), idempotency_key=idempotency_key, request_hash=digest)
    try:
        session.execute(insert(Job), [values])  # Core insert: the hot path skips the unit of work
        if on_insert is not None:
            on_insert(session, [values["id"]])
        session.commit()
    except IntegrityError:
        session.rollback()
        if idempotency_key is None:
            raise
        existing = _by_idempotency_key(session, owner, idempotency_key)
        if existing is None:
            raise
        return _replay(existing, digest)
    return _detached(values), True


def _detached(values: dict[str, Any]) -> Job:
    """A Job object holding what was just inserted (no read back)."""
    row = {"started_at": None, "finished_at": None, "result": None, "error": None, "engine_version": None,
           "idempotency_key": None, "request_hash": None, **values}  # fmt: skip
    return Job(**row)


def _by_idempotency_key(session: Session, owner: str | None, key: str) -> Job | None:
    owner_match = Job.owner.is_(None) if owner is None else Job.owner == owner
    return session.scalars(select(Job).where(owner_match, Job.idempotency_key == key)).first()


def _replay(existing: Job, digest: str | None) -> tuple[Job, bool]:
    if existing.request_hash != digest:
        raise IdempotencyConflict(existing.id)
    return existing, False


def create_jobs(
    session: Session,
    payloads: Sequence[dict[str, Any]],
    *,
    owner: str | None = None,
    on_insert: InsertHook | None = None,
) -> list[Job]:
    """Store many queued jobs in one transaction (the batch endpoint)."""
    now = utcnow()
    rows = [_new_job(p, owner, now) for p in payloads]
    session.execute(insert(Job), rows)
    if on_insert is not None:
        on_insert(session, [row["id"] for row in rows])
    session.commit()
    return [_detached(row) for row in rows]


def get_job(session: Session, job_id: uuid.UUID, *, owner: str | None = None) -> Job:
    job = session.get(Job, job_id)
    if job is None or (owner is not None and job.owner != owner):
        raise JobNotFound(str(job_id))
    return job


def encode_cursor(job: Job) -> str:
    raw = f"{job.created_at.isoformat()}|{job.id}"
    return base64.urlsafe_b64encode(raw.encode()).decode().rstrip("=")


def decode_cursor(cursor: str) -> tuple[datetime, uuid.UUID]:
    try:
        raw = base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4)).decode()
        created, job_id = raw.split("|")
        when = datetime.fromisoformat(created)
        if when.tzinfo is None:
            raise ValueError("naive")
        return when, uuid.UUID(job_id)
    except (binascii.Error, UnicodeDecodeError, ValueError) as exc:
        raise BadCursor("the cursor is not one this API returned") from exc


def list_jobs(
    session: Session,
    *,
    statuses: Sequence[str] = (),
    created_after: datetime | None = None,
    created_before: datetime | None = None,
    cursor: str | None = None,
    limit: int = 50,
    owner: str | None = None,
) -> tuple[list[Job], str | None]:
    """Jobs newest first (created_at, then id, descending) and the cursor of the next page."""
    query = select(Job)
    if statuses:
        query = query.where(Job.status.in_(list(statuses)))
    if owner is not None:
        query = query.where(Job.owner == owner)
    if created_after is not None:
        query = query.where(Job.created_at >= created_after)
    if created_before is not None:
        query = query.where(Job.created_at < created_before)
    if cursor is not None:
        at, job_id = decode_cursor(cursor)
        query = query.where(or_(Job.created_at < at, and_(Job.created_at == at, Job.id < job_id)))
    query = query.order_by(Job.created_at.desc(), Job.id.desc()).limit(limit + 1)
    jobs = list(session.scalars(query))
    next_cursor = encode_cursor(jobs[limit - 1]) if len(jobs) > limit else None
    return jobs[:limit], next_cursor


def cancel_job(session: Session, job_id: uuid.UUID, *, owner: str | None = None) -> tuple[Job, bool]:
    """Move a queued or running job to cancelled; return it and whether this call cancelled it
    (False: it already was, and is returned as it is).

    Raises ``JobNotFound``, or ``JobFinished`` when it already succeeded or failed.
    """
    get_job(session, job_id, owner=owner)
    outcome: CursorResult[Any] = session.execute(  # type: ignore[assignment]
        update(Job)
        .where(Job.id == job_id, Job.status.in_([JobStatus.queued.value, JobStatus.running.value]))
        .values(status=JobStatus.cancelled.value, finished_at=utcnow())
    )
    session.commit()
    job = get_job(session, job_id, owner=owner)
    session.refresh(job)
    if job.status in (JobStatus.succeeded.value, JobStatus.failed.value):
        raise JobFinished(job)
    return job, outcome.rowcount == 1


# ------------------------------------------------------------------ worker side


@dataclass(frozen=True)
class Claim:
    """A run of a job that this worker owns: fenced by the attempt number."""

    job_id: uuid.UUID
    attempt: int
    payload: dict[str, Any]
    created_at: datetime


_JOBS = cast(Table, Job.__table__)
_CLAIM = (
    update(_JOBS)
    .where(_JOBS.c.id == bindparam("job_id"), _JOBS.c.status == JobStatus.queued.value)
    .values(
        status=JobStatus.running.value,
        started_at=bindparam("now"),
        attempts=_JOBS.c.attempts + 1,
        engine_version=bindparam("engine_version"),
    )
    .returning(_JOBS.c.attempts, _JOBS.c.payload, _JOBS.c.created_at)
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
        finished_at=bindparam("now"),
        result=bindparam("result"),
        error=bindparam("error"),
        engine_version=func.coalesce(bindparam("engine_version"), _JOBS.c.engine_version),
    )
)
_MEASURES = cast(Table, JobMeasures.__table__)
_STRAINS = cast(Table, VertebraStrain.__table__)
_INSERT_MEASURES = insert(_MEASURES)
_INSERT_STRAINS = insert(_STRAINS)
_MEASURE_COLUMNS = [c for c in _MEASURES.c if c.name != "job_id"]
_STRAIN_COLUMNS = [c for c in _STRAINS.c if c.name != "job_id"]
_NO_MEASURES = {c.name: None for c in _MEASURE_COLUMNS}


def _finish_one_statement() -> Any:
    """PostgreSQL: ``_FINISH`` and both measure inserts as one statement with data-modifying CTEs.

    ``WITH done AS (UPDATE jobs … RETURNING id), m AS (INSERT INTO job_measures SELECT … FROM done
    WHERE :with_measures), s AS (INSERT INTO vertebra_strains SELECT done.id, r.* FROM done,
    jsonb_to_recordset(:strains) AS r(level text, u1 float8, …)) SELECT count(*) FROM done``:
    nothing is inserted when the fenced update matched no row, and all of it commits together.
    """
    done = _FINISH.returning(_JOBS.c.id).cte("done")
    measures = insert(_MEASURES).from_select(
        ["job_id", *[c.name for c in _MEASURE_COLUMNS]],
        select(done.c.id, *[bindparam(c.name, type_=c.type) for c in _MEASURE_COLUMNS]).where(
            bindparam("with_measures", type_=Boolean())
        ),
    )
    record = (
        func.jsonb_to_recordset(bindparam("strains", type_=JSONB()))
        .table_valued(*[column(c.name, c.type) for c in _STRAIN_COLUMNS])
        .render_derived(with_types=True)
    )
    strains = insert(_STRAINS).from_select(
        ["job_id", *[c.name for c in _STRAIN_COLUMNS]],
        select(done.c.id, *[record.c[c.name] for c in _STRAIN_COLUMNS]).select_from(done).join(record, true()),
    )
    return select(func.count()).select_from(done).add_cte(measures.cte("m"), strains.cte("s"))


_FINISH_ONE_STATEMENT = _finish_one_statement()
# Statements are built once and executed on Core tables with bound parameters: the worker's
# per-job cost stays in the database, not in statement construction.


def claim_job(session: Session, job_id: uuid.UUID, engine_version: str | None) -> Claim | None:
    """queued → running, attempts + 1; None when the job is not queued (duplicate, cancelled…).

    One statement. The worker runs it on a session of ``services.db.engine.worker_session(settings,
    durable=False)``: on PostgreSQL that commits without waiting for the disk; if the server
    crashes and loses the claim, the job is simply queued again, and the run's final update,
    fenced on running and this attempt, stores nothing.
    """
    row = session.execute(_CLAIM, {"job_id": job_id, "now": utcnow(), "engine_version": engine_version}).first()
    session.commit()
    if row is None:
        return None
    return Claim(job_id, row.attempts, row.payload, row.created_at)


def finish_job(
    session: Session,
    claim: Claim,
    *,
    result: dict[str, Any] | None = None,
    error: dict[str, Any] | None = None,
    engine_version: str | None = None,
) -> bool:
    """running → succeeded (with ``result``) or failed (with ``error``), only for this run.

    The job's row, its ``job_measures`` row and its ``vertebra_strains`` rows are written in one
    transaction: on PostgreSQL as one statement (one round trip), elsewhere as three.
    Returns False, storing nothing, when the job was cancelled or handed to another run meanwhile.
    """
    status = JobStatus.succeeded if error is None else JobStatus.failed
    params = {
        "job_id": claim.job_id,
        "attempt": claim.attempt,
        "status": status.value,
        "now": utcnow(),
        "result": result,
        "error": error,
        "engine_version": engine_version,
    }
    measures = _measures_row(result) if result is not None else None
    strains = _strain_rows(result) if result is not None else []
    if session.get_bind().dialect.name == "postgresql":
        stored = session.execute(
            _FINISH_ONE_STATEMENT,
            {**params, **(measures or _NO_MEASURES), "with_measures": measures is not None, "strains": strains},
        ).scalar_one()
        session.commit()
        return bool(stored)
    outcome: CursorResult[Any] = session.execute(_FINISH, params)  # type: ignore[assignment]
    if outcome.rowcount != 1:
        session.rollback()
        return False
    if measures is not None:
        session.execute(_INSERT_MEASURES, {**measures, "job_id": claim.job_id})
    if strains:
        session.execute(_INSERT_STRAINS, [{**row, "job_id": claim.job_id} for row in strains])
    session.commit()
    return True


def _measures_row(result: dict[str, Any]) -> dict[str, Any]:
    """The ``job_measures`` columns of a result (the major curve, kyphosis, lordosis, fit)."""
    measures = result.get("measures") or {}
    curves = measures.get("cobb") or []
    major = next((c for c in curves if c.get("major")), None) or {}
    fit = result.get("fit") or {}
    return {
        "major_cobb_deg": major.get("angle_deg"),
        "major_curve_upper": major.get("upper"),
        "major_curve_lower": major.get("lower"),
        "major_curve_apex": major.get("apex"),
        "major_convexity": major.get("convexity"),
        "major_apex_axial_rotation_deg": major.get("apex_axial_rotation_deg"),
        "major_plane_of_max_curvature_deg": major.get("plane_of_max_curvature_deg"),
        "curve_count": len(curves),
        "thoracic_kyphosis_t4_t12_deg": measures["thoracic_kyphosis_t4_t12_deg"],
        "thoracic_kyphosis_t5_t12_deg": measures["thoracic_kyphosis_t5_t12_deg"],
        "lumbar_lordosis_l1_l5_deg": measures["lumbar_lordosis_l1_l5_deg"],
        "mean_registration_error_mm": fit["mean_registration_error_mm"],
        "converged": bool(fit["converged"]),
    }


def _strain_rows(result: dict[str, Any]) -> list[dict[str, Any]]:
    """The ``vertebra_strains`` rows of a result, one per vertebra (without the job id)."""
    rows = []
    for v in result.get("vertebrae") or []:
        u = v.get("u") or (None, None, None)
        s = v.get("v") or (None, None, None)
        rows.append(
            {
                "level": v["level"],
                "u1": u[0], "u2": u[1], "u3": u[2],
                "v1": s[0], "v2": s[1], "v3": s[2],
                "pa_bending_deg": v.get("pa_bending_deg"),
                "lateral_bending_deg": v.get("lateral_bending_deg"),
                "twist_deg": v.get("twist_deg"),
                "axial_rotation_deg": v["axial_rotation_deg"],
            }
        )  # fmt: skip
    return rows


@dataclass(frozen=True)
class Reconciliation:
    requeue: list[uuid.UUID]
    """Jobs to publish again: queued too long since last enqueued, or taken back from a lost run."""
    failed: list[uuid.UUID]
    """Jobs stranded in running after their last allowed attempt, now failed."""


def reconcile(
    session: Session,
    *,
    queued_timeout: timedelta,
    running_timeout: timedelta,
    max_attempts: int,
    lost_problem: dict[str, Any],
    batch: int = 1000,
) -> Reconciliation:
    """Find jobs a lost message or a dead worker stranded, and hand them back or fail them."""
    now = utcnow()
    requeue: list[uuid.UUID] = []
    failed: list[uuid.UUID] = []
    stale_running = session.execute(
        select(Job.id, Job.attempts)
        .where(Job.status == JobStatus.running.value, Job.started_at < now - running_timeout)
        .limit(batch)
    ).all()
    for job_id, attempts in stale_running:
        guard = (Job.id == job_id, Job.status == JobStatus.running.value, Job.attempts == attempts)
        if attempts >= max_attempts:
            done: CursorResult[Any] = session.execute(  # type: ignore[assignment]
                update(Job).where(*guard).values(status=JobStatus.failed.value, finished_at=now, error=lost_problem)
            )
            if done.rowcount == 1:
                failed.append(job_id)
        else:
            back: CursorResult[Any] = session.execute(  # type: ignore[assignment]
                update(Job).where(*guard).values(status=JobStatus.queued.value, enqueued_at=now)
            )
            if back.rowcount == 1:
                requeue.append(job_id)
    # Queued too long since last enqueued, or known to have no message (``mark_unpublished``).
    stale = or_(Job.enqueued_at < now - queued_timeout, Job.enqueued_at.is_(None))
    stale_queued = list(
        session.scalars(select(Job.id).where(Job.status == JobStatus.queued.value, stale).limit(batch))
    )
    if stale_queued:
        touched = session.scalars(
            update(Job)
            .where(Job.id.in_(stale_queued), Job.status == JobStatus.queued.value, stale)
            .values(enqueued_at=now)
            .returning(Job.id)
        ).all()
        requeue.extend(touched)
    session.commit()
    return Reconciliation(requeue, failed)


# ------------------------------------------------------------------ metrics


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


def count_by_status(session: Session) -> dict[str, int]:
    counts = {s.value: 0 for s in JobStatus}
    for status, n in session.execute(select(Job.status, func.count()).group_by(Job.status)):
        counts[status] = n
    return counts


def recent_durations(session: Session, since: datetime, limit: int = 20_000) -> list[tuple[float, float]]:
    """(fit seconds, end-to-end seconds) of jobs that succeeded or failed since ``since``."""
    rows = session.execute(
        select(Job.created_at, Job.started_at, Job.finished_at)
        .where(
            Job.finished_at >= since,
            Job.status.in_([JobStatus.succeeded.value, JobStatus.failed.value]),
            Job.started_at.is_not(None),
        )
        .order_by(Job.finished_at.desc())
        .limit(limit)
    ).all()
    return [
        ((finished - started).total_seconds(), (finished - created).total_seconds())
        for created, started, finished in rows
        if started is not None and finished is not None
    ]
