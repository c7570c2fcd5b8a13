"""/v1/jobs/{id}/sr.dcm and /figure.dcm: a succeeded job's result as DICOM (``services.dicom``).

The SR (TID 1500 Measurement Report) and the figure's Secondary Capture belong to the job's study
(from its ``study`` and what was read from the image headers), in two new series, with UIDs derived
from the job: the same instances as those the service stores in the PACS.
"""

from __future__ import annotations

import uuid
from typing import Any

from fastapi import APIRouter
from fastapi.responses import Response

from services.api.deps import AccessDep, SessionDep
from services.api.job_reads import read_succeeded_job
from services.api.schemas import Problem
from services.core.problems import PROBLEM_MEDIA_TYPE
from services.dicom.merge import apply_reads, engine_payload
from services.dicom.results import job_figure_sc, job_sr
from spine_engine.figures import render_figure

router = APIRouter(prefix="/v1/jobs", tags=["dicom"])
DICOM = "application/dicom"


def _responses(what: str) -> dict[int | str, dict[str, Any]]:
    problems: dict[int | str, dict[str, Any]] = {
        s: {"model": Problem, "content": {PROBLEM_MEDIA_TYPE: {}}} for s in (404, 409, 422)
    }
    return {200: {"content": {DICOM: {}}, "description": f"The {what} as a DICOM Part 10 file."}} | problems


@router.get(
    "/{job_id}/sr.dcm",
    response_class=Response,
    summary="A succeeded job's measures as a DICOM SR (TID 1500 Measurement Report)",
    description="Cobb angles (285285000, SCT) with their end and apical vertebrae as finding sites (SNOMED CT, "
    "PS3.16 CID 7603), kyphosis, lordosis, axial rotations and bending in a private scheme (99SPINE) declared in "
    "the SR, each with its SD and whether it is measured or model-based, the landmarks as SCOORD on the source "
    "image when known, and the algorithm's name, version and profile. In a new series of the job's study. "
    "404 for an unknown job; 409 while it has no result.",
    responses=_responses("SR"),
)
def sr_dcm(job_id: uuid.UUID, session: SessionDep, access: AccessDep) -> Response:
    job, result = read_succeeded_job(session, job_id, access, "SR")
    payload = apply_reads(job.payload, job.dicom)
    body = job_sr(job.id, payload, result, job.dicom, job.finished_at)
    return Response(body, media_type=DICOM, headers={"Content-Disposition": f'attachment; filename="{job_id}-sr.dcm"'})


@router.get(
    "/{job_id}/figure.dcm",
    response_class=Response,
    summary="A succeeded job's figure as a DICOM Secondary Capture",
    description="The figure of figure.png as an RGB Secondary Capture in a new series of the job's study. "
    "404 for an unknown job; 409 while it has no result.",
    responses=_responses("figure"),
)
def figure_dcm(job_id: uuid.UUID, session: SessionDep, access: AccessDep) -> Response:
    job, result = read_succeeded_job(session, job_id, access, "figure")
    payload = apply_reads(job.payload, job.dicom)
    body = job_figure_sc(job.id, payload, render_figure(result, engine_payload(payload)), job.finished_at)
    headers = {"Content-Disposition": f'attachment; filename="{job_id}-figure.dcm"'}
    return Response(body, media_type=DICOM, headers=headers)
