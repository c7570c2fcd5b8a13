"""The page with a PACS, end to end: a real Orthanc (Debian's, with its DICOMweb plug-in) and a
`spine serve` pointed at it; a synthetic DX film stored in Orthanc is opened by its Study Instance UID
("Open from the PACS"), used as the PA film (its header's spacing shown as for a file from disk),
landmarked by 17 clicks and sent; the job succeeds and its payload names the study and the image by
UID. Reopened from its URL, the job shows its film again, fetched from the PACS by those UIDs; once
the image is deleted from the PACS, the blank frame says why. An unknown study is said in plain
words; a service without a PACS shows no such control."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pydicom
import pytest
from page_fixtures import (
    LEVELS,
    PA_SPACING,
    Serve,
    canvas_grey,
    canvas_point,
    centreline,
    make_dicom,
    open_page,
    pa_corners,
    run_axe,
    spacing_shown,
    start_serve,
    stop_serve,
)
from pydicom.uid import generate_uid

from services.core.config import DicomwebConfig
from services.dicom.dicomweb import Pacs
from tests.conftest import spine_payload
from tools.dicom.orthanc import OrthancServer

pytestmark = pytest.mark.browser


@pytest.fixture(scope="module")
def pacs_serve(tmp_path_factory: pytest.TempPathFactory, orthanc: OrthancServer) -> Iterator[Serve]:
    serve = start_serve(tmp_path_factory.mktemp("page-pacs-service"), SPINE_DICOMWEB_URL=orthanc.dicomweb_url,
                        SPINE_DICOMWEB_USERNAME=orthanc.username, SPINE_DICOMWEB_PASSWORD=orthanc.password)  # fmt: skip
    try:
        yield serve
    finally:
        stop_serve(serve.proc)


def _store_film(orthanc: OrthancServer, tmp_path: Path) -> pydicom.Dataset:
    path = tmp_path / "pa.dcm"
    make_dicom(path, view="pa")
    film = pydicom.dcmread(path)
    film.StudyInstanceUID, film.SeriesInstanceUID = generate_uid(), generate_uid()
    film.SeriesDescription = "Whole spine PA"
    with Pacs(DicomwebConfig(orthanc.dicomweb_url, orthanc.username, orthanc.password)) as pacs:
        pacs.store([film])
    return film


def test_open_a_film_from_the_pacs_landmark_it_and_send(
    browser: Any, pacs_serve: Serve, orthanc: OrthancServer, tmp_path: Path
) -> None:
    film = _store_film(orthanc, tmp_path)
    context, page, watch = open_page(browser, pacs_serve.url + "/", pacs_serve.api_key, height=1100)
    page.wait_for_selector("#pacs-open:not([hidden])")

    # -- an unknown study: the service's problem detail, in words
    page.fill("#pacs-study", "1.2.826.0.1.3680043.8.498.404")
    page.press("#pacs-study", "Enter")  # the form submits by keyboard
    page.wait_for_selector("#pacs-problem:not([hidden])")
    assert "has no instance of study 1.2.826.0.1.3680043.8.498.404" in (page.text_content("#pacs-problem") or "")

    # -- the study: its image listed, used as the PA film
    page.fill("#pacs-study", film.StudyInstanceUID)
    page.click("#pacs-list")
    page.wait_for_selector("#pacs-images tbody tr")
    row = page.text_content("#pacs-images tbody tr") or ""
    for text in ("DX", "PA", "Whole spine PA", "560 × 900"):
        assert text in row, (text, row)
    assert page.is_hidden("#pacs-problem")
    assert run_axe(page) == []
    page.click("#pacs-pa-0")
    page.wait_for_selector("#pa-header dd")
    header = page.text_content("#pa-header") or ""
    for text in ("DOE JANE", "PAT-0042", "Imager Pixel Spacing 0.4 mm", film.StudyInstanceUID):
        assert text in header, (text, header)
    spacing = PA_SPACING / 1.2  # the fixtures' film: Imager Pixel Spacing / its ERMF, as the service reads it
    assert page.input_value("#pa-spacing") == spacing_shown(spacing)
    assert "from the PACS as the PA film" in (page.text_content("#pacs-note") or "")

    # -- 17 top endplate midpoints, sent
    for i in range(len(LEVELS)):
        col, row_px, _ = centreline(i)
        page.mouse.click(*canvas_point(page, "pa", col, row_px))
    assert "17 vertebrae" in (page.text_content("#pa-status") or "")
    with page.expect_response(lambda r: r.request.method == "POST" and r.url.endswith("/v1/jobs")) as posted:
        page.click("#submit")
    assert posted.value.status == 202, posted.value.text()
    job_id = json.loads(posted.value.text())["id"]
    page.wait_for_selector("#job-status[data-status=succeeded]", timeout=90_000)
    job = httpx.get(f"{pacs_serve.url}/v1/jobs/{job_id}", headers={"Authorization": f"Bearer {pacs_serve.api_key}"},
                    timeout=10).json()  # fmt: skip
    study = job["payload"]["study"]
    assert study["study_instance_uid"] == film.StudyInstanceUID
    assert study["pa_sop_instance_uid"] == film.SOPInstanceUID
    assert job["payload"]["pa"]["pixel_spacing"] == [spacing, spacing]

    # -- reopened from its URL in a new page: the film fetched again from the PACS under the landmarks
    page.goto(f"{pacs_serve.url}/#/jobs/{job_id}")
    page.reload()
    page.wait_for_selector("#job-status[data-status=succeeded]", timeout=30_000)
    page.wait_for_selector("#pa-header dd:has-text('DOE JANE')", timeout=30_000)
    assert film.StudyInstanceUID in (page.text_content("#pa-header") or "")
    assert page.get_attribute("#pa-canvas", "data-blank") == ""
    body = pa_corners()[8]
    centre = ((body[0][0] + body[3][0]) / 2, (body[0][1] + body[3][1]) / 2)
    assert canvas_grey(page, "pa", *centre) > canvas_grey(page, "pa", 20, 20) + 80  # the film's bone, not a blank frame
    assert "17 vertebrae" in (page.text_content("#pa-status") or "")
    assert (
        json.loads(page.text_content("#payload-preview") or "{}")["pa"]["landmarks"]
        == job["payload"]["pa"]["landmarks"]
    )
    page.wait_for_selector("#pa-caption:has-text('over the film')")  # the result's PA projection over it too

    # -- the image gone from the PACS: the frame says why it is blank
    found = httpx.post(
        f"{orthanc.url}/tools/lookup", content=film.SOPInstanceUID, auth=orthanc.auth(), timeout=10
    ).json()
    httpx.delete(f"{orthanc.url}{found[0]['Path']}", auth=orthanc.auth(), timeout=10).raise_for_status()
    page.goto(f"{pacs_serve.url}/#/jobs")
    page.goto(f"{pacs_serve.url}/#/jobs/{job_id}")
    page.reload()
    page.wait_for_selector("#pa-canvas[data-blank*='could not be fetched again']", timeout=30_000)
    why = page.get_attribute("#pa-canvas", "data-blank") or ""
    assert film.SOPInstanceUID in why and "blank frame" in why, why
    assert why in (page.text_content("#pa-header") or "")
    # the one console error is Chromium's note of the unknown study's 404, which the page said in words
    assert [
        e for e in watch.errors if "status of 404" not in e
    ] == [] and watch.foreign == []  # 404s: unknown study, image gone
    context.close()


def test_no_pacs_no_control(browser: Any, live_url: str, api_key: str) -> None:
    context, page, _ = open_page(browser, live_url + "/", api_key)
    page.wait_for_timeout(800)  # the key's check of /v1/pacs is debounced
    assert page.is_hidden("#pacs-open")
    context.close()


def test_a_reopened_jobs_landmarks_in_mm_stay_on_the_blank_frame_not_over_the_pacs_film(
    browser: Any, pacs_serve: Serve, orthanc: OrthancServer, tmp_path: Path
) -> None:
    """A job whose payload names its PA image in the PACS but gives its landmarks in mm without a pixel
    spacing (as the Python client may send them): reopened, the film is not fetched and put under the
    landmarks as if their mm were its pixels; they stay on the blank frame, which says why, and are sent
    again in mm as they were."""
    film = _store_film(orthanc, tmp_path)
    payload = spine_payload(curve_mm=30.0)  # mm, no pixel spacing
    del payload["boundary"]
    payload["study"] = {"study_instance_uid": film.StudyInstanceUID, "pa_sop_instance_uid": film.SOPInstanceUID}
    headers = {"Authorization": f"Bearer {pacs_serve.api_key}"}
    answer = httpx.post(f"{pacs_serve.url}/v1/jobs", json=payload, headers=headers, timeout=30)
    assert answer.status_code == 202, answer.text
    stored = httpx.get(f"{pacs_serve.url}/v1/jobs/{answer.json()['id']}", headers=headers, timeout=10).json()
    context, page, watch = open_page(browser, pacs_serve.url + "/", pacs_serve.api_key)
    page.evaluate(f"() => location.hash = '#/jobs/{answer.json()['id']}'")
    page.wait_for_selector("#pa-canvas[data-blank]:not([data-blank^='Fetching'])", timeout=30_000)
    page.wait_for_load_state("networkidle")  # the PACS asked, and its film fetched if the page fetches it
    sent = json.loads(page.text_content("#payload-preview") or "{}")["pa"]
    assert sent.get("units", "mm") == "mm" and sent["landmarks"] == stored["payload"]["pa"]["landmarks"], sent
    assert "17 vertebrae" in (page.text_content("#pa-status") or "")
    assert "in mm without a pixel spacing" in (page.get_attribute("#pa-canvas", "data-blank") or "")
    assert "in mm without a pixel spacing" in (page.text_content("#pa-header") or "")
    assert not watch.errors, watch.errors
    context.close()
