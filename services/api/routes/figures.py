"""/v1/jobs/{id}/figure.png and figure.svg: the reconstruction drawn by ``spine_engine.figures``."""

from __future__ import annotations

import uuid
from typing import Any

from fastapi import APIRouter
from fastapi.responses import Response
from sqlalchemy.orm import Session

from services.api.access import Access
from services.api.deps import AccessDep, SessionDep
from services.api.job_reads import read_succeeded_job
from services.api.schemas import Problem
from services.core.problems import PROBLEM_MEDIA_TYPE
from spine_engine.figures import MEDIA_TYPES, FigureFormat, render_figure

router = APIRouter(prefix="/v1/jobs", tags=["figures"])

DESCRIPTION = (
    "PA and lateral views of the reconstruction with the landmarks and their residuals, vertebrae "
    "coloured by lateral bending (u2·Δs), and per-level plots of the strains u and v. "
    "404 for an unknown job; 409 (`job-has-no-result`) while the job is queued or running, or when "
    "it failed or was cancelled."
)


def _responses(fmt: str) -> dict[int | str, dict[str, Any]]:
    problems: dict[int | str, dict[str, Any]] = {
        s: {"model": Problem, "content": {PROBLEM_MEDIA_TYPE: {}}} for s in (404, 409, 422)
    }
    ok: dict[int | str, dict[str, Any]] = {
        200: {"content": {MEDIA_TYPES[fmt]: {}}, "description": f"The figure as {fmt.upper()}."}
    }
    return ok | problems


def _figure(job_id: uuid.UUID, fmt: FigureFormat, session: Session, access: Access) -> Response:
    job, result = read_succeeded_job(session, job_id, access, "figure")
    body = render_figure(result, job.payload, fmt)  # a sync route: this runs in the thread pool
    return Response(body, media_type=MEDIA_TYPES[fmt], headers={"Cache-Control": "private, max-age=3600"})


@router.get(
    "/{job_id}/figure.png",
    response_class=Response,
    summary="Figure of a succeeded job's reconstruction (PNG)",
    description=DESCRIPTION,
    responses=_responses("png"),
)
def figure_png(job_id: uuid.UUID, session: SessionDep, access: AccessDep) -> Response:
    return _figure(job_id, "png", session, access)


@router.get(
    "/{job_id}/figure.svg",
    response_class=Response,
    summary="Figure of a succeeded job's reconstruction (SVG)",
    description=DESCRIPTION,
    responses=_responses("svg"),
)
def figure_svg(job_id: uuid.UUID, session: SessionDep, access: AccessDep) -> Response:
    return _figure(job_id, "svg", session, access)
