"""A finished job → its SR and its figure's Secondary Capture, as Part 10 bytes (what
``GET /v1/jobs/{id}/sr.dcm`` and ``/figure.dcm`` return), and both stored in the PACS in one STOW-RS
request (``store_job_results``).

Both are built from the job's forms (``services.db.job_forms.JobForms``: the payload it ran with,
its DICOM provenance, its result). The study and patient come from the effective payload's ``study``
(filled from the header when one was read: ``StudyIdentity.from_study``); the source images (for
the SR's evidence and the landmarks' SCOORD) from the job's DICOM provenance (SOP Class UID,
series) or, without it, from ``study``'s SOP Instance UIDs, whose SOP class is then unknown: such an
image is not referenced (an SR's image reference needs its Referenced SOP Class UID, Type 1 in the
SOP Instance Reference Macro, PS3.3 Table 10-11) and the landmarks are left out of the SR.

Only a job with the patient's identity is stored in a PACS (``store_job_results``; ``not_storable``): a
job without ``study`` (a CSV or the web page's job) has no study of the patient to store into (its
SR and SC, which ``GET …/sr.dcm`` and ``…/figure.dcm`` still give, open a study of their own whose UID
derives from the job), and a study without a Patient ID (the payload gave none and no film's header was
read: its SOP Instance UID not found, or the PACS down while a complete payload ran without it) would
put instances with an empty Patient ID, Name, Accession Number and Study Date into the patient's study.
"""

from __future__ import annotations

import uuid
from collections.abc import Mapping
from datetime import datetime
from typing import Any

from pydicom.dataset import Dataset

from services.core.config import DicomwebConfig
from services.db.job_forms import JobForms
from spine_client.dicom.errors import DicomError
from spine_engine.figures import render_figure

from .dicomweb import Pacs, part10
from .sc import build_sc
from .sr import SourceImage, StudyIdentity, build_sr

PART10_MEDIA_TYPE = "application/dicom"
"""Media type of a DICOM Part 10 file (RFC 3240; PS3.18 §8.7.3, DICOM media types)."""


NOT_STORABLE = "dicom-no-patient-identity"
"""Problem slug of a job whose results are not stored in the PACS for want of the patient's identity
(``NoPatientIdentity``): on its STOW-RS attempt (``jobs.dicom_stores[].problem_type``), never retried."""


class NoPatientIdentity(DicomError):
    """The job's results are not to be stored in a PACS: it has no study, or its study no Patient ID
    (``not_storable``)."""

    problem = NOT_STORABLE


def not_storable(forms: JobForms) -> str | None:
    """Why the job's SR and SC are not to be stored in a PACS, in plain words, or None when they may be:
    the job has no study (no Study Instance UID to store into), or its study (the payload's with the
    films' header values, ``JobForms.study``) has no Patient ID."""
    study = forms.study or {}
    study_uid = study.get("study_instance_uid")
    if not study_uid:
        return ("not stored in the PACS: the job has no study (its payload names none), so there is no patient's "
                "study to store its SR and figure into")  # fmt: skip
    if not study.get("patient_id"):
        return (f"not stored in the PACS: the job's study {study_uid} has no Patient ID (neither the payload's "
                "study nor a film's header gave one, e.g. the film was not read), and results are stored only "
                "with the patient's identity")  # fmt: skip
    return None


def source_images(payload: Mapping[str, Any], provenance: Mapping[str, Any] | None) -> dict[str, SourceImage]:
    """The radiographs the landmarks were placed on, by view, as far as their SOP class is known."""
    images: dict[str, SourceImage] = {}
    for role in ("pa", "lateral"):
        record = (provenance or {}).get(role)
        if not record or not record.get("sop_class_uid"):
            continue
        view = payload.get(role) or {}
        spacing = view.get("pixel_spacing")
        images[role] = SourceImage(
            sop_instance_uid=record["sop_instance_uid"], sop_class_uid=record["sop_class_uid"],
            series_instance_uid=record.get("series_instance_uid"), study_instance_uid=record.get("study_instance_uid"),
            pixel_spacing=(float(spacing[0]), float(spacing[1])) if spacing else None,
        )  # fmt: skip
    return images


def job_sr_dataset(job_id: uuid.UUID | str, forms: JobForms, finished_at: datetime | None = None) -> Dataset:
    """The job's SR (``sr.build_sr``)."""
    payload, result = forms.effective, forms.result or {}
    identity = StudyIdentity.from_study(forms.study)
    images = source_images(payload, forms.provenance)
    return build_sr(result, payload, job_id, identity, images, content_datetime=finished_at)


def job_sr(job_id: uuid.UUID | str, forms: JobForms, finished_at: datetime | None = None) -> bytes:
    """The job's SR as Part 10 bytes; the same bytes for the same job."""
    return part10(job_sr_dataset(job_id, forms, finished_at))


def job_figure_sc_dataset(job_id: uuid.UUID | str, forms: JobForms, finished_at: datetime | None = None) -> Dataset:
    """The job's figure (``spine_engine.figures``, drawn from the payload it ran with) as a Secondary
    Capture (``sc.build_sc``)."""
    png = render_figure(forms.result or {}, forms.engine)
    return build_sc(png, job_id, StudyIdentity.from_study(forms.study), content_datetime=finished_at)


def job_figure_sc(job_id: uuid.UUID | str, forms: JobForms, finished_at: datetime | None = None) -> bytes:
    """The job's figure as a Secondary Capture, Part 10 bytes."""
    return part10(job_figure_sc_dataset(job_id, forms, finished_at))


def store_job_results(
    config: DicomwebConfig, job_id: uuid.UUID | str, forms: JobForms, finished_at: datetime | None = None
) -> list[str]:
    """Store the job's SR and figure (Secondary Capture) in the PACS in one STOW-RS request (PS3.18
    §10.5); the SOP Instance UIDs it stored. Their UIDs derive from the job, so storing again stores the
    same instances (the PACS replaces or ignores them). Raises ``NoPatientIdentity`` before building
    anything when the job has no study or its study no Patient ID (``not_storable``): nothing is sent;
    ``DicomwebError`` when the PACS is unavailable or refuses, another ``DicomError`` when the result
    cannot be put in DICOM."""
    reason = not_storable(forms)
    if reason is not None:
        raise NoPatientIdentity(reason)
    sr = job_sr_dataset(job_id, forms, finished_at)
    sc = job_figure_sc_dataset(job_id, forms, finished_at)
    with Pacs(config) as pacs:
        return list(pacs.store([sr, sc]).stored)
