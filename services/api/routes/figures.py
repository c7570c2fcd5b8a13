"""/v1/jobs/{id}/figure.png and figure.svg: the reconstruction drawn by ``spine_engine.figures``, with a
strong ``ETag`` (RFC 9110 §8.8.3), 304 on a matching ``If-None-Match`` (§13.1.2, §15.4.5) before any
drawing, and the bytes kept in the app's ``ArtifactCache`` (``services/api/artifacts.py``)."""

from __future__ import annotations

import uuid

from fastapi import APIRouter
from fastapi.responses import Response
from sqlalchemy.orm import Session

from services.api.access import Access
from services.api.artifacts import (
    CONDITIONAL,
    ArtifactCache,
    ArtifactCacheDep,
    IfNoneMatchDep,
    artifact_response,
    artifact_responses,
)
from services.api.deps import AccessDep, SessionDep
from services.api.job_reads import read_succeeded_job
from services.api.schemas import BINARY_SCHEMA, TEXT_SCHEMA
from services.db.job_forms import job_forms
from spine_engine.figures import MEDIA_TYPES, FigureFormat, render_figure

router = APIRouter(prefix="/v1/jobs", tags=["figures"])

DESCRIPTION = (
    "PA and lateral views of the reconstruction with the landmarks and their residuals, vertebrae "
    "coloured by lateral bending (u2·Δs), and per-level plots of the strains u and v. "
    "404 for an unknown job; 409 (`job-has-no-result`) while the job is queued or running, or when "
    "it failed or was cancelled." + CONDITIONAL
)


def _figure(
    job_id: uuid.UUID, fmt: FigureFormat, session: Session, access: Access, if_none_match: str | None,
    cache: ArtifactCache,
) -> Response:  # fmt: skip
    job, result = read_succeeded_job(session, job_id, access, "figure")
    # a sync route: rendering runs in the thread pool, and only when the client's copy is not current;
    # drawn from the payload the job ran with (header values included), as the SC is
    return artifact_response("figure.png" if fmt == "png" else "figure.svg", job, if_none_match, cache,
                             lambda: render_figure(result, job_forms(job).engine, fmt), MEDIA_TYPES[fmt])  # fmt: skip


@router.get(
    "/{job_id}/figure.png",
    response_class=Response,
    summary="Figure of a succeeded job's reconstruction (PNG)",
    description=DESCRIPTION,
    responses=artifact_responses(MEDIA_TYPES["png"], "The figure as PNG.", BINARY_SCHEMA),
)
def figure_png(
    job_id: uuid.UUID, session: SessionDep, access: AccessDep, if_none_match: IfNoneMatchDep, cache: ArtifactCacheDep
) -> Response:
    return _figure(job_id, "png", session, access, if_none_match, cache)


@router.get(
    "/{job_id}/figure.svg",
    response_class=Response,
    summary="Figure of a succeeded job's reconstruction (SVG)",
    description=DESCRIPTION,
    responses=artifact_responses(MEDIA_TYPES["svg"], "The figure as SVG (an XML text document, UTF-8).", TEXT_SCHEMA),
)
def figure_svg(
    job_id: uuid.UUID, session: SessionDep, access: AccessDep, if_none_match: IfNoneMatchDep, cache: ArtifactCacheDep
) -> Response:
    return _figure(job_id, "svg", session, access, if_none_match, cache)
