"""What is sent is what is on the page, in Debian's Chromium against a real `spine serve`: a second
film starts without the first film's landmarks; a reopened job resets both panels and the draft to
its payload and is sent again with its `study` and `options`; films of two patients (or studies)
are not sent, and a film opened in the other view's panel is warned about; a failed CSV import
leaves nothing of the previous CSV to send; choosing a level selects it for Delete; the page refuses
corners and pedicles as the service does, in its words; a refusal's apostrophes stay apostrophes; a
damaged DICOM file's parser message; the focus after Reconstruct; an unchanged draft sent twice is
one job (Idempotency-Key)."""

from __future__ import annotations

import itertools
import random
import uuid
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import httpx
import pytest
from page_fixtures import (
    LEVELS,
    canvas_point,
    centreline,
    click_pa_midpoints,
    lateral_points,
    make_dicom,
    open_film,
    open_page,
    pa_corners,
    payload_preview,
    run_job,
)
from sqlalchemy import select

from services.core.config import Settings
from services.db.engine import session_factory
from services.db.models import Job
from tests.conftest import spine_payload

pytestmark = pytest.mark.browser


def _midpoints(page: Any, n: int) -> None:
    click_pa_midpoints(page, range(n))


def _wait_final(page: Any) -> None:
    page.wait_for_function(
        "() => ['succeeded', 'failed'].includes(document.getElementById('job-status').dataset.status)", timeout=90_000
    )


def test_a_new_film_starts_without_the_old_films_landmarks_and_undo_brings_them_back(
    browser: Any, live_url: str, api_key: str, tmp_path: Path
) -> None:
    make_dicom(tmp_path / "pa.dcm", view="pa")
    make_dicom(tmp_path / "pa-small.dcm", view="pa", size=(400, 700))
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    open_film(page, "pa", tmp_path / "pa.dcm")
    _midpoints(page, 6)
    placed_first = payload_preview(page)["pa"]["landmarks"]
    assert len(placed_first) == 6
    open_film(page, "pa", tmp_path / "pa-small.dcm")
    assert payload_preview(page) == "Give landmarks first."  # no landmark of the first film on the second
    status = page.text_content("#pa-status") or ""
    assert "The landmarks of 6 vertebrae placed on the previous film were removed" in status, status
    assert "(the film pa.dcm: 6 vertebrae (T1–T6): 6 midpoints)" in status, status
    assert "Undo (the button, or Ctrl+Z on the film) brings back the film pa.dcm and its landmarks" in status
    assert "No landmark on this film yet." in status
    assert page.input_value("#pa-level") == "T1"
    # a film opened over placed landmarks by mistake: Undo brings back the film, its landmarks and their history
    placed = placed_first
    assert page.is_enabled("#pa-undo")
    page.focus("#pa-canvas")
    page.keyboard.press("Control+z")
    assert len(payload_preview(page)["pa"]["landmarks"]) == 6
    assert "pa.dcm" in (page.get_attribute("#pa-canvas", "aria-label") or "")
    assert "pa-small.dcm" not in (page.get_attribute("#pa-canvas", "aria-label") or "")
    status = page.text_content("#pa-status") or ""
    back = "Undone: the film pa.dcm and the landmarks of 6 vertebrae (T1–T6): 6 midpoints are back in place of pa-small"
    assert back in status, status
    page.keyboard.press("Control+z")  # the placements' own history came back too
    assert len(payload_preview(page)["pa"]["landmarks"]) == 5
    page.keyboard.press("Control+Shift+z")
    assert payload_preview(page)["pa"]["landmarks"] == placed
    # Redo opens the second film again, without the first's landmarks
    page.keyboard.press("Control+Shift+z")
    assert payload_preview(page) == "Give landmarks first."
    assert "pa-small.dcm" in (page.get_attribute("#pa-canvas", "aria-label") or "")
    assert "Redone: pa-small.dcm is open again" in (page.text_content("#pa-status") or "")
    page.click("#pa-undo")  # and the button undoes it again
    assert payload_preview(page)["pa"]["landmarks"] == placed
    page.click("#pa-redo")
    assert payload_preview(page) == "Give landmarks first."
    _midpoints(page, 2)  # placing again: the note goes
    assert "removed" not in (page.text_content("#pa-status") or "")
    assert not watch.errors, watch.errors
    context.close()


def test_films_of_two_patients_are_not_sent_and_a_film_in_the_other_panel_is_warned(
    browser: Any, live_url: str, api_key: str, tmp_path: Path
) -> None:
    make_dicom(tmp_path / "pa.dcm", view="pa")  # patient PAT-0042, View Position PA
    make_dicom(tmp_path / "lat-other.dcm", view="lateral", study={"PatientID": "PAT-OTHER"})
    make_dicom(tmp_path / "lat-study.dcm", view="lateral", study={"StudyInstanceUID": "1.2.826.0.1.3680043.8.498.9999"})
    make_dicom(tmp_path / "lat.dcm", view="lateral")
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    open_film(page, "pa", tmp_path / "pa.dcm")
    assert page.is_hidden("#pa-warning")
    _midpoints(page, 17)
    # the PA film opened as the lateral: a warning in the panel, not a refusal
    open_film(page, "lateral", tmp_path / "pa.dcm")
    warning = page.text_content("#lateral-warning") or ""
    assert page.is_visible("#lateral-warning")
    assert "its header says View Position PA (a frontal film), but it is open as the lateral film" in warning
    # a lateral film of another patient: sending is blocked, naming both IDs
    open_film(page, "lateral", tmp_path / "lat-other.dcm")
    assert page.is_hidden("#lateral-warning")
    for _, col, row in lateral_points("T4"):
        page.mouse.click(*canvas_point(page, "lateral", col, row))
    two = "the PA film is of patient ID PAT-0042, the lateral film of patient ID PAT-OTHER"
    assert two in (page.text_content("#missing") or "")
    page.click("#submit")
    assert two in (page.text_content("#problem") or "")
    assert not watch.posted_jobs()
    # of another study
    open_film(page, "lateral", tmp_path / "lat-study.dcm")
    assert "the lateral film of study 1.2.826.0.1.3680043.8.498.9999" in (page.text_content("#missing") or "")
    # closing the lateral film lifts the block; the right one opens without a word
    page.click("#lateral-close")
    assert "two " not in (page.text_content("#missing") or "")
    assert "lateral" not in payload_preview(page)
    assert (page.get_attribute("#lateral-canvas", "aria-label") or "").endswith("no film open")
    open_film(page, "lateral", tmp_path / "lat.dcm")
    assert "two " not in (page.text_content("#missing") or "") and page.is_hidden("#lateral-warning")
    assert not watch.errors, watch.errors
    context.close()


def test_a_reopened_job_is_its_payload_and_is_sent_again_with_its_study_and_options(
    browser: Any, live_url: str, api_key: str, tmp_path: Path
) -> None:
    payload = spine_payload(curve_mm=30.0, spacing_mm=0.4)
    del payload["boundary"]
    payload["pa"]["pixel_spacing"] = [0.4, 0.4]
    payload["study"] = {"study_instance_uid": "1.2.826.0.1.3680043.8.498.4242", "patient_id": "PAT-REOPEN"}
    payload["options"] = {"profile": "literature"}
    headers = {"Authorization": f"Bearer {api_key}"}
    answer = httpx.post(f"{live_url}/v1/jobs", json=payload, headers=headers, timeout=30)
    assert answer.status_code == 202, answer.text
    job_id = answer.json()["id"]
    stored = httpx.get(f"{live_url}/v1/jobs/{job_id}", headers=headers, timeout=30).json()["payload"]

    make_dicom(tmp_path / "pa.dcm", view="pa")
    make_dicom(tmp_path / "lat.dcm", view="lateral")
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    open_film(page, "lateral", tmp_path / "lat.dcm")
    for _, col, row in lateral_points("T4"):
        page.mouse.click(*canvas_point(page, "lateral", col, row))
    open_film(page, "pa", tmp_path / "pa.dcm")
    _midpoints(page, 5)
    page.evaluate(f"() => location.hash = '#/jobs/{job_id}'")
    _wait_final(page)
    page.wait_for_function("() => /17 PA landmarks/.test(document.getElementById('landmark-summary').textContent)")
    sent = payload_preview(page)
    assert "lateral" not in sent, sent  # the PA-only job: nothing of the lateral film before it
    assert (page.text_content("#lateral-header") or "") == ""
    assert (page.get_attribute("#lateral-canvas", "aria-label") or "").endswith("no film open")
    assert [lm["point"] for lm in sent["pa"]["landmarks"]] == [lm["point"] for lm in stored["pa"]["landmarks"]]
    assert sent["study"] == stored["study"]  # not the DICOM film's study of before
    assert sent["options"] == stored["options"]
    assert page.is_disabled("#pa-undo") and page.is_disabled("#lateral-undo")
    assert "PAT-0042" not in (page.text_content("#pa-header") or "")
    # sent again as it is: with the job's study and options
    assert page.get_attribute("#missing", "data-ready") == "true", page.text_content("#missing")
    page.click("#submit")
    page.wait_for_function("(id) => !location.hash.includes(id)", arg=job_id, timeout=30_000)
    posted = watch.posted_jobs()[-1].post_data_json
    assert posted["study"] == stored["study"] and posted["options"] == stored["options"]
    # a DICOM film of another study opened under the job's landmarks: its study, and not the job's options
    open_film(page, "pa", tmp_path / "pa.dcm")
    assert payload_preview(page)["study"]["study_instance_uid"] == "1.2.826.0.1.3680043.8.498.1001"
    assert "options" not in payload_preview(page)
    assert not watch.errors, watch.errors
    context.close()


def test_a_failed_csv_import_leaves_nothing_of_the_previous_csv(browser: Any, live_url: str, api_key: str) -> None:
    rows = "\n".join(f"{lv},{centreline(i)[0] * 0.4:.1f},{centreline(i)[1] * 0.4:.1f}" for i, lv in enumerate(LEVELS))
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    page.click("#tab-csv")
    page.fill("#csv-text", f"level,column,row\n{rows}")
    page.select_option("#csv-units", "mm")
    page.click("#use-csv")
    page.wait_for_selector("#missing[data-ready=true]")
    page.fill("#csv-text", f"level;column;row\n{rows.replace(',', ';')}")
    page.click("#use-csv")
    error = page.text_content("#input-error") or ""
    assert "The landmarks of the CSV used before were dropped" in error, error
    assert page.get_attribute("#missing", "data-ready") == "false"
    assert "Ready to send" not in (page.text_content("#missing") or "")
    assert page.text_content("#landmark-summary") == "No landmarks yet."
    page.click("#submit")
    assert not watch.posted_jobs()
    context.close()


def test_choosing_a_level_selects_it_for_delete(browser: Any, live_url: str, api_key: str, tmp_path: Path) -> None:
    make_dicom(tmp_path / "pa.dcm", view="pa")
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    open_film(page, "pa", tmp_path / "pa.dcm")
    _midpoints(page, 6)

    def levels() -> list[str]:
        return [lm["level"] for lm in payload_preview(page)["pa"]["landmarks"]]

    page.select_option("#pa-level", "T3")
    assert page.get_attribute("#pa-canvas", "data-selected") == "T3 midpoint"
    page.focus("#pa-canvas")
    page.keyboard.press("Delete")
    assert levels() == ["T1", "T2", "T4", "T5", "T6"]
    page.select_option("#pa-level", "T10")  # nothing placed there: nothing selected, Delete removes nothing
    assert page.get_attribute("#pa-canvas", "data-selected") == ""
    page.click("#pa-delete")
    assert levels() == ["T1", "T2", "T4", "T5", "T6"]
    page.focus("#pa-canvas")
    page.keyboard.press("[")  # T9 by keyboard: nothing either
    page.keyboard.press("Delete")
    assert levels() == ["T1", "T2", "T4", "T5", "T6"]
    assert not watch.errors, watch.errors
    context.close()


def _fake_job(payload: dict[str, Any], error: dict[str, Any] | None = None) -> dict[str, Any]:
    return {
        "id": str(uuid.uuid4()), "status": "failed", "created_at": "2026-01-01T00:00:00Z", "finished_at": None,
        "payload": payload, "result": None, "error": error, "study": None,
    }  # fmt: skip


def _cases() -> list[tuple[list[list[float]], list[list[float]]]]:
    """Corners (every order of one body's four, then random quadrilaterals) with pedicles (in order,
    swapped, or at one column), each for a level placed where pa_corners() puts it."""
    rng = random.Random(7)
    out = []
    body = pa_corners()[5]
    for perm in itertools.permutations(range(4)):
        out.append([[round(body[k][0] - body[0][0], 1), round(body[k][1] - body[0][1], 1)] for k in perm])
    for _ in range(44):
        out.append([[round(rng.uniform(-10, 50), 1), round(rng.uniform(-10, 30), 1)] for _ in range(4)])
    cases = []
    for i, quad in enumerate(out):
        a, b = round(rng.uniform(0, 40), 1), round(rng.uniform(0, 40), 1)
        pedicles = [[a, 10.0], [a if i % 7 == 0 else b, 10.0]]
        cases.append((quad, pedicles))
    return cases


def test_corners_and_pedicles_are_refused_before_sending_as_the_service_refuses_them(
    browser: Any, live_url: str, api_key: str
) -> None:
    """Every order of one body's corners and random quadrilaterals, with pedicles in order or not: the
    page names (and draws) exactly the landmarks the service refuses, in the service's words."""
    headers = {"Authorization": f"Bearer {api_key}"}
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    jobs: dict[str, dict[str, Any]] = {}
    page.route("**/v1/jobs/*", lambda route: route.fulfill(json=jobs[route.request.url.rsplit("/", 1)[1]])
               if route.request.url.rsplit("/", 1)[1] in jobs else route.continue_())  # fmt: skip
    cases = _cases()
    # 10 levels a job: at most 20 refusals (corners and pedicles), all listed in one 422 (a problem lists at
    # most 20 field errors, services/api/errors.MAX_ERRORS)
    per_job = 10
    for start in range(0, len(cases), per_job):
        chunk = cases[start : start + per_job]
        landmarks: list[dict[str, Any]] = []
        for i, (quad, pedicles) in enumerate(chunk):
            at = pa_corners()[i][0]
            corners = [[round(at[0] + x, 1), round(at[1] + y, 1)] for x, y in quad]
            ped = [[round(at[0] + x, 1), round(at[1] + y, 1)] for x, y in pedicles]
            landmarks.append({"level": LEVELS[i], "corners": corners, "pedicles": ped})
        payload = {"pa": {"units": "px", "pixel_spacing": [0.4, 0.4], "landmarks": landmarks}}
        answer = httpx.post(f"{live_url}/v1/jobs", json=payload, headers=headers, timeout=30)
        refused: dict[str, list[str]] = {}
        if answer.status_code == 422:
            for e in answer.json()["errors"]:
                if e["type"] in ("corners_not_convex", "corners_not_upright", "pedicles_not_in_order"):
                    refused.setdefault(landmarks[int(e["path"].split("[")[1].split("]")[0])]["level"], []).append(
                        e["msg"]
                    )
        else:
            assert answer.status_code == 202, answer.text
        job = _fake_job(payload)
        jobs[job["id"]] = job
        page.evaluate(f"() => location.hash = '#/jobs/{job['id']}'")
        # "Job … failed." once the payload is restored (not "Opening job …")
        page.wait_for_function(
            f"() => document.getElementById('job-status').textContent.startsWith('Job {job['id']} ')"
        )
        page.wait_for_function("() => /PA landmarks/.test(document.getElementById('landmark-summary').textContent)")
        missing = page.text_content("#missing") or ""
        named = {
            lv for lv in LEVELS
            if f"PA film, {lv}: the corners of {lv} " in missing or f"PA film, {lv}: the pedicles of {lv} " in missing
        }  # fmt: skip
        assert named == set(refused), (start, sorted(named), refused)
        for level, msgs in refused.items():
            for msg in msgs:
                assert f"PA film, {level}: {msg}" in missing, (level, msg, missing)
        drawn = set((page.get_attribute("#pa-canvas", "data-problems") or "").split())
        assert set(refused) <= drawn, (refused, drawn)
        assert page.get_attribute("#missing", "data-ready") == ("false" if refused else "true")
    page.click("#submit")  # the last chunk has refused landmarks: nothing is sent
    assert not watch.posted_jobs()
    assert not watch.errors, watch.errors
    context.close()


def test_a_refusals_apostrophes_stay_apostrophes(browser: Any, live_url: str, api_key: str) -> None:
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    # a refusal with apostrophes and a quoted value, from a (faked) failed job
    msg = (
        "the pedicles of T4 are given at one column: give the image-left pedicle's centre first; "
        "a vertebra's two pedicles, units 'px'"
    )
    error = {"type": "about:blank", "title": "Invalid input", "status": 422, "detail": "The input is invalid.",
             "errors": [{"path": "pa.landmarks[3].pedicles", "msg": msg, "type": "pedicles_not_in_order"}]}  # fmt: skip
    job = _fake_job(spine_payload(spacing_mm=0.4), error)
    page.route(f"**/v1/jobs/{job['id']}", lambda route: route.fulfill(json=job))
    page.evaluate(f"() => location.hash = '#/jobs/{job['id']}'")
    page.wait_for_selector("#problem:not([hidden])")
    shown = page.text_content("#problem") or ""
    assert "image-left pedicle's centre first; a vertebra's two pedicles, units “px”" in shown, shown
    assert not watch.errors, watch.errors
    context.close()


def test_a_damaged_dicom_file_is_said_in_the_parsers_words(
    browser: Any, live_url: str, api_key: str, tmp_path: Path
) -> None:
    whole = tmp_path / "pa.dcm"
    make_dicom(whole, view="pa")
    damaged = tmp_path / "damaged.dcm"
    damaged.write_bytes(whole.read_bytes()[:500_000])
    context, page, _watch = open_page(browser, f"{live_url}/", api_key)
    page.set_input_files("#pa-file", str(damaged))
    page.wait_for_selector("#pa-error:not([hidden])")
    said = page.text_content("#pa-error") or ""
    assert "damaged.dcm is a damaged DICOM file" in said and "object Object" not in said, said
    assert "past end of buffer" in said or "truncated" in said or "overrun" in said or "not enough" in said, said
    context.close()


def test_reconstruct_gives_the_focus_back_and_an_unchanged_draft_is_one_job(
    browser: Any, live_url: str, api_key: str, tmp_path: Path
) -> None:
    whole = tmp_path / "pa.dcm"
    make_dicom(whole, view="pa")
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    open_film(page, "pa", whole)
    _midpoints(page, 17)
    page.focus("#submit")
    page.keyboard.press("Enter")
    page.wait_for_function("() => location.hash.startsWith('#/jobs/')")
    _wait_final(page)
    page.wait_for_function("() => document.activeElement && document.activeElement.id === 'submit'", timeout=5_000)
    first = page.evaluate("() => location.hash")
    keys = [p.headers.get("idempotency-key") for p in watch.posted_jobs()]
    assert len(keys) == 1 and keys[0], keys
    page.click("#submit")  # an accidental second click
    page.wait_for_function("() => /Sent again unchanged/.test(document.getElementById('job-status').textContent)")
    keys = [p.headers.get("idempotency-key") for p in watch.posted_jobs()]
    assert len(keys) == 2 and keys[0] == keys[1], keys
    assert page.evaluate("() => location.hash") == first  # the same job
    # an edit: a new key and a new job
    page.focus("#pa-canvas")
    page.keyboard.press(",")
    page.keyboard.press("Alt+ArrowRight")
    page.click("#submit")
    page.wait_for_function("(h) => location.hash !== h", arg=first, timeout=30_000)
    third = watch.posted_jobs()[2].headers.get("idempotency-key")
    assert third and third != keys[0]
    _wait_final(page)
    assert "Sent again" not in (page.text_content("#job-status") or "")
    assert not watch.errors, watch.errors
    context.close()


def test_a_film_of_another_patient_under_a_reopened_jobs_landmarks_is_named_and_not_sent(
    browser: Any, live_url: str, api_key: str, tmp_path: Path
) -> None:
    """A job of patient PAT-JOB (its payload's study names its PA image by SOP Instance UID), reopened: its
    17 landmarks on a blank frame. A DICOM film of patient PAT-0042 opened under them is warned about in
    the panel (the header's Patient ID against the job's) and listed before sending, and Reconstruct
    sends nothing, relabelled one level or not, until those landmarks are gone (Clear all, and one placed
    on the film). A film of the
    job's patient with another SOP Instance UID is warned about, not blocked (the job's study is
    replaced by the film's, as docs/web.md says). The landmarks below row 900 lie off the 560 × 900 px
    film: said too."""
    payload = spine_payload(curve_mm=30.0, spacing_mm=0.4)
    del payload["boundary"]
    payload["pa"]["pixel_spacing"] = [0.4, 0.4]
    payload["study"] = {"study_instance_uid": "1.2.826.0.1.3680043.8.498.4343", "patient_id": "PAT-JOB",
                        "pa_sop_instance_uid": "1.2.826.0.1.3680043.8.498.4343.1"}  # fmt: skip
    answer = httpx.post(f"{live_url}/v1/jobs", json=payload, headers={"Authorization": f"Bearer {api_key}"}, timeout=30)
    assert answer.status_code == 202, answer.text
    job_id = answer.json()["id"]
    off = [lm["level"] for lm in payload["pa"]["landmarks"] if lm["point"][1] > 900]
    assert off  # rows up to (50 + 420) / 0.4 = 1175 px (tests/conftest.spine_payload)
    make_dicom(tmp_path / "other.dcm", view="pa")  # PatientID PAT-0042 (page_fixtures.make_dicom)
    make_dicom(
        tmp_path / "same.dcm",
        view="pa",
        study={"PatientID": "PAT-JOB", "StudyInstanceUID": "1.2.826.0.1.3680043.8.498.4343"},
    )

    for name in ("other.dcm", "same.dcm"):
        context, page, watch = open_page(browser, f"{live_url}/", api_key)
        page.evaluate(f"() => location.hash = '#/jobs/{job_id}'")
        page.wait_for_function("() => /17 PA landmarks/.test(document.getElementById('landmark-summary').textContent)")
        page.wait_for_selector("#pa-canvas[data-blank*='Not stored by the service']")  # the PACS asked, or not
        open_film(page, "pa", tmp_path / name)
        warning = page.text_content("#pa-warning") or ""
        assert page.is_visible("#pa-warning")
        assert f"The landmarks of {off[0]}, " in warning or f"The landmarks of {', '.join(off)}" in warning, warning
        assert "outside this film (560 × 900 px)" in warning, warning
        missing = page.text_content("#missing") or ""
        if name == "same.dcm":
            assert "its header says image " in warning and "the job's is 1.2.826.0.1.3680043.8.498.4343.1" in warning
            assert "not the reopened job's:" not in missing, missing
            context.close()
            continue
        assert "its header says patient ID PAT-0042, the job's is PAT-JOB" in warning, warning
        assert "The PA film is not the reopened job's: its header says patient ID PAT-0042" in missing, missing
        assert "17 vertebrae (T1–L5)" in missing, missing
        assert page.get_attribute("#missing", "data-ready") != "true"
        sent = len(watch.posted_jobs())
        page.click("#submit")
        assert len(watch.posted_jobs()) == sent
        # relabelled one level (L5's deleted first), the job's landmarks are still the job's: still not sent
        page.select_option("#pa-level", "L5")
        page.click("#pa-delete")
        page.click("#pa-shift-down")
        missing = page.text_content("#missing") or ""
        assert "The PA film is not the reopened job's" in missing and "16 vertebrae (T2–L5)" in missing, missing
        # the job's landmarks cleared and one placed on this film: nothing of the job's is over it
        page.click("#pa-clear")
        col, row, _ = centreline(0)
        page.mouse.click(*canvas_point(page, "pa", col, row))
        assert "not the reopened job's" not in (page.text_content("#missing") or "")
        assert not watch.errors, watch.errors
        context.close()


def test_a_film_opened_by_hand_while_the_pacs_is_asked_is_not_covered_by_the_fetch(
    browser: Any, live_url: str, api_key: str, tmp_path: Path
) -> None:
    """A reopened job whose study names its PA image: the page asks the service whether it has a PACS to
    fetch the film again (GET /v1/pacs, held here until the film is open, as a slow service would). The
    radiographer opens the job's film from disk meanwhile: the landmarks stay over it, and the answer
    that comes later (no PACS) does not replace the film's header with a note about the fetch."""
    payload = spine_payload(curve_mm=30.0, spacing_mm=0.4)
    del payload["boundary"]
    payload["pa"]["pixel_spacing"] = [0.4, 0.4]
    uid = "1.2.826.0.1.3680043.8.498.4444"
    payload["study"] = {"study_instance_uid": uid, "patient_id": "PAT-0042", "pa_sop_instance_uid": f"{uid}.1"}
    answer = httpx.post(f"{live_url}/v1/jobs", json=payload, headers={"Authorization": f"Bearer {api_key}"}, timeout=30)
    assert answer.status_code == 202, answer.text
    make_dicom(tmp_path / "job.dcm", view="pa", study={"StudyInstanceUID": uid, "SOPInstanceUID": f"{uid}.1"})
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    page.wait_for_load_state("networkidle")  # the key's own GET /v1/pacs answered
    held: list[Any] = []
    page.route("**/v1/pacs", lambda route: held.append(route))
    page.evaluate(f"() => location.hash = '#/jobs/{answer.json()['id']}'")
    page.wait_for_function("() => /17 PA landmarks/.test(document.getElementById('landmark-summary').textContent)")
    for _ in range(100):
        if held:
            break
        page.wait_for_timeout(50)
    assert held, "the page did not ask whether the service has a PACS"
    open_film(page, "pa", tmp_path / "job.dcm")
    assert "ID PAT-0042" in (page.text_content("#pa-header") or "")
    for route in held:
        route.continue_()
    page.unroute("**/v1/pacs")
    page.wait_for_load_state("networkidle")
    page.wait_for_timeout(300)
    header = page.text_content("#pa-header") or ""
    assert "ID PAT-0042" in header and "no PACS" not in header, header
    assert "17 vertebrae on the PA film (T1–L5)" in (page.text_content("#pa-status") or "")
    assert not watch.errors, watch.errors
    context.close()


def test_a_reopened_jobs_landmarks_in_mm_are_not_put_over_a_film_as_pixels(
    browser: Any, live_url: str, api_key: str, tmp_path: Path
) -> None:
    """A job sent in mm without a pixel spacing (the payload's default units, as the Python client sends
    them), reopened: its landmarks on the blank frame (1 px = 1 mm). A film opened under them does not
    take them as its pixels (T1 at column 100 mm would be sent as column 100 px, 0.4 mm each, 60 mm
    off): they are removed and the panel says why, and nothing of them is left to send."""
    payload = spine_payload(curve_mm=30.0)  # mm, no pixel spacing
    del payload["boundary"]
    answer = httpx.post(f"{live_url}/v1/jobs", json=payload, headers={"Authorization": f"Bearer {api_key}"}, timeout=30)
    assert answer.status_code == 202, answer.text
    make_dicom(tmp_path / "pa.dcm", view="pa")
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    page.evaluate(f"() => location.hash = '#/jobs/{answer.json()['id']}'")
    page.wait_for_function("() => /17 PA landmarks/.test(document.getElementById('landmark-summary').textContent)")
    assert payload_preview(page)["pa"].get("units", "mm") == "mm"
    open_film(page, "pa", tmp_path / "pa.dcm")
    status = page.text_content("#pa-status") or ""
    assert "The reopened job's landmarks of 17 vertebrae are in mm without a pixel spacing" in status, status
    assert "removed, not guessed" in status and status.endswith("No landmark on this film yet."), status
    assert not isinstance(payload_preview(page), dict) or "pa" not in payload_preview(page), payload_preview(page)
    # Undo brings them back on their blank frame, in mm as the job has them
    page.click("#pa-undo", timeout=5_000)
    back = payload_preview(page)["pa"]
    assert back.get("units", "mm") == "mm" and len(back["landmarks"]) == 17, back
    assert not watch.errors, watch.errors
    context.close()


def test_a_slow_answer_for_an_earlier_job_does_not_replace_the_job_opened_since(
    browser: Any, live_url: str, api_key: str
) -> None:
    """Job A opened from its address, its answer slow (held here); job B opened before it came: B's
    landmarks and status stay, and A's answer, arriving last, does not put A's landmarks under B's
    address (to be edited and sent again as if they were B's)."""
    payloads = []
    for curve in (20.0, 40.0):
        payload = spine_payload(curve_mm=curve, spacing_mm=0.4)
        del payload["boundary"]
        payload["pa"]["pixel_spacing"] = [0.4, 0.4]
        payloads.append(payload)
    job_a, job_b = (run_job(live_url, api_key, p)["id"] for p in payloads)
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    held: list[Any] = []
    page.route(f"**/v1/jobs/{job_a}", lambda route: held.append(route))
    page.evaluate(f"() => location.hash = '#/jobs/{job_a}'")
    for _ in range(100):
        if held:
            break
        page.wait_for_timeout(50)
    assert held, "the page did not ask for job A"
    page.evaluate(f"() => location.hash = '#/jobs/{job_b}'")
    page.wait_for_selector(f"#result[data-job-id='{job_b}']", timeout=30_000)
    for route in held:
        route.continue_()
    page.unroute(f"**/v1/jobs/{job_a}")
    page.wait_for_load_state("networkidle")
    page.wait_for_timeout(300)
    assert page.get_attribute("#result", "data-job-id") == job_b
    assert (page.text_content("#job-status") or "").startswith(f"Job {job_b} succeeded")
    sent = payload_preview(page)["pa"]["landmarks"]
    assert [lm["point"] for lm in sent] == [lm["point"] for lm in payloads[1]["pa"]["landmarks"]]
    assert not watch.errors, watch.errors
    context.close()


def test_a_slow_poll_of_a_running_job_does_not_replace_the_job_opened_since(
    browser: Any, live_url: str, api_key: str, live_data_dir: Path
) -> None:
    """Job A still running (set so in the service's database, with a lease an hour ahead, which the
    reconciler leaves alone) is opened and polled; one poll's answer is slow (held here) and job B is
    opened before it came: A's late answer does not take the status line and the result back to A."""
    payloads = []
    for curve in (20.0, 40.0):
        payload = spine_payload(curve_mm=curve, spacing_mm=0.4)
        del payload["boundary"]
        payload["pa"]["pixel_spacing"] = [0.4, 0.4]
        payloads.append(payload)
    job_a, job_b = (run_job(live_url, api_key, p)["id"] for p in payloads)
    with session_factory(Settings(data_dir=live_data_dir, DATABASE_URL=None))() as session:
        running = session.scalars(select(Job).where(Job.id == uuid.UUID(job_a))).one()
        running.status, running.result, running.finished_at = "running", None, None
        running.lease_expires_at = datetime.now(UTC) + timedelta(hours=1)
        session.commit()
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    page.evaluate(f"() => location.hash = '#/jobs/{job_a}'")
    page.wait_for_selector("#job-status[data-status=running]")
    held: list[Any] = []
    page.route(f"**/v1/jobs/{job_a}", lambda route: held.append(route))
    for _ in range(100):  # the next poll (every 0.4 s)
        if held:
            break
        page.wait_for_timeout(50)
    assert held, "the page did not poll job A"
    page.evaluate(f"() => location.hash = '#/jobs/{job_b}'")
    page.wait_for_selector(f"#result[data-job-id='{job_b}']", timeout=30_000)
    for route in held:
        route.continue_()
    page.unroute(f"**/v1/jobs/{job_a}")
    page.wait_for_load_state("networkidle")
    page.wait_for_timeout(1000)  # two more poll periods, had A's polling resumed
    assert (page.text_content("#job-status") or "").startswith(f"Job {job_b} succeeded")
    assert page.get_attribute("#job-status", "data-status") == "succeeded"
    assert [lm["point"] for lm in payload_preview(page)["pa"]["landmarks"]] == [
        lm["point"] for lm in payloads[1]["pa"]["landmarks"]
    ]
    assert not watch.errors, watch.errors
    context.close()
