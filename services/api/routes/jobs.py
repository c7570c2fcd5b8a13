"""/v1/jobs: create (one or a batch), read, list and cancel jobs; store a job's results in the PACS again."""

from __future__ import annotations

import math
import uuid
from datetime import UTC, datetime, timedelta
from functools import partial
from typing import Annotated, Any

from fastapi import APIRouter, Header, Query, Response
from starlette.exceptions import HTTPException as StarletteHTTPException

from services.api import job_reads
from services.api.admission import admit, split_dicom
from services.api.batch import batch_response
from services.api.deps import AccessDep, BatchBody, IsoDateTime, JobBody, QueueDep, SessionDep, SettingsDep
from services.api.errors import METHOD_GUARD, ProblemError, field_problem
from services.api.schemas import (
    BatchEntry,
    BatchResponse,
    Job,
    JobPage,
    JobStatusName,
    Problem,
    problem_responses,
)
from services.core.problems import problem, validation_problem
from services.core.status import JobStatus
from services.db import dicom_stores
from services.db import jobs as jobs_repo
from services.db.deliveries import deliveries, job_ended
from services.db.job_forms import job_forms
from services.db.jobs import MAX_BATCH_KEY_LENGTH
from services.db.runs import publish
from services.dicom.results import NOT_STORABLE, not_storable
from spine_engine.errors import FieldError, InvalidInput
from spine_engine.models import (
    DICOM_LO_MAX_LENGTH,
    DICOM_SH_MAX_LENGTH,
    DICOM_TEXT_PATTERN,
    DICOM_UID_MAX_LENGTH,
    DICOM_UID_PATTERN,
)

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])

PAYLOAD_BODY = {
    "requestBody": {
        "required": True,
        "content": {"application/json": {"schema": {"$ref": "#/components/schemas/JobPayload"}}},
    }
}
BATCH_BODY = {
    "requestBody": {
        "required": True,
        "content": {"application/json": {"schema": {"$ref": "#/components/schemas/BatchRequest"}}},
    }
}


def _location(job_id: uuid.UUID | str) -> str:
    return f"/v1/jobs/{job_id}"


IDEMPOTENCY_KEY = (
    "Makes a retry safe: the same key (1 to 255 characters, per client) with the same body returns the job it "
    "first made, without making another and whatever the client's queued-job cap; with another body, a 409. "
    "An empty value is refused (422)."
)
BATCH_IDEMPOTENCY_KEY = (
    "Makes a retry safe: payload i is stored under <key>#i (the key 1 to 240 characters, per client), so the same "
    "key and body return the same jobs, without making others and whatever the client's queued-job cap; an entry "
    "whose body changed is a 409 entry. These keys are apart from those of POST /v1/jobs (one keyed <key>#i is "
    "another request). An empty value is refused (422)."
)
REPLAYED_HEADER: dict[str, Any] = {
    "description": "`true` when the answer replays what an earlier request with the same Idempotency-Key made "
    "(nothing new was stored); absent otherwise.",
    "schema": {"type": "string", "enum": ["true"]},
}
SUBMIT_HEADERS: dict[int | str, dict[str, Any]] = {
    202: {
        "description": "Accepted: the queued job, or on a replay the job the Idempotency-Key first made.",
        "headers": {
            "Location": {
                "description": "The job's URL, `/v1/jobs/{id}` (relative to the service), new or replayed.",
                "required": True,
                "schema": {"type": "string", "format": "uri-reference"},
            },
            "Idempotent-Replayed": REPLAYED_HEADER,
        }
    }
}
BATCH_HEADERS: dict[int | str, dict[str, Any]] = {
    200: {
        "description": "One entry per payload, in order: the job (status 202) or the problem with it.",
        "headers": {
            "Idempotent-Replayed": {
                **REPLAYED_HEADER,
                "description": "`true` when the batch was sent with an Idempotency-Key and made no new job: every "
                "accepted entry replays a job an earlier request with that key made; absent otherwise.",
            }
        }
    }
}


@router.post(
    "",
    status_code=202,
    response_model=Job,
    response_model_exclude_unset=True,
    summary="Submit a registration job",
    description="Validates the payload fully, stores a queued job and enqueues it. "
    "With an Idempotency-Key, the same key and body return the same job; another body is a 409.",
    openapi_extra=PAYLOAD_BODY,
    responses={**SUBMIT_HEADERS, **problem_responses(400, 409, 413, 415, 422, 503)},
)
def submit_job(
    body: JobBody,
    response: Response,
    session: SessionDep,
    queue: QueueDep,
    access: AccessDep,
    settings: SettingsDep,
    idempotency_key: Annotated[str | None, Header(min_length=1, max_length=255, description=IDEMPOTENCY_KEY)] = None,
) -> Job:
    try:
        payload, dicom = split_dicom(body)
        admit(payload, settings, session, access.owner, dicom)
    except InvalidInput as exc:
        raise ProblemError(field_problem(exc.errors)) from None
    try:  # the cap (access.admit) is applied after the key's lookup: a replay makes no job and is never a 429
        job, created = jobs_repo.create_job(session, payload, owner=access.owner, client=access.client,
                                            idempotency_key=idempotency_key, on_insert=access.created, dicom=dicom,
                                            admit=partial(access.admit, session))  # fmt: skip
    except jobs_repo.IdempotencyConflict as exc:
        raise ProblemError(
            problem(
                "idempotency-conflict",
                f"the Idempotency-Key {idempotency_key!r} was used for job {exc.job_id} with another body",
                job=_location(exc.job_id),
            )
        ) from None
    if created:
        publish(session, queue, [job.id])
    else:
        access.record(session, "read", [job.id])
    response.headers["Location"] = _location(job.id)
    if not created:
        response.headers["Idempotent-Replayed"] = "true"
    return Job.summary(job)


@router.post(
    "/batch",
    response_model=BatchResponse,
    response_model_exclude_unset=True,
    summary="Submit up to 1,000 jobs at once",
    description="Each payload is validated on its own; the answer has one entry per payload, "
    "in order: the created job (status 202) or the problem with it.",
    openapi_extra=BATCH_BODY,
    responses={**BATCH_HEADERS, **problem_responses(400, 413, 415, 422)},
)
def submit_batch(
    body: BatchBody,
    response: Response,
    session: SessionDep,
    queue: QueueDep,
    access: AccessDep,
    settings: SettingsDep,
    idempotency_key: Annotated[
        str | None, Header(min_length=1, max_length=MAX_BATCH_KEY_LENGTH, description=BATCH_IDEMPOTENCY_KEY)
    ] = None,
) -> BatchResponse:
    if not isinstance(body, dict) or not isinstance(body.get("jobs"), list):
        raise ProblemError(
            validation_problem([FieldError(("jobs",), "the body must be an object with a list 'jobs'", "list_type")])
        )
    payloads: list[Any] = body["jobs"]
    if len(payloads) > settings.batch_max_jobs:
        raise ProblemError(
            problem(
                "payload-too-large",
                f"{len(payloads)} payloads in one batch; at most {settings.batch_max_jobs}",
                limit=settings.batch_max_jobs,
            )
        )
    entries: list[BatchEntry | None] = [None] * len(payloads)
    valid: list[tuple[int, dict[str, Any]]] = []
    for i, payload in enumerate(payloads):
        try:
            admit(payload, settings, session, access.owner)
            valid.append((i, payload))
        except InvalidInput as exc:
            errors = [FieldError(("jobs", i, *e.loc), e.msg, e.type) for e in exc.errors]
            p = field_problem(errors, instance="/v1/jobs/batch")
            entries[i] = BatchEntry(index=i, status=p["status"], problem=Problem.model_validate(p))
    if idempotency_key is not None:  # the cap counts the new jobs only, after the keys' lookup
        answer, replayed_only = batch_response(session, queue, owner=access.owner, client=access.client,
                                               key=idempotency_key,
                                               total=len(payloads), valid=valid, entries=entries,
                                               on_insert=access.created,
                                               admit=partial(access.admit, session))  # fmt: skip
        if replayed_only:
            response.headers["Idempotent-Replayed"] = "true"
        return answer
    access.admit(session, len(valid))
    jobs = jobs_repo.create_jobs(session, [p for _, p in valid], owner=access.owner,
                                 on_insert=access.created) if valid else []  # fmt: skip
    publish(session, queue, [job.id for job in jobs])
    for (i, _), job in zip(valid, jobs, strict=True):
        entries[i] = BatchEntry(index=i, status=202, job=Job.summary(job))
    return BatchResponse(accepted=len(jobs), rejected=len(payloads) - len(jobs), results=entries)


@router.api_route("/batch", methods=["GET", "PUT", "PATCH", "DELETE"], include_in_schema=False, name=METHOD_GUARD)
async def batch_other_methods() -> None:
    """/v1/jobs/batch takes POST only: a 405 (its ``Allow`` as for any 405), not the job route's 422
    for a job id "batch"."""
    raise StarletteHTTPException(405, "Method Not Allowed")


@router.get(
    "",
    response_model=JobPage,
    response_model_exclude_unset=True,
    summary="List jobs, newest first",
    description="Filter by status (repeatable), creation time and the DICOM study (Study Instance UID, accession "
    "number, patient ID: the caller's own jobs only); page with the returned cursor.",
    responses=problem_responses(422),
)
def list_jobs(
    session: SessionDep,
    access: AccessDep,
    status: Annotated[list[JobStatusName] | None, Query(description="Keep jobs in these states.")] = None,
    created_after: Annotated[IsoDateTime | None, Query(description="Created at or after (ISO 8601).")] = None,
    created_before: Annotated[IsoDateTime | None, Query(description="Created before (ISO 8601).")] = None,
    cursor: Annotated[str | None, Query(description="next_cursor of the previous page.")] = None,
    limit: Annotated[int, Query(ge=1, le=500)] = 50,
    study_instance_uid: Annotated[
        str | None,
        Query(max_length=DICOM_UID_MAX_LENGTH, pattern=DICOM_UID_PATTERN,
              description="Jobs of this DICOM Study Instance UID (0020,000D)."),
    ] = None,
    accession_number: Annotated[
        str | None,
        Query(min_length=1, max_length=DICOM_SH_MAX_LENGTH, pattern=DICOM_TEXT_PATTERN,
              description="Jobs of this Accession Number (0008,0050): DICOM SH."),
    ] = None,
    patient_id: Annotated[
        str | None,
        Query(min_length=1, max_length=DICOM_LO_MAX_LENGTH, pattern=DICOM_TEXT_PATTERN,
              description="Jobs of this Patient ID (0010,0020): DICOM LO."),
    ] = None,
) -> JobPage:
    def utc(value: datetime | None) -> datetime | None:
        return value.replace(tzinfo=UTC) if value is not None and value.tzinfo is None else value

    try:
        jobs, next_cursor = jobs_repo.list_jobs(
            session,
            statuses=status or [],
            created_after=utc(created_after),
            created_before=utc(created_before),
            cursor=cursor,
            limit=limit,
            owner=access.owner,
            study_instance_uid=study_instance_uid,
            accession_number=accession_number,
            patient_id=patient_id,
        )
    except jobs_repo.BadCursor as exc:
        raise ProblemError(validation_problem([FieldError(("query", "cursor"), str(exc), "cursor")])) from None
    access.record(session, "list", [j.id for j in jobs])
    return JobPage(jobs=[Job.summary(j) for j in jobs], next_cursor=next_cursor)


@router.get(
    "/{job_id}",
    response_model=Job,
    response_model_exclude_unset=True,
    summary="Read a job",
    responses=problem_responses(404, 422),
)
def read_job(job_id: uuid.UUID, session: SessionDep, access: AccessDep) -> Job:
    job = job_reads.read_job(session, job_id, access)
    return Job.detail(job, deliveries(session, job.id) if job.callback_url is not None else [])


@router.post(
    "/{job_id}/cancel",
    response_model=Job,
    response_model_exclude_unset=True,
    summary="Cancel a queued or running job",
    description="The job ends cancelled and is never run again; cancelling a cancelled job is a no-op. "
    "A job that already succeeded or failed is a 409.",
    responses=problem_responses(404, 409, 422),
)
def cancel_job(
    job_id: uuid.UUID, session: SessionDep, access: AccessDep, queue: QueueDep, settings: SettingsDep
) -> Job:
    try:
        job, cancelled_now = jobs_repo.cancel_job(session, job_id, owner=access.owner)
    except jobs_repo.JobNotFound:
        raise job_reads.not_found(job_id) from None
    except jobs_repo.JobFinished as exc:
        raise ProblemError(
            problem("job-not-cancellable", f"job {job_id} has already {exc.job.status}", job_status=exc.job.status)
        ) from None
    access.record(session, "cancel", [job_id])
    url = job.callback_url
    if url and cancelled_now:  # a repeated cancel sends no second webhook
        job_ended(settings, job.id, "cancelled", url=url, celery=queue)
    return Job.summary(job)


STORE_AGAIN_RESPONSES: dict[int | str, dict[str, Any]] = {
    202: {
        "description": "Accepted: the job as GET /v1/jobs/{id} answers it, its `dicom_stores` ending with the "
        "request's entry (`requested_by`, the new run's first attempt number, due now).",
        "headers": {
            "Location": {
                "description": "The job's URL, `/v1/jobs/{id}` (relative to the service): its attempts' list.",
                "required": True,
                "schema": {"type": "string", "format": "uri-reference"},
            }
        },
    },
    409: {
        "description": "`job-has-no-result` (the job has not succeeded), `dicom-no-patient-identity` (its results "
        "are never stored: no study, or no Patient ID), or `dicom-store-pending` (an attempt is still due or under "
        "way; `Retry-After`: the seconds until it is due, at least 1).",
        "headers": {
            "Retry-After": {
                "description": "With `dicom-store-pending`: the seconds until the attempt is due (at least 1).",
                "schema": {"type": "integer", "minimum": 1},
            }
        },
    },
}


@router.post(
    "/{job_id}/dicom-store",
    status_code=202,
    response_model=Job,
    response_model_exclude_unset=True,
    summary="Store a succeeded job's results in the PACS again",
    description="Publishes a new run of STOW-RS attempts of the job's SR and figure (Secondary Capture): for the "
    "results of a job whose attempts all failed (a PACS outage longer than the retries), or that a PACS lost. "
    "The instances' UIDs derive from the job, so the same instances are stored again. Attempt numbers go on "
    "after the last recorded one, and the run has SPINE_DICOMWEB_MAX_ATTEMPTS attempts from its first; each "
    "is listed in the job's `dicom_stores`. Allowed to whoever may cancel the job (its owner, an admin key), "
    "audited as `store`. 404 `not-found` for a job the key may not see; 404 `dicomweb-not-configured` when the "
    "service has no PACS (SPINE_DICOMWEB_URL unset), 404 `dicomweb-store-disabled` when it stores no results "
    "(SPINE_DICOMWEB_STORE_RESULTS off); 409 `job-has-no-result`, `dicom-no-patient-identity` or "
    "`dicom-store-pending` (with Retry-After).",
    responses={
        202: STORE_AGAIN_RESPONSES[202],
        **problem_responses(404),
        409: {**problem_responses(409)[409], **STORE_AGAIN_RESPONSES[409]},  # the problem with its Retry-After
        **problem_responses(422),
    },
)
def store_job_again(
    job_id: uuid.UUID,
    response: Response,
    session: SessionDep,
    access: AccessDep,
    queue: QueueDep,
    settings: SettingsDep,
) -> Job:
    try:
        job = jobs_repo.get_job(session, job_id, owner=access.owner)
    except jobs_repo.JobNotFound:
        raise job_reads.not_found(job_id) from None
    location = _location(job_id)
    if settings.dicomweb is None:
        raise ProblemError(problem("dicomweb-not-configured", "the service is not connected to a PACS "
                                   "(SPINE_DICOMWEB_URL is unset), so it stores no results there"))  # fmt: skip
    if not settings.stores_dicom_results:  # the worker's test (dicom_tasks.job_succeeded)
        raise ProblemError(problem("dicomweb-store-disabled", "the service does not store results in its PACS "
                                   "(SPINE_DICOMWEB_STORE_RESULTS is off)"))  # fmt: skip
    if job.status != JobStatus.succeeded.value or job.result is None:
        detail = f"job {job_id} is {job.status}: only a succeeded job's results are stored in the PACS"
        raise ProblemError(problem("job-has-no-result", detail, job_status=str(job.status), job=location))
    reason = not_storable(job_forms(job))
    if reason is not None:
        raise ProblemError(problem(NOT_STORABLE, f"job {job_id}'s results are {reason}", job=location))
    sweep_after = timedelta(seconds=settings.dicomweb_sweep_after_s)
    try:
        entry = dicom_stores.request_run(session, job_id, access.client, sweep_after)
    except dicom_stores.StorePending as exc:
        session.rollback()
        wait_s = max(1, math.ceil(exc.wait_s))  # Retry-After: whole seconds (RFC 9110 §10.2.3), at least 1
        when = f"due in about {wait_s} s" if exc.wait_s > 0 else "due now or under way"
        detail = (f"attempt {exc.attempt} to store job {job_id}'s results in the PACS is {when}; ask again once it "
                  "is recorded on the job (dicom_stores)")  # fmt: skip
        raise ProblemError(problem("dicom-store-pending", detail, attempt=exc.attempt, job=location),
                           headers={"Retry-After": str(wait_s)}) from None  # fmt: skip
    access.record(session, "store", [job_id])  # commits the request with its audit row, before publishing
    dicom_stores.publish_run(settings, session, job_id, entry.attempt, queue)
    session.refresh(job)
    response.headers["Location"] = location
    return Job.detail(job, deliveries(session, job.id) if job.callback_url is not None else [])
