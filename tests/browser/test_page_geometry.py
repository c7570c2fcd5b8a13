"""The films' acquisition geometry and the service's refusals on the films, in Debian's Chromium against a
real `spine serve`: the page names, before sending, exactly the SID, SOD, magnification and central-ray
geometry the service refuses (spine_engine/validation.py `_geometry_errors`, models.Acquisition's SOD <
SID), field by field and in the service's words, compared with the service's own 422 on the same
payloads; "Ignore header geometry" sends a film whose header has a wrong SID as an uncalibrated film; a
header whose SOD is not below its SID is named, not dropped; and a 422 naming landmarks rings them in
red on the film, and says so, until they are moved."""

from __future__ import annotations

import json
import random
import uuid
from pathlib import Path
from typing import Any

import httpx
import pytest
from page_fixtures import (
    FILM_SIZE,
    LEVELS,
    PA_SPACING,
    canvas_point,
    centreline,
    click_pa_midpoints,
    make_dicom,
    open_film,
    open_page,
    spacing_shown,
)

pytestmark = pytest.mark.browser

# The page's words for each acquisition field a refusal names (web/src/checks.ts GEOMETRY_FIELD_WORDS).
FIELD_WORDS = {
    "pa.acquisition.magnification": "magnification (ERMF, DICOM (0018,1114))",
    "pa.acquisition.distance_source_to_detector_mm": "SID (source to detector, DICOM (0018,1110))",
    "pa.acquisition.distance_source_to_patient_mm": "SOD (source to patient, DICOM (0018,1111))",
    "pa.acquisition": "SID and SOD (DICOM (0018,1110) and (0018,1111))",
    "pa.acquisition.image_size": (
        "image size (its centre taken as the central ray; Columns (0028,0011) × Rows (0028,0010))"
    ),
    "pa.acquisition.central_ray": "central ray",
}
IMAGE = [FILM_SIZE[0], FILM_SIZE[1]]
SID, SOD, ERMF = "distance_source_to_detector_mm", "distance_source_to_patient_mm", "magnification"
PERSPECTIVE = {"projection_model": "perspective"}


def _cases() -> list[dict[str, Any]]:
    """Acquisitions on each side of each rule (SOD ≥ 300 mm, SID/SOD ≤ 3.5, magnification 0.36–3.5, the
    ray within 45°, landmarks on the image, SOD < SID), then random ones."""
    cases: list[dict[str, Any]] = [
        {ERMF: 1.2, SID: 1800, SOD: 1500, "image_size": IMAGE, **PERSPECTIVE},  # the fixtures' DX film
        {SID: 150, "image_size": IMAGE, **PERSPECTIVE},  # spine 50 mm behind the source
        {SID: 499, **PERSPECTIVE},
        {SID: 500, **PERSPECTIVE},  # SOD assumed SID − 200: 299 and 300 mm
        {SOD: 299, **PERSPECTIVE},
        {SOD: 300, **PERSPECTIVE},
        {SID: 1000, SOD: 280},
        {SID: 600, ERMF: 2.5, **PERSPECTIVE},  # SOD 280, and 600 / 2.5 = 240 mm
        {SID: 1800, SOD: 1900},
        {SID: 1800, SOD: 1800},  # SOD not below the SID
        {ERMF: 0.35},
        {ERMF: 0.36},
        {ERMF: 3.5},
        {ERMF: 3.6},
        {ERMF: 5, SID: 1800, **PERSPECTIVE},
        {SID: 2000, SOD: 500},
        {SID: 1750, SOD: 500},  # SID/SOD 4 and 3.5
        {SOD: 1000, ERMF: 2, **PERSPECTIVE},
        {SID: 1800, SOD: 1500, "central_ray": [5000, 5000]},  # the ray 2.8 m from the spine
        {SID: 1800, SOD: 1500, "image_size": [20000, 20000]},  # the image centre 4 m from it
        {SID: 400, SOD: 350, "image_size": [560, 3000]},  # 576 mm from the farthest landmark at SID 400
        {SID: 1800, SOD: 1500, "image_size": [100, 100]},  # landmarks off the image
        {"image_size": IMAGE, **PERSPECTIVE},  # full-spine geometry assumed
    ]
    rng = random.Random(11)
    while len(cases) < 40:
        acq: dict[str, Any] = {}
        if rng.random() < 0.6:
            acq[SID] = round(rng.uniform(100, 2500), 1)
        if rng.random() < 0.5:
            acq[SOD] = round(rng.uniform(100, 2200), 1)
        if rng.random() < 0.4:
            acq[ERMF] = round(rng.uniform(1.01, 4.5), 2)
        if rng.random() < 0.5:
            acq["central_ray"] = [round(rng.uniform(-4000, 4000), 1), round(rng.uniform(-4000, 4000), 1)]
        elif rng.random() < 0.7:
            acq["image_size"] = [round(rng.uniform(300, 9000)), round(rng.uniform(850, 9000))]
        if not (SID in acq and SOD in acq):
            acq.update(PERSPECTIVE)  # a point source: the distances it lacks are assumed
        cases.append(acq)
    return cases


def _payload(acquisition: dict[str, Any]) -> dict[str, Any]:
    landmarks = [{"level": lv, "point": [round(centreline(i)[0], 1), round(centreline(i)[1], 1)]}
                 for i, lv in enumerate(LEVELS)]  # fmt: skip
    return {"pa": {"units": "px", "pixel_spacing": [PA_SPACING, PA_SPACING], "patient_orientation": ["L", "F"],
                   "landmarks": landmarks, "acquisition": acquisition}}  # fmt: skip


def _service_refusals(url: str, key: str, payload: dict[str, Any]) -> list[dict[str, Any]]:
    """The service's own refusals of the payload's acquisition. An unknown profile is added so that the
    payload is always refused (422) and no job is made: the service lists every error of the payload,
    the geometry's among them (validation.py `validate_payload`)."""
    probe = {**payload, "options": {"profile": "no-such-profile"}}
    answer = httpx.post(f"{url}/v1/jobs", json=probe, headers={"Authorization": f"Bearer {key}"}, timeout=30)
    assert answer.status_code == 422, answer.text
    return [e for e in answer.json()["errors"] if e["path"].startswith("pa.acquisition")]


def _missing(page: Any) -> list[str]:
    return [t.strip() for t in page.locator("#missing li").all_text_contents()]


def _reopen(page: Any, jobs: dict[str, dict[str, Any]], payload: dict[str, Any]) -> None:
    job: dict[str, Any] = {
        "id": str(uuid.uuid4()), "status": "failed", "created_at": "2026-01-01T00:00:00Z", "finished_at": None,
        "payload": payload, "result": None, "error": None, "study": None,
    }  # fmt: skip
    jobs[job["id"]] = job
    page.evaluate(f"() => location.hash = '#/jobs/{job['id']}'")
    page.wait_for_function(f"() => document.getElementById('job-status').textContent.startsWith('Job {job['id']} ')")
    page.wait_for_function("() => /17 PA landmarks/.test(document.getElementById('landmark-summary').textContent)")


def test_the_page_refuses_the_geometry_the_service_refuses_in_its_words(
    browser: Any, live_url: str, api_key: str
) -> None:
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    jobs: dict[str, dict[str, Any]] = {}
    page.route("**/v1/jobs/*", lambda route: route.fulfill(json=jobs[route.request.url.rsplit("/", 1)[1]])
               if route.request.url.rsplit("/", 1)[1] in jobs else route.continue_())  # fmt: skip
    refused_cases = 0
    for acquisition in _cases():
        payload = _payload(acquisition)
        refusals = _service_refusals(live_url, api_key, payload)
        _reopen(page, jobs, payload)
        said = [
            line for line in _missing(page) if any(line.startswith(f"PA film, {w}: ") for w in FIELD_WORDS.values())
        ]
        assert len(said) == len(refusals), (acquisition, refusals, said)
        for e in refusals:
            head = f"PA film, {FIELD_WORDS[e['path']]}: "
            if e["type"] == "value_error":  # models.Acquisition: the SOD must be below the SID
                want = f"the SOD ({acquisition[SOD]:g} mm) must be smaller than the SID ({acquisition[SID]:g} mm)"
            else:
                want = e["msg"]
            assert any(line.startswith(head + want) for line in said), (acquisition, e, said)
        assert page.get_attribute("#missing", "data-ready") == ("false" if refusals else "true"), (acquisition, said)
        refused_cases += bool(refusals)
    assert 10 <= refused_cases <= 30, refused_cases  # both verdicts well represented
    assert not watch.errors, watch.errors
    context.close()


def test_a_wrong_header_geometry_is_named_and_can_be_ignored(
    browser: Any, live_url: str, api_key: str, tmp_path: Path
) -> None:
    """A DX film whose header says SID 150 mm (no SOD, no ERMF): named before sending as the service
    names it, nothing sent; "Ignore header geometry" sends it without the header's geometry, and the
    service takes it. A header with its SOD above its SID is named too (it was dropped in silence), and a SID of 0
    is left out and said, as is a Pixel Spacing of 0\\0 beside a usable Imager Pixel Spacing."""
    detector = {"ImagerPixelSpacing": [PA_SPACING, PA_SPACING]}  # and no ERMF, SID or SOD but the study's below
    make_dicom(tmp_path / "sid150.dcm", view="pa", spacing=detector, study={"DistanceSourceToDetector": "150"})
    make_dicom(tmp_path / "sod-over-sid.dcm", view="pa", spacing=detector,
               study={"DistanceSourceToDetector": "1000", "DistanceSourceToPatient": "1200"})  # fmt: skip
    make_dicom(tmp_path / "sid0.dcm", view="pa", spacing={**detector, "PixelSpacing": [0.0, 0.0]},
               study={"DistanceSourceToDetector": "0", "DistanceSourceToPatient": "1600"})  # fmt: skip
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    open_film(page, "pa", tmp_path / "sid150.dcm")
    assert page.is_visible("#pa-ignore-geometry") and not page.is_checked("#pa-ignore-geometry")
    click_pa_midpoints(page, range(len(LEVELS)))
    page.wait_for_function("() => document.getElementById('payload-preview').textContent.includes('distance_source')")
    payload = json.loads(page.text_content("#payload-preview") or "{}")
    assert payload["pa"]["acquisition"][SID] == 150
    refusals = _service_refusals(live_url, api_key, payload)
    assert [e["path"] for e in refusals] == ["pa.acquisition.distance_source_to_detector_mm"], refusals
    line = f"PA film, {FIELD_WORDS['pa.acquisition.distance_source_to_detector_mm']}: {refusals[0]['msg']}"
    assert any(m.startswith(line) and "tick “Ignore header geometry” under the PA film" in m for m in _missing(page)), (
        line, _missing(page))  # fmt: skip
    page.click("#submit")
    assert not watch.posted_jobs()
    assert "SID 150 mm puts the spine -50 mm from the source" in (page.text_content("#problem") or "")

    page.check("#pa-ignore-geometry")
    assert page.get_attribute("#missing", "data-ready") == "true", _missing(page)
    assert "ignored: sent as an uncalibrated film" in (page.text_content("#pa-header") or "")
    with page.expect_response(lambda r: r.request.method == "POST" and r.url.endswith("/v1/jobs")) as posted:
        page.click("#submit")
    assert posted.value.status == 202, posted.value.text()
    sent = posted.value.request.post_data_json["pa"]["acquisition"]
    assert not {SID, SOD, ERMF} & set(sent), sent  # no geometry of the header's
    assert sent.get("image_size") == IMAGE  # the film's extent still goes

    open_film(page, "pa", tmp_path / "sod-over-sid.dcm")
    assert not page.is_checked("#pa-ignore-geometry")  # a new film: its own header
    assert "SOD 1200 mm" in (page.text_content("#pa-header") or "")
    click_pa_midpoints(page, range(3))
    said = [m for m in _missing(page) if m.startswith(f"PA film, {FIELD_WORDS['pa.acquisition']}: ")]
    assert said and said[0].startswith(
        f"PA film, {FIELD_WORDS['pa.acquisition']}: the SOD (1200 mm) must be smaller than the SID (1000 mm)"
    ), said
    page.check("#pa-ignore-geometry")
    assert not [m for m in _missing(page) if "SID" in m], _missing(page)

    # a writer's 0 for "not known": left out and said, as the service says it in the job's warnings
    open_film(page, "pa", tmp_path / "sid0.dcm")
    header = page.text_content("#pa-header") or ""
    assert "SID 0" not in header and "SID " not in header.split("SOD 1600 mm")[0], header
    assert "SOD 1600 mm. Distance Source to Detector (0018,1110) 0 is not a distance: left out." in header
    # and a spacing of 0\0: the Imager Pixel Spacing read, the other named (the service warns of it too)
    spacing = header.split("Spacing", 1)[1].split("Orientation", 1)[0]
    assert f"{PA_SPACING}" in spacing, header
    assert 'Pixel Spacing (0028,0030) "0.0\\0.0" is not two positive numbers: left out.' in spacing, header
    assert not watch.errors, watch.errors
    context.close()


def _red(page: Any, x: float, y: float) -> bool:
    """The canvas pixel at page point (x, y) is red (the refusal's ring), not the grey film or a yellow mark."""
    r, g, b = page.evaluate(
        """([x, y]) => {
            const c = document.getElementById('pa-canvas');
            const box = c.getBoundingClientRect();
            const k = c.width / box.width;
            const [px, py] = [Math.round((x - box.left) * k), Math.round((y - box.top) * k)];
            return Array.from(c.getContext('2d').getImageData(px, py, 1, 1).data.slice(0, 3));
        }""",
        [x, y],
    )  # fmt: skip
    return bool(r > 180 and g < 90 and b < 90)


def test_a_refusal_naming_landmarks_rings_them_on_the_film(
    browser: Any, live_url: str, api_key: str, tmp_path: Path
) -> None:
    """T1 and T2 820 px apart, 273 mm in the patient plane at the film's calibrated spacing (Imager Pixel Spacing
    0.4 mm / ERMF 1.2, as the service reads it): the page's own checks pass them, the service refuses T2's
    landmark (`pa.landmarks[1]`, implausible_distance); the page rings T2 in red and says so; moving T2
    takes the ring away."""
    make_dicom(tmp_path / "pa.dcm", view="pa")
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    open_film(page, "pa", tmp_path / "pa.dcm")
    t1, t2 = (280.0, 40.0), (281.0, 860.0)
    for point in (t1, t2):
        page.mouse.click(*canvas_point(page, "pa", *point))
    assert page.get_attribute("#missing", "data-ready") == "true", _missing(page)
    with page.expect_response(lambda r: r.request.method == "POST" and r.url.endswith("/v1/jobs")) as posted:
        page.click("#submit")
    assert posted.value.status == 422
    errors = posted.value.json()["errors"]
    assert [e["path"] for e in errors if e["path"].startswith("pa.landmarks")] == ["pa.landmarks[1]"], errors
    page.wait_for_selector("#refused-note")
    assert page.get_attribute("#pa-canvas", "data-refused") == "T2"
    note = page.text_content("#refused-note") or ""
    assert "ringed in red on the PA film (T2)" in note, note
    assert "T1 and T2 are 273 mm apart" in (page.text_content("#problem") or "")  # 820 px · 0.4 / 1.2 mm
    x, y = canvas_point(page, "pa", *t2)
    ring = 14  # CSS px: the ring's radius around a single point (web/src/film.ts, at least 14)
    assert all(_red(page, x + dx, y + dy) for dx, dy in ((ring, 0), (-ring, 0), (0, ring), (0, -ring)))
    assert not _red(page, *canvas_point(page, "pa", *t1))  # T1 is not ringed
    # T2 moved (selected by its level, Alt+arrow): the refusal no longer describes it
    page.select_option("#pa-level", "T2")
    page.focus("#pa-canvas")
    page.keyboard.press("Alt+ArrowUp")
    assert page.get_attribute("#pa-canvas", "data-refused") == ""
    assert not _red(page, x + ring, y)
    unexpected = [e for e in watch.errors if "status of 422" not in e]  # the refusal itself is logged
    assert not unexpected, unexpected
    context.close()


def _preview(page: Any) -> dict[str, Any]:
    view: dict[str, Any] = json.loads(page.text_content("#payload-preview") or "{}")["pa"]
    return view


def test_ignoring_a_calibrated_films_geometry_reads_its_spacing_without_it(
    browser: Any, live_url: str, api_key: str, tmp_path: Path
) -> None:
    """The fixtures' PA film (Imager Pixel Spacing 0.4 mm, ERMF 1.2, SID 1800, SOD 1500 mm) reads, as the service
    reads it, 0.4 / 1.2 mm calibrated, sent with its geometry; "Ignore header geometry" sends it as a header
    without ERMF, SID and SOD gives it (0.4 mm at the detector, no geometry, still a point source: a DX film,
    PS3.4 Annex B.5), the spacing field following; untick, and it is back. A FIDUCIAL film with SID and SOD keeps
    them (the box shown), and without them stays calibrated."""
    make_dicom(tmp_path / "ermf.dcm", view="pa")
    fiducial = {"PixelSpacing": [0.35, 0.35], "ImagerPixelSpacing": [0.4, 0.4]}
    make_dicom(tmp_path / "fiducial.dcm", view="pa", spacing=fiducial,
               study={"PixelSpacingCalibrationType": "FIDUCIAL", "DistanceSourceToDetector": "1800",
                      "DistanceSourceToPatient": "1575"})  # fmt: skip
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    open_film(page, "pa", tmp_path / "ermf.dcm")
    click_pa_midpoints(page, range(3))
    calibrated = PA_SPACING / 1.2  # the fixtures' ERMF (page_fixtures.make_dicom)
    assert page.input_value("#pa-spacing") == spacing_shown(calibrated)
    view = _preview(page)
    assert view["pixel_spacing"] == [calibrated, calibrated] and view["pixel_spacing_calibration"] == "calibrated"
    assert {k: view["acquisition"][k] for k in (ERMF, SID, SOD, "projection_model")} == {
        ERMF: 1.2, SID: 1800, SOD: 1500, "projection_model": "perspective"}  # fmt: skip

    page.check("#pa-ignore-geometry")
    assert page.input_value("#pa-spacing") == spacing_shown(PA_SPACING)
    view = _preview(page)
    assert view["pixel_spacing"] == [PA_SPACING, PA_SPACING] and view["pixel_spacing_calibration"] == "detector"
    assert not {SID, SOD, ERMF} & set(view["acquisition"]) and view["acquisition"]["projection_model"] == "perspective"
    header = page.text_content("#pa-header") or ""
    assert "Calibration: detector." in header and "ignored: sent as an uncalibrated film" in header, header
    page.uncheck("#pa-ignore-geometry")
    assert page.input_value("#pa-spacing") == spacing_shown(calibrated)
    assert _preview(page)["pixel_spacing_calibration"] == "calibrated"

    open_film(page, "pa", tmp_path / "fiducial.dcm")
    click_pa_midpoints(page, range(3))
    assert page.is_visible("#pa-ignore-geometry")  # calibrated, but its geometry goes with it
    view = _preview(page)
    assert view["pixel_spacing"] == [0.35, 0.35] and view["pixel_spacing_calibration"] == "calibrated"
    # header.py: no projection_model for calibrated mm without an ERMF; SID and SOD make it a point source
    assert view["acquisition"][SID] == 1800 and view["acquisition"][SOD] == 1575
    assert "projection_model" not in view["acquisition"]
    page.check("#pa-ignore-geometry")
    assert page.input_value("#pa-spacing") == "0.35"
    view = _preview(page)
    assert view["pixel_spacing_calibration"] == "calibrated" and not {SID, SOD, ERMF} & set(view["acquisition"])
    assert "ignored: sent as a film without geometry" in (page.text_content("#pa-header") or "")
    assert not watch.errors, watch.errors
    context.close()
