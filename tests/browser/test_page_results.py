"""The result side as a surgeon and a radiographer read it, in Debian's Chromium against a real
`spine serve`: the measures CSV names its patient, reads in a spreadsheet as written (UTF-8 with a byte
order mark) and holds no cell a spreadsheet would run as a formula (OWASP "CSV Injection"); a failed
job opened after a succeeded one shows no result of the other job, its problem goes when the other
job is opened again, and the jobs list says in words why a job failed."""

from __future__ import annotations

import csv
import io
import re
import uuid
from pathlib import Path
from typing import Any, get_args

import pytest
from page_fixtures import open_page, pa_points_payload, run_job
from sqlalchemy import select

from services.core.config import Settings
from services.db.engine import session_factory
from services.db.models import Job
from spine_engine.models import AssumptionName

pytestmark = pytest.mark.browser

# OWASP "CSV Injection": a cell starting with one of these is run as a formula by Excel, LibreOffice Calc
# and Google Sheets (tab and carriage return included); a plain number is no formula.
FORMULA_START = re.compile(r"^[=+\-@\t\r]")
NUMBER = re.compile(r"^[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")
BOM = b"\xef\xbb\xbf"  # UTF-8's byte order mark (Unicode §23.8): what tells Excel the file is UTF-8


def _study(**extra: str) -> dict[str, str]:
    return {"study_instance_uid": f"1.2.826.0.1.3680043.8.498.{uuid.uuid4().int % 10**12}", **extra}


def test_measures_csv_names_the_patient_in_utf8_and_holds_no_formula(
    browser: Any, live_url: str, api_key: str, tmp_path: Path
) -> None:
    study = _study(patient_name="Ørsted^Zoë", patient_id="=cmd", study_date="2025-10-01")
    job = run_job(live_url, api_key, {**pa_points_payload(), "study": study})
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    page.goto(f"{live_url}/#/jobs/{job['id']}")
    page.wait_for_selector("#job-status[data-status=succeeded]", timeout=90_000)
    with page.expect_download() as info:
        page.click("#download-measures")
    raw = Path(info.value.path()).read_bytes()
    assert raw.startswith(BOM), raw[:20]
    rows = list(csv.reader(io.StringIO(raw.decode("utf-8-sig"))))
    assert rows[0] == ["measure", "value", "sd", "unit", "model_estimate", "note"]
    about = {r[0]: r[1] for r in rows[1:5]}
    assert about["Patient"] == "Ørsted Zoë", about  # the report head's form of the DICOM PN
    assert about["Patient ID"] == "'=cmd", about  # text, not a formula
    assert about["Study date"] == "2025-10-01" and about["Job"] == job["id"], about
    assert any("Cobb angle" in r[0] for r in rows), rows
    formulas = [c for r in rows for c in r if FORMULA_START.match(c) and not NUMBER.match(c)]
    assert not formulas, formulas
    # a negative measure is a plain number a spreadsheet computes with (its SD a cell of its own), no text mark;
    # the page's table gives the same value
    negative = [r for r in rows[5:] if NUMBER.match(r[1]) and float(r[1]) < 0]
    assert negative, rows
    shown = page.locator("#measures tr", has_text=negative[0][0]).first.text_content() or ""
    assert f"{float(negative[0][1]):.1f}°" in shown, (negative[0], shown)
    assert not watch.errors, watch.errors
    context.close()


def test_a_failed_job_shows_no_other_result_and_the_jobs_list_says_why(
    browser: Any, live_url: str, api_key: str, live_data_dir: Path
) -> None:
    """Two real jobs, the second then marked failed in the service's database with a fit-failed problem
    (the worker's words for a fit that did not converge)."""
    done = run_job(live_url, api_key, {**pa_points_payload(), "study": _study(patient_id="RES-OK")})
    broken = run_job(live_url, api_key, {**pa_points_payload(), "study": _study(patient_id="RES-FAILED")})
    reason = "the fit did not converge within 200 iterations"
    with session_factory(Settings(data_dir=live_data_dir, DATABASE_URL=None))() as session:
        failed = session.scalars(select(Job).where(Job.id == uuid.UUID(broken["id"]))).one()
        failed.status, failed.result = "failed", None
        failed.error = {"type": "about:blank", "title": "Fit failed", "status": 422, "detail": reason}
        session.commit()

    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    page.goto(f"{live_url}/#/jobs/{done['id']}")
    page.wait_for_selector("#job-status[data-status=succeeded]", timeout=90_000)
    assert page.is_visible("#result")
    page.goto(f"{live_url}/#/jobs/{broken['id']}")
    page.wait_for_selector("#job-status[data-status=failed]")
    assert reason in (page.text_content("#problem") or "")
    # the succeeded job's measures, 3D view, downloads and report are not left under the failed job's address
    assert page.is_hidden("#result")
    empty = page.text_content("#result-empty") or ""
    assert page.is_visible("#result-empty") and f"Job {broken['id'][:8]} failed" in empty, empty

    # the succeeded job opened again: the failure is not said over its result
    page.goto(f"{live_url}/#/jobs/{done['id']}")
    page.wait_for_selector("#job-status[data-status=succeeded]")
    page.wait_for_selector("#result:not([hidden])")
    assert page.is_hidden("#problem")

    # the jobs list says why the job failed, in the problem's words
    page.goto(f"{live_url}/#/jobs")
    row = page.locator("#jobs-table tbody tr", has_text=broken["id"][:8])
    row.wait_for()
    status = row.locator("td").nth(1).text_content() or ""
    assert status == f"failed: {reason}", status
    ok = page.locator("#jobs-table tbody tr", has_text=done["id"][:8]).locator("td").nth(1).text_content()
    assert ok == "succeeded"
    assert not watch.errors, watch.errors
    context.close()


def test_the_3d_view_says_it_is_loading_and_when_it_cannot_load(browser: Any, live_url: str, api_key: str) -> None:
    """three.js (the viewer's chunk, fetched with the first result) held back by Playwright's routing, as
    on a slow link, then refused, as on a dropped one: the view says it is loading, then that it could not
    load and what does not need it, instead of an empty box; the measures are there meanwhile."""
    job = run_job(live_url, api_key, {**pa_points_payload(), "study": _study()})
    held: list[Any] = []
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    page.route("**/assets/viewer3d-*.js", lambda route: held.append(route))
    page.goto(f"{live_url}/#/jobs/{job['id']}")
    page.wait_for_selector("#job-status[data-status=succeeded]", timeout=90_000)
    page.wait_for_function("() => document.querySelector('#measures tbody tr') !== null")
    assert page.text_content("#view3d-orientation") == "Loading the 3D view…"
    assert page.get_attribute("#view3d", "aria-busy") == "true"
    page.wait_for_function("() => true")  # let the route handler run
    assert held, "the viewer's chunk was not asked for"
    held[0].abort()
    page.wait_for_function(
        "() => /could not be loaded/.test(document.querySelector('#view3d-orientation').textContent)"
    )
    said = page.text_content("#view3d-orientation") or ""
    assert "the measures, the PA and lateral projections and the report below do not need it" in said, said
    assert page.get_attribute("#view3d", "aria-busy") is None
    # the refused chunk's own console line is the only error
    assert [e for e in watch.errors if "ERR_FAILED" not in e] == [], watch.errors
    context.close()


def test_the_jobs_list_reaches_older_jobs_page_by_page(browser: Any, live_url: str, api_key: str) -> None:
    """Three real jobs and the service's real paging (`next_cursor`), its page made 2 jobs long by
    rewriting the page's `limit` (50) in Playwright's routing, so that a list longer than one page needs
    no 51 jobs: the newest 2 are shown with "Show older jobs", which adds the third, newest first."""
    ids = [run_job(live_url, api_key, {**pa_points_payload(), "study": _study()})["id"] for _ in range(3)]
    context, page, watch = open_page(browser, f"{live_url}/", api_key)

    def small_pages(route: Any) -> None:
        route.continue_(url=re.sub(r"([?&])limit=\d+", r"\1limit=2", route.request.url))

    page.route(re.compile(r".*/v1/jobs\?.*"), small_pages)
    page.goto(f"{live_url}/#/jobs")
    page.wait_for_selector("#jobs-table tbody tr")
    shown = page.locator("#jobs-table tbody tr td:first-child a").all_text_contents()
    assert shown == [ids[2][:8], ids[1][:8]], shown
    assert "The newest 2 jobs are shown" in (page.text_content("#jobs-note") or "")
    page.click("#jobs-more", timeout=5_000)
    page.wait_for_function("() => document.querySelectorAll('#jobs-table tbody tr').length > 2")
    shown = page.locator("#jobs-table tbody tr td:first-child a").all_text_contents()
    assert shown[:3] == [ids[2][:8], ids[1][:8], ids[0][:8]], shown
    assert len(shown) == len(set(shown))  # no job twice
    assert not watch.errors, watch.errors
    context.close()


def test_the_printed_report_waits_for_its_own_jobs_figure(browser: Any, live_url: str, api_key: str) -> None:
    """Two real jobs; the second's figure held back by Playwright's routing (a slow service): "Print the
    report" clicked meanwhile does not print the first job's figure under the second's report, nor the
    report without its figure; it prints once the second's figure is in (`window.print` recorded)."""
    first = run_job(live_url, api_key, {**pa_points_payload(), "study": _study()})["id"]
    second = run_job(live_url, api_key, {**pa_points_payload(), "study": _study()})["id"]
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    page.goto(f"{live_url}/#/jobs/{first}")
    page.wait_for_selector("#report-figure[data-loaded=true]", state="attached", timeout=30_000)
    page.evaluate(
        """() => { window.printed = []; window.print = () => { const img = document.getElementById('report-figure');
             window.printed.push({job: document.getElementById('result').dataset.jobId, loaded: img.dataset.loaded,
                                  src: img.getAttribute('src')}); }; }"""
    )
    first_src = page.get_attribute("#report-figure", "src")
    held: list[Any] = []
    page.route(f"**/v1/jobs/{second}/figure.png", lambda route: held.append(route))
    page.goto(f"{live_url}/#/jobs/{second}")
    page.wait_for_function(f"() => document.getElementById('result').dataset.jobId === '{second}'")
    assert page.get_attribute("#report-figure", "src") != first_src  # not the first job's figure
    page.click("#print-report")
    page.wait_for_timeout(300)
    assert page.evaluate("() => window.printed") == []  # not printed without its figure
    assert held, "the figure was not asked for"
    held[0].continue_()
    page.wait_for_function("() => window.printed.length === 1")
    printed = page.evaluate("() => window.printed[0]")
    assert printed["job"] == second and printed["loaded"] == "true" and printed["src"] != first_src, printed
    assert not watch.errors, watch.errors
    context.close()


def test_the_result_says_what_was_assumed_and_a_newer_services_name_as_written(
    browser: Any, live_url: str, api_key: str
) -> None:
    """A real PA-only job, its answer given one more ``fit.assumed`` entry whose name this page does not know,
    as a newer service may add (an extensible enum; rewritten in Playwright's routing): each entry is a row
    "Assumed" of the measures table (", PA film" when it concerns the PA) with the service's reason as its
    note, in the measures CSV too, the unknown name shown as written."""
    job = run_job(live_url, api_key, {**pa_points_payload(), "study": _study(patient_id="RES-ASSUMED")})
    later = {"name": "a_prior_of_a_later_engine", "view": None, "reason": "what a later engine assumed"}
    assumed = [*job["result"]["fit"]["assumed"], later]
    assert {"standing_orientation", "population_sagittal_shape"} <= {a["name"] for a in assumed}, assumed

    def newer(route: Any) -> None:
        answer = route.fetch()
        body = answer.json()
        body["result"]["fit"]["assumed"].append(later)
        route.fulfill(response=answer, json=body)

    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    page.route(re.compile(rf"/v1/jobs/{job['id']}(\?.*)?$"), newer)
    page.goto(f"{live_url}/#/jobs/{job['id']}")
    page.wait_for_selector("#job-status[data-status=succeeded]", timeout=90_000)
    rows = page.locator("#measures tbody tr", has=page.locator("th", has_text=re.compile("^Assumed")))
    heads = [rows.nth(i).locator("th").text_content() or "" for i in range(rows.count())]
    assert len(heads) == len(assumed), heads
    for head, a in zip(heads, assumed, strict=True):
        film = {"pa": "Assumed, PA film", "lateral": "Assumed, lateral film", None: "Assumed"}[a.get("view")]
        assert head.startswith(film) and a["reason"] in head, (head, a)
    assert (rows.nth(len(assumed) - 1).locator("td").text_content() or "").strip() == "a prior of a later engine"
    with page.expect_download() as info:
        page.click("#download-measures")
    csv_rows = list(csv.reader(io.StringIO(Path(info.value.path()).read_bytes().decode("utf-8-sig"))))
    notes = [r[5] for r in csv_rows if r[0].startswith("Assumed")]
    assert notes == [a["reason"] for a in assumed], notes
    assert not watch.errors, watch.errors
    context.close()


def test_the_page_has_words_for_every_assumption_the_engine_names() -> None:
    """The page's few words per ``fit.assumed`` name (web/src/results.ts ``ASSUMED``) cover the engine's
    ``AssumptionName`` exactly: a name the engine adds gets words, not only its name as written (the page's
    way with a newer service's name); read from the source, no browser needed."""
    source = (Path(__file__).resolve().parents[2] / "web" / "src" / "results.ts").read_text(encoding="utf-8")
    block = re.search(r"const ASSUMED: Record<string, string> = \{(.*?)\n\};", source, re.S)
    assert block is not None, "web/src/results.ts has no ASSUMED table"
    assert re.findall(r"^\s*(\w+):", block.group(1), re.M) == list(get_args(AssumptionName))
