"""Who the patient is: a job whose payload and films, or whose PA and lateral films, disagree on the
patient (Patient ID, its issuer, a Patient's Name without an agreeing ID) or whose payload names another
study than its film's is refused, never reconstructed nor stored into the film's study (PS3.3 §C.7.1.1,
§C.7.2.1: a study belongs to one patient). Client-read: ``spine submit`` refuses it before sending (exit 2)
and the API's admission answers 422 naming the field to a block read by a client that sent it anyway;
by reference: the job fails with ``dicom-patient-conflict`` (real Orthanc, PostgreSQL, Redis and a
``spine worker``). The study's other values (accession number, a name the Patient ID confirms) are the
film's in the SR and SC, the payload's recorded as a conflict."""

from __future__ import annotations

import io
import json
import time
from pathlib import Path
from typing import Any

import pydicom
import pytest

from spine_client.cli import EXIT_USAGE, main
from spine_client.dicom.errors import PatientConflict
from spine_client.dicom.header import read_header
from spine_client.dicom.merge import apply_headers, normalised_person_name
from spine_client.dicom_input import payload_from_dicom
from tests.conftest import Service, spine_payload
from tools.dicom import synthetic

from .conftest import OrthancServer, pacs_of

SPACING = 0.15
STORE_TIMEOUT_S = 60.0
"""As ``test_dicom_service``: the SR and SC are stored by the worker's dicom queue right after the job succeeds (s)."""


def _lateral_of(pa: pydicom.Dataset, **film: Any) -> pydicom.Dataset:
    """A lateral film of ``pa``'s study (another patient's when ``film`` says so)."""
    return synthetic.radiograph(patient_orientation=("A", "F"), view_position="LL", rows=3200, columns=1200,
                                study_instance_uid=pa.StudyInstanceUID, **film)  # fmt: skip


def _pa(**film: Any) -> pydicom.Dataset:
    return synthetic.radiograph(imager_pixel_spacing=(SPACING, SPACING), rows=3200, columns=1200, **film)


# ------------------------------------------------------------------ the rule (merge.identity_problems)


@pytest.mark.parametrize(
    ("study", "lateral", "field", "values"),
    [
        ({"patient_id": "P-OTHER"}, None, "study.patient_id", ("'P-OTHER'", "'P-0001'")),
        ({}, {"patient_id": "P-0002", "patient_name": "Roe^Richard"}, "study.patient_id", ("'P-0001'", "'P-0002'")),
        ({"patient_name": "Roe^Richard"}, None, "study.patient_name", ("'Roe^Richard'", "'Doe^Jane'")),
        ({"study_instance_uid": "1.2.826.0.1.4"}, None, "study.study_instance_uid", ("'1.2.826.0.1.4'",)),
        ({"patient_id": "P-0001", "patient_id_issuer": {"issuer_of_patient_id": "HOSP-B"}}, None,
         "study.patient_id_issuer", ("'HOSP-B'", "'HOSP-A'")),
        ({}, {"patient_id": "P-0001", "extra": {"IssuerOfPatientID": "HOSP-B"}}, "study.patient_id_issuer",
         ("'HOSP-A'", "'HOSP-B'")),
        ({}, {"patient_id": None, "patient_name": "Roe^Richard"}, "study.patient_name",
         ("'Doe^Jane'", "'Roe^Richard'")),
    ],
)  # fmt: skip
def test_films_and_payload_of_two_patients_are_refused(
    study: dict[str, Any], lateral: dict[str, Any] | None, field: str, values: tuple[str, ...]
) -> None:
    """Refused, naming the field and both values, whichever of the payload or the lateral disagrees
    with the PA film; a name only when no Patient ID given by both says the two are one patient."""
    pa = _pa(extra={"IssuerOfPatientID": "HOSP-A"})
    headers = {"pa": read_header(pa)}
    payload = spine_payload(spacing_mm=SPACING)
    payload["study"] = study
    if lateral is not None:
        headers["lateral"] = read_header(_lateral_of(pa, **lateral))
        payload["lateral"] = {"units": "px", "landmarks": []}
    with pytest.raises(PatientConflict) as refused:
        apply_headers(payload, headers, source="file")  # type: ignore[arg-type]
    assert refused.value.field == field and refused.value.problem == "dicom-patient-conflict"
    assert all(value in str(refused.value) for value in values), str(refused.value)


def test_the_films_study_values_are_used_and_a_name_the_id_confirms_is_a_conflict() -> None:
    """The payload's Accession Number, or a Patient's Name where its Patient ID is the film's, is not the
    SR's: the film's is used (``used``, so the job's effective study has it), the payload's a conflict; a
    name that differs only as PN allows (case, trailing ``^`` and spaces) is no conflict."""
    pa = _pa(patient_name="Doe^Jane")
    payload = spine_payload(spacing_mm=SPACING)
    payload["study"] = {"patient_id": " P-0001 ", "patient_name": "Doe^Janet", "accession_number": "TYPED"}
    merged, provenance = apply_headers(payload, {"pa": read_header(pa)}, source="file")
    assert (merged["study"]["patient_name"], merged["study"]["accession_number"]) == ("Doe^Jane", "ACC-42")
    assert {c.field: (c.payload, c.header) for c in provenance.conflicts} == {
        "study.patient_id": (" P-0001 ", "P-0001"), "study.patient_name": ("Doe^Janet", "Doe^Jane"),
        "study.accession_number": ("TYPED", "ACC-42")}  # fmt: skip
    used = {r.field for r in provenance.study if r.used}
    assert {"study.patient_name", "study.accession_number"} <= used and "study.patient_id" not in used
    payload["study"] = {"patient_name": "DOE^jane^^ ", "accession_number": "ACC-42"}
    merged, provenance = apply_headers(payload, {"pa": read_header(pa)}, source="file")
    assert [c.field for c in provenance.conflicts] == ["study.patient_name"]  # recorded, and not refused
    assert normalised_person_name("DOE^jane^^ ") == normalised_person_name("Doe^Jane") == "doe^jane"
    assert normalised_person_name("Doe^Jane=ドウ^ジェーン") != normalised_person_name("Doe^Jane")


# ------------------------------------------------------------------ the client refuses before sending


def _landmarks(tmp_path: Path) -> Path:
    csv = tmp_path / "landmarks.csv"
    pa = spine_payload(spacing_mm=SPACING)["pa"]["landmarks"]
    rows = [f"{lm['level']},{lm['point'][0]},{lm['point'][1]},pa" for lm in pa]
    rows += [f"{lm['level']},{lm['point'][0] - 20},{lm['point'][1]},lateral" for lm in pa[4:]]
    csv.write_text("level,column,row,view\n" + "\n".join(rows) + "\n", encoding="utf-8")
    return csv


def test_spine_submit_refuses_a_lateral_of_another_patient(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pa = _pa()
    synthetic.write(pa, tmp_path / "pa.dcm")
    synthetic.write(_lateral_of(pa, patient_id="P-0002", patient_name="Roe^Richard"), tmp_path / "lat.dcm")
    csv = _landmarks(tmp_path)
    code = main(["submit", "--pa-dicom", str(tmp_path / "pa.dcm"), "--lateral-dicom", str(tmp_path / "lat.dcm"),
                 str(csv), "--print-payload"])  # fmt: skip
    out, err = capsys.readouterr()
    assert code == EXIT_USAGE and out == "", out
    assert "study.patient_id" in err and "'P-0001'" in err and "'P-0002'" in err and "PatientID (0010,0020)" in err
    (tmp_path / "base.json").write_text(json.dumps({"study": {"patient_id": "P-TYPED"}}))
    code = main(["submit", "--pa-dicom", str(tmp_path / "pa.dcm"), "--base", str(tmp_path / "base.json"), str(csv),
                 "--print-payload"])  # fmt: skip
    out, err = capsys.readouterr()
    assert code == EXIT_USAGE and "'P-TYPED'" in err and "'P-0001'" in err


# ------------------------------------------------------------------ the service (real Orthanc, PostgreSQL, Redis)


def _client_block(
    tmp_path: Path, pa: pydicom.Dataset, lateral: pydicom.Dataset
) -> tuple[dict[str, Any], dict[str, Any]]:
    """(payload, ``dicom`` block) as ``spine submit --pa-dicom --lateral-dicom`` sends them, for one patient's films."""
    synthetic.write(pa, tmp_path / "pa.dcm")
    synthetic.write(lateral, tmp_path / "lat.dcm")
    base = {"boundary": spine_payload()["boundary"]}
    return payload_from_dicom(_landmarks(tmp_path), tmp_path / "pa.dcm", tmp_path / "lat.dcm", base=base)


def test_the_api_refuses_a_client_read_block_of_two_patients(pacs_service: Service, tmp_path: Path) -> None:
    """What a client that does not refuse sends (the client of before, or one that sends anyway): the
    payload's Patient ID kept against the film's, a lateral read of another patient, a film's Accession
    Number not used: each a 422 naming the field and both values, and no job. The same films of one
    patient are taken."""
    pa = _pa(patient_id="P-API")
    payload, block = _client_block(tmp_path, pa, _lateral_of(pa, patient_id="P-API"))
    assert block["conflicts"] == []

    def refused(body: dict[str, Any]) -> list[dict[str, Any]]:
        response = pacs_service.client.post("/v1/jobs", json=body)
        assert response.status_code == 422, response.text
        return list(response.json()["errors"])

    index = {r["field"]: i for i, r in enumerate(block["study"]) if not r["attribute"].startswith("lateral")}
    typed = json.loads(json.dumps({**payload, "dicom": block}))  # the payload's Patient ID kept, as before
    typed["study"]["patient_id"] = "P-TYPED"
    typed["dicom"]["study"][index["study.patient_id"]]["used"] = False
    typed["dicom"]["conflicts"] = [{"field": "study.patient_id", "payload": "P-TYPED", "header": "P-API",
                                    "attribute": "PatientID (0010,0020)"}]  # fmt: skip
    [error] = refused(typed)
    assert error["loc"] == ["study", "patient_id"] and error["type"] == "patient_conflict"
    assert "'P-TYPED'" in error["msg"] and "'P-API'" in error["msg"] and "PatientID (0010,0020)" in error["msg"]

    other = json.loads(json.dumps({**payload, "dicom": block}))  # a lateral of another patient
    lateral_id = next(r for r in other["dicom"]["study"] if r["field"] == "study.patient_id" and not r["used"])
    lateral_id["value"] = "P-OTHER"
    [error] = refused(other)
    assert error["loc"] == ["study", "patient_id"]
    assert "'P-API'" in error["msg"] and "'P-OTHER'" in error["msg"] and "lateral film" in error["msg"]

    accession = json.loads(json.dumps({**payload, "dicom": block}))  # the SR would carry the typed one
    accession["study"]["accession_number"] = "TYPED"
    accession["dicom"]["study"][index["study.accession_number"]]["used"] = False
    [error] = refused(accession)
    assert error["loc"] == ["dicom", "study", index["study.accession_number"], "used"]
    assert "'ACC-42'" in error["msg"] and "'TYPED'" in error["msg"]

    assert pacs_service.client.post("/v1/jobs", json={**payload, "dicom": block}).status_code == 202


def _lateral_view() -> dict[str, Any]:
    points = spine_payload(spacing_mm=SPACING)["pa"]["landmarks"][4:]
    return {"units": "px", "landmarks": [{"level": lm["level"], "point": [lm["point"][0] - 20, lm["point"][1]]}
                                         for lm in points]}  # fmt: skip


def test_by_reference_films_of_another_patient_fail_the_job(pacs_service: Service, orthanc: OrthancServer) -> None:
    """Stored in Orthanc: a PA of P-REF, a lateral of P-LAT in the same study. A job naming the PA with
    another Patient ID (its spacing typed: the header is read only for the SR, where a PACS problem
    would not fail it), and one naming both films (read before the fit), each fail at once with
    ``dicom-patient-conflict`` naming the field and both values; nothing is stored in the study."""
    pa = _pa(patient_id="P-REF", patient_name="Ref^Anna")
    lateral = _lateral_of(pa, patient_id="P-LAT", patient_name="Lat^Otto")
    with pacs_of(orthanc) as pacs:
        pacs.store([pa, lateral])
    typed = spine_payload(spacing_mm=SPACING)
    typed["pa"].update(pixel_spacing=[SPACING, SPACING], patient_orientation=["L", "F"])
    typed["study"] = {"study_instance_uid": pa.StudyInstanceUID, "pa_sop_instance_uid": pa.SOPInstanceUID,
                      "patient_id": "P-TYPED", "patient_name": "Typed^Name"}  # fmt: skip
    both = spine_payload(spacing_mm=SPACING)
    both["lateral"] = _lateral_view()
    both["study"] = {"study_instance_uid": pa.StudyInstanceUID, "pa_sop_instance_uid": pa.SOPInstanceUID,
                     "lateral_sop_instance_uid": lateral.SOPInstanceUID}  # fmt: skip
    jobs = [pacs_service.submit(typed)["id"], pacs_service.submit(both)["id"]]
    for job_id, values in zip(jobs, (("'P-TYPED'", "'P-REF'"), ("'P-REF'", "'P-LAT'")), strict=True):
        job = pacs_service.wait(job_id, timeout=120)
        assert job["status"] == "failed" and job["attempts"] == 1, (job.get("error"), pacs_service.worker_log()[-3000:])
        error = job["error"]
        assert error["type"].endswith("/dicom-patient-conflict") and error["field"] == "study.patient_id", error
        assert all(value in error["detail"] for value in values), error["detail"]
        assert "PatientID (0010,0020)" in error["attributes"] and job["result"] is None
    time.sleep(2.0)  # a store task would have run by now (it follows a success at once)
    with pacs_of(orthanc) as pacs:
        assert len(pacs.search_instances(pa.StudyInstanceUID)) == 2  # the two films, no SR nor figure


def test_by_reference_the_sr_carries_the_films_accession_and_name(
    pacs_service: Service, orthanc: OrthancServer
) -> None:
    """A by-reference job whose payload types another Accession Number and a misspelt name of the film's
    Patient ID succeeds; its SR and SC in the film's study carry the film's values, not the payload's."""
    pa = _pa(patient_id="P-ACC", patient_name="Acc^Maria", accession_number="ACC-FILM")
    with pacs_of(orthanc) as pacs:
        pacs.store([pa])
    payload = spine_payload(spacing_mm=SPACING)
    payload["study"] = {"study_instance_uid": pa.StudyInstanceUID, "pa_sop_instance_uid": pa.SOPInstanceUID,
                        "patient_id": "P-ACC", "patient_name": "Acc^Mario",
                        "accession_number": "ACC-TYPED"}  # fmt: skip
    job = pacs_service.wait(pacs_service.submit(payload)["id"], timeout=120)
    assert job["status"] == "succeeded", job.get("error")
    assert {c["field"] for c in job["dicom"]["conflicts"]} == {"study.patient_name", "study.accession_number"}
    assert (job["study"]["accession_number"], job["study"]["patient_name"]) == ("ACC-FILM", "Acc^Maria")
    for artifact in ("sr.dcm", "figure.dcm"):
        response = pacs_service.client.get(f"/v1/jobs/{job['id']}/{artifact}")
        assert response.status_code == 200, response.text
        ds = pydicom.dcmread(io.BytesIO(response.content))
        assert (ds.StudyInstanceUID, ds.PatientID, str(ds.PatientName), ds.AccessionNumber) == (
            pa.StudyInstanceUID, "P-ACC", "Acc^Maria", "ACC-FILM"), artifact  # fmt: skip
