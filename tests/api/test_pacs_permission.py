"""Browsing the PACS (``/v1/pacs``) is a permission: admin keys have it, and the keys of the clients named in
``SPINE_PACS_CLIENTS``; any other client key (a clinic's integration key) gets a 403 ``forbidden`` problem
naming the permission ``pacs`` on every route, before the PACS is asked, and reads no patient's images.

A real Orthanc holding a study of another patient, the API in process on the real PostgreSQL (and SQLite)
database where the keys are."""

from __future__ import annotations

import io
import json
import uuid
from collections.abc import Iterator

import pydicom
import pytest
from fastapi.testclient import TestClient
from pydantic import SecretStr
from pydicom.uid import generate_uid

from services.api.app import create_app
from services.core.config import DicomwebConfig, Settings
from services.core.problems import PROBLEM_BASE
from services.dicom.dicomweb import Pacs
from tests.conftest import make_key, problem_of
from tools.dicom import synthetic
from tools.dicom.orthanc import OrthancServer

BACKENDS = pytest.mark.parametrize("db_settings", ["postgresql", "sqlite"], indirect=True)
PATIENT = "PACS-PERMISSION-0042"


@pytest.fixture
def study(orthanc: OrthancServer) -> pydicom.Dataset:
    """One film of patient ``PATIENT`` in the PACS."""
    image = synthetic.radiograph(study_instance_uid=generate_uid(prefix="2.25."), transfer_syntax="implicit",
                                 extra={"PatientID": PATIENT})  # fmt: skip
    with Pacs(DicomwebConfig(orthanc.dicomweb_url, orthanc.username, orthanc.password)) as pacs:
        pacs.store([image])
    return image


@pytest.fixture
def api(db_settings: Settings, orthanc: OrthancServer) -> Iterator[tuple[TestClient, str]]:
    """The API connected to the PACS, with SPINE_PACS_CLIENTS naming one client; and that client's name."""
    allowed = f"viewer-{uuid.uuid4().hex[:8]}"
    settings = db_settings.model_copy(update={
        "dicomweb_url": orthanc.dicomweb_url, "dicomweb_username": orthanc.username,
        "dicomweb_password": SecretStr(orthanc.password), "pacs_clients": f"other-clinic, {allowed}",
        "api_key_cache_s": 0,
    })  # fmt: skip
    with TestClient(create_app(settings)) as client:
        yield client, allowed


def _paths(image: pydicom.Dataset) -> list[str]:
    return ["/v1/pacs", f"/v1/pacs/studies/{image.StudyInstanceUID}/images",
            f"/v1/pacs/studies/{image.StudyInstanceUID}/series/{image.SeriesInstanceUID}"
            f"/instances/{image.SOPInstanceUID}"]  # fmt: skip


def _bearer(settings: Settings, name: str, role: str = "client") -> dict[str, str]:
    return {"Authorization": f"Bearer {make_key(settings, name, role)}"}


@BACKENDS
def test_a_client_key_without_the_permission_reads_no_image(
    db_settings: Settings, api: tuple[TestClient, str], study: pydicom.Dataset
) -> None:
    client, _ = api
    clinic = _bearer(db_settings, f"clinic-{uuid.uuid4().hex[:8]}")
    for path in [*_paths(study), "/v1/pacs/studies/not-a-uid/images"]:  # refused before the UID is even read
        answer = client.get(path, headers=clinic)
        assert answer.status_code == 403, (path, answer.text)
        problem = problem_of(answer)
        assert problem["type"] == PROBLEM_BASE + "forbidden" and problem["permission"] == "pacs", problem
        assert "`pacs`" in problem["detail"] and "SPINE_PACS_CLIENTS" in problem["detail"]
        assert PATIENT not in answer.text and "images" not in answer.json()


@BACKENDS
def test_admin_keys_and_the_named_clients_keys_browse_the_pacs(
    db_settings: Settings, api: tuple[TestClient, str], study: pydicom.Dataset
) -> None:
    client, allowed = api
    for headers in (_bearer(db_settings, allowed), _bearer(db_settings, f"ops-{uuid.uuid4().hex[:8]}", "admin")):
        status, images, instance = (client.get(path, headers=headers) for path in _paths(study))
        assert status.json() == {"configured": True}
        assert images.status_code == 200, images.text
        assert [i["patient_id"] for i in images.json()["images"]] == [PATIENT]
        assert instance.status_code == 200, instance.text
        assert pydicom.dcmread(io.BytesIO(instance.content)).SOPInstanceUID == study.SOPInstanceUID


def test_the_contract_declares_the_403_of_every_pacs_route(db_settings: Settings) -> None:
    with TestClient(create_app(db_settings)) as client:
        paths = client.get("/openapi.json").json()["paths"]
    pacs = {path: item for path, item in paths.items() if path.startswith("/v1/pacs")}
    assert len(pacs) == 3
    for path, item in pacs.items():
        answer = item["get"]["responses"]["403"]
        assert "application/problem+json" in answer["content"], (path, json.dumps(answer))
