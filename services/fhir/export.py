"""FHIR export of a succeeded job: a Bundle (type collection) of Observations of its clinical measures.

Built and validated with ``fhir.resources``' R4B models (FHIR 4.3.0). fhir.resources has no
separate R4 (4.0.1) package for pydantic 2 (6.4 and older need pydantic 1); R4B changed neither
Observation nor Bundle for the elements written here (status, category, code, issued, value[x]
Quantity, component, note, method, derivedFrom, identifier; Bundle type, timestamp, entry.fullUrl),
so the JSON is valid R4 as well.

Coding: each Observation's ``code`` keeps its ``text`` and carries a coding where one exists.
The frontal Cobb angle is SNOMED CT 285285000 "Cobb angle" (``http://snomed.info/sct``), the code
DICOM PS3.16 CID 7550 "Angle Measurement" gives it and the SR uses. PS3.16 (pydicom 3.0.2's concept
dictionary, which lists all of it) has no code for thoracic kyphosis, lumbar lordosis or the axial
rotation of a vertebra, and no LOINC term for them was found; a CodeableConcept's codings are
translations of one meaning (FHIR R4 CodeableConcept.coding), so the broader "Cobb angle" is not put
on the sagittal angles. Those, and the components with a concept of their own, are coded in the
service's local code system ``LOCAL_CODE_SYSTEM`` (a ``urn:uuid``: FHIR R4 §4.1 "Using Codes" allows
a UUID as the system of a code system without a URL), whose codes are the SR's private ``99SPINE``
code values with the same meanings (``LOCAL_CODES``, documented in docs/fhir.md). The other codes used
are FHIR's category ``imaging`` (http://terminology.hl7.org/CodeSystem/observation-category) and
UCUM ``deg``. The input images' DICOM Study Instance UID, when the payload had a ``study``, is
referenced in ``derivedFrom`` as an ImagingStudy identifier (system ``urn:dicom:uid``, value
``urn:oid:<uid>``).

Model estimates: a value from the spine model's prior (``services.core.estimates.model_estimate_reason``,
the SR's rule) has
``interpretation`` the local code ``MODEL-BASED`` (the SR's method code) and a note giving the
result's reason, on the Observation or on the Cobb Observation's component; a Cobb angle's end-plate
variant, plane of maximum curvature and Cobb angle in that plane are flagged with the Cobb angle when it
is one (``fit.unreliable`` ``cobb``), as the SR marks them. An SD the result gives is a component whose
text says where it comes from (``sd_component_text``).

Subject and time: ``subject`` is the Patient by identifier (DICOM Patient ID (0010,0020)) whenever a
patient ID is known, with ``system`` the film's issuer when its Issuer of Patient ID Qualifiers Sequence
names it by a URI (``issuer_system``), else the setting ``SPINE_PATIENT_ID_SYSTEM`` (the issuer's
namespace), else none; the issuer's local name is ``identifier.assigner.display``. Every Observation
has ``effectiveDateTime`` (``effective_date_time``): the study's date and time, else the film's
acquisition (or content) date and time, else the job's creation.
"""

from __future__ import annotations

import re
import uuid
from collections.abc import Mapping, Sequence
from datetime import date, datetime, timedelta
from typing import Any

from fhir.resources.R4B.bundle import Bundle

from services.core.estimates import EXACT_ENDS, model_estimate_reason
from spine_client.dicom.datetimes import iso_offset, parse_utc_offset
from spine_engine.levels import apex_words
from spine_engine.models import read_study_date

FHIR_MEDIA_TYPE = "application/fhir+json"
FHIR_VERSION = "4.0.1"
UCUM = "http://unitsofmeasure.org"
OBSERVATION_CATEGORY = "http://terminology.hl7.org/CodeSystem/observation-category"
SNOMED_CT = "http://snomed.info/sct"
COBB_ANGLE = {"system": SNOMED_CT, "code": "285285000", "display": "Cobb angle"}
"""SNOMED CT "Cobb angle", DICOM PS3.16 CID 7550 "Angle Measurement" (as in the SR)."""
LOCAL_CODE_SYSTEM = "urn:uuid:4b0e7d3c-5f0a-5c11-9a7e-0c2f6d1e8a55"
"""The service's own code system for measures without a standard code (fixed for all releases)."""
LOCAL_CODE_SYSTEM_VERSION = "1"
LOCAL_CODES: dict[str, str] = {
    "KYPH-T4-T12": "Thoracic kyphosis T4-T12",
    "KYPH-T5-T12": "Thoracic kyphosis T5-T12",
    "LORD-L1-L5": "Lumbar lordosis L1-L5",
    "APEX-AXROT": "Axial rotation of the apical vertebra",
    "PMC-ORIENT": "Orientation of the plane of maximum curvature",
    "PMC-COBB": "Cobb angle in the plane of maximum curvature",
    "ENDPLATE-COBB": "Cobb angle between the end vertebrae's endplates",
    "CONVEXITY": "Convexity of the curve",
    "MAJOR-CURVE": "Major curve (the largest)",
    "MODEL-BASED": "Model-based estimate (from the spine model's prior)",
}
"""The local code system's concepts: code -> display (the SR's ``99SPINE`` values and meanings)."""
DICOM_UID = "urn:dicom:uid"
URI = "urn:ietf:rfc:3986"
METHOD = (
    "3D reconstruction of the spine from radiograph landmarks by discrete Cosserat rod registration "
    "(Li, Leow, Huang and Howe, CAIP 2009)"
)
_NAMESPACE = uuid.UUID("6f1c2a57-2a4e-5d0b-8a53-2f3f7c1b9e10")


def _estimate_note(reason: str, what: str | None = None) -> str:
    return f"Model estimate{f' ({what})' if what else ''}: {reason}."


MODEL_BASED = {"coding": [{"system": LOCAL_CODE_SYSTEM, "version": LOCAL_CODE_SYSTEM_VERSION, "code": "MODEL-BASED",
                           "display": LOCAL_CODES["MODEL-BASED"]}], "text": "Model estimate"}  # fmt: skip
"""``interpretation`` of an Observation or component whose value is a model estimate: the SR's method code
``MODEL-BASED`` (99SPINE), in the local code system."""


SD_COMPONENT = "Standard deviation of the value"
"""How the text of an Observation's SD component begins (``sd_component_text`` says where the SD comes from)."""

_LAPLACE = (
    "the fit's Laplace SD, scaled by constants fitted on VerSe dev spines and widened by the landmarks' misfit beyond "
    "their stated SD (fit.uncertainty_scale, fit.landmark_misfit_ratio)"
)
_MODEL_TILT_ENDS = ("model", "mixed")
"""``tilt_source`` of a Cobb angle some of whose end vertebrae's tilts are the model's (no corners)."""


def _assumed(fit: Mapping[str, Any], name: str) -> bool:
    return any(isinstance(a, Mapping) and a.get("name") == name for a in fit.get("assumed") or [])


def sd_component_text(fit: Mapping[str, Any], quantity: str, *, level: str | None = None,
                      tilt_source: str | None = None) -> str:  # fmt: skip
    """The text of an SD component (1 SD of the Observation's value, degrees): where the engine's SD of
    ``quantity`` (``cobb``, ``kyphosis``, ``lordosis``, ``axial_rotation`` of ``level``) comes from, as the
    result's ``fit`` says (docs/engine.md "Honest SDs", docs/measures.md, docs/accuracy.md "Intervals"):

    - every SD starts from the fit's Laplace SD scaled by constants fitted on VerSe dev and widened by
      the landmarks' misfit beyond their stated SD (``fit.uncertainty_scale``, ``fit.landmark_misfit_ratio``);
    - a Cobb angle with an end vertebra of model tilt (``tilt_source`` model or mixed) adds the spread of
      real endplates (AASCE 2019 training); with ``cobb`` in ``fit.unreliable`` an angle that depends on
      a level the PA film's landmarks do not show has at least the population's SD of the major Cobb
      angle (18.4°), the others their own: the result does not say which, so the text says both;
    - kyphosis and lordosis when no film places the spine in depth (``depth`` in ``fit.unreliable``: no
      boundary, fewer than 2 lateral landmarks) have at least the population's SD (VerSe dev);
    - an axial rotation of the population's (``fit.assumed`` ``population_axial_rotation``) adds the
      population's spread at its curve's Cobb angle, except T1's and L5's given exactly."""
    unreliable = set(fit.get("unreliable") or [])
    source = _LAPLACE
    if quantity == "cobb":
        if tilt_source in _MODEL_TILT_ENDS:
            source += (
                ", with the spread of real endplates about the centreline added for the end vertebrae "
                "no corners drew (calibrated on AASCE 2019 training)"
            )
        if "cobb" in unreliable:
            source = (
                "at least the population's SD of the major Cobb angle (AASCE 2019 training) if the angle "
                f"depends on a level the PA film's landmarks do not show (fit.unreliable: cobb), else {source}"
            )
    elif quantity in ("kyphosis", "lordosis") and "depth" in unreliable:
        source = (
            f"the population's SD (VerSe dev) or {_LAPLACE}, whichever is larger: no film places the "
            "spine in depth (fit.unreliable: depth)"
        )
    elif (
        quantity == "axial_rotation"
        and _assumed(fit, "population_axial_rotation")
        and not (fit.get("boundary", "given") == "given" and level in EXACT_ENDS)
    ):
        source += (
            ", with the population's spread of axial rotation at its curve's Cobb angle added "
            "(fit.assumed: population_axial_rotation)"
        )
    return f"{SD_COMPONENT} (1 SD: {source}; a 95 % interval is ±1.96 SD)"


def _deg(value: float) -> dict[str, Any]:
    """A UCUM ``deg`` Quantity to 0.01°; a value that rounds to zero is ``0.0``, never ``-0.0``."""
    rounded = round(float(value), 2)
    return {"value": 0.0 if rounded == 0 else rounded, "unit": "deg", "system": UCUM, "code": "deg"}


def _text(text: str) -> dict[str, Any]:
    return {"text": text}


def _local(code: str) -> dict[str, Any]:
    return {"system": LOCAL_CODE_SYSTEM, "version": LOCAL_CODE_SYSTEM_VERSION, "code": code,
            "display": LOCAL_CODES[code]}  # fmt: skip


def _coded(text: str, coding: dict[str, Any] | None) -> dict[str, Any]:
    """A CodeableConcept: ``text`` always, with ``coding`` when the concept has a code."""
    return {"coding": [coding], "text": text} if coding else _text(text)


_ESTIMATE_KEY = "_estimate"
"""A component's model-estimate reason while the Observation is built (``_estimate_notes``
moves it into a note; never in the JSON)."""


def _component(name: str, code: str | None = None, estimate: str | None = None, **value: Any) -> dict[str, Any]:
    """An Observation component; ``estimate`` (why its value is a model estimate) flags it with
    ``interpretation`` ``MODEL_BASED`` and, through ``_estimate_notes``, a note."""
    component = {"code": _coded(name, _local(code) if code else None), **value}
    if estimate:
        component["interpretation"] = [MODEL_BASED]
        component[_ESTIMATE_KEY] = estimate
    return component


def _estimate_notes(estimate: str | None, components: Sequence[dict[str, Any]]) -> list[str]:
    """The model-estimate notes of an Observation whose value is one for the reason ``estimate`` (None:
    measured): one per reason, naming the components it flags (their reasons taken out of them), the
    value's first; components with the value's reason are named in its note (a Cobb angle's end-plate
    variant), not in a second note repeating it."""
    by_reason: dict[str, list[str]] = {estimate: []} if estimate else {}
    for component in components:
        reason = component.pop(_ESTIMATE_KEY, None)
        if reason:
            by_reason.setdefault(reason, []).append(component["code"]["text"])
    notes = []
    for reason, names in by_reason.items():
        parts = (["the value"] if reason == estimate else []) + (["components: " + "; ".join(names)] if names else [])
        notes.append(_estimate_note(reason, "; ".join(parts) if names else None))
    return notes


def _derived_from(study: dict[str, Any] | None) -> list[dict[str, Any]]:
    if not study or not study.get("study_instance_uid"):
        return []
    uid = study["study_instance_uid"]
    return [
        {
            "type": "ImagingStudy",
            "identifier": {"system": DICOM_UID, "value": f"urn:oid:{uid}"},
            "display": f"DICOM study {uid}",
        }
    ]


FHIR_OID = re.compile(r"^[0-2](\.(0|[1-9][0-9]*))+$")
"""An OID in dot notation as FHIR R4's ``oid`` datatype takes it after ``urn:oid:`` (its regex
``urn:oid:[0-2](\\.(0|[1-9][0-9]*))+``; RFC 3001)."""
FHIR_UUID = re.compile(r"^[0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12}$")
"""A UUID as FHIR R4's ``uuid`` datatype takes it after ``urn:uuid:`` (lower-case hex, RFC 4122 §3)."""
ABSOLUTE_URI = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*:\S+$")
"""An absolute URI (RFC 3986 §4.3: a scheme, a colon, then no whitespace), as FHIR R4 ``Identifier.system``
(a ``uri``) needs, the rule ``SPINE_PATIENT_ID_SYSTEM`` is held to."""


def issuer_system(issuer: Mapping[str, Any] | None) -> str | None:
    """The FHIR ``Identifier.system`` URI of a DICOM issuer of Patient ID (the study's ``patient_id_issuer``:
    Universal Entity ID (0040,0032) and its Type (0040,0033) of Issuer of Patient ID Qualifiers Sequence
    (0010,0024), PS3.3 §C.7.1.1, §10.14): ``ISO`` (an OID) → ``urn:oid:<oid>``, ``UUID`` → ``urn:uuid:<uuid>``
    in lower case, ``URI`` → the URI itself when absolute. None for the other Types (DNS, EUI64, X400, X500:
    names, not URIs), for a value not of its Type's form, and for an issuer known only by its local name,
    Issuer of Patient ID (0010,0021), which is no URI (FHIR R4 Identifier.system is a ``uri``)."""
    issuer = issuer or {}
    value, kind = str(issuer.get("universal_entity_id") or "").strip(), issuer.get("universal_entity_id_type")
    if kind == "ISO" and FHIR_OID.match(value):
        return f"urn:oid:{value}"
    if kind == "UUID" and FHIR_UUID.match(value.lower()):
        return f"urn:uuid:{value.lower()}"
    if kind == "URI" and ABSOLUTE_URI.match(value):
        return value
    return None


def _subject(study: Mapping[str, Any] | None, patient_id_system: str | None) -> dict[str, Any] | None:
    """The Patient by identifier (DICOM Patient ID (0010,0020)), with the DICOM Patient's Name as display
    (``person_name_display``); None without a patient ID. The identifier's ``system`` is the film's issuer
    when it names it by a URI (``issuer_system``), else ``patient_id_system`` (``SPINE_PATIENT_ID_SYSTEM``)
    when configured, else none; the issuer's local name (Issuer of Patient ID (0010,0021), not a URI) is
    the identifier's ``assigner.display`` (FHIR R4 Identifier.assigner, a Reference that may hold only a
    display)."""
    if not study or not study.get("patient_id"):
        return None
    issuer = study.get("patient_id_issuer")
    issuer = issuer if isinstance(issuer, Mapping) else None
    identifier: dict[str, Any] = {"value": study["patient_id"]}
    system = issuer_system(issuer) or patient_id_system
    if system:
        identifier = {"system": system, **identifier}
    if issuer and issuer.get("issuer_of_patient_id"):
        identifier["assigner"] = {"display": issuer["issuer_of_patient_id"]}
    subject: dict[str, Any] = {"type": "Patient", "identifier": identifier}
    display = person_name_display(study.get("patient_name"))
    if display:
        subject["display"] = display
    return subject


def person_name_display(name: object) -> str | None:
    """A DICOM PN (PS3.5 §6.2.1) as a person reads it; None when it holds no name.

    A PN is up to three component groups separated by ``=`` (alphabetic, ideographic, phonetic), each
    of five components separated by ``^``: family, given, middle, prefix, suffix. The alphabetic group
    is used; when it is empty (a name written in ideographs only, ``=山田^太郎``) the first group that is
    not. The components are joined by one space, empty ones left out, in the orders FHIR names for a
    HumanName's display (extension ``humanname-assembly-order``, HL7 v2 table 0444): ``G`` "Prefix
    Given Family Suffix" for the alphabetic group, as FHIR R4's own example Patient's
    ``HumanName.text`` "Peter James Chalmers" (``DOE^JOHN^^DR`` → "DR JOHN DOE"); ``F`` "Prefix Family
    Given Suffix" for an ideographic or phonetic group, the order those names are written in (PS3.5
    Annex H, ``Yamada^Tarou=山田^太郎=やまだ^たろう`` → "山田 太郎" when alone)."""
    if name is None:
        return None
    for index, group in enumerate(str(name).split("=")[:3]):
        parts = [" ".join(part.split()) for part in group.split("^")[:5]]
        family, given, middle, prefix, suffix = parts + [""] * (5 - len(parts))
        order = [prefix, given, middle, family, suffix] if index == 0 else [prefix, family, given, middle, suffix]
        display = " ".join(part for part in order if part)
        if display:
            return display
    return None


_DICOM_TM = re.compile(r"^([01]\d|2[0-3])(?::?([0-5]\d)(?::?([0-5]\d|60)(\.\d{1,6})?)?)?$")
"""DICOM TM (PS3.5 §6.2): HH, HHMM, HHMMSS or HHMMSS.FFFFFF, SS up to 60 (a leap second, which FHIR's
``dateTime`` also allows)."""


def _study_date_time(study: Mapping[str, Any]) -> str | None:
    """The study's Study Date (0008,0020), with its Study Time (0008,0030) when the study also gives
    its Timezone Offset From UTC (0008,0201): FHIR R4 ``dateTime`` SHALL have a time zone when it has
    a time (datatypes §2.24.0.1), and a DICOM TM alone is in no stated zone."""
    when = read_study_date(study.get("study_date"))
    if when is None:
        return None
    day = when.isoformat()
    time_match = _DICOM_TM.match(str(study.get("study_time") or ""))
    zone = parse_utc_offset(study.get("timezone_offset_from_utc"))
    if time_match is None or zone is None:
        return day
    hh, mm, ss, fraction = time_match.groups()
    return f"{day}T{hh}:{mm or '00'}:{ss or '00'}{fraction or ''}{iso_offset(zone)}"


_PARTIAL_DATE = re.compile(r"^\d{4}(-(0[1-9]|1[0-2]))?$")


_LEAP_SECOND = re.compile(r"^(\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:)60((\.\d+)?([+-]\d{2}:\d{2}|Z)?)$")
FHIR_HIGHEST_OFFSET = timedelta(hours=14)
"""FHIR R4 ``dateTime``'s zone is at most 14:00 either side of UTC (its regex: ``(0[0-9]|1[0-3]):[0-5][0-9]|14:00``)."""


def _date_time(value: datetime | date | str) -> str | None:
    """A FHIR ``dateTime`` of a datetime, a date or ISO 8601 text; None when the text is no date.

    FHIR R4 dateTime (datatypes §2.24.0.1) is a year, year-month or date, or a date-time to the second
    that SHALL have a time zone of at most 14:00 either side: a date-time without one (a stored film's
    '2024-05-06T10:11:12', a naive datetime) or with a zone no clock has ('+15:00') is read as its date
    alone, the part that is certain; a time with its zone is written to the second in ``isoformat``.
    A leap second (``23:59:60``, which the header reader writes from a DICOM TM ``235960``, PS3.5
    §6.2) is kept: FHIR allows it, Python's datetime does not, so it is checked as ``:59``."""
    if isinstance(value, str):
        text = value.strip()
        if _PARTIAL_DATE.match(text):
            return text
        leap = _LEAP_SECOND.match(text)
        if leap is not None:
            checked = _date_time(f"{leap.group(1)}59{leap.group(2)}")
            return text.replace("Z", "+00:00") if checked is not None and "T" in checked else checked
        try:
            parsed: datetime | date = datetime.fromisoformat(text) if len(text) > 10 else date.fromisoformat(text)
        except ValueError:
            return None
        value = parsed
    if isinstance(value, datetime):
        offset = value.utcoffset()
        if offset is None or abs(offset) > FHIR_HIGHEST_OFFSET:
            return value.date().isoformat()
        return value.isoformat()
    return value.isoformat()


def effective_date_time(
    study: Mapping[str, Any] | None, film_datetime: datetime | date | str | None, created_at: datetime
) -> str:
    """``effectiveDateTime``, the clinically relevant time of the measures: the study's date (and
    time, ``_study_date_time``), else the film's acquisition or content date and time, else the job's
    creation (the landmarks' time when nothing of the films is known). A film's date-time without a
    time zone counts for its date; one that is no date at all (a stored job's malformed value) is
    skipped (``_date_time``)."""
    from_study = _study_date_time(study) if study else None
    if from_study:
        return from_study
    from_film = _date_time(film_datetime) if film_datetime is not None else None
    return from_film or _date_time(created_at) or created_at.date().isoformat()


def _image_note(study: dict[str, Any] | None) -> list[dict[str, Any]]:
    if not study:
        return []
    parts = [
        f"{label} {study[key]}"
        for key, label in (
            ("series_instance_uid", "Series Instance UID"),
            ("pa_sop_instance_uid", "PA image SOP Instance UID"),
            ("lateral_sop_instance_uid", "lateral image SOP Instance UID"),
        )
        if study.get(key)
    ]
    return [{"text": "Measured on DICOM " + "; ".join(parts) + "."}] if parts else []


def observation_bundle(
    job_id: uuid.UUID | str,
    result: dict[str, Any],
    *,
    finished_at: datetime,
    study: dict[str, Any] | None = None,
    created_at: datetime | None = None,
    film_datetime: datetime | date | str | None = None,
    patient_id_system: str | None = None,
) -> dict[str, Any]:
    """The Bundle of a job's measures as FHIR JSON (validated by fhir.resources). ``created_at`` is the
    job's creation (``finished_at`` when not given), ``film_datetime`` the film's acquisition date
    and time when the DICOM layer read one (``effective_date_time``); ``patient_id_system`` is
    ``SPINE_PATIENT_ID_SYSTEM``, the subject identifier's system when the study names no issuer by a URI
    (``_subject``)."""
    measures = result.get("measures") or {}
    fit = result.get("fit") or {}
    version = (result.get("engine") or {}).get("version", "unknown")
    issued = finished_at.isoformat()
    derived = _derived_from(study)
    image_note = _image_note(study)
    subject = _subject(study, patient_id_system)
    effective = effective_date_time(study, film_datetime, created_at or finished_at)

    def observation(key: str, name: str, value: float, *, coding: dict[str, Any], notes: Sequence[str] = (),
                    components: Sequence[dict[str, Any]] = (), estimate: str | None = None,
                    sd: float | None = None, sd_text: str = SD_COMPONENT) -> dict[str, Any]:  # fmt: skip
        """``estimate``: why the value is a model estimate (``model_estimate_reason``), None when measured;
        ``sd``: its SD, a component named ``sd_text`` (``sd_component_text``)."""
        if sd is not None:
            components = [*components, _component(sd_text, valueQuantity=_deg(sd))]
        obs_id = str(uuid.uuid5(_NAMESPACE, f"{job_id}:{key}"))
        estimate_notes = _estimate_notes(estimate, components)
        texts = [{"text": n} for n in [*notes, *estimate_notes]] + image_note
        body: dict[str, Any] = {
            "resourceType": "Observation",
            "id": obs_id,
            "identifier": [{"system": URI, "value": f"urn:uuid:{obs_id}"}],
            "status": "final",
            "category": [{"coding": [{"system": OBSERVATION_CATEGORY, "code": "imaging", "display": "Imaging"}]}],
            "code": _coded(name, coding),
            "effectiveDateTime": effective,
            "issued": issued,
            "valueQuantity": _deg(value),
            "method": _text(f"{METHOD}; spine_engine {version}"),
        }
        if estimate:
            body["interpretation"] = [MODEL_BASED]
        if texts:
            body["note"] = texts
        if derived:
            body["derivedFrom"] = derived
        if subject:
            body["subject"] = subject
        if components:
            body["component"] = list(components)
        return body

    observations: list[dict[str, Any]] = []
    curves = sorted(measures.get("cobb") or [], key=lambda c: not c.get("major"))
    cobb_estimate = model_estimate_reason(fit, "cobb")
    # the plane of maximum curvature and the Cobb angle in it: the prior's without depth, and a curve's
    # whose Cobb angle is the prior's (docs/measures.md, `cobb`), as in the SR
    plane_estimate = model_estimate_reason(fit, "plane_of_max_curvature") or cobb_estimate
    for i, curve in enumerate(curves):
        kind = "major curve" if curve.get("major") else "minor curve"
        components = [
            _component("Upper end vertebra", valueString=curve["upper"]),
            _component("Lower end vertebra", valueString=curve["lower"]),
            _component("Apex vertebra", valueString=curve["apex"]),
            _component("Convexity (patient side)", "CONVEXITY", valueString=curve["convexity"]),
            _component("Major curve", "MAJOR-CURVE", valueBoolean=bool(curve.get("major"))),
            _component("Apical vertebral axial rotation", "APEX-AXROT",
                       valueQuantity=_deg(curve["apex_axial_rotation_deg"]),
                       estimate=model_estimate_reason(fit, "axial_rotation", curve["apex"])),
            _component("Plane of maximum curvature, azimuth from the frontal plane toward anterior", "PMC-ORIENT",
                       valueQuantity=_deg(curve["plane_of_max_curvature_deg"]), estimate=plane_estimate),
            _component("Cobb angle in the plane of maximum curvature", "PMC-COBB",
                       valueQuantity=_deg(curve["max_curvature_deg"]), estimate=plane_estimate),
        ]  # fmt: skip
        if curve.get("endplate_angle_deg") is not None:  # the same estimate as the Cobb angle it is a variant of
            endplates = _deg(curve["endplate_angle_deg"])
            components.append(_component("Cobb angle between end plates, frontal plane", "ENDPLATE-COBB",
                                         valueQuantity=endplates, estimate=cobb_estimate))  # fmt: skip
        note = (
            f"{kind.capitalize()} {curve['upper']}–{curve['lower']}, "
            f"apex {apex_words(curve['apex'], bool(curve.get('apical_disc')))}, "
            f"convex to the patient's {curve['convexity']}."
        )
        observations.append(
            observation(f"cobb:{i}:{curve['upper']}-{curve['lower']}", f"Cobb angle, frontal plane, {kind}",
                        curve["angle_deg"], coding=COBB_ANGLE, notes=[note], components=components,
                        sd=curve.get("angle_sd_deg"), estimate=cobb_estimate,
                        sd_text=sd_component_text(fit, "cobb", tilt_source=curve.get("tilt_source")))
        )  # fmt: skip
    largest = measures.get("largest_cobb")
    if largest and not largest.get("reported_as_curve"):  # no curve of 10°: `cobb` is empty
        ends = f"{largest['upper']}–{largest['lower']}"
        note = f"No frontal curve of 10° or more; the largest frontal angle, between {ends}, the most tilted vertebrae."
        observations.append(
            observation(f"cobb:largest:{largest['upper']}-{largest['lower']}",
                        "Cobb angle, frontal plane, largest (below the 10° of a scoliotic curve)",
                        largest["angle_deg"], coding=COBB_ANGLE, notes=[note], sd=largest.get("angle_sd_deg"),
                        estimate=cobb_estimate,
                        sd_text=sd_component_text(fit, "cobb", tilt_source=largest.get("tilt_source")),
                        components=[_component("Upper end vertebra", valueString=largest["upper"]),
                                    _component("Lower end vertebra", valueString=largest["lower"])])
        )  # fmt: skip
    major = next((c for c in curves if c.get("major")), None)
    for key, name, field, flag, code in (
        ("kyphosis-t4-t12", "Thoracic kyphosis T4–T12 (sagittal Cobb angle)", "thoracic_kyphosis_t4_t12_deg",
         "kyphosis", "KYPH-T4-T12"),
        ("kyphosis-t5-t12", "Thoracic kyphosis T5–T12 (sagittal Cobb angle)", "thoracic_kyphosis_t5_t12_deg",
         "kyphosis", "KYPH-T5-T12"),
        ("lordosis-l1-l5", "Lumbar lordosis L1–L5 (sagittal Cobb angle)", "lumbar_lordosis_l1_l5_deg", "lordosis",
         "LORD-L1-L5"),
    ):  # fmt: skip
        if measures.get(field) is not None:
            sign = "positive when convex posteriorly" if flag == "kyphosis" else "positive when convex anteriorly"
            observations.append(observation(key, name, measures[field], coding=_local(code), notes=[f"Sign: {sign}."],
                                            estimate=model_estimate_reason(fit, flag),
                                            sd=measures.get(field.replace("_deg", "_sd_deg")),
                                            sd_text=sd_component_text(fit, flag)))  # fmt: skip
    if major is not None:
        apex = [v for v in result.get("vertebrae") or [] if v.get("level") == major["apex"]]
        apex_sd = apex[0].get("axial_rotation_sd_deg") if apex else None
        observations.append(
            observation(
                "apical-axial-rotation",
                "Apical vertebral axial rotation of the major curve",
                major["apex_axial_rotation_deg"],
                coding=_local("APEX-AXROT"),
                notes=[f"Apex {major['apex']}; positive toward the patient's left (SRS sense, seen from above)."],
                components=[_component("Apex vertebra", valueString=major["apex"])],
                estimate=model_estimate_reason(fit, "axial_rotation", major["apex"]),
                sd=apex_sd,
                sd_text=sd_component_text(fit, "axial_rotation", level=major["apex"]),
            )
        )
    bundle = {
        "resourceType": "Bundle",
        "id": str(job_id),
        "identifier": {"system": URI, "value": f"urn:uuid:{job_id}"},
        "type": "collection",
        "timestamp": issued,
        "entry": [{"fullUrl": f"urn:uuid:{o['id']}", "resource": o} for o in observations],
    }
    validated: dict[str, Any] = Bundle.model_validate(bundle).model_dump(mode="json", exclude_none=True)
    return validated
