"""``POST /v1/jobs/batch`` with an ``Idempotency-Key``: a retried batch never makes two jobs.

The store is ``services.db.jobs.create_jobs_idempotent`` (payload ``i`` under ``K#i``); an entry
whose body differs from the one first sent under ``K#i`` gets an ``idempotency-conflict`` problem.
"""

from __future__ import annotations

import uuid
from collections.abc import Callable
from typing import Any

from fastapi.responses import JSONResponse
from sqlalchemy.orm import Session

from services.core.problems import problem
from services.db import jobs as jobs_repo
from services.db.jobs import InsertHook, create_jobs_idempotent, entry_key, job_json
from services.db.runs import publish


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
