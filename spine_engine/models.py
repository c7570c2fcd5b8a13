"""Pydantic models of the job payload (what a client posts) and the result (what it reads back).

These models are the public contract shared by the engine, the API and ``openapi.yaml``.
Conventions (``DESIGN.md``): 3D frame DICOM LPS in mm (+x patient left, +y posterior,
+z superior); directors d1 ≈ patient left, d2 ≈ anterior, d3 = centreline tangent pointing
caudally, d1 × d2 = d3; directors are sent as rows ``[d1, d2, d3]``.
"""

from __future__ import annotations

import math
import re
from datetime import date
from typing import Annotated, Literal, get_args

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    Strict,
    TypeAdapter,
    ValidationError,
    WithJsonSchema,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from .levels import LEVEL_INDEX, Level

DIRECTOR_TOLERANCE = 1e-3
"""Largest accepted |RᵀR − I| entry and |det R − 1| for boundary directors."""

MAX_LANDMARKS_PER_VIEW = 17 * 6
"""Upper bound on landmark entries per view (17 levels; leaves room for later landmark kinds)."""

PATIENT_DIRECTIONS = ("L", "R", "A", "P", "H", "F")
PATIENT_AXES: dict[str, tuple[float, float, float]] = {
    "L": (1.0, 0.0, 0.0),
    "R": (-1.0, 0.0, 0.0),
    "P": (0.0, 1.0, 0.0),
    "A": (0.0, -1.0, 0.0),
    "H": (0.0, 0.0, 1.0),
    "F": (0.0, 0.0, -1.0),
}
"""LPS unit vector of each DICOM patient-direction letter (PS3.3 C.7.6.1.1.1, Patient Orientation)."""

_LAX_DATE: TypeAdapter[date] = TypeAdapter(date)
"""pydantic's lax ``date``: how ``Study.study_date`` read a posted value before it took only YYYY-MM-DD."""

MAX_COORDINATE = 1e6
"""Largest accepted |coordinate| (mm or px): a metre-scale spine never comes near it, and larger
numbers only overflow the fit."""

Number = Annotated[float, Strict()]
"""A number of the payload: a JSON number, an integer (``1`` is taken as ``1.0``) or not, and never a string
(``"1.0"``) nor a boolean (``true``), which pydantic's lax mode would otherwise turn into 1.0: a client that
sends either where the contract says number gets a validation error naming the field (``float_type``).
Every number type of the payload below is built on it. Strict ``float`` takes Python ``int`` and ``float``
(numpy's floats and ints, ``Decimal`` too) and refuses ``str`` and ``bool`` (pydantic 2 conversion table,
``float`` in strict mode); the JSON schema is unchanged (``type: number``)."""
FiniteFloat = Annotated[Number, Field(allow_inf_nan=False, ge=-MAX_COORDINATE, le=MAX_COORDINATE)]
PositiveFactor = Annotated[Number, Field(gt=0, le=1e3, allow_inf_nan=False)]
DistanceMm = Annotated[Number, Field(gt=0, le=1e5, allow_inf_nan=False)]
"""A positive distance in mm (source-to-detector and source-to-patient distances are 1–5 m)."""
Vec2 = tuple[FiniteFloat, FiniteFloat]
PositiveCoordinate = Annotated[Number, Field(gt=0, le=MAX_COORDINATE, allow_inf_nan=False)]
Vec3 = tuple[FiniteFloat, FiniteFloat, FiniteFloat]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


# ---------------------------------------------------------------- payload


class Landmark(_Strict):
    """A landmark of one vertebra on one view, as image (column, row) in the view's units: either
    the midpoint of its top endplate (``point``, the paper's form) or its four corners
    (``corners``, the AASCE 2019 form), exactly one of the two; optionally its two pedicle centres.
    """

    level: Level = Field(description="Vertebral level, T1..L5.")
    point: Vec2 | None = Field(
        None, description="Midpoint of the superior endplate, image (column, row). Exactly one of point / corners."
    )
    corners: tuple[Vec2, Vec2, Vec2, Vec2] | None = Field(
        None,
        description="The vertebral body's four corners as they appear in the image: top-left, top-right, "
        "bottom-left, bottom-right (column, row). The superior endplate midpoint is fitted as the point; the "
        "line from the left-edge midpoint to the right-edge midpoint constrains the vertebra's tilt. Needs an "
        "upright view (rows toward F or H). Exactly one of point / corners.",
    )
    pedicles: tuple[Vec2, Vec2] | None = Field(
        None,
        description="Centres of the two pedicles, image-left then image-right (column, row); PA (frontal) "
        "view only. Their columns make axial rotation observable (docs/measures.md).",
    )

    @model_validator(mode="after")
    def _one_form(self) -> Landmark:
        if self.point is None and self.corners is None:
            raise PydanticCustomError("landmark_point_missing", "a landmark needs either point or corners")
        if self.point is not None and self.corners is not None:
            raise PydanticCustomError("landmark_point_and_corners", "give either point or corners, not both")
        return self


class Projection(_Strict):
    """Weak perspective of a view: image point = scale·(e_c·r, e_r·r) + translation (mm)."""

    scale: PositiveFactor = Field(
        description="Dimensionless magnification s from patient mm to detector mm."
    )
    translation: Vec2 = Field(description="Translation T (column, row) in detector mm.")


LANDMARK_SD_MM_MIN = 1e-3
"""Smallest ``landmark_sd_mm`` a view may state, mm: a thousandth of the inter-rater errors of experts
placing vertebral landmarks (``LANDMARK_SD_MM_DEFAULT``'s source). Below it the fit's landmark weights
(1/σ²) swamp the rod's: stated at 1e-5 mm on the test payload of one PA film the fit stops after 500
iterations without converging, and at 1e-9 mm every reported SD reads 0 (``tests/engine/test_landmark_sd.py``)."""

LANDMARK_SD_MM_DEFAULT = 1.0
"""Default 1 SD of a clicked landmark per image coordinate, detector mm, when a view gives no
``landmark_sd_mm``: the order of the inter-rater point-location errors of experts placing vertebral
landmarks on AP and lateral radiographs (Jang, Kim, Ku, Lee, "Reliability Analysis of Vertebral
Landmark Labelling on Lumbar Spine X-ray Images", Diagnostics 2023;13(8):1411,
doi:10.3390/diagnostics13081411; 12 raters, 1000 image pairs) and the ~1 mm of the issue's
benchmark noise (DESIGN.md, "The clinic's inputs")."""

PixelSpacingCalibration = Literal["calibrated", "projection", "detector", "unknown"]


FULL_SPINE_SID_MM = 1800.0
"""Source–image distance assumed for a point-source film that states neither SID nor SOD, mm: the
usual full-spine distance of about 1.8 m (72 inches), ``clinical.PA_MAGNIFICATION_PRIOR``'s geometry."""
SPINE_TO_DETECTOR_MM = 200.0
"""Distance from the spine's mid-plane to the detector assumed for a point-source film that states
only one of SID and SOD and no magnification, mm (SOD = SID − 200 = 1600 at 1.8 m:
``clinical.PA_MAGNIFICATION_PRIOR``'s geometry)."""


class Acquisition(_Strict):
    """How a radiograph was taken, when known (all optional). SID and SOD together give a pinhole
    (perspective) projection, as does projection_model "perspective" with the geometry it lacks assumed;
    otherwise the view is fitted with a weak perspective."""

    magnification: PositiveFactor | None = Field(
        None,
        description="Estimated radiographic magnification factor (DICOM (0018,1114) ERMF, dimensionless): "
        "detector mm per patient mm at the spine. Fixes the view's scale instead of the model's prior.",
    )
    distance_source_to_detector_mm: DistanceMm | None = Field(
        None,
        description="Source-to-image distance SID, mm (DICOM (0018,1110)). With distance_source_to_patient_mm "
        "the view is projected in perspective.",
    )
    distance_source_to_patient_mm: DistanceMm | None = Field(
        None,
        description="Source to the spine's mid-plane SOD, mm (DICOM (0018,1111) measures it to the isocentre / "
        "patient; here it is taken as the distance to the plane through the spine). Must be below the SID.",
    )
    central_ray: Vec2 | None = Field(
        None,
        description="Where the central ray (the perpendicular from the source) meets the detector, image "
        "(column, row) in the view's units. When absent: the image's centre if image_size is given (with SID and "
        "SOD; fit.assumed then names central_ray_at_image_centre), else estimated in the fit.",
    )
    image_size: tuple[PositiveCoordinate, PositiveCoordinate] | None = Field(
        None,
        description="The image's extent [columns, rows] in the view's units: in px the DICOM Columns (0028,0011) "
        "and Rows (0028,0010), in mm those times the pixel spacing (filled by the DICOM layer). Coordinates run "
        "from (0, 0), the top-left corner of the top-left pixel, so the image's centre is (columns/2, rows/2). "
        "Used with SID and SOD when central_ray is absent: the central ray is taken to meet the detector at the "
        "image's centre (SID is measured to the detector's centre, DICOM PS3.3 C.8.7.6 and C.8.11.5).",
    )
    projection_model: Literal["perspective", "weak_perspective"] | None = Field(
        None,
        description="How the film projects the patient. perspective: from a point source, as every "
        "radiograph (CR, DX) is: SID and SOD when given, else those of full-spine radiography (SID 1800 mm, the "
        "spine's mid-plane 200 mm before the detector; with one of the two given, the other 200 mm apart, or "
        "through the ERMF when one is given: SID = SOD × magnification), the "
        "spine's distance from the source then held by a prior (SD 50 mm on the PA, 100 mm on the lateral; "
        "fit.assumed names full_spine_geometry). weak_perspective: parallel rays scaled by one magnification, "
        "refused with SID and SOD. Absent: perspective when SID and SOD are given, else weak_perspective. "
        "The DICOM layer and the page send perspective for a film read from DICOM.",
    )

    @model_validator(mode="after")
    def _geometry(self) -> Acquisition:
        sid, sod = self.distance_source_to_detector_mm, self.distance_source_to_patient_mm
        if sid is not None and sod is not None and not sod < sid:
            raise ValueError(
                f"distance_source_to_patient_mm ({sod:g}) must be smaller than distance_source_to_detector_mm ({sid:g})"
            )
        if self.projection_model == "perspective" and self.magnification is not None and not self.magnification > 1.0:
            raise ValueError(
                f"magnification ({self.magnification:g}) must exceed 1 with projection_model perspective: a point "
                "source magnifies the spine on the detector behind it"
            )
        if self.projection_model == "weak_perspective" and self.perspective:
            raise ValueError(
                "projection_model weak_perspective contradicts distance_source_to_detector_mm and "
                "distance_source_to_patient_mm, which give a pinhole: send one or the other"
            )
        return self

    def point_source_distances(self) -> tuple[float, float] | None:
        """(SID, SOD) in mm of a point-source view (``point_source``), else None: the given ones; a missing
        one from the other through the ERMF m (SID = SOD·m), else ``SPINE_TO_DETECTOR_MM`` apart; neither
        given: ``FULL_SPINE_SID_MM`` and the SOD from it. The SOD may come out ≤ 0 (an SID of 200 mm or
        less with nothing else), which validation refuses."""
        if not self.point_source:
            return None
        sid, sod, m = self.distance_source_to_detector_mm, self.distance_source_to_patient_mm, self.magnification
        if sid is None and sod is None:
            sid = FULL_SPINE_SID_MM
        if sod is None:
            assert sid is not None
            sod = sid / m if m is not None else sid - SPINE_TO_DETECTOR_MM
        if sid is None:
            sid = sod * m if m is not None else sod + SPINE_TO_DETECTOR_MM
        return float(sid), float(sod)

    @property
    def perspective(self) -> bool:
        """True when SID and SOD are both given (pinhole projection of known geometry)."""
        return self.distance_source_to_detector_mm is not None and self.distance_source_to_patient_mm is not None

    @property
    def point_source(self) -> bool:
        """True when the view is projected from a point source: SID and SOD given, or projection_model
        "perspective" (the geometry it lacks then assumed, ``clinical.pinhole_geometry``)."""
        return self.perspective or self.projection_model == "perspective"


class _View(_Strict):
    units: Literal["mm", "px"] = Field("mm", description="Units of the landmark coordinates.")
    pixel_spacing: tuple[
        PositiveFactor, PositiveFactor
    ] | None = Field(
        None,
        description="DICOM (0028,0030) pixel spacing [row spacing, column spacing] in mm; "
        "required when units is px.",
    )
    patient_orientation: tuple[str, str]
    landmarks: list[Landmark] = Field(max_length=MAX_LANDMARKS_PER_VIEW)
    projection: Projection | None = Field(
        None,
        description="Known weak perspective of this view, in detector mm. When absent the scale, translation "
        "and a small in-plane rotation are estimated jointly with the spine in the fit (docs/engine.md).",
    )
    acquisition: Acquisition | None = Field(
        None, description="Acquisition geometry (magnification, SID, SOD, central ray) when known."
    )
    landmark_sd_mm: Annotated[Number, Field(ge=LANDMARK_SD_MM_MIN, le=1e3, allow_inf_nan=False)] | None = Field(
        None,
        description="1 SD of a landmark per image coordinate on this view, detector mm; weights the view's "
        f"landmarks, at least {LANDMARK_SD_MM_MIN:g} mm (models.LANDMARK_SD_MM_MIN says why). Default (null): "
        f"{LANDMARK_SD_MM_DEFAULT:g} mm (clinicians' landmark placement; "
        "models.LANDMARK_SD_MM_DEFAULT cites the source). When the view's landmarks lie more than 4 such SDs (RMS "
        "per coordinate) from the spine fitted to them, the job fails with a validation problem naming this "
        "field (landmark_sd_contradicted): the SD is too small for them.",
    )
    pixel_spacing_calibration: PixelSpacingCalibration | None = Field(
        None,
        description="Which calibration gave the view's mm (filled by the DICOM layer, PS3.3 §10.7.1.1): "
        "'calibrated' mm in the patient plane ((0028,0030) after a calibration, or imager spacing divided by the "
        "ERMF or SID/SOD); 'projection' ((0028,0030) equal to (0018,1164)) and 'detector' ((0018,1164) only) mm at "
        "the detector; 'unknown' or null: taken as detector mm. With 'calibrated' the engine multiplies the mm by "
        "the acquisition's magnification (ERMF, else SID/SOD; with projection_model perspective and neither, the "
        "assumed SID/SOD of full-spine radiography, the spine held at that SOD) to reach the detector, and without "
        "one it takes the magnification as 1 (not the prior). Carried to fit.<view>.pixel_spacing_calibration.",
    )

    @property
    def sd_mm(self) -> float:
        """σ, detector mm: ``landmark_sd_mm``, or ``LANDMARK_SD_MM_DEFAULT`` when the view states none."""
        return self.landmark_sd_mm if self.landmark_sd_mm is not None else LANDMARK_SD_MM_DEFAULT

    @field_validator("patient_orientation")
    @classmethod
    def _orientation(cls, value: tuple[str, str]) -> tuple[str, str]:
        col, row = value
        for name, d in (("column", col), ("row", row)):
            if d not in PATIENT_DIRECTIONS:
                raise ValueError(f"{name} direction {d!r} is not one of {list(PATIENT_DIRECTIONS)}")
        axis = {"L": 0, "R": 0, "A": 1, "P": 1, "H": 2, "F": 2}
        if axis[col] == axis[row]:
            raise ValueError(f"column and row directions {col!r}, {row!r} are not orthogonal")
        return value

    @field_validator("landmarks")
    @classmethod
    def _unique_levels(cls, value: list[Landmark]) -> list[Landmark]:
        seen: set[str] = set()
        for lm in value:
            if lm.level in seen:
                raise ValueError(f"level {lm.level} is given more than once")
            seen.add(lm.level)
        return sorted(value, key=lambda lm: LEVEL_INDEX[lm.level])


PA_ORIENTATION: tuple[str, str] = ("L", "F")
"""Default ``patient_orientation`` of the PA view: columns toward the patient's left, rows toward
the feet (DICOM PS3.3 C.7.6.1.1.1 Patient Orientation), as a PA film is hung."""
LATERAL_ORIENTATION: tuple[str, str] = ("A", "F")
"""Default ``patient_orientation`` of the lateral view: columns toward anterior, rows toward the feet."""


class PAView(_View):
    """The postero-anterior radiograph and its landmarks."""

    patient_orientation: tuple[str, str] = Field(
        PA_ORIENTATION,
        description="DICOM (0020,0020) patient orientation of the column and row directions.",
    )
    landmarks: list[Landmark] = Field(min_length=1, max_length=MAX_LANDMARKS_PER_VIEW)


class LateralView(_View):
    """An optional lateral radiograph and its landmarks (any subset of levels)."""

    patient_orientation: tuple[str, str] = Field(
        LATERAL_ORIENTATION,
        description="DICOM (0020,0020) patient orientation of the column and row directions.",
    )


class Pose(_Strict):
    """Position (mm, LPS) and directors (rows d1, d2, d3) of a boundary vertebra; exact (the paper's
    constraint) unless a standard deviation is given, then a soft (Gaussian) constraint."""

    position: Vec3
    directors: tuple[Vec3, Vec3, Vec3] = Field(
        description="Rows d1 (≈ patient left), d2 (≈ anterior), d3 (caudal tangent); "
        "orthonormal and right-handed within 1e-3."
    )
    position_sd_mm: PositiveFactor | None = Field(
        None,
        description="1 SD of each position coordinate, mm (a pose measured by another means). Null: exact. "
        "Give it together with directors_sd_deg (both null or both set).",
    )
    directors_sd_deg: PositiveFactor | None = Field(
        None,
        description="1 SD of the rotation about each axis, degrees. Null: exact. Give it together with "
        "position_sd_mm.",
    )

    @model_validator(mode="after")
    def _both_sds(self) -> Pose:
        if (self.position_sd_mm is None) != (self.directors_sd_deg is None):
            missing = "directors_sd_deg" if self.directors_sd_deg is None else "position_sd_mm"
            raise PydanticCustomError(
                "pose_sd_incomplete",
                "a soft pose needs both position_sd_mm and directors_sd_deg ({missing} is missing)",
                {"missing": missing},
            )
        return self

    @property
    def soft(self) -> bool:
        """True when the pose is a soft constraint (both SDs given)."""
        return self.position_sd_mm is not None

    @field_validator("directors")
    @classmethod
    def _orthonormal(cls, value: tuple[Vec3, Vec3, Vec3]) -> tuple[Vec3, Vec3, Vec3]:
        # plain floats: nine products beat numpy's per-call overhead on a 3 × 3
        (a1, a2, a3), (b1, b2, b3), (c1, c2, c3) = value
        gram_error = max(
            abs(a1 * a1 + a2 * a2 + a3 * a3 - 1.0),
            abs(b1 * b1 + b2 * b2 + b3 * b3 - 1.0),
            abs(c1 * c1 + c2 * c2 + c3 * c3 - 1.0),
            abs(a1 * b1 + a2 * b2 + a3 * b3),
            abs(a1 * c1 + a2 * c2 + a3 * c3),
            abs(b1 * c1 + b2 * c2 + b3 * c3),
        )
        if gram_error > DIRECTOR_TOLERANCE:
            raise ValueError(
                f"directors are not orthonormal: largest |d_i·d_j − δ_ij| is {gram_error:.3g} "
                f"(tolerance {DIRECTOR_TOLERANCE})"
            )
        det = a1 * (b2 * c3 - b3 * c2) - a2 * (b1 * c3 - b3 * c1) + a3 * (b1 * c2 - b2 * c1)
        if abs(det - 1.0) > DIRECTOR_TOLERANCE:
            raise ValueError(f"directors are not right-handed: det [d1; d2; d3] = {det:.4g}, expected 1")
        return value


class Boundary(_Strict):
    """Boundary conditions: T1 and L5 poses, fixed exactly or (with SDs) held softly."""

    T1: Pose
    L5: Pose

    @model_validator(mode="after")
    def _distinct(self) -> Boundary:
        gap = math.dist(self.T1.position, self.L5.position)
        if gap < 1.0:
            raise ValueError(f"T1 and L5 positions are {gap:.3g} mm apart; they must be distinct")
        return self


class Options(_Strict):
    profile: str = Field(
        "default",
        description="Name of the elastic-property profile to use, one shipped with the engine "
        "(spine_engine/profiles/); another name is refused naming this field (unknown_profile).",
    )
    tilt_prior: bool | None = Field(
        None,
        description="Use the calibrated prior on the frontal tilt of PA vertebrae given by a point only "
        "(predicted from the landmarks' chords; docs/accuracy.md). Default (null): on without boundary "
        "conditions, off with them.",
    )


DICOM_UID_MAX_LENGTH = 64
DICOM_LO_MAX_LENGTH = 64
"""PS3.5 §6.2: Long String (LO), at most 64 characters."""
DICOM_SH_MAX_LENGTH = 16
"""PS3.5 §6.2: Short String (SH), at most 16 characters."""
DICOM_PN_GROUP_MAX_LENGTH = 64
DICOM_PN_GROUPS = ("alphabetic", "ideographic", "phonetic")
DICOM_PN_MAX_LENGTH = len(DICOM_PN_GROUPS) * DICOM_PN_GROUP_MAX_LENGTH + len(DICOM_PN_GROUPS) - 1
"""PS3.5 §6.2 (Table 6.2-1) and §6.2.1: a Person Name (PN) is up to three component groups separated by
``=`` (alphabetic, ideographic, phonetic), each of at most 64 characters and of up to five components
separated by ``^`` (family, given, middle, prefix, suffix): at most 3 × 64 characters and two ``=``."""


def person_name_problem(text: str) -> str | None:
    """Why ``text`` is not a DICOM PN (``DICOM_PN_MAX_LENGTH``'s rule), None when it is. Characters, not
    bytes, are counted, as PS3.5 §6.2 counts them. The DICOM header reader of the client, which installs
    without the engine, applies the same rule to a film's name (``spine_client.dicom.header``)."""
    groups = text.split("=")
    if len(groups) > len(DICOM_PN_GROUPS):
        return (f"has {len(groups)} component groups separated by '=': a PN has at most 3, alphabetic, "
                "ideographic and phonetic (PS3.5 §6.2.1)")  # fmt: skip
    for name, group in zip(DICOM_PN_GROUPS, groups, strict=False):
        if len(group) > DICOM_PN_GROUP_MAX_LENGTH:
            return (f"has {len(group)} characters in its {name} component group: a PN holds at most "
                    f"{DICOM_PN_GROUP_MAX_LENGTH} per component group (PS3.5 §6.2, Table 6.2-1)")  # fmt: skip
        if group.count("^") > 4:
            return (f"has {group.count('^') + 1} components in its {name} component group: a PN has at most 5, "
                    "family^given^middle^prefix^suffix (PS3.5 §6.2.1)")  # fmt: skip
    return None
DICOM_TEXT_PATTERN = r"^[^\\\u0000-\u001f\u007f]*$"
"""A DICOM LO, SH or PN value as this contract takes it (PS3.5 §6.2): no backslash (5CH, the delimiter
between the values of a multi-valued element) and no control character. The standard allows ESC
for ISO 2022 code extensions; JSON carries the decoded Unicode text, which needs none."""
DICOM_TEXT_REASON = "a DICOM text value holds no backslash and no control character"
DICOM_UID_PATTERN = r"^[0-9]+(\.[0-9]+)*$"
"""A DICOM UID's characters (PS3.5 §9.1): digits in dot-separated components (its 64-character limit
is checked apart)."""
DICOM_UID_REASON = "a DICOM UID is digits in dot-separated components, e.g. 1.2.840.10008.1.1"
DICOM_UID_STRICT_PATTERN = r"^(0|[1-9][0-9]*)(\.(0|[1-9][0-9]*))*$"
"""A DICOM UID as PS3.5 §9.1 writes it: besides ``DICOM_UID_PATTERN``, no component starts with 0 unless it is 0
(what a PACS is asked for; the job's own UIDs are taken as ``DICOM_UID_PATTERN`` takes them)."""
DICOM_UID_STRICT_REASON = "a DICOM UID is digits in dot-separated components without leading zeros (PS3.5 §9.1)"
PATTERN_REASONS = {
    DICOM_TEXT_PATTERN: DICOM_TEXT_REASON,
    DICOM_UID_PATTERN: DICOM_UID_REASON,
    DICOM_UID_STRICT_PATTERN: DICOM_UID_STRICT_REASON,
}
"""Each pattern of the contract's strings with its reason in plain words, for errors that would quote the regex."""


STUDY_DATE_PATTERN = r"^[0-9]{4}-[0-9]{2}-[0-9]{2}$"
STUDY_DATE_REASON = (
    "a Study Date is a calendar date written YYYY-MM-DD (ISO 8601; the film's DICOM DA 20260210 is 2026-02-10), "
    "not a date-time, a number or another form"
)


def read_study_date(value: object) -> date | None:
    """The day of a ``study_date`` as a job stores it (the payload as posted): the contract's YYYY-MM-DD,
    and the forms a job stored before ``Study`` took only that (a number or numeric string of Unix
    seconds, a date-time at midnight) read as the contract then read them; None when absent or not a
    date at all."""
    if value is None or isinstance(value, date):
        return value if isinstance(value, date) else None
    try:
        return _LAX_DATE.validate_python(value)
    except ValidationError:
        return None


UniversalEntityIdType = Literal["DNS", "EUI64", "ISO", "URI", "UUID", "X400", "X500"]
"""Universal Entity ID Type (0040,0033) defined terms (PS3.3 §10.14, HL7v2 Hierarchic Designator Macro): the
kind of Universal Entity ID (0040,0032) the issuer of an identifier is named by."""


class PatientIdIssuer(_Strict):
    """Who issued the Patient ID, as the film's Patient Module names it (PS3.3 §C.7.1.1).

    Issuer of Patient ID (0010,0021), a local name, and from the single item of Issuer of Patient ID
    Qualifiers Sequence (0010,0024) the issuer's Universal Entity ID (0040,0032) with its Type (0040,0033),
    which that module requires with the ID."""

    issuer_of_patient_id: str | None = Field(
        None, max_length=DICOM_LO_MAX_LENGTH,
        description="Issuer of Patient ID (0010,0021): the issuer's local name (DICOM LO, at most 64 characters).",
    )
    universal_entity_id: str | None = Field(
        None, min_length=1,
        description="Universal Entity ID (0040,0032) of the issuer (DICOM UT), e.g. an ISO OID 1.2.3.4.5.",
    )
    universal_entity_id_type: UniversalEntityIdType | None = Field(
        None,
        description="Universal Entity ID Type (0040,0033) (PS3.3 §10.14): ISO (an OID), UUID, URI, DNS, EUI64, "
        "X400 or X500; given exactly when universal_entity_id is.",
    )

    @field_validator("issuer_of_patient_id", "universal_entity_id")
    @classmethod
    def _dicom_text(cls, value: str | None) -> str | None:
        if value is not None and not re.fullmatch(DICOM_TEXT_PATTERN, value):
            raise ValueError(DICOM_TEXT_REASON)
        return value

    @model_validator(mode="after")
    def _qualified(self) -> PatientIdIssuer:
        if (self.universal_entity_id is None) != (self.universal_entity_id_type is None):
            raise ValueError("universal_entity_id and universal_entity_id_type come together: the Type (0040,0033) "
                             "is required with the ID (0040,0032) and says nothing without it (PS3.3 §C.7.1.1)")
        if self.issuer_of_patient_id is None and self.universal_entity_id is None:
            raise ValueError("an issuer has a local name (issuer_of_patient_id), a universal_entity_id, or both")
        return self


class Study(_Strict):
    """DICOM identifiers of the radiographs the landmarks come from. Carried unchanged to the job
    (and its webhook and FHIR export) so that a PACS can match results to its images; the engine
    does not use them. The UIDs are DICOM UIDs: digits in dot-separated components, at most 64 characters.
    The patient and accession fields are filled from the image header when the DICOM layer reads one.
    """

    study_instance_uid: str = Field(description="Study Instance UID (0020,000D).")
    series_instance_uid: str | None = Field(None, description="Series Instance UID (0020,000E).")
    pa_sop_instance_uid: str | None = Field(None, description="SOP Instance UID (0008,0018) of the PA image.")
    lateral_sop_instance_uid: str | None = Field(
        None, description="SOP Instance UID (0008,0018) of the lateral image."
    )
    patient_id: str | None = Field(
        None, max_length=DICOM_LO_MAX_LENGTH, description="Patient ID (0010,0020): DICOM LO, at most 64 characters."
    )
    patient_name: str | None = Field(
        None,
        max_length=DICOM_PN_MAX_LENGTH,
        description="Patient's Name (0010,0010) in DICOM PN form (Family^Given^Middle^Prefix^Suffix), up to three "
        "component groups separated by '=' (alphabetic, ideographic, phonetic), each of at most 64 characters.",
    )
    accession_number: str | None = Field(
        None,
        max_length=DICOM_SH_MAX_LENGTH,
        description="Accession Number (0008,0050): DICOM SH, at most 16 characters.",
    )
    study_date: date | None = Field(None, description="Study Date (0008,0020) as ISO 8601 YYYY-MM-DD.")
    patient_id_issuer: PatientIdIssuer | None = Field(
        None,
        description="Who issued patient_id (Issuer of Patient ID (0010,0021) and Issuer of Patient ID Qualifiers "
        "Sequence (0010,0024)), filled from the image header when the DICOM layer reads one; copied into the SR "
        "and SC, and the FHIR export's subject identifier system when it names the issuer by a URI (ISO OID, UUID "
        "or URI).",
    )

    @field_validator("patient_id", "patient_name", "accession_number")
    @classmethod
    def _dicom_text(cls, value: str | None) -> str | None:
        """DICOM LO, SH and PN values (PS3.5 §6.2) hold no backslash (the value separator) and no
        control character."""
        if value is None:
            return value
        if not re.fullmatch(DICOM_TEXT_PATTERN, value):
            raise ValueError(DICOM_TEXT_REASON)
        return value

    @field_validator("patient_id")
    @classmethod
    def _not_blank(cls, value: str | None) -> str | None:
        """A Patient ID of spaces only is an empty value (DICOM LO: leading and trailing spaces are
        insignificant, PS3.5 §6.2, Table 6.2-1): leave the member out instead."""
        if value is not None and not value.strip():
            raise ValueError("a Patient ID of spaces only is empty: give the patient's ID or leave patient_id out")
        return value

    @field_validator("study_date", mode="before")
    @classmethod
    def _calendar_date(cls, value: object) -> object:
        """``STUDY_DATE_REASON``: a date object (Python callers), or a string of exactly YYYY-MM-DD;
        pydantic's lax ``date`` would take a number or a numeric string as Unix seconds and a date-time
        at midnight as its day."""
        if value is None or type(value) is date:
            return value
        if isinstance(value, str) and re.fullmatch(STUDY_DATE_PATTERN, value):
            return value
        raise PydanticCustomError("study_date_format", STUDY_DATE_REASON)

    @field_validator("patient_name")
    @classmethod
    def _person_name(cls, value: str | None) -> str | None:
        problem = None if value is None else person_name_problem(value)
        if problem is not None:
            raise ValueError(f"the Patient's Name {problem}")
        return value

    @field_validator("study_instance_uid", "series_instance_uid", "pa_sop_instance_uid", "lateral_sop_instance_uid")
    @classmethod
    def _dicom_uid(cls, value: str | None) -> str | None:
        if value is None:
            return value
        if len(value) > DICOM_UID_MAX_LENGTH:
            raise ValueError(f"a DICOM UID has at most {DICOM_UID_MAX_LENGTH} characters, this one {len(value)}")
        if not re.fullmatch(DICOM_UID_PATTERN, value):
            raise ValueError(DICOM_UID_REASON)
        return value


class JobPayload(_Strict):
    """The body a client posts to create a job, and the argument of ``spine_engine.register``.

    Checks that span several fields (px units need pixel_spacing; each view needs a minimum number
    of landmarked levels, any levels) live in ``spine_engine.validation.validate_payload``, so that
    their errors name the field.
    """

    pa: PAView
    lateral: LateralView | None = None
    boundary: Boundary | None = Field(
        None,
        description="T1 and L5 poses: exact, or soft when given with position_sd_mm and directors_sd_deg. "
        "Optional: without them all 17 vertebrae are free (T1 is placed at the patient origin), and "
        "fit.unreliable lists the quantities that then come from the model only.",
    )
    options: Options = Field(default_factory=Options)
    study: Study | None = Field(
        None, description="DICOM identifiers of the images, carried unchanged to the job; not used by the engine."
    )
    callback_url: str | None = Field(
        None,
        max_length=2048,
        description="Service only (the engine ignores it): http(s) URL that receives the job, signed as Standard "
        "Webhooks do, when it ends. Must match the service's allow-list (SPINE_WEBHOOK_ALLOWED_URLS).",
    )


# ---------------------------------------------------------------- result


class VertebraResult(BaseModel):
    """The reconstructed pose of one vertebra and the strains of the segment below it.

    The segment of vertebra i joins it to vertebra i+1 (caudally); L5 has no segment, so its
    strain fields are null. u in rad/mm, v dimensionless; the angles are u·Δs in degrees.
    """

    level: Level
    position: tuple[float, float, float]
    directors: tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]
    u: tuple[float, float, float] | None = Field(description="Angular strain (u1, u2, u3), rad/mm.")
    v: tuple[float, float, float] | None = Field(description="Shear v1, v2 and stretch v3.")
    sagittal_bending_deg: float | None = Field(
        None, description="Sagittal bending u1·Δs (about d1, in the sagittal plane), degrees."
    )
    frontal_bending_deg: float | None = Field(
        None, description="Frontal (coronal) bending u2·Δs (about d2, in the frontal plane), degrees."
    )
    pa_bending_deg: float | None = Field(
        None,
        description="Deprecated alias of sagittal_bending_deg (same value); removed in a later version.",
        deprecated="use sagittal_bending_deg (same value)",
    )
    lateral_bending_deg: float | None = Field(
        None,
        description="Deprecated alias of frontal_bending_deg (same value); removed in a later version.",
        deprecated="use frontal_bending_deg (same value)",
    )
    twist_deg: float | None = Field(description="Twist u3·Δs about d3, degrees.")
    axial_rotation_deg: float = Field(
        description="Axial rotation in the transverse plane, degrees (docs/measures.md). Without pedicles it is "
        "the population's mean given the frontal curves, toward each curve's convexity (fit.assumed "
        "population_axial_rotation), not the directors' turn."
    )
    frontal_tilt_deg: float | None = Field(
        None,
        description="Frontal tilt used by the Cobb measure, degrees: from the corners when given on the PA "
        "view, else the reconstructed d1 projected on the frontal plane (docs/measures.md).",
    )
    frontal_tilt_source: Literal["corners", "model"] | None = None
    position_sd_mm: tuple[float, float, float] | None = Field(
        None,
        description="1 SD of the position (x, y, z), mm, relative to the centroid of the 17 positions (Laplace "
        "approximation at the fit's optimum, times fit.uncertainty_scale). Null when not computed.",
    )
    axial_rotation_sd_deg: float | None = Field(
        None,
        description="1 SD of axial_rotation_deg, degrees (as position_sd_mm); without pedicles it includes the "
        "population's spread of axial rotation at the Cobb angle of the vertebra's curve (docs/measures.md). "
        "Null when not computed.",
    )

    @model_validator(mode="after")
    def _aliases(self) -> VertebraResult:
        # The deprecated names carry the new names' values (either may be given on construction).
        data = self.__dict__
        for new, old in (("sagittal_bending_deg", "pa_bending_deg"), ("frontal_bending_deg", "lateral_bending_deg")):
            if data[new] is None:
                data[new] = data[old]
            data[old] = data[new]
        return self


class CobbCurve(BaseModel):
    """One frontal curve: Cobb angle between its end vertebrae, apex and 3D descriptors."""

    upper: Level
    lower: Level
    apex: Level
    angle_deg: float = Field(description="Frontal Cobb angle, degrees.")
    angle_sd_deg: float | None = Field(
        None,
        description="1 SD of angle_deg, degrees (Laplace approximation, calibrated), with the spread of real "
        "endplates about the centreline when no corner observed an end vertebra, and at least the population's SD "
        "when an end vertebra lies on a level the PA film's landmarks do not show (docs/measures.md). Null when not "
        "computed.",
    )
    major: bool = Field(description="True for the largest curve; exactly one when any curve exists.")
    convexity: Literal["left", "right"]
    apical_disc: bool = Field(
        False,
        description="True when the curve's apex is the intervertebral disc between `apex` and the vertebra below it "
        "(SRS apical disc): a curve of one segment, whose only vertebrae are its two end vertebrae; `apex` then names "
        "the disc's upper vertebra. False: `apex` is the apical vertebra, strictly between the end vertebrae "
        "(docs/measures.md).",
    )
    apex_axial_rotation_deg: float
    plane_of_max_curvature_deg: float = Field(
        description="Azimuth of the plane of maximum curvature from the frontal plane toward "
        "anterior, degrees (SRS 3D terminology; docs/measures.md)."
    )
    max_curvature_deg: float = Field(description="Cobb angle measured in that plane, degrees.")
    endplate_angle_deg: float | None = Field(
        None,
        description="Endplate variant: angle between the superior endplate of the upper end vertebra and the "
        "inferior endplate of the lower one, frontal plane, degrees (docs/measures.md).",
    )
    tilt_source: Literal["corners", "model", "mixed"] | None = Field(
        None, description="Where the end vertebrae's tilts come from."
    )


class LargestCobbAngle(BaseModel):
    """The spine's largest frontal Cobb angle whatever its size: what ``cobb`` reports as the major
    curve when it reaches the reporting threshold, and what it leaves out below it."""

    upper: Level
    lower: Level
    angle_deg: float = Field(
        description="The major curve's angle_deg when `cobb` has one; else the frontal Cobb angle between the two "
        "vertebrae most tilted relative to each other (max θ − min θ of the frontal tilts), degrees. The two differ "
        "only when a counter-curve of 10° or more lies between the most tilted vertebrae, which splits them into "
        "curves of their own (docs/measures.md)."
    )
    angle_sd_deg: float | None = Field(
        None,
        description="1 SD of angle_deg, degrees, as a curve's angle_sd_deg, and at least the population's SD when "
        "a level is one the PA film's landmarks do not show (docs/measures.md). Null when not computed.",
    )
    tilt_source: Literal["corners", "model", "mixed"] = Field(description="Where the two vertebrae's tilts come from.")
    reported_as_curve: bool = Field(
        description="True when the angle reaches the reporting threshold (10°) and `cobb` lists it as the major "
        "curve; false for a spine whose frontal curves are all below it (no curve is then listed)."
    )


class AasceMajorAngle(BaseModel):
    """The major angle of the AASCE 2019 challenge's Cobb script, from four corners on every level."""

    angle_deg: float = Field(
        description="Largest angle between the transverse axes (left-edge midpoint → right-edge midpoint) of "
        "any two vertebrae, arccos of the cosine clipped to [0, 1] (so at most 90°), degrees."
    )
    upper: Level
    lower: Level


class LenkeCurve(BaseModel):
    """The largest frontal curve of one Lenke region (apex level), with the structural criteria the
    reconstruction can evaluate. A model estimate: side-bending radiographs decide structurality."""

    region: Literal["proximal_thoracic", "main_thoracic", "thoracolumbar_lumbar"]
    upper: Level
    lower: Level
    apex: Level
    angle_deg: float
    major: bool = Field(description="The largest curve of the spine (always structural in Lenke's scheme).")
    structural_by_magnitude: bool = Field(
        description="Major, or standing Cobb ≥ 25°: a curve below 25° cannot reach 25° on side bending, so "
        "only these can be structural by Lenke's bending criterion."
    )
    structural_by_kyphosis: bool = Field(
        description="Regional kyphosis ≥ +20° (T2–T5 for proximal thoracic, T10–L2 otherwise), from the 3D model."
    )
    structural_by_kyphosis_probability: float | None = Field(
        None,
        description="Probability that the regional kyphosis is ≥ +20°, under a normal distribution of the reported "
        "regional kyphosis and its SD (LenkeInputs); null without that SD.",
    )


class LenkeInputs(BaseModel):
    """Inputs of the Lenke classification (Lenke et al., J Bone Joint Surg Am 2001;83:1169–1181)
    that the reconstruction supports. Model estimates, not a classification (docs/measures.md)."""

    model_estimate: Literal[True] = True
    curves: list[LenkeCurve]
    t2_t5_kyphosis_deg: float = Field(
        description="T2–T5 kyphosis, degrees (+: convex posteriorly), read as the other sagittal measures. Without a "
        "lateral film as calibrated on VerSe dev: the centreline's reading plus an offset where one PA film predicts "
        "it, else the population's mean (docs/engine.md)."
    )
    t5_t12_kyphosis_deg: float = Field(description="T5–T12 kyphosis, degrees: measures.thoracic_kyphosis_t5_t12_deg.")
    t10_l2_kyphosis_deg: float = Field(description="T10–L2 kyphosis, degrees, as the T2–T5 one.")
    t2_t5_kyphosis_sd_deg: float | None = Field(
        None,
        description="1 SD of t2_t5_kyphosis_deg, degrees (Laplace, calibrated; without a lateral film at least the "
        "population's SD on VerSe dev); null when not computed.",
    )
    t5_t12_kyphosis_sd_deg: float | None = Field(
        None, description="1 SD of t5_t12_kyphosis_deg, degrees: measures.thoracic_kyphosis_t5_t12_sd_deg."
    )
    t10_l2_kyphosis_sd_deg: float | None = Field(
        None, description="1 SD of t10_l2_kyphosis_deg, degrees, as the T2–T5 one."
    )
    sagittal_thoracic_modifier: Literal["-", "N", "+"] = Field(
        description="T5–T12 kyphosis < 10° '-', 10–40° 'N', > 40° '+'."
    )
    sagittal_thoracic_modifier_probability: float | None = Field(
        None,
        description="Probability of the modifier given, under a normal distribution of t5_t12_kyphosis_deg and its "
        "SD; null without that SD.",
    )
    not_supported: list[str] = Field(
        description="Lenke inputs the reconstruction cannot give (e.g. side-bending Cobb angles, the lumbar "
        "modifier's CSVL)."
    )


class Measures(BaseModel):
    """Clinical measures computed from the reconstruction (definitions in docs/measures.md)."""

    cobb: list[CobbCurve]
    largest_cobb: LargestCobbAngle | None = Field(
        None,
        description="The largest frontal Cobb angle whatever its size, also below the 10° threshold under which "
        "`cobb` lists no curve (for follow-up of mild curves and comparison with data sets that measure every "
        "spine). Null in results stored before it existed.",
    )
    thoracic_kyphosis_t4_t12_deg: float = Field(
        description="T4–T12 kyphosis, degrees, on the reconstructed centreline (a vertebra's own tilt where a lateral "
        "film's corners or the boundary gave it; docs/measures.md). Without a lateral film (fit.assumed "
        "population_sagittal_shape) as calibrated on VerSe dev: the film's reading plus an offset where "
        "one PA film predicts the measure, else the population's mean; a kyphosis's reading is 0.7 of the PA "
        "film's foreshortening read against VerSe dev's sagittal shapes and 0.3 of the centreline's "
        "(docs/engine.md)."
    )
    thoracic_kyphosis_t5_t12_deg: float = Field(description="T5–T12 kyphosis, degrees, as the T4–T12 one.")
    lumbar_lordosis_l1_l5_deg: float = Field(description="L1–L5 lordosis, degrees, as the kyphosis.")
    thoracic_kyphosis_t4_t12_sd_deg: float | None = Field(
        None, description="1 SD of thoracic_kyphosis_t4_t12_deg, degrees (Laplace, calibrated); null when not computed."
    )
    thoracic_kyphosis_t5_t12_sd_deg: float | None = Field(
        None, description="1 SD of thoracic_kyphosis_t5_t12_deg, degrees; null when not computed."
    )
    lumbar_lordosis_l1_l5_sd_deg: float | None = Field(
        None, description="1 SD of lumbar_lordosis_l1_l5_deg, degrees; null when not computed."
    )
    aasce2019: AasceMajorAngle | None = Field(
        None, description="The AASCE 2019 script's major angle; only when the PA view has corners on all 17 levels."
    )
    lenke: LenkeInputs | None = None


class Residual(BaseModel):
    view: Literal["pa", "lateral"]
    level: Level
    residual_mm: float = Field(description="Distance between landmark and projected model point, patient mm.")


class TiltResidual(BaseModel):
    view: Literal["pa", "lateral"]
    level: Level
    source: Literal["corners", "prior"]
    residual_deg: float = Field(description="Signed angle from the observed to the model's transverse axis, degrees.")


class PedicleResidual(BaseModel):
    view: Literal["pa"]
    level: Level
    side: Literal["image_left", "image_right"]
    residual_mm: float = Field(description="Signed column residual of the pedicle centre, patient mm.")


def extensible(values: object) -> WithJsonSchema:
    """The published schema of an output value whose list grows with the engine (the ``Literal``
    ``values``): a string with today's values as ``examples``, an "extensible enum" (Zalando RESTful API
    guidelines, rule 112; its rule 108 asks clients to keep a value they do not know). A JSON ``enum``
    would have a client generated from today's contract refuse a whole result naming a value a newer
    engine adds, as ``projection_unstated`` was refused (CHANGELOG). The field is a ``str`` for the same
    reason on this side: a result a newer engine stored (a rollback, a worker upgraded before the API)
    is read back with its names kept, where a ``Literal`` made its job and the jobs list answer 500.
    This engine writes only ``values`` (``reconstruction._assumption``, ``Unreliable``-typed lists)."""
    return WithJsonSchema({"type": "string", "examples": list(get_args(values))})


Unreliable = Literal[
    "scale", "depth", "kyphosis", "lordosis", "plane_of_max_curvature", "axial_rotation", "twist", "cobb"
]


class ViewProjection(BaseModel):
    """The projection of one view used by (or estimated in) the fit."""

    scale: float = Field(
        description="Magnification s, detector mm per patient mm (perspective: SID/SOD at the spine's mid-plane)."
    )
    translation: tuple[float, float] = Field(
        description="Translation T (column, row), detector mm: the image of the patient origin (weak perspective) "
        "or the central ray's foot on the detector (perspective)."
    )
    estimated: bool = Field(description="True when any of scale, translation or rotation was estimated.")
    model: Literal["weak_perspective", "perspective"] = Field(
        "weak_perspective",
        description="weak_perspective p = s·Rot(ψ)(e_c·r, e_r·r) + T; perspective: pinhole from acquisition SID/SOD "
        "(given, or assumed with projection_model perspective).",
    )
    rotation_deg: float = Field(0.0, description="In-plane film rotation ψ, degrees (estimated; 0 when given).")
    scale_source: Literal["given", "acquisition", "prior", "estimated"] = Field(
        "given",
        description="Where s comes from: the payload's projection ('given'), the acquisition's magnification or "
        "geometry ('acquisition'), the model's prior on magnification or the assumed full-spine geometry "
        "('prior': fit.unreliable then lists 'scale'), or the fit with the other views ('estimated').",
    )
    pixel_spacing_calibration: PixelSpacingCalibration | None = Field(
        None, description="Carried from the payload's view (which calibration gave the mm)."
    )
    source_to_detector_mm: float | None = Field(
        None, description="Perspective: the SID the fit projected with, given or assumed (acquisition), mm; null in "
        "weak perspective."
    )
    source_to_patient_mm: float | None = Field(
        None, description="Perspective: the SOD, source to the spine's mid-plane, given or assumed, mm; null in weak "
        "perspective."
    )
    central_ray_point_mm: tuple[float, float, float] | None = Field(
        None,
        description="Perspective: o, the central ray's point at SOD from the source, patient mm (the frame of the "
        "vertebrae's positions), as fitted. With translation c, rotation_deg ψ, beam_direction b, SID and SOD it "
        "gives the projection of a patient point r: p = c + m·Rot(ψ)·(e_c·(r − o), e_r·(r − o)), "
        "m = SID / (SOD + b·(r − o)), e_c and e_r the image axes of the view's patient_orientation (docs/engine.md). "
        "Null in weak perspective.",
    )
    beam_direction: tuple[float, float, float] | None = Field(
        None, description="Perspective: the unit beam direction b, source to detector, patient frame; null in weak "
        "perspective."
    )


AssumptionName = Literal[
    "central_ray_at_image_centre", "central_ray_near_landmarks", "magnification_prior", "standing_orientation",
    "population_sagittal_shape", "full_spine_geometry", "population_axial_rotation", "projection_unstated",
]


class Assumption(BaseModel):
    """A prior or default that decided a number of the result because the input did not give it."""

    name: Annotated[str, extensible(AssumptionName)] = Field(
        description="What was assumed (an extensible list: a newer service may name others): "
        "central_ray_at_image_centre (SID and SOD given without a central ray: "
        "the ray is taken at the centre of acquisition.image_size); central_ray_near_landmarks (neither a "
        "central ray nor an image size: a prior holds the ray within 50 mm of the landmarks' centre); "
        "magnification_prior (the PA's magnification from the full-spine prior 1.125 ± 0.035); "
        "standing_orientation (no lateral film: the spine's lean and spin about the vertical from the prior "
        "of a standing patient facing the detector); population_sagittal_shape (no lateral film: kyphosis "
        "and lordosis from the population prior, with its SD; the population's mean where one PA film does not "
        "predict them); full_spine_geometry (projection_model "
        "perspective without SID or SOD: those of full-spine radiography, the spine's distance from the source "
        "under a prior); population_axial_rotation (no pedicles: each vertebra's axial rotation is the "
        "population's mean given the frontal curves, toward each curve's convexity, with the population's SD); "
        "projection_unstated (two films, this one without SID and SOD or projection_model: read in weak "
        "perspective, with how far it comes from a point source, 1/SOD, read from the two films under a prior "
        "about the parallel beam, SD that of full-spine radiography's 1/1600 mm⁻¹; the reason then says whether "
        "the films showed a point source that moved the spine, and its 1/SOD as read, with its SD)."
    )
    view: Literal["pa", "lateral"] | None = Field(None, description="The view it concerns, if one.")
    reason: str = Field(description="In plain words: what was missing and what was taken instead.")


class FitReport(BaseModel):
    residuals: list[Residual]
    mean_registration_error_mm: float = Field(description="Mean PA landmark residual, patient mm.")
    energy_fit: float = Field(description="Fitting error E_f, N·mm.")
    energy_internal: float = Field(description="Potential energy E_I of the rod, N·mm.")
    iterations: int
    converged: bool
    runtime_ms: float
    pa: ViewProjection
    lateral: ViewProjection | None = None
    boundary: Literal["given", "soft", "estimated"] = Field(
        "given",
        description="T1 and L5: 'given' (exact, the paper's constraint), 'soft' (given with standard deviations) "
        "or 'estimated' (no boundary: all 17 vertebrae free, gauge fixed as docs/engine.md says).",
    )
    unreliable: list[Annotated[str, extensible(Unreliable)]] = Field(
        default_factory=list,
        description="An extensible list (a newer service may name others). Quantities that come from the model's "
        "priors more than from the input (docs/measures.md): "
        "what no view determines, kyphosis or lordosis whenever its SD exceeds half the population's, and 'cobb' "
        "(the frontal Cobb angles: `measures.cobb`, `largest_cobb`, the Lenke curves) when one depends on "
        "levels the PA film's landmarks do not show (two or more in a row without one, or beyond its first or "
        "last: a curve ending there; the largest angle whenever such a level exists) or "
        "a Cobb angle's SD exceeds half the population's.",
    )
    tilt_prior: bool = Field(False, description="Whether the tilt prior was applied.")
    tilt_residuals: list[TiltResidual] = Field(default_factory=list)
    pedicle_residuals: list[PedicleResidual] = Field(default_factory=list)
    uncertainty_scale: float | None = Field(
        None,
        description="Factor applied to the Laplace standard deviations: the constant calibrated on VerSe dev so "
        "that ±1.96 SD covers 95 % of truth, times landmark_misfit_ratio when that exceeds 1. Null when no "
        "uncertainty was computed.",
    )
    landmark_misfit_ratio: float | None = Field(
        None,
        description="Birge ratio √(χ²/ν) of the image landmarks (points, corners' midpoints, pedicles) about the "
        "fitted spine against their landmark SDs, ν their count less the parameters they determine: about 1 or "
        "less when they scatter as stated; above 1 every SD is widened by it (a projection model that is not the "
        "film's, or an SD stated below the clicks' scatter). Null when no uncertainty was computed.",
    )
    assumed: list[Assumption] = Field(
        default_factory=list,
        description="Each prior or default that decided a number because the input did not give it (name, view, "
        "reason); empty when the input gave everything used.",
    )


class EngineInfo(BaseModel):
    version: str
    profile: str


class RegistrationResult(BaseModel):
    """What ``spine_engine.register`` returns and what a client reads back as ``result``."""

    vertebrae: list[VertebraResult]
    measures: Measures
    fit: FitReport
    engine: EngineInfo
