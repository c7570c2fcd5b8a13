"""Typed views of what the service answers. The result reuses ``spine_engine.models``.

Models accept members they do not know (``extra="allow"``), so a newer service does not break an
older client.
"""

from __future__ import annotations

import uuid
from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from spine_engine.models import RegistrationResult, Study

JobStatus = Literal["queued", "running", "succeeded", "failed", "cancelled"]
FINAL_STATUSES: frozenset[str] = frozenset({"succeeded", "failed", "cancelled"})


class _Open(BaseModel):
    model_config = ConfigDict(extra="allow")


class FieldProblem(_Open):
    path: str = ""
    loc: list[str | int] = Field(default_factory=list)
    msg: str = ""
    type: str = ""


class Problem(_Open):
    """RFC 9457 problem details."""

    type: str = "about:blank"
    title: str = ""
    status: int | None = None
    detail: str = ""
    instance: str | None = None
    errors: list[FieldProblem] | None = None


class WebhookDelivery(_Open):
    event: str
    message_id: str
    attempt: int
    url: str
    attempted_at: datetime
    status_code: int | None = None
    error: str | None = None
    duration_ms: float | None = None
    next_attempt_at: datetime | None = None


class Job(_Open):
    """A job and, once finished, its result or error."""

    id: uuid.UUID
    status: JobStatus
    owner: str | None = None
    created_at: datetime
    started_at: datetime | None = None
    finished_at: datetime | None = None
    attempts: int = 0
    engine_version: str | None = None
    result: RegistrationResult | None = None
    error: Problem | None = None
    payload: dict[str, Any] | None = None
    study: Study | None = None
    deliveries: list[WebhookDelivery] | None = None

    @property
    def finished(self) -> bool:
        return self.status in FINAL_STATUSES

    def raise_for_status(self) -> Job:
        """Raise ``JobFailed`` when the job failed or was cancelled; return it otherwise."""
        if self.status in ("failed", "cancelled"):
            from spine_client.errors import JobFailed

            raise JobFailed(self)
        return self


class JobPage(_Open):
    jobs: list[Job]
    next_cursor: str | None = None


class BatchEntry(_Open):
    index: int
    status: int
    job: Job | None = None
    problem: Problem | None = None


class BatchResult(_Open):
    accepted: int
    rejected: int
    results: list[BatchEntry]
