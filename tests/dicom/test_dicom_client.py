"""``spine submit --pa-dicom FILE [--lateral-dicom FILE] LANDMARKS.csv`` reads the headers on the
client's side: the payload it would send (``--print-payload``), conflicts on stderr, bad input exit 2."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from spine_client.cli import EXIT_OK, EXIT_USAGE, main
from spine_client.dicom_input import LandmarkCsvError, parse_landmark_csv, payload_from_dicom
from spine_engine.levels import LEVELS
from spine_engine.models import PAView
from tools.dicom import synthetic


def _files(tmp_path: Path) -> dict[str, Any]:
    pa = synthetic.radiograph(imager_pixel_spacing=(0.15, 0.15), ermf=1.25, sid=1800.0, rows=3200, columns=1200)
    lateral = synthetic.radiograph(patient_orientation=("A", "F"), view_position="LL",
                                   study_instance_uid=pa.StudyInstanceUID, imager_pixel_spacing=(0.15, 0.15),
                                   rows=3200, columns=1200)  # fmt: skip
    synthetic.write(pa, tmp_path / "pa.dcm")
    synthetic.write(lateral, tmp_path / "lat.dcm")
    lines = ["level,column,row,view", "# clicked on the PA"]
    lines += [f"{level},{600 + i},{300 + 160 * i},pa" for i, level in enumerate(LEVELS)]
    lines += [f"{level},{500 - i},{300 + 160 * i},lateral" for i, level in enumerate(LEVELS[4:], start=4)]
    (tmp_path / "landmarks.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    return {"pa": pa, "lateral": lateral}


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_submit_reads_the_headers(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    images = _files(tmp_path)
    code, out, err = _run(capsys, "submit", "--pa-dicom", str(tmp_path / "pa.dcm"), "--lateral-dicom",
                          str(tmp_path / "lat.dcm"), str(tmp_path / "landmarks.csv"), "--print-payload")  # fmt: skip
    assert code == EXIT_OK, err
    payload = json.loads(out)
    assert payload["pa"]["units"] == "px"
    assert payload["pa"]["pixel_spacing"] == pytest.approx([0.12, 0.12])  # Imager Pixel Spacing / ERMF
    if "acquisition" in PAView.model_fields:  # the contract's new view fields, once the engine has them
        assert payload["pa"]["pixel_spacing_calibration"] == "calibrated"
        assert payload["pa"]["acquisition"]["magnification"] == 1.25
    else:
        assert "acquisition" not in payload["pa"] and "pixel_spacing_calibration" not in payload["pa"]
    assert payload["pa"]["patient_orientation"] == ["L", "F"]
    assert payload["lateral"]["patient_orientation"] == ["A", "F"]
    assert [lm["level"] for lm in payload["pa"]["landmarks"]] == list(LEVELS)
    assert [lm["level"] for lm in payload["lateral"]["landmarks"]] == list(LEVELS[4:])
    assert payload["pa"]["landmarks"][0]["point"] == [600.0, 300.0]
    study = payload["study"]
    assert study["study_instance_uid"] == images["pa"].StudyInstanceUID
    assert study["pa_sop_instance_uid"] == images["pa"].SOPInstanceUID
    assert study["lateral_sop_instance_uid"] == images["lateral"].SOPInstanceUID
    assert (study["patient_id"], study["accession_number"], study["study_date"]) == ("P-0001", "ACC-42", "2026-11-30")
    assert err == ""


def test_base_payload_wins_and_conflicts_are_warned(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _files(tmp_path)
    (tmp_path / "base.json").write_text(json.dumps({"pa": {"pixel_spacing": [0.2, 0.2]}, "options": {"profile": "x"}}))
    code, out, err = _run(capsys, "submit", "--pa-dicom", str(tmp_path / "pa.dcm"), "--base",
                          str(tmp_path / "base.json"), str(tmp_path / "landmarks.csv"), "--print-payload")  # fmt: skip
    assert code == EXIT_OK
    payload = json.loads(out)
    assert payload["pa"]["pixel_spacing"] == [0.2, 0.2] and payload["options"] == {"profile": "x"}
    assert "pa.pixel_spacing" in err and "ImagerPixelSpacing (0018,1164)" in err


def test_bad_input_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _files(tmp_path)
    (tmp_path / "not.dcm").write_bytes(b"not a dicom file" * 20)
    code, _, err = _run(capsys, "submit", "--pa-dicom", str(tmp_path / "not.dcm"), str(tmp_path / "landmarks.csv"))
    assert code == EXIT_USAGE and "not a DICOM file" in err
    code, _, err = _run(capsys, "submit", "--pa-dicom", str(tmp_path / "lat.dcm"), str(tmp_path / "landmarks.csv"))
    assert code == EXIT_USAGE and "PatientOrientation (0020,0020)" in err and "lateral" in err
    code, _, err = _run(capsys, "submit", "--lateral-dicom", str(tmp_path / "lat.dcm"), str(tmp_path / "landmarks.csv"))
    assert code == EXIT_USAGE and "--lateral-dicom needs --pa-dicom" in err
    (tmp_path / "bad.csv").write_text("T1,1,2\nX9,1,2\nT2,a,2\n")
    code, _, err = _run(capsys, "submit", "--pa-dicom", str(tmp_path / "pa.dcm"), str(tmp_path / "bad.csv"))
    assert code == EXIT_USAGE and "line 2" in err and "line 3" in err


def test_parse_landmark_csv() -> None:
    parsed = parse_landmark_csv("level,column,row\nT2,3,4\nT1,1,2\nT1,5,6,lateral\n")
    assert parsed == {"pa": [{"level": "T1", "point": [1.0, 2.0]}, {"level": "T2", "point": [3.0, 4.0]}],
                      "lateral": [{"level": "T1", "point": [5.0, 6.0]}]}  # fmt: skip
    with pytest.raises(LandmarkCsvError, match="more than once"):
        parse_landmark_csv("T1,1,2\nT1,1,2\n")
    with pytest.raises(LandmarkCsvError, match="no PA landmark"):
        parse_landmark_csv("T1,1,2,lateral\n")
    with pytest.raises(LandmarkCsvError, match="line 2: not readable as CSV"):  # was csv.Error: a traceback
        parse_landmark_csv("T1,1,2\nT2,\"" + "9" * 200_000 + "\",4\n")


def test_python_client_builds_the_same_payload(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _files(tmp_path)
    payload, provenance = payload_from_dicom(tmp_path / "landmarks.csv", tmp_path / "pa.dcm")
    code, out, _ = _run(capsys, "submit", "--pa-dicom", str(tmp_path / "pa.dcm"), str(tmp_path / "landmarks.csv"),
                        "--print-payload")  # fmt: skip
    assert code == EXIT_OK and json.loads(out) == json.loads(json.dumps({**payload, "dicom": provenance}))
    assert provenance["pa"]["cornerstone_calibration_type"] == "ERMF" and provenance["conflicts"] == []
    read = {r["field"]: r["value"] for r in provenance["pa"]["read"]}  # recorded even when not sent
    assert read["pa.acquisition.magnification"] == 1.25 and read["pa.pixel_spacing_calibration"] == "calibrated"
    # lateral landmarks without a lateral image are sent as they are: the service names the missing spacing
    assert payload["lateral"]["units"] == "px" and "pixel_spacing" not in payload["lateral"]


def test_submit_by_reference_prints_the_uids(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _files(tmp_path)
    code, out, err = _run(capsys, "submit", str(tmp_path / "landmarks.csv"), "--study-instance-uid", "1.2.3",
                          "--pa-sop-instance-uid", "1.2.3.4", "--lateral-sop-instance-uid", "1.2.3.5",
                          "--print-payload")  # fmt: skip
    assert code == EXIT_OK, err
    payload = json.loads(out)
    assert payload["study"] == {"study_instance_uid": "1.2.3", "pa_sop_instance_uid": "1.2.3.4",
                                "lateral_sop_instance_uid": "1.2.3.5"}  # fmt: skip
    assert payload["pa"]["units"] == "px" and "pixel_spacing" not in payload["pa"]
    code, _, err = _run(capsys, "submit", str(tmp_path / "landmarks.csv"), "--study-instance-uid", "1.2.3")
    assert code == EXIT_USAGE and "--pa-sop-instance-uid" in err


@pytest.mark.parametrize(
    ("value", "reason"),
    [
        ("2024-05-06", None),
        ("2024-05-06T10:11:12+02:00", None),
        ("2024-05-06T10:11:12.5Z", None),
        ("2024-05-06T10:11:12", "has a time but no time zone"),
        ("2024-05-06 10:11", "has a time but no time zone"),
        ("2024-02-30", "is not a calendar date"),
        ("yesterday", "is not a date"),
    ],
)
def test_a_client_blocks_film_datetime_is_as_the_header_reader_writes_it(value: str, reason: str | None) -> None:
    """``client_provenance_errors``: ``dicom.<view>.film_datetime`` becomes FHIR's effectiveDateTime,
    whose time SHALL have a zone (FHIR R4 datatypes §2.24.0.1)."""
    from spine_client.dicom.merge import DicomProvenance, ViewProvenance, client_provenance_errors

    view = ViewProvenance(source="file", study_instance_uid="1.2", sop_instance_uid="1.2.3", film_datetime=value)
    errors = client_provenance_errors(DicomProvenance(pa=view))
    if reason is None:
        assert errors == []
    else:
        [(loc, message)] = errors
        assert loc == ("pa", "film_datetime") and reason in message and "film's date must be" in message
