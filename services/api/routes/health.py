"""Liveness, readiness and Prometheus metrics."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from sqlalchemy import text

from services.api.deps import QueueDep, SessionDep
from services.api.schemas import Health, problem_responses
from services.core.jobqueue import ping_broker
from services.core.problems import PROBLEM_MEDIA_TYPE, problem

router = APIRouter(tags=["operations"])


@router.get("/healthz", response_model=Health, summary="The process is alive")
def healthz() -> Health:
    return Health(status="ok", checks={})


@router.get(
    "/readyz",
    response_model=Health,
    summary="The database and the broker are reachable",
    responses=problem_responses(503),
)
def readyz(request: Request, session: SessionDep, queue: QueueDep) -> Health | JSONResponse:
    checks: dict[str, str] = {}
    try:
        session.execute(text("SELECT 1"))
        checks["database"] = "ok"
    except Exception as exc:
        checks["database"] = f"unreachable: {type(exc).__name__}"
    try:
        ping_broker(queue)
        checks["broker"] = "ok"
    except Exception as exc:
        checks["broker"] = f"unreachable: {type(exc).__name__}"
    if all(v == "ok" for v in checks.values()):
        return Health(status="ready", checks=checks)
    down = ", ".join(k for k, v in checks.items() if v != "ok")
    body = problem("service-unavailable", f"not ready: {down} unreachable", instance=request.url.path, checks=checks)
    return JSONResponse(body, status_code=503, media_type=PROBLEM_MEDIA_TYPE, headers={"Retry-After": "5"})


@router.get(
    "/metrics",
    summary="Prometheus metrics",
    response_class=Response,
    responses={200: {"content": {CONTENT_TYPE_LATEST: {}}, "description": "Prometheus text format."}},
)
def metrics(request: Request) -> Response:
    return Response(generate_latest(request.app.state.registry), media_type=CONTENT_TYPE_LATEST)
