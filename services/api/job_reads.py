"""Reading one job as its owner (or an admin) does: the lookup, the 404, the audit row, the 409."""

from __future__ import annotations

import uuid
from typing import Any

from sqlalchemy.orm import Session

from services.api.access import Access
from services.api.errors import ProblemError
from services.core.problems import problem
from services.db import jobs as jobs_repo
from services.db.models import Job


def not_found(job_id: uuid.UUID) -> ProblemError:
    """The 404 problem of an unknown job, and of another client's job (the same body)."""
    return ProblemError(problem("not-found", f"there is no job {job_id}"))


def read_job(session: Session, job_id: uuid.UUID, access: Access) -> Job:
    """The job the caller may see (an admin sees all), audited as a read; else a 404 problem."""
    try:
        job = jobs_repo.get_job(session, job_id, owner=access.owner)
    except jobs_repo.JobNotFound:
        raise not_found(job_id) from None
    access.record(session, "read", [job.id])
    return job


def read_succeeded_job(session: Session, job_id: uuid.UUID, access: Access, product: str) -> tuple[Job, dict[str, Any]]:
    """``read_job`` and its result, or a 409 ``job-has-no-result`` problem unless the job succeeded;
    ``product`` names what the caller derives from the result (e.g. "figure"), for the detail."""
    job = read_job(session, job_id, access)
    if job.status == "succeeded" and job.result is not None:
        return job, job.result
    if job.status in ("queued", "running"):
        detail = f"job {job_id} is {job.status}; its {product} exists once it has succeeded"
    else:
        detail = f"job {job_id} {'was cancelled' if job.status == 'cancelled' else job.status} and has no result"
    raise ProblemError(problem("job-has-no-result", detail, job_status=str(job.status), job=f"/v1/jobs/{job_id}"))
