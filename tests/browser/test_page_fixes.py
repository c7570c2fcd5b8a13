"""The rough edges a new user hit, in Debian's Chromium against a real `spine serve`: the API key's
refusal at the top and a retry as the key is typed, the missing key listed before sending; a text
file named .dcm; the spacing in the service's words; FHIR and figure.dcm downloads; the Lenke
table's regional kyphosis; the 3D axes' labels; the strains table within an A4 page."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import httpx
import pytest
from page_fixtures import make_dicom, open_page, spacing_shown

from tests.conftest import spine_payload

pytestmark = pytest.mark.browser

A4_CSS_PX = round((210 - 2 * 12) / 25.4 * 96)  # A4 width less the report's 12 mm margins (style.css @page), CSS px


def _succeeded_job(url: str, key: str) -> str:
    headers = {"Authorization": f"Bearer {key}"}
    job_id = str(
        httpx.post(f"{url}/v1/jobs", json=spine_payload(curve_mm=40.0), headers=headers, timeout=30).json()["id"]
    )
    deadline = time.monotonic() + 90
    while (status := httpx.get(f"{url}/v1/jobs/{job_id}", headers=headers, timeout=10).json()["status"]) != "succeeded":
        assert status in ("queued", "running") and time.monotonic() < deadline, status
        time.sleep(0.3)
    return job_id


def test_key_refused_at_the_top_and_retried_as_typed(browser: Any, live_url: str, api_key: str) -> None:
    job_id = _succeeded_job(live_url, api_key)
    context, page, watch = open_page(browser, f"{live_url}/", None)
    page.wait_for_selector(
        "#missing li:has-text('Enter the API key at the top of the page')"
    )  # once /openapi.json is read
    page.goto(f"{live_url}/#/jobs/{job_id}")
    page.wait_for_selector("#key-problem:not([hidden])")
    box = page.locator("#key-problem").bounding_box()
    assert box is not None and box["y"] + box["height"] < 1000  # above the fold of a 1000 px window
    assert "An API key is needed" in (page.text_content("#key-problem") or "")
    page.fill("#api-key", api_key)  # no reload: typing the key retries
    page.wait_for_selector("#job-status[data-status=succeeded]", timeout=30_000)
    assert page.is_hidden("#key-problem")
    assert "Enter the API key" not in (page.text_content("#missing") or "")
    assert all("401" in e for e in watch.errors), watch.errors  # the refused reads only
    context.close()


def test_files_spacing_downloads_lenke_axes_and_print(
    browser: Any, live_url: str, api_key: str, tmp_path: Path
) -> None:
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    text = tmp_path / "notes.dcm"
    text.write_text("this is a text file\n" * 20)
    page.set_input_files("#pa-file", str(text))
    page.wait_for_selector("#pa-error:not([hidden])")
    assert "notes.dcm is not a DICOM file" in (page.text_content("#pa-error") or "")
    film = tmp_path / "pa.dcm"
    make_dicom(film, view="pa")  # Imager Pixel Spacing 0.4 mm, ERMF 1.2: the service reads 0.4 / 1.2 mm, calibrated
    page.set_input_files("#pa-file", str(film))
    page.wait_for_selector("#pa-header dd")
    header = page.text_content("#pa-header") or ""
    assert "Imager Pixel Spacing 0.4 mm / ERMF 1.2 = 0.3333 mm in the patient plane. Calibration: calibrated." in header
    # the page reads the film as the service does, and shows it to six significant digits
    assert page.input_value("#pa-spacing") == spacing_shown(0.4 / 1.2) == "0.333333"

    job_id = _succeeded_job(live_url, api_key)
    page.goto(f"{live_url}/#/jobs/{job_id}")
    page.wait_for_selector(f"#result[data-job-id='{job_id}']", timeout=30_000)
    with page.expect_download() as fhir:
        page.click("#download-fhir")
    assert json.loads(Path(fhir.value.path()).read_text())["resourceType"] == "Bundle"
    with page.expect_download() as figure:
        page.click("#download-figure-dcm")
    assert Path(figure.value.path()).read_bytes()[128:132] == b"DICM"
    job = httpx.get(f"{live_url}/v1/jobs/{job_id}", headers={"Authorization": f"Bearer {api_key}"}).json()
    lenke = job["result"]["measures"]["lenke"]
    rows = page.locator("#lenke tbody tr")
    for i, curve in enumerate(lenke["curves"]):
        span, key = ("T2–T5", "t2_t5") if curve["region"] == "proximal_thoracic" else ("T10–L2", "t10_l2")
        value, sd = lenke[f"{key}_kyphosis_deg"], lenke[f"{key}_kyphosis_sd_deg"]
        assert f"({span} {value:.1f}° ± {sd:.1f}°" in (rows.nth(i).locator("td").last.text_content() or "")
    page.wait_for_selector("#view3d[data-shown]")
    labels = page.locator("#view3d .axis-label")
    assert sorted(labels.all_text_contents()) == ["x left", "y posterior", "z head"]
    # the report's strains table within an A4 page's width
    page.set_viewport_size({"width": A4_CSS_PX, "height": 1000})
    page.emulate_media(media="print")
    widths = page.evaluate(
        "() => { const t = document.getElementById('strains'); return [t.scrollWidth, t.parentElement.clientWidth]; }"
    )
    assert widths[0] <= widths[1], widths
    assert not watch.errors, watch.errors
    context.close()
