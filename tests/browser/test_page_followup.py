"""The Follow-up view in Debian's Chromium against a real `spine serve`: three succeeded jobs of one
patient with study dates give the table by date, one plot per measure and a flagged progression.

The jobs are real (posted to the service, run by its worker). To show an 8° progression with SDs of
1.5°, the test then sets the major curve's angle and SD in the three stored results (40°, 48°, 49.5°,
all ± 1.5°): 1.96 × √(1.5² + 1.5²) = 4.2° is below 5°, so 8° is flagged by the 5° convention and the
1.5° change after it is not. The flags are computed by the API from the stored results.

Model estimates: the API says per value why it comes from the spine model's prior (`MeasureValue.
model_estimate`, from the stored result's `fit.unreliable` and `fit.assumed` by services/core/estimates.py);
the test sets those two lists in the stored results, so the reasons are the service's own.
"""

from __future__ import annotations

import re
import time
import uuid
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import httpx
import pytest
from page_fixtures import open_page, pdf_text, run_axe
from sqlalchemy import select

from services.core.config import Settings
from services.db.engine import session_factory
from services.db.models import Job
from tests.conftest import spine_payload

pytestmark = pytest.mark.browser

VISITS = [("2025-01-10", 40.0), ("2025-07-08", 48.0), ("2026-01-12", 49.5)]  # study date, major Cobb (deg)
SD = 1.5


def _jobs(url: str, key: str, patient: str, dates: list[str]) -> list[str]:
    """One real succeeded job per study date, each its own study of ``patient``."""
    headers = {"Authorization": f"Bearer {key}"}
    ids = []
    for i, when in enumerate(dates):
        payload: dict[str, Any] = spine_payload(curve_mm=30.0 + 5 * i)
        payload["study"] = {"study_instance_uid": f"1.2.826.0.1.3680043.8.498.{uuid.uuid4().int % 10**12}",
                            "patient_id": patient, "study_date": when}  # fmt: skip
        response = httpx.post(f"{url}/v1/jobs", json=payload, headers=headers, timeout=30)
        assert response.status_code == 202, response.text
        ids.append(response.json()["id"])
    deadline = time.monotonic() + 90
    while True:
        states = [httpx.get(f"{url}/v1/jobs/{j}", headers=headers, timeout=10).json()["status"] for j in ids]
        if all(s == "succeeded" for s in states):
            break
        assert time.monotonic() < deadline and not {"failed", "cancelled"} & set(states), states
        time.sleep(0.3)
    return ids


def _set_results(data_dir: Path, ids: list[str], major: list[tuple[float, float]],
                 fits: list[dict[str, Any]] | None = None) -> None:  # fmt: skip
    """Set each stored result's major Cobb angle and SD (deg) and, when given, update its ``fit``."""
    with session_factory(Settings(data_dir=data_dir, DATABASE_URL=None))() as session:
        for i, (job_id, (angle, sd)) in enumerate(zip(ids, major, strict=True)):
            job = session.scalars(select(Job).where(Job.id == uuid.UUID(job_id))).one()
            result = dict(job.result or {})
            curves = [dict(c) for c in result["measures"]["cobb"]]
            curve = next(c for c in curves if c["major"])
            curve.update(angle_deg=angle, angle_sd_deg=sd)
            result["measures"] = {**result["measures"], "cobb": curves}
            if fits is not None:
                result["fit"] = {**result["fit"], **fits[i]}
            job.result = result
        session.commit()


def _three_jobs(url: str, key: str, data_dir: Path, patient: str) -> list[str]:
    ids = _jobs(url, key, patient, [d for d, _ in VISITS])
    _set_results(data_dir, ids, [(angle, SD) for _, angle in VISITS])
    return ids


def test_follow_up_of_three_visits_flags_an_8_deg_progression(
    browser: Any, live_url: str, api_key: str, live_data_dir: Path, tmp_path: Path
) -> None:
    patient = f"FU-{uuid.uuid4().hex[:8]}"
    ids = _three_jobs(live_url, api_key, live_data_dir, patient)
    context, page, watch = open_page(browser, f"{live_url}/", api_key)

    # from a job: its result links to the patient's follow-up
    page.goto(f"{live_url}/#/jobs/{ids[2]}")
    page.wait_for_selector("#job-status[data-status=succeeded]", timeout=30_000)
    page.click("#followup-link")
    page.wait_for_selector(f"#followup[data-patient='{patient}'] table")
    rows = page.locator(".followup-visits tbody tr")
    assert rows.count() == 3
    assert [rows.nth(i).locator("th").text_content() for i in range(3)] == [d for d, _ in VISITS]
    assert "48.0° ± 1.5°" in (rows.nth(1).text_content() or "")
    flagged = page.locator(".followup-changes tr[data-measure=major_cobb]")
    assert flagged.count() == 2
    first, second = flagged.nth(0), flagged.nth(1)
    assert first.get_attribute("data-flagged") == "true" and "+8.0°" in (first.text_content() or "")
    assert "5° convention" in (first.text_content() or "")
    assert second.get_attribute("data-flagged") == "false" and "+1.5°" in (second.text_content() or "")
    assert "Major Cobb +8.0° (2025-01-10 → 2025-07-08)" in (page.text_content("#followup-summary") or "")
    # one plot per measure, the flagged segment drawn in red
    assert page.locator(".followup-plot").count() >= 4
    plot = page.locator(".followup-plot[data-measure=major_cobb]")
    assert plot.locator("circle").count() == 3 and plot.locator("line.trend.flagged").count() == 1
    assert "1 flagged change" in (plot.get_attribute("aria-label") or "")
    assert not run_axe(page)

    # from a patient ID typed in the form
    page.goto(f"{live_url}/#/follow-up")
    page.fill("#followup-patient", patient)
    page.click("#followup-form button[type=submit]")
    page.wait_for_selector(f"#followup[data-patient='{patient}'] .followup-changes")
    assert page.locator(".followup-visits tbody tr").count() == 3

    # the printed report with the follow-up table
    page.goto(f"{live_url}/#/jobs/{ids[1]}")
    page.wait_for_selector(f"#result[data-job-id='{ids[1]}']", timeout=30_000)
    page.check("#print-followup")
    page.wait_for_selector("#report-followup table.followup-changes")
    page.emulate_media(media="print")
    pdf = tmp_path / "report.pdf"
    page.pdf(path=str(pdf), format="A4", print_background=True)
    text = pdf_text(pdf)
    assert f"Follow-up of patient {patient}" in text and "2025-07-08" in text
    assert not watch.errors, watch.errors
    context.close()


def test_follow_up_says_visits_and_why_an_undated_visit_is_off_the_time_axis(
    browser: Any, live_url: str, api_key: str
) -> None:
    """Two real jobs of one patient, one without a study date: the page counts visits (not jobs), and says
    that the undated visit is left out of the time axis and why; its row stays in the table."""
    patient = f"FU-{uuid.uuid4().hex[:8]}"
    headers = {"Authorization": f"Bearer {api_key}"}
    ids = []
    for date in ("2025-03-04", None):
        payload: dict[str, Any] = spine_payload(curve_mm=30.0)
        payload["study"] = {"study_instance_uid": f"1.2.826.0.1.3680043.8.498.{uuid.uuid4().int % 10**12}",
                            "patient_id": patient, **({"study_date": date} if date else {})}  # fmt: skip
        response = httpx.post(f"{live_url}/v1/jobs", json=payload, headers=headers, timeout=30)
        assert response.status_code == 202, response.text
        ids.append(response.json()["id"])
    deadline = time.monotonic() + 90

    def states() -> set[str]:
        return {httpx.get(f"{live_url}/v1/jobs/{j}", headers=headers, timeout=10).json()["status"] for j in ids}

    while states() != {"succeeded"}:
        assert time.monotonic() < deadline
        time.sleep(0.3)
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    page.evaluate(f"() => location.hash = '#/follow-up/{patient}'")
    page.wait_for_selector(f"#followup[data-patient='{patient}'] table")
    summary = page.text_content("#followup-summary") or ""
    assert summary.startswith(f"2 visits of patient {patient};"), summary
    undated = page.text_content("#followup-undated") or ""
    assert f"One visit has no study date: job {ids[1][:8]}" in undated, undated
    assert "left out of the time axis" in undated and "Study Date (0008,0020)" in undated, undated
    rows = page.locator(".followup-visits tbody tr")
    assert [rows.nth(i).locator("th").text_content() for i in range(2)] == [
        "2025-03-04", "no study date: not on the time axis"]  # fmt: skip
    kyphosis = page.locator(".followup-plot[data-measure=kyphosis_t4_t12] > circle.point")  # its points, not its legend
    assert kyphosis.count() == 1  # the dated visit only
    assert "visits" in (page.text_content("#followup-help") or "")
    assert not run_axe(page)
    assert not watch.errors, watch.errors
    context.close()


COBB_REASON = "the PA film's landmarks do not reach every level from T1 to L5"  # services/core/estimates.py
POPULATION_COBB_SD = 18.4  # the major Cobb angle's population SD, the floor of a model-estimated one (docs/measures.md)


def test_follow_up_marks_model_estimates_and_the_changes_that_compare_them(
    browser: Any, live_url: str, api_key: str, live_data_dir: Path, tmp_path: Path
) -> None:
    """Three real jobs of one patient: the first and last measured (their stored fit lists nothing in
    `unreliable` or `assumed`), the middle one's frontal Cobb angles model estimates (`fit.unreliable`
    ["cobb"], the major 48° ± 18.4°). The middle visit's Major and Minor Cobb carry the mark with the
    service's reason as tooltip, and nothing else of any visit does; each Cobb change to or from it says
    it compares a model estimate, the kyphosis changes do not; its Major Cobb point is hollow with a legend
    entry; the printed report has the marks and the reason in words."""
    patient = f"FU-{uuid.uuid4().hex[:8]}"
    dates = ["2025-01-10", "2025-07-08", "2026-01-12"]
    ids = _jobs(live_url, api_key, patient, dates)
    measured: dict[str, Any] = {"unreliable": [], "assumed": []}
    _set_results(live_data_dir, ids, [(40.0, SD), (48.0, POPULATION_COBB_SD), (49.5, SD)],
                 [measured, {"unreliable": ["cobb"], "assumed": []}, measured])  # fmt: skip
    answer = httpx.get(f"{live_url}/v1/patients/{patient}/measures", headers={"Authorization": f"Bearer {api_key}"},
                       timeout=10).json()  # fmt: skip
    reason = answer["visits"][1]["major_cobb"]["model_estimate"]
    assert reason and reason.startswith(COBB_REASON), answer["visits"][1]

    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    page.evaluate(f"() => location.hash = '#/follow-up/{patient}'")
    page.wait_for_selector(f"#followup[data-patient='{patient}'] table.followup-changes")
    rows = page.locator(".followup-visits tbody tr")
    assert [rows.nth(i).locator("th").text_content() for i in range(3)] == dates
    # the model-estimated visit: its two frontal Cobb angles marked, the reason as the mark's tooltip
    marked = rows.nth(1).locator("td.is-model")
    measures = sorted(marked.nth(i).get_attribute("data-measure") or "" for i in range(marked.count()))
    assert measures == ["major_cobb", "minor_cobb"]
    mark = marked.nth(0).locator(".model-mark")
    assert mark.text_content() == "model estimate"
    assert mark.get_attribute("title") == f"From the model's prior: {reason}."
    assert "48.0° ± 18.4°" in (marked.nth(0).text_content() or "")
    # the measured visits: no mark
    for i in (0, 2):
        assert rows.nth(i).locator(".model-mark").count() == 0, rows.nth(i).text_content()
    notes = page.text_content("#followup .followup-estimates") or ""
    assert f"Major Cobb of 2025-07-08; Minor Cobb of 2025-07-08: {reason}." in notes, notes
    # every Cobb change involves the middle visit; no kyphosis change involves a model estimate
    for measure in ("major_cobb", "minor_cobb"):
        changes = page.locator(f".followup-changes tr[data-measure={measure}]")
        assert changes.count() == 2
        for i in range(2):
            row = changes.nth(i)
            assert row.get_attribute("data-model-estimate") == "true"
            note = row.locator("td").nth(1).locator(".model-mark")
            assert note.text_content() == "compares a model estimate"
            assert f"The 2025-07-08 value is a model estimate: {reason}." in (note.get_attribute("title") or "")
    kyphosis = page.locator(".followup-changes tr[data-measure=kyphosis_t4_t12]")
    assert kyphosis.count() == 2
    assert "model estimate" not in (kyphosis.nth(0).text_content() or "") + (kyphosis.nth(1).text_content() or "")
    # the plots: the model estimate hollow (white fill, the CSS's), with a legend entry; a measured plot has neither
    plot = page.locator(".followup-plot[data-measure=major_cobb]")
    assert plot.locator("> circle.point").count() == 3
    hollow = plot.locator("> circle.point.model-estimate")
    assert hollow.count() == 1
    assert hollow.evaluate("c => getComputedStyle(c).fill") == "rgb(255, 255, 255)"
    assert plot.locator(".plot-legend").text_content() == "from the filmsmodel estimate"
    assert "2025-07-08 48.0° ± 18.4° (model estimate)" in (plot.get_attribute("aria-label") or "")
    level = page.locator(".followup-plot[data-measure=kyphosis_t4_t12]")
    assert level.locator(".model-estimate").count() == 0 and level.locator(".plot-legend").count() == 0
    assert not run_axe(page)

    # the printed report: the marks and the reason in words (a tooltip does not print)
    page.goto(f"{live_url}/#/jobs/{ids[1]}")
    page.wait_for_selector(f"#result[data-job-id='{ids[1]}']", timeout=30_000)
    page.check("#print-followup")
    page.wait_for_selector("#report-followup table.followup-changes")
    page.emulate_media(media="print")
    assert page.locator("#report-followup .followup-visits tbody tr").nth(1).locator(".model-mark").count() == 2
    assert page.locator("#report-followup .followup-changes tr[data-model-estimate=true]").count() == 4
    assert page.locator("#report-followup .followup-estimates").is_visible()
    pdf = tmp_path / "report.pdf"
    page.pdf(path=str(pdf), format="A4", print_background=True)
    text = " ".join(pdf_text(pdf).split())
    assert f"Major Cobb of 2025-07-08; Minor Cobb of 2025-07-08: {COBB_REASON}" in text, text
    assert not watch.errors, watch.errors
    context.close()


DATE = re.compile(r"\d{4}-\d{2}")  # a time-axis label (year and month, or the day), not a degree tick


def test_follow_up_plot_ticks_never_read_minus_zero(
    browser: Any, live_url: str, api_key: str, live_data_dir: Path
) -> None:
    """Two real jobs whose stored major Cobb angles are 1.2° and 2.0°, both ± 0.8° (a straight spine):
    the plot's axis runs from 1.2 − 1.96 × 0.8 = −0.37° less a tenth of its 5° span, so its lower tick,
    a tenth of the axis up (measurePlot), is −0.27°: written "0°", never "-0", and each tick is a whole
    degree drawn at its own height."""
    patient = f"FU-{uuid.uuid4().hex[:8]}"
    ids = _jobs(live_url, api_key, patient, ["2025-02-03", "2025-09-01"])
    _set_results(live_data_dir, ids, [(1.2, 0.8), (2.0, 0.8)])
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    page.evaluate(f"() => location.hash = '#/follow-up/{patient}'")
    page.wait_for_selector(f"#followup[data-patient='{patient}'] .followup-plot[data-measure=major_cobb]")
    labels = page.locator(".followup-plot[data-measure=major_cobb] text.tick")
    ticks = [labels.nth(i) for i in range(labels.count()) if not DATE.match(labels.nth(i).text_content() or "")]
    texts = [t.text_content() for t in ticks]
    assert texts == ["0°", "5°"], texts
    # each tick at the height of its own value: the lower one at the point of 0°, between the two visits' bars
    heights = [float(t.get_attribute("y") or "nan") - 4 for t in ticks]
    per_degree = (heights[0] - heights[1]) / 5
    first = page.locator(".followup-plot[data-measure=major_cobb] > circle.point").first
    point = float(first.get_attribute("cy") or "nan")
    assert point == pytest.approx(heights[0] - 1.2 * per_degree, abs=0.01)
    assert not watch.errors, watch.errors
    context.close()


def test_follow_up_tells_same_day_visits_apart(browser: Any, live_url: str, api_key: str, live_data_dir: Path) -> None:
    """Two real jobs of one patient, two studies of the same study date (a film repeated on the day) with
    major Cobb angles 40° and 47° ± 1.5°: the 7° change is flagged by the service (5° rule), but it is
    not a progression over time. The changes table and the summary name the two jobs and say so, and
    the plot's time axis says the one day once (a month, or the same label twice, told nothing). In the
    plot the two points lie side by side, at least a point's diameter apart (2 × its radius, read from the
    drawing) and centred on the date's tick (the time axis stays the date's), each named by its job in
    its tooltip and in the plot's description."""
    patient = f"FU-{uuid.uuid4().hex[:8]}"
    ids = _jobs(live_url, api_key, patient, ["2025-04-02", "2025-04-02"])
    _set_results(live_data_dir, ids, [(40.0, SD), (47.0, SD)])
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    page.evaluate(f"() => location.hash = '#/follow-up/{patient}'")
    page.wait_for_selector(f"#followup[data-patient='{patient}'] table.followup-changes")
    first, second = (page.locator(".followup-visits tbody tr").nth(i).locator("a").text_content() for i in range(2))
    row = page.locator(".followup-changes tr[data-measure=major_cobb]")
    assert row.get_attribute("data-flagged") == "true" and row.get_attribute("data-same-day") == "true"
    between = row.locator("td").nth(0).text_content() or ""
    assert f"2025-04-02 (job {first}) → 2025-04-02 (job {second})" in between, between
    assert "not a progression over time" in between, between
    summary = page.text_content("#followup-summary") or ""
    assert f"(job {first})" in summary and "not a progression over time" in summary, summary
    labels = page.locator(".followup-plot[data-measure=major_cobb] text.tick")
    dates = [text for i in range(labels.count()) if DATE.match(text := labels.nth(i).text_content() or "")]
    assert dates == ["2025-04-02"], dates
    plot = page.locator(".followup-plot[data-measure=major_cobb]")
    points = plot.locator(":scope > circle.point")
    assert points.count() == 2
    cx = [float(points.nth(i).get_attribute("cx") or "nan") for i in range(2)]
    radius = float(points.nth(0).get_attribute("r") or "nan")
    assert abs(cx[1] - cx[0]) >= 2 * radius, cx  # not drawn over each other
    tick = float(plot.locator("text.date-tick").get_attribute("x") or "nan")
    assert (cx[0] + cx[1]) / 2 == pytest.approx(tick, abs=0.01)  # around the date, not moved in time
    tips = [points.nth(i).locator("title").text_content() or "" for i in range(2)]
    assert f"(job {first}) 40.0° ± 1.5°" in tips[0] and f"(job {second}) 47.0° ± 1.5°" in tips[1], tips
    described = plot.get_attribute("aria-label") or ""
    assert f"(job {first})" in described and f"(job {second})" in described and "side by side" in described, described
    assert not watch.errors, watch.errors
    context.close()


def test_follow_up_names_the_patients_jobs_that_are_not_visits(
    browser: Any, live_url: str, api_key: str, live_data_dir: Path
) -> None:
    """Three real jobs of one patient, each its own study; then, in the service's database, the second
    marked failed (with an error) and the third running (with a lease an hour ahead, which the
    reconciler leaves alone): the follow-up has one visit (succeeded jobs only, the API's rule) and the
    page names the other two jobs, their study dates and states, instead of leaving them out silently."""
    patient = f"FU-{uuid.uuid4().hex[:8]}"
    ids = _jobs(live_url, api_key, patient, ["2024-10-01", "2025-04-01", "2025-10-01"])
    with session_factory(Settings(data_dir=live_data_dir, DATABASE_URL=None))() as session:
        failed = session.scalars(select(Job).where(Job.id == uuid.UUID(ids[1]))).one()
        failed.status, failed.result = "failed", None
        failed.error = {"type": "about:blank", "title": "Fit failed", "status": 422, "detail": "set by the test"}
        running = session.scalars(select(Job).where(Job.id == uuid.UUID(ids[2]))).one()
        running.status, running.result, running.finished_at = "running", None, None
        running.lease_expires_at = datetime.now(UTC) + timedelta(hours=1)
        session.commit()
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    page.evaluate(f"() => location.hash = '#/follow-up/{patient}'")
    page.wait_for_selector(f"#followup[data-patient='{patient}'] table.followup-visits")
    assert page.locator(".followup-visits tbody tr").count() == 1
    note = page.text_content("#followup-not-visits") or ""
    assert note.startswith("2 jobs of this patient are not in the follow-up"), note
    assert f"job {ids[1][:8]} (study date 2025-04-01) failed" in note, note
    assert f"job {ids[2][:8]} (study date 2025-10-01) is still running" in note, note
    assert not run_axe(page)

    # the printed report's follow-up table names them too, in the same words
    page.evaluate(f"() => location.hash = '#/jobs/{ids[0]}'")
    page.wait_for_selector(f"#result[data-job-id='{ids[0]}']", timeout=30_000)
    page.check("#print-followup")
    page.wait_for_selector("#report-followup table.followup-changes")
    page.emulate_media(media="print")
    assert page.is_visible("#report-followup-not-visits")
    assert (page.text_content("#report-followup-not-visits") or "") == note
    assert not watch.errors, watch.errors
    context.close()


def test_printing_the_follow_up_page_prints_no_search_form(browser: Any, live_url: str, api_key: str) -> None:
    """The follow-up page printed (print stylesheet): the visits, not the form that asked for them."""
    patient = f"FU-{uuid.uuid4().hex[:8]}"
    _jobs(live_url, api_key, patient, ["2025-05-06"])
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    page.evaluate(f"() => location.hash = '#/follow-up/{patient}'")
    page.wait_for_selector(f"#followup[data-patient='{patient}'] table.followup-visits")
    assert page.is_visible("#followup-form")
    page.emulate_media(media="print")
    for control in ("#followup-form", "#followup-patient", "#followup-form button", "#followup-help"):
        assert page.is_hidden(control), control
    assert page.is_visible("table.followup-visits") and page.is_visible("#followup-summary")
    assert page.is_visible("#h-follow-up")
    assert not watch.errors, watch.errors
    context.close()


def test_follow_up_says_the_sign_of_each_signed_measure(browser: Any, live_url: str, api_key: str) -> None:
    """Kyphosis, lordosis and axial rotation are signed (a negative kyphosis is a lordotic thoracic spine,
    an axial rotation's sign its side): the visits table's heads and the plots' descriptions say each
    sign in the result view's words; the Cobb angles, magnitudes, say none."""
    patient = f"FU-{uuid.uuid4().hex[:8]}"
    _jobs(live_url, api_key, patient, ["2025-05-06"])
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    page.evaluate(f"() => location.hash = '#/follow-up/{patient}'")
    page.wait_for_selector(f"#followup[data-patient='{patient}'] table.followup-visits")
    heads = page.locator(".followup-visits thead th")
    words = [heads.nth(i).text_content() for i in range(heads.count())]
    assert words[2:] == [
        "Major Cobb",
        "Minor Cobb",
        "Kyphosis T4–T12 (positive: convex posteriorly)",
        "Lordosis L1–L5 (positive: convex anteriorly)",
        "Apex axial rotation (positive: toward the patient's left, seen from above)",
    ], words
    label = page.get_attribute(".followup-plot[data-measure=kyphosis_t4_t12]", "aria-label") or ""
    assert label.startswith("Kyphosis T4–T12 (positive: convex posteriorly) over time: 2025-05-06 "), label
    assert not run_axe(page)
    assert not watch.errors, watch.errors
    context.close()


def test_a_slow_follow_up_answer_does_not_replace_the_patient_asked_for_since(
    browser: Any, live_url: str, api_key: str
) -> None:
    """Patient A's follow-up asked for, then patient B's before A's answer came (A's held here, as a slow
    service would): B's follow-up is shown, and A's answer, arriving last, does not replace it under B's
    address."""
    first, second = f"FU-{uuid.uuid4().hex[:8]}", f"FU-{uuid.uuid4().hex[:8]}"
    _jobs(live_url, api_key, first, ["2025-01-02"])
    _jobs(live_url, api_key, second, ["2025-03-04", "2025-09-10"])
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    held: list[Any] = []
    page.route(f"**/v1/patients/{first}/measures", lambda route: held.append(route))
    page.evaluate(f"() => location.hash = '#/follow-up/{first}'")
    for _ in range(100):
        if held:
            break
        page.wait_for_timeout(50)
    assert held, "the page did not ask for the first patient's follow-up"
    page.evaluate(f"() => location.hash = '#/follow-up/{second}'")
    page.wait_for_selector(f"#followup[data-patient='{second}'] table.followup-visits")
    for route in held:
        route.continue_()
    page.unroute(f"**/v1/patients/{first}/measures")
    page.wait_for_load_state("networkidle")
    page.wait_for_timeout(300)
    assert page.get_attribute("#followup", "data-patient") == second
    assert (page.text_content("#followup-summary") or "").startswith(f"2 visits of patient {second};")
    assert page.input_value("#followup-patient") == second
    assert not watch.errors, watch.errors
    context.close()


def test_a_slow_follow_up_for_the_report_is_not_printed_with_another_job(
    browser: Any, live_url: str, api_key: str
) -> None:
    """The box "Include the follow-up table in the printed report" ticked on a job of patient A, whose follow-up
    answer is slow (held here); job B of patient B opened before it came: B's report has no follow-up
    table, and A's answer, arriving last, does not put A's visits into B's printed report."""
    first, second = f"FU-{uuid.uuid4().hex[:8]}", f"FU-{uuid.uuid4().hex[:8]}"
    (job_a,) = _jobs(live_url, api_key, first, ["2025-01-02"])
    (job_b,) = _jobs(live_url, api_key, second, ["2025-03-04"])
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    page.evaluate(f"() => location.hash = '#/jobs/{job_a}'")
    page.wait_for_selector(f"#result[data-job-id='{job_a}']", timeout=30_000)
    held: list[Any] = []
    page.route(f"**/v1/patients/{first}/measures", lambda route: held.append(route))
    page.check("#print-followup")
    for _ in range(100):
        if held:
            break
        page.wait_for_timeout(50)
    assert held, "the page did not ask for the patient's follow-up"
    page.evaluate(f"() => location.hash = '#/jobs/{job_b}'")
    page.wait_for_selector(f"#result[data-job-id='{job_b}']", timeout=30_000)
    for route in held:
        route.continue_()
    page.unroute(f"**/v1/patients/{first}/measures")
    page.wait_for_load_state("networkidle")
    page.wait_for_timeout(300)
    assert not page.is_checked("#print-followup")
    assert page.is_hidden("#report-followup")
    assert first not in (page.text_content("#report-followup") or "")
    page.emulate_media(media="print")
    assert page.is_hidden("#report-followup")
    assert not watch.errors, watch.errors
    context.close()
