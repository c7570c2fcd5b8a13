"""The result tables of a succeeded job: its measures (``job_measures``, one row) and its
per-vertebra strains (``vertebra_strains``), read from the ``RegistrationResult`` model."""

from __future__ import annotations

from typing import Any

from spine_engine.models import RegistrationResult


def measures_row(result: RegistrationResult) -> dict[str, Any]:
    """The ``job_measures`` columns of a result (the major curve, kyphosis, lordosis, fit)."""
    measures = result.measures
    major = next((c for c in measures.cobb if c.major), None)
    return {
        "major_cobb_deg": major.angle_deg if major else None,
        "major_curve_upper": major.upper if major else None,
        "major_curve_lower": major.lower if major else None,
        "major_curve_apex": major.apex if major else None,
        "major_convexity": major.convexity if major else None,
        "major_apex_axial_rotation_deg": major.apex_axial_rotation_deg if major else None,
        "major_plane_of_max_curvature_deg": major.plane_of_max_curvature_deg if major else None,
        "curve_count": len(measures.cobb),
        "thoracic_kyphosis_t4_t12_deg": measures.thoracic_kyphosis_t4_t12_deg,
        "thoracic_kyphosis_t5_t12_deg": measures.thoracic_kyphosis_t5_t12_deg,
        "lumbar_lordosis_l1_l5_deg": measures.lumbar_lordosis_l1_l5_deg,
        "mean_registration_error_mm": result.fit.mean_registration_error_mm,
        "converged": bool(result.fit.converged),
    }


def strain_rows(result: RegistrationResult) -> list[dict[str, Any]]:
    """The ``vertebra_strains`` rows of a result, one per vertebra (without the job id)."""
    rows = []
    for v in result.vertebrae:
        u = v.u or (None, None, None)
        s = v.v or (None, None, None)
        rows.append(
            {
                "level": v.level,
                "u1": u[0], "u2": u[1], "u3": u[2],
                "v1": s[0], "v2": s[1], "v3": s[2],
                "sagittal_bending_deg": v.sagittal_bending_deg,
                "frontal_bending_deg": v.frontal_bending_deg,
                "twist_deg": v.twist_deg,
                "axial_rotation_deg": v.axial_rotation_deg,
            }
        )  # fmt: skip
    return rows
