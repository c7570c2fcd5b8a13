"""The service with a PACS, end to end on real Orthanc, PostgreSQL and Redis (a `spine worker`
subprocess): a radiograph stored in Orthanc, a job posted with px landmarks and only the study's
UIDs succeeds with the header's spacing (the same 3D result as with the spacing typed in), what was
read is on the job, the SR and the figure land in the study (QIDO finds them), the job is found by
study, accession and patient (only the caller's), FHIR has the subject and date; a missing instance
fails the job with its own problem type; a PACS that stays down fails the job after its attempts, and
one that comes back on its port gets the handed-back jobs done. And the list filters alone, on the
embedded database."""

from __future__ import annotations

import io
import json
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import highdicom as hd
import numpy as np
import pydicom
import pytest
from fastapi.testclient import TestClient

from services.api.app import create_app
from services.core.config import Settings
from services.db.migrate import upgrade
from services.dicom.dicomweb import Pacs
from services.dicom.sr import CORNERSTONE_COBB_ANGLE
from services.dicom.uids import job_uids
from tests.conftest import Service, _purge_queue, make_key, spawned_service, spine_payload
from tests.interop_helpers import wait_until
from tools.dicom import synthetic
from tools.dicom.orthanc import free_port, orthanc_missing, start_orthanc, stop_orthanc
from tools.sr_adapter import adapter_missing, adapter_tool_state

from .conftest import OrthancServer, pacs_of

SPACING = 0.15
STORE_TIMEOUT_S = 60.0
"""The SR is stored by the worker's dicom queue right after the job succeeds (seconds); 60 s covers
building the SR on two loaded cores."""




def test_job_by_reference_end_to_end(pacs_service: Service, orthanc: OrthancServer) -> None:
    image = synthetic.radiograph(imager_pixel_spacing=(SPACING, SPACING), rows=3200, columns=1200,
                                 accession_number="ACC-E2E", patient_id="P-E2E")  # fmt: skip
    with pacs_of(orthanc) as pacs:
        pacs.store([image])
    by_reference = spine_payload(spacing_mm=SPACING)
    by_reference["study"] = {"study_instance_uid": image.StudyInstanceUID, "pa_sop_instance_uid": image.SOPInstanceUID}
    typed = spine_payload(spacing_mm=SPACING)
    typed["pa"]["pixel_spacing"] = [SPACING, SPACING]
    # what the DX header fills besides the spacing: a point-source film of the image's [columns, rows]
    typed["pa"]["acquisition"] = {"projection_model": "perspective", "image_size": [1200.0, 3200.0]}
    ref_job = pacs_service.submit(by_reference)
    typed_job = pacs_service.submit(typed)
    done = pacs_service.wait(ref_job["id"], timeout=120)
    assert done["status"] == "succeeded", done.get("error")
    other = pacs_service.wait(typed_job["id"], timeout=120)
    assert other["status"] == "succeeded"
    for a, b in zip(done["result"]["vertebrae"], other["result"]["vertebrae"], strict=True):
        assert a["position"] == pytest.approx(b["position"], abs=1e-9)
    assert done["result"]["measures"]["cobb"] == other["result"]["measures"]["cobb"]

    dicom = done["dicom"]
    read = {r["field"]: r for r in dicom["pa"]["read"]}
    assert read["pa.pixel_spacing"]["value"] == [SPACING, SPACING] and read["pa.pixel_spacing"]["used"]
    assert read["pa.pixel_spacing"]["attribute"] == "ImagerPixelSpacing (0018,1164)"
    assert read["pa.acquisition.projection_model"]["value"] == "perspective"
    assert dicom["pa"]["source"] == "dicomweb" and dicom["conflicts"] == []
    assert "pixel_spacing" not in done["payload"]["pa"]  # the payload stays as posted

    # found by study, accession and patient; the typed-in job has no study
    for key, value in (("study_instance_uid", image.StudyInstanceUID), ("accession_number", "ACC-E2E"),
                       ("patient_id", "P-E2E")):  # fmt: skip
        listed = pacs_service.client.get("/v1/jobs", params={key: value}).json()["jobs"]
        assert [j["id"] for j in listed] == [ref_job["id"]], key

    # the SR and the figure land in the study: once the job records the STOW-RS answered, as the SR alone can
    # be found while the same request still stores the figure
    deadline = time.monotonic() + STORE_TIMEOUT_S
    with pacs_of(orthanc) as pacs:
        while True:
            found = pacs.search_instances(image.StudyInstanceUID, Modality="SR")
            stored = any(attempt["ok"] for attempt in pacs_service.job(ref_job["id"])["dicom_stores"] or [])
            if (found and stored) or time.monotonic() > deadline:
                break
            time.sleep(0.5)
        assert len(found) == 1, f"no SR in the study after {STORE_TIMEOUT_S:g} s:\n{pacs_service.worker_log()[-3000:]}"
        assert len(pacs.search_instances(image.StudyInstanceUID)) == 3  # image, SR, figure
    stores = pacs_service.job(ref_job["id"])["dicom_stores"]
    assert stores[-1]["ok"] and len(stores[-1]["stored"]) == 2

    sr_response = pacs_service.client.get(f"/v1/jobs/{ref_job['id']}/sr.dcm")
    assert sr_response.status_code == 200 and sr_response.headers["content-type"] == "application/dicom"
    sr = pydicom.dcmread(io.BytesIO(sr_response.content))
    assert sr.SOPInstanceUID == found[0]["00080018"]["Value"][0]
    assert (sr.StudyInstanceUID, sr.PatientID, sr.AccessionNumber) == (image.StudyInstanceUID, "P-E2E", "ACC-E2E")
    figure = pacs_service.client.get(f"/v1/jobs/{ref_job['id']}/figure.dcm")
    assert figure.status_code == 200 and pydicom.dcmread(io.BytesIO(figure.content)).Modality == "OT"

    bundle = pacs_service.client.get(f"/v1/jobs/{ref_job['id']}/fhir").json()
    observation = bundle["entry"][0]["resource"]
    assert observation["subject"]["identifier"]["value"] == "P-E2E"
    assert observation["effectiveDateTime"] == "2026-11-30"


def test_missing_instance_fails_the_job(pacs_service: Service, orthanc: OrthancServer) -> None:
    image = synthetic.radiograph()
    with pacs_of(orthanc) as pacs:
        pacs.store([image])
    payload = spine_payload(spacing_mm=SPACING)
    payload["study"] = {"study_instance_uid": image.StudyInstanceUID, "pa_sop_instance_uid": "1.2.826.0.1.99"}
    job = pacs_service.wait(pacs_service.submit(payload)["id"], timeout=120)
    assert job["status"] == "failed"
    assert job["error"]["type"].endswith("/dicomweb-instance-not-found"), job["error"]
    assert "1.2.826.0.1.99" in job["error"]["detail"]


def test_a_control_character_in_the_headers_patient_id_fails_the_job_at_once(
    pacs_service: Service, orthanc: OrthancServer
) -> None:
    """A PatientID holding a line break (not DICOM text, PS3.5 §6.2) fails the job on its first run,
    the problem naming the attribute as the header has it (Orthanc cuts a value at a NUL, so a NUL
    does not come through it; ``test_dicom_header`` holds the reader's refusal of one)."""
    image = synthetic.radiograph(patient_id="P\nLF")
    with pacs_of(orthanc) as pacs:
        pacs.store([image])
    payload = spine_payload(spacing_mm=SPACING)
    payload["study"] = {"study_instance_uid": image.StudyInstanceUID, "pa_sop_instance_uid": image.SOPInstanceUID}
    job = pacs_service.wait(pacs_service.submit(payload)["id"], timeout=120)
    assert job["status"] == "failed" and job["attempts"] == 1, json.dumps(job.get("study"))
    assert job["error"]["type"].endswith("/dicom-invalid-attribute"), job["error"]
    assert "PatientID (0010,0020)" in job["error"]["detail"] and "control character" in job["error"]["detail"]


@pytest.fixture
def two_clients(tmp_path: Path) -> Iterator[tuple[TestClient, TestClient]]:
    settings = Settings(data_dir=tmp_path)
    upgrade(settings, quiet=True)
    with TestClient(create_app(settings)) as a, TestClient(create_app(settings)) as b:
        a.headers["Authorization"] = f"Bearer {make_key(settings, 'client-a')}"
        b.headers["Authorization"] = f"Bearer {make_key(settings, 'client-b')}"
        yield a, b


def _post(client: TestClient, study: dict[str, Any]) -> str:
    payload = spine_payload()
    payload["study"] = study
    response = client.post("/v1/jobs", json=payload)
    assert response.status_code == 202, response.text
    return str(response.json()["id"])


def test_list_filters_within_the_callers_jobs(two_clients: tuple[TestClient, TestClient]) -> None:
    a, b = two_clients
    mine = _post(a, {"study_instance_uid": "1.2.3", "accession_number": "A1", "patient_id": "P1"})
    _post(a, {"study_instance_uid": "1.2.4", "accession_number": "A2", "patient_id": "P2"})
    _post(b, {"study_instance_uid": "1.2.3", "accession_number": "A1", "patient_id": "P1"})  # another client's
    for key, value in (("study_instance_uid", "1.2.3"), ("accession_number", "A1"), ("patient_id", "P1")):
        listed = a.get("/v1/jobs", params={key: value}).json()["jobs"]
        assert [j["id"] for j in listed] == [mine], key
    assert a.get("/v1/jobs", params={"patient_id": "nobody"}).json()["jobs"] == []
    assert a.get("/v1/jobs", params={"accession_number": "X" * 17}).status_code == 422


def test_by_reference_needs_no_spacing_only_with_a_pacs(two_clients: tuple[TestClient, TestClient]) -> None:
    a, _ = two_clients
    payload = spine_payload(spacing_mm=SPACING)
    payload["study"] = {"study_instance_uid": "1.2.3", "pa_sop_instance_uid": "1.2.3.4"}
    response = a.post("/v1/jobs", json=payload)  # no SPINE_DICOMWEB_URL: the spacing is needed now
    assert response.status_code == 422 and "pa.pixel_spacing" in response.text


def test_pacs_down_retries_then_fails_the_job(
    tmp_path_factory: pytest.TempPathFactory, postgres_url: str, redis_url: str
) -> None:
    from tools.dicom.orthanc import free_port

    with spawned_service("dicom-down", tmp_path_factory.mktemp("dicom-down"), postgres_url=postgres_url,
                         redis_url=redis_url, SPINE_DICOMWEB_URL=f"http://127.0.0.1:{free_port()}/dicom-web",
                         SPINE_DICOMWEB_TIMEOUT_S="2", SPINE_MAX_ATTEMPTS="2") as service:  # fmt: skip
        payload = spine_payload(spacing_mm=SPACING)
        payload["study"] = {"study_instance_uid": "1.2.3", "pa_sop_instance_uid": "1.2.3.4"}
        job = service.wait(service.submit(payload)["id"], timeout=120)
    assert job["status"] == "failed"
    assert job["error"]["type"].endswith("/dicomweb-unavailable"), job["error"]
    assert job["attempts"] == 2  # handed back to the queue once (2 s backoff), failed on the last attempt
    assert "did not answer" in job["error"]["detail"]
    assert "back to the queue" in service.worker_log()


def test_a_pacs_that_comes_back_gets_the_job_done(
    tmp_path_factory: pytest.TempPathFactory, postgres_url: str, redis_url: str
) -> None:
    """By-reference jobs submitted while nothing listens on the PACS's port are handed back to the queue;
    the PACS then comes back on that very port, holding the referenced instance, and the jobs succeed
    with the header's spacing: none lost, each try counted (attempts = hand-backs + 1)."""
    reason = orthanc_missing()
    if reason:
        pytest.skip(reason)
    folder = tmp_path_factory.mktemp("pacs-back")
    image = synthetic.radiograph(imager_pixel_spacing=(SPACING, SPACING), rows=3200, columns=1200)
    proc, before = start_orthanc(folder)  # the PACS before its outage: it receives the image, then stops
    try:
        with pacs_of(before) as pacs:
            pacs.store([image])
    finally:
        stop_orthanc(proc)

    port = free_port()  # nothing listens there until the PACS comes back
    # 5 attempts: hand-backs after 2, 4, 8 and 16 s leave 30 s for the PACS to come back (it takes ~1 s)
    back: subprocess.Popen[bytes] | None = None
    with spawned_service("dicom-back", tmp_path_factory.mktemp("dicom-back"), postgres_url=postgres_url,
                         redis_url=redis_url, SPINE_DICOMWEB_URL=f"http://127.0.0.1:{port}/dicom-web",
                         SPINE_DICOMWEB_TIMEOUT_S="2", SPINE_DICOMWEB_USERNAME=before.username,
                         SPINE_DICOMWEB_PASSWORD=before.password, SPINE_MAX_ATTEMPTS="5") as service:  # fmt: skip
        try:
            payload = spine_payload(spacing_mm=SPACING)
            payload["study"] = {"study_instance_uid": image.StudyInstanceUID,
                                "pa_sop_instance_uid": image.SOPInstanceUID}  # fmt: skip
            job_ids = [service.submit(payload)["id"] for _ in range(2)]
            wait_until(lambda: all(f"job {j} back to the queue" in service.worker_log() for j in job_ids), 60,
                        "every job handed back to the queue while the PACS is down")  # fmt: skip
            assert all(service.job(j)["status"] in ("queued", "running") for j in job_ids)
            back, server = start_orthanc(folder, port=port)
            assert server.dicomweb_url == service.env["SPINE_DICOMWEB_URL"]
            done = [service.wait(j, timeout=120) for j in job_ids]
        finally:
            if back is not None:
                stop_orthanc(back)
    log = service.worker_log()
    for job in done:
        assert job["status"] == "succeeded", (job.get("error"), log[-3000:])
        handed_back = log.count(f"job {job['id']} back to the queue")
        assert handed_back >= 1 and job["attempts"] == handed_back + 1, (handed_back, job["attempts"])
        read = {r["field"]: r for r in job["dicom"]["pa"]["read"]}
        assert read["pa.pixel_spacing"]["value"] == [SPACING, SPACING] and read["pa.pixel_spacing"]["used"]
        assert job["dicom"]["pa"]["source"] == "dicomweb"
    assert done[0]["result"]["measures"]["cobb"] == done[1]["result"]["measures"]["cobb"]


def test_python_client_and_cli_get_the_sr(
    pacs_service: Service, orthanc: OrthancServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    from spine_client import SpineClient
    from spine_client import cli as spine_cli

    image = synthetic.radiograph(imager_pixel_spacing=(SPACING, SPACING), rows=3200, columns=1200,
                                 accession_number="ACC-CLI", patient_id="P-CLI")  # fmt: skip
    synthetic.write(image, tmp_path / "pa.dcm")
    csv = tmp_path / "landmarks.csv"
    payload = spine_payload(spacing_mm=SPACING)
    csv.write_text("".join(f"{lm['level']},{lm['point'][0]},{lm['point'][1]}\n" for lm in payload["pa"]["landmarks"]))
    transport = pacs_service.client._transport  # the API in process, through the client's own HTTP code
    key = pacs_service.api_key

    def client_for(args: Any) -> SpineClient:
        return SpineClient("http://testserver", key, transport=transport, retries=0)

    monkeypatch.setattr(spine_cli, "_client", client_for)
    with client_for(None) as client:
        base = {"boundary": payload["boundary"]}
        job, provenance = client.submit_dicom(csv, tmp_path / "pa.dcm", base=base)  # headers read here
        assert provenance["pa"]["sop_instance_uid"] == image.SOPInstanceUID
        done = client.wait(job.id, timeout=120)
        assert done.status == "succeeded", done
        listed = client.list(accession_number="ACC-CLI").jobs
        assert [str(j.id) for j in listed] == [str(job.id)]
        sr = pydicom.dcmread(io.BytesIO(client.sr(job.id)))
        assert sr.Modality == "SR" and sr.StudyInstanceUID == image.StudyInstanceUID and sr.PatientID == "P-CLI"
    out = tmp_path / "out-sr.dcm"
    assert spine_cli.main(["get", str(job.id), "--sr", str(out), "--figure-dcm", str(tmp_path / "fig.dcm")]) == 0
    assert pydicom.dcmread(out).SOPInstanceUID == sr.SOPInstanceUID
    assert pydicom.dcmread(tmp_path / "fig.dcm").Modality == "OT"
    assert "wrote" in capsys.readouterr().err


def test_sweep_publishes_an_overdue_stow_once_per_due_time(tmp_path: Path, redis_url: str) -> None:
    """A STOW-RS attempt whose message was never published (attempt 0) or was lost is published by the
    reconciler's sweep once overdue, as the next attempt; out of attempts, the job is left alone."""
    import uuid as uuid_module
    from datetime import timedelta

    import redis
    from sqlalchemy import update

    from services.core.jobqueue import STORE_DICOM, make_celery
    from services.db import jobs as jobs_repo
    from services.db.engine import session_scope
    from services.db.models import Job, utcnow
    from services.worker import dicom_tasks

    queue = f"spine-test-{uuid_module.uuid4().hex[:8]}"
    settings = Settings(data_dir=tmp_path, CELERY_BROKER_URL=redis_url, queue_name=queue,
                        dicomweb_url="http://127.0.0.1:9/dicom-web", dicomweb_store_results=True,
                        dicomweb_max_attempts=3)  # fmt: skip
    upgrade(settings, quiet=True)
    with session_scope(settings) as session:
        job, _ = jobs_repo.create_job(session, spine_payload())
    past = utcnow() - timedelta(seconds=1)
    attempt0 = {"attempt": 0, "attempted_at": past.isoformat(), "ok": False, "error": "not published"}
    with session_scope(settings) as session:
        session.execute(update(Job).where(Job.id == job.id).values(
            status="succeeded", dicom_stores=[attempt0], dicom_store_due_at=past))  # fmt: skip
    broker = redis.Redis.from_url(redis_url)
    app = make_celery(settings)
    try:
        assert dicom_tasks.sweep(settings, app) == 1
        assert broker.llen(settings.dicom_queue) == 1
        message = json.loads(broker.lindex(settings.dicom_queue, 0))  # type: ignore[arg-type]
        assert message["headers"]["task"] == STORE_DICOM and message["headers"]["argsrepr"] == f"['{job.id}', 1]"
        assert dicom_tasks.sweep(settings, app) == 0  # due again only SPINE_DICOMWEB_SWEEP_AFTER_S later
        with session_scope(settings) as session:
            due = session.get(Job, job.id).dicom_store_due_at  # type: ignore[union-attr]
            assert due is not None and due > utcnow() + timedelta(seconds=250)
            stores = [{**attempt0, "attempt": n} for n in (1, 2, 3)]
            session.execute(update(Job).where(Job.id == job.id).values(dicom_stores=stores, dicom_store_due_at=past))
        assert dicom_tasks.sweep(settings, app) == 0  # out of attempts: cleared, not published
        with session_scope(settings) as session:
            assert session.get(Job, job.id).dicom_store_due_at is None  # type: ignore[union-attr]
        assert broker.llen(settings.dicom_queue) == 1
    finally:
        _purge_queue(redis_url, queue)


ARTIFACTS = ("sr.dcm", "figure.dcm", "figure.png", "figure.svg", "fhir")


def _cobb_angle_deg(points: Any) -> float:
    """The angle between lines 1–2 and 3–4 of four points (the CobbAngle tool's two lines), degrees."""
    p = np.asarray(points, dtype=float)[:, :2]
    a, b = p[1] - p[0], p[3] - p[2]
    return float(np.degrees(np.arccos(abs(a @ b) / np.linalg.norm(a) / np.linalg.norm(b))))


def test_every_artifact_of_a_job_made_each_way(
    pacs_service: Service, orthanc: OrthancServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    """One film in the PACS, three jobs on it: JSON with the spacing typed (and the study's UIDs), the
    CLI's ``spine submit --pa-dicom`` (headers read on the client, sent as the job's ``dicom``), and
    the UIDs only (the service reads the header). Each keeps the film (``dicom``), every artifact
    answers 200, the SR and SC carry the film's patient and study, highdicom finds the Cobb angles
    as planar ROI groups on the film, and the Cornerstone adapters (Node) load them as CobbAngle
    annotations with the SR's values and lines that meet at that angle."""
    from spine_client import SpineClient
    from spine_client import cli as spine_cli

    reason = adapter_missing()
    if reason:
        pytest.skip(reason)
    film = synthetic.radiograph(imager_pixel_spacing=(SPACING, SPACING), rows=3200, columns=1200,
                                accession_number="ACC-WAYS", patient_id="P-WAYS",
                                extra={"TimezoneOffsetFromUTC": "+0100"})  # fmt: skip
    with pacs_of(orthanc) as pacs:
        pacs.store([film])
    synthetic.write(film, tmp_path / "pa.dcm")
    study = {"study_instance_uid": film.StudyInstanceUID, "pa_sop_instance_uid": film.SOPInstanceUID}

    typed = spine_payload(spacing_mm=SPACING)
    typed["pa"]["pixel_spacing"] = [SPACING, SPACING]
    typed["study"] = study
    by_reference = spine_payload(spacing_mm=SPACING)
    by_reference["study"] = study
    csv = tmp_path / "landmarks.csv"
    csv.write_text(
        "".join(f"{lm['level']},{lm['point'][0]},{lm['point'][1]}\n" for lm in by_reference["pa"]["landmarks"])
    )
    (tmp_path / "base.json").write_text(json.dumps({"boundary": by_reference["boundary"]}))
    transport, key = pacs_service.client._transport, pacs_service.api_key
    monkeypatch.setattr(spine_cli, "_client", lambda args: SpineClient("http://testserver", key, transport=transport,
                                                                       retries=0))  # fmt: skip
    assert spine_cli.main(["submit", "--pa-dicom", str(tmp_path / "pa.dcm"), "--base", str(tmp_path / "base.json"),
                           str(csv)]) == 0  # fmt: skip
    ids = {"json": pacs_service.submit(typed)["id"], "file": json.loads(capsys.readouterr().out)["id"],
           "pacs": pacs_service.submit(by_reference)["id"]}  # fmt: skip
    jobs = dict(zip(ids, pacs_service.wait_all(list(ids.values()), timeout=180), strict=True))

    for way, job in jobs.items():
        assert job["status"] == "succeeded", (way, job.get("error"))
        assert job["dicom"]["pa"]["sop_instance_uid"] == film.SOPInstanceUID, way  # the film is kept
        assert job["dicom"]["pa"]["source"] == ("file" if way == "file" else "dicomweb")
        assert job["study"]["patient_id"] == "P-WAYS", way
        answers = {name: pacs_service.client.get(f"/v1/jobs/{job['id']}/{name}") for name in ARTIFACTS}
        assert {name: r.status_code for name, r in answers.items()} == dict.fromkeys(ARTIFACTS, 200), way

        sr_path = tmp_path / f"{way}-sr.dcm"
        sr_path.write_bytes(answers["sr.dcm"].content)
        sr, sc = pydicom.dcmread(sr_path), pydicom.dcmread(io.BytesIO(answers["figure.dcm"].content))
        for made in (sr, sc):  # Patient and General Study Modules as the film's (PS3.3 §C.7.1.1, §C.7.2.1),
            # and the film's zone, which dates the study's date and time copied (PS3.3 §C.12.1.1.8)
            for keyword in ("PatientID", "PatientName", "PatientBirthDate", "PatientSex", "StudyInstanceUID",
                            "StudyDate", "StudyTime", "StudyID", "AccessionNumber",
                            "TimezoneOffsetFromUTC"):  # fmt: skip
                assert made.get(keyword) == film.get(keyword), (way, made.Modality, keyword)
        # the study's date and time (2026-11-30, 10:15:00, synthetic.radiograph) in the film's zone
        observations = [e["resource"] for e in answers["fhir"].json()["entry"]]
        assert {o["effectiveDateTime"] for o in observations} == {"2026-11-30T10:15:00+01:00"}, way
        assert "Laterality" not in sc and "Laterality" not in sr

        curves = job["result"]["measures"]["cobb"]
        assert curves, "the C-curve payload has a Cobb angle"
        planar = hd.sr.srread(sr_path).content.get_planar_roi_measurement_groups()
        groups = [g for g in planar if g.tracking_identifier == CORNERSTONE_COBB_ANGLE]
        assert len(groups) == len(curves), way
        assert len(planar) - len(groups) == 17, way  # the 17 landmarks as SCOORDs on the film
        for group in groups:
            ref = group.roi.ContentSequence[0].ReferencedSOPSequence[0]
            assert (ref.ReferencedSOPInstanceUID, ref.ReferencedSOPClassUID) == (film.SOPInstanceUID, film.SOPClassUID)

        state = adapter_tool_state(sr_path, film.SOPInstanceUID, (SPACING, SPACING))
        assert len(state["CobbAngle"]) == len(curves), (way, state["tools"])
        for read, curve in zip(state["CobbAngle"], curves, strict=True):
            # the NUM's value (DS: 16 characters, PS3.5 §6.2) and the lines in mm (FL coordinates: float32)
            assert read["angle"] == pytest.approx(curve["angle_deg"], abs=1e-9), way
            assert _cobb_angle_deg(read["points"]) == pytest.approx(curve["angle_deg"], abs=1e-3), way
            assert read["referencedImageId"].endswith(film.SOPInstanceUID)


def test_a_dicom_block_completes_the_payload_only_as_a_header_does(
    two_clients: tuple[TestClient, TestClient], tmp_path: Path
) -> None:
    """``POST /v1/jobs`` with the ``dicom`` block the CLI reads from a file: kept on the job, its used
    reads completing the payload (the px landmarks get the film's spacing); a block that claims the
    PACS's reads, fills another field or holds a value DICOM cannot carry is a 422 naming it."""
    from spine_client.dicom_input import payload_from_dicom

    a, _ = two_clients
    film = synthetic.radiograph(imager_pixel_spacing=(SPACING, SPACING), rows=3200, columns=1200)  # the landmarks on it
    synthetic.write(film, tmp_path / "pa.dcm")
    csv = tmp_path / "landmarks.csv"
    points = spine_payload(spacing_mm=SPACING)["pa"]["landmarks"]
    csv.write_text("".join(f"{lm['level']},{lm['point'][0]},{lm['point'][1]}\n" for lm in points))
    payload, dicom = payload_from_dicom(csv, tmp_path / "pa.dcm")
    del payload["pa"]["pixel_spacing"]  # the block's read gives it back
    answer = a.post("/v1/jobs", json={**payload, "dicom": dicom})
    assert answer.status_code == 202, answer.text
    job = a.get(f"/v1/jobs/{answer.json()['id']}").json()
    assert job["dicom"] == dicom and "pixel_spacing" not in job["payload"]["pa"]
    assert job["study"]["patient_id"] == "P-0001"

    def refused(block: dict[str, Any]) -> list[str]:
        response = a.post("/v1/jobs", json={**payload, "dicom": block})
        assert response.status_code == 422, response.text
        return [".".join(map(str, e["loc"])) for e in response.json()["errors"]]

    pacs_claim = json.loads(json.dumps(dicom))
    pacs_claim["pa"]["source"] = "dicomweb"
    assert refused(pacs_claim) == ["dicom.pa.source"]
    landmarks = json.loads(json.dumps(dicom))
    landmarks["pa"]["read"][0]["field"] = "pa.landmarks"
    assert refused(landmarks) == ["dicom.pa.read.0.field"]
    sex = json.loads(json.dumps(dicom))
    index = next(i for i, r in enumerate(sex["study"]) if r["field"] == "study.patient_sex")
    sex["study"][index]["value"] = "female"
    assert refused(sex) == [f"dicom.study.{index}.value"]
    assert refused({"pa": "nothing"}) == ["dicom.pa"]
    # a film date-time is as the header reader writes it: a time without its zone is no FHIR dateTime
    for value in ("2024-05-06T10:11:12", "06/05/2024", "2024-13-01"):
        when = json.loads(json.dumps(dicom))
        when["pa"]["film_datetime"] = value
        assert refused(when) == ["dicom.pa.film_datetime"], value
        detail = a.post("/v1/jobs", json={**payload, "dicom": when}).json()["errors"][0]["msg"]
        assert "film's date must be a date (YYYY-MM-DD) or a date and time with its UTC offset" in detail


NOT_STORED = "dicom-no-patient-identity"
"""The ``problem_type`` of the STOW-RS attempt of a job whose results are not stored for want of the
patient's identity (``services.dicom.results.NoPatientIdentity``)."""


def _complete_payload() -> dict[str, Any]:
    """px landmarks with all the PA's header would give typed in (spacing and orientation): a job that
    needs no header, whose header read (when its study names the film) may fail without failing it."""
    payload = spine_payload(spacing_mm=SPACING)
    payload["pa"].update(pixel_spacing=[SPACING, SPACING], patient_orientation=["L", "F"])
    return payload


def _first_store(service: Service, job_id: str) -> list[dict[str, Any]]:
    """The job's ``dicom_stores`` once its first STOW-RS attempt is recorded (within ``STORE_TIMEOUT_S``)."""
    wait_until(lambda: bool(service.job(job_id)["dicom_stores"]), STORE_TIMEOUT_S,
                f"a STOW-RS attempt on job {job_id}:\n{service.worker_log()[-3000:]}")  # fmt: skip
    return list(service.job(job_id)["dicom_stores"])


def _held_anywhere(pacs: Pacs, sop_instance_uid: str) -> list[dict[str, Any]]:
    """QIDO-RS of every study's instances with this SOP Instance UID (PS3.18 §10.6: /instances)."""
    return list(pacs.client.search_for_instances(search_filters={"SOPInstanceUID": sop_instance_uid}))


def _assert_not_stored(service: Service, orthanc: OrthancServer, job_id: str, reason: str) -> None:
    """The job succeeded, its one STOW-RS attempt says why nothing was stored, is not retried (no next
    attempt; still one attempt after twice the first retry's delay, SPINE_DICOMWEB_RETRY_BASE_S 2 s),
    and the PACS holds neither its SR nor its figure, in any study."""
    stores = _first_store(service, job_id)
    time.sleep(2 * service.settings.dicomweb_retry_base_s)  # a retry would be recorded by now
    job = service.job(job_id)
    assert job["status"] == "succeeded" and job["error"] is None
    assert job["dicom_stores"] == stores and len(stores) == 1, stores
    attempt = stores[0]
    assert (attempt["ok"], attempt["stored"], attempt["problem_type"], attempt["next_attempt_at"]) == (
        False, [], NOT_STORED, None), attempt  # fmt: skip
    assert reason in attempt["error"], attempt["error"]
    uids = job_uids(job_id)
    with pacs_of(orthanc) as pacs:
        for role in ("sr", "sc"):
            assert _held_anywhere(pacs, uids[role]) == [], role
        assert pacs.search_instances(uids["study"]) == []


def test_a_job_without_a_study_is_not_stored_in_the_pacs(pacs_service: Service, orthanc: OrthancServer) -> None:
    """A job whose payload names no study (a CSV or the web page's job, its geometry typed): its results have
    no patient's study to go into, and are not stored (they made a new, patient-less study)."""
    payload = _complete_payload()
    job = pacs_service.wait(pacs_service.submit(payload)["id"], timeout=120)
    assert job["status"] == "succeeded" and job["study"] is None, job.get("error")
    _assert_not_stored(pacs_service, orthanc, job["id"], "the job has no study")


def test_a_study_without_a_patient_id_is_not_stored_in_the_pacs(pacs_service: Service, orthanc: OrthancServer) -> None:
    """A by-reference job whose header read failed (its SOP Instance UID is not in the PACS) but whose
    payload is complete (spacing and orientation typed): it succeeds without a header (``dicom`` null), its study has no
    Patient ID, and its results are not stored in the patient's study (they went in with an empty
    Patient ID, Name, Accession Number and Study Date): the film's study keeps the film only."""
    film = synthetic.radiograph(imager_pixel_spacing=(SPACING, SPACING), rows=3200, columns=1200,
                                accession_number="ACC-NOID", patient_id="P-NOID")  # fmt: skip
    with pacs_of(orthanc) as pacs:
        pacs.store([film])
    payload = _complete_payload()
    payload["study"] = {"study_instance_uid": film.StudyInstanceUID, "pa_sop_instance_uid": "1.2.826.0.1.98"}
    job = pacs_service.wait(pacs_service.submit(payload)["id"], timeout=120)
    assert job["status"] == "succeeded" and job["dicom"] is None, job.get("error")
    assert "patient_id" not in job["study"]
    _assert_not_stored(pacs_service, orthanc, job["id"], "has no Patient ID")
    with pacs_of(orthanc) as pacs:
        assert len(pacs.search_instances(film.StudyInstanceUID)) == 1  # the film alone


def test_a_study_with_the_payloads_patient_id_is_stored(pacs_service: Service, orthanc: OrthancServer) -> None:
    """The same job with the patient's ID typed in its study (no header read either): its SR and figure
    are stored in the study, with that Patient ID."""
    film = synthetic.radiograph(imager_pixel_spacing=(SPACING, SPACING), rows=3200, columns=1200,
                                accession_number="ACC-TYPED", patient_id="P-TYPED")  # fmt: skip
    with pacs_of(orthanc) as pacs:
        pacs.store([film])
    payload = _complete_payload()
    payload["study"] = {"study_instance_uid": film.StudyInstanceUID, "pa_sop_instance_uid": "1.2.826.0.1.97",
                        "patient_id": "P-TYPED"}  # fmt: skip
    job = pacs_service.wait(pacs_service.submit(payload)["id"], timeout=120)
    assert job["status"] == "succeeded" and job["dicom"] is None, job.get("error")
    stores = _first_store(pacs_service, job["id"])
    assert stores[-1]["ok"] and len(stores[-1]["stored"]) == 2, stores
    uids = job_uids(job["id"])
    with pacs_of(orthanc) as pacs:
        assert len(pacs.search_instances(film.StudyInstanceUID)) == 3  # film, SR, figure
        for role in ("sr", "sc"):
            stored = pacs.retrieve_explicit_le(film.StudyInstanceUID, uids[f"{role}-series"], uids[role])
            assert (stored.StudyInstanceUID, stored.PatientID) == (film.StudyInstanceUID, "P-TYPED"), role
