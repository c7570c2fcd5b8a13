"""Text that the job database cannot store, or that no DICOM header holds, is a 422 naming the field,
on both databases the service runs on: PostgreSQL's text and jsonb refuse the NUL character
(PostgreSQL 15 documentation, §8.3 and §8.14) and its json parser an unpaired surrogate, where SQLite
stores both, so on PostgreSQL such a job was a 500 at its insert; and a DICOM LO or SH value holds
no backslash and no control character (PS3.5 §6.2), so a filter or a follow-up asked for with one is
refused, not a 404 or a 500."""

from __future__ import annotations

import copy
import json
from collections.abc import Callable
from typing import Any
from urllib.parse import quote

import pytest
from fastapi.testclient import TestClient

from spine_engine.models import DICOM_TEXT_REASON, DICOM_UID_REASON
from tests.conftest import problem_of, spine_payload

BACKENDS = pytest.mark.parametrize("db_settings", ["sqlite", "postgresql"], indirect=True)
WITH_NUL = "x\x00y"
FILM = {"source": "file", "study_instance_uid": "1.2.3", "sop_instance_uid": "1.2.3.4"}


@pytest.fixture
def client(own_client: TestClient) -> TestClient:
    return own_client


def _profile(p: dict[str, Any]) -> None:
    p["options"] = {"profile": WITH_NUL}


def _film_warning(p: dict[str, Any]) -> None:
    p["dicom"] = {"pa": {**FILM, "warnings": [WITH_NUL]}}


def _member_name(p: dict[str, Any]) -> None:
    p["options"] = {WITH_NUL: 1}


@BACKENDS
@pytest.mark.parametrize(
    ("edit", "path"),
    [(_profile, "options.profile"), (_film_warning, "dicom.pa.warnings[0]"), (_member_name, "options.x\x00y")],
    ids=["a field's value", "the client's DICOM reads", "a member's name"],
)
def test_a_nul_in_a_posted_text_is_a_422_naming_it_and_nothing_is_stored(
    client: TestClient, edit: Callable[[dict[str, Any]], None], path: str
) -> None:
    payload = copy.deepcopy(spine_payload())
    edit(payload)
    problem = problem_of(client.post("/v1/jobs", json=payload))
    assert problem["status"] == 422
    assert [(e["path"], e["type"]) for e in problem["errors"]] == [(path, "nul_character")]
    assert "NUL character (U+0000)" in problem["detail"]
    assert client.get("/v1/jobs").json()["jobs"] == []


@BACKENDS
@pytest.mark.parametrize("escape", ["\\ud800", "\\udfff"], ids=["high", "low"])
def test_an_unpaired_surrogate_is_a_422_naming_it_and_nothing_is_stored(client: TestClient, escape: str) -> None:
    """A ``\\ud800`` escape alone decodes to no character (RFC 8259 §8.2); PostgreSQL's json parser
    refuses it."""
    body = json.dumps(spine_payload())[:-1] + f', "options": {{"profile": "x{escape}y"}}}}'
    answer = client.post("/v1/jobs", content=body.encode(), headers={"Content-Type": "application/json"})
    problem = problem_of(answer)
    assert problem["status"] == 422
    assert [(e["path"], e["type"]) for e in problem["errors"]] == [("options.profile", "unpaired_surrogate")]
    assert client.get("/v1/jobs").json()["jobs"] == []


@BACKENDS
def test_a_nul_in_one_batch_entry_refuses_that_entry_only(client: TestClient) -> None:
    bad = spine_payload()
    _profile(bad)
    answer = client.post("/v1/jobs/batch", json={"jobs": [spine_payload(), bad]})
    assert answer.status_code == 200, answer.text
    body = answer.json()
    assert (body["accepted"], body["rejected"]) == (1, 1)
    assert [e["path"] for e in body["results"][1]["problem"]["errors"]] == ["jobs[1].options.profile"]
    assert len(client.get("/v1/jobs").json()["jobs"]) == 1


@BACKENDS
@pytest.mark.parametrize("name", ["patient_id", "accession_number"])
@pytest.mark.parametrize("value", ["x\x00y", "x\ny", "x\\y"], ids=["NUL", "line break", "backslash"])
def test_a_dicom_text_filter_with_a_control_character_or_backslash_is_a_422(
    client: TestClient, name: str, value: str
) -> None:
    problem = problem_of(client.get("/v1/jobs", params={name: value}))
    assert problem["status"] == 422
    assert [(e["path"], e["msg"]) for e in problem["errors"]] == [(f"query.{name}", DICOM_TEXT_REASON)]


@BACKENDS
def test_a_study_filter_that_is_no_uid_is_a_422_and_a_uid_is_taken(client: TestClient) -> None:
    problem = problem_of(client.get("/v1/jobs", params={"study_instance_uid": "1.2.x\x00"}))
    assert [(e["path"], e["msg"]) for e in problem["errors"]] == [("query.study_instance_uid", DICOM_UID_REASON)]
    assert client.get("/v1/jobs", params={"study_instance_uid": "1.2.840.10008"}).status_code == 200


@BACKENDS
@pytest.mark.parametrize("value", ["x\x00y", "x\ny"], ids=["NUL", "line break"])
def test_a_follow_up_asked_with_a_control_character_is_a_422_not_a_404(client: TestClient, value: str) -> None:
    problem = problem_of(client.get(f"/v1/patients/{quote(value, safe='')}/measures"))
    assert problem["status"] == 422
    assert [(e["path"], e["msg"]) for e in problem["errors"]] == [("path.patient_id", DICOM_TEXT_REASON)]


@BACKENDS
def test_a_patient_id_with_a_slash_is_still_a_patient_id(client: TestClient) -> None:
    """LO allows "/" (PS3.5 §6.2): percent-encoded, it names the patient, not a deeper path."""
    payload = spine_payload()
    payload["study"] = {"study_instance_uid": "1.2.3", "patient_id": "A/B 12"}
    assert client.post("/v1/jobs", json=payload).status_code == 202
    answer = client.get(f"/v1/patients/{quote('A/B 12', safe='')}/measures")
    assert answer.status_code == 200, answer.text
    assert answer.json()["patient_id"] == "A/B 12"


@pytest.mark.parametrize(
    ("name", "reason"),
    [
        ("D" * 60 + "^JOHN", "65 characters in its alphabetic component group"),
        ("DOE^JOHN=" + "山" * 65, "65 characters in its ideographic component group"),
        ("A=B=C=D", "4 component groups"),
        ("A^B^C^D^E^F", "6 components in its alphabetic component group"),
    ],
)
def test_a_patient_name_no_dicom_pn_holds_is_a_422_naming_it(client: TestClient, name: str, reason: str) -> None:
    """A PN is up to three '='-separated groups of at most 64 characters and five '^'-separated
    components each (PS3.5 §6.2, Table 6.2-1, §6.2.1): a longer name would be copied into the SR and SC
    the service writes, which no DICOM reader then takes (dciodvfy reports it). Nothing is stored."""
    payload = spine_payload()
    payload["study"] = {"study_instance_uid": "1.2.3", "patient_name": name}
    problem = problem_of(client.post("/v1/jobs", json=payload))
    assert problem["status"] == 422
    assert [e["path"] for e in problem["errors"]] == ["study.patient_name"]
    assert reason in problem["errors"][0]["msg"]
    assert client.get("/v1/jobs").json()["jobs"] == []


def test_a_patient_name_of_three_full_groups_is_taken(client: TestClient) -> None:
    name = "=".join(["A" * 60 + "^B^C", "山" * 64, "や" * 64])
    payload = spine_payload()
    payload["study"] = {"study_instance_uid": "1.2.3", "patient_name": name}
    assert client.post("/v1/jobs", json=payload).status_code == 202
