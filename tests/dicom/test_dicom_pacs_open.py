"""Opening a study from the PACS through the API (``/v1/pacs``), on a real Orthanc and the embedded
database: the study's images listed by QIDO-RS with their attributes, one image returned as a Part 10
file in Explicit VR Little Endian (transcoded by the PACS when stored otherwise), and the problems:
unknown study or instance, a path parameter that is not a UID, no PACS configured, a PACS down, no key."""

from __future__ import annotations

import io
from collections.abc import Iterator
from pathlib import Path

import pydicom
import pytest
from fastapi.testclient import TestClient
from pydicom.uid import ExplicitVRLittleEndian, RLELossless, generate_uid

from services.api.app import create_app
from services.core.config import DicomwebConfig, Settings
from services.db.migrate import upgrade
from services.dicom.dicomweb import Pacs
from tests.conftest import make_key
from tools.dicom import synthetic

from .conftest import OrthancServer, free_port


def _client(tmp_path: Path, **settings_kwargs: object) -> TestClient:
    # the client is one SPINE_PACS_CLIENTS names: browsing the PACS is a permission (docs/security.md)
    settings = Settings(data_dir=tmp_path, pacs_clients="pacs-client", **settings_kwargs)  # type: ignore[arg-type]
    upgrade(settings, quiet=True)
    client = TestClient(create_app(settings))
    client.headers["Authorization"] = f"Bearer {make_key(settings, 'pacs-client')}"
    return client


@pytest.fixture
def api(tmp_path: Path, orthanc: OrthancServer) -> Iterator[TestClient]:
    with _client(tmp_path, dicomweb_url=orthanc.dicomweb_url, dicomweb_username=orthanc.username,
                 dicomweb_password=orthanc.password) as client:  # fmt: skip
        yield client


def _stow_to_pacs(orthanc: OrthancServer, *images: pydicom.Dataset) -> None:
    with Pacs(DicomwebConfig(orthanc.dicomweb_url, orthanc.username, orthanc.password)) as pacs:
        pacs.store(list(images))


def _instance_url(image: pydicom.Dataset) -> str:
    return (f"/v1/pacs/studies/{image.StudyInstanceUID}/series/{image.SeriesInstanceUID}"
            f"/instances/{image.SOPInstanceUID}")  # fmt: skip


def test_list_and_open_a_study(api: TestClient, orthanc: OrthancServer) -> None:
    study = generate_uid(prefix="2.25.")
    described = {"SeriesNumber": 2, "InstanceNumber": 1, "SeriesDescription": "PA spine"}
    pa = synthetic.radiograph(study_instance_uid=study, rows=120, columns=48, transfer_syntax="implicit",
                              extra=described)  # fmt: skip
    lateral = synthetic.radiograph(study_instance_uid=study, modality="CR", view_position="LL",
                                   patient_orientation=("A", "F"), rows=100, columns=40,
                                   extra={"SeriesNumber": 1, "InstanceNumber": 3})  # fmt: skip
    _stow_to_pacs(orthanc, pa, lateral)
    assert api.get("/v1/pacs").json() == {"configured": True}

    listed = api.get(f"/v1/pacs/studies/{study}/images")
    assert listed.status_code == 200, listed.text
    body = listed.json()
    assert body["study_instance_uid"] == study
    assert [i["sop_instance_uid"] for i in body["images"]] == [lateral.SOPInstanceUID, pa.SOPInstanceUID]
    first = body["images"][1]
    assert first == {
        "series_instance_uid": pa.SeriesInstanceUID, "sop_instance_uid": pa.SOPInstanceUID,
        "sop_class_uid": pa.SOPClassUID, "modality": "DX", "view_position": "PA",
        "image_laterality": first["image_laterality"], "rows": 120, "columns": 48,
        "series_description": "PA spine", "series_number": 2, "instance_number": 1, "patient_id": "P-0001",
        "patient_name": "Doe^Jane", "study_date": "20261130", "accession_number": "ACC-42",
    }  # fmt: skip
    assert body["images"][0]["modality"] == "CR" and body["images"][0]["view_position"] == "LL"

    got = api.get(_instance_url(pa))
    assert got.status_code == 200, got.text
    assert got.headers["content-type"] == "application/dicom"
    ds = pydicom.dcmread(io.BytesIO(got.content))
    assert ds.file_meta.TransferSyntaxUID == ExplicitVRLittleEndian  # stored implicit, sent explicit
    assert ds.SOPInstanceUID == pa.SOPInstanceUID and ds.PixelData == pa.PixelData
    assert (ds.Rows, ds.Columns) == (120, 48) and list(ds.ImagerPixelSpacing) == [0.15, 0.15]


def test_a_compressed_film_comes_uncompressed(api: TestClient, orthanc: OrthancServer) -> None:
    image = synthetic.radiograph(rows=64, columns=32)
    pixels = image.pixel_array
    image.compress(RLELossless)
    _stow_to_pacs(orthanc, image)
    got = api.get(_instance_url(image))
    assert got.status_code == 200, got.text
    ds = pydicom.dcmread(io.BytesIO(got.content))
    assert ds.file_meta.TransferSyntaxUID == ExplicitVRLittleEndian
    assert (ds.pixel_array == pixels).all()


def test_problems(api: TestClient, orthanc: OrthancServer, tmp_path: Path) -> None:
    image = synthetic.radiograph()
    _stow_to_pacs(orthanc, image)
    unknown = api.get("/v1/pacs/studies/1.2.3.999/images")
    assert unknown.status_code == 404 and unknown.headers["content-type"] == "application/problem+json"
    assert unknown.json()["type"].endswith("/dicomweb-study-not-found") and "1.2.3.999" in unknown.json()["detail"]
    missing = api.get(f"/v1/pacs/studies/{image.StudyInstanceUID}/series/{image.SeriesInstanceUID}/instances/1.2.3")
    assert missing.status_code == 404 and missing.json()["type"].endswith("/dicomweb-instance-not-found")

    for bad in ("1.2.03", "1.2.x", "1." + "2" * 70):
        for url in (f"/v1/pacs/studies/{bad}/images", f"/v1/pacs/studies/1.2/series/1.3/instances/{bad}"):
            refused = api.get(url)
            assert refused.status_code == 422, (url, refused.text)
            paths = [e["path"] for e in refused.json()["errors"]]
            assert paths == [("path.study_instance_uid" if "images" in url else "path.sop_instance_uid")], paths

    no_key = api.get(f"/v1/pacs/studies/{image.StudyInstanceUID}/images", headers={"Authorization": ""})
    assert no_key.status_code == 401

    with _client(tmp_path / "none") as without:
        assert without.get("/v1/pacs").json() == {"configured": False}
        none = without.get(f"/v1/pacs/studies/{image.StudyInstanceUID}/images")
        assert none.status_code == 404 and none.json()["type"].endswith("/dicomweb-not-configured")
        assert "SPINE_DICOMWEB_URL" in none.json()["detail"]

    down_url = f"http://127.0.0.1:{free_port()}/dicom-web"
    with _client(tmp_path / "down", dicomweb_url=down_url, dicomweb_timeout_s=2) as down:
        for url in (f"/v1/pacs/studies/{image.StudyInstanceUID}/images", _instance_url(image)):
            answer = down.get(url)
            assert answer.status_code == 503, answer.text
            assert answer.json()["type"].endswith("/dicomweb-unavailable") and answer.headers["Retry-After"] == "10"
