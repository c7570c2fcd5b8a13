"""A job payload from a landmark CSV, its images named by UID (``payload_by_reference``) or read from
their DICOM files on the client's side (``spine_client.dicom_input``, the ``[dicom]`` extra).

The landmark CSV is the page's (README "Landmark CSV"): one landmark a line, ``level,column,row[,view]``,
view ``pa`` (default) or ``lateral``, a header line starting with ``level`` and ``#`` lines skipped.
With a DICOM file the coordinates are image pixels (``units: px``, column and row with (0, 0) the
top-left corner of the top-left pixel) unless told ``mm``.

``LEVELS`` are the contract's (``Landmark.level`` of openapi.yaml), T1 to L5.
"""

from __future__ import annotations

import codecs
import csv
import io
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO, Literal, get_args

from spine_client.contract import Landmark

LEVELS: tuple[str, ...] = get_args(Landmark.model_fields["level"].annotation)


class LandmarkCsvError(ValueError):
    """A landmark CSV line that cannot be read; the message names the line."""


LandmarkSource = str | Path | BinaryIO
"""Where a landmark CSV is read from: a file's path, or an open binary stream (``spine submit -``: stdin)."""


def read_landmark_csv(source: LandmarkSource) -> str:
    """The CSV's text, decoded as UTF-8 (RFC 4180 §3 leaves the charset to the
    ``text/csv`` media type's parameter); a leading byte-order mark (U+FEFF, as spreadsheets write it)
    is skipped. ``LandmarkCsvError`` names the first byte that is not UTF-8; ``OSError`` when the file
    cannot be read."""
    data = Path(source).read_bytes() if isinstance(source, (str, Path)) else source.read()
    skipped = len(codecs.BOM_UTF8) if data.startswith(codecs.BOM_UTF8) else 0
    try:
        return data[skipped:].decode("utf-8")
    except UnicodeDecodeError as exc:
        at = skipped + exc.start
        raise LandmarkCsvError(f"not UTF-8 text: byte 0x{data[at]:02x} at offset {at}") from None


def _rows_or_error(rows: Iterator[list[str]]) -> Iterator[list[str]]:
    """The CSV's rows; ``LandmarkCsvError`` naming the line where the reader gives up (a field beyond
    ``csv.field_size_limit``, a NUL where the reader refuses one)."""
    while True:
        try:
            yield next(rows)
        except StopIteration:
            return
        except csv.Error as exc:
            line = getattr(rows, "line_num", 0)
            raise LandmarkCsvError(f"line {line}: not readable as CSV ({exc})") from None


def parse_landmark_csv(text: str) -> dict[str, list[dict[str, Any]]]:
    """``{"pa": [...], "lateral": [...]}`` landmarks (``{"level", "point"}``) sorted T1 → L5."""
    out: dict[str, list[dict[str, Any]]] = {"pa": [], "lateral": []}
    errors: list[str] = []
    for number, cells in enumerate(_rows_or_error(csv.reader(io.StringIO(text))), start=1):
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


def payload_with_landmarks(
    landmarks_csv: LandmarkSource, *, units: Literal["px", "mm"], base: dict[str, Any] | None, lateral: bool
) -> dict[str, Any]:
    """``base`` with the CSV's landmarks as its ``pa`` (and ``lateral``, when the CSV has lateral
    landmarks or ``lateral`` is true) view, in ``units`` unless ``base`` says otherwise."""
    landmarks = parse_landmark_csv(read_landmark_csv(landmarks_csv))
    payload: dict[str, Any] = dict(base or {})
    payload["pa"] = {"units": units, **(payload.get("pa") or {}), "landmarks": landmarks["pa"]}
    if landmarks["lateral"] or lateral:
        payload["lateral"] = {"units": units, **(payload.get("lateral") or {}), "landmarks": landmarks["lateral"]}
    return payload


def payload_by_reference(
    landmarks_csv: LandmarkSource,
    study_instance_uid: str,
    pa_sop_instance_uid: str,
    lateral_sop_instance_uid: str | None = None,
    *,
    units: Literal["px", "mm"] = "px",
    base: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """A payload naming its images by UID only: the service reads their spacing, orientation and
    geometry from its PACS (``SPINE_DICOMWEB_URL``) when the job runs."""
    payload = payload_with_landmarks(landmarks_csv, units=units, base=base,
                                     lateral=lateral_sop_instance_uid is not None)  # fmt: skip
    study = {**(payload.get("study") or {}), "study_instance_uid": study_instance_uid,
             "pa_sop_instance_uid": pa_sop_instance_uid}  # fmt: skip
    if lateral_sop_instance_uid is not None:
        study["lateral_sop_instance_uid"] = lateral_sop_instance_uid
    payload["study"] = study
    return payload
