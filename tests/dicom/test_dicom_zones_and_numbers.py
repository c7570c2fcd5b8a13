"""The SR's and SC's dates follow the film's Timezone Offset From UTC (0008,0201), so that the film's
Study Date and Time copied into them keep their meaning; a malformed offset is ignored (the UTC
stamp); a measure the fit gives as a negative zero is written as DS "0.0", never "-0.0"."""

from __future__ import annotations

import copy
import shutil
import subprocess
import uuid
from datetime import UTC, datetime, timedelta, timezone
from pathlib import Path
from typing import Any

import pydicom
import pytest
from pydicom.dataset import Dataset

from services.dicom.sc import build_sc
from services.dicom.sr import SourceImage, StudyIdentity, build_sr
from spine_engine import register
from spine_engine.figures import render_figure
from tests.conftest import spine_payload

JOB = uuid.UUID("5d0c7a8e-2b1f-4f55-8c0e-9a3b1d2e4f60")
FINISHED = datetime(2026, 3, 1, 21, 30, tzinfo=UTC)
STUDY = {"study_instance_uid": "1.2.826.0.1.3680043.10.1.1", "patient_id": "P1", "patient_name": "DOE^JANE",
         "study_date": "2026-03-01", "study_time": "101500"}  # fmt: skip


@pytest.fixture(scope="module")
def case() -> dict[str, Any]:
    payload = spine_payload(curve_mm=25.0)
    return {"payload": payload, "result": register(copy.deepcopy(payload))}


def _written(ds: Dataset, path: Path) -> Dataset:
    ds.save_as(path, enforce_file_format=True)
    return pydicom.dcmread(path)


def _dciodvfy_errors(path: Path) -> list[str]:
    if shutil.which("dciodvfy") is None:
        return []
    run = subprocess.run(["dciodvfy", str(path)], capture_output=True, text=True, timeout=60)
    return [line for line in (run.stdout + run.stderr).splitlines() if line.startswith("Error")]


@pytest.mark.parametrize(
    ("offset", "expected_offset", "content"),
    [
        # 21:30 UTC is 22:30 at +0100 and 16:30 at -0500, 11:30 on the next day at +1400 (PS3.5 §6.2's
        # highest offset), 03:00 on the next day at +0530 (minutes kept)
        ("+0100", "+0100", ("20260301", "223000")),
        ("-0500", "-0500", ("20260301", "163000")),
        ("+1400", "+1400", ("20260302", "113000")),
        ("+0530", "+0530", ("20260302", "030000")),
        # not a DICOM offset (PS3.5 §6.2: &ZZXX, -1200 to +1400, never -0000): ignored, the UTC stamp
        ("+2500", "+0000", ("20260301", "213000")),
        ("-1300", "+0000", ("20260301", "213000")),
        ("+0160", "+0000", ("20260301", "213000")),
        ("-0000", "+0000", ("20260301", "213000")),
        ("+01:00", "+0000", ("20260301", "213000")),
        ("0100", "+0000", ("20260301", "213000")),
        (None, "+0000", ("20260301", "213000")),
    ],
)
def test_the_films_offset_dates_the_sr_and_the_sc(
    case: dict[str, Any], tmp_path: Path, offset: str | None, expected_offset: str, content: tuple[str, str]
) -> None:
    """PS3.3 §C.12.1.1.8: Timezone Offset From UTC dates every DA and TM of the instance, the Study Date and
    Time copied from the film included. With the film's offset the SR and SC take it and write the job's
    end in that zone; the film's Study Time stays as the film has it."""
    identity = StudyIdentity.from_study({**STUDY, "timezone_offset_from_utc": offset})
    image = SourceImage("1.2.826.0.1.3680043.10.1.3", "1.2.840.10008.5.1.4.1.1.1.1", "1.2.826.0.1.3680043.10.1.2",
                        STUDY["study_instance_uid"])  # fmt: skip
    sr = build_sr(case["result"], case["payload"], JOB, identity, {"pa": image}, content_datetime=FINISHED)
    sc = build_sc(render_figure(case["result"], case["payload"], dpi=30), JOB, identity, content_datetime=FINISHED)
    for name, ds in (("sr", sr), ("sc", sc)):
        back = _written(ds, tmp_path / f"{name}.dcm")
        assert back.TimezoneOffsetFromUTC == expected_offset, name
        assert (back.StudyDate, back.StudyTime) == ("20260301", "101500"), name
        assert (back.ContentDate, back.ContentTime) == content, name
        assert (back.InstanceCreationDate, back.InstanceCreationTime) == content, name
        assert back.ContributingEquipmentSequence[0].ContributionDateTime == "".join(content) + expected_offset
        assert _dciodvfy_errors(tmp_path / f"{name}.dcm") == [], name
    assert (str(sc.DateOfSecondaryCapture), str(sc.TimeOfSecondaryCapture)) == content


def test_the_instant_is_the_jobs_end_whatever_the_zone(case: dict[str, Any]) -> None:
    """The zone changes the clock reading, not the instant: the SR's content date, time and offset read
    back as the job's end."""
    identity = StudyIdentity.from_study({**STUDY, "timezone_offset_from_utc": "-0330"})
    end = datetime(2026, 3, 1, 2, 15, 30, tzinfo=timezone(timedelta(hours=2)))  # 00:15:30 UTC
    sr = build_sr(case["result"], case["payload"], JOB, identity, content_datetime=end)
    zone = timezone(-timedelta(hours=3, minutes=30))
    read = datetime.strptime(f"{sr.ContentDate}{sr.ContentTime}", "%Y%m%d%H%M%S").replace(tzinfo=zone)
    assert (sr.TimezoneOffsetFromUTC, read) == ("-0330", end)


def _ds_values(ds: Dataset) -> list[str]:
    """Every DS value of ``ds`` and its sequences, as the file holds it."""
    values = []
    for element in ds.iterall():
        if element.VR == "DS" and element.value not in (None, ""):
            items = element.value if element.VM > 1 else [element.value]
            values += [str(v) for v in items]
    return values


def test_a_negative_zero_is_written_as_a_positive_zero(case: dict[str, Any], tmp_path: Path) -> None:
    """A measure the fit computes as -0.0 (a symmetric spine's twist or rotation, an SD of zero) is written
    "0.0" (PS3.5 §6.2 DS), never "-0.0"; every other value keeps its sign."""
    result = copy.deepcopy(case["result"])
    result["vertebrae"][3]["twist_deg"] = -0.0
    result["vertebrae"][3]["axial_rotation_deg"] = -1e-300  # not zero: DS writes it "-1e-300"
    result["vertebrae"][4]["axial_rotation_deg"] = -0.0
    result["vertebrae"][4]["axial_rotation_sd_deg"] = -0.0
    result["measures"]["cobb"][0]["apex_axial_rotation_deg"] = -0.0
    sr = build_sr(result, case["payload"], JOB, StudyIdentity.from_study(STUDY), content_datetime=FINISHED)
    values = _ds_values(_written(sr, tmp_path / "sr.dcm"))
    assert values.count("0.0") >= 5  # the five -0.0 put in: twist, two rotations, the SD's upper and lower
    assert [v for v in values if float(v) == 0 and v.startswith("-")] == []
    assert "-1e-300" in values  # a tiny negative value is not zero and keeps its sign
    assert _dciodvfy_errors(tmp_path / "sr.dcm") == []
