"""/v1/jobs/{id}/figure.png and figure.svg: the reconstruction drawn by ``spine_engine.figures``."""

from __future__ import annotations

import uuid
from typing import Any

from fastapi import APIRouter
from fastapi.responses import Response
from sqlalchemy.orm import Session

from services.api import security
from services.api.deps import OwnerDep, SessionDep
from services.api.errors import ProblemError
from services.api.schemas import Problem
from services.db import jobs as jobs_repo
from services.problems import PROBLEM_MEDIA_TYPE, problem
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


def _figure(job_id: uuid.UUID, fmt: FigureFormat, session: Session, owner: str | None) -> Response:
    try:
        job = jobs_repo.get_job(session, job_id, owner=owner)
    except jobs_repo.JobNotFound:
        raise ProblemError(problem("not-found", f"there is no job {job_id}")) from None
    security.record(session, "read", [job.id])
    if job.status != "succeeded" or job.result is None:
        if job.status in ("queued", "running"):
            detail = f"job {job_id} is {job.status}; its figure exists once it has succeeded"
        else:
            detail = f"job {job_id} {'was cancelled' if job.status == 'cancelled' else job.status} and has no result"
        raise ProblemError(problem("job-has-no-result", detail, job_status=str(job.status), job=f"/v1/jobs/{job_id}"))
    result, payload = job.result, job.payload
    body = render_figure(result, payload, fmt)  # a sync route: this runs in the thread pool
    return Response(body, media_type=MEDIA_TYPES[fmt], headers={"Cache-Control": "private, max-age=3600"})


@router.get(
    "/{job_id}/figure.png",
    response_class=Response,
    summary="Figure of a succeeded job's reconstruction (PNG)",
    description=DESCRIPTION,
    responses=_responses("png"),
)
def figure_png(job_id: uuid.UUID, session: SessionDep, owner: OwnerDep) -> Response:
    return _figure(job_id, "png", session, owner)


@router.get(
    "/{job_id}/figure.svg",
    response_class=Response,
    summary="Figure of a succeeded job's reconstruction (SVG)",
    description=DESCRIPTION,
    responses=_responses("svg"),
)
def figure_svg(job_id: uuid.UUID, session: SessionDep, owner: OwnerDep) -> Response:
    return _figure(job_id, "svg", session, owner)
