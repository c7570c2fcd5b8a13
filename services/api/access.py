"""What a route does in its caller's name: audit rows of the jobs it touches and the per-client cap
on queued jobs. An ``Access`` is made per request by the ``AccessDep`` dependency from the
``CurrentCaller`` (``services/api/deps.py``); there is no request without a caller here, so
nothing is ever skipped silently."""

from __future__ import annotations

import uuid
from collections.abc import Sequence
from dataclasses import dataclass

from sqlalchemy.orm import Session
from starlette.datastructures import State

from services.api.quota import QueuedCap
from services.core.logs import job_id_var
from services.db.audit import AuditAction, audit
from services.db.keys import Caller


@dataclass(frozen=True)
class Access:
    """The authenticated caller of one request, with the cap and the request's state."""

    caller: Caller
    cap: QueuedCap
    state: State
    """The request's state: its ``request_id`` (set by the edge middleware); ``job_id`` is set here
    for the access log."""

    @property
    def owner(self) -> str | None:
        """The owner whose jobs the caller may see and cancel (None: an admin sees every job)."""
        return self.caller.read_scope

    def record(
        self, session: Session, action: AuditAction, job_ids: Sequence[uuid.UUID], *, commit: bool = True
    ) -> None:
        """Audit ``action`` on ``job_ids`` (one INSERT), and commit unless told not to."""
        if not job_ids:
            return
        if len(job_ids) == 1:
            self.state.job_id = str(job_ids[0])
            job_id_var.set(str(job_ids[0]))
        audit(session, self.caller, action, job_ids, getattr(self.state, "request_id", None))
        if commit:
            session.commit()

    def created(self, session: Session, job_ids: list[uuid.UUID]) -> None:
        """The create hook of the job store: audit rows in the transaction that stores the jobs."""
        self.record(session, "create", job_ids, commit=False)

    def admit(self, session: Session, n: int) -> None:
        """A 429 problem when ``n`` more queued jobs would put the caller over its cap."""
        self.cap.admit(session, self.caller, n)

    def accepted(self, n: int) -> None:
        """Count ``n`` jobs just stored against the caller's cap."""
        self.cap.accepted(self.caller, n)
