"""``POST /v1/jobs/batch`` with an ``Idempotency-Key``: a retried batch never makes two jobs.

The write is ``services.db.jobs.create_jobs_idempotent`` (payload ``i`` under ``K#i``, apart from the
keys of single submissions); an entry whose body differs from the one first sent under ``K#i`` gets an
``idempotency-conflict`` problem.
"""

from __future__ import annotations

import uuid
from typing import Any

from sqlalchemy.orm import Session

from services.api.schemas import BatchEntry, BatchResponse, Job, Problem
from services.core.problems import problem
from services.db import jobs as jobs_repo
from services.db.jobs import AdmitHook, InsertHook, create_jobs_idempotent
from services.db.runs import publish


def batch_response(
    session: Session,
    queue: Any,
    *,
    owner: str | None,
    client: str,
    key: str,
    total: int,
    valid: list[tuple[int, dict[str, Any]]],
    entries: list[BatchEntry | None],
    on_insert: InsertHook | None = None,
    admit: AdmitHook | None = None,
) -> tuple[BatchResponse, bool]:
    """The answer of a batch sent with an Idempotency-Key (``entries`` holds the rejected ones), and
    whether it only replayed jobs (then the answer carries ``Idempotent-Replayed: true``).

    ``client``: whose key it is (the API key's name, an admin's too). ``admit(n)`` gets the number of new
    jobs before they are inserted (the cap; replays are not counted); ``on_insert(session, ids)`` runs in
    the inserting transaction.
    """
    outcomes = create_jobs_idempotent(session, valid, owner=owner, client=client, key=key, on_insert=on_insert,
                                      admit=admit) if valid else []  # fmt: skip
    created: list[uuid.UUID] = []
    replayed = 0
    for (i, _), outcome in zip(valid, outcomes, strict=True):
        if isinstance(outcome, jobs_repo.IdempotencyConflict):
            detail = (f"entry {i} of a batch sent with the Idempotency-Key {key!r} made job {outcome.job_id} "
                      "with another body")  # fmt: skip
            p = problem("idempotency-conflict", detail, instance="/v1/jobs/batch", job=f"/v1/jobs/{outcome.job_id}")
            entries[i] = BatchEntry(index=i, status=p["status"], problem=Problem.model_validate(p))
            continue
        job, new = outcome
        if new:
            created.append(job.id)
        else:
            replayed += 1
        entries[i] = BatchEntry(index=i, status=202, job=Job.summary(job))
    publish(session, queue, created)
    accepted = sum(1 for e in entries if e is not None and e.status == 202)
    answer = BatchResponse(accepted=accepted, rejected=total - accepted, results=entries)
    return answer, bool(replayed and not created)
