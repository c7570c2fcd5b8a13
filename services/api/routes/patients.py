"""/v1/patients/{patient_id}/measures: a patient's follow-up over time, from the caller's succeeded jobs.

A scoliosis patient is filmed every 4–12 months and the question is whether the curve progresses.
Each visit is one study of the patient (Patient ID (0010,0020), compared without its padding spaces: the
payload's ``study`` or the header the DICOM layer read): its succeeded jobs of one Study Instance UID
are one visit, the latest (by finished_at, then created_at) standing for it, since a film read again
(landmarks corrected and sent anew) is the same visit, not a progression over 0 days; a job without a
Study Instance UID is a visit of its own. Visits are ordered by their study date (Study Date
(0008,0020), same sources). Only the newest ``MAX_PATIENT_JOBS`` succeeded jobs are read, and the
answer says when older ones were left out. Between
consecutive visits with a study date, each measure's change Δ = m₂ − m₁ (degrees) is flagged when

    |Δ| > 5°                      (the convention for a progressing Cobb angle: the inter-observer
                                   variability of manual Cobb measurement is about 5°, Morrissy et al.,
                                   J Bone Joint Surg Am 1990;72:320–327), and
    |Δ| > 1.96 · √(sd₁² + sd₂²)    (the two visits' 95 % interval of the difference, their SDs being
                                   independent),

i.e. when |Δ| exceeds the larger of the two thresholds; ``decided_by`` names that larger one (the rule
that decided the flag, either way). Without an SD on either visit only the 5° rule applies.
"""

from __future__ import annotations

import itertools
import math
from datetime import date, datetime
from typing import Annotated, Any

from fastapi import APIRouter, Path
from starlette.convertors import PathConvertor, register_url_convertor

from services.api.deps import AccessDep, SessionDep
from services.api.schemas import (
    MEASURES,
    Change,
    MeasureName,
    MeasureValue,
    PatientMeasures,
    Visit,
    problem_responses,
)
from services.core.estimates import model_estimate_reason
from services.db import jobs as jobs_repo
from services.db.job_forms import job_study
from services.db.models import Job
from spine_engine.levels import apex_words
from spine_engine.models import (
    DICOM_LO_MAX_LENGTH,
    DICOM_TEXT_PATTERN,
    CobbCurve,
    LargestCobbAngle,
    RegistrationResult,
    read_study_date,
)


class AnyTextConvertor(PathConvertor):
    """A path segment holding any text, slashes and line breaks included: Starlette's ``path`` stops
    at a line break (its ``.``), which made a Patient ID with one a 404 for no route instead of the
    422 naming the parameter."""

    regex = r"[\s\S]*"


register_url_convertor("anytext", AnyTextConvertor())
router = APIRouter(prefix="/v1/patients", tags=["jobs"])

CONVENTION_DEG = 5.0
"""A change of a Cobb angle is called progression only beyond 5° (inter-observer variability)."""
Z95 = 1.96
"""Two-sided 95 % quantile of the normal distribution."""

RULE = (
    "A change between consecutive visits is flagged when it exceeds both 5° (the convention for progression) "
    "and 1.96 × √(sd₁² + sd₂²) (the 95 % interval of the difference); decided_by names the larger threshold."
)


def _study(job: Job) -> dict[str, Any]:
    """The job's study with the header's values (``services.db.job_forms``, the one owner of a job's forms)."""
    return job_study(job) or {}


def _cobb(curve: CobbCurve | None, estimate: str | None) -> MeasureValue | None:
    if curve is None:
        return None
    levels = f"{curve.upper}–{curve.lower}, apex {apex_words(curve.apex, curve.apical_disc)}"
    return MeasureValue(value_deg=curve.angle_deg, sd_deg=curve.angle_sd_deg, levels=levels, model_estimate=estimate)


def _below_threshold(largest: LargestCobbAngle | None, estimate: str | None) -> MeasureValue | None:
    """The largest frontal angle of a spine whose curves are all below the reporting threshold."""
    if largest is None or largest.reported_as_curve:
        return None
    levels = f"{largest.upper}–{largest.lower}, below 10°"
    return MeasureValue(value_deg=largest.angle_deg, sd_deg=largest.angle_sd_deg, levels=levels,
                        model_estimate=estimate)  # fmt: skip


def visit(job: Job) -> Visit:
    """One visit: the job's study identifiers and its measures from the stored result, each with the
    reason it is a model estimate when it is one (``services.core.estimates``)."""
    result = RegistrationResult.model_validate(job.result)
    fit = result.fit.model_dump(mode="json")
    cobb = model_estimate_reason(fit, "cobb")
    measures = result.measures
    curves = sorted(measures.cobb, key=lambda c: -c.angle_deg)
    major = next((c for c in curves if c.major), None)
    minor = next((c for c in curves if c is not major), None)
    rotation = None
    if major:
        apex = next((v for v in result.vertebrae if v.level == major.apex), None)
        rotation = MeasureValue(value_deg=major.apex_axial_rotation_deg,
                                sd_deg=apex.axial_rotation_sd_deg if apex else None, levels=major.apex,
                                model_estimate=model_estimate_reason(fit, "axial_rotation", major.apex))  # fmt: skip
    study = _study(job)
    return Visit(
        job_id=job.id,
        study_date=read_study_date(study.get("study_date")),
        study_instance_uid=study.get("study_instance_uid"),
        accession_number=study.get("accession_number"),
        finished_at=job.finished_at,
        major_cobb=_cobb(major, cobb) or _below_threshold(measures.largest_cobb, cobb),
        minor_cobb=_cobb(minor, cobb),
        kyphosis_t4_t12=MeasureValue(value_deg=measures.thoracic_kyphosis_t4_t12_deg,
                                     sd_deg=measures.thoracic_kyphosis_t4_t12_sd_deg,
                                     model_estimate=model_estimate_reason(fit, "kyphosis")),
        lordosis_l1_l5=MeasureValue(value_deg=measures.lumbar_lordosis_l1_l5_deg,
                                    sd_deg=measures.lumbar_lordosis_l1_l5_sd_deg,
                                    model_estimate=model_estimate_reason(fit, "lordosis")),
        apex_axial_rotation=rotation,
    )  # fmt: skip


def change(name: MeasureName, earlier: Visit, later: Visit) -> Change | None:
    """The flagged-or-not change of one measure between two dated visits (None when either lacks it)."""
    a: MeasureValue | None = getattr(earlier, name)
    b: MeasureValue | None = getattr(later, name)
    if a is None or b is None or earlier.study_date is None or later.study_date is None:
        return None
    delta = b.value_deg - a.value_deg
    sd = math.hypot(a.sd_deg, b.sd_deg) if a.sd_deg is not None and b.sd_deg is not None else None
    by_sd = Z95 * sd if sd is not None else 0.0
    threshold = max(CONVENTION_DEG, by_sd)
    return Change(
        measure=name, from_job=earlier.job_id, to_job=later.job_id, from_date=earlier.study_date,
        to_date=later.study_date, change_deg=delta, combined_sd_deg=sd, threshold_deg=threshold,
        flagged=abs(delta) > threshold, decided_by="combined_sd" if by_sd > CONVENTION_DEG else "convention_5deg",
    )  # fmt: skip


def one_job_per_study(jobs: list[Job]) -> list[Job]:
    """The jobs that stand for a visit, in the order given: of the jobs of one Study Instance UID, the
    latest to finish (then the latest made); every job without a Study Instance UID."""
    uids = [_study(job).get("study_instance_uid") for job in jobs]
    latest: dict[str, Job] = {}
    for job, uid in zip(jobs, uids, strict=True):
        if isinstance(uid, str) and uid and (uid not in latest or _recency(job) > _recency(latest[uid])):
            latest[uid] = job
    return [job for job, uid in zip(jobs, uids, strict=True)
            if not (isinstance(uid, str) and uid) or latest[uid] is job]  # fmt: skip


def _recency(job: Job) -> tuple[datetime, datetime]:
    finished = job.finished_at or job.created_at
    return finished, job.created_at


def follow_up(patient_id: str, jobs: list[Job], *, older_left_out: bool = False) -> PatientMeasures:
    """The visits (one per study: ``one_job_per_study``) by study date (undated last, in the order of
    ``jobs``, creation) and the changes between dated ones."""
    visits = sorted((visit(j) for j in one_job_per_study(jobs)),
                    key=lambda v: (v.study_date is None, v.study_date or date.min))  # fmt: skip
    dated = [v for v in visits if v.study_date is not None]
    changes = [c for name in MEASURES for a, b in itertools.pairwise(dated) if (c := change(name, a, b))]
    return PatientMeasures(patient_id=patient_id, visits=visits, changes=changes, rule=RULE,
                           older_visits_left_out=older_left_out)  # fmt: skip


@router.get(
    "/{patient_id:anytext}/measures",
    response_model=PatientMeasures,
    summary="A patient's measures over time (follow-up)",
    description="The visits of this Patient ID (0010,0020; leading and trailing spaces are padding, not part of "
    "the ID) in the caller's succeeded jobs, by Study Date (0008,0020): one visit per Study Instance UID, the "
    "study's latest succeeded job (by finished_at, then created_at) standing for it, so that a film read again is "
    "not a second visit; a job without a Study Instance UID is a visit of its own. Each visit has its major and "
    "minor Cobb angles, kyphosis T4–T12, lordosis L1–L5 and the major curve's apex axial rotation, with their SDs; "
    "each change between consecutive visits is flagged when it exceeds both 5° and 1.96 × the combined SD "
    f"√(sd₁² + sd₂²), saying which rule decided. The newest {jobs_repo.MAX_PATIENT_JOBS:,} succeeded jobs are read; "
    "older_visits_left_out says when older ones were left out. Only the caller's jobs (an admin key: every job); "
    "a patient without any is an empty list, not a 404 (the answer says nothing of other clients' patients).",
    responses=problem_responses(422),
)
def patient_measures(
    patient_id: Annotated[
        str,
        Path(min_length=1, max_length=DICOM_LO_MAX_LENGTH, pattern=DICOM_TEXT_PATTERN,
             description="Patient ID (0010,0020): DICOM LO."),
    ],
    session: SessionDep,
    access: AccessDep,
) -> PatientMeasures:
    patient_id = jobs_repo.dicom_identifier(patient_id)
    jobs, older_left_out = jobs_repo.succeeded_jobs_of_patient(session, patient_id, owner=access.owner)
    answer = follow_up(patient_id, jobs, older_left_out=older_left_out)
    access.record(session, "list", [v.job_id for v in answer.visits])
    return answer
