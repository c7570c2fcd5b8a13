"""Pydantic models of the job payload (what a client posts) and the result (what it reads back).

These models are the public contract shared by the engine, the API and ``openapi.yaml``.
Conventions (``DESIGN.md``): 3D frame DICOM LPS in mm (+x patient left, +y posterior,
+z superior); directors d1 ≈ patient left, d2 ≈ anterior, d3 = centreline tangent pointing
caudally, d1 × d2 = d3; directors are sent as rows ``[d1, d2, d3]``.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from .levels import LEVEL_INDEX, Level

DIRECTOR_TOLERANCE = 1e-3
"""Largest accepted |RᵀR − I| entry and |det R − 1| for boundary directors."""

MAX_LANDMARKS_PER_VIEW = 17 * 6
"""Upper bound on landmark entries per view (17 levels; leaves room for later landmark kinds)."""

PATIENT_DIRECTIONS = ("L", "R", "A", "P", "H", "F")

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
Vec2 = tuple[FiniteFloat, FiniteFloat]
Vec3 = tuple[FiniteFloat, FiniteFloat, FiniteFloat]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


# ---------------------------------------------------------------- payload


class Landmark(_Strict):
    """A landmark of one vertebra on one view: the midpoint of its top endplate, as (column, row)."""

    level: Level = Field(description="Vertebral level, T1..L5.")
    point: Vec2 = Field(description="Image coordinates (column, row) in the view's units.")


class Projection(_Strict):
    """Weak perspective of a view: image point = scale·(e_c·r, e_r·r) + translation (mm)."""

    scale: Annotated[float, Field(gt=0, allow_inf_nan=False)] = Field(
        description="Dimensionless magnification s from patient mm to detector mm."
    )
    translation: Vec2 = Field(description="Translation T (column, row) in detector mm.")


class _View(_Strict):
    units: Literal["mm", "px"] = Field("mm", description="Units of the landmark coordinates.")
    pixel_spacing: tuple[
        Annotated[float, Field(gt=0, allow_inf_nan=False)], Annotated[float, Field(gt=0, allow_inf_nan=False)]
    ] | None = Field(
        None,
        description="DICOM (0028,0030) pixel spacing [row spacing, column spacing] in mm; "
        "required when units is px.",
    )
    patient_orientation: tuple[str, str]
    landmarks: list[Landmark] = Field(max_length=MAX_LANDMARKS_PER_VIEW)
    projection: Projection | None = Field(
        None,
        description="Known weak perspective of this view, in detector mm. When absent it is "
        "estimated in closed form from the boundary vertebrae's landmarks.",
    )

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


class PAView(_View):
    """The postero-anterior radiograph and its landmarks."""

    patient_orientation: tuple[str, str] = Field(
        ("L", "F"),
        description="DICOM (0020,0020) patient orientation of the column and row directions.",
    )
    landmarks: list[Landmark] = Field(min_length=1, max_length=MAX_LANDMARKS_PER_VIEW)


class LateralView(_View):
    """An optional lateral radiograph and its landmarks (any subset of levels)."""

    patient_orientation: tuple[str, str] = Field(
        ("A", "F"),
        description="DICOM (0020,0020) patient orientation of the column and row directions.",
    )


class Pose(_Strict):
    """Position (mm, LPS) and directors (rows d1, d2, d3) of a boundary vertebra."""

    position: Vec3
    directors: tuple[Vec3, Vec3, Vec3] = Field(
        description="Rows d1 (≈ patient left), d2 (≈ anterior), d3 (caudal tangent); "
        "orthonormal and right-handed within 1e-3."
    )

    @field_validator("directors")
    @classmethod
    def _orthonormal(cls, value: tuple[Vec3, Vec3, Vec3]) -> tuple[Vec3, Vec3, Vec3]:
        m = np.asarray(value, dtype=float)
        gram_error = float(np.max(np.abs(m @ m.T - np.eye(3))))
        if gram_error > DIRECTOR_TOLERANCE:
            raise ValueError(
                f"directors are not orthonormal: largest |d_i·d_j − δ_ij| is {gram_error:.3g} "
                f"(tolerance {DIRECTOR_TOLERANCE})"
            )
        det = float(np.linalg.det(m))
        if abs(det - 1.0) > DIRECTOR_TOLERANCE:
            raise ValueError(f"directors are not right-handed: det [d1; d2; d3] = {det:.4g}, expected 1")
        return value


class Boundary(_Strict):
    """Boundary conditions: T1 and L5 fixed in position and orientation."""

    T1: Pose
    L5: Pose

    @model_validator(mode="after")
    def _distinct(self) -> Boundary:
        gap = math.dist(self.T1.position, self.L5.position)
        if gap < 1.0:
            raise ValueError(f"T1 and L5 positions are {gap:.3g} mm apart; they must be distinct")
        return self


class Options(_Strict):
    profile: str = Field("default", description="Name of the elastic-property profile to use.")


class JobPayload(_Strict):
    """The body a client posts to create a job, and the argument of ``spine_engine.register``.

    Checks that span several fields (px units need pixel_spacing; without a projection a view
    needs its T1 and L5 landmarks) live in ``spine_engine.validation.validate_payload``, so that
    their errors name the field.
    """

    pa: PAView
    lateral: LateralView | None = None
    boundary: Boundary
    options: Options = Field(default_factory=Options)


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
    pa_bending_deg: float | None = Field(description="Sagittal (postero-anterior) bending u1·Δs, degrees.")
    lateral_bending_deg: float | None = Field(description="Coronal (lateral) bending u2·Δs, degrees.")
    twist_deg: float | None = Field(description="Twist u3·Δs about d3, degrees.")
    axial_rotation_deg: float = Field(
        description="Axial rotation in the transverse plane, degrees (docs/measures.md)."
    )


class CobbCurve(BaseModel):
    """One frontal curve: Cobb angle between its end vertebrae, apex and 3D descriptors."""

    upper: Level
    lower: Level
    apex: Level
    angle_deg: float = Field(description="Frontal Cobb angle, degrees.")
    major: bool = Field(description="True for the largest curve; exactly one when any curve exists.")
    convexity: Literal["left", "right"]
    apex_axial_rotation_deg: float
    plane_of_max_curvature_deg: float = Field(
        description="Azimuth of the plane of maximum curvature from the frontal plane toward "
        "anterior, degrees (SRS 3D terminology; docs/measures.md)."
    )
    max_curvature_deg: float = Field(description="Cobb angle measured in that plane, degrees.")


class Measures(BaseModel):
    """Clinical measures computed from the reconstruction (definitions in docs/measures.md)."""

    cobb: list[CobbCurve]
    thoracic_kyphosis_t4_t12_deg: float
    thoracic_kyphosis_t5_t12_deg: float
    lumbar_lordosis_l1_l5_deg: float


class Residual(BaseModel):
    view: Literal["pa", "lateral"]
    level: Level
    residual_mm: float = Field(description="Distance between landmark and projected model point, patient mm.")


class ViewProjection(BaseModel):
    scale: float
    translation: tuple[float, float]
    estimated: bool = Field(description="True when estimated from the boundary vertebrae.")


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


class EngineInfo(BaseModel):
    version: str
    profile: str


class RegistrationResult(BaseModel):
    """What ``spine_engine.register`` returns and what a client reads back as ``result``."""

    vertebrae: list[VertebraResult]
    measures: Measures
    fit: FitReport
    engine: EngineInfo
