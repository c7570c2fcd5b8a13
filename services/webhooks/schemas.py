"""Response models of webhook deliveries (the ``deliveries`` member of a job)."""

from __future__ import annotations

from pydantic import BaseModel, Field

from services.db.models import UtcTimestamp


class WebhookDeliveryAttempt(BaseModel):
    """One attempt to POST a job's webhook to its callback_url."""

    event: str = Field(
        description="job.succeeded, job.failed or job.cancelled (the job's end); job.dicom_stored or "
        "job.dicom_store_failed (a run of STOW-RS attempts of its SR and figure ended: stored, or not stored and no "
        "attempt follows; only when the service stores results in the PACS), one message per run."
    )
    message_id: str = Field(description="The webhook-id header: the same on every attempt of a message.")
    attempt: int = Field(
        description="1 for the first attempt of the message; 0 when the message could not be published as the "
        "job (or its run of STOW-RS attempts) ended (no request was made; the reconciler publishes it again when "
        "next_attempt_at is SPINE_WEBHOOK_SWEEP_AFTER_S past)."
    )
    url: str
    attempted_at: UtcTimestamp
    status_code: int | None = Field(description="The receiver's HTTP status; null when no answer came.")
    error: str | None = Field(description="Why the attempt failed or was not made; null on success (2xx).")
    duration_ms: float | None
    next_attempt_at: UtcTimestamp | None = Field(description="When the next attempt is due; null when none follows.")
