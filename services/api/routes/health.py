"""Liveness, readiness and Prometheus metrics."""

from __future__ import annotations

import functools
import threading
import time
from concurrent.futures import Future
from typing import Any

from alembic.script import ScriptDirectory
from celery import Celery
from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from sqlalchemy import text
from sqlalchemy.orm import Session

from services.api.deps import QueueDep, SettingsDep
from services.api.metrics import answer_by, start_check
from services.api.schemas import Health, problem_responses
from services.core.config import Settings
from services.core.jobqueue import ping_broker
from services.core.problems import PROBLEM_MEDIA_TYPE, problem
from services.core.retry import schema_not_migrated
from services.db.engine import session_factory
from services.db.migrate import ALEMBIC_INI

router = APIRouter(tags=["operations"])


@router.get("/healthz", response_model=Health, summary="The process is alive")
def healthz() -> Health:
    return Health(status="ok", checks={})


READY_503: dict[int | str, dict[str, Any]] = {
    503: {
        **problem_responses(503)[503],
        "description": "Not ready: a `service-unavailable` problem whose `detail` and `checks` name each "
        "dependency that is not (`database`, `broker`) and why; a schema not migrated says to run "
        "`spine migrate`.",
        "headers": {
            "Retry-After": {"description": "Seconds to wait before asking again.", "schema": {"type": "integer"}}
        },
    }
}


@router.get(
    "/readyz",
    response_model=Health,
    summary="The database (its schema migrated) and the broker are ready",
    description="200 when the database answers and its schema is at this release's Alembic head (`spine migrate` "
    "has run), and the broker answers. Otherwise 503 with `checks` per dependency: the database unreachable; its "
    "schema not migrated (no revision, or an older one than this release's head: run `spine migrate`); migrated "
    "by a newer release (run the release that migrated it); the broker unreachable.",
    responses=READY_503,
)
def readyz(request: Request, settings: SettingsDep, queue: QueueDep) -> Health | JSONResponse:
    # Both checks run at once, each in a thread of its own, and the answer does not wait for either
    # more than SPINE_READY_TIMEOUT_S: a dependency that accepts connections but does not answer (a
    # stopped process, a half-open network path) makes a prompt 503, not a probe that hangs.
    bound = settings.ready_timeout_s
    started = time.monotonic()
    pending = {
        "database": start_check(functools.partial(_database_check, settings), _CHECK_SLOTS),
        "broker": start_check(functools.partial(_broker_check, queue), _CHECK_SLOTS),
    }
    checks = {name: _outcome(check, started + bound, bound) for name, check in pending.items()}
    if all(v == "ok" for v in checks.values()):
        return Health(status="ready", checks=checks)
    why = [_why(name, value) for name, value in checks.items() if value != "ok"]
    body = problem("service-unavailable", f"not ready: {'; '.join(why)}", instance=request.url.path, checks=checks)
    return JSONResponse(body, status_code=503, media_type=PROBLEM_MEDIA_TYPE, headers={"Retry-After": "5"})


def _why(name: str, check: str) -> str:
    if check.startswith("unreachable"):
        return f"{name} unreachable"
    if check.startswith("no answer"):
        return f"{name}: {check}"
    return f"database {check}"  # its schema


_CHECK_SLOTS = threading.BoundedSemaphore(4)
"""Readiness checks running at once per process, each in a daemon thread (``services.api.metrics.
start_check``): with every slot held by checks stuck on a dependency, a check is not started and
answers "no answer" in time."""


def _outcome(check: Future[str], deadline: float, bound: float) -> str:
    """``ok``, what is wrong, or that the dependency did not answer by ``deadline``."""
    try:
        return answer_by(check, deadline)
    except TimeoutError:
        return f"no answer within {bound:g} s (SPINE_READY_TIMEOUT_S)"
    except Exception as exc:
        return f"unreachable: {type(exc).__name__}"


def _database_check(settings: Settings) -> str:
    with session_factory(settings)() as session:
        session.execute(text("SELECT 1"))
        return _schema_check(session)


def _broker_check(queue: Celery) -> str:
    ping_broker(queue)
    return "ok"


@functools.cache
def _scripts() -> ScriptDirectory:
    return ScriptDirectory(str(ALEMBIC_INI.parent))


@functools.cache
def code_head() -> str:
    """The Alembic head revision of the code's migrations (read once: it does not change in a process)."""
    return ",".join(sorted(_scripts().get_heads()))


def _schema_check(session: Session) -> str:
    """``ok`` when the database's schema revision is the code's head, else what was found and expected
    and what to do."""
    expected = code_head()
    try:
        found = sorted(session.scalars(text("SELECT version_num FROM alembic_version")))
    except Exception as exc:
        session.rollback()
        if not schema_not_migrated(exc):
            raise
        found = []
    if ",".join(found) == expected:
        return "ok"
    if not found:
        return f"schema not migrated (no schema revision, expected {expected}): run `spine migrate`"
    known = {script.revision for script in _scripts().walk_revisions()}
    if not set(found) <= known:  # a newer release migrated it: this code is the older one
        return (f"schema at revision {','.join(found)}, unknown to this version of the service (expected "
                f"{expected}): run the release that migrated it")  # fmt: skip
    return f"schema not migrated (revision {','.join(found)}, expected {expected}): run `spine migrate`"


@router.get(
    "/metrics",
    summary="Prometheus metrics",
    response_class=Response,
    responses={200: {"content": {CONTENT_TYPE_LATEST: {}}, "description": "Prometheus text format."}},
)
def metrics(request: Request) -> Response:
    return Response(generate_latest(request.app.state.registry), media_type=CONTENT_TYPE_LATEST)
