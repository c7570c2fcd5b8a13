"""Typed exceptions of the client. An ``ApiError`` carries the server's RFC 9457 problem."""

from __future__ import annotations

import contextlib
from typing import Any

import httpx

from spine_client.contract import Job, Problem

PROBLEM_BASE = "https://spine.example/problems/"
ROUTE_NOT_FOUND = "route-not-found"
"""The service's problem type (after ``PROBLEM_BASE``) of a 404 for a path it does not serve
(services/core/problems.py), as opposed to ``not-found``: a job the path names that is not there."""


class SpineError(Exception):
    """Base of every error the client raises."""


class ApiError(SpineError):
    """The service answered with an error status; ``problem`` is its problem+json body."""

    def __init__(self, status: int, problem: Problem, headers: dict[str, str] | None = None):
        self.status = status
        self.problem = problem
        self.headers = headers or {}
        text = f"{status} {problem.title}"
        super().__init__(f"{text}: {problem.detail}" if problem.detail else text)

    @property
    def kind(self) -> str:
        """The problem type without the service's URI prefix, e.g. ``validation-error``."""
        return self.problem.type.removeprefix(PROBLEM_BASE)


class InvalidRequest(ApiError):
    """400, 413, 415 or 422: the request (usually the payload) was refused; see ``problem.errors``."""


class Unauthorized(ApiError):
    """401: missing, invalid or revoked API key."""


class Forbidden(ApiError):
    """403: the API key may not do this."""


class NotFound(ApiError):
    """404: no such job (or not one of this API key's)."""


class RouteNotFound(ApiError):
    """404 ``route-not-found``: the service has no such path, so the base URL is not the service's (a
    path added to it, such as ``…/docs``), not that a job is missing. Not a ``NotFound``: code that
    reads ``NotFound`` as "no such job" must not take a wrong URL for one."""


class Conflict(ApiError):
    """409: the request conflicts with the job's state or an earlier request."""


class IdempotencyConflict(Conflict):
    """The Idempotency-Key was used before with another body."""


class JobNotCancellable(Conflict):
    """The job already succeeded or failed."""


class JobHasNoResult(Conflict):
    """The job has not succeeded (yet): no figure, CSV or FHIR export."""


class DicomStorePending(Conflict):
    """``spine store``: an attempt to store the job's results in the PACS is still due or under way (its
    ``Retry-After``: the seconds until it is due)."""


class NoPatientIdentity(Conflict):
    """``spine store``: the job's results are never stored in a PACS: it has no study, or its study no
    Patient ID."""


class RateLimited(ApiError):
    """429, still after the client's retries."""


class ServerError(ApiError):
    """5xx, still after the client's retries."""


class UnexpectedResponse(SpineError):
    """A response that is not one of the contract's: a success or redirect whose body is not the JSON
    (or the media type) the operation answers with; most often a URL that is not the service's (a
    proxy's login page, the web page, http redirected to https)."""


class ServiceUnreachable(SpineError):
    """No HTTP answer (connection refused, timeout…), still after the client's retries."""


class WaitTimeout(SpineError):
    """``wait`` gave up before the job finished; ``job`` is the last state seen."""

    def __init__(self, job: Job, timeout: float):
        self.job = job
        self.timeout = timeout
        super().__init__(f"job {job.id} still {job.status} after {timeout:g} s")


class JobFailed(SpineError):
    """Raised by ``Job.raise_for_status`` for a failed or cancelled job."""

    def __init__(self, job: Job):
        self.job = job
        reason = f": {job.error.detail}" if job.error is not None else ""
        super().__init__(f"job {job.id} {job.status}{reason}")


_CONFLICTS = {
    "idempotency-conflict": IdempotencyConflict,
    "job-not-cancellable": JobNotCancellable,
    "job-has-no-result": JobHasNoResult,
    "dicom-store-pending": DicomStorePending,
    "dicom-no-patient-identity": NoPatientIdentity,
}


def problem_of(response: httpx.Response) -> Problem:
    """The response's problem+json body, or one made from its status when it has none. Members a
    problem from elsewhere (a proxy) may leave out, all optional in RFC 9457 §3.1, are the response's
    status and empty texts."""
    body: Any = None
    with contextlib.suppress(ValueError):
        body = response.json()
    if isinstance(body, dict) and "type" in body:
        try:
            return Problem.model_validate({"title": "", "status": response.status_code, "detail": "", **body})
        except ValueError:
            pass
    return Problem(
        type="about:blank",
        title=response.reason_phrase or f"HTTP {response.status_code}",
        status=response.status_code,
        detail=response.text[:500],
    )


def error_for(response: httpx.Response) -> ApiError:
    """The typed exception of an error response."""
    status = response.status_code
    problem = problem_of(response)
    headers = dict(response.headers)
    cls: type[ApiError]
    if status == 409:
        cls = _CONFLICTS.get(problem.type.removeprefix(PROBLEM_BASE), Conflict)
    elif status in (400, 413, 415, 422):
        cls = InvalidRequest
    elif status == 404 and problem.type == PROBLEM_BASE + ROUTE_NOT_FOUND:
        cls = RouteNotFound
    else:
        cls = {401: Unauthorized, 403: Forbidden, 404: NotFound, 429: RateLimited}.get(
            status, ServerError if status >= 500 else ApiError
        )
    return cls(status, problem, headers)
