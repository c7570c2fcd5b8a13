"""/v1/jobs/{id}/sr.dcm and /figure.dcm: a succeeded job's result as DICOM (``services.dicom``).

The SR (TID 1500 Measurement Report) and the figure's Secondary Capture belong to the job's study
(from its ``study`` and what was read from the image headers), in two new series, with UIDs derived
from the job: the same instances as those the service stores in the PACS. Each has a strong ``ETag``
(RFC 9110 §8.8.3); a matching ``If-None-Match`` is a 304 (§13.1.2, §15.4.5) before anything is built
(the SR takes about a second of CPU), and the bytes are kept in the app's ``ArtifactCache``
(``services/api/artifacts.py``).
"""

from __future__ import annotations

import uuid

from fastapi import APIRouter
from fastapi.responses import Response

from services.api.artifacts import (
    CONDITIONAL,
    ArtifactCacheDep,
    IfNoneMatchDep,
    artifact_response,
    artifact_responses,
)
from services.api.deps import AccessDep, SessionDep
from services.api.job_reads import read_succeeded_job
from services.api.schemas import BINARY_SCHEMA
from services.db.job_forms import job_forms
from services.dicom.results import PART10_MEDIA_TYPE, job_figure_sc, job_sr

router = APIRouter(prefix="/v1/jobs", tags=["dicom"])


@router.get(
    "/{job_id}/sr.dcm",
    response_class=Response,
    summary="A succeeded job's measures as a DICOM SR (TID 1500 Measurement Report)",
    description="Cobb angles (285285000, SCT) with their end and apical vertebrae as finding sites (SNOMED CT, "
    "PS3.16 CID 7603), kyphosis, lordosis, axial rotations and bending in a private scheme (99SPINE) declared in "
    "the SR, each with its SD and whether it is measured or model-based, the landmarks as SCOORD on the source "
    "image when known, and the algorithm's name, version and profile. In a new series of the job's study. "
    "404 for an unknown job; 409 while it has no result." + CONDITIONAL,
    responses=artifact_responses(PART10_MEDIA_TYPE, "The SR as a DICOM Part 10 file.", BINARY_SCHEMA),
)
def sr_dcm(
    job_id: uuid.UUID, session: SessionDep, access: AccessDep, if_none_match: IfNoneMatchDep, cache: ArtifactCacheDep
) -> Response:
    job, _ = read_succeeded_job(session, job_id, access, "SR")

    def build() -> bytes:  # payload, provenance, result and finished_at: all fixed once the job succeeded
        return job_sr(job.id, job_forms(job), job.finished_at)

    headers = {"Content-Disposition": f'attachment; filename="{job_id}-sr.dcm"'}
    return artifact_response("sr.dcm", job, if_none_match, cache, build, PART10_MEDIA_TYPE, headers)


@router.get(
    "/{job_id}/figure.dcm",
    response_class=Response,
    summary="A succeeded job's figure as a DICOM Secondary Capture",
    description="The figure of figure.png as an RGB Secondary Capture in a new series of the job's study. "
    "404 for an unknown job; 409 while it has no result." + CONDITIONAL,
    responses=artifact_responses(PART10_MEDIA_TYPE, "The figure as a DICOM Part 10 file.", BINARY_SCHEMA),
)
def figure_dcm(
    job_id: uuid.UUID, session: SessionDep, access: AccessDep, if_none_match: IfNoneMatchDep, cache: ArtifactCacheDep
) -> Response:
    job, _ = read_succeeded_job(session, job_id, access, "figure")

    def build() -> bytes:
        return job_figure_sc(job.id, job_forms(job), job.finished_at)

    headers = {"Content-Disposition": f'attachment; filename="{job_id}-figure.dcm"'}
    return artifact_response("figure.dcm", job, if_none_match, cache, build, PART10_MEDIA_TYPE, headers)
