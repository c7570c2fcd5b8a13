"""Header values into a job payload: what the payload gives explicitly wins, a header value that
disagrees is reported as a conflict (never silently taken), and what was read is recorded with its
attribute (``DicomProvenance``, shown on the job as ``dicom`` in openapi.yaml).

Except who the patient is and which study it is: the SR and SC go into the film's study, which belongs to
one patient (PS3.3 §C.7.1.1, §C.7.2.1). A payload and a film, or the PA and the lateral films, that
disagree on the Patient ID, its issuer, the Patient's Name without a Patient ID both give alike, or a
payload naming another study than the PA film's, are refused (``PatientConflict``, ``identity_problems``);
the study's other values (``FILM_VALUES``: accession number, date, the name when the Patient ID agrees...)
are the film's, the payload's value recorded as a conflict.

Works on the payload as JSON (a dict), so that fields the engine adds (``acquisition``,
``pixel_spacing_calibration``) pass through whatever version of the contract the reader holds.
"""

from __future__ import annotations

import copy
import math
import re
from collections.abc import Mapping, Sequence
from typing import Any, Literal

from pydantic import BaseModel, Field

from spine_client.dicom.errors import PatientConflict, UnsupportedOrientation, attribute_label

from .datetimes import parse_iso_datetime
from .header import (
    IDENTITY_VALUES,
    PatientIdIssuer,
    RadiographHeader,
    ViewRole,
    identity_problem,
    person_name_problem,
)

VALUE_RTOL = 1e-6
"""Relative tolerance under which a payload number equals the header's (DS values carry at most 16
characters, PS3.5 §6.2, so a value copied from a header and printed back differs by rounding only)."""


class AttributeRead(BaseModel):
    field: str = Field(description="JSON path of the payload field, e.g. pa.pixel_spacing.")
    value: Any = Field(description="The value read from the header.")
    attribute: str = Field(description="The DICOM attribute(s) it comes from, keyword and tag, or the rule used.")
    used: bool = Field(description="True when the job uses it (the payload did not give the field).")


class Conflict(BaseModel):
    field: str
    payload: Any
    header: Any
    attribute: str


class ViewProvenance(BaseModel):
    source: Literal["file", "dicomweb"]
    study_instance_uid: str
    series_instance_uid: str | None = None
    sop_instance_uid: str
    sop_class_uid: str | None = None
    rows: int | None = None
    columns: int | None = None
    pixel_spacing_calibration: str | None = None
    cornerstone_calibration_type: str | None = Field(
        None, description="Cornerstone3D's calibration type for the same header (Calibrated, ERMF, Proj, Unknown)."
    )
    orientation_assumed: bool = False
    film_datetime: str | None = Field(
        None, description="When the film was taken (Acquisition DateTime, else Acquisition or Content Date and Time), "
        "ISO 8601: the FHIR Observations' effectiveDateTime when the study has no date."
    )
    read: list[AttributeRead] = Field(default_factory=list)
    warnings: list[str] = Field(default_factory=list)


class DicomProvenance(BaseModel):
    """What the DICOM layer read, per view, and every disagreement between payload and header."""

    pa: ViewProvenance | None = None
    lateral: ViewProvenance | None = None
    study: list[AttributeRead] = Field(default_factory=list)
    conflicts: list[Conflict] = Field(default_factory=list)


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, int | float) and isinstance(b, int | float):
        return math.isclose(float(a), float(b), rel_tol=VALUE_RTOL)
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return bool(a == b)


def _jsonable(value: Any) -> Any:
    if isinstance(value, PatientIdIssuer):
        return value.as_payload()
    if isinstance(value, tuple):
        return [_jsonable(v) for v in value]
    if hasattr(value, "isoformat"):
        return value.isoformat()
    return value


class _Merger:
    def __init__(self, provenance: DicomProvenance):
        self.provenance = provenance

    def fill(self, target: dict[str, Any], key: str, path: str, value: Any, attribute: str,
             reads: list[AttributeRead], *, header_wins: bool = False) -> bool:  # fmt: skip
        """Put ``value`` into ``target[key]`` unless the payload has it (or, ``header_wins``, has another
        value: then the header's is put in its place); record the read and any conflict. Returns True when
        the header's value is used."""
        value = _jsonable(value)
        given = target.get(key)
        differs = given is not None and not _same(_jsonable(given), value)
        if differs:
            self.provenance.conflicts.append(Conflict(field=path, payload=_jsonable(given), header=value,
                                                      attribute=attribute))  # fmt: skip
        if given is None or (differs and header_wins):
            target[key] = value
            reads.append(AttributeRead(field=path, value=value, attribute=attribute, used=True))
            return True
        reads.append(AttributeRead(field=path, value=value, attribute=attribute, used=False))
        return False


def merge_view(
    payload: dict[str, Any], role: ViewRole, header: RadiographHeader, *,
    source: Literal["file", "dicomweb"], provenance: DicomProvenance,
) -> None:  # fmt: skip
    """Fill ``payload[role]`` from ``header`` in place: pixel spacing (and its calibration when the
    header's spacing is the one used), patient orientation, acquisition (with the image size in the view's
    units). Raises
    ``UnsupportedOrientation`` when the header's image is not the view it is given as (a lateral
    image sent as ``pa``), and ``MissingAttribute`` when the view's landmarks are in px and neither
    payload nor header gives a spacing, or neither gives an orientation."""
    view = payload.setdefault(role, {})
    if header.view is not None and header.view != role:
        raise UnsupportedOrientation(
            f"the image given as {role} is a {header.view} radiograph by its "
            f"{header.sources.get('patient_orientation', attribute_label('PatientOrientation'))} "
            f"{list(header.patient_orientation or ())}",
            attributes=("PatientOrientation",),
            field=f"{role}.patient_orientation",
        )
    record = ViewProvenance(
        source=source, study_instance_uid=header.study_instance_uid, series_instance_uid=header.series_instance_uid,
        sop_instance_uid=header.sop_instance_uid, sop_class_uid=header.sop_class_uid, rows=header.rows,
        columns=header.columns, pixel_spacing_calibration=header.pixel_spacing_calibration,
        cornerstone_calibration_type=header.cornerstone_calibration_type,
        orientation_assumed=header.orientation_assumed, film_datetime=header.film_datetime,
        warnings=list(header.warnings),
    )  # fmt: skip
    merger = _Merger(provenance)
    if header.pixel_spacing is not None:
        used = merger.fill(view, "pixel_spacing", f"{role}.pixel_spacing", header.pixel_spacing,
                           header.sources["pixel_spacing"], record.read)  # fmt: skip
        if used or _same(_jsonable(view["pixel_spacing"]), _jsonable(header.pixel_spacing)):
            calibration_source = header.sources["pixel_spacing_calibration"]
            merger.fill(view, "pixel_spacing_calibration", f"{role}.pixel_spacing_calibration",
                        header.pixel_spacing_calibration, calibration_source, record.read)  # fmt: skip
    elif view.get("units") == "px" and view.get("pixel_spacing") is None:
        header.require_spacing(f"{role}.pixel_spacing")
    if header.patient_orientation is not None:
        merger.fill(view, "patient_orientation", f"{role}.patient_orientation", header.patient_orientation,
                    header.sources["patient_orientation"], record.read)  # fmt: skip
    elif view.get("patient_orientation") is None:
        header.require_orientation(f"{role}.patient_orientation")
    acquisition = header.view_acquisition(view.get("units", "mm"), view.get("pixel_spacing"))
    if acquisition:
        target = dict(view.get("acquisition") or {})
        for key, value in acquisition.items():
            merger.fill(target, key, f"{role}.acquisition.{key}", value, header.sources[f"acquisition.{key}"],
                        record.read)  # fmt: skip
        view["acquisition"] = target
    setattr(provenance, role, record)


STUDY_FIELDS = (
    ("study_instance_uid", "StudyInstanceUID"),
    ("patient_id", "PatientID"),
    ("patient_name", "PatientName"),
    ("accession_number", "AccessionNumber"),
    ("study_date", "StudyDate"),
    ("study_time", "StudyTime"),
    ("study_id", "StudyID"),
    ("patient_birth_date", "PatientBirthDate"),
    ("patient_sex", "PatientSex"),
    ("referring_physician_name", "ReferringPhysicianName"),
    ("timezone_offset_from_utc", "TimezoneOffsetFromUTC"),
    ("patient_id_issuer", "IssuerOfPatientID"),
)
"""What the study block takes from the header, each with the attribute it is read from (the issuer's with
its Issuer of Patient ID Qualifiers Sequence (0010,0024), ``ISSUER_ATTRIBUTES``). The contract's ``Study``
has the first five and ``patient_id_issuer``; the others
(``IDENTITY_VALUES``) stay in the provenance and the job's effective payload (``services.db.job_forms``),
for the SR, the SC and the FHIR export. Two films of one study that disagree on one of them (a lateral
with another Timezone Offset From UTC) are a conflict like any other: the PA's value is used."""


FILM_VALUES = frozenset({
    "patient_name", "patient_id_issuer", "accession_number", "study_date", "study_time", "study_id",
    "patient_birth_date", "patient_sex", "referring_physician_name", "timezone_offset_from_utc",
})  # fmt: skip
"""The study's values that are the film's when the payload gives another (the conflict recorded): the SR and
SC repeat the film's Patient and General Study Modules in its study (PS3.3 §C.7.1.1, §C.7.2.1), so a typed
Accession Number or Patient's Name does not make one study say two things. Between the films, the PA's.
Who the patient is and which study is never taken over: ``identity_problems`` refuses a disagreement."""

LATERAL_PREFIX = "lateral image's "
"""How a study read of the lateral film names its attribute (``merge_study``), apart from the PA's."""

WHO_FIELDS = {"study_instance_uid": "StudyInstanceUID", "patient_id": "PatientID",
              "patient_id_issuer": "IssuerOfPatientID", "patient_name": "PatientName"}  # fmt: skip
"""The study's values that say who the patient is and which study (``identity_problems``), with their keyword."""


def normalised_person_name(value: str) -> str:
    """A PN as compared: case-folded, each component without its leading and trailing spaces, and no
    trailing empty component or component group (PS3.5 §6.2.1: trailing ``^`` and ``=`` may be left out,
    so ``Doe^Jane^^^`` is ``DOE^JANE``; the case of a name is how it was typed, not who it names)."""
    groups = []
    for group in value.split("="):
        components = [c.strip().casefold() for c in group.split("^")]
        while components and not components[-1]:
            components.pop()
        groups.append("^".join(components))
    while groups and not groups[-1]:
        groups.pop()
    return "=".join(groups)


def _text(value: Any) -> str:
    """A Patient ID or UID as compared: an LO's and a UI's leading and trailing spaces are padding (PS3.5 §6.2)."""
    return str(value).strip()


def _issuers_differ(a: Any, b: Any) -> bool:
    """Whether two ``patient_id_issuer`` values name two issuers: the local names (Issuer of Patient ID)
    both give differ, or the universal IDs both give differ (with their Type). Two that share no member
    name none in common: not a disagreement."""
    a = a if isinstance(a, Mapping) else {}
    b = b if isinstance(b, Mapping) else {}
    local = (a.get("issuer_of_patient_id"), b.get("issuer_of_patient_id"))
    if None not in local and _text(local[0]) != _text(local[1]):
        return True
    if a.get("universal_entity_id") is not None and b.get("universal_entity_id") is not None:
        keys = ("universal_entity_id", "universal_entity_id_type")
        return tuple(_text(a.get(k)) for k in keys) != tuple(_text(b.get(k)) for k in keys)
    return False


_WHO_PAIRS = (("payload", "pa"), ("payload", "lateral"), ("pa", "lateral"))


def identity_problems(payload_study: Mapping[str, Any], reads: Sequence[AttributeRead]) -> list[tuple[str, str, str]]:
    """(field, reason, keyword) for each of ``WHO_FIELDS`` on which the payload's study (the values it gives
    itself) and the films' headers (the study reads, the lateral's named with ``LATERAL_PREFIX``), or the
    two films, disagree; empty when they are of one patient and study:

    - Patient ID: after its padding; with its issuer, when both give one (``_issuers_differ``);
    - Patient's Name, as ``normalised_person_name``, when the two do not give the same Patient ID: a
      Patient ID is the identifier, and when both give it alike a name that differs is one spelling
      against another (the film's is used, ``FILM_VALUES``); without it, the name is all that says who
      the patient is;
    - Study Instance UID, the payload's against the PA film's (the study the SR and SC go into). A lateral
      of another study of the same patient is a conflict recorded, the PA's used."""
    claims: dict[str, dict[str, tuple[str, Any]]] = {"payload": {}, "pa": {}, "lateral": {}}
    for key in WHO_FIELDS:
        value = payload_study.get(key)
        if value is not None and not (isinstance(value, str) and not value.strip()):
            claims["payload"][key] = (f"the payload's study.{key}", value)
    for read in reads:
        key = read.field.removeprefix("study.")
        if key not in WHO_FIELDS or read.value is None:
            continue
        lateral = read.attribute.startswith(LATERAL_PREFIX)
        role = "lateral" if lateral else "pa"
        claims[role].setdefault(key, (f"the {role if lateral else 'PA'} film's "
                                      f"{read.attribute.removeprefix(LATERAL_PREFIX)}", read.value))  # fmt: skip
    problems: list[tuple[str, str, str]] = []
    for key, keyword in WHO_FIELDS.items():
        for a, b in _WHO_PAIRS:
            if key not in claims[a] or key not in claims[b] or (key == "study_instance_uid" and b != "pa"):
                continue
            (a_label, a_value), (b_label, b_value) = claims[a][key], claims[b][key]
            if key == "patient_name":
                ids = (claims[a].get("patient_id"), claims[b].get("patient_id"))
                if normalised_person_name(str(a_value)) == normalised_person_name(str(b_value)) or (
                        None not in ids and _text(ids[0][1]) == _text(ids[1][1])):  # type: ignore[index]
                    continue
                why = "name two patients, and no Patient ID given by both says they are one"
            elif key == "patient_id_issuer":
                if not _issuers_differ(a_value, b_value):
                    continue
                why = "name two issuers of the Patient ID: the same ID from two issuers may be two patients"
            elif _text(a_value) == _text(b_value):
                continue
            elif key == "patient_id":
                why = "name two patients"
            else:
                why = "name two studies: the results go into the film's study"
            problems.append((f"study.{key}", f"{a_label} {_jsonable(a_value)!r} and {b_label} "
                                             f"{_jsonable(b_value)!r} {why}", keyword))  # fmt: skip
            break
    return problems


ISSUER_ATTRIBUTES = (f"{attribute_label('IssuerOfPatientID')}, {attribute_label('IssuerOfPatientIDQualifiersSequence')}"
                     f" > {attribute_label('UniversalEntityID')}, {attribute_label('UniversalEntityIDType')}")
"""The attributes ``study.patient_id_issuer`` is read from (``header._patient_id_issuer``)."""


def merge_study(
    payload: dict[str, Any], headers: dict[ViewRole, RadiographHeader], provenance: DicomProvenance
) -> None:
    """Fill ``payload["study"]`` from the headers (the PA's first): study UID, patient, accession,
    date, and each view's SOP Instance UID (and the PA's series). Conflicts between payload and
    header, or between the two images, are recorded; of ``FILM_VALUES`` the film's value is used (the
    PA's, the lateral's where the PA has none). Raises ``PatientConflict`` when the payload and the
    films, or the two films, are not of one patient and study (``identity_problems``)."""
    study = payload.get("study") or {}
    given = dict(study)
    merger = _Merger(provenance)
    pa = headers.get("pa")
    for role in ("pa", "lateral"):
        header = headers.get(role)  # type: ignore[call-overload]
        if header is None:
            continue
        prefix = "" if role == "pa" else LATERAL_PREFIX
        for key, keyword in STUDY_FIELDS:
            value = getattr(header, key)
            label = ISSUER_ATTRIBUTES if key == "patient_id_issuer" else attribute_label(keyword)
            over_payload = role == "pa" or pa is None or getattr(pa, key) is None
            if value is not None:
                merger.fill(study, key, f"study.{key}", value, prefix + label, provenance.study,
                            header_wins=key in FILM_VALUES and over_payload)  # fmt: skip
        merger.fill(study, f"{role}_sop_instance_uid", f"study.{role}_sop_instance_uid", header.sop_instance_uid,
                    attribute_label("SOPInstanceUID"), provenance.study)  # fmt: skip
        if role == "pa" and header.series_instance_uid is not None:
            merger.fill(study, "series_instance_uid", "study.series_instance_uid", header.series_instance_uid,
                        attribute_label("SeriesInstanceUID"), provenance.study)  # fmt: skip
    problems = identity_problems(given, provenance.study)
    if problems:
        detail = "; ".join(f"{field}: {reason}" for field, reason, _ in problems)
        raise PatientConflict(f"{detail}: refused, a job's payload and films must be of one patient and study "
                              "(PS3.3 §C.7.1.1)", attributes=tuple(keyword for _, _, keyword in problems),
                              field=problems[0][0])  # fmt: skip
    payload["study"] = study


def apply_headers(
    payload: dict[str, Any], headers: dict[ViewRole, RadiographHeader], *, source: Literal["file", "dicomweb"]
) -> tuple[dict[str, Any], DicomProvenance]:
    """A copy of ``payload`` with the headers' values filled in, and the provenance of every value."""
    merged = copy.deepcopy(payload)
    provenance = DicomProvenance()
    for role, header in headers.items():
        merge_view(merged, role, header, source=source, provenance=provenance)
    merge_study(merged, headers, provenance)
    return merged, provenance


_VIEW_FIELDS = ("pixel_spacing", "pixel_spacing_calibration", "patient_orientation")
_STUDY_FIELDS = {key for key, _ in STUDY_FIELDS} | {"pa_sop_instance_uid", "lateral_sop_instance_uid",
                                                     "series_instance_uid"}  # fmt: skip


def _header_field(section: str, path: str) -> bool:
    """Whether ``path`` is a payload field the DICOM layer fills from a header, in ``section``."""
    parts = path.split(".")
    if section == "study":
        return len(parts) == 2 and parts[0] == "study" and parts[1] in _STUDY_FIELDS
    if parts[0] != section:
        return False
    return (len(parts) == 2 and parts[1] in _VIEW_FIELDS) or (len(parts) == 3 and parts[1] == "acquisition")


_FILM_DATE = re.compile(r"^\d{4}-\d{2}-\d{2}$")
_FILM_DATE_TIME = re.compile(r"^\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:(\d{2}|60)(\.\d+)?([+-]\d{2}:\d{2}|Z)$")


def film_datetime_problem(value: str) -> str | None:
    """Why ``ViewProvenance.film_datetime`` is not in the form the header reader writes it
    (``header._film_datetime``), None when it is: an ISO 8601 date (YYYY-MM-DD), or a date and time to
    the second with its UTC offset (YYYY-MM-DDThh:mm:ss±hh:mm), a leap second ``:60`` included
    (``datetimes``: PS3.5 §6.2 and FHIR R4 allow it; the rest of the value is checked with it read as
    ``:59``). It becomes the FHIR Observations' ``effectiveDateTime`` when the study has no date, and a
    FHIR R4 dateTime with a time SHALL have a time zone (datatypes §2.24.0.1)."""
    text = value.strip()
    form = "a date (YYYY-MM-DD) or a date and time with its UTC offset (YYYY-MM-DDThh:mm:ss+hh:mm)"
    if _FILM_DATE.match(text) or _FILM_DATE_TIME.match(text):
        try:
            parse_iso_datetime(text)
        except ValueError:
            return f"{value!r} is not a calendar date or time: the film's date must be {form}"
        return None
    if re.match(r"^\d{4}-\d{2}-\d{2}[T ]\d{2}:\d{2}(:\d{2}(\.\d+)?)?$", text):
        return (f"{value!r} has a time but no time zone: the film's date must be {form}, as the header "
                "reader writes it (a time of unknown zone is sent as the date alone)")  # fmt: skip
    return f"{value!r} is not a date: the film's date must be {form}"


def client_provenance_errors(provenance: DicomProvenance) -> list[tuple[tuple[str | int, ...], str]]:
    """What is wrong with a ``dicom`` block a client read from its image files and sends with a payload
    (``spine submit --pa-dicom``), as (JSON path within the block, reason): every view's ``source``
    is ``file`` (``dicomweb`` reads are the service's own), every read fills a field the DICOM layer
    fills from a header (so that the block can only complete a payload as a header does), a study
    value the contract has no field for is as DICOM writes it, so is the Patient's Name (a PN of at most
    64 characters per component group, ``person_name_problem``, as the header reader takes it), and a
    view's ``film_datetime`` is as the header reader writes it (``film_datetime_problem``)."""
    errors: list[tuple[tuple[str | int, ...], str]] = []
    sections: list[tuple[str, list[AttributeRead]]] = [("study", provenance.study)]
    for role in ("pa", "lateral"):
        record: ViewProvenance | None = getattr(provenance, role)
        if record is None:
            continue
        if record.source != "file":
            errors.append(((role, "source"), "must be 'file': the service reads the PACS itself"))
        if record.film_datetime is not None:
            problem = film_datetime_problem(record.film_datetime)
            if problem is not None:
                errors.append(((role, "film_datetime"), problem))
        sections.append((role, record.read))
    for section, reads in sections:
        base: tuple[str | int, ...] = (section,) if section == "study" else (section, "read")
        for i, read in enumerate(reads):
            if not _header_field(section, read.field):
                errors.append(((*base, i, "field"), f"{read.field!r} is not a field a {section} header fills"))
                continue
            key = read.field.split(".")[-1]
            reason = None
            if section == "study" and key in IDENTITY_VALUES:
                reason = identity_problem(key, read.value)
            elif section == "study" and key == "patient_name" and isinstance(read.value, str):
                problem = person_name_problem(read.value)
                reason = f"{read.value[:80]!r} {problem}" if problem is not None else None
            if reason is not None:
                errors.append(((*base, i, "value"), reason))
    return errors


def client_identity_errors(
    payload: Mapping[str, Any], provenance: DicomProvenance
) -> list[tuple[tuple[str | int, ...], str]]:
    """What in a payload and the ``dicom`` block a client read from its image files says that they are
    not of one patient and study, as (JSON path in the posted body, reason), as ``merge_study`` refuses it
    on the client (a client that sends it anyway, or one older than that refusal): each of
    ``identity_problems`` between the payload's study (its values no read fills) and the study reads, at
    the study's field; and a read of ``FILM_VALUES`` from the PA film that is not used where the payload
    gives another value (the SR and SC would carry the payload's into the film's study), at the read."""
    study = payload.get("study")
    study = study if isinstance(study, Mapping) else {}
    used = {read.field for read in provenance.study if read.used}
    own = {key: value for key, value in study.items() if f"study.{key}" not in used}
    errors: list[tuple[tuple[str | int, ...], str]] = [
        (tuple(field.split(".")), reason) for field, reason, _ in identity_problems(own, provenance.study)]
    for i, read in enumerate(provenance.study):
        key = read.field.removeprefix("study.")
        if key not in FILM_VALUES or read.used or read.attribute.startswith(LATERAL_PREFIX):
            continue
        given = study.get(key)
        if given is not None and not _same(_jsonable(given), read.value):
            errors.append((("dicom", "study", i, "used"),
                           f"the PA film's {read.attribute} {read.value!r} is the study's, not the payload's "
                           f"{_jsonable(given)!r}: the SR and SC go into the film's study with the film's values "
                           f"(give the film's value in study.{key}, or leave it out)"))  # fmt: skip
    return errors
