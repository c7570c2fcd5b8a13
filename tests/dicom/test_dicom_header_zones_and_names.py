"""The header reader's time zone, leap seconds and Patient's Name, and what the merge makes of them.

- Timezone Offset From UTC (0008,0201) is read by one rule (``spine_client.dicom.datetimes``: PS3.5 §6.2
  DT ``&ZZXX`` from -1200 to +1400, never -0000), ignored with a warning naming it when it is no offset,
  and carried in the job's study to the SR, SC and FHIR export; the film's date-time takes the same rule.
- A leap second (PS3.5 §6.2 TM and DT: seconds 00–60) is kept by the reader and accepted by the merge's
  checks of a client's block.
- A Patient's Name is a PN of at most 64 characters per component group (PS3.5 §6.2, Table 6.2-1):
  longer refuses the film, naming (0010,0010).
"""

from __future__ import annotations

import copy
import re
import shutil
import subprocess
import uuid
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest
from pydicom.dataset import Dataset

from services.db.job_forms import JobForms, engine_payload
from services.dicom.sr import StudyIdentity, build_sr, stamp_content_time
from services.fhir.export import effective_date_time
from spine_client.dicom.datetimes import UTC_OFFSET_PATTERN, parse_utc_offset, utc_offset_problem
from spine_client.dicom.errors import InvalidAttribute
from spine_client.dicom.header import identity_problem, read_header
from spine_client.dicom.merge import (
    AttributeRead,
    DicomProvenance,
    apply_headers,
    client_provenance_errors,
    film_datetime_problem,
)
from spine_engine import register
from spine_engine.models import Study
from tests.conftest import spine_payload
from tools.dicom import synthetic

OFFSET_LABEL = "TimezoneOffsetFromUTC (0008,0201)"
CREATED = datetime(2026, 12, 1, 8, 0, tzinfo=UTC)


def _film(**attributes: str) -> Dataset:
    """A synthetic DX film without its Content Date and Time (it dates its content as its study), with
    ``attributes`` set."""
    ds = synthetic.radiograph()
    for keyword in ("ContentDate", "ContentTime"):
        if keyword in ds:
            delattr(ds, keyword)
    for keyword, value in attributes.items():
        setattr(ds, keyword, value)
    return ds


# ------------------------------------------------------------------ the offset rule


def test_the_offset_pattern_is_the_offset_rule_on_every_value() -> None:
    """``UTC_OFFSET_PATTERN`` (for a schema or a model's field) accepts exactly what ``utc_offset_problem``
    accepts, on both signs and all 10 000 four-digit values."""
    pattern = re.compile(UTC_OFFSET_PATTERN)
    for sign in "+-":
        for n in range(10_000):
            text = f"{sign}{n:04d}"
            assert (pattern.match(text) is not None) == (utc_offset_problem(text) is None), text
    # the edges of PS3.5 §6.2's range, and the forms that are no offset
    assert [utc_offset_problem(t) is None for t in ("+1400", "+1401", "-1200", "-1201", "+0000", "-0000")] == [
        True, False, True, False, True, False]  # fmt: skip
    assert [pattern.match(t) for t in ("+01:00", "0100", "+100", " +0100", "+0100 ")] == [None] * 5


# ------------------------------------------------------------------ the reader


@pytest.mark.parametrize(
    ("offset", "expected", "film_datetime"),
    [
        ("+0100", "+0100", "2026-11-15T09:30:12+01:00"),
        ("-0530", "-0530", "2026-11-15T09:30:12-05:30"),
        ("+0000", "+0000", "2026-11-15T09:30:12+00:00"),
        ("+1400", "+1400", "2026-11-15T09:30:12+14:00"),  # PS3.5 §6.2's highest
        ("-1200", "-1200", "2026-11-15T09:30:12-12:00"),  # and lowest
        ("+0100 ", "+0100", "2026-11-15T09:30:12+01:00"),  # DICOM's trailing padding (PS3.5 §6.2)
        # not an offset: ignored with a warning, and the film's time is in no stated zone: the date alone
        ("+2500", None, "2026-11-15"),
        ("+1401", None, "2026-11-15"),
        ("-1201", None, "2026-11-15"),
        ("-0000", None, "2026-11-15"),
        ("+0160", None, "2026-11-15"),
        ("+01:00", None, "2026-11-15"),
        ("0100", None, "2026-11-15"),
    ],
)
def test_the_films_offset_is_read_by_the_rule(offset: str, expected: str | None, film_datetime: str) -> None:
    header = read_header(_film(AcquisitionDate="20261115", AcquisitionTime="093012", TimezoneOffsetFromUTC=offset))
    assert header.timezone_offset_from_utc == expected
    assert header.film_datetime == film_datetime
    warned = [w for w in header.warnings if OFFSET_LABEL in w]
    if expected is None:
        [warning] = warned
        assert repr(offset) in warning and "ignored" in warning, warning
    else:
        assert warned == []


def test_an_absent_offset_is_no_warning() -> None:
    header = read_header(_film(AcquisitionDate="20261115", AcquisitionTime="093012"))
    assert (header.timezone_offset_from_utc, header.film_datetime, header.warnings) == (None, "2026-11-15", ())


@pytest.mark.parametrize(
    ("attributes", "expected", "warned"),
    [
        # PS3.3 §C.12.1.1.8, Note 2: (0008,0201) dates a DT that has no offset of its own, not one that has
        ({"AcquisitionDateTime": "20261115093012", "TimezoneOffsetFromUTC": "-0500"}, "2026-11-15T09:30:12-05:00",
         False),
        ({"AcquisitionDateTime": "20261115093012+0100", "TimezoneOffsetFromUTC": "-0500"},
         "2026-11-15T09:30:12+01:00", False),
        # a DT suffix that is no offset counts as absent (warned): then (0008,0201), else the date alone
        ({"AcquisitionDateTime": "20261115093012+2500", "TimezoneOffsetFromUTC": "-0500"},
         "2026-11-15T09:30:12-05:00", True),
        ({"AcquisitionDateTime": "20261115093012-0000"}, "2026-11-15", True),
        # a time that is no TM: the date alone, never "25:60:00" (which the merge's check would refuse)
        ({"AcquisitionDate": "20261115", "AcquisitionTime": "256000", "TimezoneOffsetFromUTC": "+0100"},
         "2026-11-15", False),
        ({"AcquisitionDateTime": "20261115239912+0100"}, "2026-11-15", False),
    ],
)
def test_the_films_date_time_takes_the_same_rule(attributes: dict[str, str], expected: str, warned: bool) -> None:
    header = read_header(_film(**attributes))
    assert header.film_datetime == expected
    assert film_datetime_problem(expected) is None  # what the reader writes, the merge's check takes
    assert any("AcquisitionDateTime (0008,002A)" in w for w in header.warnings) == warned, header.warnings


# ------------------------------------------------------------------ leap seconds


def test_a_leap_second_is_kept_by_the_reader_and_taken_by_the_merge() -> None:
    """PS3.5 §6.2: a TM's and a DT's seconds run 00–60. The reader keeps Study Time ``235960`` and writes
    the film's leap second as ISO 8601 ``23:59:60`` (``spine_client.dicom.datetimes``), and the merge's
    checks of a client's block take both."""
    header = read_header(_film(StudyTime="235960", AcquisitionDateTime="20161231235960.5+0000"))
    assert header.study_time == "235960"
    assert header.film_datetime == "2016-12-31T23:59:60+00:00"
    assert film_datetime_problem(header.film_datetime) is None
    assert film_datetime_problem("2016-12-31T23:59:60Z") is None
    assert identity_problem("study_time", "235960") is None
    assert identity_problem("study_time", "235960.999999") is None
    # 60 is the last second a minute can have, and the date is still checked with it
    assert read_header(_film(StudyTime="235961")).study_time is None
    assert identity_problem("study_time", "235961") is not None
    assert "is not a calendar date" in (film_datetime_problem("2016-02-30T23:59:60+00:00") or "")
    assert film_datetime_problem("2016-12-31T23:59:61+00:00") is not None


def test_a_leap_second_study_time_goes_into_the_job() -> None:
    header = read_header(_film(StudyTime="235960"))
    merged, provenance = apply_headers({"pa": {"landmarks": []}}, {"pa": header}, source="file")
    assert merged["study"]["study_time"] == "235960"
    assert client_provenance_errors(provenance) == []


# ------------------------------------------------------------------ the merge: the study's offset


def _two_films(pa_offset: str | None, lateral_offset: str | None) -> tuple[dict[str, Any], DicomProvenance]:
    pa_attributes = {"TimezoneOffsetFromUTC": pa_offset} if pa_offset else {}
    pa = _film(**pa_attributes)
    lateral = synthetic.radiograph(patient_orientation=("A", "F"), view_position="LL",
                                   study_instance_uid=pa.StudyInstanceUID)  # fmt: skip
    if lateral_offset:
        lateral.TimezoneOffsetFromUTC = lateral_offset
    payload = {"pa": {"units": "px", "landmarks": []}, "lateral": {"units": "px", "landmarks": []}}
    return apply_headers(payload, {"pa": read_header(pa), "lateral": read_header(lateral)}, source="file")


def test_the_films_offset_goes_into_the_jobs_study_and_dates_its_artifacts() -> None:
    """The study block takes (0008,0201) as the other values the contract's ``Study`` has no field for
    (``study_time``...): in the merged payload and the provenance, the engine's payload still valid, and
    in the job's effective study, which the SR's stamp and the FHIR export read."""
    merged, provenance = _two_films("+0100", None)
    assert merged["study"]["timezone_offset_from_utc"] == "+0100"
    read = {r.field: r for r in provenance.study}["study.timezone_offset_from_utc"]
    assert (read.value, read.attribute, read.used) == ("+0100", OFFSET_LABEL, True)
    assert provenance.conflicts == []
    assert client_provenance_errors(provenance) == []

    engine = engine_payload(merged)
    Study.model_validate(engine["study"])  # the engine's payload is valid with it
    forms = JobForms(posted=engine, provenance=provenance.model_dump(mode="json"), result=None)
    assert forms.study is not None and forms.study["timezone_offset_from_utc"] == "+0100"
    # the film's Study Date and Time (2026-11-30, 10:15:00, synthetic.radiograph) in its zone
    assert effective_date_time(forms.study, None, CREATED) == "2026-11-30T10:15:00+01:00"
    stamped = stamp_content_time(Dataset(), CREATED, ("ContentDate",), ("ContentTime",),
                                 StudyIdentity.from_study(forms.study).timezone_offset_from_utc)  # fmt: skip
    assert (stamped.TimezoneOffsetFromUTC, str(stamped.ContentTime)) == ("+0100", "090000")  # 08:00 UTC at +0100


@pytest.mark.parametrize(
    ("pa", "lateral", "used", "conflict"),
    [
        ("+0100", "+0200", "+0100", True),  # the PA's, the lateral's a conflict as for any identity value
        ("+0100", "+0100", "+0100", False),
        (None, "+0200", "+0200", False),  # the PA has none (or an ignored one): the lateral's
        ("+2500", "+0200", "+0200", False),
        ("+0100", "-0000", "+0100", False),  # the lateral's is ignored: nothing to disagree with
    ],
)
def test_two_films_of_one_study_with_different_offsets(pa: str | None, lateral: str | None, used: str,
                                                        conflict: bool) -> None:  # fmt: skip
    merged, provenance = _two_films(pa, lateral)
    assert merged["study"]["timezone_offset_from_utc"] == used
    conflicts = [c for c in provenance.conflicts if c.field == "study.timezone_offset_from_utc"]
    if conflict:
        [c] = conflicts
        assert (c.payload, c.header, c.attribute) == (pa, lateral, f"lateral image's {OFFSET_LABEL}")
    else:
        assert conflicts == []


@pytest.mark.parametrize("value", ["+2500", "-0000", "+01:00", " +0100", 100])
def test_a_client_blocks_offset_is_as_dicom_writes_it(value: Any) -> None:
    """``client_provenance_errors``: the study's ``timezone_offset_from_utc`` that a client read is an
    offset by the same rule; a valid one is taken (``test_the_films_offset_goes_into...``)."""
    read = AttributeRead(field="study.timezone_offset_from_utc", value=value, attribute=OFFSET_LABEL, used=True)
    [(loc, reason)] = client_provenance_errors(DicomProvenance(study=[read]))
    assert loc == ("study", 0, "value") and "UTC offset" in reason and "-1200 to +1400" in reason


# ------------------------------------------------------------------ the Patient's Name

LONG_NAME = "A" * 100 + "^" + "B" * 100  # 201 characters, one component group


@pytest.mark.parametrize(
    ("name", "reason"),
    [
        (LONG_NAME, "201 characters in its alphabetic component group"),
        ("A" * 32 + "^" + "B" * 32, "65 characters in its alphabetic component group"),
        ("Yamada^Tarou=" + "山" * 65, "65 characters in its ideographic component group"),
        ("Yamada^Tarou=山田^太郎=やまだ^たろう=X", "4 component groups"),
        ("A^B^C^D^E^F", "6 components in its alphabetic component group"),
    ],
)
def test_a_patients_name_beyond_a_pn_refuses_the_film_naming_it(name: str, reason: str) -> None:
    """PS3.5 §6.2 (Table 6.2-1) and §6.2.1: a PN has at most three component groups of at most 64
    characters and five components each. The film is refused (as a Patient ID beyond LO's 64): the SR
    and SC carry the film's identity, which a name cut or left out would no longer be."""
    with pytest.raises(InvalidAttribute) as info:
        read_header(synthetic.radiograph(patient_name=name))
    assert info.value.attributes == ("PatientName",)
    message = str(info.value)
    assert "PatientName (0010,0010)" in message and reason in message, message
    assert "PS3.5 §6.2" in message


@pytest.mark.parametrize(
    "name",
    [
        "A" * 31 + "^" + "B" * 32,  # 64 characters: the most one group holds
        "=".join(["A" * 31 + "^" + "B" * 32] * 3),  # three such groups (192 characters)
        "Yamada^Tarou=" + "山" * 64,  # 64 ideographs: characters are counted, not UTF-8 bytes
        "DOE^JOHN^PAUL^DR^JR",
    ],
)
def test_a_patients_name_within_a_pn_is_read(name: str) -> None:
    assert read_header(synthetic.radiograph(patient_name=name)).patient_name == name


def test_a_referring_physicians_name_beyond_a_pn_is_left_out() -> None:
    """Not an identity the job is matched by: left out of the SR and SC as a malformed identity value is."""
    def read(name: str) -> str | None:
        return read_header(synthetic.radiograph(extra={"ReferringPhysicianName": name})).referring_physician_name

    assert (read(LONG_NAME), read("WHO^DR")) == (None, "WHO^DR")


@pytest.mark.parametrize(("name", "refused"), [(LONG_NAME, True), ("A" * 31 + "^" + "B" * 32, False)])
def test_a_client_blocks_patients_name_is_a_pn(name: str, refused: bool) -> None:
    read = AttributeRead(field="study.patient_name", value=name, attribute="PatientName (0010,0010)", used=True)
    errors = client_provenance_errors(DicomProvenance(study=[read]))
    if refused:
        [(loc, reason)] = errors
        assert loc == ("study", 0, "value") and "64 per component group" in reason, reason
    else:
        assert errors == []


@pytest.mark.skipif(shutil.which("dciodvfy") is None, reason="dicom3tools' dciodvfy is not installed")
def test_the_longest_name_the_reader_takes_makes_an_sr_dciodvfy_accepts(tmp_path: Path) -> None:
    """The reader's bound is the SR's: a 64-character name (read from a film) gives an SR without a
    dciodvfy error, one character more (which the reader refuses) would not."""
    payload = spine_payload(curve_mm=25.0)
    result = register(copy.deepcopy(payload))
    name = read_header(synthetic.radiograph(patient_name="A" * 31 + "^" + "B" * 32)).patient_name

    def errors(patient_name: str | None) -> list[str]:
        study = {"study_instance_uid": "1.2.826.0.1.3680043.10.1.1", "patient_id": "P1", "patient_name": patient_name}
        sr = build_sr(result, payload, uuid.UUID(int=7), StudyIdentity.from_study(study),
                      content_datetime=CREATED)  # fmt: skip
        path = tmp_path / "sr.dcm"
        sr.save_as(path, enforce_file_format=True)
        run = subprocess.run(["dciodvfy", str(path)], capture_output=True, text=True, timeout=60)
        return [line for line in (run.stdout + run.stderr).splitlines() if line.startswith("Error")]

    assert errors(name) == []
    assert any("Patient's Name" in line for line in errors(str(name) + "B"))


def test_parse_utc_offset_is_the_rule() -> None:
    """The zone read from an offset: UTC for +0000, the minutes kept, None for what the rule ignores."""
    zone = parse_utc_offset("-0530")
    assert zone is not None and zone.utcoffset(None) is not None
    assert str(zone) == "UTC-05:30" and parse_utc_offset("+0000") is UTC
    assert [parse_utc_offset(v) for v in ("-0000", "+1401", None, 100)] == [None] * 4
