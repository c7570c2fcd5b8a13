"""Edits of a film's landmarks that must never cost a radiographer their work, in Debian's Chromium
against a real `spine serve`: "Close film" is undone (the Undo button or Ctrl+Z) with the film, its
header and its landmarks, and says what it removed; every landmark of a film is relabelled one level
up or down the spine at once (a radiographer who started one level off), refused with the reason when
a level would leave T1–L5, and undone like any other edit."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from page_fixtures import (
    click_pa_midpoints,
    make_dicom,
    make_png,
    open_film,
    open_page,
    payload_preview,
)

pytestmark = pytest.mark.browser

QUICK_MS = 5_000  # a control that exists is clicked at once; one missing fails the test in 5 s, not 30 s


def _levels(page: Any) -> list[str]:
    payload = payload_preview(page)
    return [lm["level"] for lm in payload["pa"]["landmarks"]] if isinstance(payload, dict) else []


def test_close_film_is_undone_with_its_landmarks_and_says_what_it_removed(
    browser: Any, live_url: str, api_key: str, tmp_path: Path
) -> None:
    make_dicom(tmp_path / "pa.dcm", view="pa")
    make_dicom(tmp_path / "pa-other.dcm", view="pa", size=(400, 700))
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    open_film(page, "pa", tmp_path / "pa.dcm")
    click_pa_midpoints(page, range(6))
    placed = payload_preview(page)["pa"]["landmarks"]
    assert [lm["level"] for lm in placed] == ["T1", "T2", "T3", "T4", "T5", "T6"]
    header = page.text_content("#pa-header") or ""
    assert "PAT-0042" in header, header

    # a misclick on "Close film": the panel is empty, and says what went and how to bring it back
    page.click("#pa-close")
    assert payload_preview(page) == "Give landmarks first."
    status = page.text_content("#pa-status") or ""
    said = "Closed the film pa.dcm: the landmarks of 6 vertebrae (T1–T6): 6 midpoints on it were removed"
    assert said in status, status
    assert "Undo" in status, status
    assert page.is_enabled("#pa-undo")

    # Ctrl+Z on the film brings back the film, its header and its landmarks exactly
    page.focus("#pa-canvas")
    page.keyboard.press("Control+z")
    assert payload_preview(page)["pa"]["landmarks"] == placed
    assert "pa.dcm" in (page.get_attribute("#pa-canvas", "aria-label") or "")
    assert (page.text_content("#pa-header") or "") == header
    assert "Undone: the film pa.dcm and the landmarks of 6 vertebrae" in (page.text_content("#pa-status") or "")
    # the undo history of the placements came back with them; redo goes forward again
    page.keyboard.press("Control+z")
    assert _levels(page) == ["T1", "T2", "T3", "T4", "T5"]
    page.keyboard.press("Control+Shift+z")
    assert payload_preview(page)["pa"]["landmarks"] == placed

    # the buttons too: close, Undo, then Redo closes again
    page.click("#pa-close")
    page.click("#pa-undo")
    assert payload_preview(page)["pa"]["landmarks"] == placed
    page.click("#pa-redo")
    assert payload_preview(page) == "Give landmarks first."
    assert "Closed the film pa.dcm" in (page.text_content("#pa-status") or "")

    # another film opened after the close: the closed one is gone for good (its landmarks are not put on this one)
    open_film(page, "pa", tmp_path / "pa-other.dcm")
    assert page.is_disabled("#pa-undo")
    page.focus("#pa-canvas")
    page.keyboard.press("Control+z")
    assert payload_preview(page) == "Give landmarks first."
    assert "pa-other.dcm" in (page.get_attribute("#pa-canvas", "aria-label") or "")
    assert not watch.errors, watch.errors
    context.close()


def test_ctrl_z_in_the_film_panel_undoes_landmarks_never_the_typed_spacing(
    browser: Any, live_url: str, api_key: str, tmp_path: Path
) -> None:
    """A PNG's pixel spacing typed, 5 midpoints placed, the Undo button clicked: Ctrl+Z with the focus on
    that button (or on the level list) undid the browser's last typing, the spacing 0.45 → 0.4, out of sight,
    and the page said "Ready to send". It undoes a landmark; in the spacing field it undoes its typing."""
    make_png(tmp_path / "pa.png")
    context, page, watch = open_page(browser, f"{live_url}/", api_key, height=1100)
    page.set_input_files("#pa-file", str(tmp_path / "pa.png"))
    page.wait_for_selector("#pa-header dd")
    page.click("#pa-spacing")
    page.keyboard.type("0.45")
    click_pa_midpoints(page, range(5))
    page.click("#pa-undo")
    assert _levels(page) == ["T1", "T2", "T3", "T4"]
    page.keyboard.press("Control+z")  # the focus on the Undo button
    assert page.input_value("#pa-spacing") == "0.45"
    assert _levels(page) == ["T1", "T2", "T3"]
    page.focus("#pa-level")
    page.keyboard.press("Control+Shift+z")
    assert page.input_value("#pa-spacing") == "0.45" and _levels(page) == ["T1", "T2", "T3", "T4"]
    page.focus("#pa-spacing")  # in the field itself, Ctrl+Z is the field's own
    page.keyboard.press("Control+z")
    assert page.input_value("#pa-spacing") != "0.45" and _levels(page) == ["T1", "T2", "T3", "T4"]
    assert not watch.errors, watch.errors
    context.close()


def test_all_levels_of_a_film_are_relabelled_one_level_refused_outside_t1_l5_and_undone(
    browser: Any, live_url: str, api_key: str, tmp_path: Path
) -> None:
    make_dicom(tmp_path / "pa.dcm", view="pa")
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    open_film(page, "pa", tmp_path / "pa.dcm")
    click_pa_midpoints(page, range(5))  # placed as T1–T5, but they were T2–T6
    placed = payload_preview(page)["pa"]["landmarks"]
    points = [lm["point"] for lm in placed]
    assert _levels(page) == ["T1", "T2", "T3", "T4", "T5"]

    page.click("#pa-shift-down", timeout=QUICK_MS)
    moved = payload_preview(page)["pa"]["landmarks"]
    assert [lm["level"] for lm in moved] == ["T2", "T3", "T4", "T5", "T6"]
    assert [lm["point"] for lm in moved] == points  # relabelled, not moved
    status = page.text_content("#pa-status") or ""
    assert "Relabelled one level down: the landmarks of T1–T5 are now of T2–T6" in status, status

    page.click("#pa-shift-up", timeout=QUICK_MS)
    assert _levels(page) == ["T1", "T2", "T3", "T4", "T5"]
    # T1 cannot go up: refused, nothing changed, and why
    page.click("#pa-shift-up", timeout=QUICK_MS)
    assert payload_preview(page)["pa"]["landmarks"] == placed
    status = page.text_content("#pa-status") or ""
    assert "Not relabelled: T1's landmarks would become the level above T1" in status, status

    # each relabelling is one step of Undo and Redo
    page.focus("#pa-canvas")
    page.keyboard.press("Control+z")
    assert _levels(page) == ["T2", "T3", "T4", "T5", "T6"]
    page.keyboard.press("Control+z")
    assert payload_preview(page)["pa"]["landmarks"] == placed
    page.keyboard.press("Control+Shift+z")
    assert _levels(page) == ["T2", "T3", "T4", "T5", "T6"]

    # L5 placed: down is refused (a level below L5 is no level of the payload)
    page.select_option("#pa-level", "L5")
    click_pa_midpoints(page, [16])
    assert _levels(page) == ["T2", "T3", "T4", "T5", "T6", "L5"]
    page.click("#pa-shift-down", timeout=QUICK_MS)
    assert _levels(page) == ["T2", "T3", "T4", "T5", "T6", "L5"]
    status = page.text_content("#pa-status") or ""
    assert "Not relabelled: L5's landmarks would become the level below L5" in status, status
    page.click("#pa-shift-up")
    assert _levels(page) == ["T1", "T2", "T3", "T4", "T5", "L4"]
    assert not watch.errors, watch.errors
    context.close()
