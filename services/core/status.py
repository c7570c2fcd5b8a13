"""The job status: the one enum of the service (DESIGN.md, "Job life cycle").

``queued → running → succeeded | failed``, and ``cancelled`` from ``queued`` or ``running``.
The database's check constraint, the API's ``Job.status`` and openapi.yaml are made from it.
"""

from __future__ import annotations

import enum


class JobStatus(enum.StrEnum):
    queued = "queued"
    running = "running"
    succeeded = "succeeded"
    failed = "failed"
    cancelled = "cancelled"


FINAL_STATUSES = frozenset({JobStatus.succeeded, JobStatus.failed, JobStatus.cancelled})
"""States a job never leaves."""
