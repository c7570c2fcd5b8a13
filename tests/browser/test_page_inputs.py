"""Placing and importing landmarks, in Debian's Chromium against a real `spine serve`: a level placed
again in the middle moves on to the next level not placed yet (or stays, complete, when every level
below is placed); a pixel CSV gives each film its own pixel spacing (an old CSV with one spacing still
works, and the page says the lateral took the PA's); a CSV number in hexadecimal or another notation
is refused, naming its line and field."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from page_fixtures import LEVELS, canvas_point, centreline, make_dicom, open_page

pytestmark = pytest.mark.browser


def _preview(page: Any) -> Any:
    return json.loads(page.text_content("#payload-preview") or "{}")


def _levels(page: Any) -> list[str]:
    return [lm["level"] for lm in _preview(page)["pa"]["landmarks"]]


def test_placing_a_middle_level_again_moves_on_to_the_next_unplaced_level(
    browser: Any, live_url: str, api_key: str, tmp_path: Path
) -> None:
    make_dicom(tmp_path / "pa.dcm", view="pa")
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    page.set_input_files("#pa-file", str(tmp_path / "pa.dcm"))
    page.wait_for_function("() => /pa.dcm/.test(document.getElementById('pa-canvas').getAttribute('aria-label'))")

    def click(i: int) -> None:
        col, row, _ = centreline(i)
        page.mouse.click(*canvas_point(page, "pa", col, row))

    for i in range(8):  # T1–T8
        click(i)
    assert page.input_value("#pa-level") == "T9"
    page.select_option("#pa-level", "T4")
    click(3)  # T4 placed again: T5–T8 are placed, T9 is not
    assert page.input_value("#pa-level") == "T9"
    assert page.get_attribute("#pa-canvas", "data-next") == "T9 midpoint"
    click(8)
    assert _levels(page) == list(LEVELS[:9]) and page.input_value("#pa-level") == "T10"
    for i in range(9, len(LEVELS)):  # T10–L5
        click(i)
    # every level below T6 placed: T6 placed again stays, complete, and the next click places nothing
    page.select_option("#pa-level", "T6")
    click(5)
    assert page.input_value("#pa-level") == "T6"
    assert "T6 is complete" in (page.text_content("#pa-prompt") or "")
    before = _preview(page)["pa"]["landmarks"]
    click(6)
    assert _preview(page)["pa"]["landmarks"] == before  # nothing placed on T7, nor T6 moved
    assert page.get_attribute("#pa-canvas", "data-next") == "Nothing placed: T6 is complete"
    # pedicles go level by level too: after T3's, T4 (no pedicles yet), not a level that has them
    page.check("#pa-mode-pedicles")
    page.select_option("#pa-level", "T4")
    for dx in (-8, 8):
        col, row, _ = centreline(3)
        page.mouse.click(*canvas_point(page, "pa", col + dx, row + 10))
    assert page.input_value("#pa-level") == "T5"
    page.select_option("#pa-level", "T3")
    for dx in (-8, 8):
        col, row, _ = centreline(2)
        page.mouse.click(*canvas_point(page, "pa", col + dx, row + 10))
    assert page.input_value("#pa-level") == "T5"  # T4 has its pedicles
    assert not watch.errors, watch.errors
    context.close()


def test_a_pixel_csv_gives_each_film_its_own_spacing(browser: Any, live_url: str, api_key: str) -> None:
    rows = ["level,column,row,view"]
    rows += [f"{lv},{300 + i},{100 + 60 * i},pa" for i, lv in enumerate(LEVELS)]
    rows += [f"{lv},{250 - i},{120 + 55 * i},lateral" for i, lv in enumerate(LEVELS)]
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    page.set_default_timeout(5_000)
    page.click("#tab-csv")
    page.fill("#csv-text", "\n".join(rows))
    page.select_option("#csv-units", "px")
    page.fill("#csv-spacing", "0.4")
    page.fill("#csv-spacing-lateral", "0.5")
    page.click("#use-csv")
    assert page.is_hidden("#input-error"), page.text_content("#input-error")
    sent = _preview(page)
    assert sent["pa"]["pixel_spacing"] == [0.4, 0.4] and sent["lateral"]["pixel_spacing"] == [0.5, 0.5]
    assert "taken as the PA" not in (page.text_content("#landmark-summary") or "")
    # an old CSV with one spacing: the lateral film takes the PA film's, and the page says so
    page.fill("#csv-spacing-lateral", "")
    page.click("#use-csv")
    sent = _preview(page)
    assert sent["pa"]["pixel_spacing"] == [0.4, 0.4] and sent["lateral"]["pixel_spacing"] == [0.4, 0.4]
    summary = page.text_content("#landmark-summary") or ""
    assert "The lateral film's pixel spacing is taken as the PA film's, 0.4 mm" in summary, summary
    # a lateral spacing that is no number is refused by name
    page.fill("#csv-spacing-lateral", "-1")
    page.click("#use-csv")
    assert 'the lateral film\'s pixel spacing "-1" is not a positive number' in (
        page.text_content("#input-error") or ""
    )
    assert not watch.errors, watch.errors
    context.close()


def test_a_csv_number_in_hexadecimal_is_refused_naming_line_and_field(
    browser: Any, live_url: str, api_key: str
) -> None:
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    page.click("#tab-csv")
    page.select_option("#csv-units", "mm")
    page.fill("#csv-text", "level,column,row\nT1,0x1A,50\nT2,100,0b110\nT3,0o17,60\nT4,1e2,7.5E1\nT5,,80\n")
    page.click("#use-csv")
    error = page.text_content("#input-error") or ""
    assert 'line 2, field 2 (column): "0x1A" is not a decimal number' in error, error
    assert 'line 3, field 3 (row): "0b110" is not a decimal number' in error, error
    assert 'line 4, field 2 (column): "0o17" is not a decimal number' in error, error
    assert "line 5" not in error, error  # 1e2 and 7.5E1 are decimal
    assert 'line 6: column and row must be finite decimal numbers; field 2 (column) is ""' in error, error
    assert page.text_content("#landmark-summary") == "No landmarks yet."
    page.fill("#csv-text", "level,column,row\nT1,26,50\nT4,1e2,7.5E1\n")
    page.click("#use-csv")
    assert page.is_hidden("#input-error")
    assert [lm["point"] for lm in _preview(page)["pa"]["landmarks"]] == [[26, 50], [100, 75]]
    assert not watch.errors, watch.errors
    context.close()
