"""Response and request models of the HTTP API (the job payload itself is spine_engine's)."""

from __future__ import annotations

import uuid
from collections.abc import Sequence
from datetime import date, datetime
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from services.core.problems import PROBLEM_MEDIA_TYPE
from services.core.status import JobStatus
from services.db.dicom_stores import DicomStoreAttempt
from services.db.jobs import MAX_PATIENT_JOBS, job_members
from services.db.models import Job as JobRow
from services.db.models import UtcTimestamp, WebhookDelivery
from services.dicom.dicomweb import StudyImage
from services.webhooks.schemas import WebhookDeliveryAttempt
from spine_client.dicom.merge import DicomProvenance
from spine_engine.models import RegistrationResult, Study, extensible

JobStatusName = JobStatus
"""The job status of the contract (one enum: ``services.core.status.JobStatus``)."""


class FieldProblem(BaseModel):
    path: str = Field(description="JSON path of the offending field, e.g. pa.landmarks[3].level.")
    loc: list[str | int] = Field(description="The same path as a list of keys and indexes.")
    msg: str
    type: str = Field(description="Machine-readable kind of the field error.")


class Problem(BaseModel):
    """RFC 9457 problem details (application/problem+json)."""

    model_config = ConfigDict(extra="allow")

    type: str = Field(description="Stable URI of the kind of problem.")
    title: str
    status: int
    detail: str
    instance: str | None = None
    errors: list[FieldProblem] | None = Field(
        None, description="Validation problems: every offending field with its JSON path."
    )


PROBLEM_SCHEMA_REF = "#/components/schemas/Problem"

BINARY_SCHEMA: dict[str, str] = {"type": "string", "format": "binary"}
"""The schema of a body of bytes (a PNG, a DICOM Part 10 file): what client generators read as a file."""

TEXT_SCHEMA: dict[str, str] = {"type": "string"}
"""The schema of a text body (an SVG document: UTF-8 XML)."""


def problem_responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """A route's OpenAPI ``responses`` for these statuses: each a ``Problem`` as application/problem+json,
    its only media type (no error is answered as application/json). The app's ``openapi()`` puts the
    ``Problem`` schema in the components."""
    return {s: {"content": {PROBLEM_MEDIA_TYPE: {"schema": {"$ref": PROBLEM_SCHEMA_REF}}}} for s in statuses}


# Built from the row by ``Job.summary`` (POST, the list, a batch, cancel) or ``Job.detail`` (GET by id).
# A summary leaves the members only GET /v1/jobs/{id} has unset, and every route answering with jobs
# declares ``response_model_exclude_unset=True``: an unset member is absent from the JSON, as is any
# member of a stored result or error that the stored JSON lacks. (The docstring is the contract's text.)
class Job(BaseModel):
    """A job and, once finished, its result or error."""

    id: uuid.UUID
    status: JobStatusName
    owner: str | None = Field(
        description="The client whose job it is (the name of the client API key that created it); null for a job an "
        "admin key created, which every admin key sees, or one made before API keys existed."
    )
    created_at: UtcTimestamp
    started_at: UtcTimestamp | None
    finished_at: UtcTimestamp | None
    attempts: int = Field(description="Runs started so far (a worker lost mid-fit counts one).")
    engine_version: str | None
    result: RegistrationResult | None = Field(description="The reconstruction, when succeeded.")
    error: Problem | None = Field(description="Why the job failed, when failed.")
    payload: dict[str, Any] | None = Field(None, description="The payload as posted; only in GET /v1/jobs/{id}.")
    study: Study | None = Field(
        None,
        description="The job's DICOM identifiers: the payload's, completed by the values read from the images' "
        "headers (listed in `dicom.study`); null without.",
    )
    deliveries: list[WebhookDeliveryAttempt] | None = Field(
        None, description="Webhook delivery attempts to the payload's callback_url; only in GET /v1/jobs/{id}."
    )
    dicom: DicomProvenance | None = Field(
        None,
        description="What the DICOM layer read from the images' headers (per view: each attribute and what it "
        "filled) and every conflict with the payload; null when no header was read. Only in GET /v1/jobs/{id}.",
    )
    dicom_stores: list[DicomStoreAttempt] | None = Field(
        None, description="STOW-RS attempts of the job's SR and figure to the PACS; only in GET /v1/jobs/{id}."
    )

    @classmethod
    def summary(cls, row: JobRow) -> Job:
        """The job without the members only GET /v1/jobs/{id} has (they stay unset)."""
        return cls(**job_members(row))

    @classmethod
    def detail(cls, row: JobRow, deliveries: Sequence[WebhookDelivery]) -> Job:
        """The job as GET /v1/jobs/{id} answers it: with the payload, DICOM provenance, STOW-RS and
        webhook delivery attempts (``deliveries``: the rows of ``services.db.deliveries.deliveries``)."""
        return cls(
            **job_members(row),
            payload=row.payload,
            dicom=row.dicom,
            dicom_stores=row.dicom_stores or [],
            deliveries=[WebhookDeliveryAttempt.model_validate(d, from_attributes=True) for d in deliveries],
        )


class JobPage(BaseModel):
    jobs: list[Job]
    next_cursor: str | None = Field(description="Pass as ?cursor= for the next (older) page; null at the end.")


class BatchRequest(BaseModel):
    jobs: list[Any] = Field(
        description="Up to SPINE_BATCH_MAX_JOBS (1000) job payloads (JobPayload), each validated on its own: "
        "an entry that is not a valid payload (not even an object) gets its own 422 problem in the answer."
    )


class BatchEntry(BaseModel):
    index: int = Field(description="Position of the payload in the request.")
    status: int = Field(description="202 when a job was created, else the problem's status.")
    job: Job | None = None
    problem: Problem | None = None


class BatchResponse(BaseModel):
    accepted: int
    rejected: int
    results: list[BatchEntry]


class Health(BaseModel):
    status: str
    checks: dict[str, str] = Field(default_factory=dict)


class PacsStatus(BaseModel):
    """Whether the service is connected to a PACS (``SPINE_DICOMWEB_URL``): the page shows "Open from the
    PACS" only then."""

    configured: bool = Field(description="True when SPINE_DICOMWEB_URL is set (reachability is not checked).")


class PacsStudyImages(BaseModel):
    study_instance_uid: str
    images: list[StudyImage] = Field(
        description="The study's images (DX, CR and other radiograph modalities, and any instance with Rows and "
        "Columns; no SR or other non-image), sorted by series number then instance number."
    )


# ------------------------------------------------------------------ a patient's follow-up


MeasureName = Literal["major_cobb", "minor_cobb", "kyphosis_t4_t12", "lordosis_l1_l5", "apex_axial_rotation"]
MEASURES: tuple[MeasureName, ...] = (
    "major_cobb",
    "minor_cobb",
    "kyphosis_t4_t12",
    "lordosis_l1_l5",
    "apex_axial_rotation",
)


class MeasureValue(BaseModel):
    value_deg: float = Field(description="The measure, degrees.")
    sd_deg: float | None = Field(None, description="1 SD of the measure, degrees; null when the job has none.")
    levels: str | None = Field(
        None, description="For a Cobb angle its end vertebrae and apex (e.g. 'T5–T12, apex T8'; 'L4–L5, apex "
        "L4/L5 disc' for a curve of one segment); for the apex rotation the apex vertebra."
    )  # fmt: skip
    model_estimate: str | None = Field(
        None, description="Why the value comes from the spine model's prior rather than the films (the job's "
        "fit.unreliable or fit.assumed, in words, as the SR and FHIR export say it); null when the films determine "
        "it. A change involving such a value compares model estimates."
    )  # fmt: skip


class Visit(BaseModel):
    job_id: uuid.UUID
    study_date: date | None = Field(
        description="Study Date (0008,0020); null when neither payload nor header gives it."
    )
    study_instance_uid: str | None = None
    accession_number: str | None = None
    finished_at: datetime | None = None
    major_cobb: MeasureValue | None = Field(
        None,
        description="The major (largest) frontal Cobb angle; for a spine whose curves are all below the 10° "
        "reporting threshold, its largest frontal angle (measures.largest_cobb; levels say 'below 10°'), so that a "
        "mild curve is followed. Null for a result stored before largest_cobb existed and without a curve.",
    )
    minor_cobb: MeasureValue | None = Field(None, description="The largest other frontal curve; null with one curve.")
    kyphosis_t4_t12: MeasureValue = Field(description="Thoracic kyphosis T4–T12.")
    lordosis_l1_l5: MeasureValue = Field(description="Lumbar lordosis L1–L5.")
    apex_axial_rotation: MeasureValue | None = Field(
        None, description="Axial rotation of the major curve's apex vertebra (SD: that vertebra's)."
    )


class Change(BaseModel):
    measure: Annotated[str, extensible(MeasureName)] = Field(
        description="The measure compared, a Visit member's name (an extensible list: a newer service may follow "
        "others)."
    )
    from_job: uuid.UUID
    to_job: uuid.UUID
    from_date: date
    to_date: date
    change_deg: float = Field(description="Later minus earlier value, degrees.")
    combined_sd_deg: float | None = Field(description="√(sd₁² + sd₂²), degrees; null when a visit has no SD.")
    threshold_deg: float = Field(description="max(5°, 1.96 × combined SD): |change| must exceed it to be flagged.")
    flagged: bool = Field(description="|change| exceeds both 5° and 1.96 × the combined SD.")
    decided_by: Literal["convention_5deg", "combined_sd"] = Field(
        description="The larger threshold, the one that decided: the 5° convention or 1.96 × the combined SD."
    )


class PatientMeasures(BaseModel):
    patient_id: str = Field(
        description="The Patient ID asked for, without leading and trailing spaces (padding in a DICOM LO: "
        "'P ' and 'P' are one patient)."
    )
    visits: list[Visit] = Field(
        description="One visit per study: the caller's succeeded jobs of the patient, one per Study Instance UID "
        "(the study's latest succeeded job by finished_at, then created_at, stands for it: a film read again, e.g. "
        "with corrected landmarks, is not a second visit); a job without a Study Instance UID is a visit of its own. "
        "By study date (visits without one last, by creation)."
    )
    changes: list[Change] = Field(
        description="Per measure, the change between consecutive visits that have a study date and the measure."
    )
    rule: str = Field(description="The flagging rule in words.")
    older_visits_left_out: bool = Field(
        False,
        description=f"True when the patient has more succeeded jobs than a follow-up reads ({MAX_PATIENT_JOBS:,}): "
        f"the newest {MAX_PATIENT_JOBS:,} are kept, and the visits of older ones are not in visits or changes.",
    )
