"""A job payload from a landmark CSV and the radiographs' DICOM files, read on the client's side.

The landmark CSV is the page's (README "Landmark CSV"): one landmark a line, ``level,column,row[,view]``,
view ``pa`` (default) or ``lateral``, a header line starting with ``level`` and ``#`` lines skipped.
With a DICOM file the coordinates are image pixels (``units: px``, column and row with (0, 0) the
top-left corner of the top-left pixel) unless told ``mm``.

The header is read by ``services.dicom.header`` (pydicom), imported only when a DICOM file is given,
so that the client's other commands do not load pydicom. What the header gives fills the payload
where the payload is silent; a payload value that differs is kept and reported as a conflict.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any, Literal

LEVELS = ("T1", "T2", "T3", "T4", "T5", "T6", "T7", "T8", "T9", "T10", "T11", "T12", "L1", "L2", "L3", "L4", "L5")


class LandmarkCsvError(ValueError):
    """A landmark CSV line that cannot be read; the message names the line."""


def parse_landmark_csv(text: str) -> dict[str, list[dict[str, Any]]]:
    """``{"pa": [...], "lateral": [...]}`` landmarks (``{"level", "point"}``) sorted T1 → L5."""
    out: dict[str, list[dict[str, Any]]] = {"pa": [], "lateral": []}
    errors: list[str] = []
    for number, cells in enumerate(csv.reader(io.StringIO(text)), start=1):
        cells = [c.strip() for c in cells]
        if not cells or not any(cells) or cells[0].startswith("#") or cells[0].lower() == "level":
            continue
        where = f"line {number}"
        if not 3 <= len(cells) <= 4:
            errors.append(f"{where}: expected level,column,row[,view], got {len(cells)} fields")
            continue
        level = cells[0].upper()
        if level not in LEVELS:
            errors.append(f"{where}: level {cells[0]!r} is not one of T1..T12, L1..L5")
            continue
        try:
            column, row = float(cells[1]), float(cells[2])
        except ValueError:
            errors.append(f"{where}: column and row must be numbers")
            continue
        if not all(abs(v) < float("inf") for v in (column, row)):
            errors.append(f"{where}: column and row must be finite numbers")
            continue
        view = (cells[3] if len(cells) == 4 and cells[3] else "pa").lower()
        if view not in out:
            errors.append(f"{where}: view {cells[3]!r} is not pa or lateral")
            continue
        if any(lm["level"] == level for lm in out[view]):
            errors.append(f"{where}: level {level} is given more than once for the {view} view")
            continue
        out[view].append({"level": level, "point": [column, row]})
    if not errors and not out["pa"]:
        errors.append("no PA landmark found")
    if errors:
        raise LandmarkCsvError("; ".join(errors))
    for landmarks in out.values():
        landmarks.sort(key=lambda lm: LEVELS.index(lm["level"]))
    return out


def payload_by_reference(
    landmarks_csv: str | Path,
    study_instance_uid: str,
    pa_sop_instance_uid: str,
    lateral_sop_instance_uid: str | None = None,
    *,
    units: Literal["px", "mm"] = "px",
    base: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """A payload naming its images by UID only: the service reads their spacing, orientation and
    geometry from its PACS (``SPINE_DICOMWEB_URL``) when the job runs."""
    landmarks = parse_landmark_csv(Path(landmarks_csv).read_text(encoding="utf-8"))
    payload: dict[str, Any] = dict(base or {})
    payload["pa"] = {"units": units, **(payload.get("pa") or {}), "landmarks": landmarks["pa"]}
    if landmarks["lateral"] or lateral_sop_instance_uid is not None:
        payload["lateral"] = {"units": units, **(payload.get("lateral") or {}), "landmarks": landmarks["lateral"]}
    study = {**(payload.get("study") or {}), "study_instance_uid": study_instance_uid,
             "pa_sop_instance_uid": pa_sop_instance_uid}  # fmt: skip
    if lateral_sop_instance_uid is not None:
        study["lateral_sop_instance_uid"] = lateral_sop_instance_uid
    payload["study"] = study
    return payload


def payload_from_dicom(
    landmarks_csv: str | Path,
    pa_dicom: str | Path,
    lateral_dicom: str | Path | None = None,
    *,
    units: Literal["px", "mm"] = "px",
    base: dict[str, Any] | None = None,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """(payload, provenance as JSON) from a landmark CSV and the PA (and lateral) DICOM files.

    ``base`` is a payload whose explicit values win over the headers' (e.g. ``options``, a
    ``boundary``, or a spacing typed in). View fields this version's payload contract does not know
    (``spine_engine.models``) are left out of the payload and stay in the provenance. Raises
    ``LandmarkCsvError`` and the DICOM layer's ``DicomError`` subclasses (``NotDicom``,
    ``MissingAttribute``, ``InvalidAttribute``, ``UnsupportedOrientation``), each naming the
    attribute by keyword and tag.
    """
    from services.db.job_forms import engine_payload
    from services.dicom.header import read_header
    from services.dicom.merge import apply_headers

    landmarks = parse_landmark_csv(Path(landmarks_csv).read_text(encoding="utf-8"))
    payload: dict[str, Any] = dict(base or {})
    payload["pa"] = {"units": units, **(payload.get("pa") or {}), "landmarks": landmarks["pa"]}
    headers = {"pa": read_header(Path(pa_dicom))}
    if lateral_dicom is not None:
        headers["lateral"] = read_header(Path(lateral_dicom))
    if landmarks["lateral"] or lateral_dicom is not None:
        payload["lateral"] = {"units": units, **(payload.get("lateral") or {}), "landmarks": landmarks["lateral"]}
    merged, provenance = apply_headers(payload, headers, source="file")  # type: ignore[arg-type]
    return engine_payload(merged), provenance.model_dump(mode="json")
