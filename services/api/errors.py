"""HTTP error handling: every error leaves the API as an RFC 9457 problem+json response."""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.routing import iter_route_contexts
from fastapi.staticfiles import StaticFiles
from sqlalchemy.exc import InterfaceError, OperationalError, ProgrammingError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from services.core.problems import PROBLEM_MEDIA_TYPE, problem, validation_problem
from services.core.retry import schema_not_migrated
from spine_engine.errors import FieldError
from spine_engine.models import PATTERN_REASONS

log = logging.getLogger(__name__)

MAX_ERRORS = 20
"""Most field errors one validation problem lists (a batch: per entry), so that an answer is bounded
whatever the body holds wrong: listing them all, a 770 kB payload of 60,000 unknown members is a
5.9 MB problem (100 bytes per error), and a 16 MiB batch of such entries a gigabyte held in the API
process while it is built. The problem's ``detail`` says how many there were in all."""


class ProblemError(Exception):
    """Raise to answer with this problem dict."""

    def __init__(self, body: dict[str, Any], headers: dict[str, str] | None = None):
        self.body = body
        self.headers = headers
        super().__init__(body.get("detail", ""))


def problem_response(body: dict[str, Any], headers: dict[str, str] | None = None) -> JSONResponse:
    return JSONResponse(body, status_code=int(body["status"]), media_type=PROBLEM_MEDIA_TYPE, headers=headers)


def field_problem(errors: list[FieldError], *, instance: str | None = None) -> dict[str, Any]:
    """The validation problem of ``errors``, listing the first ``MAX_ERRORS`` of them; when there were
    more, its ``detail`` says how many in all."""
    listed = errors[:MAX_ERRORS]
    body = validation_problem(listed, instance=instance)
    if len(errors) > len(listed):
        named = str(body["detail"]).partition(": ")[2]
        body["detail"] = f"{len(errors)} fields failed validation, the first {len(listed)} listed in errors: {named}"
    return body


async def _problem_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, ProblemError)
    body = dict(exc.body)
    body.setdefault("instance", request.url.path)
    return problem_response(body, exc.headers)


def _reason(error: dict[str, Any]) -> str:
    """A request validation error's message; a pattern of the contract's strings said in plain words
    (``PATTERN_REASONS``) instead of pydantic's "String should match pattern '…'", and an empty header
    (``Idempotency-Key:`` with no value) said to be one."""
    if error.get("type") == "string_pattern_mismatch":
        reason = PATTERN_REASONS.get(str((error.get("ctx") or {}).get("pattern", "")))
        if reason is not None:
            return reason
    loc = error.get("loc", ())
    if error.get("type") == "string_too_short" and len(loc) == 2 and loc[0] == "header" and not error.get("input"):
        name = "-".join(word.capitalize() for word in str(loc[1]).split("-"))
        return f"the {name} header is empty; give it a value or leave the header out"
    return str(error.get("msg", ""))


async def _request_validation(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    errors = [
        FieldError(tuple(p for p in e.get("loc", ()) if isinstance(p, (str, int))), _reason(e), str(e.get("type", "")))
        for e in exc.errors()
    ]
    return problem_response(validation_problem(errors, instance=request.url.path))


async def _http_error(request: Request, exc: Exception) -> JSONResponse:
    """Starlette's own errors. Its 404 is the router's (no route has the path) or a static mount's (no
    such file): ``route-not-found``, not the ``not-found`` of a job the path names but that is not there."""
    assert isinstance(exc, StarletteHTTPException)
    kind = {404: "route-not-found", 405: "method-not-allowed", 413: "payload-too-large",
            415: "unsupported-media-type"}  # fmt: skip
    detail = str(exc.detail)
    if exc.status_code == 404:
        detail = f"nothing is served at {request.url.path}; the API's paths are listed in /openapi.json"
    body = problem(kind.get(exc.status_code, "http-error"), detail, status=exc.status_code,
                   instance=request.url.path)  # fmt: skip
    headers = dict(exc.headers) if exc.headers else {}
    if exc.status_code == 405:  # every method the path has, not only those of the first route matched
        headers["Allow"] = ", ".join(_allowed_methods(request)) or headers.get("Allow", "")
    return problem_response(body, headers or None)


METHOD_GUARD = "method-not-allowed"
"""The name of a route that only answers 405 for its methods (e.g. GET /v1/jobs/batch, which the job
route would otherwise take as a job id): its methods are not allowed ones."""


def _allowed_methods(request: Request) -> list[str]:
    """The methods the request's path answers (RFC 9110 §15.5.6: a 405 "MUST generate an Allow header
    field containing a list of the target resource's currently supported methods"): each method of a
    route whose path matches, when the first route that the router would take for it is not a guard,
    and HEAD wherever GET is (``security.HeadAsGet`` answers it).
    Routes are walked as the router walks them, included routers flattened (``iter_route_contexts``)."""
    routes = list(iter_route_contexts(request.app.router.routes))
    # the scope as the app's router saw it (a mount that answered extended root_path for its own app)
    base = {**request.scope, "root_path": request.scope.get("app_root_path", request.scope.get("root_path", ""))}
    candidates: set[str] = set()
    for route in routes:
        if route.matches(base)[0] != Match.NONE:
            candidates |= set(route.methods or ())
            if isinstance(getattr(route, "app", None), StaticFiles):  # a mount of files answers these two
                candidates |= {"GET", "HEAD"}
    allowed = []
    for method in sorted(candidates):
        scope = {**base, "method": method}
        first = next((r for r in routes if r.matches(scope)[0] == Match.FULL), None)
        if first is not None and first.name != METHOD_GUARD:
            allowed.append(method)
    if "GET" in allowed and "HEAD" not in allowed:  # every GET answers HEAD too (security.HeadAsGet)
        allowed = sorted([*allowed, "HEAD"])
    return allowed


NOT_MIGRATED = "the database schema is not migrated: run `spine migrate`"
NOT_MIGRATED_RETRY_AFTER_S = "30"


def not_migrated_problem(instance: str) -> tuple[dict[str, Any], dict[str, str]]:
    """The 503 problem (and its headers) of a request that found the schema not migrated."""
    body = problem("service-unavailable", NOT_MIGRATED, instance=instance)
    return body, {"Retry-After": NOT_MIGRATED_RETRY_AFTER_S}


def _not_migrated_response(request: Request, exc: Exception) -> JSONResponse | None:
    """The 503 of a request that met the schema not migrated (``schema_not_migrated``), logged; else None."""
    if not schema_not_migrated(exc):
        return None
    log.error("database schema not migrated (run `spine migrate`): %s", type(exc).__name__)
    return problem_response(*not_migrated_problem(request.url.path))


async def _database_down(request: Request, exc: Exception) -> JSONResponse:
    if (answer := _not_migrated_response(request, exc)) is not None:
        return answer
    log.warning("database unreachable: %s", exc)
    body = problem("service-unavailable", "the job database is unreachable; retry later",
                   instance=request.url.path)  # fmt: skip
    return problem_response(body, {"Retry-After": "5"})


async def _database_programming_error(request: Request, exc: Exception) -> JSONResponse:
    if (answer := _not_migrated_response(request, exc)) is not None:
        return answer
    raise exc  # any other: an unexpected error (``UnexpectedErrors``)


PATIENTS_PREFIX = "/v1/patients/"
MEASURES_SUFFIX = "/measures"


def logged_path(path: str) -> str:
    """A request's path as the logs write it: under ``/v1/patients/`` the path holds a Patient ID
    (0010,0020), an identifier of a person (PS3.3 C.7.1.1), which the logs never hold; it is written as
    ``{patient_id}`` (the route's template when the path is the route's; the ID may hold slashes, so
    ``{patient_id}`` stands for all the rest otherwise). Other paths name jobs and DICOM instances by
    their UIDs, which the logs keep."""
    if not path.startswith(PATIENTS_PREFIX):
        return path
    return PATIENTS_PREFIX + "{patient_id}" + (MEASURES_SUFFIX if path.endswith(MEASURES_SUFFIX) else "")


def unexpected_error_response(scope: Scope) -> JSONResponse:
    """The 500 problem of an unhandled exception, logged (with its traceback and the request id)."""
    log.exception("unhandled error on %s %s", scope.get("method"), logged_path(str(scope.get("path", ""))))
    body = problem("internal-error", "an unexpected error occurred; it has been logged",
                   instance=scope.get("path", ""))  # fmt: skip
    return problem_response(body)


async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
    """Last resort (Starlette's outermost ``ServerErrorMiddleware``): what escaped the middlewares."""
    return unexpected_error_response(request.scope)


class UnexpectedErrors:
    """Turns an exception no handler took into the 500 problem, inside every other middleware: the
    answer then gets the request id, the security headers and CORS (``services.api.security``), is
    counted by the metrics, and its log line carries the request id. (Starlette runs a handler of
    ``Exception`` outside all middlewares, where none of that happens.)"""

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = False

        async def tracking(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, receive, tracking)
        except Exception:
            if started:  # too late for another answer
                raise
            await unexpected_error_response(scope)(scope, receive, send)


def install_error_handlers(app: FastAPI) -> None:
    """The problem+json handlers; call before any middleware is added (``UnexpectedErrors`` is then
    the innermost middleware)."""
    app.add_exception_handler(ProblemError, _problem_error)
    app.add_exception_handler(RequestValidationError, _request_validation)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(OperationalError, _database_down)
    app.add_exception_handler(InterfaceError, _database_down)
    app.add_exception_handler(ProgrammingError, _database_programming_error)
    app.add_exception_handler(Exception, _unexpected)
    app.add_middleware(UnexpectedErrors)
