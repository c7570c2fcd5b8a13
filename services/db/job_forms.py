"""The forms of one job, built in one place from its row and used by every consumer (the API's job
views, figures, SR, Secondary Capture, FHIR, the STOW-RS task, webhooks, the worker's run).

A job's row keeps the payload as posted (``jobs.payload``) and, apart, what the DICOM layer read from
the images' headers (``jobs.dicom``: ``spine_client.dicom.merge.DicomProvenance`` as JSON, each value
with the JSON path it fills and whether the job uses it). From these:

- ``effective``: the payload the job ran with, the posted payload with every header value marked
  ``used`` put back at its JSON path (``apply_reads``). It may hold header values that the engine's
  contract has no field for (a view's ``acquisition`` on an older engine, the study's
  ``patient_sex``...): the SR and SC read them.
- ``engine``: ``effective`` cut to the fields of ``spine_engine.models`` (``engine_payload``): what
  ``spine_engine.register`` and ``spine_engine.figures.render_figure`` take, and the job's ``study``
  as the API and webhooks show it.
- ``result``: the result as stored (``RegistrationResult`` as JSON, what the SR, SC, figures and FHIR
  read; the API's job views validate it into the model).

All are deterministic functions of the row: an artifact rebuilt from them is the same bytes.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import Any

from spine_engine.models import JobPayload, LateralView, PAView, Study, read_study_date

from .models import Job

_ENGINE_MODELS = (("pa", PAView), ("lateral", LateralView), ("study", Study))


def apply_reads(payload: Mapping[str, Any], provenance: Mapping[str, Any] | None) -> dict[str, Any]:
    """``payload`` (as posted) with every header value the provenance (``DicomProvenance`` as JSON)
    marks as used put back at its JSON path."""
    merged: dict[str, Any] = copy.deepcopy(dict(payload))
    if not provenance:
        return merged
    reads = list(provenance.get("study") or [])
    for role in ("pa", "lateral"):
        reads += list((provenance.get(role) or {}).get("read") or [])
    for read in reads:
        if not read.get("used"):
            continue
        *parents, leaf = str(read["field"]).split(".")
        target = merged
        for key in parents:
            target = target.setdefault(key, {})
        target[leaf] = copy.deepcopy(read["value"])
    return merged


def stored_study(study: Mapping[str, Any]) -> dict[str, Any]:
    """A study as a job stored it, in the contract's forms of today: a ``study_date`` posted before
    ``Study`` took only YYYY-MM-DD is its day (``read_study_date``: as the API then read it) or left
    out when it names none, and a Patient ID of spaces only, an empty DICOM value, is left out."""
    out = dict(study)
    if "study_date" in out:
        day = read_study_date(out["study_date"])
        if day is None:
            del out["study_date"]
        else:
            out["study_date"] = day.isoformat()
    if isinstance(out.get("patient_id"), str) and not out["patient_id"].strip():
        del out["patient_id"]
    return out


def engine_payload(payload: Mapping[str, Any]) -> dict[str, Any]:
    """``payload`` without the view and study fields the installed ``spine_engine.models`` does not
    know: the header's extra values stay in the provenance (and in ``effective``), and the engine's
    strict models do not refuse them; its study as ``stored_study`` reads it."""
    out = dict(payload)
    for key, model in _ENGINE_MODELS:
        part = out.get(key)
        if isinstance(part, dict):
            out[key] = {k: v for k, v in part.items() if k in model.model_fields}
    if isinstance(out.get("study"), dict):
        out["study"] = stored_study(out["study"])
    for key in list(out):
        if key not in JobPayload.model_fields:
            del out[key]
    return out


@dataclass(frozen=True)
class JobForms:
    """One job's payload as posted, its DICOM provenance and result, and the forms derived from them."""

    posted: Mapping[str, Any]
    provenance: Mapping[str, Any] | None
    result: dict[str, Any] | None

    @cached_property
    def effective(self) -> dict[str, Any]:
        return apply_reads(self.posted, self.provenance)

    @cached_property
    def engine(self) -> dict[str, Any]:
        return engine_payload(self.effective)

    @property
    def study(self) -> dict[str, Any] | None:
        """The study with the header's values (``effective``), every field the SR and SC copy."""
        study = self.effective.get("study")
        return stored_study(study) if isinstance(study, dict) else None

    @property
    def engine_study(self) -> dict[str, Any] | None:
        """The study as the contract's ``Study`` (the API's and webhooks' ``study``)."""
        study = self.engine.get("study")
        return study if isinstance(study, dict) else None


def job_forms(job: Job) -> JobForms:
    """The forms of the job in ``job``'s row."""
    posted = job.payload if isinstance(job.payload, dict) else {}
    return JobForms(posted=posted, provenance=job.dicom, result=job.result)


def job_study(job: Job) -> dict[str, Any] | None:
    """The ``study`` member of the job's API and webhook views: ``JobForms.engine_study``, read without
    copying the whole payload (a list page builds it for each of up to 500 jobs)."""
    posted = job.payload.get("study") if isinstance(job.payload, dict) else None
    reads = (job.dicom or {}).get("study") or []
    if not any(read.get("used") for read in reads):
        return stored_study(posted) if isinstance(posted, dict) else None
    return JobForms(posted={"study": posted or {}}, provenance={"study": reads}, result=None).engine_study
