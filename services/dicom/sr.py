"""A job's result as a DICOM Structured Report: TID 1500 Measurement Report (PS3.16), built with highdicom.

Document: Comprehensive 3D SR (PS3.3 §A.35.13), in a new series of the source study, with the
source's patient, accession and study (copied from the source image's header), UIDs derived from
the job id (``uids.py``) so that a resend is the same instance.

Content (PS3.16 TID 1500 → TID 1501 / TID 1410 groups, each measurement a TID 300 item):

- one TID 1501 group per Cobb curve: Cobb angle (285285000, SCT, "Cobb angle"; PS3.16 CID 7550
  Angle Measurement) in degrees (UCUM ``deg``), with finding sites (TID 300 row "Finding Site")
  the upper end vertebra (topographical modifier Superior, 264217000 SCT), the lower end vertebra
  (Inferior, 261089000 SCT) and the apex (Apical, 43674008 SCT), each vertebra by its SNOMED CT
  code from PS3.16 CID 7603 "Vertebra" (``VERTEBRA_CODES``); the curve's apical axial rotation,
  plane and magnitude of maximum curvature in the private scheme; convexity and "major" as
  qualitative evaluations;
- one group for the sagittal measures (kyphosis T4–T12 and T5–T12, lordosis L1–L5) and the fit's
  mean registration error, in the private scheme;
- one group per vertebra: axial rotation, sagittal and frontal bending and twist of its segment;
- one TID 1410 group per landmark (endplate midpoint: POINT; four corners: closed POLYLINE; pedicle
  centres: POINT each) as SCOORD on the source image, when its SOP Instance UID is known and its
  coordinates can be put in pixels (``px``, or ``mm`` with a pixel spacing). SCOORD coordinates are
  (column, row) with (0, 0) the top-left corner of the top-left pixel (PS3.3 §C.18.6.1.1); landmark
  px coordinates are taken in that convention unchanged.

Every measurement carries: its method (private ``MEASURED`` or ``MODEL_BASED``: model-based when
``fit.unreliable`` names its quantity, or for an axial rotation when ``fit.assumed`` names
``population_axial_rotation``, ``model_based``; DESIGN.md; a curve's plane of maximum curvature, the
Cobb angle in it and its endplate variant also when its Cobb angle is, ``cobb``), its standard deviation
when the result gives one as TID 310 upper and lower measurement uncertainty (371886008 / 371885007
SCT) both equal to one SD: the Cobb angles (``angle_sd_deg``), the sagittal measures (``*_sd_deg``),
each vertebra's axial rotation and the curve's apical one (the apex's ``axial_rotation_sd_deg``), and
the endplate variant of a model-estimated Cobb angle (that angle's SD); the result gives none of the
plane of maximum curvature, the Cobb angle in it, a measured endplate variant, bending, twist or the
registration error, and none is written; each group carries the algorithm identification (TID 4019: name, version,
profile), once per group rather than once per measurement (TID 1501 row 5 and TID 300 row 9 both
allow it; per measurement it tripled the document's size and build time).

The private coding scheme ``99SPINE`` (PS3.16 §8: designators beginning "99" are private) is
declared in the Coding Scheme Identification Sequence (0008,0110) (PS3.3 §C.12.1.1.1). Text beyond
ASCII (a patient's name) is written in UTF-8, declared as Specific Character Set ``ISO_IR 192``
(``declare_character_set``).
"""

from __future__ import annotations

import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, date, datetime
from typing import Any, TypeVar

import highdicom as hd
import numpy as np
from highdicom.sr import CodedConcept
from pydicom.dataset import Dataset
from pydicom.sr.codedict import codes
from pydicom.valuerep import DA, DT, TM, PersonName

from services.core.estimates import model_estimate_reason
from spine_client.dicom.datetimes import format_utc_offset, parse_utc_offset
from spine_engine.models import read_study_date

from .cobb_lines import cobb_lines_px
from .uids import job_uids

PRIVATE_SCHEME = "99SPINE"
PRIVATE_SCHEME_NAME = "Spine reconstruction service measures"
PRIVATE_SCHEME_VERSION = "1"

ALGORITHM_NAME = "spine_engine Cosserat-rod registration"
MANUFACTURER = "spine-reconstruction"

VERTEBRA_CODES: dict[str, tuple[str, str]] = {
    "T1": ("64864005", "T1 vertebra"),
    "T2": ("53733008", "T2 vertebra"),
    "T3": ("1626008", "T3 vertebra"),
    "T4": ("73071006", "T4 vertebra"),
    "T5": ("56401006", "T5 vertebra"),
    "T6": ("45296009", "T6 vertebra"),
    "T7": ("62487009", "T7 vertebra"),
    "T8": ("11068009", "T8 vertebra"),
    "T9": ("82687006", "T9 vertebra"),
    "T10": ("7610001", "T10 vertebra"),
    "T11": ("12989004", "T11 vertebra"),
    "T12": ("23215003", "T12 vertebra"),
    "L1": ("66794005", "L1 vertebra"),
    "L2": ("14293000", "L2 vertebra"),
    "L3": ("36470004", "L3 vertebra"),
    "L4": ("11994002", "L4 vertebra"),
    "L5": ("49668003", "L5 vertebra"),
}
"""SNOMED CT codes of the 17 vertebrae, PS3.16 CID 7603 "Vertebra" (as pydicom 3.0.2's
``pydicom/sr/_concepts_dict.py`` lists them: ``codes.SCT.T1Vertebra`` ... ``codes.SCT.L5Vertebra``)."""


UTF8_CHARACTER_SET = "ISO_IR 192"
"""Specific Character Set (0008,0005) of Unicode in UTF-8 (PS3.5 §6.1.2.5.3; PS3.3 §C.12.1.1.2)."""


AnyDataset = TypeVar("AnyDataset", bound=Dataset)


UTC_OFFSET = "+0000"
"""Timezone Offset From UTC (0008,0201) of the SR and SC when the study's offset is not known."""


def stamp_content_time(ds: AnyDataset, when: datetime | None, dates: Sequence[str], times: Sequence[str],
                       study_offset: str | None = None) -> AnyDataset:  # fmt: skip
    """Write ``when`` (the job's end; now when None) into the DA attributes ``dates`` and TM ``times``,
    highdicom's Contributing Equipment entry's ContributionDateTime (a DT, with its own offset), and
    Timezone Offset From UTC (0008,0201). That attribute dates every DA and TM of the instance (PS3.3
    §C.12.1.1.8), the Study Date and Time copied from the film included, so: with the film's own offset
    ``study_offset`` (a valid ``&ZZXX``, ``datetimes.parse_utc_offset``) the instance takes it and
    ``when`` is written in that zone, and the film's study time keeps its meaning; without one (absent
    or ignored as malformed) ``+0000`` and ``when`` in UTC, which also declares the study time UTC. A
    datetime without a zone is taken as UTC (the job's timestamps are)."""
    zone = parse_utc_offset(study_offset) or UTC
    when = datetime.now(UTC) if when is None else when
    when = (when if when.tzinfo is not None else when.replace(tzinfo=UTC)).astimezone(zone)
    for keyword in dates:
        setattr(ds, keyword, DA(when.date()))
    for keyword in times:
        setattr(ds, keyword, TM(when.time().replace(tzinfo=None)))
    for item in ds.get("ContributingEquipmentSequence") or []:  # highdicom's own entry, dated now
        item.ContributionDateTime = DT(when)
    ds.TimezoneOffsetFromUTC = format_utc_offset(zone) if zone is not UTC else UTC_OFFSET
    return ds


def ds_number(value: float) -> float:
    """``value`` as a float to be written as a DS (a NUM's Numeric Value, PS3.5 §6.2: at most 16 bytes,
    pydicom's ``format_number_as_ds``), with a zero always positive: ``-0.0`` (an angle the fit
    computes as a negative zero) would be written ``"-0.0"``, a signed zero a reader may show as
    "-0 deg". Every other value keeps its sign: DS rounds none of them to zero (it keeps 10
    significant digits, in scientific notation below 1e-4)."""
    number = float(value)
    return 0.0 if number == 0 else number


def declare_character_set(ds: AnyDataset) -> AnyDataset:
    """``ds`` with Specific Character Set (0008,0005) ``ISO_IR 192`` when a text value of it or of its
    sequences is not ASCII (a patient's name "Müller^Jürgen", one in ideographs), as PS3.3 §C.12.1.1.2
    requires of a dataset using other than the default repertoire (ISO-IR 6, ASCII): without it pydicom
    writes such text in Latin-1 or as "?", and a reader decodes it as ASCII."""
    for element in ds.iterall():
        values = element.value if isinstance(element.value, list | tuple) else [element.value]
        if any(isinstance(v, str | PersonName) and not str(v).isascii() for v in values):
            ds.SpecificCharacterSet = UTF8_CHARACTER_SET
            break
    return ds


def _private(value: str, meaning: str) -> CodedConcept:
    return CodedConcept(value, PRIVATE_SCHEME, meaning, PRIVATE_SCHEME_VERSION)


class PrivateCodes:
    """The private scheme's concepts (code value SH, at most 16 characters; meaning LO, at most 64)."""

    KYPHOSIS_T4_T12 = _private("KYPH-T4-T12", "Thoracic kyphosis T4-T12")
    KYPHOSIS_T5_T12 = _private("KYPH-T5-T12", "Thoracic kyphosis T5-T12")
    LORDOSIS_L1_L5 = _private("LORD-L1-L5", "Lumbar lordosis L1-L5")
    APEX_AXIAL_ROTATION = _private("APEX-AXROT", "Axial rotation of the apical vertebra")
    PLANE_MAX_CURVATURE = _private("PMC-ORIENT", "Orientation of the plane of maximum curvature")
    MAX_CURVATURE = _private("PMC-COBB", "Cobb angle in the plane of maximum curvature")
    ENDPLATE_ANGLE = _private("ENDPLATE-COBB", "Cobb angle between the end vertebrae's endplates")
    AXIAL_ROTATION = _private("AXROT", "Vertebral axial rotation")
    SAGITTAL_BENDING = _private("SAG-BEND", "Sagittal bending of the segment below the vertebra")
    FRONTAL_BENDING = _private("FRONT-BEND", "Frontal bending of the segment below the vertebra")
    TWIST = _private("TWIST", "Twist of the segment below the vertebra")
    REGISTRATION_ERROR = _private("REG-ERR", "Mean registration error of the PA landmarks")
    MISFIT_RATIO = _private("MISFIT-RATIO", "Landmark misfit ratio against the stated landmark SD")
    COBB_LINES = _private("COBB-LINES", "Lines across the end vertebrae (upper, then lower)")
    MEASURED = _private("MEASURED", "Measured (determined by the image landmarks)")
    MODEL_BASED = _private("MODEL-BASED", "Model-based estimate (from the spine model's prior)")
    CONVEXITY = _private("CONVEXITY", "Convexity of the curve")
    MAJOR_CURVE = _private("MAJOR-CURVE", "Major curve (the largest)")
    ENDPLATE_MIDPOINT = _private("LM-EP-MID", "Landmark: midpoint of the superior endplate")
    BODY_CORNERS = _private("LM-CORNERS", "Landmark: four corners of the vertebral body")
    PEDICLE_LEFT = _private("LM-PED-IMG-L", "Landmark: pedicle centre on the image's left")
    PEDICLE_RIGHT = _private("LM-PED-IMG-R", "Landmark: pedicle centre on the image's right")


DEGREE = CodedConcept("deg", "UCUM", "degree")
MILLIMETRE = CodedConcept("mm", "UCUM", "millimeter")
NO_UNITS = CodedConcept("1", "UCUM", "no units")
"""A ratio's unit (PS3.16 CID 7181 "Abstract Multi-dimensional Image Model Component Units": (1, UCUM, "no units"))."""
COBB_ANGLE = CodedConcept("285285000", "SCT", "Cobb angle")
SUPERIOR, INFERIOR, APICAL = codes.SCT.Superior, codes.SCT.Inferior, codes.SCT.Apical
PROCEDURE = CodedConcept("363680008", "SCT", "Radiographic imaging procedure")
CORNERSTONE_COBB_ANGLE = "Cornerstone3DTools@^0.1.0:CobbAngle"
"""The tracking identifier by which ``@cornerstonejs/adapters`` (what OHIF loads SR measurements with)
recognises a Cobb angle: its ``CORNERSTONE_3D_TAG`` and tool type (``Cornerstone3D/cornerstone3DTag.js``,
``CobbAngle.ts``, ``BaseAdapter3D.init``)."""


@dataclass(frozen=True)
class SourceImage:
    """A radiograph the landmarks were placed on, as far as it is known."""

    sop_instance_uid: str
    sop_class_uid: str
    series_instance_uid: str | None = None
    study_instance_uid: str | None = None
    pixel_spacing: tuple[float, float] | None = None
    """[row, column] mm per pixel of the landmarks' mm (for mm → px); None when the landmarks are in px."""


@dataclass(frozen=True)
class StudyIdentity:
    """The study and patient the results belong to (from the source header or the job's ``study``)."""

    study_instance_uid: str | None = None
    patient_id: str | None = None
    patient_name: str | None = None
    accession_number: str | None = None
    study_date: date | None = None
    study_time: str | None = None
    study_id: str | None = None
    patient_birth_date: str | None = None
    patient_sex: str | None = None
    referring_physician_name: str | None = None
    timezone_offset_from_utc: str | None = None
    """The film's Timezone Offset From UTC (0008,0201) as DICOM writes it (``+0100``): the zone of its
    Study Date and Time (``stamp_content_time``)."""
    issuer_of_patient_id: str | None = None
    universal_entity_id: str | None = None
    universal_entity_id_type: str | None = None
    """Who issued the Patient ID: Issuer of Patient ID (0010,0021) and the Universal Entity ID (0040,0032) with
    its Type (0040,0033) of Issuer of Patient ID Qualifiers Sequence (0010,0024) (the study's
    ``patient_id_issuer``; ``write_patient_id_issuer``)."""

    @classmethod
    def from_study(cls, study: Mapping[str, Any] | None) -> StudyIdentity:
        study = study or {}
        when = study.get("study_date")
        issuer = study.get("patient_id_issuer")
        issuer = issuer if isinstance(issuer, Mapping) else {}
        return cls(
            issuer_of_patient_id=issuer.get("issuer_of_patient_id"),
            universal_entity_id=issuer.get("universal_entity_id"),
            universal_entity_id_type=issuer.get("universal_entity_id_type"),
            study_instance_uid=study.get("study_instance_uid"),
            patient_id=study.get("patient_id"),
            patient_name=study.get("patient_name"),
            accession_number=study.get("accession_number"),
            study_date=read_study_date(when),
            study_time=study.get("study_time"),
            study_id=study.get("study_id"),
            patient_birth_date=study.get("patient_birth_date"),
            patient_sex=study.get("patient_sex"),
            referring_physician_name=study.get("referring_physician_name"),
            timezone_offset_from_utc=study.get("timezone_offset_from_utc"),
        )


def write_patient_id_issuer(ds: AnyDataset, identity: StudyIdentity) -> AnyDataset:
    """``ds`` with the issuer of its Patient ID as the film has it (Patient Module, PS3.3 §C.7.1.1: a new series
    of the film's study repeats its patient): Issuer of Patient ID (0010,0021) when known, and Issuer of
    Patient ID Qualifiers Sequence (0010,0024) with one item, Universal Entity ID (0040,0032) and its Type
    (0040,0033), when the issuer's universal ID is known (the Type is required with the ID, Type 1C). Both
    are Type 3: nothing is written when unknown."""
    if identity.issuer_of_patient_id:
        ds.IssuerOfPatientID = identity.issuer_of_patient_id
    if identity.universal_entity_id and identity.universal_entity_id_type:
        item = Dataset()
        item.UniversalEntityID = identity.universal_entity_id
        item.UniversalEntityIDType = identity.universal_entity_id_type
        ds.IssuerOfPatientIDQualifiersSequence = [item]
    return ds


def _evidence(identity: StudyIdentity, study_uid: str, image: SourceImage | None, fallback_uid: str) -> Dataset:
    ds = Dataset()
    ds.StudyInstanceUID = (image.study_instance_uid if image and image.study_instance_uid else None) or study_uid
    ds.SeriesInstanceUID = (image.series_instance_uid if image else None) or fallback_uid
    ds.SOPInstanceUID = image.sop_instance_uid if image else fallback_uid
    ds.SOPClassUID = image.sop_class_uid if image else "1.2.840.10008.5.1.4.1.1.7"
    ds.PatientID = identity.patient_id or ""
    ds.PatientName = identity.patient_name or ""
    ds.PatientBirthDate = identity.patient_birth_date or ""
    ds.PatientSex = identity.patient_sex or ""
    ds.AccessionNumber = identity.accession_number or ""
    ds.StudyID = identity.study_id or ""
    ds.StudyDate = identity.study_date.strftime("%Y%m%d") if identity.study_date else ""
    ds.StudyTime = identity.study_time or ""
    ds.ReferringPhysicianName = identity.referring_physician_name or ""
    return ds


def model_based(fit: Mapping[str, Any], quantity: str | None, level: str | None = None) -> bool:
    """Whether a value of the result is a model-based estimate (``MODEL_BASED``) rather than measured:
    ``services.core.estimates.model_estimate_reason``'s rule, which the FHIR export's notes also follow."""
    return quantity is not None and model_estimate_reason(fit, quantity, level) is not None


class _Builder:
    def __init__(self, result: Mapping[str, Any], algorithm: hd.sr.AlgorithmIdentification, job_id: uuid.UUID):
        self.result = result
        self.algorithm = algorithm
        self.fit: Mapping[str, Any] = result.get("fit") or {}
        self.job_id = job_id
        self.groups: list[Any] = []

    def measurement(self, name: CodedConcept, value: float | None, *, unit: CodedConcept = DEGREE,
                    quantity: str | tuple[str, ...] | None = None, level: str | None = None,
                    sd: float | None = None,
                    sites: Sequence[hd.sr.FindingSite] = ()) -> hd.sr.Measurement | None:  # fmt: skip
        """A TID 300 NUM of ``value`` in ``unit``: method ``MODEL_BASED`` when ``model_based`` says so of
        ``quantity`` (or of any of several: a value that depends on each), else ``MEASURED``; ``sd`` (1 SD,
        in ``unit``) as TID 310 upper and lower measurement uncertainty. None when ``value`` is None."""
        if value is None:
            return None
        properties = None
        if sd is not None:
            properties = hd.sr.MeasurementProperties(upper_measurement_uncertainty=ds_number(sd),
                                                     lower_measurement_uncertainty=ds_number(sd))  # fmt: skip
            for item in properties:  # highdicom writes (1, UCUM, "no units"); an SD has the value's unit
                if item.ValueType == "NUM":
                    item.MeasuredValueSequence[0].MeasurementUnitsCodeSequence = [unit]
        quantities = (quantity,) if isinstance(quantity, str) else quantity or ()
        estimate = any(model_based(self.fit, q, level) for q in quantities)
        method = PrivateCodes.MODEL_BASED if estimate else PrivateCodes.MEASURED
        return hd.sr.Measurement(
            name=name, value=ds_number(value), unit=unit, method=method, properties=properties,
            finding_sites=list(sites) or None,
        )  # fmt: skip

    def group(self, label: str, measurements: Sequence[hd.sr.Measurement | None], *,
              sites: Sequence[hd.sr.FindingSite] = (),
              evaluations: Sequence[hd.sr.QualitativeEvaluation] = (),
              lines: tuple[hd.sr.ImageRegion, hd.sr.ScoordContentItem] | None = None) -> None:  # fmt: skip
        """A TID 1501 group, or with ``lines`` (a Cobb angle drawn on the film) a TID 1410 group whose
        image region they are, tracked as the Cornerstone adapters' CobbAngle (``_cobb_lines``)."""
        items = [m for m in measurements if m is not None]
        if not items and not evaluations:
            return
        uid = _tracking_uid(self.job_id, label)
        common: dict[str, Any] = {
            "algorithm_id": self.algorithm, "finding_sites": list(sites) or None, "measurements": items or None,
            "qualitative_evaluations": list(evaluations) or None,
        }  # fmt: skip
        if lines is None:
            tracking = hd.sr.TrackingIdentifier(uid=uid, identifier=label)
            self.groups.append(hd.sr.MeasurementsAndQualitativeEvaluations(tracking_identifier=tracking, **common))
            return
        region, scoord = lines
        tracking = hd.sr.TrackingIdentifier(uid=uid, identifier=CORNERSTONE_COBB_ANGLE)
        group = hd.sr.PlanarROIMeasurementsAndQualitativeEvaluations(
            tracking_identifier=tracking, referenced_region=region, **common)  # fmt: skip
        # the lines under the first NUM, the Cobb angle, where the adapters look for them; TID 300 allows
        # an INFERRED FROM SCOORD (TID 320), highdicom's constructor does not, so it is added after
        [num] = [item for item in group[0].ContentSequence if item.ValueType == "NUM" and item.name == COBB_ANGLE]
        num.ContentSequence.append(scoord)
        self.groups.append(group)


def _cobb_lines(
    result: Mapping[str, Any], payload: Mapping[str, Any], curve: Mapping[str, Any], image: SourceImage | None,
    cobb: hd.sr.Measurement | None,
) -> tuple[hd.sr.ImageRegion, hd.sr.ScoordContentItem] | None:  # fmt: skip
    """A Cobb curve's two endplate lines on the PA film (``cobb_lines.cobb_lines_px``), written as the
    Cornerstone adapters read a CobbAngle (module docstring): the four points as one image SCOORD
    POLYLINE under the Cobb angle's NUM (INFERRED FROM, the image SELECTED FROM), and the group's
    image region, the closed quadrilateral they bound (TID 1410 row 7). None without the PA image or
    its pixel spacing."""
    if image is None or image.pixel_spacing is None or cobb is None:
        return None
    points = cobb_lines_px(result, payload, curve, image.pixel_spacing)
    if points is None:
        return None
    def source() -> hd.sr.SourceImageForRegion:
        return hd.sr.SourceImageForRegion(referenced_sop_class_uid=image.sop_class_uid,
                                          referenced_sop_instance_uid=image.sop_instance_uid)  # fmt: skip

    lines = hd.sr.ScoordContentItem(
        name=PrivateCodes.COBB_LINES, graphic_type=hd.sr.GraphicTypeValues.POLYLINE, graphic_data=points,
        relationship_type=hd.sr.RelationshipTypeValues.INFERRED_FROM,
    )  # fmt: skip
    lines.ContentSequence = hd.sr.ContentSequence([source()])
    p1, p2, p3, p4 = points
    region = hd.sr.ImageRegion(graphic_type="POLYLINE", graphic_data=np.array([p1, p2, p4, p3, p1]),
                               source_image=source())  # fmt: skip
    return region, lines


def _tracking_uid(job_id: uuid.UUID, label: str) -> str:
    return f"2.25.{uuid.uuid5(job_id, label).int}"


def vertebra(level: str, modifier: Any = None) -> hd.sr.FindingSite:
    code, meaning = VERTEBRA_CODES[level]
    return hd.sr.FindingSite(anatomic_location=CodedConcept(code, "SCT", meaning), topographical_modifier=modifier)


def _landmark_regions(builder: _Builder, payload: Mapping[str, Any], view: str, image: SourceImage) -> None:
    """TID 1410 groups: each landmark as SCOORD on ``image`` (module docstring)."""
    spec = payload.get(view) or {}
    units = spec.get("units", "mm")
    if units == "mm":
        if image.pixel_spacing is None:
            return
        row_mm, col_mm = image.pixel_spacing
    else:
        row_mm = col_mm = 1.0
    source = hd.sr.SourceImageForRegion(referenced_sop_class_uid=image.sop_class_uid,
                                        referenced_sop_instance_uid=image.sop_instance_uid)  # fmt: skip

    def px(points: Sequence[Sequence[float]]) -> np.ndarray:
        return np.array([[p[0] / col_mm, p[1] / row_mm] for p in points], dtype=float)

    for lm in spec.get("landmarks") or []:
        level = lm["level"]
        shapes: list[tuple[CodedConcept, str, np.ndarray]] = []
        if lm.get("point") is not None:
            shapes.append((PrivateCodes.ENDPLATE_MIDPOINT, "POINT", px([lm["point"]])))
        if lm.get("corners") is not None:
            tl, tr, bl, br = lm["corners"]
            shapes.append((PrivateCodes.BODY_CORNERS, "POLYLINE", px([tl, tr, br, bl, tl])))
        if lm.get("pedicles") is not None:
            left, right = lm["pedicles"]
            shapes.append((PrivateCodes.PEDICLE_LEFT, "POINT", px([left])))
            shapes.append((PrivateCodes.PEDICLE_RIGHT, "POINT", px([right])))
        for kind, graphic_type, data in shapes:
            label = f"{view} {level} {kind.value}"
            builder.groups.append(hd.sr.PlanarROIMeasurementsAndQualitativeEvaluations(
                tracking_identifier=hd.sr.TrackingIdentifier(uid=_tracking_uid(builder.job_id, label),
                                                             identifier=label),
                referenced_region=hd.sr.ImageRegion(graphic_type=graphic_type, graphic_data=data, source_image=source),
                finding_type=kind, finding_sites=[vertebra(level)], algorithm_id=builder.algorithm,
            ))  # fmt: skip


def build_sr(
    result: Mapping[str, Any] | Any,
    payload: Mapping[str, Any],
    job_id: uuid.UUID | str,
    identity: StudyIdentity,
    images: Mapping[str, SourceImage] | None = None,
    *,
    series_number: int = 9901,
    content_datetime: datetime | None = None,
) -> hd.sr.Comprehensive3DSR:
    """The SR of one job (module docstring). ``result`` is a ``RegistrationResult`` or its JSON,
    ``payload`` the job's payload (JSON), ``images`` the source radiographs by view (``pa``,
    ``lateral``) when known. Without a study UID (a job without ``study``) the SR opens a new study
    whose UID is derived from the job id. ``content_datetime`` (e.g. the job's end) is the Content
    and Instance Creation Date/Time, in the film's zone when its offset is known, else in UTC with
    Timezone Offset From UTC ``+0000`` (``stamp_content_time``), so that every build of a job is the
    same bytes; without it they are the build's time."""
    if hasattr(result, "model_dump"):
        result = result.model_dump(mode="json")
    job = uuid.UUID(str(job_id))
    uids = job_uids(job)
    images = dict(images or {})
    study_uid = identity.study_instance_uid or uids["study"]
    engine = result.get("engine") or {}
    algorithm = hd.sr.AlgorithmIdentification(
        name=ALGORITHM_NAME, version=str(engine.get("version", "unknown")),
        parameters=[f"profile={engine.get('profile', 'default')}"],
    )  # fmt: skip
    b = _Builder(result, algorithm, job)
    measures = result.get("measures") or {}

    rotation_sd = {v["level"]: v.get("axial_rotation_sd_deg") for v in result.get("vertebrae") or []}
    cobb_estimated = model_based(b.fit, "cobb")
    for i, c in enumerate(measures.get("cobb") or [], start=1):
        sites = [vertebra(c["upper"], SUPERIOR), vertebra(c["lower"], INFERIOR), vertebra(c["apex"], APICAL)]
        cobb_sd = c.get("angle_sd_deg")
        cobb = b.measurement(COBB_ANGLE, c["angle_deg"], sd=cobb_sd, quantity="cobb", sites=sites)
        b.group(
            f"Cobb curve {i} {c['upper']}-{c['lower']}",
            [
                cobb,
                # the apex's own SD (the result's vertebra); the plane and the angle in it have none in the
                # result, and are the prior's too when the curve's Cobb angle is (docs/measures.md: `cobb`)
                b.measurement(PrivateCodes.APEX_AXIAL_ROTATION, c.get("apex_axial_rotation_deg"),
                              quantity="axial_rotation", level=c["apex"], sd=rotation_sd.get(c["apex"]),
                              sites=[vertebra(c["apex"], APICAL)]),
                b.measurement(PrivateCodes.PLANE_MAX_CURVATURE, c.get("plane_of_max_curvature_deg"),
                              quantity=("plane_of_max_curvature", "cobb")),
                b.measurement(PrivateCodes.MAX_CURVATURE, c.get("max_curvature_deg"),
                              quantity=("plane_of_max_curvature", "cobb")),
                # the endplate variant of a model-estimated Cobb angle is the same estimate (its value is the
                # angle's when no corners drew the endplates): its mark and its SD; measured, the result has
                # no SD of it
                b.measurement(PrivateCodes.ENDPLATE_ANGLE, c.get("endplate_angle_deg"), quantity="cobb",
                              sd=cobb_sd if cobb_estimated else None),
            ],
            sites=sites,
            evaluations=[
                hd.sr.QualitativeEvaluation(PrivateCodes.CONVEXITY,
                                            codes.SCT.Left if c["convexity"] == "left" else codes.SCT.Right),
                hd.sr.QualitativeEvaluation(PrivateCodes.MAJOR_CURVE,
                                            codes.SCT.Yes if c.get("major") else codes.SCT.No),
            ],
            lines=_cobb_lines(result, payload, c, images.get("pa"), cobb),
        )  # fmt: skip

    largest = measures.get("largest_cobb")
    if largest and not largest.get("reported_as_curve"):  # no curve of 10°: `cobb` is empty
        sites = [vertebra(largest["upper"], SUPERIOR), vertebra(largest["lower"], INFERIOR)]
        cobb = b.measurement(COBB_ANGLE, largest["angle_deg"], sd=largest.get("angle_sd_deg"), quantity="cobb",
                             sites=sites)  # fmt: skip
        b.group(f"Largest frontal angle {largest['upper']}-{largest['lower']}, below 10°", [cobb], sites=sites,
                evaluations=[hd.sr.QualitativeEvaluation(PrivateCodes.MAJOR_CURVE, codes.SCT.No)],
                lines=_cobb_lines(result, payload, largest, images.get("pa"), cobb))  # fmt: skip

    fit = result.get("fit") or {}
    b.group("Sagittal measures", [
        b.measurement(PrivateCodes.KYPHOSIS_T4_T12, measures.get("thoracic_kyphosis_t4_t12_deg"), quantity="kyphosis",
                      sd=measures.get("thoracic_kyphosis_t4_t12_sd_deg"),
                      sites=[vertebra("T4", SUPERIOR), vertebra("T12", INFERIOR)]),
        b.measurement(PrivateCodes.KYPHOSIS_T5_T12, measures.get("thoracic_kyphosis_t5_t12_deg"), quantity="kyphosis",
                      sd=measures.get("thoracic_kyphosis_t5_t12_sd_deg"),
                      sites=[vertebra("T5", SUPERIOR), vertebra("T12", INFERIOR)]),
        b.measurement(PrivateCodes.LORDOSIS_L1_L5, measures.get("lumbar_lordosis_l1_l5_deg"), quantity="lordosis",
                      sd=measures.get("lumbar_lordosis_l1_l5_sd_deg"),
                      sites=[vertebra("L1", SUPERIOR), vertebra("L5", INFERIOR)]),
        b.measurement(PrivateCodes.REGISTRATION_ERROR, fit.get("mean_registration_error_mm"), unit=MILLIMETRE),
        b.measurement(PrivateCodes.MISFIT_RATIO, fit.get("landmark_misfit_ratio"), unit=NO_UNITS),
    ])  # fmt: skip

    for v in result.get("vertebrae") or []:
        level = v["level"]
        sagittal = v.get("sagittal_bending_deg", v.get("pa_bending_deg"))
        frontal = v.get("frontal_bending_deg", v.get("lateral_bending_deg"))
        b.group(f"Vertebra {level}", [
            b.measurement(PrivateCodes.AXIAL_ROTATION, v.get("axial_rotation_deg"), quantity="axial_rotation",
                          level=level, sd=v.get("axial_rotation_sd_deg")),
            b.measurement(PrivateCodes.SAGITTAL_BENDING, sagittal, quantity="kyphosis"),
            b.measurement(PrivateCodes.FRONTAL_BENDING, frontal),
            b.measurement(PrivateCodes.TWIST, v.get("twist_deg"), quantity="twist"),
        ], sites=[vertebra(level)])  # fmt: skip

    for view, image in images.items():
        _landmark_regions(b, payload, view, image)

    device = hd.sr.ObserverContext(
        observer_type=codes.DCM.Device,
        observer_identifying_attributes=hd.sr.DeviceObserverIdentifyingAttributes(
            uid=uids["device"], name=MANUFACTURER, manufacturer_name=MANUFACTURER, model_name="spine_engine",
        ),
    )  # fmt: skip
    report = hd.sr.MeasurementReport(
        observation_context=hd.sr.ObservationContext(observer_device_context=device),
        procedure_reported=PROCEDURE,
        imaging_measurements=b.groups,
        title=codes.DCM.ImagingMeasurementReport,
    )
    evidence = [_evidence(identity, study_uid, image, uids["sr"]) for image in images.values()]
    if not evidence:
        evidence = [_evidence(identity, study_uid, None, uids["sr"])]
    sr = hd.sr.Comprehensive3DSR(
        evidence=evidence, content=report, series_instance_uid=uids["sr-series"], series_number=series_number,
        sop_instance_uid=uids["sr"], instance_number=1, manufacturer=MANUFACTURER, is_complete=True,
        series_description="Spine reconstruction measurements",
    )  # fmt: skip
    stamp_content_time(sr, content_datetime, ("ContentDate", "InstanceCreationDate"),
                       ("ContentTime", "InstanceCreationTime"), identity.timezone_offset_from_utc)  # fmt: skip
    if not images:
        for keyword in ("CurrentRequestedProcedureEvidenceSequence", "PertinentOtherEvidenceSequence"):
            if keyword in sr:
                delattr(sr, keyword)
    scheme = Dataset()
    scheme.CodingSchemeDesignator = PRIVATE_SCHEME
    scheme.CodingSchemeName = PRIVATE_SCHEME_NAME
    scheme.CodingSchemeVersion = PRIVATE_SCHEME_VERSION
    scheme.CodingSchemeResponsibleOrganization = MANUFACTURER
    sr.CodingSchemeIdentificationSequence = [scheme]
    return declare_character_set(write_patient_id_issuer(sr, identity))
