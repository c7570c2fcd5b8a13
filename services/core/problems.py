"""RFC 9457 problem details: the catalogue of problem kinds and a builder of problem dicts.

Every error the API answers and every error stored on a failed job is such a dict, with a
stable ``type`` URI per kind (``PROBLEM_BASE`` + kind): one kind per kind of problem, so that a client
can act on the type alone (RFC 9457 §3.1.1). ``not-found`` is a resource the path names but that does
not exist (a job id); ``route-not-found`` a path that names nothing (a typo in the URL). Validation
problems carry ``errors``: one entry per offending field with its JSON path.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from spine_engine.errors import FieldError

PROBLEM_BASE = "https://spine.example/problems/"
PROBLEM_MEDIA_TYPE = "application/problem+json"

# kind -> (title, default HTTP status)
KINDS: dict[str, tuple[str, int]] = {
    "validation-error": ("The request does not satisfy the API contract (its body, path or query)", 422),
    "malformed-json": ("The request body is not valid JSON", 400),
    "unsupported-media-type": ("The request body must be application/json", 415),
    "payload-too-large": ("The request body is too large", 413),
    "not-found": ("No such resource", 404),
    "route-not-found": ("Nothing is served at this path", 404),
    "method-not-allowed": ("Method not allowed", 405),
    "idempotency-conflict": ("The Idempotency-Key was used with another body", 409),
    "job-not-cancellable": ("The job has already finished", 409),
    "job-has-no-result": ("The job has no result: it has not succeeded (yet)", 409),
    "service-unavailable": ("A dependency of the service is unreachable", 503),
    "unauthorized": ("Missing, invalid or revoked API key", 401),
    "forbidden": ("The API key's role does not allow this", 403),
    "too-many-queued-jobs": ("Too many of this client's jobs are queued", 429),
    "internal-error": ("Internal error", 500),
    "http-error": ("HTTP error", 400),
    # Stored on failed jobs by the worker.
    "fit-failed": ("The registration ran but did not produce a reconstruction", 422),
    "fit-timeout": ("The registration exceeded its time limit", 504),
    "worker-lost": ("The job's worker stopped too many times while running it", 500),
    "engine-error": ("The engine raised an unexpected error", 500),
    "result-not-stored": ("The job's result could not be stored", 500),
    # The DICOM layer (services/dicom): each names the DICOM attribute by keyword and tag.
    "dicom-not-dicom": ("The data is not DICOM", 422),
    "dicom-missing-attribute": ("The image's header lacks an attribute the job needs", 422),
    "dicom-invalid-attribute": ("An attribute of the image's header is not usable", 422),
    "dicom-unsupported-orientation": ("The image is not a PA/AP or lateral radiograph, or not the view given", 422),
    "dicom-patient-conflict": ("The payload and the films, or the two films, are not of one patient", 422),
    "dicomweb-unavailable": ("The PACS (DICOMweb) did not answer, after the retries", 503),
    "dicomweb-instance-not-found": ("The PACS does not hold the image the job names", 422),
    "dicomweb-study-not-found": ("The PACS holds no image of this study", 404),
    "dicomweb-not-configured": ("The service is not connected to a PACS", 404),
    "dicomweb-store-disabled": ("The service does not store results in its PACS", 404),
    "dicom-store-pending": ("An attempt to store the job's results in the PACS is still due or under way", 409),
    "dicom-no-patient-identity": ("The job's results are not stored in a PACS without the patient's identity", 409),
    "dicomweb-transfer-syntax-unavailable": ("The PACS cannot send the image uncompressed", 502),
    "dicomweb-store-refused": ("The PACS refused to store the results", 502),
    "dicomweb-error": ("The PACS answered with an error", 502),
    "dicom-invalid": ("The DICOM data is not usable", 422),
}


def problem_type(kind: str) -> str:
    return PROBLEM_BASE + kind


def problem(
    kind: str,
    detail: str,
    *,
    status: int | None = None,
    instance: str | None = None,
    **extensions: Any,
) -> dict[str, Any]:
    """A problem dict of ``kind`` (a key of ``KINDS``) with extension members."""
    title, default_status = KINDS[kind]
    body: dict[str, Any] = {
        "type": problem_type(kind),
        "title": title,
        "status": status or default_status,
        "detail": detail,
    }
    if instance is not None:
        body["instance"] = instance
    body.update(extensions)
    return body


def field_errors(errors: Iterable[FieldError]) -> list[dict[str, Any]]:
    """The ``errors`` member of a validation problem: JSON path, location, message and type."""
    return [{"path": e.path, "loc": list(e.loc), "msg": e.msg, "type": e.type} for e in errors]


def validation_problem(
    errors: list[FieldError], *, kind: str = "validation-error", instance: str | None = None
) -> dict[str, Any]:
    n = len(errors)
    detail = f"{n} field{'s' if n != 1 else ''} failed validation: " + "; ".join(
        f"{e.path or '(body)'}: {e.msg}" for e in errors[:5]
    )
    if n > 5:
        detail += f"; and {n - 5} more"
    return problem(kind, detail, instance=instance, errors=field_errors(errors))
