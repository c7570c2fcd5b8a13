"""The result tables of a succeeded job: its measures (``job_measures``, one row) and its
per-vertebra strains (``vertebra_strains``), made from the ``RegistrationResult``."""

from __future__ import annotations

from typing import Any


def measures_row(result: dict[str, Any]) -> dict[str, Any]:
    """The ``job_measures`` columns of a result (the major curve, kyphosis, lordosis, fit)."""
    measures = result.get("measures") or {}
    curves = measures.get("cobb") or []
    major = next((c for c in curves if c.get("major")), None) or {}
    fit = result.get("fit") or {}
    return {
        "major_cobb_deg": major.get("angle_deg"),
        "major_curve_upper": major.get("upper"),
        "major_curve_lower": major.get("lower"),
        "major_curve_apex": major.get("apex"),
        "major_convexity": major.get("convexity"),
        "major_apex_axial_rotation_deg": major.get("apex_axial_rotation_deg"),
        "major_plane_of_max_curvature_deg": major.get("plane_of_max_curvature_deg"),
        "curve_count": len(curves),
        "thoracic_kyphosis_t4_t12_deg": measures["thoracic_kyphosis_t4_t12_deg"],
        "thoracic_kyphosis_t5_t12_deg": measures["thoracic_kyphosis_t5_t12_deg"],
        "lumbar_lordosis_l1_l5_deg": measures["lumbar_lordosis_l1_l5_deg"],
        "mean_registration_error_mm": fit["mean_registration_error_mm"],
        "converged": bool(fit["converged"]),
    }


def strain_rows(result: dict[str, Any]) -> list[dict[str, Any]]:
    """The ``vertebra_strains`` rows of a result, one per vertebra (without the job id)."""
    rows = []
    for v in result.get("vertebrae") or []:
        u = v.get("u") or (None, None, None)
        s = v.get("v") or (None, None, None)
        rows.append(
            {
                "level": v["level"],
                "u1": u[0], "u2": u[1], "u3": u[2],
                "v1": s[0], "v2": s[1], "v3": s[2],
                "pa_bending_deg": v.get("pa_bending_deg"),
                "lateral_bending_deg": v.get("lateral_bending_deg"),
                "twist_deg": v.get("twist_deg"),
                "axial_rotation_deg": v["axial_rotation_deg"],
            }
        )  # fmt: skip
    return rows
