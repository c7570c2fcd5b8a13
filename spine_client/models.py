"""The client's views of what the service answers: the contract's models (``spine_client.contract``,
generated from ``openapi.yaml``) with the behaviour a script uses (``Job.finished``,
``Job.raise_for_status``).

Models accept members they do not know (``extra="allow"``), so a newer service does not break an
older client.
"""

from __future__ import annotations

from spine_client import contract
from spine_client.contract import FieldProblem, JobStatus, Problem, RegistrationResult, Study, WebhookDeliveryAttempt
from spine_client.errors import JobFailed

FINAL_STATUSES: frozenset[str] = frozenset({"succeeded", "failed", "cancelled"})

__all__ = [
    "FINAL_STATUSES",
    "BatchEntry",
    "BatchResult",
    "FieldProblem",
    "Job",
    "JobPage",
    "JobStatus",
    "Problem",
    "RegistrationResult",
    "Study",
    "WebhookDeliveryAttempt",
]


class Job(contract.Job):
    """A job and, once finished, its result or error."""

    @property
    def finished(self) -> bool:
        return self.status in FINAL_STATUSES

    def raise_for_status(self) -> Job:
        """Raise ``JobFailed`` when the job failed or was cancelled; return it otherwise."""
        if self.status in ("failed", "cancelled"):
            raise JobFailed(self)
        return self


class JobPage(contract.JobPage):
    jobs: list[Job]  # type: ignore[assignment]  # the same items, with Job's behaviour


class BatchEntry(contract.BatchEntry):
    job: Job | None = None


class BatchResult(contract.BatchResponse):
    """The answer of POST /v1/jobs/batch (the contract's ``BatchResponse``)."""

    results: list[BatchEntry]  # type: ignore[assignment]  # the same items, with Job's behaviour
