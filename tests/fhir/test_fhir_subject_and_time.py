"""The FHIR export's subject display is the Patient's Name as a person reads it (PS3.5 §6.2.1 components,
FHIR's name assembly orders), its effective time never makes the Bundle invalid (offsets outside
DICOM's and FHIR's range, a leap second), and no quantity is "-0.0"."""

from __future__ import annotations

import copy
import json
import uuid
from datetime import UTC, datetime
from typing import Any

import pytest
from fhir.resources.R4B.bundle import Bundle

from services.fhir.export import observation_bundle
from spine_engine import register
from tests.conftest import spine_payload

FINISHED = datetime(2026, 3, 1, 9, 30, tzinfo=UTC)
CREATED = datetime(2026, 3, 1, 9, 29, 55, tzinfo=UTC)
STUDY = {"study_instance_uid": "1.2.826.0.1.3680043.10.1.1", "patient_id": "P1"}


@pytest.fixture(scope="module")
def result() -> dict[str, Any]:
    out: dict[str, Any] = register(spine_payload(curve_mm=25.0))
    return out


def _bundle(result: dict[str, Any], study: dict[str, Any] | None = None, film: str | None = None) -> dict[str, Any]:
    bundle = observation_bundle(uuid.uuid4(), result, finished_at=FINISHED, created_at=CREATED, study=study,
                                film_datetime=film)  # fmt: skip
    Bundle.model_validate(bundle)
    return bundle


def _one(bundle: dict[str, Any], key: str) -> Any:
    values = {json.dumps(e["resource"].get(key), ensure_ascii=False) for e in bundle["entry"]}
    assert len(values) == 1, values
    return json.loads(values.pop())


@pytest.mark.parametrize(
    ("name", "display"),
    [
        ("DOE^JOHN", "JOHN DOE"),  # FHIR's "G" order: prefix given family suffix
        ("DOE^^JOHN", "JOHN DOE"),  # no given name, JOHN the middle one: no double space
        ("DOE^JOHN^^^", "JOHN DOE"),  # trailing empty components
        ("DOE^JOHN^PAUL^DR^JR", "DR JOHN PAUL DOE JR"),
        ("DOE  ^ JOHN", "JOHN DOE"),  # padding inside components
        ("VAN DER BERG^ANNA", "ANNA VAN DER BERG"),  # a family name of several words kept whole
        ("Yamada^Tarou=山田^太郎=やまだ^たろう", "Tarou Yamada"),  # the alphabetic group only (PS3.5 Annex H)
        ("=山田^太郎=やまだ^たろう", "山田 太郎"),  # no alphabetic group: the ideographic, family first ("F")
        ("DOE", "DOE"),
        ("^^^", None),  # no name at all: no display
    ],
)
def test_the_subject_display_is_the_patients_name_as_read(result: dict[str, Any], name: str,
                                                          display: str | None) -> None:  # fmt: skip
    subject = _one(_bundle(result, {**STUDY, "patient_name": name}), "subject")
    assert subject.get("display") == display
    assert subject["identifier"] == {"value": "P1"}


@pytest.mark.parametrize(
    ("time", "offset", "expected"),
    [
        ("101500", "+0100", "2026-11-30T10:15:00+01:00"),
        ("101500.25", "+0530", "2026-11-30T10:15:00.250000+05:30"),  # fhir.resources writes microseconds
        ("235960", "+0100", "2026-11-30T23:59:60+01:00"),  # a leap second (PS3.5 §6.2 TM: SS 00-60)
        ("101500", "+2500", "2026-11-30"),  # no clock is 25 h from UTC: ignored, the date alone
        ("101500", "+1401", "2026-11-30"),  # beyond DICOM's +1400 (and FHIR's 14:00)
        ("101500", "-0000", "2026-11-30"),  # "shall not be used" (PS3.5 §6.2); "unknown" in RFC 3339 §4.3
        ("101500", "+0160", "2026-11-30"),  # 60 minutes
        ("251500", "+0100", "2026-11-30"),  # hour 25: no time
    ],
)
def test_the_study_time_is_kept_only_with_a_valid_offset(result: dict[str, Any], time: str, offset: str,
                                                         expected: str) -> None:  # fmt: skip
    study = {**STUDY, "study_date": "2026-11-30", "study_time": time, "timezone_offset_from_utc": offset}
    assert _one(_bundle(result, study), "effectiveDateTime") == expected


@pytest.mark.parametrize(
    ("film", "expected"),
    [
        ("2026-11-30T23:59:60+01:00", "2026-11-30T23:59:60+01:00"),  # the header reader's form of TM 235960
        ("2026-11-30T23:59:60", "2026-11-30"),  # a leap second without a zone: its date
        ("2026-11-30T10:15:00+15:00", "2026-11-30"),  # a zone beyond FHIR's 14:00: its date
    ],
)
def test_a_film_date_time_at_the_edges_is_a_valid_fhir_date_time(result: dict[str, Any], film: str,
                                                                  expected: str) -> None:  # fmt: skip
    assert _one(_bundle(result, film=film), "effectiveDateTime") == expected


def test_no_quantity_is_a_negative_zero(result: dict[str, Any]) -> None:
    """Values are rounded to 0.01°: one that rounds to zero is 0.0, not -0.0 (FHIR decimal allows "-0.0",
    a reader shows "-0 deg")."""
    tiny = copy.deepcopy(result)
    major = next(c for c in tiny["measures"]["cobb"] if c["major"])
    major["apex_axial_rotation_deg"] = -0.004
    major["plane_of_max_curvature_deg"] = -0.0
    text = json.dumps(_bundle(tiny))
    assert '"value": -0.0' not in text
    assert text.count('"value": 0.0') >= 3  # the Cobb component twice (rotation, plane) and the Observation
