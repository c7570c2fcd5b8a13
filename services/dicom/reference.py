"""A payload that names its images by UID gets their header values from the PACS (by reference).

Rule: a view whose image is named in ``study`` (``pa_sop_instance_uid``, ``lateral_sop_instance_uid``,
with ``study_instance_uid`` and, optionally, ``series_instance_uid`` for the PA) and whose JSON lacks
``pixel_spacing`` or ``patient_orientation`` has that instance's WADO-RS metadata read, and the
header's values merged (``merge.apply_headers``: the payload's explicit values win, conflicts are
recorded). A view that gives both is not fetched: a PACS that is down does not fail a job that
needs nothing from it. Errors: ``PacsUnavailable`` (transient: retry), ``InstanceNotFound``, and the
header's own (``MissingAttribute``, ``InvalidAttribute``, ``UnsupportedOrientation``).
"""

from __future__ import annotations

from typing import Any

from .dicomweb import Pacs
from .header import RadiographHeader, ViewRole
from .merge import DicomProvenance, apply_headers


def views_to_fetch(payload: dict[str, Any]) -> dict[ViewRole, str]:
    """The views (→ SOP Instance UID) whose header is needed: named in ``study`` and missing a value."""
    study = payload.get("study") or {}
    wanted: dict[ViewRole, str] = {}
    for role in ("pa", "lateral"):
        sop = study.get(f"{role}_sop_instance_uid")
        view = payload.get(role)
        if not sop or not study.get("study_instance_uid"):
            continue
        if role == "lateral" and view is None:
            continue
        view = view or {}
        if view.get("pixel_spacing") is None or view.get("patient_orientation") is None:
            wanted[role] = str(sop)  # type: ignore[index]
    return wanted


def resolve_by_reference(payload: dict[str, Any], pacs: Pacs) -> tuple[dict[str, Any], DicomProvenance | None]:
    """(payload with header values filled in, provenance), or (payload unchanged, None) when nothing is fetched."""
    wanted = views_to_fetch(payload)
    if not wanted:
        return payload, None
    study = payload["study"]
    headers: dict[ViewRole, RadiographHeader] = {}
    for role, sop in wanted.items():
        series = study.get("series_instance_uid") if role == "pa" else None
        headers[role] = pacs.read_header(study["study_instance_uid"], sop, series)
    return apply_headers(payload, headers, source="dicomweb")
