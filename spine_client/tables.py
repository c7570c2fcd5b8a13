"""CSV views of a job's result: one row per vertebra, or one row per measure, and the summary of
``spine submit-dir``. Column names carry their units (docs/client.md).

Every number with its trust, as in the page's CSVs (web/src/csv.ts, web/src/results.ts): the
standard deviations the result gives (``position_sd_*_mm``, ``axial_rotation_sd_deg``; a measure's
``sd`` in its unit) and a ``model_estimate`` mark on what comes from the model's prior rather than the
landmarks (``fit.unreliable``): per vertebra, the columns so estimated joined by ``;`` (the same on
every row); per measure, ``model estimate`` or empty; per job (``spine list``, ``submit-dir``'s summary),
the job's columns so estimated joined by ``;``, with the SD of each angle in a ``_sd_deg`` column.
Columns a version adds go at the end, so that a script reading columns by position keeps reading the
same ones (docs/client.md)."""

from __future__ import annotations

import csv
import io
from collections.abc import Iterable, Sequence
from typing import Any

DEPRECATED_VERTEBRA_COLUMNS = ("pa_bending_deg", "lateral_bending_deg")
"""The result contract's deprecated aliases of ``sagittal_bending_deg`` and ``frontal_bending_deg``
(same values), kept as the last columns until the contract removes them (docs/client.md)."""
VERTEBRA_COLUMNS = [
    "level", "x_mm", "y_mm", "z_mm", "position_sd_x_mm", "position_sd_y_mm", "position_sd_z_mm",
    "u1_rad_per_mm", "u2_rad_per_mm", "u3_rad_per_mm", "v1", "v2", "v3",
    "sagittal_bending_deg", "frontal_bending_deg", "twist_deg", "axial_rotation_deg", "axial_rotation_sd_deg",
    "frontal_tilt_deg", "model_estimate", *DEPRECATED_VERTEBRA_COLUMNS,
]  # fmt: skip
MEASURE_COLUMNS = ["measure", "value", "sd", "unit", "upper", "lower", "apex", "convexity", "major", "model_estimate"]
MODEL_MARK = "model estimate"
"""The page's mark of a measure from the model's prior (web/src/results.ts ``MODEL_MARK``)."""
MODEL_COLUMNS: dict[str, tuple[str, ...]] = {
    "depth": ("y_mm",),
    "axial_rotation": ("axial_rotation_deg",),
    "twist": ("u3_rad_per_mm", "twist_deg"),
    "kyphosis": ("sagittal_bending_deg", "pa_bending_deg"),
    "cobb": ("frontal_tilt_deg",),
}
"""The vertebra columns that come from the model's prior when ``fit.unreliable`` names the quantity
(the page's ``MODEL_COLUMNS``, with the deprecated alias ``pa_bending_deg`` while it is a column, and
``frontal_tilt_deg``, which the page's CSV does not have: the tilts the frontal Cobb angles are read
from, the prior's where no PA landmark shows them, docs/measures.md)."""
JOB_MEASURES = (
    ("major_cobb_deg", "major_cobb_sd_deg", "cobb"),
    ("thoracic_kyphosis_t4_t12_deg", "thoracic_kyphosis_t4_t12_sd_deg", "kyphosis"),
    ("lumbar_lordosis_l1_l5_deg", "lumbar_lordosis_l1_l5_sd_deg", "lordosis"),
)
"""A job's row's angles (deg): the column, the column of its SD (deg) and the ``fit.unreliable``
quantity that makes it a model estimate (docs/measures.md: ``cobb`` covers every frontal Cobb angle,
``kyphosis`` and ``lordosis`` their measures)."""
SUMMARY_COLUMNS = [
    "file", "job_id", "status", "major_cobb_deg", "major_upper", "major_lower", "major_apex", "major_convexity",
    "thoracic_kyphosis_t4_t12_deg", "lumbar_lordosis_l1_l5_deg", "mean_registration_error_mm", "problem_type",
    "detail", "major_cobb_sd_deg", "thoracic_kyphosis_t4_t12_sd_deg", "lumbar_lordosis_l1_l5_sd_deg",
    "model_estimate",
]  # fmt: skip
"""``submit-dir``'s summary.csv; the SDs and the model-estimate mark came last, after ``detail``."""
LIST_COLUMNS = [
    "job_id", "status", "created_at", "finished_at", "major_cobb_deg", "major_upper", "major_lower", "problem_type",
    "major_cobb_sd_deg", "model_estimate",
]  # fmt: skip
"""``spine list --format csv``; the SD and the model-estimate mark came last, after ``problem_type``."""
LIST_TABLE_COLUMNS = [c for c in LIST_COLUMNS if c not in ("major_cobb_sd_deg", "model_estimate")]
"""``spine list``'s table: the major Cobb angle's cell reads ``value ± SD`` and its mark (``list_cells``)."""


def _csv(columns: Sequence[str], rows: Iterable[dict[str, Any]]) -> str:
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=list(columns), lineterminator="\n", extrasaction="ignore")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: _cell(v) for k, v in row.items()})
    return out.getvalue()


def _cell(value: Any) -> Any:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    return value


def _unreliable(result: dict[str, Any]) -> list[str]:
    """``fit.unreliable``: the quantities that come from the model's prior, in the result's order."""
    return list((result.get("fit") or {}).get("unreliable") or [])


def vertebrae_csv(result: dict[str, Any]) -> str:
    """One row per vertebra, T1 to L5: position (LPS, mm) and its SD, strains u (rad/mm) and v,
    angles, the axial rotation's SD, and the columns that are model estimates."""
    model = ";".join(c for q in _unreliable(result) for c in MODEL_COLUMNS.get(q, ()))
    rows = []
    for v in result.get("vertebrae") or []:
        u = v.get("u") or (None, None, None)
        s = v.get("v") or (None, None, None)
        sd = v.get("position_sd_mm") or (None, None, None)
        x, y, z = v["position"]
        sagittal = v.get("sagittal_bending_deg", v.get("pa_bending_deg"))
        frontal = v.get("frontal_bending_deg", v.get("lateral_bending_deg"))
        rows.append({
            "level": v["level"], "x_mm": x, "y_mm": y, "z_mm": z,
            "position_sd_x_mm": sd[0], "position_sd_y_mm": sd[1], "position_sd_z_mm": sd[2],
            "u1_rad_per_mm": u[0], "u2_rad_per_mm": u[1], "u3_rad_per_mm": u[2], "v1": s[0], "v2": s[1], "v3": s[2],
            "sagittal_bending_deg": sagittal, "frontal_bending_deg": frontal,
            "pa_bending_deg": sagittal, "lateral_bending_deg": frontal,
            "twist_deg": v.get("twist_deg"), "axial_rotation_deg": v.get("axial_rotation_deg"),
            "axial_rotation_sd_deg": v.get("axial_rotation_sd_deg"), "frontal_tilt_deg": v.get("frontal_tilt_deg"),
            "model_estimate": model,
        })  # fmt: skip
    return _csv(VERTEBRA_COLUMNS, rows)


def measure_rows(result: dict[str, Any]) -> list[dict[str, Any]]:
    """The measures' rows, each with its SD (when the result gives one) and its model-estimate mark
    (the page's ``measureRows``: the apex's rotation when ``axial_rotation`` is unreliable, the plane
    of maximum curvature and the Cobb angle in it when ``plane_of_max_curvature`` is, the frontal Cobb
    angles when ``cobb`` is, kyphosis and lordosis by their names)."""
    measures = result.get("measures") or {}
    unreliable = set(_unreliable(result))

    def mark(quantity: str | None) -> str:
        return MODEL_MARK if quantity in unreliable else ""

    rotation_sd = {v.get("level"): v.get("axial_rotation_sd_deg") for v in result.get("vertebrae") or []}
    rows: list[dict[str, Any]] = []
    for c in measures.get("cobb") or []:
        where = {"upper": c["upper"], "lower": c["lower"], "apex": c["apex"], "convexity": c["convexity"],
                 "major": bool(c.get("major"))}  # fmt: skip
        plane = mark("plane_of_max_curvature")
        rows += [
            {"measure": "cobb_angle", "value": c["angle_deg"], "sd": c.get("angle_sd_deg"), "unit": "deg", **where,
             "model_estimate": mark("cobb")},
            {"measure": "apex_axial_rotation", "value": c["apex_axial_rotation_deg"], "sd": rotation_sd.get(c["apex"]),
             "unit": "deg", **where, "model_estimate": mark("axial_rotation")},
            {"measure": "plane_of_max_curvature", "value": c["plane_of_max_curvature_deg"], "unit": "deg", **where,
             "model_estimate": plane},
            {"measure": "max_curvature", "value": c["max_curvature_deg"], "unit": "deg", **where,
             "model_estimate": plane},
        ]  # fmt: skip
    largest = measures.get("largest_cobb")
    if largest and not largest.get("reported_as_curve"):  # no curve of 10°: the page's "largest frontal angle"
        rows.append({"measure": "largest_cobb_angle", "value": largest["angle_deg"], "sd": largest.get("angle_sd_deg"),
                     "unit": "deg", "upper": largest["upper"], "lower": largest["lower"],
                     "model_estimate": mark("cobb")})  # fmt: skip
    for name, upper, lower, quantity in (
        ("thoracic_kyphosis_t4_t12", "T4", "T12", "kyphosis"),
        ("thoracic_kyphosis_t5_t12", "T5", "T12", "kyphosis"),
        ("lumbar_lordosis_l1_l5", "L1", "L5", "lordosis"),
    ):
        if measures.get(f"{name}_deg") is not None:
            rows.append({"measure": name, "value": measures[f"{name}_deg"], "sd": measures.get(f"{name}_sd_deg"),
                         "unit": "deg", "upper": upper, "lower": lower, "model_estimate": mark(quantity)})  # fmt: skip
    fit = result.get("fit") or {}
    if fit.get("mean_registration_error_mm") is not None:
        rows.append({"measure": "mean_registration_error", "value": fit["mean_registration_error_mm"], "unit": "mm"})
    if fit.get("landmark_misfit_ratio") is not None:
        rows.append({"measure": "landmark_misfit_ratio", "value": fit["landmark_misfit_ratio"], "unit": "1"})
    return rows


def measure_records(result: dict[str, Any]) -> list[dict[str, Any]]:
    """The measures' rows as JSON objects (``spine get --measures --format json``): every column of
    ``MEASURE_COLUMNS``, null where the CSV's cell is empty, ``major`` and ``model_estimate`` booleans
    (``model_estimate`` true where the CSV says ``model estimate``)."""
    records = []
    for row in measure_rows(result):
        record = {c: row.get(c) for c in MEASURE_COLUMNS}
        record["model_estimate"] = row.get("model_estimate") == MODEL_MARK
        records.append(record)
    return records


def measures_csv(result: dict[str, Any]) -> str:
    """One row per measure: every Cobb curve (angle, apical rotation, plane and magnitude of maximum
    curvature), the largest frontal angle when no curve reaches 10°, kyphosis, lordosis and the mean
    registration error, each with its SD and mark."""
    return _csv(MEASURE_COLUMNS, measure_rows(result))


def _job_measures(result: dict[str, Any]) -> dict[str, Any]:
    """A job's row's measures: the major curve (its Cobb angle and SD, deg; ends, apex, convexity), the
    kyphosis T4–T12 and lordosis L1–L5 with their SDs (deg), the mean registration error (mm), and
    ``model_estimate``: the columns of ``JOB_MEASURES`` with a value that ``fit.unreliable`` makes the
    model's prior's, joined by ``;``."""
    measures = result.get("measures") or {}
    major = next((c for c in measures.get("cobb") or [] if c.get("major")), None) or {}
    row = {
        "major_cobb_deg": major.get("angle_deg"), "major_cobb_sd_deg": major.get("angle_sd_deg"),
        "major_upper": major.get("upper"), "major_lower": major.get("lower"), "major_apex": major.get("apex"),
        "major_convexity": major.get("convexity"),
        "mean_registration_error_mm": (result.get("fit") or {}).get("mean_registration_error_mm"),
    }  # fmt: skip
    for name in ("thoracic_kyphosis_t4_t12", "lumbar_lordosis_l1_l5"):
        row[f"{name}_deg"], row[f"{name}_sd_deg"] = measures.get(f"{name}_deg"), measures.get(f"{name}_sd_deg")
    unreliable = set(_unreliable(result))
    row["model_estimate"] = ";".join(c for c, _, q in JOB_MEASURES if q in unreliable and row[c] is not None)
    return row


def summary_row(file: str, job: dict[str, Any] | None, *, status: str | None = None,
                problem: dict[str, Any] | None = None) -> dict[str, Any]:  # fmt: skip
    row: dict[str, Any] = {"file": file, "status": status or (job or {}).get("status")}
    if job is not None:
        row["job_id"] = job.get("id")
        row.update(_job_measures(job.get("result") or {}))
        problem = problem or job.get("error")
    if problem:
        row["problem_type"] = str(problem.get("type", "")).rsplit("/", 1)[-1]
        row["detail"] = problem.get("detail")
    return row


def summary_csv(rows: Iterable[dict[str, Any]]) -> str:
    return _csv(SUMMARY_COLUMNS, rows)


def list_row(job: dict[str, Any]) -> dict[str, Any]:
    """A row of ``spine list``: the job's summary row with its times, its ``model_estimate`` naming only
    the columns ``LIST_COLUMNS`` has."""
    row = summary_row("", job)
    row.update(created_at=job.get("created_at"), finished_at=job.get("finished_at"))
    row["model_estimate"] = ";".join(c for c in (row.get("model_estimate") or "").split(";") if c in LIST_COLUMNS)
    return row


def list_csv(rows: Iterable[dict[str, Any]]) -> str:
    return _csv(LIST_COLUMNS, rows)


def with_sd(value: float, sd: float | None, marked: bool) -> str:
    """An angle (deg) as a person reads it in a table: one decimal, ``± SD`` when the result gives one,
    and ``(model estimate)`` when it comes from the model's prior."""
    text = f"{value:.1f}" if sd is None else f"{value:.1f} ± {sd:.1f}"
    return f"{text} ({MODEL_MARK})" if marked else text


def list_cells(row: dict[str, Any]) -> list[str]:
    """A ``spine list`` row as its table shows it: ``LIST_COLUMNS`` without the SD and the mark, which
    the major Cobb angle's cell carries (``with_sd``)."""
    marked = set((row.get("model_estimate") or "").split(";"))
    cells = []
    for c in LIST_TABLE_COLUMNS:
        value = row.get(c)
        if value is None:
            cells.append("")
        elif c == "major_cobb_deg":
            cells.append(with_sd(float(value), row.get("major_cobb_sd_deg"), c in marked))
        else:
            cells.append(f"{value:.1f}" if isinstance(value, float) else str(value))
    return cells
