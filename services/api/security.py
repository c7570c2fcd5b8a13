"""Security of the HTTP API: API keys on /v1, request ids, security headers, CORS, access log.

``install_security(app, settings)`` adds two ASGI middlewares around the app:

- ``AuthMiddleware`` (inside the metrics middleware, so that refused requests are counted):
  every request under ``/v1`` needs ``Authorization: Bearer <key>``; a missing, malformed,
  unknown or revoked key answers a 401 problem with ``WWW-Authenticate: Bearer``. The caller
  (key id, client name, role) is put in ``request.state.caller``, which routes receive as the
  typed ``CurrentCaller`` dependency (``services/api/deps.py``). A verified key is trusted for
  ``SPINE_API_KEY_CACHE_S`` before the database is asked again (keys are not cached when refused).
  ``/metrics`` needs an admin key when ``SPINE_METRICS_REQUIRE_KEY`` is set.
- ``EdgeMiddleware`` (outermost): the request id (``X-Request-ID`` accepted when it is 1 to 64 of
  ``A-Za-z0-9._-``, else generated; echoed on the answer), the security headers on every answer,
  and one JSON access-log line per request (``SPINE_ACCESS_LOG``).

``HeadAsGet`` (inside those two, outside the metrics): HEAD is answered as GET without the content.

CORS (Starlette's middleware) sits between the two when ``SPINE_CORS_ORIGINS`` is set: it lets a page of those
origins send ``CORS_ALLOW_HEADERS`` and read ``CORS_EXPOSE_HEADERS`` (``ETag`` and ``If-None-Match`` included, for
the artifacts' conditional GET).
"""

from __future__ import annotations

import copy
import logging
import re
import threading
import time
import uuid
from typing import Any

import anyio.to_thread
from fastapi import FastAPI
from fastapi.responses import JSONResponse
from sqlalchemy.exc import InterfaceError, OperationalError, ProgrammingError
from starlette.datastructures import MutableHeaders
from starlette.middleware.cors import CORSMiddleware
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from services.api.access import QueuedCap
from services.api.errors import logged_path, not_migrated_problem, unexpected_error_response
from services.core.config import Settings
from services.core.logs import request_id_var
from services.core.problems import PROBLEM_MEDIA_TYPE, problem
from services.core.retry import schema_not_migrated
from services.db.engine import session_factory
from services.db.keys import Caller, digest, verify_key

log = logging.getLogger(__name__)
access_log = logging.getLogger("services.access")

REQUEST_ID = re.compile(r"^[A-Za-z0-9._-]{1,64}$")
REALM = 'Bearer realm="spine"'
API_POLICY = "default-src 'none'; frame-ancestors 'none'; base-uri 'none'; form-action 'none'"
# FastAPI's /docs and /redoc pages load Swagger UI / ReDoc from a CDN and start them inline.
DOCS_POLICY = (  # Swagger UI and ReDoc are served from the service's own assets (services/api/docs_ui.py)
    "default-src 'none'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data:; "
    "font-src 'self'; connect-src 'self'; worker-src blob:; frame-ancestors 'none'; base-uri 'none'; "
    "form-action 'none'"
)
DOCS_PATHS = ("/docs", "/redoc")
CACHE_CACHE_MAX = 10_000


def needs_key(path: str) -> bool:
    return path == "/v1" or path.startswith("/v1/")


def _problem(scope: Scope, body: dict[str, Any], headers: dict[str, str] | None = None) -> JSONResponse:
    body.setdefault("instance", scope.get("path", ""))
    return JSONResponse(body, status_code=int(body["status"]), media_type=PROBLEM_MEDIA_TYPE, headers=headers)


def unauthorized(detail: str, *, invalid: bool) -> tuple[dict[str, Any], dict[str, str]]:
    challenge = f'{REALM}, error="invalid_token"' if invalid else REALM
    return problem("unauthorized", detail), {"WWW-Authenticate": challenge}


class KeyCache:
    """Verified keys (by digest) for a few seconds, so that most requests need no key lookup."""

    def __init__(self, ttl_s: float):
        self.ttl_s = ttl_s
        self._entries: dict[str, tuple[Caller, float]] = {}
        self._lock = threading.Lock()

    def get(self, key_digest: str) -> Caller | None:
        if self.ttl_s <= 0:
            return None
        entry = self._entries.get(key_digest)
        if entry is None or entry[1] < time.monotonic():
            return None
        return entry[0]

    def put(self, key_digest: str, caller: Caller) -> None:
        if self.ttl_s <= 0:
            return
        with self._lock:
            if len(self._entries) >= CACHE_CACHE_MAX:
                self._entries.clear()
            self._entries[key_digest] = (caller, time.monotonic() + self.ttl_s)

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()


def bearer_token(scope: Scope) -> str | None:
    for name, value in scope.get("headers", ()):
        if name == b"authorization":
            scheme, _, token = value.decode("latin-1").strip().partition(" ")
            if scheme.lower() == "bearer" and token.strip():
                return token.strip()
            return ""
    return None


class AuthMiddleware:
    """API keys on /v1 (and on /metrics when SPINE_METRICS_REQUIRE_KEY is set)."""

    def __init__(self, app: ASGIApp, settings: Settings, cache: KeyCache):
        self.app = app
        self.settings = settings
        self.cache = cache

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        path: str = scope["path"]
        metrics = path == "/metrics" and self.settings.metrics_require_key
        if not (needs_key(path) or metrics):
            await self.app(scope, receive, send)
            return
        token = bearer_token(scope)
        if not token:
            body, headers = unauthorized(
                "this endpoint needs an API key, sent as `Authorization: Bearer <key>`", invalid=token == ""
            )
            await _problem(scope, body, headers)(scope, receive, send)
            return
        try:
            caller = await self.verify(token)
        except (OperationalError, InterfaceError, ProgrammingError) as exc:
            if schema_not_migrated(exc):
                log.error("key lookup: the database schema is not migrated (run `spine migrate`)")
                await _problem(scope, *not_migrated_problem(scope["path"]))(scope, receive, send)
                return
            if isinstance(exc, ProgrammingError):
                raise
            log.warning("key lookup: the database is unreachable: %s", type(exc).__name__)
            body = problem("service-unavailable", "the API key database is unreachable; retry later")
            await _problem(scope, body, {"Retry-After": "5"})(scope, receive, send)
            return
        if caller is None:
            body, headers = unauthorized("the API key is not valid: unknown, malformed or revoked", invalid=True)
            await _problem(scope, body, headers)(scope, receive, send)
            return
        if metrics and not caller.is_admin:
            await _problem(scope, problem("forbidden", "/metrics needs an admin API key"))(scope, receive, send)
            return
        scope.setdefault("state", {})["caller"] = caller  # read by the CurrentCaller dependency (deps.py)
        await self.app(scope, receive, send)

    async def verify(self, token: str) -> Caller | None:
        key_digest = digest(token)
        caller = self.cache.get(key_digest)
        if caller is not None:
            return caller
        caller = await anyio.to_thread.run_sync(self._lookup, token)
        if caller is not None:
            self.cache.put(key_digest, caller)
        return caller

    def _lookup(self, token: str) -> Caller | None:
        session = session_factory(self.settings)()
        try:
            return verify_key(session, token)
        finally:
            session.close()


class EdgeMiddleware:
    """Request id, security headers and the access log, around everything else."""

    def __init__(self, app: ASGIApp, settings: Settings):
        self.app = app
        self.settings = settings
        self.hsts = (
            f"max-age={settings.hsts_max_age_s}; includeSubDomains" if settings.hsts_max_age_s > 0 else None
        )

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        request_id = None
        for name, value in scope.get("headers", ()):
            if name == b"x-request-id":
                candidate = value.decode("latin-1")
                request_id = candidate if REQUEST_ID.match(candidate) else None
                break
        request_id = request_id or uuid.uuid4().hex
        state = scope.setdefault("state", {})
        state["request_id"] = request_id
        token = request_id_var.set(request_id)
        path: str = scope["path"]
        started = time.perf_counter()
        status = [500]
        response_started = [False]

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                response_started[0] = True
                status[0] = int(message["status"])
                self._secure(MutableHeaders(scope=message), path, request_id)
            await send(message)

        try:
            await self.app(scope, receive, send_with_headers)
        except Exception:
            if response_started[0]:  # too late for another answer
                raise
            # raised by a middleware (errors.UnexpectedErrors catches the app's): still the headers
            await unexpected_error_response(scope)(scope, receive, send_with_headers)
        finally:
            request_id_var.reset(token)
            if self.settings.access_log:
                caller: Caller | None = state.get("caller")
                extra: dict[str, Any] = {
                    "request_id": request_id,
                    "method": scope["method"],
                    "path": logged_path(path),
                    "status": status[0],
                    "duration_ms": round((time.perf_counter() - started) * 1000, 2),
                }
                if caller is not None:
                    extra["key_id"] = caller.key_id
                if state.get("job_id"):
                    extra["job_id"] = state["job_id"]
                access_log.info("request", extra=extra)

    def _secure(self, headers: MutableHeaders, path: str, request_id: str) -> None:
        headers["X-Request-ID"] = request_id
        headers["X-Content-Type-Options"] = "nosniff"
        headers["X-Frame-Options"] = "DENY"
        headers["Referrer-Policy"] = "no-referrer"
        if "content-security-policy" not in headers:
            docs = path in DOCS_PATHS or path.startswith("/docs/")
            headers["Content-Security-Policy"] = DOCS_POLICY if docs else API_POLICY
        if needs_key(path):
            headers["Cache-Control"] = "no-store"  # patients' data: no copy in any cache
        elif "cache-control" not in headers and not path.startswith("/assets/"):
            headers["Cache-Control"] = "no-store"
        if self.hsts:
            headers["Strict-Transport-Security"] = self.hsts


CORS_ALLOW_HEADERS = ["Authorization", "Content-Type", "Idempotency-Key", "If-None-Match", "X-Request-ID"]
"""Request headers a cross-origin page may send (the Fetch standard's "CORS-safelisted request-header" covers
none of them as the API takes them, so the browser asks first): ``If-None-Match`` for the artifacts'
conditional GET (RFC 9110 §13.1.2, services/api/artifacts.py)."""
CORS_EXPOSE_HEADERS = ["ETag", "Location", "Retry-After", "X-Request-ID", "Idempotent-Replayed", "Content-Disposition"]
"""Answer headers a cross-origin page may read besides the Fetch standard's "CORS-safelisted response-header
names" (Cache-Control, Content-Language, Content-Length, Content-Type, Expires, Last-Modified, Pragma):
``ETag``, which the page sends back in ``If-None-Match``; ``Content-Disposition``, the file name of a download
(RFC 6266: ``sr.dcm``, ``figure.dcm``, a PACS image), which a page saves the file under."""


def cors_origins(settings: Settings) -> list[str]:
    return [o.strip().rstrip("/") for o in settings.cors_origins.split(",") if o.strip()]


def install_auth(app: FastAPI, settings: Settings) -> None:
    """The API-key middleware; call before the metrics middleware is added (it then sits inside it)."""
    app.state.key_cache = KeyCache(settings.api_key_cache_s)
    app.state.queued_cap = QueuedCap(settings.max_queued_per_client)
    app.add_middleware(AuthMiddleware, settings=settings, cache=app.state.key_cache)


class HeadAsGet:
    """HEAD answered as GET without the content (RFC 9110 §9.1: a general-purpose server MUST support
    GET and HEAD; §9.3.2: HEAD's answer has GET's status and header fields, ``Content-Length``,
    ``ETag`` and ``Cache-Control`` included, and no content): a 304 to ``If-None-Match`` and a 401 or
    403 alike. FastAPI's routes answer only the methods they declare (Starlette's ``Route`` adds HEAD to
    GET, FastAPI's ``APIRoute`` does not: fastapi/fastapi#1773), and listing HEAD on each would add an
    operation per route to the contract: the request goes on as GET, and only its content is held back.
    A path without GET answers HEAD as it answers GET (405, its ``Allow`` from ``errors._allowed_methods``).

    The access log (outside) writes HEAD; the metrics (inside) count it as a GET."""

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "HEAD":
            await self.app(scope, receive, send)
            return

        async def headers_only(message: Message) -> None:
            if message["type"] == "http.response.start":
                await send(message)
            elif not message.get("more_body", False):  # the last body (or a file sent by path): none
                await send({"type": "http.response.body", "body": b"", "more_body": False})

        await self.app({**scope, "method": "GET"}, receive, headers_only)  # one "state": the access log's caller


def install_edge(app: FastAPI, settings: Settings) -> None:
    """HEAD as GET, CORS (when origins are configured) and the edge middleware; call last (outermost)."""
    app.add_middleware(HeadAsGet)
    origins = cors_origins(settings)
    if origins:
        app.add_middleware(
            CORSMiddleware,
            allow_origins=origins,
            allow_methods=["GET", "POST"],
            allow_headers=CORS_ALLOW_HEADERS,
            expose_headers=CORS_EXPOSE_HEADERS,
            allow_credentials=False,
            max_age=600,
        )
    app.add_middleware(EdgeMiddleware, settings=settings)


# ------------------------------------------------------------------ the contract

SECURITY_SCHEME = "ApiKey"
_PROBLEM_CONTENT = {PROBLEM_MEDIA_TYPE: {"schema": {"$ref": "#/components/schemas/Problem"}}}


def secure_openapi(schema: dict[str, Any]) -> dict[str, Any]:
    """Declare the bearer API key on every /v1 operation, with its 401 (and 429, 503) problems."""
    info = schema.setdefault("info", {})
    info["description"] = info.get("description", "") + (
        "\n\nEvery `/v1` operation needs an API key (`spine keys create`), sent as `Authorization: Bearer <key>`; "
        "a client key sees and cancels only its own jobs, an admin key every job. `X-Request-ID` is accepted "
        "(1 to 64 of `A-Za-z0-9._-`) or generated, and echoed on every answer."
    )
    components = schema.setdefault("components", {})
    components.setdefault("securitySchemes", {})[SECURITY_SCHEME] = {
        "type": "http",
        "scheme": "bearer",
        "description": "An API key from `spine keys create`, sent as `Authorization: Bearer spine_<id>_<secret>`.",
    }
    for path, item in schema.get("paths", {}).items():
        if not needs_key(path):
            continue
        for method, operation in item.items():
            if method not in ("get", "post", "put", "patch", "delete"):
                continue
            operation["security"] = [{SECURITY_SCHEME: []}]
            responses = operation.setdefault("responses", {})
            extra = {
                "401": "Missing, invalid or revoked API key (`WWW-Authenticate: Bearer`).",
                "503": "The job database is unreachable; retry after `Retry-After` seconds.",
            }
            if method == "post" and path in ("/v1/jobs", "/v1/jobs/batch"):
                extra["429"] = "Too many of this client's jobs are queued; retry after `Retry-After` seconds."
            for status, description in extra.items():
                responses.setdefault(status, {"description": description, "content": copy.deepcopy(_PROBLEM_CONTENT)})
    return schema
