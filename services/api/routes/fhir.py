"""/v1/jobs/{id}/fhir: a succeeded job's clinical measures as a FHIR R4 Bundle of Observations, with a
strong ``ETag`` (RFC 9110 §8.8.3), 304 on a matching ``If-None-Match`` (§13.1.2, §15.4.5), and the bytes
kept in the app's ``ArtifactCache`` (``services/api/artifacts.py``)."""

from __future__ import annotations

import json
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
from services.api.deps import AccessDep, SessionDep, SettingsDep
from services.api.job_reads import read_succeeded_job
from services.db.job_forms import job_forms
from services.db.models import utcnow
from services.fhir.export import observation_bundle

router = APIRouter(prefix="/v1/jobs", tags=["interoperability"])

FHIR_MEDIA_TYPE = "application/fhir+json"

DESCRIPTION = (
    "A FHIR R4 Bundle (type `collection`) of Observations (status `final`, category `imaging`, UCUM `deg`): "
    "the Cobb angle of every frontal curve (end and apex vertebrae, convexity, apical axial rotation and plane "
    "of maximum curvature as components), thoracic kyphosis T4–T12 and T5–T12, lumbar lordosis L1–L5, and the "
    'apical axial rotation of the major curve. `code` keeps its text and is coded: SNOMED CT 285285000 "Cobb '
    'angle" for the frontal Cobb angles, the service\'s local code system (docs/fhir.md) for the '
    "measures no standard code names. With a `study` in the payload, each Observation's `derivedFrom` names the "
    "ImagingStudy by its DICOM Study Instance UID. With a patient ID (typed in or read from the image header), "
    "`subject` is the Patient by identifier, its `system` the film's issuer of Patient ID when it names it "
    "by a URI (Issuer of Patient ID Qualifiers Sequence (0010,0024): ISO OID → urn:oid:, UUID → urn:uuid:, "
    "URI as is), else the setting "
    "`SPINE_PATIENT_ID_SYSTEM`; the issuer's local name is `identifier.assigner.display`. "
    "`effectiveDateTime` is the study's date, else the PA film's (or the lateral's) acquisition date, else the "
    "job's creation. 404 for an unknown job; 409 "
    "(`job-has-no-result`) unless the job succeeded." + CONDITIONAL
)


def film_datetime(provenance: dict[str, object] | None) -> str | None:
    """The PA film's date-time read from its header (``ViewProvenance.film_datetime``), else the lateral's."""
    for role in ("pa", "lateral"):
        view = (provenance or {}).get(role)
        if isinstance(view, dict) and isinstance(view.get("film_datetime"), str):
            return str(view["film_datetime"])
    return None


@router.get(
    "/{job_id}/fhir",
    response_class=Response,
    summary="A succeeded job's measures as a FHIR R4 Bundle",
    description=DESCRIPTION,
    responses=artifact_responses(
        FHIR_MEDIA_TYPE, "The Bundle.", {"type": "object", "description": "FHIR R4 Bundle (collection)"}
    ),
)
def job_fhir(
    job_id: uuid.UUID,
    session: SessionDep,
    access: AccessDep,
    if_none_match: IfNoneMatchDep,
    cache: ArtifactCacheDep,
    settings: SettingsDep,
) -> Response:
    job, result = read_succeeded_job(session, job_id, access, "FHIR export")

    def build() -> bytes:
        study = job_forms(job).study
        bundle = observation_bundle(
            job.id,
            result,
            finished_at=job.finished_at or utcnow(),
            study=study,
            created_at=job.created_at,
            film_datetime=film_datetime(job.dicom),
            patient_id_system=settings.patient_id_system,
        )
        return json.dumps(bundle, ensure_ascii=False).encode()

    return artifact_response("fhir", job, if_none_match, cache, build, FHIR_MEDIA_TYPE,
                             variant=f"patient_id_system={settings.patient_id_system or ''}")  # fmt: skip
