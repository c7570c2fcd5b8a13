"""The FastAPI application: ``create_app(settings)`` (``uvicorn --factory services.api.app:create_app``)."""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import anyio.to_thread
from celery import Celery
from fastapi import Depends, FastAPI
from fastapi.openapi.utils import get_openapi
from prometheus_client import CollectorRegistry

from services.api.artifacts import ArtifactCache
from services.api.deps import reject_unknown_query
from services.api.docs_ui import mount_docs
from services.api.errors import install_error_handlers
from services.api.metrics import HTTPMetrics, JobStateCollector
from services.api.routes import dicom, fhir, figures, health, jobs, pacs, patients
from services.api.schemas import BatchRequest, Problem
from services.api.security import install_auth, install_edge, secure_openapi
from services.api.web import mount_web
from services.core.config import Settings, get_settings
from services.core.jobqueue import make_celery
from services.core.problems import PROBLEM_BASE
from services.db.engine import get_engine
from spine_engine.models import JobPayload

REF = "#/components/schemas/{model}"
CLIENT_DICOM: dict[str, Any] = {
    "anyOf": [{"$ref": "#/components/schemas/DicomProvenance"}, {"type": "null"}],
    "description": "Service only (POST /v1/jobs; the engine ignores it): what the client read from the radiographs' "
    "DICOM files (`spine submit --pa-dicom`), in the form of the job's `dicom` member, every view's `source` `file`. "
    "Kept on the job as the service keeps its own PACS reads: its reads marked `used` complete the payload (they may "
    "only fill what a header fills: a view's spacing, calibration, orientation and acquisition, the study's "
    "identifiers), and the SR references the film and copies its patient and study. 422 naming the member otherwise.",
}
"""The ``dicom`` member of a posted payload (``services.api.admission.split_dicom``)."""

log = logging.getLogger(__name__)

DESCRIPTION = (
    "3D reconstruction of a scoliotic spine from landmarks on radiographs (discrete Cosserat rod "
    "registration, Li et al., CAIP 2009), as jobs: POST a payload, poll the job for its result.\n\n"
    "Errors are RFC 9457 `application/problem+json` bodies whose `type` is a stable URI under "
    f"`{PROBLEM_BASE}`; validation problems list every offending field with its JSON path in `errors`."
)


def warm_up(settings: Settings, celery: Celery) -> None:
    """Open database and broker connections before the first request, so that it does not pay
    for them (a dependency that is down is only logged: /readyz reports it)."""
    connections = []
    try:
        engine = get_engine(settings)
        for _ in range(min(settings.db_pool_size, 8)):
            connections.append(engine.connect())
        with celery.producer_or_acquire():
            pass
    except Exception as exc:
        log.warning("warm-up: a dependency is unreachable: %s", exc)
    finally:
        for connection in connections:
            connection.close()


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        await anyio.to_thread.run_sync(warm_up, settings, app.state.celery)
        yield

    app = FastAPI(
        title="Spine reconstruction service",
        version="1.0.0",
        description=DESCRIPTION,
        lifespan=lifespan,
        dependencies=[Depends(reject_unknown_query)],
        docs_url=None,  # FastAPI's own pages load Swagger UI and ReDoc from a CDN: served by mount_docs instead
        redoc_url=None,
    )
    app.state.settings = settings
    app.state.celery = make_celery(settings)
    app.state.artifact_cache = ArtifactCache(int(settings.artifact_cache_mb * 1024 * 1024))
    registry = CollectorRegistry()
    registry.register(JobStateCollector(settings, app.state.celery))
    app.state.registry = registry
    install_error_handlers(app)
    app.include_router(jobs.router)
    app.include_router(health.router)
    app.include_router(figures.router)
    app.include_router(fhir.router)
    app.include_router(dicom.router)
    app.include_router(pacs.router)
    app.include_router(patients.router)
    mount_docs(app)
    mount_web(app)
    install_auth(app, settings)  # API keys on /v1, inside the metrics middleware: refusals are counted
    app.add_middleware(HTTPMetrics, registry=registry)
    install_edge(app, settings)  # outermost: request id, security headers, CORS, access log

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
            defs = JobPayload.model_json_schema(mode="validation", ref_template="#/components/schemas/{model}")
            components = schema.setdefault("components", {}).setdefault("schemas", {})
            for name, definition in defs.pop("$defs", {}).items():
                components.setdefault(name, definition)
            components["JobPayload"] = defs
            defs["properties"]["dicom"] = CLIENT_DICOM  # service only, read by the API (admission.split_dicom)
            # POST /v1/jobs/batch's body (declared through openapi_extra, so FastAPI does not add it), and the
            # body of every problem+json answer (schemas.problem_responses refers to it by name)
            for model in (BatchRequest, Problem):
                defs = model.model_json_schema(ref_template=REF)
                for name, definition in defs.pop("$defs", {}).items():
                    components.setdefault(name, definition)
                components.setdefault(model.__name__, defs)
            app.openapi_schema = secure_openapi(schema)
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
    logging.getLogger("services").setLevel(settings.log_level.upper())
    return app
