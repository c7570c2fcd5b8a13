"""Every kind of bad input, sent over HTTP to a real `spine serve` (tools/badinput.py --spawn):
each is refused with the expected problem, none is a 5xx, and docs/reliability.md's table is the
one this run produces."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from tools.badinput import run, spawned, table

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "reliability.md"
BEGIN, END = "<!-- bad-input-table: python -m tools.badinput --spawn -->", "<!-- /bad-input-table -->"

EXPECTED = {
    "malformed JSON": (400, "malformed-json"),
    "empty body": (400, "malformed-json"),
    "not UTF-8": (400, "malformed-json"),
    "JSON but not an object": (422, "validation-error"),
    "wrong types": (422, "validation-error"),
    "number as a string": (422, "validation-error"),
    "boolean as a number": (422, "validation-error"),
    "NaN": (422, "validation-error"),
    "infinity": (422, "validation-error"),
    "huge number (float overflow)": (422, "validation-error"),
    "huge number (finite)": (422, "validation-error"),
    "huge number (too many digits)": (400, "malformed-json"),
    "unknown level": (422, "validation-error"),
    "duplicate levels": (422, "validation-error"),
    "duplicate key": (422, "validation-error"),
    "duplicate key in a batch entry": (422, "validation-error"),
    "landmarks out of order": (422, "validation-error"),
    "levels implausibly far apart": (422, "validation-error"),
    "crossed corners": (422, "validation-error"),
    "corners turned upside down": (422, "validation-error"),
    "pedicles swapped": (422, "validation-error"),
    "no room for the spine": (422, "validation-error"),
    "landmarks off the image": (422, "validation-error"),
    "too many landmarks": (422, "validation-error"),
    "non-orthonormal directors": (422, "validation-error"),
    "left-handed directors": (422, "validation-error"),
    "unknown field": (422, "validation-error"),
    "unknown profile": (422, "validation-error"),
    "NUL character in a text": (422, "validation-error"),
    "study date not YYYY-MM-DD": (422, "validation-error"),
    "study date as a number": (422, "validation-error"),
    "blank Patient ID": (422, "validation-error"),
    "deep nesting (parser)": (400, "malformed-json"),
    "deep nesting (in a field)": (422, "validation-error"),
    "10 MB body": (413, "payload-too-large"),
    "batch of 1001": (413, "payload-too-large"),
    "batch entry not an object": ("200 (entry 422)", "validation-error"),
    "wrong content type": (415, "unsupported-media-type"),
    "form content type": (415, "unsupported-media-type"),
    "no content type": (415, "unsupported-media-type"),
    "oversized Idempotency-Key": (422, "validation-error"),
    "empty Idempotency-Key": (422, "validation-error"),
    "unknown query parameter": (422, "validation-error"),
    "control character in a DICOM filter": (422, "validation-error"),
    "empty DICOM filter": (422, "validation-error"),
    "number as a timestamp": (422, "validation-error"),
    "timestamp beyond year 9999 in UTC": (422, "validation-error"),
    "method not allowed": ("405 (Allow: GET, HEAD, POST)", "method-not-allowed"),
    "bad job id": (422, "validation-error"),
    "another client's job": (404, "not-found"),
    "unknown job": (404, "not-found"),
    "missing API key": (401, "unauthorized"),
    "malformed API key": (401, "unauthorized"),
    "wrong API key": (401, "unauthorized"),
    "revoked API key": (401, "unauthorized"),
    "not Bearer": (401, "unauthorized"),
}


@pytest.fixture(scope="module")
def rows() -> list[dict[str, Any]]:
    with spawned() as (url, keys):
        return run(url, keys)


def test_every_bad_input_gets_its_problem(rows: list[dict[str, Any]]) -> None:
    got = {r["kind"]: (r["status"], r["type"]) for r in rows}
    assert got == EXPECTED
    for r in rows:
        if r["status"] == 401:
            assert r["www_authenticate"].startswith('Bearer realm="spine"'), r
    validation = {r["kind"]: r["fields"] for r in rows if r["type"] == "validation-error"}
    assert validation["unknown level"] == "pa.landmarks[3].level"
    assert validation["non-orthonormal directors"] == "boundary.T1.directors"
    assert validation["huge number (finite)"] == "pa.landmarks[0].point[0]"
    assert validation["levels implausibly far apart"] == "pa.landmarks[1]"
    assert validation["crossed corners"] == "pa.landmarks[4].corners"
    details = {r["kind"]: r["detail"] for r in rows}
    assert "T1 and T2 are 336 mm apart" in details["levels implausibly far apart"]
    assert "corners of T5" in details["crossed corners"]
    assert validation["duplicate key"] == "pa.units"
    assert validation["duplicate key in a batch entry"] == "jobs[0].pa.units"
    assert validation["NUL character in a text"] == "options.profile"
    assert validation["unknown profile"] == "options.profile"
    assert validation["study date not YYYY-MM-DD"] == validation["study date as a number"] == "study.study_date"
    assert "written YYYY-MM-DD" in details["study date as a number"]
    assert validation["blank Patient ID"] == "study.patient_id"
    assert validation["corners turned upside down"] == "pa.landmarks[4].corners"
    assert validation["pedicles swapped"] == "pa.landmarks[4].pedicles"
    assert validation["no room for the spine"] == "pa.acquisition.distance_source_to_detector_mm"
    assert validation["landmarks off the image"] == "pa.acquisition.image_size"
    assert "turned by 90° or more" in details["corners turned upside down"]
    assert "image-right first" in details["pedicles swapped"]
    assert validation["control character in a DICOM filter"] == "query.patient_id"
    assert validation["empty DICOM filter"] == "query.patient_id"
    assert validation["empty Idempotency-Key"] == "header.idempotency-key"
    assert "the Idempotency-Key header is empty" in details["empty Idempotency-Key"]


def test_another_clients_job_answers_exactly_as_an_unknown_one(rows: list[dict[str, Any]]) -> None:
    by_kind = {r["kind"]: r for r in rows}
    other, unknown = by_kind["another client's job"], by_kind["unknown job"]
    assert (other["status"], other["type"], other["detail"]) == (unknown["status"], unknown["type"], unknown["detail"])
    assert other["detail"] == "there is no job <id>"


def test_docs_hold_the_table_this_run_produces(rows: list[dict[str, Any]]) -> None:
    text = DOC.read_text()
    assert BEGIN in text and END in text, f"{DOC} lacks the bad-input table markers"
    published = text.split(BEGIN, 1)[1].split(END, 1)[0].strip()
    assert published == table(rows).strip(), (
        "docs/reliability.md's bad-input table is stale: paste `python -m tools.badinput --spawn`"
    )
