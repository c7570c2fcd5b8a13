"""A payload that names its images by UID gets their header values from the PACS (by reference).

Rule: a view whose image is named in ``study`` (``pa_sop_instance_uid``, ``lateral_sop_instance_uid``,
with ``study_instance_uid`` and, optionally, ``series_instance_uid`` for the PA) and whose JSON lacks
``pixel_spacing`` or ``patient_orientation`` has that instance's WADO-RS metadata read, and the
header's values merged (``merge.apply_headers``: the payload's explicit values win, conflicts are
recorded). A view that gives both is read too, for the SR's image reference and the study's
attributes (``all_named``), but then a PACS that is down or lacks the image does not fail the job,
which needs nothing from it (the worker runs it without the reads). Errors: ``PacsUnavailable``
(transient: retry), ``InstanceNotFound``, and the header's own (``MissingAttribute``,
``InvalidAttribute``, ``UnsupportedOrientation``).
"""

from __future__ import annotations

from typing import Any

from spine_client.dicom.header import RadiographHeader, ViewRole
from spine_client.dicom.merge import DicomProvenance, apply_headers

from .dicomweb import Pacs


def views_to_fetch(payload: dict[str, Any], *, all_named: bool = False) -> dict[ViewRole, str]:
    """The views (→ SOP Instance UID) whose header is needed: named in ``study`` and missing a value
    (or, with ``all_named``, every view ``study`` names)."""
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
        if all_named or view.get("pixel_spacing") is None or view.get("patient_orientation") is None:
            wanted[role] = str(sop)  # type: ignore[index]
    return wanted


def resolve_by_reference(
    payload: dict[str, Any], pacs: Pacs, *, all_named: bool = False
) -> tuple[dict[str, Any], DicomProvenance | None]:
    """(payload with header values filled in, provenance), or (payload unchanged, None) when nothing is
    fetched. ``all_named``: read every image ``study`` names, even when the payload gives all it needs
    (for the SR's reference to it: its SOP class and series, the patient and study attributes)."""
    wanted = views_to_fetch(payload, all_named=all_named)
    if not wanted:
        return payload, None
    study = payload["study"]
    headers: dict[ViewRole, RadiographHeader] = {}
    for role, sop in wanted.items():
        series = study.get("series_instance_uid") if role == "pa" else None
        headers[role] = pacs.read_header(study["study_instance_uid"], sop, series)
    return apply_headers(payload, headers, source="dicomweb")
