"""Odd but valid films through the service's path (header read by the client, the job's forms, the SR, SC and
FHIR Bundle the API serves): a leap second with a Timezone Offset From UTC, a name of three component groups
in ISO 2022 (read) and UTF-8 (written), the longest PN, no patient name or ID. Each SR and SC reads back
(pydicom, highdicom) and passes dciodvfy but for the two reports where dciodvfy (Debian's 2022-06-18 build)
departs from PS3.5 §6.2, kept and documented in docs/dicom.md ("Text values"):

- TM: "SS contains seconds (range "00" - "60")" (PS3.5 §6.2, Table 6.2-1): dciodvfy calls a Study Time
  ``235960`` "Character invalid for this VR";
- PN: "64 chars maximum per component group" (Table 6.2-1), lengths of a VR whose repertoire can be extended
  "expressly specified in characters rather than bytes" (§6.2): dciodvfy holds the whole value, in bytes,
  to 64."""

from __future__ import annotations

import copy
import re
import shutil
import subprocess
import uuid
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import highdicom as hd
import pydicom
import pytest
from fhir.resources.R4B.bundle import Bundle

from services.api.routes.fhir import film_datetime
from services.db.job_forms import JobForms
from services.dicom.dicomweb import part10
from services.dicom.results import job_figure_sc_dataset, job_sr_dataset
from services.fhir.export import observation_bundle
from spine_client.dicom.header import read_header
from spine_client.dicom.merge import apply_headers
from spine_engine import register
from tests.conftest import spine_payload
from tools.dicom import synthetic

SPACING = 0.15
FINISHED = datetime(2026, 12, 1, 12, 0, tzinfo=UTC)
LONGEST = "A" * 31 + "^" + "B" * 32 + "=" + "山" * 31 + "^" + "太" * 32 + "=" + "や" * 31 + "^" + "た" * 32
"""A PN of three component groups of 64 characters each (PS3.5 Table 6.2-1): 446 bytes in UTF-8."""
LEAP_SECOND_TM = re.compile(r"^Error - Value invalid for this VR - \(0x0008,0x0030\) TM Study Time .*<2359(60)[.\d]*> "
                            r"- Character invalid for this VR = '6'")  # fmt: skip
PN_IN_BYTES = re.compile(r"^Error - Value invalid for this VR - \(0x0010,0x0010\) PN Patient's Name .* - Length "
                         r"invalid for this VR = (\d+), expected <= 64$")  # fmt: skip
SUMMARY = "Error - Dicom dataset contains invalid data values for Value Representations"


@pytest.fixture(scope="module")
def case() -> tuple[dict[str, Any], dict[str, Any]]:
    payload = spine_payload(spacing_mm=SPACING)
    payload["pa"]["pixel_spacing"] = [SPACING, SPACING]
    return payload, register(copy.deepcopy(payload))


def _artifacts(case: tuple[dict[str, Any], dict[str, Any]], tmp_path: Path, **film: Any) -> dict[str, Any]:
    """The SR, SC (paths) and FHIR Bundle of a job made from ``film``'s header as the client reads it."""
    payload, result = case
    posted = copy.deepcopy(payload)
    header = read_header(synthetic.radiograph(imager_pixel_spacing=(SPACING, SPACING), rows=3200, columns=1200,
                                              **film))  # fmt: skip
    _, provenance = apply_headers(posted, {"pa": header}, source="file")
    dicom = provenance.model_dump(mode="json")
    forms = JobForms(posted=posted, provenance=dicom, result=result)
    out: dict[str, Any] = {"study": forms.study}
    for kind, build in (("sr", job_sr_dataset), ("sc", job_figure_sc_dataset)):
        path = tmp_path / f"{kind}.dcm"
        path.write_bytes(part10(build(uuid.UUID(int=5), forms, FINISHED)))
        out[kind] = path
    out["fhir"] = observation_bundle(uuid.UUID(int=5), result, finished_at=FINISHED, study=forms.study,
                                     created_at=FINISHED, film_datetime=film_datetime(dicom))  # fmt: skip
    Bundle.model_validate(out["fhir"])
    return out


def _dciodvfy_errors(path: Path) -> list[str]:
    run = subprocess.run(["dciodvfy", str(path)], capture_output=True, text=True, timeout=60)
    return [line for line in (run.stdout + run.stderr).splitlines() if line.startswith("Error")]


needs_dciodvfy = pytest.mark.skipif(shutil.which("dciodvfy") is None, reason="dicom3tools' dciodvfy is not installed")


@needs_dciodvfy
def test_a_leap_second_is_written_as_read_and_only_dciodvfy_disagrees(case: Any, tmp_path: Path) -> None:
    out = _artifacts(case, tmp_path, extra={"StudyTime": "235960", "TimezoneOffsetFromUTC": "+0900"})
    for kind in ("sr", "sc"):
        back = pydicom.dcmread(out[kind])
        assert (back.StudyTime, back.TimezoneOffsetFromUTC) == ("235960", "+0900")
        errors = _dciodvfy_errors(out[kind])
        assert [e for e in errors if not LEAP_SECOND_TM.match(e) and e != SUMMARY] == [], errors
        assert any(LEAP_SECOND_TM.match(e) for e in errors)  # the disagreement docs/dicom.md states
    assert {e["resource"]["effectiveDateTime"] for e in out["fhir"]["entry"]} == {"2026-11-30T23:59:60+09:00"}
    hd.sr.srread(out["sr"])


@needs_dciodvfy
@pytest.mark.parametrize("character_set", [["", "ISO 2022 IR 87"], "ISO_IR 192"])
def test_a_name_of_three_groups_read_in_any_character_set_is_written_in_utf8(
    case: Any, tmp_path: Path, character_set: Any
) -> None:  # fmt: skip
    """PS3.5 §6.1.2.5.3 and Annex H: the film's ISO 2022 escapes are decoded on reading; the SR and SC are
    written in UTF-8, declared ``ISO_IR 192`` (PS3.3 §C.12.1.1.2), the name unchanged."""
    name = "Yamada^Tarou=山田^太郎=やまだ^たろう"
    out = _artifacts(case, tmp_path, patient_name=name, extra={"SpecificCharacterSet": character_set})
    for kind in ("sr", "sc"):
        back = pydicom.dcmread(out[kind])
        assert (back.SpecificCharacterSet, str(back.PatientName)) == ("ISO_IR 192", name)
        assert _dciodvfy_errors(out[kind]) == []
    assert {e["resource"]["subject"]["display"] for e in out["fhir"]["entry"]} == {"Tarou Yamada"}


@needs_dciodvfy
def test_the_longest_pn_is_kept_and_only_dciodvfy_counts_its_bytes(case: Any, tmp_path: Path) -> None:
    out = _artifacts(case, tmp_path, patient_name=LONGEST, extra={"SpecificCharacterSet": "ISO_IR 192"})
    for kind in ("sr", "sc"):
        assert str(pydicom.dcmread(out[kind]).PatientName) == LONGEST
        errors = _dciodvfy_errors(out[kind])
        assert [e for e in errors if not PN_IN_BYTES.match(e) and e != SUMMARY] == [], errors
        lengths = [int(m.group(1)) for e in errors if (m := PN_IN_BYTES.match(e))]
        assert lengths == [len(LONGEST.encode())]  # 446: the whole value, in bytes, held to 64


@needs_dciodvfy
def test_a_film_without_patient_name_or_id(case: Any, tmp_path: Path) -> None:
    """Patient's Name and ID are Type 2 in the Patient Module (PS3.3 §C.7.1.1): written empty; the FHIR
    Observations have no subject (nothing identifies the patient)."""
    out = _artifacts(case, tmp_path, patient_name=None, patient_id=None)
    for kind in ("sr", "sc"):
        back = pydicom.dcmread(out[kind])
        assert (str(back.PatientName), back.PatientID) == ("", "")
        assert _dciodvfy_errors(out[kind]) == []
    assert all("subject" not in e["resource"] for e in out["fhir"]["entry"])
