"""What a route does in its caller's name: audit rows of the jobs it touches, and the per-client
cap on queued jobs (``QueuedCap``: past ``SPINE_MAX_QUEUED_PER_CLIENT`` queued jobs of a client
role, submissions answer 429 with Retry-After). An ``Access`` is made per request by the
``AccessDep`` dependency from the ``CurrentCaller`` (``services/api/deps.py``); there is no
request without a caller here, so nothing is ever skipped silently."""

from __future__ import annotations

import uuid
from collections.abc import Sequence
from dataclasses import dataclass

from sqlalchemy.orm import Session
from starlette.datastructures import State

from services.api.errors import ProblemError
from services.core.logs import job_id_var
from services.core.problems import problem
from services.db import stats
from services.db.keys import AuditAction, Caller, audit

RETRY_AFTER_S = 30


class QueuedCap:
    """At most ``cap`` queued jobs per client (0: no cap; admins are never capped).

    The count is made under the owner's submission lock (``stats.count_queued_for_insert``), in the
    transaction that then inserts the jobs and commits, so concurrent submissions of one client are
    counted one after another and never pass the cap together. Nothing is cached between requests: a
    count remembered from an earlier request would let every request of a burst pass on it."""

    def __init__(self, cap: int):
        self.cap = cap

    def admit(self, session: Session, caller: Caller, n: int) -> None:
        """Raise a 429 problem when ``n`` more queued jobs would put ``caller`` over the cap; otherwise
        the owner's submissions stay locked until ``session``'s transaction, which inserts them, ends."""
        if self.cap <= 0 or caller.is_admin or n <= 0:
            return
        queued = stats.count_queued_for_insert(session, caller.owner, self.cap + 1)
        if queued + n > self.cap:
            session.rollback()  # ends the transaction: the lock is released now, not when the request ends
            raise ProblemError(
                problem(
                    "too-many-queued-jobs",
                    f"{queued} of this client's jobs are queued and {n} more would pass the cap of {self.cap}; "
                    f"retry once some have run",
                    queued=queued,
                    limit=self.cap,
                ),
                headers={"Retry-After": str(RETRY_AFTER_S)},
            )


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

    @property
    def client(self) -> str:
        """The client whose Idempotency-Keys the caller sends: its key's name (docs/security.md, "A key's
        name is its client"), an admin's too, whatever jobs it may see."""
        return self.caller.name

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
        """The create hook of the jobs table: audit rows in the transaction that stores the jobs."""
        self.record(session, "create", job_ids, commit=False)

    def admit(self, session: Session, n: int) -> None:
        """A 429 problem when ``n`` more queued jobs would put the caller over its cap (called in the
        transaction that inserts them: ``QueuedCap.admit``)."""
        self.cap.admit(session, self.caller, n)
