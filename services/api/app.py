"""The FastAPI application: ``create_app(settings)`` (``uvicorn --factory services.api.app:create_app``)."""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi
from prometheus_client import CollectorRegistry

from services.api.errors import install_error_handlers
from services.api.metrics import HTTPMetrics, JobStateCollector
from services.api.routes import figures, health, jobs
from services.api.web import mount_web
from services.jobqueue import make_celery
from services.problems import PROBLEM_BASE
from services.settings import Settings, get_settings
from spine_engine.models import JobPayload

DESCRIPTION = (
    "3D reconstruction of a scoliotic spine from landmarks on radiographs (discrete Cosserat rod "
    "registration, Li et al., CAIP 2009), as jobs: POST a payload, poll the job for its result.\n\n"
    "Errors are RFC 9457 `application/problem+json` bodies whose `type` is a stable URI under "
    f"`{PROBLEM_BASE}`; validation problems list every offending field with its JSON path in `errors`."
)


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        yield

    app = FastAPI(
        title="Spine reconstruction service",
        version="1.0.0",
        description=DESCRIPTION,
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.celery = make_celery(settings)
    registry = CollectorRegistry()
    registry.register(JobStateCollector(settings, app.state.celery))
    app.state.registry = registry
    install_error_handlers(app)
    app.include_router(jobs.router)
    app.include_router(health.router)
    app.include_router(figures.router)
    mount_web(app)
    app.add_middleware(HTTPMetrics, registry=registry)

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
            defs = JobPayload.model_json_schema(mode="validation", ref_template="#/components/schemas/{model}")
            components = schema.setdefault("components", {}).setdefault("schemas", {})
            for name, definition in defs.pop("$defs", {}).items():
                components.setdefault(name, definition)
            components["JobPayload"] = defs
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
    logging.getLogger("services").setLevel(settings.log_level.upper())
    return app
