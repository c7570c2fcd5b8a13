"""Python client of the spine reconstruction service, and its command line (``spine submit`` …).

    from spine_client import SpineClient

    with SpineClient("http://127.0.0.1:8000", api_key="…") as client:
        job = client.wait(client.submit(payload).id, timeout=60).raise_for_status()
        print(job.result.measures.cobb[0].angle_deg)
"""

from spine_client.client import SpineClient
from spine_client.errors import (
    ApiError,
    Conflict,
    DicomStorePending,
    Forbidden,
    IdempotencyConflict,
    InvalidRequest,
    JobFailed,
    JobHasNoResult,
    JobNotCancellable,
    NoPatientIdentity,
    NotFound,
    RateLimited,
    RouteNotFound,
    ServerError,
    ServiceUnreachable,
    SpineError,
    Unauthorized,
    WaitTimeout,
)
from spine_client.models import BatchEntry, BatchResult, Job, JobPage, Problem

__version__ = "0.1.0"
"""The client's version, as spine_client/pyproject.toml gives it (``spine --version``;
tests/cli/test_client_scripting.py holds the two equal)."""

__all__ = [
    "ApiError",
    "BatchEntry",
    "BatchResult",
    "Conflict",
    "DicomStorePending",
    "Forbidden",
    "IdempotencyConflict",
    "InvalidRequest",
    "Job",
    "JobFailed",
    "JobHasNoResult",
    "JobNotCancellable",
    "JobPage",
    "NoPatientIdentity",
    "NotFound",
    "Problem",
    "RateLimited",
    "RouteNotFound",
    "ServerError",
    "ServiceUnreachable",
    "SpineClient",
    "SpineError",
    "Unauthorized",
    "WaitTimeout",
    "__version__",
]
