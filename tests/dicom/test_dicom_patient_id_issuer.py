"""The issuer of the film's Patient ID: read from Issuer of Patient ID (0010,0021) and Issuer of Patient ID
Qualifiers Sequence (0010,0024) (PS3.3 §C.7.1.1, Patient Module; PS3.3 §10.14 for the Universal Entity ID
Types), carried in the job's ``study.patient_id_issuer`` (the contract's ``PatientIdIssuer``), and written
back into the SR and SC (a new series of the film's study repeats its Patient Module). A value that is not
as the standard writes it is left out with a warning naming it, never a refusal (the attributes are Type 3).
The FHIR side (the identifier system built from the issuer) is tests/fhir/test_fhir_patient_id_issuer.py."""

from __future__ import annotations

import shutil
import subprocess
import typing
import uuid
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pydicom
import pytest
from pydantic import ValidationError
from pydicom.dataset import Dataset

from services.db.job_forms import engine_payload
from services.dicom.sc import build_sc
from services.dicom.sr import StudyIdentity, build_sr
from spine_client.dicom.errors import PatientConflict
from spine_client.dicom.header import UNIVERSAL_ENTITY_ID_TYPES, PatientIdIssuer, read_header
from spine_client.dicom.merge import ISSUER_ATTRIBUTES, apply_headers
from spine_engine import register
from spine_engine.figures import render_figure
from spine_engine.models import Study, UniversalEntityIdType
from tests.conftest import spine_payload
from tools.dicom import synthetic

OID = "1.2.826.0.1.3680043.10.1234"
FINISHED = datetime(2026, 12, 1, 12, 0, tzinfo=UTC)


def qualifiers(universal: str | None, kind: str | None, items: int = 1) -> list[Dataset]:
    """Issuer of Patient ID Qualifiers Sequence (0010,0024) items: Universal Entity ID and its Type when given."""
    out = []
    for _ in range(items):
        item = Dataset()
        if universal is not None:
            item.UniversalEntityID = universal
        if kind is not None:
            item.UniversalEntityIDType = kind
        out.append(item)
    return out


def test_the_readers_types_are_the_contracts() -> None:
    """The client's reader (installed without the engine) and the contract name the same defined terms."""
    assert typing.get_args(UniversalEntityIdType) == UNIVERSAL_ENTITY_ID_TYPES


@pytest.mark.parametrize(
    ("extra", "issuer"),
    [
        ({"IssuerOfPatientID": "HOSP-A", "IssuerOfPatientIDQualifiersSequence": qualifiers(OID, "ISO")},
         PatientIdIssuer("HOSP-A", OID, "ISO")),
        ({"IssuerOfPatientIDQualifiersSequence": qualifiers("https://hospital.example/mrn", "URI")},
         PatientIdIssuer(None, "https://hospital.example/mrn", "URI")),
        ({"IssuerOfPatientID": "Hôpital Nord"}, PatientIdIssuer("Hôpital Nord")),  # a local name only
        ({}, None),
    ],
)  # fmt: skip
def test_the_issuer_is_read(extra: dict[str, Any], issuer: PatientIdIssuer | None) -> None:
    header = read_header(synthetic.radiograph(extra={"SpecificCharacterSet": "ISO_IR 192", **extra}))
    assert header.patient_id_issuer == issuer
    assert not [w for w in header.warnings if "Issuer" in w]
    if issuer is not None:  # what the reader keeps, the contract takes (the worker validates the job's study)
        Study.model_validate({"study_instance_uid": "1.2.3", "patient_id_issuer": issuer.as_payload()})


def test_the_issuer_is_read_from_dicom_json() -> None:
    """WADO-RS metadata (PS3.18 §F.2), what the worker reads a film by: the same issuer."""
    film = synthetic.radiograph(extra={"IssuerOfPatientID": "HOSP-A",
                                       "IssuerOfPatientIDQualifiersSequence": qualifiers(OID, "ISO")})  # fmt: skip
    assert read_header(film.to_json_dict()).patient_id_issuer == PatientIdIssuer("HOSP-A", OID, "ISO")


@pytest.mark.parametrize(
    ("extra", "kept", "warned"),
    [
        ({"IssuerOfPatientID": "X" * 65}, None, "longer than an LO"),  # LO: 64 characters (PS3.5 §6.2)
        ({"IssuerOfPatientID": "HOSP-A", "IssuerOfPatientIDQualifiersSequence": qualifiers(OID, None)},
         PatientIdIssuer("HOSP-A"), "has no Type"),  # the Type is Type 1C with the ID
        ({"IssuerOfPatientIDQualifiersSequence": qualifiers(OID, "OID")}, None, "'OID' is not one of"),
        ({"IssuerOfPatientID": "HOSP-A", "IssuerOfPatientIDQualifiersSequence": qualifiers(OID, "ISO", items=2)},
         PatientIdIssuer("HOSP-A"), "holds 2 items"),  # "only a single Item is permitted"
        ({"IssuerOfPatientID": "HOSP\nA"}, None, "control character"),
        ({"IssuerOfPatientIDQualifiersSequence": qualifiers("C=US\\O=H", "X500")}, None, "backslash"),
    ],
)  # fmt: skip
def test_an_issuer_not_as_dicom_writes_it_is_left_out_with_a_warning(
    extra: dict[str, Any], kept: PatientIdIssuer | None, warned: str
) -> None:  # fmt: skip
    header = read_header(synthetic.radiograph(extra=extra))  # not refused: the attributes are Type 3
    assert header.patient_id_issuer == kept
    assert any(warned in w and "left out" in w for w in header.warnings), header.warnings


def test_the_issuer_goes_into_the_jobs_study_and_the_contract_takes_it() -> None:
    pa = synthetic.radiograph(extra={"IssuerOfPatientID": "HOSP-A",
                                     "IssuerOfPatientIDQualifiersSequence": qualifiers(OID, "ISO")})  # fmt: skip
    lateral = synthetic.radiograph(study_instance_uid=pa.StudyInstanceUID, patient_orientation=("A", "F"),
                                   view_position="LL", extra={"IssuerOfPatientID": "HOSP-A"})  # fmt: skip
    merged, provenance = apply_headers(spine_payload(), {"pa": read_header(pa), "lateral": read_header(lateral)},
                                       source="file")  # fmt: skip
    expected = {"issuer_of_patient_id": "HOSP-A", "universal_entity_id": OID, "universal_entity_id_type": "ISO"}
    assert merged["study"]["patient_id_issuer"] == expected
    read = next(r for r in provenance.study if r.field == "study.patient_id_issuer" and r.used)
    assert read.attribute == ISSUER_ATTRIBUTES and "(0010,0021)" in read.attribute and "(0010,0024)" in read.attribute
    assert [c.header for c in provenance.conflicts if c.field == "study.patient_id_issuer"] == [
        {"issuer_of_patient_id": "HOSP-A"}]  # the lateral's, without the universal ID: a conflict, the PA's used
    assert Study.model_validate(engine_payload(merged)["study"]).patient_id_issuer is not None
    # a lateral whose Patient ID another issuer gave may be another patient: refused (merge.identity_problems)
    other = synthetic.radiograph(study_instance_uid=pa.StudyInstanceUID, patient_orientation=("A", "F"),
                                 view_position="LL", extra={"IssuerOfPatientID": "HOSP-B"})  # fmt: skip
    with pytest.raises(PatientConflict, match=r"'HOSP-A'.*'HOSP-B'") as refused:
        apply_headers(spine_payload(), {"pa": read_header(pa), "lateral": read_header(other)}, source="file")
    assert refused.value.field == "study.patient_id_issuer"


@pytest.mark.parametrize(
    "issuer",
    [
        {"universal_entity_id": OID},  # the ID without its Type (Type 1C, PS3.3 §C.7.1.1)
        {"universal_entity_id_type": "ISO"},
        {"universal_entity_id": OID, "universal_entity_id_type": "OID"},  # not a defined term (PS3.3 §10.14)
        {"issuer_of_patient_id": "X" * 65},  # LO, 64 characters
        {"issuer_of_patient_id": "A\\B"},  # a backslash separates values
        {},
    ],
)
def test_the_contract_refuses_an_issuer_dicom_would_not_write(issuer: dict[str, Any]) -> None:
    with pytest.raises(ValidationError):
        Study.model_validate({"study_instance_uid": "1.2.3", "patient_id": "P1", "patient_id_issuer": issuer})


@pytest.fixture(scope="module")
def result() -> dict[str, Any]:
    out: dict[str, Any] = register(spine_payload(curve_mm=25.0))
    return out


@pytest.mark.parametrize(
    ("issuer", "local", "qualified"),
    [
        ({"issuer_of_patient_id": "Hôpital Nord", "universal_entity_id": OID, "universal_entity_id_type": "ISO"},
         "Hôpital Nord", (OID, "ISO")),
        ({"issuer_of_patient_id": "HOSP-A"}, "HOSP-A", None),
        (None, None, None),
    ],
)  # fmt: skip
def test_the_sr_and_sc_carry_the_films_issuer(
    result: dict[str, Any], tmp_path: Path, issuer: dict[str, Any] | None, local: str | None,
    qualified: tuple[str, str] | None,
) -> None:  # fmt: skip
    """PS3.3 §C.7.1.1: Issuer of Patient ID (0010,0021) and its Qualifiers Sequence (0010,0024), one item with
    the Universal Entity ID (0040,0032) and its Type (0040,0033); neither when unknown (Type 3). dciodvfy
    finds no error in either instance."""
    payload = spine_payload(curve_mm=25.0)
    study = {"study_instance_uid": "1.2.826.0.1.3680043.10.1.1", "patient_id": "P1", "patient_id_issuer": issuer}
    identity = StudyIdentity.from_study(study)
    sr = build_sr(result, payload, uuid.UUID(int=3), identity, content_datetime=FINISHED)
    sc = build_sc(render_figure(result, payload, dpi=40), uuid.UUID(int=3), identity, content_datetime=FINISHED)
    for name, ds in (("sr", sr), ("sc", sc)):
        path = tmp_path / f"{name}.dcm"
        ds.save_as(path, enforce_file_format=True)
        back = pydicom.dcmread(path)
        assert back.get("IssuerOfPatientID") == local
        items = back.get("IssuerOfPatientIDQualifiersSequence")
        assert ([(i.UniversalEntityID, i.UniversalEntityIDType) for i in items] if items else None) == (
            [qualified] if qualified else None)  # fmt: skip
        if shutil.which("dciodvfy") is not None:
            run = subprocess.run(["dciodvfy", str(path)], capture_output=True, text=True, timeout=60)
            assert [line for line in (run.stdout + run.stderr).splitlines() if line.startswith("Error")] == []
