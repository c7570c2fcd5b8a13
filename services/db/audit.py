"""The audit trail of job access (table ``job_audit``): who (key id) created, read, listed or
cancelled which job, when, in which request."""

from __future__ import annotations

import uuid
from collections.abc import Sequence
from typing import Any, Literal, cast

from sqlalchemy import Table, insert, select
from sqlalchemy.orm import Session

from services.db.keys import Caller
from services.db.models import JobAudit, utcnow

AuditAction = Literal["create", "read", "list", "cancel"]

_AUDIT = insert(cast(Table, JobAudit.__table__))


def audit(
    session: Session, caller: Caller, action: AuditAction, job_ids: Sequence[uuid.UUID], request_id: str | None
) -> None:
    """Add one audit row per job to the session's transaction (one INSERT statement; the caller commits)."""
    if not job_ids:
        return
    now = utcnow()
    rows: list[dict[str, Any]] = [
        {"at": now, "key_id": caller.key_id, "action": action, "job_id": job_id, "request_id": request_id}
        for job_id in job_ids
    ]
    session.execute(_AUDIT, rows)


def audit_trail(session: Session, job_id: uuid.UUID) -> list[JobAudit]:
    """The audit rows of a job, oldest first."""
    return list(session.scalars(select(JobAudit).where(JobAudit.job_id == job_id).order_by(JobAudit.id)))
