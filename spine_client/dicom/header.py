"""A radiograph's DICOM header → the view fields the service needs (``RadiographHeader``).

Only the header is read (``stop_before_pixels``): the photometric interpretation (MONOCHROME1 or 2),
the bit depth and the pixel data's encoding do not matter, so no Transfer Syntax with a readable
header is refused (explicit and implicit VR little endian, big endian, any compressed syntax).

Pixel spacing follows PS3.3 §10.7.1.1 (Basic Pixel Spacing Calibration Macro) and §C.8.11.4
(DX Detector Module, Imager Pixel Spacing) exactly as Cornerstone3D reads them:
``packages/metadata/src/utilities/getPixelSpacingInformation.ts`` (cornerstonejs/cornerstone3D,
commit 7034957b10f5e91ad8f4d7978591ef688e262d26, functions ``getERMF``,
``calculateRadiographicPixelSpacing`` and ``getPixelSpacingInformation``). For a projection
radiograph SOP class (CR, DX, MG, IO, XA, RF, the same list as Cornerstone3D):

1. Pixel Spacing (0028,0030) with Pixel Spacing Calibration Type (0028,0A02) ``GEOMETRY`` →
   Pixel Spacing, Cornerstone type ``ERMF``; with ``FIDUCIAL`` → Pixel Spacing, type ``Calibrated``.
2. Else Imager Pixel Spacing (0018,1164) present: the magnification M is, in this order,
   Estimated Radiographic Magnification Factor (0018,1114) when > 1; SID/SOD when SOD < SID
   (Distance Source to Detector (0018,1110) over Distance Source to Patient (0018,1111), or
   Distance Source to Entrance (0040,0306) when (0018,1111) is absent; with both, their mid-plane, the
   SOD the view's acquisition carries, where Cornerstone3D takes (0018,1111): the engine multiplies
   calibrated mm by that acquisition's SID/SOD, so both must be one ratio); "already applied" when
   Imager Pixel Spacing > Pixel Spacing. Then spacing = Imager Pixel Spacing / M (type ``ERMF``),
   or Pixel Spacing when already applied (type ``ERMF``), else Pixel Spacing or Imager Pixel
   Spacing unchanged (type ``Proj``: millimetres at the detector).
3. Else Pixel Spacing alone, type ``Unknown``.

Other SOP classes (e.g. Secondary Capture) give Pixel Spacing with Cornerstone's type ``""``
(not applicable), mapped to ``unknown``. The service's ``pixel_spacing_calibration`` (openapi.yaml)
is: ``calibrated`` (Cornerstone ``Calibrated`` or ``ERMF``: millimetres in the patient, at the
plane the magnification refers to), ``projection`` (``Proj`` from Pixel Spacing: equal to, or
standing for, the imager's spacing, millimetres at the detector), ``detector`` (``Proj`` from
Imager Pixel Spacing alone), ``unknown``.

Acquisition geometry (the view's ``acquisition``): ``distance_source_to_detector_mm`` = SID
(0018,1110). ``distance_source_to_patient_mm`` is the source to the spine's mid-plane (DESIGN.md),
which no attribute states: PS3.3 §C.8.11.7 (DX Positioning Module) defines Distance Source to
Patient (0018,1111) as "from source to the table, support or bucky side that is closest to the
Imaging Subject" (the detector-side surface of the body) and Distance Source to Entrance
(0040,0306) (PS3.3 §C.8.7.8, X-Ray Acquisition Dose Module) as to the surface of the patient
closest to the source; the spine lies between them. Conversion, in this order:
(a) SID / ERMF when ERMF (0018,1114) is given: ERMF is defined as SID/SOD of the object of
interest (PS3.3 §C.8.11.7), so its SOD is the one wanted;
(b) (DSE + DSP) / 2 when both are given: the body's mid-plane between its two surfaces;
(c) DSP alone, or DSE alone, unchanged (as Cornerstone3D does), recorded as an approximation: for a
    typical adult trunk 200–300 mm deep the spine lies 100–150 mm from either surface, so at SID
    1800 mm the magnification SID/SOD is off by about 0.5–1 % either way.
A geometry value (SID, DSP, DSE, ERMF) that is no distance or ratio (not one finite number, or not a
positive one: a writer's 0 for "not known", say) is left out with a warning (``GEOMETRY_KEYWORDS``), as
the page leaves it out (``web/src/dicom.ts`` ``readAcquisition``) and as Weasis ignores a magnification
that is not positive.
``magnification`` = ERMF when given. ``image_size`` = [Columns (0028,0011), Rows (0028,0010)] in px,
or those times the column and row spacing in mm (``view_acquisition``: the view's units decide): with
SID and SOD but no central ray the engine puts the ray at the image's centre (the pixel data's extent,
PS3.3 §C.7.6.3; SID is measured to the detector's centre, PS3.3 §C.8.7.6).
``projection_model`` = "perspective" for a projection radiograph's SOP class (CR, DX and the
other X-ray image storage classes, ``PROJECTION_RADIOGRAPH_SOP_CLASSES``): its image is cast from a point
source, so without SID or SOD the engine takes full-spine radiography's; not for millimetres already
in the patient plane whose magnification the header does not give (``calibrated`` without ERMF).

Orientation: Patient Orientation (0020,0020) (PS3.3 §C.7.6.1.1.1: the patient directions of the
image's rows and columns, the first letter of a combination being the main one); without it View
Position (0018,5101) (PS3.3 §C.8.11.5, defined terms AP, PA, LL, RL, ...) gives the conventional
display: AP/PA → ``["L","F"]``, LL/RL → ``["A","F"]`` (the project's defaults, DESIGN.md), marked
as assumed; oblique (RLO, LLO...) and decubitus views are refused, and so is an orientation whose
plane is not frontal (x, z) or sagittal (y, z).
"""

from __future__ import annotations

import io
import math
import re
import string
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from datetime import date, timezone
from pathlib import Path
from typing import Any, Literal

import pydicom
from pydicom.dataset import Dataset
from pydicom.errors import InvalidDicomError

from spine_client.dicom.errors import (
    InvalidAttribute,
    MissingAttribute,
    NotDicom,
    UnsupportedOrientation,
    attribute_label,
)

from .datetimes import (
    UTC_OFFSET_FORM,
    is_dicom_time,
    iso_offset,
    iso_time,
    parse_utc_offset,
    split_dt,
    utc_offset_problem,
)

Calibration = Literal["calibrated", "projection", "detector", "unknown"]
ViewRole = Literal["pa", "lateral"]

PROJECTION_RADIOGRAPH_SOP_CLASSES = frozenset({
    "1.2.840.10008.5.1.4.1.1.1",  # CR Image Storage
    "1.2.840.10008.5.1.4.1.1.1.1",  # Digital X-Ray Image Storage - For Presentation
    "1.2.840.10008.5.1.4.1.1.1.1.1",  # Digital X-Ray Image Storage - For Processing
    "1.2.840.10008.5.1.4.1.1.1.2",  # Digital Mammography X-Ray Image Storage - For Presentation
    "1.2.840.10008.5.1.4.1.1.1.2.1",  # Digital Mammography X-Ray Image Storage - For Processing
    "1.2.840.10008.5.1.4.1.1.1.3",  # Digital Intra-Oral X-Ray Image Storage - For Presentation
    "1.2.840.10008.5.1.4.1.1.1.3.1",  # Digital Intra-Oral X-Ray Image Storage - For Processing
    "1.2.840.10008.5.1.4.1.1.12.1",  # X-Ray Angiographic Image Storage
    "1.2.840.10008.5.1.4.1.1.12.1.1",  # Enhanced XA Image Storage
    "1.2.840.10008.5.1.4.1.1.12.2",  # X-Ray Radiofluoroscopic Image Storage
    "1.2.840.10008.5.1.4.1.1.12.2.1",  # Enhanced XRF Image Storage
    "1.2.840.10008.5.1.4.1.1.12.3",  # X-Ray Angiographic Bi-plane Image Storage (retired)
})  # fmt: skip
"""The SOP classes Cornerstone3D treats as projection radiographs (``projectionRadiographSOPClassUIDs``)."""

UID_PATTERN = re.compile(r"^(0|[1-9][0-9]*)(\.(0|[1-9][0-9]*))*$")
"""PS3.5 §9.1: digits in dot-separated components, no leading zero in a component, at most 64 characters."""

SPACING_EQUAL_RTOL = 1e-6
"""Relative tolerance of 'Pixel Spacing equals Imager Pixel Spacing' (DS values are decimal strings,
PS3.5 §6.2: at most 16 characters, so equal spacings print equal and differ by rounding only)."""

_AXIS = {"L": 0, "R": 0, "A": 1, "P": 1, "H": 2, "F": 2}
_VIEW_POSITION_ORIENTATION: dict[str, tuple[ViewRole, tuple[str, str]]] = {
    "PA": ("pa", ("L", "F")),
    "AP": ("pa", ("L", "F")),
    "LL": ("lateral", ("A", "F")),
    "RL": ("lateral", ("A", "F")),
}
"""View Position (0018,5101) → (view, conventional display orientation) (DESIGN.md defaults)."""


@dataclass(frozen=True)
class Acquisition:
    """The view's acquisition geometry from the header (openapi.yaml ``Acquisition``), mm and ratios."""

    magnification: float | None = None
    distance_source_to_detector_mm: float | None = None
    distance_source_to_patient_mm: float | None = None

    def as_payload(self) -> dict[str, float]:
        return {k: v for k, v in self.__dict__.items() if v is not None}


UNIVERSAL_ENTITY_ID_TYPES = ("DNS", "EUI64", "ISO", "URI", "UUID", "X400", "X500")
"""Universal Entity ID Type (0040,0033) defined terms (PS3.3 §10.14, HL7v2 Hierarchic Designator Macro), the
contract's ``UniversalEntityIdType`` (spine_engine.models; a test holds the two equal)."""


@dataclass(frozen=True)
class PatientIdIssuer:
    """Who issued the film's Patient ID (PS3.3 §C.7.1.1, Patient Module; openapi.yaml ``PatientIdIssuer``):
    Issuer of Patient ID (0010,0021), a local name (LO), and from the one item of Issuer of Patient ID
    Qualifiers Sequence (0010,0024) the issuer's Universal Entity ID (0040,0032) and its Type (0040,0033)."""

    issuer_of_patient_id: str | None = None
    universal_entity_id: str | None = None
    universal_entity_id_type: str | None = None

    def as_payload(self) -> dict[str, str]:
        """The study's ``patient_id_issuer`` member: the values known."""
        return {k: v for k, v in self.__dict__.items() if v is not None}


@dataclass(frozen=True)
class RadiographHeader:
    """What the service reads from one radiograph's header. Every value's source attribute is in
    ``sources`` (payload field name → ``"Keyword (gggg,eeee)"`` or a rule naming several)."""

    sop_class_uid: str | None
    sop_instance_uid: str
    series_instance_uid: str | None
    study_instance_uid: str
    patient_id: str | None
    patient_name: str | None
    accession_number: str | None
    study_date: date | None
    study_time: str | None
    timezone_offset_from_utc: str | None
    """Timezone Offset From UTC (0008,0201) as DICOM writes it (``+0100``): the zone of the film's DA and
    TM values, its Study Date and Time among them (PS3.3 §C.12.1.1.8). None when absent or not an offset
    (``datetimes.utc_offset_problem``: ignored, with a warning)."""
    film_datetime: str | None
    """When the film was taken, ISO 8601 (date, or date and time to the second, a leap second written
    ``:60``, ``datetimes``): Acquisition DateTime (0008,002A), else Acquisition Date (0008,0022) with
    Acquisition Time (0008,0032), else Content Date (0008,0023) with Content Time (0008,0033) (PS3.3
    C.7.6.1 General Image Module). The time only with its zone: the DT's own offset, else Timezone Offset
    From UTC (0008,0201) (PS3.3 §C.12.1.1.8, Note 2); an offset that is not one counts as absent. None
    when none is given."""
    study_id: str | None
    patient_birth_date: str | None
    patient_sex: str | None
    referring_physician_name: str | None
    patient_id_issuer: PatientIdIssuer | None
    """Study time (TM), study ID, birth date (DA) and sex (M, F, O), referring physician (PN) as the
    header writes them, and the issuer of its Patient ID (``_patient_id_issuer``): copied into the SR and SC
    (General Study and Patient Modules, PS3.3 §C.7.2.1, §C.7.1.1)."""
    modality: str | None
    rows: int | None
    columns: int | None
    photometric_interpretation: str | None
    pixel_spacing: tuple[float, float] | None
    """[row spacing, column spacing] in mm as Cornerstone3D computes it (module docstring)."""
    pixel_spacing_calibration: Calibration | None
    cornerstone_calibration_type: str | None
    """Cornerstone3D's ``CalibrationTypes`` value ("Calibrated", "ERMF", "Proj", "Unknown", "")."""
    patient_orientation: tuple[str, str] | None
    orientation_assumed: bool
    """True when the orientation comes from View Position's conventional display, not (0020,0020)."""
    view: ViewRole | None
    """``pa`` for a frontal image (rows and columns in the x–z plane), ``lateral`` for a sagittal one."""
    acquisition: Acquisition
    sources: Mapping[str, str] = field(default_factory=dict)
    warnings: tuple[str, ...] = ()

    def view_acquisition(self, units: str, pixel_spacing: Any) -> dict[str, Any]:
        """The view's ``acquisition`` fields from this header (``Acquisition.as_payload``) and
        ``image_size`` [columns, rows] in the view's ``units``: [Columns, Rows] in px; in mm
        [Columns · column spacing, Rows · row spacing] with ``pixel_spacing`` [row, column] the
        spacing the view uses (none in mm: no image_size). Each key's source is in ``sources``
        (``acquisition.<key>``)."""
        fields: dict[str, Any] = dict(self.acquisition.as_payload())
        if "acquisition.projection_model" in self.sources:
            fields["projection_model"] = "perspective"
        if self.rows is None or self.columns is None:
            return fields
        if units == "px":
            fields["image_size"] = [float(self.columns), float(self.rows)]
        elif pixel_spacing is not None:
            row_spacing, column_spacing = (float(v) for v in pixel_spacing)
            fields["image_size"] = [self.columns * column_spacing, self.rows * row_spacing]
        return fields

    def require_spacing(self, json_path: str) -> tuple[float, float]:
        if self.pixel_spacing is None:
            raise MissingAttribute(
                f"the image has neither {attribute_label('PixelSpacing')} nor {attribute_label('ImagerPixelSpacing')}, "
                f"and the payload gives no {json_path}: the landmarks in px cannot be converted to millimetres",
                attributes=("PixelSpacing", "ImagerPixelSpacing"),
                field=json_path,
            )
        return self.pixel_spacing

    def require_orientation(self, json_path: str) -> tuple[str, str]:
        if self.patient_orientation is None:
            raise MissingAttribute(
                f"the image has neither {attribute_label('PatientOrientation')} nor a frontal or lateral "
                f"{attribute_label('ViewPosition')}, and the payload gives no {json_path}",
                attributes=("PatientOrientation", "ViewPosition"),
                field=json_path,
            )
        return self.patient_orientation


# ------------------------------------------------------------------ reading


def load_dataset(source: str | Path | bytes | io.BufferedIOBase | Dataset | Mapping[str, Any]) -> Dataset:
    """A header as a pydicom Dataset from a file path, Part 10 bytes or stream, a Dataset, or
    DICOM JSON (PS3.18 §F.2, what WADO-RS metadata returns). Raises ``NotDicom``."""
    if isinstance(source, Dataset):
        return source
    if isinstance(source, Mapping):
        try:
            return Dataset.from_json(dict(source), bulk_data_uri_handler=lambda *_: None)
        except Exception as exc:  # pydicom raises ValueError/TypeError/KeyError on malformed JSON
            raise NotDicom(f"the DICOM JSON object is not valid: {exc}") from None
    if isinstance(source, bytes):
        source = io.BytesIO(source)
    try:
        return pydicom.dcmread(source, stop_before_pixels=True)
    except InvalidDicomError:
        name = source if isinstance(source, (str, Path)) else "the data"
        raise NotDicom(
            f"{name} is not a DICOM file: a DICOM Part 10 file has the four bytes 'DICM' after a 128-byte "
            "preamble (PS3.10 §7.1)"
        ) from None
    except (OSError, EOFError, ValueError, KeyError, TypeError) as exc:
        if isinstance(exc, FileNotFoundError | IsADirectoryError | PermissionError):
            raise
        raise NotDicom(f"the DICOM file could not be read: {exc}") from None


def check_uid(value: str, keyword: str) -> str:
    """``value`` if it is a DICOM UID (PS3.5 §9.1), else ``InvalidAttribute`` naming ``keyword``."""
    value = str(value).strip("\0 ")
    if len(value) > 64 or not UID_PATTERN.match(value):
        raise InvalidAttribute(
            f"{attribute_label(keyword)} is {value!r}, not a DICOM UID: digits in dot-separated components "
            "without leading zeros, at most 64 characters (PS3.5 §9.1)",
            attributes=(keyword,),
        )
    return value


TEXT_PADDING = string.whitespace + "\0"
"""Trailing and leading characters a text value is read without: the spaces DICOM pads with (PS3.5
§6.2), and the NULs some writers pad with in their place."""


def _text(ds: Dataset, keyword: str) -> str | None:
    """The attribute's value as text without its padding, None when absent or empty. ``InvalidAttribute``
    when it holds several values (every attribute read so is of VM 1, PS3.6 §6: a list's text would
    become the patient's ID), or when a control character is left inside: none of the VRs read here
    (AE, CS, DA, DT, LO, PN, SH, TM, UI) holds one but ESC (PS3.5 §6.2), which the character set's
    decoding removes; such a value could be neither matched nor stored (PostgreSQL's text holds no NUL)."""
    value = ds.get(keyword)
    if value is None:
        return None
    if isinstance(value, pydicom.multival.MultiValue | list | tuple):
        if len(value) > 1:
            raise InvalidAttribute(
                f"{attribute_label(keyword)} holds {len(value)} values {[str(v) for v in value][:4]}: it has one "
                "(VM 1, PS3.6 §6)",
                attributes=(keyword,),
            )
        value = value[0] if value else ""
    text = str(value).strip(TEXT_PADDING)
    bad = next((ch for ch in text if ord(ch) < 32 or ord(ch) == 127), None)
    if bad is not None:
        raise InvalidAttribute(
            f"{attribute_label(keyword)} is {text!r}, which holds the control character {bad!r}: a DICOM "
            "text value holds none (PS3.5 §6.2)",
            attributes=(keyword,),
        )
    return text or None


IDENTIFIER_MAX_LENGTH = {"PatientID": 64, "AccessionNumber": 16}
"""Longest value of the patient and study identifiers a job carries (PS3.5 §6.2: LO 64 and SH 16
characters), as the contract's ``study`` takes them. The Patient's Name is a PN: ``person_name_problem``."""

PN_GROUP_MAX_LENGTH = 64
PN_GROUPS = ("alphabetic", "ideographic", "phonetic")
"""A PN (PS3.5 §6.2, Table 6.2-1, and §6.2.1) is up to three component groups separated by ``=``, in this
order, each of at most 64 characters and of up to five components separated by ``^`` (family, given,
middle, prefix, suffix). So a name holds at most 3 × 64 characters and two ``=``."""


def person_name_problem(text: str) -> str | None:
    """Why ``text`` is not a PN as DICOM writes it (``PN_GROUPS``), None when it is. Characters, not
    bytes, are counted, as PS3.5 §6.2 counts them (a name in ideographs takes more bytes in UTF-8)."""
    groups = text.split("=")
    if len(groups) > len(PN_GROUPS):
        return (f"has {len(groups)} component groups separated by '=': a PN has at most 3, alphabetic, "
                "ideographic and phonetic (PS3.5 §6.2.1)")  # fmt: skip
    for name, group in zip(PN_GROUPS, groups, strict=False):
        if len(group) > PN_GROUP_MAX_LENGTH:
            return (f"has {len(group)} characters in its {name} component group: a PN holds at most "
                    f"{PN_GROUP_MAX_LENGTH} per component group (PS3.5 §6.2, Table 6.2-1)")  # fmt: skip
        if group.count("^") > 4:
            return (f"has {group.count('^') + 1} components in its {name} component group: a PN has at most 5, "
                    "family^given^middle^prefix^suffix (PS3.5 §6.2.1)")  # fmt: skip
    return None


def _quoted(text: str) -> str:
    """``text`` as a message quotes a value: its first 80 characters, and its length when longer."""
    return f"{text[:80]!r}… ({len(text)} characters)" if len(text) > 80 else repr(text)


def _identifier(ds: Dataset, keyword: str) -> str | None:
    """``_text`` of one of ``IDENTIFIER_MAX_LENGTH``'s attributes; ``InvalidAttribute`` when longer than its
    VR allows (a non-conformant header: the job could neither carry it nor write it back)."""
    text = _text(ds, keyword)
    limit = IDENTIFIER_MAX_LENGTH[keyword]
    if text is not None and len(text) > limit:
        raise InvalidAttribute(
            f"{attribute_label(keyword)} is {text[:80]!r}{'…' if len(text) > 80 else ''} ({len(text)} characters): "
            f"its VR holds at most {limit} (PS3.5 §6.2)",
            attributes=(keyword,),
        )
    return text


def _patient_name(ds: Dataset) -> str | None:
    """Patient's Name (0010,0010) as ``_text`` reads it; ``InvalidAttribute`` naming it when it is not a PN
    (``person_name_problem``). Refused, not dropped: the SR and SC go back into the patient's record with
    the film's identity (Patient Module, PS3.3 §C.7.1.1), and a name left out or cut would no longer be the
    film's (a PACS reconciles a study's objects by patient ID and name)."""
    text = _text(ds, "PatientName")
    problem = person_name_problem(text) if text is not None else None
    if text is not None and problem is not None:
        raise InvalidAttribute(f"{attribute_label('PatientName')} {_quoted(text)} {problem}",
                               attributes=("PatientName",))  # fmt: skip
    return text


def _optional_text(ds: Dataset, keyword: str) -> str | None:
    """``_text`` of a value the header reads only when well formed (dates, times, the SR's identity
    values): None where ``_text`` refuses it."""
    try:
        return _text(ds, keyword)
    except InvalidAttribute:
        return None


IDENTITY_VALUES: dict[str, tuple[str, Callable[[str], bool]]] = {
    "study_time": ("a DICOM TM time HHMMSS.FFFFFF, seconds 00 to 60 (PS3.5 §6.2)", is_dicom_time),
    "study_id": ("a DICOM SH of at most 16 characters (PS3.5 §6.2)", lambda v: 0 < len(v) <= 16),
    "patient_birth_date": ("a DICOM DA date YYYYMMDD (PS3.5 §6.2)",
                           lambda v: len(v) == 8 and v.isdigit() and 1 <= int(v[4:6]) <= 12 and 1 <= int(v[6:]) <= 31),
    "patient_sex": ("M, F or O (PS3.3 §C.7.1.1)", lambda v: v in ("M", "F", "O")),
    "referring_physician_name": ("a DICOM PN: at most 3 component groups of at most 64 characters and 5 components "
                                 "each (PS3.5 §6.2, §6.2.1)", lambda v: bool(v) and person_name_problem(v) is None),
    "timezone_offset_from_utc": (f"a DICOM UTC offset {UTC_OFFSET_FORM}", lambda v: utc_offset_problem(v) is None),
}  # fmt: skip
"""The study block's values the contract's ``Study`` has no field for: what each must be to go into
the SR and SC as the header had it (the study time and its zone also date the FHIR Observations)."""


def identity_problem(key: str, value: Any) -> str | None:
    """Why ``value`` cannot be the study's ``key`` (one of ``IDENTITY_VALUES``), or None when it can."""
    what, ok = IDENTITY_VALUES[key]
    if not isinstance(value, str) or "\\" in value or any(ord(ch) < 32 for ch in value) or not ok(value):
        return f"must be {what}"
    return None



def _identity(ds: Dataset, keyword: str, key: str) -> str | None:
    """A header's study or patient value for the SR and SC, None when absent or not as DICOM writes it."""
    value = _optional_text(ds, keyword)
    return value if value is not None and identity_problem(key, value) is None else None


LO_MAX_LENGTH = 64
"""Longest Long String (LO), in characters (PS3.5 §6.2, Table 6.2-1): Issuer of Patient ID (0010,0021)."""


def _patient_id_issuer(ds: Dataset) -> tuple[PatientIdIssuer | None, tuple[str, ...]]:
    """(``RadiographHeader.patient_id_issuer``, warnings): Issuer of Patient ID (0010,0021), LO (at most 64
    characters, PS3.5 §6.2), and the Universal Entity ID (0040,0032) with its Type (0040,0033), one of
    ``UNIVERSAL_ENTITY_ID_TYPES``, from Issuer of Patient ID Qualifiers Sequence (0010,0024), of which "only a
    single Item is permitted" (PS3.3 §C.7.1.1, Table C.7-1). Each is Type 3 and changes no measurement: a value
    that is not as the standard writes it (too long, a control character, an ID with a backslash, which the
    contract's DICOM text refuses, an ID without its Type or of a Type that is no defined term, a sequence of
    several items) is left out with a warning naming it, never a
    refusal, as the film's other identity values only the SR, SC and FHIR carry (docs/dicom.md, "Text
    values")."""
    warnings: list[str] = []
    local_label = attribute_label("IssuerOfPatientID")
    try:
        local = _text(ds, "IssuerOfPatientID")
    except InvalidAttribute as exc:
        local, warnings = None, [f"{exc.message}: left out"]
    if local is not None and len(local) > LO_MAX_LENGTH:
        warnings.append(f"{local_label} {_quoted(local)} is longer than an LO holds (64 characters, PS3.5 §6.2): "
                        "left out")  # fmt: skip
        local = None
    universal: str | None = None
    kind: str | None = None
    items = ds.get("IssuerOfPatientIDQualifiersSequence") or []
    seq_label = attribute_label("IssuerOfPatientIDQualifiersSequence")
    if len(items) > 1:
        warnings.append(f"{seq_label} holds {len(items)} items: a single one is permitted (PS3.3 §C.7.1.1): "
                        "its issuer is left out")  # fmt: skip
    elif len(items) == 1:
        try:
            universal = _text(items[0], "UniversalEntityID")
            kind = _text(items[0], "UniversalEntityIDType")
        except InvalidAttribute as exc:
            universal, kind = None, None
            warnings.append(f"{seq_label}: {exc.message}: its issuer is left out")
        if universal is not None and "\\" in universal:
            warnings.append(f"{seq_label}: {attribute_label('UniversalEntityID')} {_quoted(universal)} holds a "
                            "backslash, which the contract's DICOM text holds none of: left out")  # fmt: skip
            universal, kind = None, None
        elif universal is not None and kind not in UNIVERSAL_ENTITY_ID_TYPES:
            what = f"Type {kind!r} is not one of {', '.join(UNIVERSAL_ENTITY_ID_TYPES)}" if kind else "has no Type"
            warnings.append(f"{seq_label}: {attribute_label('UniversalEntityID')} {_quoted(universal)} {what} "
                            f"({attribute_label('UniversalEntityIDType')}, PS3.3 §10.14): left out")  # fmt: skip
            universal, kind = None, None
        elif universal is None:
            kind = None
    if local is None and universal is None:
        return None, tuple(warnings)
    return PatientIdIssuer(local, universal, kind), tuple(warnings)


def _uid(ds: Dataset, keyword: str, *, required: bool) -> str | None:
    value = _text(ds, keyword)
    if value is None:
        if required:
            raise MissingAttribute(f"the image has no {attribute_label(keyword)}", attributes=(keyword,))
        return None
    return check_uid(value, keyword)


def _numbers(ds: Dataset, keyword: str, count: int) -> tuple[float, ...] | None:
    """An attribute's ``count`` finite decimal numbers, None when absent or empty; ``InvalidAttribute`` when
    they are not ``count`` finite numbers."""
    if keyword not in ds or ds[keyword].value in (None, "", []):
        return None
    raw = ds[keyword].value
    values = list(raw) if isinstance(raw, list | tuple | pydicom.multival.MultiValue) else [raw]
    try:
        numbers = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        raise InvalidAttribute(
            f"{attribute_label(keyword)} is {raw!r}, not {count} decimal number(s)", attributes=(keyword,)
        ) from None
    if len(numbers) != count:
        raise InvalidAttribute(
            f"{attribute_label(keyword)} has {len(numbers)} value(s), expected {count}", attributes=(keyword,)
        )
    if not all(math.isfinite(n) for n in numbers):
        raise InvalidAttribute(f"{attribute_label(keyword)} is {list(numbers)}: not finite", attributes=(keyword,))
    return numbers


def _positive_numbers(ds: Dataset, keyword: str, count: int) -> tuple[float, ...] | None:
    numbers = _numbers(ds, keyword, count)
    if numbers is not None and not all(n > 0 for n in numbers):
        raise InvalidAttribute(
            f"{attribute_label(keyword)} is {list(numbers)}: every value must be a positive number",
            attributes=(keyword,),
        )
    return numbers


GEOMETRY_KEYWORDS = (
    "EstimatedRadiographicMagnificationFactor",
    "DistanceSourceToDetector",
    "DistanceSourceToPatient",
    "DistanceSourceToEntrance",
)
"""The attributes of the acquisition geometry, read by ``_geometry_reading``."""


def _geometry_reading(ds: Dataset, keyword: str) -> tuple[float | None, str | None]:
    """A geometry attribute's one value (``GEOMETRY_KEYWORDS``) and, when the header gives one that is no
    distance or ratio (not one finite number, or not a positive one), None and the warning that says it is
    left out (module docstring)."""
    try:
        numbers = _numbers(ds, keyword, 1)
    except InvalidAttribute as exc:
        return None, f"{exc.message}: left out"
    if numbers is None or numbers[0] > 0:
        return (None if numbers is None else numbers[0]), None
    what = "a ratio" if keyword == "EstimatedRadiographicMagnificationFactor" else "a distance"
    return None, f"{attribute_label(keyword)} is {numbers[0]:g}: not {what}, left out"


def _geometry_number(ds: Dataset, keyword: str) -> float | None:
    """``_geometry_reading``'s value."""
    return _geometry_reading(ds, keyword)[0]


def _geometry_warnings(ds: Dataset) -> tuple[str, ...]:
    """The warnings of the geometry attributes left out (``_geometry_reading``)."""
    readings = (_geometry_reading(ds, keyword)[1] for keyword in GEOMETRY_KEYWORDS)
    return tuple(w for w in readings if w is not None)


def _dimension(ds: Dataset, keyword: str) -> int | None:
    """Rows (0028,0010) or Columns (0028,0011): one positive integer (US, VM 1, PS3.3 §C.7.6.3), None when
    absent; ``InvalidAttribute`` otherwise (several values, zero, a fraction)."""
    numbers = _positive_numbers(ds, keyword, 1)
    if numbers is None:
        return None
    if not numbers[0].is_integer():
        raise InvalidAttribute(f"{attribute_label(keyword)} is {numbers[0]:g}, not a whole number of pixels",
                               attributes=(keyword,))  # fmt: skip
    return int(numbers[0])


def _timezone_offset(ds: Dataset) -> tuple[str | None, tuple[str, ...]]:
    """(``RadiographHeader.timezone_offset_from_utc``, warnings): Timezone Offset From UTC (0008,0201) when
    it is a DICOM offset (``datetimes.utc_offset_problem``); a value that is not one is ignored, as if
    absent, with a warning naming the attribute."""
    label = attribute_label("TimezoneOffsetFromUTC")
    try:
        text = _text(ds, "TimezoneOffsetFromUTC")
    except InvalidAttribute as exc:
        return None, (f"{exc.message}: ignored, the film's dates and times are in no stated zone",)
    if text is None:
        return None, ()
    problem = utc_offset_problem(text)
    if problem is not None:
        return None, (f"{label} {text!r} {problem}: ignored, the film's dates and times are in no stated zone",)
    return text, ()


def _film_datetime(ds: Dataset, offset: timezone | None) -> tuple[str | None, tuple[str, ...]]:
    """(``RadiographHeader.film_datetime``, warnings) (its docstring): DA YYYYMMDD, TM HHMMSS[.F], DT
    YYYYMMDDHHMMSS[.F][&ZZXX] (PS3.5 §6.2) read into ISO 8601, ``offset`` the film's Timezone Offset From
    UTC (``_timezone_offset``); malformed values are skipped, a DT's suffix that is no offset with a warning."""
    warnings: tuple[str, ...] = ()
    candidates: list[tuple[str, str, timezone | None]] = []
    dt = _optional_text(ds, "AcquisitionDateTime")
    parts = split_dt(dt) if dt is not None else None
    if dt is not None and parts is not None:
        digits, time, suffix = parts
        zone = offset  # PS3.3 §C.12.1.1.8, Note 2: (0008,0201) dates a DT without its own offset
        if suffix is not None:
            problem = utc_offset_problem(suffix)
            if problem is None:
                zone = parse_utc_offset(suffix)
            else:
                warnings = (f"{attribute_label('AcquisitionDateTime')} {dt!r}: its offset {suffix!r} {problem}: "
                            "ignored",)  # fmt: skip
        candidates.append((digits, time, zone))
    for d_key, t_key in (("AcquisitionDate", "AcquisitionTime"), ("ContentDate", "ContentTime")):
        d = _optional_text(ds, d_key)
        if d is not None:
            candidates.append((d, _optional_text(ds, t_key) or "", offset))
    for d, t, zone in candidates:
        if len(d) != 8 or not d.isdigit():
            continue
        try:
            day = date(int(d[0:4]), int(d[4:6]), int(d[6:8]))
        except ValueError:
            continue
        clock = iso_time(t)
        if clock is None or zone is None:
            return day.isoformat(), warnings  # a time without a zone is not a FHIR dateTime: the date alone
        return f"{day.isoformat()}T{clock}{iso_offset(zone)}", warnings
    return None, warnings


def _study_date(ds: Dataset) -> date | None:
    text = _optional_text(ds, "StudyDate")
    if text is None:
        return None
    try:
        return date(int(text[0:4]), int(text[4:6]), int(text[6:8])) if len(text) == 8 and text.isdigit() else None
    except ValueError:
        return None


def _spacing_equal(a: tuple[float, ...], b: tuple[float, ...]) -> bool:
    return all(math.isclose(x, y, rel_tol=SPACING_EQUAL_RTOL) for x, y in zip(a, b, strict=True))


@dataclass(frozen=True)
class SpacingReading:
    spacing: tuple[float, float] | None
    calibration: Calibration | None
    cornerstone_type: str | None
    source: str
    warnings: tuple[str, ...] = ()


def _source_to_patient(ds: Dataset) -> tuple[float, str] | None:
    """The SOD of the spine's mid-plane from the header's distances, without ERMF (module docstring, rules
    (b) and (c)), with its rule in words; None when neither distance is given."""
    dsp = _geometry_number(ds, "DistanceSourceToPatient")
    dse = _geometry_number(ds, "DistanceSourceToEntrance")
    if dsp is not None and dse is not None:
        return (dsp + dse) / 2, (f"mid-plane: ({attribute_label('DistanceSourceToPatient')} + "
                                       f"{attribute_label('DistanceSourceToEntrance')}) / 2")  # fmt: skip
    if dsp is not None:
        surface = "detector-side surface, approximates the mid-plane"
        return dsp, f"{attribute_label('DistanceSourceToPatient')} ({surface})"
    if dse is not None:
        return dse, f"{attribute_label('DistanceSourceToEntrance')} (source-side skin, approximates the mid-plane)"
    return None


def _ermf(ds: Dataset, ps: tuple[float, ...] | None, ips: tuple[float, ...]) -> tuple[float | bool | None, str]:
    """Cornerstone3D's ``getERMF``: (magnification > 1 | True when already applied | None, its source). Its SOD
    is (0018,1111), else (0040,0306); with both, the mid-plane between them (``_source_to_patient``), the SOD the
    view's ``acquisition`` carries: the engine multiplies 'calibrated' mm by that acquisition's SID/SOD
    (``spine_engine.clinical.calibrated_magnification``), so the spacing must be divided by the same ratio to
    give the engine back Imager Pixel Spacing, the detector's (PS3.3 §C.8.11.4)."""
    ermf = _geometry_number(ds, "EstimatedRadiographicMagnificationFactor")
    sid = _geometry_number(ds, "DistanceSourceToDetector")
    sod = _source_to_patient(ds)
    if ermf is not None and ermf > 1:
        return ermf, attribute_label("EstimatedRadiographicMagnificationFactor")
    if sid is not None and sod is not None and sod[0] < sid:
        return sid / sod[0], f"{attribute_label('DistanceSourceToDetector')} / {sod[1]}"
    if ps is not None and ips[0] > ps[0]:
        return True, attribute_label("PixelSpacing")
    if ermf is not None:
        return None, f"illegal {attribute_label('EstimatedRadiographicMagnificationFactor')} {ermf:g} (≤ 1) ignored"
    return None, ""


def read_spacing(ds: Dataset) -> SpacingReading:
    """Pixel spacing and its calibration type, as Cornerstone3D's ``getPixelSpacingInformation``
    (module docstring). Spacing [row, column] in mm; ``spacing`` None when neither attribute is there.
    Pixel Spacing or Imager Pixel Spacing that is not two positive numbers is left out with a warning when
    the other gives the spacing, as the page leaves it out (``web/src/dicom.ts``); with neither usable it
    refuses the image (``InvalidAttribute``, naming it)."""
    readings = {keyword: _spacing_values(ds, keyword) for keyword in ("PixelSpacing", "ImagerPixelSpacing")}
    ps, ips = (values for values, _ in readings.values())
    errors = [error for _, error in readings.values() if error is not None]
    if errors and ps is None and ips is None:
        raise errors[0]
    reading = _spacing_of(ds, ps, ips)
    left_out = tuple(f"{error.message}: left out" for error in errors)
    return replace(reading, warnings=left_out + reading.warnings)


def _spacing_values(ds: Dataset, keyword: str) -> tuple[tuple[float, ...] | None, InvalidAttribute | None]:
    """Two positive numbers of a spacing attribute, or None and why they are not."""
    try:
        return _positive_numbers(ds, keyword, 2), None
    except InvalidAttribute as exc:
        return None, exc


def _spacing_of(ds: Dataset, ps: tuple[float, ...] | None, ips: tuple[float, ...] | None) -> SpacingReading:
    """``read_spacing`` from the usable Pixel Spacing and Imager Pixel Spacing (None: absent or left out)."""
    ctype = (_text(ds, "PixelSpacingCalibrationType") or "").upper()
    ps_label, ips_label = attribute_label("PixelSpacing"), attribute_label("ImagerPixelSpacing")
    ctype_label = attribute_label("PixelSpacingCalibrationType")
    sop_class = _text(ds, "SOPClassUID")

    def pair(v: tuple[float, ...]) -> tuple[float, float]:
        return (v[0], v[1])

    if sop_class not in PROJECTION_RADIOGRAPH_SOP_CLASSES:
        if ps is None:
            return SpacingReading(None, None, None, "")
        note = f"SOP class {sop_class} is not a projection radiograph: {ps_label} taken as it is"
        return SpacingReading(pair(ps), "unknown", "", ps_label, (note,))
    if ps is not None and ctype == "GEOMETRY":
        warnings: tuple[str, ...] = ()
        if ips is not None and _spacing_equal(ps, ips):
            warnings = (f"{ctype_label} is GEOMETRY but {ps_label} equals {ips_label}",)
        return SpacingReading(pair(ps), "calibrated", "ERMF", f"{ps_label} with {ctype_label} GEOMETRY", warnings)
    if ps is not None and ctype == "FIDUCIAL":
        return SpacingReading(pair(ps), "calibrated", "Calibrated", f"{ps_label} with {ctype_label} FIDUCIAL")
    if ips is not None:
        ermf, source = _ermf(ds, ps, ips)
        if isinstance(ermf, bool) and ermf and ps is not None:
            return SpacingReading(pair(ps), "calibrated", "ERMF", f"{ps_label} (smaller than {ips_label})")
        if isinstance(ermf, float):
            return SpacingReading((ips[0] / ermf, ips[1] / ermf), "calibrated", "ERMF", f"{ips_label} / {source}")
        warnings = (source,) if source.startswith("illegal") else ()
        if ps is not None:
            return SpacingReading(pair(ps), "projection", "Proj", ps_label, warnings)
        return SpacingReading(pair(ips), "detector", "Proj", ips_label, warnings)
    if ps is not None:
        return SpacingReading(pair(ps), "unknown", "Unknown", ps_label)
    return SpacingReading(None, None, None, "")


def read_acquisition(ds: Dataset) -> tuple[Acquisition, dict[str, str]]:
    """SID, SOD of the spine's mid-plane and ERMF (module docstring, rules (a)–(c)), with their sources."""
    ermf = _geometry_number(ds, "EstimatedRadiographicMagnificationFactor")
    sid = _geometry_number(ds, "DistanceSourceToDetector")
    from_distances = _source_to_patient(ds)
    sources: dict[str, str] = {}
    magnification = ermf if ermf is not None and ermf > 1 else None
    if magnification is not None:
        sources["acquisition.magnification"] = attribute_label("EstimatedRadiographicMagnificationFactor")
    if sid is not None:
        sources["acquisition.distance_source_to_detector_mm"] = attribute_label("DistanceSourceToDetector")
    sod: float | None = None
    if sid is not None and magnification is not None:
        sod = sid / magnification
        ermf_label = attribute_label("EstimatedRadiographicMagnificationFactor")
        rule = f"{attribute_label('DistanceSourceToDetector')} / {ermf_label}"
    elif from_distances is not None:
        sod, rule = from_distances
    if sod is not None:
        if sid is not None and sod >= sid:
            raise InvalidAttribute(
                f"the source-to-patient distance {sod:g} mm ({rule}) is not smaller than "
                f"{attribute_label('DistanceSourceToDetector')} {sid:g} mm",
                attributes=("DistanceSourceToPatient", "DistanceSourceToDetector"),
            )
        sources["acquisition.distance_source_to_patient_mm"] = rule
    return Acquisition(magnification, sid, sod), sources


def view_of_orientation(orientation: tuple[str, str]) -> ViewRole:
    """``pa`` when the image plane is frontal (x–z), ``lateral`` when sagittal (y–z); else refused."""
    axes = {_AXIS[orientation[0]], _AXIS[orientation[1]]}
    if axes == {0, 2}:
        return "pa"
    if axes == {1, 2}:
        return "lateral"
    raise UnsupportedOrientation(
        f"{attribute_label('PatientOrientation')} {list(orientation)} is an axial image plane, not a frontal "
        "(PA/AP) or lateral radiograph of the spine",
        attributes=("PatientOrientation",),
    )


def read_orientation(ds: Dataset) -> tuple[tuple[str, str] | None, bool, str, tuple[str, ...]]:
    """(orientation, assumed, source, warnings) from (0020,0020), else View Position (0018,5101)."""
    label = attribute_label("PatientOrientation")
    raw = ds.get("PatientOrientation")
    if raw not in (None, "", []):
        values = [
            str(v).strip().upper() for v in (raw if isinstance(raw, list | pydicom.multival.MultiValue) else [raw])
        ]
        if len(values) != 2 or not all(v and set(v) <= set(_AXIS) for v in values):
            raise InvalidAttribute(
                f"{label} is {values}: expected two values (the direction of the rows, left to right, then of "
                "the columns, top to bottom), each letters of L, R, A, P, H, F (PS3.3 §C.7.6.1.1.1)",
                attributes=("PatientOrientation",),
            )
        orientation = (values[0][0], values[1][0])
        if _AXIS[orientation[0]] == _AXIS[orientation[1]]:
            raise InvalidAttribute(f"{label} is {values}: both directions are along one patient axis",
                                   attributes=("PatientOrientation",))  # fmt: skip
        warnings: tuple[str, ...] = ()
        if any(len(v) > 1 for v in values):
            warnings = (f"{label} {values} is oblique: its main directions {list(orientation)} are used",)
        return orientation, False, label, warnings
    position = (_text(ds, "ViewPosition") or "").upper()
    if position in _VIEW_POSITION_ORIENTATION:
        laterality = _text(ds, "ImageLaterality")
        note = f" ({attribute_label('ImageLaterality')} {laterality})" if laterality else ""
        return (
            _VIEW_POSITION_ORIENTATION[position][1],
            True,
            f"{attribute_label('ViewPosition')} {position}{note}: conventional display assumed",
            (),
        )
    if position:
        raise UnsupportedOrientation(
            f"the image has no {label} and its {attribute_label('ViewPosition')} {position!r} is not a frontal "
            "(PA, AP) or lateral (LL, RL) projection (PS3.3 §C.8.11.5)",
            attributes=("PatientOrientation", "ViewPosition"),
        )
    return None, False, "", ()


def read_header(source: str | Path | bytes | io.BufferedIOBase | Dataset | Mapping[str, Any]) -> RadiographHeader:
    """Read one radiograph's header (file path, bytes, Dataset or DICOM JSON). Raises ``NotDicom``,
    ``MissingAttribute`` (no Study or SOP Instance UID), ``InvalidAttribute`` (a value that is not
    usable, a UID that is not a UID), ``UnsupportedOrientation``. Missing spacing or orientation is
    not an error here (the payload may give them): see ``require_spacing`` / ``require_orientation``.
    """
    ds = load_dataset(source)
    if not any(k in ds for k in ("SOPInstanceUID", "StudyInstanceUID", "SOPClassUID", "PixelSpacing",
                                  "ImagerPixelSpacing", "PatientOrientation", "Rows")):  # fmt: skip
        raise NotDicom("the data holds none of the attributes of an image header (no SOP Instance UID, no Rows)")
    study_uid = _uid(ds, "StudyInstanceUID", required=True)
    sop_uid = _uid(ds, "SOPInstanceUID", required=True)
    assert study_uid is not None and sop_uid is not None
    spacing = read_spacing(ds)
    orientation, assumed, orientation_source, orientation_warnings = read_orientation(ds)
    view = view_of_orientation(orientation) if orientation is not None else None
    if orientation is not None and assumed:
        view = _VIEW_POSITION_ORIENTATION[(_text(ds, "ViewPosition") or "").upper()][0]
    acquisition, acquisition_sources = read_acquisition(ds)
    sources: dict[str, str] = {}
    if spacing.spacing is not None:
        sources["pixel_spacing"] = spacing.source
        sources["pixel_spacing_calibration"] = spacing.source
    if orientation is not None:
        sources["patient_orientation"] = orientation_source
    sources.update(acquisition_sources)
    sop_class = _uid(ds, "SOPClassUID", required=False)
    if sop_class in PROJECTION_RADIOGRAPH_SOP_CLASSES and (
        spacing.calibration != "calibrated" or acquisition.magnification is not None
    ):
        sources["acquisition.projection_model"] = (
            f"{attribute_label('SOPClassUID')}: a projection radiograph, from a point source"
        )
    offset, offset_warnings = _timezone_offset(ds)
    issuer, issuer_warnings = _patient_id_issuer(ds)
    film_datetime, film_warnings = _film_datetime(ds, parse_utc_offset(offset))
    rows, columns = _dimension(ds, "Rows"), _dimension(ds, "Columns")
    if rows is not None and columns is not None:
        sources["acquisition.image_size"] = (
            f"[{attribute_label('Columns')}, {attribute_label('Rows')}] (× the pixel spacing in mm)"
        )
    return RadiographHeader(
        sop_class_uid=sop_class,
        sop_instance_uid=sop_uid,
        series_instance_uid=_uid(ds, "SeriesInstanceUID", required=False),
        study_instance_uid=study_uid,
        patient_id=_identifier(ds, "PatientID"),
        patient_name=_patient_name(ds),
        accession_number=_identifier(ds, "AccessionNumber"),
        study_date=_study_date(ds),
        study_time=_identity(ds, "StudyTime", "study_time"),
        timezone_offset_from_utc=offset,
        film_datetime=film_datetime,
        study_id=_identity(ds, "StudyID", "study_id"),
        patient_birth_date=_identity(ds, "PatientBirthDate", "patient_birth_date"),
        patient_sex=_identity(ds, "PatientSex", "patient_sex"),
        referring_physician_name=_identity(ds, "ReferringPhysicianName", "referring_physician_name"),
        patient_id_issuer=issuer,
        modality=_text(ds, "Modality"),
        rows=rows,
        columns=columns,
        photometric_interpretation=_text(ds, "PhotometricInterpretation"),
        pixel_spacing=spacing.spacing,
        pixel_spacing_calibration=spacing.calibration,
        cornerstone_calibration_type=spacing.cornerstone_type,
        patient_orientation=orientation,
        orientation_assumed=assumed,
        view=view,
        acquisition=acquisition,
        sources=sources,
        warnings=spacing.warnings + _geometry_warnings(ds) + orientation_warnings + offset_warnings + film_warnings
        + issuer_warnings,
    )
