"""A job row as the JSON of the API's ``Job`` model (``GET /v1/jobs/{id}``, the lists, webhook
bodies): built directly from the row, the hot path skips re-validation."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from services.db.models import Job as JobRow


def _ts(value: datetime | None) -> str | None:
    return value.isoformat() if value is not None else None


def job_json(job: JobRow, *, with_payload: bool = False) -> dict[str, Any]:
    """A job as the JSON of the ``Job`` model, built directly (the hot path skips re-validation)."""
    body: dict[str, Any] = {
        "id": str(job.id),
        "status": job.status,
        "owner": job.owner,
        "created_at": _ts(job.created_at),
        "started_at": _ts(job.started_at),
        "finished_at": _ts(job.finished_at),
        "attempts": job.attempts,
        "engine_version": job.engine_version,
        "result": job.result,
        "error": job.error,
        "study": job.payload.get("study") if isinstance(job.payload, dict) else None,
    }
    if with_payload:
        body["payload"] = job.payload
        body["dicom"] = job.dicom
        body["dicom_stores"] = job.dicom_stores or []
    return body
