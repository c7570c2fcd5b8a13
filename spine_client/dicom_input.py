"""A job payload from a landmark CSV and the radiographs' DICOM files, read on the client's side
(the ``spine-client[dicom]`` extra: pydicom).

With a DICOM file the CSV's coordinates are image pixels (``units: px``) unless told ``mm``. What the
header gives (``spine_client.dicom.header``) fills the payload where the payload is silent; a payload
value that differs is kept and reported as a conflict (``spine_client.dicom.merge``).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel

from spine_client.contract import JobPayload, LateralView, PAView, Study
from spine_client.dicom.errors import DicomError
from spine_client.dicom.header import RadiographHeader, ViewRole, read_header
from spine_client.dicom.merge import apply_headers
from spine_client.landmarks import (
    LandmarkCsvError,
    LandmarkSource,
    parse_landmark_csv,
    payload_by_reference,
    payload_with_landmarks,
)

__all__ = ["DicomError", "LandmarkCsvError", "contract_payload", "parse_landmark_csv", "payload_by_reference",
           "payload_from_dicom"]  # fmt: skip

_SECTIONS: tuple[tuple[str, type[BaseModel]], ...] = (("pa", PAView), ("lateral", LateralView), ("study", Study))


def contract_payload(payload: Mapping[str, Any]) -> dict[str, Any]:
    """``payload`` without the members, and the view and study fields, that the contract's ``JobPayload``
    (openapi.yaml) does not have: header values the service would refuse stay in the provenance."""
    out = {k: v for k, v in payload.items() if k in JobPayload.model_fields}
    for key, model in _SECTIONS:
        part = out.get(key)
        if isinstance(part, dict):
            out[key] = {k: v for k, v in part.items() if k in model.model_fields}
    return out


def payload_from_dicom(
    landmarks_csv: LandmarkSource,
    pa_dicom: str | Path,
    lateral_dicom: str | Path | None = None,
    *,
    units: Literal["px", "mm"] = "px",
    base: dict[str, Any] | None = None,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """(payload, provenance as JSON) from a landmark CSV and the PA (and lateral) DICOM files.

    ``base`` is a payload whose explicit values win over the headers' (e.g. ``options``, a
    ``boundary``, or a spacing typed in). View fields this version's payload contract does not know
    (``JobPayload`` of openapi.yaml) are left out of the payload and stay in the provenance. Raises
    ``LandmarkCsvError`` and the DICOM layer's ``DicomError`` subclasses (``NotDicom``,
    ``MissingAttribute``, ``InvalidAttribute``, ``UnsupportedOrientation``), each naming the
    attribute by keyword and tag.
    """
    payload = payload_with_landmarks(landmarks_csv, units=units, base=base, lateral=lateral_dicom is not None)
    headers: dict[ViewRole, RadiographHeader] = {"pa": read_header(Path(pa_dicom))}
    if lateral_dicom is not None:
        headers["lateral"] = read_header(Path(lateral_dicom))
    merged, provenance = apply_headers(payload, headers, source="file")
    return contract_payload(merged), provenance.model_dump(mode="json")
