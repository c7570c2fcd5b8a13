"""The FHIR subject identifier's ``system`` from the film's issuer of Patient ID (PS3.3 §C.7.1.1: Issuer of
Patient ID Qualifiers Sequence (0010,0024), Universal Entity ID (0040,0032) and its Type (0040,0033), PS3.3
§10.14): ISO → ``urn:oid:``, UUID → ``urn:uuid:``, URI as it is; else the setting SPINE_PATIENT_ID_SYSTEM;
else none. FHIR R4 Identifier.system is a ``uri``: a local issuer name (0010,0021) is not one, and is the
identifier's ``assigner.display``. End to end: a film whose header names its issuer, read by the client,
posted with its ``dicom`` block to the real API (embedded database), the job made succeeded with a real
result, its ``fhir`` and ``sr.dcm`` fetched."""

from __future__ import annotations

import io
import uuid
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pydicom
import pytest
from fastapi.testclient import TestClient
from fhir.resources.R4B.bundle import Bundle
from pydicom.dataset import Dataset
from sqlalchemy import update

from services.api.app import create_app
from services.core.config import Settings
from services.db.engine import session_scope
from services.db.migrate import upgrade
from services.db.models import Job as JobRow
from services.fhir.export import issuer_system, observation_bundle
from spine_client.dicom_input import payload_from_dicom
from spine_engine import register
from tests.conftest import make_key, spine_payload
from tools.dicom import synthetic

OID = "1.2.826.0.1.3680043.10.1234"
SETTING = "urn:oid:1.2.3.4.5"
FINISHED = datetime(2026, 12, 2, 9, 30, tzinfo=UTC)


@pytest.fixture(scope="module")
def result() -> dict[str, Any]:
    out: dict[str, Any] = register(spine_payload(curve_mm=25.0))
    return out


@pytest.mark.parametrize(
    ("universal", "kind", "system"),
    [
        (OID, "ISO", f"urn:oid:{OID}"),
        ("2.25.329800735698586629295641978511506172918", "ISO", "urn:oid:2.25.329800735698586629295641978511506172918"),
        ("1.2.03", "ISO", None),  # a leading zero: no OID (FHIR R4 oid: [0-2](\.(0|[1-9][0-9]*))+)
        ("3.1", "ISO", None),  # an OID's first arc is 0, 1 or 2
        ("HOSP-A", "ISO", None),
        ("2B9F4A39-7E2C-4C2B-9E8C-1D2E3F4A5B6C", "UUID", "urn:uuid:2b9f4a39-7e2c-4c2b-9e8c-1d2e3f4a5b6c"),
        ("2b9f4a397e2c4c2b9e8c1d2e3f4a5b6c", "UUID", None),  # not the 8-4-4-4-12 form
        ("https://hospital.example/mrn", "URI", "https://hospital.example/mrn"),
        ("urn:oid:1.2.3", "URI", "urn:oid:1.2.3"),
        ("hospital/mrn", "URI", None),  # relative: no scheme (RFC 3986 §4.3)
        ("hospital.example", "DNS", None),  # a name, not a URI
        ("0123456789ABCDEF", "EUI64", None),
        ("C=US;O=Hospital", "X500", None),
    ],
)
def test_the_system_of_a_qualified_issuer(universal: str, kind: str, system: str | None) -> None:
    issuer = {"universal_entity_id": universal, "universal_entity_id_type": kind}
    assert issuer_system(issuer) == system


def _subject(result: dict[str, Any], issuer: dict[str, Any] | None, setting: str | None) -> Any:
    study = {"study_instance_uid": "1.2.826.0.1.3680043.10.1.1", "patient_id": "P1", "patient_id_issuer": issuer}
    bundle = observation_bundle(uuid.UUID(int=1), result, finished_at=FINISHED, study=study,
                                patient_id_system=setting)  # fmt: skip
    Bundle.model_validate(bundle)
    subjects = [e["resource"]["subject"] for e in bundle["entry"]]
    assert all(s == subjects[0] for s in subjects)
    return subjects[0]["identifier"]


@pytest.mark.parametrize(
    ("issuer", "setting", "identifier"),
    [
        ({"issuer_of_patient_id": "HOSP-A", "universal_entity_id": OID, "universal_entity_id_type": "ISO"}, SETTING,
         {"system": f"urn:oid:{OID}", "value": "P1", "assigner": {"display": "HOSP-A"}}),  # the film's issuer first
        ({"universal_entity_id": OID, "universal_entity_id_type": "ISO"}, None,
         {"system": f"urn:oid:{OID}", "value": "P1"}),
        ({"issuer_of_patient_id": "HOSP-A"}, SETTING,
         {"system": SETTING, "value": "P1", "assigner": {"display": "HOSP-A"}}),  # a local name is no URI
        ({"issuer_of_patient_id": "HOSP-A"}, None, {"value": "P1", "assigner": {"display": "HOSP-A"}}),
        ({"universal_entity_id": "hospital.example", "universal_entity_id_type": "DNS"}, SETTING,
         {"system": SETTING, "value": "P1"}),
        (None, SETTING, {"system": SETTING, "value": "P1"}),
        (None, None, {"value": "P1"}),
    ],
)  # fmt: skip
def test_the_subject_system_is_the_films_issuer_else_the_setting(
    result: dict[str, Any], issuer: dict[str, Any] | None, setting: str | None, identifier: dict[str, Any]
) -> None:  # fmt: skip
    assert _subject(result, issuer, setting) == identifier


def test_a_film_header_with_its_issuer_gives_the_fhir_subject_system(result: dict[str, Any], tmp_path: Path) -> None:
    """End to end, the service configured with another SPINE_PATIENT_ID_SYSTEM: the film's ISO issuer is the
    identifier system; the SR carries the film's issuer too."""
    item = Dataset()
    item.UniversalEntityID, item.UniversalEntityIDType = OID, "ISO"
    film = synthetic.radiograph(imager_pixel_spacing=(0.15, 0.15), rows=3200, columns=1200,
                                extra={"IssuerOfPatientID": "HOSP-A", "IssuerOfPatientIDQualifiersSequence": [item]})
    synthetic.write(film, tmp_path / "pa.dcm")
    points = spine_payload(curve_mm=25.0)["pa"]["landmarks"]
    (tmp_path / "lm.csv").write_text("".join(f"{p['level']},{p['point'][0] / 0.15},{p['point'][1] / 0.15}\n"
                                             for p in points))  # fmt: skip
    payload, dicom = payload_from_dicom(tmp_path / "lm.csv", tmp_path / "pa.dcm")

    settings = Settings(data_dir=tmp_path / "data", patient_id_system=SETTING)
    upgrade(settings, quiet=True)
    with TestClient(create_app(settings)) as client:
        client.headers["Authorization"] = f"Bearer {make_key(settings)}"
        response = client.post("/v1/jobs", json={**payload, "dicom": dicom})
        assert response.status_code == 202, response.text
        job_id = uuid.UUID(response.json()["id"])
        with session_scope(settings) as session:
            session.execute(update(JobRow).where(JobRow.id == job_id).values(
                status="succeeded", result=result, finished_at=FINISHED, attempts=1))  # fmt: skip
        job = client.get(f"/v1/jobs/{job_id}").json()
        fhir = client.get(f"/v1/jobs/{job_id}/fhir")
        sr = client.get(f"/v1/jobs/{job_id}/sr.dcm")
    assert job["study"]["patient_id_issuer"] == {"issuer_of_patient_id": "HOSP-A", "universal_entity_id": OID,
                                                 "universal_entity_id_type": "ISO"}  # fmt: skip
    assert fhir.status_code == 200, fhir.text
    bundle = fhir.json()
    Bundle.model_validate(bundle)
    assert {e["resource"]["subject"]["identifier"]["system"] for e in bundle["entry"]} == {f"urn:oid:{OID}"}
    assert {e["resource"]["subject"]["identifier"]["assigner"]["display"] for e in bundle["entry"]} == {"HOSP-A"}
    assert sr.status_code == 200
    back = pydicom.dcmread(io.BytesIO(sr.content))
    assert back.IssuerOfPatientID == "HOSP-A"
    assert back.IssuerOfPatientIDQualifiersSequence[0].UniversalEntityID == OID
