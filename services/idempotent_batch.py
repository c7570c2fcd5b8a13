"""``POST /v1/jobs/batch`` with an ``Idempotency-Key``: a retried batch never makes two jobs.

Payload ``i`` of a batch sent with key ``K`` is stored under the job key ``K#i`` (per owner, the
same unique index as single submissions), so the same key and body return the same jobs; an entry
whose body differs from the one first sent under ``K#i`` gets an ``idempotency-conflict`` problem.
"""

from __future__ import annotations

import uuid
from collections.abc import Callable, Sequence
from typing import Any

from sqlalchemy import insert, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from services.db import jobs as jobs_repo
from services.db.models import Job, JobStatus, utcnow

MAX_BATCH_KEY_LENGTH = 240
"""Longest Idempotency-Key of a batch: ``#<index>`` is appended per job (the column holds 255)."""


def entry_key(key: str, index: int) -> str:
    return f"{key}#{index}"


InsertHook = Callable[[Session, list[uuid.UUID]], None]
"""Called with the ids of jobs just inserted, in their transaction (e.g. the API's audit rows)."""

Outcome = tuple[Job, bool] | jobs_repo.IdempotencyConflict
"""Per payload: (job, created) or the conflict with the job first stored under its key."""


def create_jobs_idempotent(
    session: Session,
    payloads: Sequence[tuple[int, dict[str, Any]]],
    *,
    owner: str | None,
    key: str,
    on_insert: InsertHook | None = None,
) -> list[Outcome]:
    """Store the (index, payload) pairs under ``key#index``; replay those already stored."""
    keys = [entry_key(key, i) for i, _ in payloads]
    owner_match = Job.owner.is_(None) if owner is None else Job.owner == owner
    stored = session.scalars(select(Job).where(owner_match, Job.idempotency_key.in_(keys)))
    existing = {j.idempotency_key: j for j in stored}
    now = utcnow()
    outcomes: list[Outcome | None] = []
    rows: list[dict[str, Any]] = []
    slots: list[int] = []
    for (_, payload), job_key in zip(payloads, keys, strict=True):
        digest = jobs_repo.request_hash(payload)
        found = existing.get(job_key)
        if found is not None:
            outcomes.append((found, False) if found.request_hash == digest else jobs_repo.IdempotencyConflict(found.id))
            continue
        slots.append(len(outcomes))
        outcomes.append(None)
        rows.append({"id": uuid.uuid4(), "owner": owner, "status": JobStatus.queued.value, "created_at": now,
                     "enqueued_at": now, "attempts": 0, "payload": payload, "idempotency_key": job_key,
                     "request_hash": digest})  # fmt: skip
    if rows:
        try:
            session.execute(insert(Job), rows)
            if on_insert is not None:
                on_insert(session, [row["id"] for row in rows])
            session.commit()
            for slot, row in zip(slots, rows, strict=True):
                outcomes[slot] = (_job(row), True)
        except IntegrityError:  # a concurrent retry stored some of them first: one at a time
            session.rollback()
            for slot, row in zip(slots, rows, strict=True):
                try:
                    outcomes[slot] = _create_one(session, row, owner, on_insert)
                except jobs_repo.IdempotencyConflict as exc:
                    outcomes[slot] = exc
    return [o for o in outcomes if o is not None]


def _create_one(session: Session, row: dict[str, Any], owner: str | None, on_insert: InsertHook | None) -> Outcome:
    if on_insert is None:
        return jobs_repo.create_job(session, row["payload"], owner=owner, idempotency_key=row["idempotency_key"])
    return jobs_repo.create_job(session, row["payload"], owner=owner, idempotency_key=row["idempotency_key"],
                                on_insert=on_insert)  # type: ignore[call-arg, unused-ignore]  # fmt: skip


def _job(row: dict[str, Any]) -> Job:
    return Job(**{"started_at": None, "finished_at": None, "result": None, "error": None, "engine_version": None,
                  **row})  # fmt: skip


def batch_response(
    session: Session,
    queue: Any,
    *,
    owner: str | None,
    key: str,
    total: int,
    valid: list[tuple[int, dict[str, Any]]],
    entries: list[dict[str, Any] | None],
    on_insert: InsertHook | None = None,
    on_accepted: Callable[[int], None] | None = None,
) -> Any:
    """The answer of a batch sent with an Idempotency-Key (``entries`` holds the rejected ones).

    ``on_insert(session, ids)`` runs in the inserting transaction; ``on_accepted(n)`` gets the number of
    jobs made (replays are not counted).
    """
    from fastapi.responses import JSONResponse

    from services.api.schemas import job_json
    from services.jobqueue import publish
    from services.problems import problem

    outcomes = create_jobs_idempotent(session, valid, owner=owner, key=key, on_insert=on_insert) if valid else []
    created: list[uuid.UUID] = []
    replayed = 0
    for (i, _), outcome in zip(valid, outcomes, strict=True):
        if isinstance(outcome, jobs_repo.IdempotencyConflict):
            detail = f"the Idempotency-Key {entry_key(key, i)!r} was used for job {outcome.job_id} with another body"
            p = problem("idempotency-conflict", detail, instance="/v1/jobs/batch", job=f"/v1/jobs/{outcome.job_id}")
            entries[i] = {"index": i, "status": p["status"], "problem": p}
            continue
        job, new = outcome
        if new:
            created.append(job.id)
        else:
            replayed += 1
        entries[i] = {"index": i, "status": 202, "job": job_json(job)}
    if on_accepted is not None:
        on_accepted(len(created))
    publish(session, queue, created)
    accepted = sum(1 for e in entries if e is not None and e["status"] == 202)
    headers = {"Idempotent-Replayed": "true"} if replayed and not created else None
    return JSONResponse({"accepted": accepted, "rejected": total - accepted, "results": entries}, headers=headers)
