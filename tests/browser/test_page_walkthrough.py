"""What a clinician's walkthrough in Debian's Chromium left, against a real `spine serve` (API, Celery worker,
its database): a job reopened by its address while the service does not answer (its reads aborted or answered
503 in Playwright's routing, the service itself untouched) is read again until it answers, a 404 stops it; the
keyboard's crosshair is said in a polite live region, in the film's terms, throttled; under the print
stylesheet at an A4 width no "model estimate" badge leaves its cell and a figure not yet loaded prints as
words, not as a broken image; landmarks in order along another direction than the film's orientation says
blame the orientation, as the service's 422 on the same payload does; the lateral film's level starts at
the PA film's first level."""

from __future__ import annotations

import itertools
import time
import uuid
from pathlib import Path
from typing import Any

import httpx
import pytest
from page_fixtures import (
    JOB_READ,
    LEVELS,
    canvas_point,
    click_pa_midpoints,
    make_dicom,
    open_film,
    open_page,
    pa_points_payload,
    payload_preview,
    run_job,
    unavailable_once,
)

pytestmark = pytest.mark.browser

# The reads stay unanswered longer than the first backoff (main.ts retryDelay: 1 s, doubling) and the second
# (2 s): at least two retries are seen before the service answers again.
UNANSWERED_S = 2.0
FIRST_BACKOFF_S = 1.0  # main.ts retryDelay: 1 s, doubling to at most 30 s
DISPATCH_S = 0.1  # allowance for Playwright's route callbacks reaching this test
A4_CSS_PX = round((210 - 2 * 12) / 25.4 * 96)  # A4 width less the report's 12 mm margins (style.css @page), CSS px
CROSSHAIR_SAY_MS = 500  # panel.ts: the least time between two sayings of the crosshair's place


@pytest.fixture(scope="module")
def fitted_job(live_url: str, api_key: str) -> dict[str, Any]:
    """One real succeeded PA-only job of the synthetic S-curve (17 PA midpoints): its depth from the model's
    prior, so `fit.unreliable` marks measures and strain columns as model estimates."""
    job = run_job(live_url, api_key, pa_points_payload())
    assert job["result"]["fit"].get("unreliable"), job["result"]["fit"]
    return job


@pytest.fixture(scope="module")
def films(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The fixtures' PA (0.4 mm Imager Pixel Spacing, ERMF 1.2) and lateral (0.45 mm calibrated) DX films."""
    folder = tmp_path_factory.mktemp("walkthrough-films")
    out = {"pa": folder / "pa.dcm", "lateral": folder / "lateral.dcm"}
    make_dicom(out["pa"], view="pa")
    make_dicom(out["lateral"], view="lateral")
    return out


def _service_errors(url: str, key: str, payload: dict[str, Any]) -> list[dict[str, Any]]:
    """The service's refusal (its 422) of the page's payload, sent as it is: no unknown profile added to keep a
    job from being made, since an error of the profile's stops the checks that run only on an otherwise valid
    payload (validation.py `validate_payload`: `_across_errors`); the test expects a refusal."""
    answer = httpx.post(f"{url}/v1/jobs", json=payload, headers={"Authorization": f"Bearer {key}"}, timeout=30)
    assert answer.status_code == 422, answer.text
    errors: list[dict[str, Any]] = answer.json()["errors"]
    return errors


def _missing(page: Any) -> list[str]:
    return [t.strip() for t in page.locator("#missing li").all_text_contents()]


# ---------------------------------------------------------------- 1. a reopened job's first read


def test_a_reopened_job_is_read_again_until_the_service_answers(
    browser: Any, live_url: str, api_key: str, fitted_job: dict[str, Any]
) -> None:
    """The job's address opened while its reads are refused a connection (for UNANSWERED_S, longer than two
    backoffs): the page says since when the service has not answered, offers "Check now", asks again at least
    FIRST_BACKOFF_S later, and shows the job once the reads come back (the old page said "could not be opened"
    after the first and gave up)."""
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    job_id = fitted_job["id"]
    aborted: list[float] = []
    blocked = [True]

    def reads(route: Any) -> None:
        if blocked[0]:
            aborted.append(time.monotonic())
            route.abort("connectionrefused")
        else:
            route.continue_()

    page.route(JOB_READ, reads)
    page.evaluate(f"() => location.hash = '#/jobs/{job_id}'")
    start = time.monotonic()
    while len(aborted) < 2 or time.monotonic() - aborted[0] < UNANSWERED_S:
        assert time.monotonic() - start < 10, aborted  # the old page read once, then gave up
        page.wait_for_timeout(50)
    said = page.text_content("#job-status") or ""
    tracking = page.get_attribute("#job-status", "data-tracking")
    check_shown = page.is_visible("#check-job")
    blocked[0] = False
    page.wait_for_selector(f"#result[data-job-id='{job_id}']", timeout=15_000)
    assert tracking == "retrying", said
    assert f"Opening job {job_id}: the service has not answered since " in said, said
    assert "The page asks again at " in said and "“Check now”" in said, said
    assert check_shown
    assert aborted[1] - aborted[0] >= FIRST_BACKOFF_S - DISPATCH_S, aborted  # backing off, not hammering
    assert page.get_attribute("#job-status", "data-status") == "succeeded"
    assert page.is_hidden("#check-job") and page.is_hidden("#problem")
    assert "17 PA landmarks" in (page.text_content("#landmark-summary") or "")  # the job's payload in the editors
    assert all("ERR_CONNECTION_REFUSED" in e for e in watch.errors), watch.errors
    context.close()


def test_a_reopened_job_honours_retry_after_checks_now_and_stops_at_404(
    browser: Any, live_url: str, api_key: str, fitted_job: dict[str, Any]
) -> None:
    """A 503 with Retry-After: 30 (answered once in Playwright's routing) holds the next read back beyond the
    first backoff; "Check now" by keyboard reads at once and opens the job. A job the service does not have
    (its real 404) is said as such and not read again."""
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    job_id = fitted_job["id"]
    reads = unavailable_once(page, JOB_READ)
    page.evaluate(f"() => location.hash = '#/jobs/{job_id}'")
    page.wait_for_selector("#job-status[data-tracking=retrying]", timeout=10_000)
    page.wait_for_timeout(1500)  # longer than the first backoff (1 s): Retry-After: 30 holds the read back
    assert len(reads) == 1, reads
    said = page.text_content("#job-status") or ""
    assert "HTTP 503, the API is restarting" in said, said
    page.focus("#check-job")
    page.keyboard.press("Enter")
    page.wait_for_selector(f"#result[data-job-id='{job_id}']", timeout=15_000)
    assert len(reads) == 2, reads
    assert page.get_attribute("#job-status", "data-tracking") is None and page.is_hidden("#check-job")

    missing = str(uuid.uuid4())
    page.evaluate(f"() => location.hash = '#/jobs/{missing}'")
    page.wait_for_selector("#job-status[data-tracking=stopped]", timeout=10_000)
    stopped_at = len(reads)
    said = page.text_content("#job-status") or ""
    assert said.startswith(f"Job {missing} could not be opened: the service has no such job"), said
    assert page.is_visible("#problem") and page.is_hidden("#check-job")
    page.wait_for_timeout(2500)  # more than two backoffs (1 s, 2 s): no read comes
    assert len(reads) == stopped_at, reads
    assert not [e for e in watch.errors if "404" not in e and "503" not in e], watch.errors
    context.close()


# ---------------------------------------------------------------- 2. the crosshair, said


def test_the_crosshair_is_said_as_the_keyboard_moves_it(
    browser: Any, live_url: str, api_key: str, films: dict[str, Path]
) -> None:
    """On the PA film with T1–T3 placed, the arrow keys move the crosshair: a polite live region says where,
    in the film's px and mm (the film's spacing), and that T4's midpoint is what Enter places; a held key (30
    presses) is said at most once per CROSSHAIR_SAY_MS and then where it stopped; the mouse says nothing."""
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    open_film(page, "pa", films["pa"])
    click_pa_midpoints(page, range(3))
    region = page.locator("#pa-crosshair")
    assert region.count() == 1  # the old page had no words for the crosshair
    assert region.get_attribute("aria-live") == "polite"
    before = region.text_content() or ""
    page.focus("#pa-canvas")
    page.keyboard.press("ArrowDown")
    said = region.text_content() or ""
    assert said != before and said.startswith("T4 midpoint next: crosshair at column "), said
    spacing = float(page.input_value("#pa-spacing"))

    def expected() -> tuple[str, str]:
        col, row = (float(x) for x in (page.get_attribute("#pa-canvas", "data-cursor") or "").split())
        return (
            f"column {round(col)}, row {round(row)} px",
            f"({col * spacing:.1f} mm across, {row * spacing:.1f} mm down",
        )

    px, mm = expected()
    assert px in said and mm in said, (said, px, mm)
    # a held key: counted in the page as the region changes
    page.evaluate("""() => { window.sayings = []; new MutationObserver(() => window.sayings.push(performance.now()))
        .observe(document.getElementById('pa-crosshair'), {childList: true, characterData: true, subtree: true}); }""")
    started = page.evaluate("() => performance.now()")
    for _ in range(30):
        page.keyboard.press("ArrowRight")
    ended = page.evaluate("() => performance.now()")
    page.wait_for_timeout(CROSSHAIR_SAY_MS + 200)  # the last position, said once the time is up
    sayings = page.evaluate("() => window.sayings")
    assert 1 <= len(sayings) <= (ended - started) / CROSSHAIR_SAY_MS + 2, (sayings, started, ended)
    assert all(b - a >= CROSSHAIR_SAY_MS - 20 for a, b in itertools.pairwise(sayings)), sayings
    said = region.text_content() or ""
    px, mm = expected()
    assert px in said and mm in said, (said, px, mm)
    # the mouse moves its own crosshair, which a sighted user sees: nothing is said
    box = page.locator("#pa-canvas").bounding_box()
    assert box is not None
    for k in range(5):
        page.mouse.move(box["x"] + box["width"] / 2 + 10 * k, box["y"] + box["height"] / 2)
    page.wait_for_timeout(CROSSHAIR_SAY_MS + 100)
    assert region.text_content() == said
    assert not watch.errors, watch.errors
    context.close()


# ---------------------------------------------------------------- 3. print


def _printed_report(browser: Any, live_url: str, api_key: str, job_id: str) -> tuple[Any, Any, Any, list[Any]]:
    """The job's report under the print stylesheet at an A4 page's width (what the browser's own Ctrl+P prints),
    its figure's request held back in Playwright's routing (the routes held returned, to be let go)."""
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    held: list[Any] = []
    page.route(f"**/v1/jobs/{job_id}/figure.png", lambda route: held.append(route))
    page.goto(f"{live_url}/#/jobs/{job_id}")
    page.wait_for_selector(f"#result[data-job-id='{job_id}']", timeout=30_000)
    page.set_viewport_size({"width": A4_CSS_PX, "height": 1000})
    page.emulate_media(media="print")
    return context, page, watch, held


def test_in_print_every_model_estimate_badge_stays_in_its_cell(
    browser: Any, live_url: str, api_key: str, fitted_job: dict[str, Any]
) -> None:
    """Every "model estimate" badge of the printed report (measures, Lenke and strains tables) lies within its
    table cell, the strains table's narrow columns included (the old badge, nowrap at the page's 0.75rem, was
    twice as wide as a strains column)."""
    context, page, watch, held = _printed_report(browser, live_url, api_key, fitted_job["id"])
    badges = page.evaluate("""() => [...document.querySelectorAll('#result td .model-mark, #result th .model-mark')]
        .filter((b) => b.getClientRects().length).map((b) => {
            const cell = b.closest('td, th'), r = b.getBoundingClientRect(), c = cell.getBoundingClientRect();
            return {where: (cell.closest('table').id || cell.closest('[id]').id) + ': ' + cell.textContent.trim(),
                    badge: [r.left, r.right, r.top, r.bottom], cell: [c.left, c.right, c.top, c.bottom]};
        })""")
    assert len(badges) >= 3, badges  # the measures' and the strains table's marks at least
    assert any(b["where"].startswith("strains: ") for b in badges), badges
    outside = [b for b in badges if b["badge"][0] < b["cell"][0] - 0.5 or b["badge"][1] > b["cell"][1] + 0.5
               or b["badge"][2] < b["cell"][2] - 0.5 or b["badge"][3] > b["cell"][3] + 0.5]  # fmt: skip
    assert not outside, outside  # half a CSS px: sub-pixel rounding of the layout
    for route in held:
        route.continue_()
    assert not watch.errors, watch.errors
    context.close()


def test_in_print_a_figure_not_loaded_is_words_not_a_broken_image(
    browser: Any, live_url: str, api_key: str, fitted_job: dict[str, Any]
) -> None:
    """The report's figure held back: the printed report shows no image that has not loaded, a sentence says the
    figure is still loading and not in this print; once it is in, the figure is printed and the sentence is not."""
    context, page, watch, held = _printed_report(browser, live_url, api_key, fitted_job["id"])
    figure = """() => { const img = document.getElementById('report-figure'); const r = img.getBoundingClientRect();
        const shown = (el) => el.getClientRects().length > 0 && getComputedStyle(el).visibility !== 'hidden';
        const pending = document.querySelector('.figure-pending'), failed = document.querySelector('.figure-failed');
        return {loaded: img.dataset.loaded, shown: shown(img) && r.width > 0, natural: img.naturalWidth,
                pending: pending && shown(pending) ? pending.textContent : null,
                failed: !!failed && shown(failed)}; }"""
    page.wait_for_timeout(100)  # let the route handler run
    assert held, "the figure was not asked for"
    now = page.evaluate(figure)
    assert now["loaded"] == "pending", now
    assert not now["shown"], now  # no image that has not loaded in the print
    assert now["pending"] and "still loading" in now["pending"] and not now["failed"], now
    held[0].continue_()
    page.wait_for_selector("#report-figure[data-loaded=true]", state="attached", timeout=30_000)
    now = page.evaluate(figure)
    assert now["shown"] and now["natural"] > 0 and now["pending"] is None and not now["failed"], now
    assert not watch.errors, watch.errors
    context.close()


# ---------------------------------------------------------------- 4. the order that says the orientation is wrong


def test_landmarks_in_order_along_another_direction_blame_the_orientation(
    browser: Any, live_url: str, api_key: str, films: dict[str, Path]
) -> None:
    """The PA film clicked top to bottom (17 midpoints) with its rows said to run toward H: the page says the
    orientation is likely wrong (the rows' control marked, “F (feet)” to choose), not that each level is above
    the one before, and sends nothing; the service refuses the same payload for the same reason, in its words
    ("on an image whose rows run toward H"). A straight spine (columns 4 px apart, within the service's noise
    allowance) under a swapped orientation ["F", "L"]: the page names the orientation at both controls, and the
    service's 422 on the same payload is `spine_across_the_film` at `pa.patient_orientation`."""
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    open_film(page, "pa", films["pa"])
    click_pa_midpoints(page, range(len(LEVELS)))
    assert page.get_attribute("#missing", "data-ready") == "true", _missing(page)
    page.select_option("#pa-orientation-row", "H")
    hint = page.locator("#pa-orientation-order")
    assert hint.is_visible()
    words = hint.text_content() or ""
    assert "the orientation is likely wrong" in words and "run in order down the image" in words, words
    assert "choose “F (feet)” for “Toward the image's bottom: the patient's”" in words, words
    assert page.get_attribute("#pa-orientation-row", "aria-invalid") == "true"
    assert "pa-orientation-order" in (page.get_attribute("#pa-orientation-row", "aria-describedby") or "")
    assert page.get_attribute("#pa-orientation-column", "aria-invalid") != "true"  # L is right: only the rows
    missing = _missing(page)
    assert any(m.startswith("PA film, orientation likely wrong") for m in missing), missing
    assert not [m for m in missing if "placed above" in m], missing  # the order is not blamed
    assert page.get_attribute("#pa-canvas", "data-problems") == ""  # nor drawn in red
    errors = _service_errors(live_url, api_key, payload_preview(page))
    assert errors and {e["type"] for e in errors} == {"landmarks_out_of_order"}, errors
    assert all("rows run toward H" in e["msg"] for e in errors), errors
    page.click("#submit")
    assert "orientation likely wrong" in (page.text_content("#problem") or "")
    assert not watch.posted_jobs()
    page.select_option("#pa-orientation-row", "F")
    assert hint.is_hidden() and page.get_attribute("#pa-orientation-row", "aria-invalid") != "true"
    assert page.get_attribute("#missing", "data-ready") == "true", _missing(page)

    # a straight spine, its columns alternating 4 px apart, clicked top to bottom
    page.click("#pa-clear")
    for i in range(len(LEVELS)):
        page.mouse.click(*canvas_point(page, "pa", 280.0 + 4.0 * (i % 2), 60.0 + 740.0 * i / (len(LEVELS) - 1)))
    assert page.get_attribute("#missing", "data-ready") == "true", _missing(page)
    page.select_option("#pa-orientation-column", "F")
    page.select_option("#pa-orientation-row", "L")
    words = hint.text_content() or ""
    assert hint.is_visible() and "the orientation is likely wrong" in words, words
    assert "the orientation says the patient's F (feet) is toward the image's right" in words, words
    assert ("choose “F (feet)” for “Toward the image's bottom: the patient's” and L (left side) or R (right side) "
            "for “Toward the image's right: the patient's”") in words, words  # fmt: skip
    for select in ("#pa-orientation-column", "#pa-orientation-row"):
        assert page.get_attribute(select, "aria-invalid") == "true", select
    missing = _missing(page)
    assert not [m for m in missing if "placed above" in m], missing
    assert page.get_attribute("#missing", "data-ready") == "false"
    errors = _service_errors(live_url, api_key, payload_preview(page))
    assert [(e["path"], e["type"]) for e in errors] == [("pa.patient_orientation", "spine_across_the_film")], errors
    page.select_option("#pa-orientation-column", "L")
    page.select_option("#pa-orientation-row", "F")
    assert hint.is_hidden() and page.get_attribute("#missing", "data-ready") == "true", _missing(page)
    assert not watch.posted_jobs() and not watch.errors, watch.errors
    context.close()


# ---------------------------------------------------------------- 5. the lateral film's first level


def test_the_lateral_film_starts_at_the_pa_films_first_level(
    browser: Any, live_url: str, api_key: str, films: dict[str, Path]
) -> None:
    """A lateral film opened with nothing on the PA film starts at T1; opened after T4–T8 are placed on the PA
    film, at T4 (the next click places T4's midpoint)."""
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    open_film(page, "lateral", films["lateral"])
    assert page.input_value("#lateral-level") == "T1"
    page.click("#lateral-close")
    open_film(page, "pa", films["pa"])
    page.select_option("#pa-level", "T4")
    click_pa_midpoints(page, range(3, 8))
    assert "5 vertebrae on the PA film (T4–T8)" in (page.text_content("#pa-status") or "")
    open_film(page, "lateral", films["lateral"])
    assert page.input_value("#lateral-level") == "T4"
    assert (page.text_content("#lateral-prompt") or "") == "Next: the top endplate midpoint of T4."
    page.mouse.click(*canvas_point(page, "lateral", 280, 200))
    assert "1 vertebra on the lateral film (T4–T4)" in (page.text_content("#lateral-status") or "")
    assert not watch.errors, watch.errors
    context.close()
