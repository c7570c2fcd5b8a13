"""DICOMweb against a real Orthanc (Debian's orthanc + orthanc-dicomweb, started by the fixture):
WADO-RS metadata gives the same header as the file, QIDO finds the series, STOW stores the SR and
the figure in the source study where QIDO finds them, and each failure is its own typed error."""

from __future__ import annotations

import uuid
from typing import Any

import httpx
import pytest

from services.core.config import DicomwebConfig
from services.dicom.dicomweb import Pacs
from services.dicom.errors import DicomwebError, InstanceNotFound, PacsUnavailable
from services.dicom.reference import resolve_by_reference, views_to_fetch
from services.dicom.sc import build_sc
from services.dicom.sr import SourceImage, StudyIdentity, build_sr
from spine_client.dicom.errors import InvalidAttribute
from spine_client.dicom.header import read_header
from spine_engine import register
from spine_engine.figures import render_figure
from tests.conftest import spine_payload
from tools.dicom import synthetic

from .conftest import OrthancServer, free_port

HEADER_CASES: list[dict[str, Any]] = [
    dict(pixel_spacing=(0.14, 0.13), imager_pixel_spacing=(0.15, 0.15), calibration_type="GEOMETRY"),
    dict(imager_pixel_spacing=(0.15, 0.15), ermf=1.25, sid=1800.0),
    dict(imager_pixel_spacing=(0.15, 0.15), sid=1800.0, sod=1500.0, dse=1300.0, transfer_syntax="implicit"),
    dict(pixel_spacing=(0.15, 0.15), imager_pixel_spacing=(0.15, 0.15), photometric="MONOCHROME1"),
    dict(imager_pixel_spacing=None, pixel_spacing=(0.2, 0.2), modality="CR", transfer_syntax="big"),
    dict(patient_orientation=None, view_position="LL", transfer_syntax="implicit"),
]


def _pacs(orthanc: OrthancServer, **overrides: Any) -> Pacs:
    config = {"url": orthanc.dicomweb_url, "username": orthanc.username, "password": orthanc.password, **overrides}
    return Pacs(DicomwebConfig(**config))


@pytest.mark.parametrize("kwargs", HEADER_CASES, ids=[str(i) for i in range(len(HEADER_CASES))])
def test_wado_metadata_gives_the_file_header(orthanc: OrthancServer, kwargs: dict[str, Any]) -> None:
    image = synthetic.radiograph(**kwargs)
    with _pacs(orthanc) as pacs:
        pacs.store([image])
        from_pacs = pacs.read_header(image.StudyInstanceUID, image.SOPInstanceUID)  # series found by QIDO
        with_series = pacs.read_header(image.StudyInstanceUID, image.SOPInstanceUID, image.SeriesInstanceUID)
    from_file = read_header(image)
    assert from_pacs == from_file == with_series


def test_missing_instance_and_bad_uid(orthanc: OrthancServer) -> None:
    image = synthetic.radiograph()
    with _pacs(orthanc) as pacs:
        pacs.store([image])
        with pytest.raises(InstanceNotFound) as info:
            pacs.read_header(image.StudyInstanceUID, "1.2.3.4")
        assert info.value.uids["SOPInstanceUID"] == "1.2.3.4" and info.value.problem == "dicomweb-instance-not-found"
        with pytest.raises(InstanceNotFound):
            pacs.read_header(image.StudyInstanceUID, image.SOPInstanceUID, "1.2.3.4")
        with pytest.raises(InvalidAttribute, match=r"SOPInstanceUID \(0008,0018\)"):
            pacs.read_header(image.StudyInstanceUID, "1.2.03")


def test_pacs_down_and_refused_credentials(orthanc: OrthancServer) -> None:
    down = Pacs(DicomwebConfig(f"http://127.0.0.1:{free_port()}/dicom-web", timeout_s=2))
    with down, pytest.raises(PacsUnavailable) as info:
        down.read_header("1.2.3", "1.2.3.4")
    assert info.value.problem == "dicomweb-unavailable" and "did not answer" in str(info.value)
    refused = _pacs(orthanc, password="wrong")
    with refused, pytest.raises(PacsUnavailable) as info:
        refused.read_header("1.2.3", "1.2.3.4")
    assert info.value.status == 401


def test_stow_sr_and_figure_then_qido_finds_them(orthanc: OrthancServer) -> None:
    image = synthetic.radiograph(imager_pixel_spacing=(0.15, 0.15), rows=3200, columns=1200)
    payload = spine_payload(spacing_mm=0.15)
    with _pacs(orthanc) as pacs:
        pacs.store([image])
        header = pacs.read_header(image.StudyInstanceUID, image.SOPInstanceUID)
        payload["pa"]["pixel_spacing"] = list(header.pixel_spacing or ())
        result = register(payload)
        identity = StudyIdentity(study_instance_uid=header.study_instance_uid, patient_id=header.patient_id,
                                 patient_name=header.patient_name, accession_number=header.accession_number,
                                 study_date=header.study_date)  # fmt: skip
        source = SourceImage(header.sop_instance_uid, str(header.sop_class_uid), header.series_instance_uid,
                             header.study_instance_uid)  # fmt: skip
        job = uuid.uuid4()
        sr = build_sr(result, payload, job, identity, {"pa": source})
        sc = build_sc(render_figure(result, payload, dpi=40), job, identity)
        outcome = pacs.store([sr, sc])
        assert set(outcome.stored) == {sr.SOPInstanceUID, sc.SOPInstanceUID}
        again = pacs.store([sr])  # a resend is the same instance: stored again, not duplicated
        assert again.stored == (sr.SOPInstanceUID,)
        found = pacs.search_instances(image.StudyInstanceUID)
        uids = sorted(item["00080018"]["Value"][0] for item in found)
        assert uids == sorted([image.SOPInstanceUID, sr.SOPInstanceUID, sc.SOPInstanceUID])
        srs = pacs.search_instances(image.StudyInstanceUID, Modality="SR")
        assert [item["00080018"]["Value"][0] for item in srs] == [sr.SOPInstanceUID]
        stored_sr = pacs.client.retrieve_instance(image.StudyInstanceUID, sr.SeriesInstanceUID, sr.SOPInstanceUID)
    assert stored_sr.PatientID == "P-0001" and stored_sr.AccessionNumber == "ACC-42"


def test_resolve_by_reference(orthanc: OrthancServer) -> None:
    image = synthetic.radiograph(imager_pixel_spacing=(0.15, 0.15), ermf=1.25, sid=1800.0, rows=3200, columns=1200)
    payload = spine_payload(spacing_mm=0.12)
    payload["study"] = {"study_instance_uid": image.StudyInstanceUID, "pa_sop_instance_uid": image.SOPInstanceUID}
    with _pacs(orthanc) as pacs:
        pacs.store([image])
        assert views_to_fetch(payload) == {"pa": image.SOPInstanceUID}
        resolved, provenance = resolve_by_reference(payload, pacs)
        assert provenance is not None and provenance.pa is not None and provenance.pa.source == "dicomweb"
        assert resolved["pa"]["pixel_spacing"] == pytest.approx([0.12, 0.12])
        assert resolved["pa"]["patient_orientation"] == ["L", "F"]
        assert resolved["study"]["patient_id"] == "P-0001" and resolved["study"]["accession_number"] == "ACC-42"
        assert resolved["study"]["series_instance_uid"] == image.SeriesInstanceUID
        missing = {**payload, "study": {**payload["study"], "pa_sop_instance_uid": "1.2.3.4"}}
        with pytest.raises(InstanceNotFound):
            resolve_by_reference(missing, pacs)
    complete = {**payload, "pa": {**payload["pa"], "pixel_spacing": [0.12, 0.12], "patient_orientation": ["L", "F"]}}
    down = Pacs(DicomwebConfig(f"http://127.0.0.1:{free_port()}/dicom-web", timeout_s=2))
    with down:
        assert views_to_fetch(complete) == {}
        assert resolve_by_reference(complete, down) == (complete, None)  # nothing needed: the PACS is not asked
        with pytest.raises(PacsUnavailable):
            resolve_by_reference(payload, down)


def _raw_instance(orthanc: OrthancServer, image: Any) -> bytes:
    """The instance as the PACS serves it (WADO-RS, PS3.18 §10.4): the first part's bytes, unparsed."""
    url = (f"{orthanc.dicomweb_url}/studies/{image.StudyInstanceUID}/series/{image.SeriesInstanceUID}"
           f"/instances/{image.SOPInstanceUID}")  # fmt: skip
    answer = httpx.get(url, headers={"Accept": 'multipart/related; type="application/dicom"'}, auth=orthanc.auth())
    assert answer.status_code == 200, answer.text
    body = answer.content
    return body[body.index(b"\r\n\r\n") + 4 :]


def test_stow_sends_part10_files_which_the_pacs_serves_back_readable(orthanc: OrthancServer) -> None:
    """A dataset built in memory (no preamble, no group length) is stored as a Part 10 file (preamble and
    ``DICM``, PS3.10 §7.1; RFC 3240's application/dicom): the PACS serves it back as one, and the page's
    retrieve reads it. dicomweb-client alone sent it as the dataset stood, which Orthanc served back raw."""
    image = synthetic.radiograph()  # Explicit VR Little Endian, as most DX films
    assert getattr(image, "preamble", None) is None
    with _pacs(orthanc) as pacs:
        pacs.store([image])
        part = _raw_instance(orthanc, image)
        assert part[128:132] == b"DICM"
        retrieved = pacs.retrieve_explicit_le(image.StudyInstanceUID, image.SeriesInstanceUID, image.SOPInstanceUID)
    assert retrieved.SOPInstanceUID == image.SOPInstanceUID


def test_a_part_that_is_not_a_dicom_file_is_a_typed_error(orthanc: OrthancServer) -> None:
    """A PACS that serves an instance without preamble (stored so by another STOW-RS client) is a
    ``dicomweb-error`` naming the instance, not an unexpected error."""
    image = synthetic.radiograph()
    with _pacs(orthanc) as pacs:
        pacs.client.store_instances([image])  # as dicomweb-client writes a dataset built in memory
        assert _raw_instance(orthanc, image)[128:132] != b"DICM"
        with pytest.raises(DicomwebError) as caught:
            pacs.retrieve_explicit_le(image.StudyInstanceUID, image.SeriesInstanceUID, image.SOPInstanceUID)
    assert caught.value.problem == "dicomweb-error" and image.SOPInstanceUID in caught.value.message
