"""Typed refusals of a radiograph's header. Each names the DICOM attribute by keyword and tag, in plain words.

The API and worker map them to RFC 9457 problem types by ``problem`` (a stable slug); nothing
here knows HTTP. ``field`` is the JSON path of the payload field the attribute would have
filled (e.g. ``pa.pixel_spacing``), when there is one.
"""

from __future__ import annotations

from typing import Any

from pydicom.datadict import keyword_for_tag, tag_for_keyword
from pydicom.tag import Tag


def attribute_label(keyword: str) -> str:
    """``"PixelSpacing (0028,0030)"``: a DICOM keyword with its tag, as every message names it."""
    tag = tag_for_keyword(keyword)
    if tag is None:
        return keyword
    t = Tag(tag)
    return f"{keyword} ({t.group:04X},{t.element:04X})"


def label_for_tag(tag: int) -> str:
    t = Tag(tag)
    return attribute_label(keyword_for_tag(t) or f"({t.group:04X},{t.element:04X})")


class DicomError(ValueError):
    """Base of every refusal of a DICOM header or of a PACS (``services.dicom.errors``)."""

    problem = "dicom-invalid"

    def __init__(self, message: str, *, attributes: tuple[str, ...] = (), field: str | None = None):
        super().__init__(message)
        self.message = message
        self.attributes = attributes
        """Keywords of the attributes concerned (``PixelSpacing``), empty when the whole file is concerned."""
        self.field = field

    @property
    def labels(self) -> list[str]:
        return [attribute_label(k) for k in self.attributes]

    @property
    def problem_fields(self) -> dict[str, Any]:
        """Extension members of its problem: the attributes by keyword and tag, and the payload field."""
        fields: dict[str, Any] = {"attributes": self.labels}
        if self.field:
            fields["field"] = self.field
        return fields


class NotDicom(DicomError):
    """The bytes are not a DICOM Part 10 file (no ``DICM`` prefix at byte 128, PS3.10 §7.1) nor DICOM JSON."""

    problem = "dicom-not-dicom"


class MissingAttribute(DicomError):
    """An attribute the service needs is absent (or empty) and the payload does not give the value either."""

    problem = "dicom-missing-attribute"


class InvalidAttribute(DicomError):
    """An attribute is present but its value is not usable (wrong count, not positive, not a UID...)."""

    problem = "dicom-invalid-attribute"


class UnsupportedOrientation(DicomError):
    """The image is not a frontal (PA/AP) or lateral projection of a standing spine, or not the view it was given as."""

    problem = "dicom-unsupported-orientation"


class PatientConflict(DicomError):
    """The payload and a film, or the PA and the lateral films, disagree on who the patient is (Patient
    ID, its issuer, the Patient's Name without an agreeing Patient ID) or the payload names another study
    than the PA film's: a study belongs to one patient (PS3.3 §C.7.1.1, §C.7.2.1), so the job is refused,
    never reconstructed nor stored. ``field`` is the first such field (``study.patient_id``)."""

    problem = "dicom-patient-conflict"
