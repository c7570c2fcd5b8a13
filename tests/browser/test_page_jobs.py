"""The page's other paths against a real `spine serve`: a PNG refused until its spacing is entered;
the trust marks rendered from a result that carries the engine's SD fields (a real result with SDs
added, served to the page by Playwright's routing: the rendering unit, whatever the engine on this
branch gives); the jobs list and its links; plain-word errors; accessibility (axe-core, WCAG 2.1
A/AA rules, and every control reached with Tab)."""

from __future__ import annotations

import copy
import csv
import json
from pathlib import Path
from typing import Any

import httpx
import pytest
from page_fixtures import (
    LEVELS,
    click_pa_midpoints,
    make_dicom,
    make_png,
    open_page,
    pa_points_payload,
    run_axe,
    run_job,
)

pytestmark = pytest.mark.browser


def _pa_payload() -> dict[str, Any]:
    return {**pa_points_payload(), "study": {"study_instance_uid": "1.2.826.0.1.3680043.8.498.77"}}


def test_a_png_is_refused_until_its_spacing_is_entered(
    browser: Any, live_url: str, api_key: str, tmp_path: Path
) -> None:
    png = tmp_path / "pa.png"
    make_png(png)
    context, page, watch = open_page(browser, live_url + "/", api_key, height=1100)
    page.set_input_files("#pa-file", str(png))
    page.wait_for_selector("#pa-header dd")
    assert page.input_value("#pa-spacing") == ""  # never guessed
    click_pa_midpoints(page, range(len(LEVELS)))
    assert "17 vertebrae" in (page.text_content("#pa-status") or "")
    missing = page.text_content("#missing") or ""
    assert "Enter the pixel spacing of the PA film" in missing and "PNG or JPEG does not carry it" in missing
    page.click("#submit")
    assert "pixel spacing" in (page.text_content("#problem") or "")
    assert not watch.posted_jobs()  # nothing sent
    page.fill("#pa-spacing", "0.4")
    assert "Ready to send" in (page.text_content("#missing") or "")
    with page.expect_response(lambda r: r.request.method == "POST" and r.url.endswith("/v1/jobs")) as posted:
        page.click("#submit")
    assert posted.value.status == 202
    sent = json.loads(posted.value.request.post_data or "{}")
    assert sent["pa"]["pixel_spacing"] == [0.4, 0.4] and sent["pa"]["units"] == "px" and "boundary" not in sent
    page.wait_for_selector("#job-status[data-status=succeeded]", timeout=90_000)
    context.close()


def test_trust_marks_and_sd_from_a_result_with_uncertainty(
    browser: Any, live_url: str, api_key: str, tmp_path: Path
) -> None:
    job = run_job(live_url, api_key, _pa_payload())
    fake = copy.deepcopy(job)
    fake["id"] = "00000000-0000-4000-8000-0000000000aa"
    m = fake["result"]["measures"]
    m["thoracic_kyphosis_t4_t12_sd_deg"] = 7.25
    m["lumbar_lordosis_l1_l5_sd_deg"] = 9.5
    for c in m["cobb"]:
        c["angle_sd_deg"] = 1.75
    for v in fake["result"]["vertebrae"]:
        v["axial_rotation_sd_deg"] = 4.0
        v["position_sd_mm"] = [1.0, 6.5, 0.5]
    fake["result"]["fit"]["unreliable"] = ["scale", "depth", "kyphosis", "lordosis", "axial_rotation", "twist"]
    context, page, _ = open_page(browser, live_url + "/", api_key)
    page.route(
        f"**/v1/jobs/{fake['id']}",
        lambda route: route.fulfill(status=200, content_type="application/json", body=json.dumps(fake)),
    )
    page.goto(f"{live_url}/#/jobs/{fake['id']}")
    page.wait_for_selector("#job-status[data-status=succeeded]")
    table = page.locator("#measures")
    kyphosis = table.locator("tr", has_text="Thoracic kyphosis T4–T12").text_content() or ""
    assert f"{m['thoracic_kyphosis_t4_t12_deg']:.1f}° ± 7.3°" in kyphosis and "model estimate" in kyphosis
    assert "± 9.5°" in (table.locator("tr", has_text="Lumbar lordosis").text_content() or "")
    major = next(c for c in m["cobb"] if c["major"])
    cobb_row = (
        table.locator("tr", has_text=f"Major curve {major['upper']}–{major['lower']}, Cobb angle").text_content() or ""
    )
    assert f"{major['angle_deg']:.1f}° ± 1.8°" in cobb_row and "model estimate" not in cobb_row  # measured
    rotation = table.locator("tr", has_text=f"Apex {major['apex']} axial rotation").text_content() or ""
    assert "± 4.0" in rotation and "model estimate" in rotation and "toward the" in rotation
    assert "model estimate" in (table.locator("tr", has_text="PA film scale").text_content() or "")
    strains_head = page.locator("#strains thead").text_content() or ""
    # sagittal bending strain u1 and sagittal bending (kyphosis), twist strain u3 and twist, axial rotation
    assert strains_head.count("model estimate") == 5
    assert "1.0 6.5 0.5" in (page.locator("#strains tbody tr").first.text_content() or "")
    with page.expect_download() as info:
        page.click("#download-csv")
    rows = Path(info.value.path()).read_text().splitlines()
    head = rows[0].split(",")
    first = dict(zip(head, rows[1].split(","), strict=True))
    assert first["axial_rotation_sd_deg"] == "4" and first["position_sd_y_mm"] == "6.5"
    assert set(first["model_estimate"].split(";")) == {
        "y_mm",
        "axial_rotation_deg",
        "u3_rad_per_mm",
        "twist_deg",
        "u1_rad_per_mm",
        "sagittal_bending_deg",
    }
    with page.expect_download() as info:
        page.click("#download-measures")
    measures_csv = Path(info.value.path()).read_text(encoding="utf-8-sig")
    kyphosis_row = next(
        r for r in csv.DictReader(measures_csv.splitlines()) if r["measure"] == "Thoracic kyphosis T4–T12"
    )
    assert float(kyphosis_row["sd"]) == 7.25 and kyphosis_row["model_estimate"] == "model estimate", kyphosis_row
    page.locator("#result").screenshot(path=str(tmp_path / "trust.png"))
    context.close()


def test_jobs_list_links_and_plain_errors(browser: Any, live_url: str, api_key: str, tmp_path: Path) -> None:
    job = run_job(live_url, api_key, _pa_payload())
    context, page, _ = open_page(browser, live_url + "/", api_key)
    page.click("a[href='#/jobs']")
    row = page.locator("#jobs-table tbody tr", has_text=job["id"][:8])
    row.wait_for()
    text = row.text_content() or ""
    major = next(c for c in job["result"]["measures"]["cobb"] if c["major"])
    assert "succeeded" in text and "1.2.826.0.1.3680043.8.498.77" in text and f"{major['angle_deg']:.1f}°" in text
    page.screenshot(path=str(tmp_path / "jobs.png"))
    spec = httpx.get(f"{live_url}/openapi.json", timeout=10).json()
    filters = [p["name"] for p in spec["paths"]["/v1/jobs"]["get"]["parameters"]]
    page.fill("#filter-study", "1.2.826.0.1.3680043.8.498.99")  # no job has this study
    with page.expect_request(lambda r: "/v1/jobs?" in r.url) as listed:
        page.click("#jobs-filter button")
    if "study_instance_uid" in filters:
        assert "study_instance_uid=1.2.826.0.1.3680043.8.498.99" in listed.value.url
        page.locator("#jobs-note", has_text="No job matches.").wait_for()
        assert page.locator("#jobs-table tbody tr").count() == 0
    else:
        assert "cannot filter by Study Instance UID" in (page.text_content("#jobs-note") or "")
    page.fill("#filter-study", "")
    page.click("#jobs-filter button")
    row.wait_for()
    row.locator("a").click()
    page.wait_for_selector("#job-status[data-status=succeeded]")
    assert page.get_attribute("#result", "data-job-id") == job["id"]
    assert "17 vertebrae on the PA film" in (page.text_content("#pa-status") or "")

    # a payload the service refuses: the problem in sentences, no JSON path code, no Python repr
    page.click("#tab-json")
    bad = _pa_payload()
    bad["pa"]["landmarks"][3]["level"] = "T13"
    page.fill("#json-text", json.dumps(bad))
    page.click("#use-json")
    with page.expect_response(lambda r: r.request.method == "POST" and r.url.endswith("/v1/jobs")) as posted:
        page.click("#submit")
    assert posted.value.status == 422
    page.locator("#problem", has_text="The service cannot use this input").wait_for()  # rendered after the answer
    problem = page.text_content("#problem") or ""
    assert (
        "The service cannot use this input" in problem
        and "PA film, landmark 4 (T13), level: It should be “T1”, “T2”" in problem
    ), problem
    assert "['" not in problem and "pa.landmarks[3]" not in problem
    context.close()


def test_accessibility_labels_keyboard_and_axe(browser: Any, live_url: str, api_key: str, tmp_path: Path) -> None:
    film = tmp_path / "pa.dcm"
    make_dicom(film)
    job = run_job(live_url, api_key, _pa_payload())
    context, page, _ = open_page(browser, live_url + "/", api_key)
    page.set_input_files("#pa-file", str(film))
    page.wait_for_selector("#pa-header dd")
    assert run_axe(page) == []
    # every visible control is reached with Tab from the top (tabs and radio groups: their selected
    # member, the others by arrow keys as ARIA's tab pattern and native radios do)
    controls = page.evaluate("""() => [...document.querySelectorAll(
            'a[href], button, input, select, textarea, summary, [tabindex="0"]')]
        .filter((e) => e.offsetParent !== null && !e.disabled && e.type !== 'radio' && e.tabIndex >= 0
                 && !e.closest('details:not([open]) > :not(summary)'))
        .map((e) => e.id || e.textContent.trim())""")
    page.focus("body")
    seen: set[str] = set()
    for _ in range(len(controls) + 40):
        page.keyboard.press("Tab")
        seen.add(page.evaluate("() => document.activeElement.id || document.activeElement.textContent.trim()"))
    missed = [c for c in controls if c not in seen]
    assert not missed, missed
    page.focus("#tab-image")
    page.keyboard.press("ArrowRight")
    assert page.evaluate("() => document.activeElement.id") == "tab-csv" and page.is_visible("#csv-text")
    page.keyboard.press("ArrowLeft")
    page.goto(f"{live_url}/#/jobs/{job['id']}")
    page.wait_for_selector("#job-status[data-status=succeeded]")
    assert run_axe(page) == []
    page.goto(f"{live_url}/#/jobs")
    page.wait_for_selector("#jobs-table tbody tr")
    assert run_axe(page) == []
    # the API key field is readable: dark text on a light field
    colours = page.evaluate(
        "() => { const s = getComputedStyle(document.getElementById('api-key')); return [s.color, s.backgroundColor]; }"
    )
    assert colours == ["rgb(27, 31, 36)", "rgb(255, 255, 255)"]
    context.close()
