"""How the page reads a DICOM film's spacing (PS3.3 §10.7.1.1) and what it refuses, in Chromium:
Pixel Spacing equal to Imager Pixel Spacing is detector spacing ("projection"), Pixel Spacing
alone measures an unknown plane ("unknown"), no spacing at all leaves the field empty and the job
refused until it is typed; a compressed film is refused by name. Only the page is needed."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from page_fixtures import click_pa_midpoints, make_dicom, open_page

pytestmark = pytest.mark.browser


@pytest.mark.parametrize(
    ("spacing", "calibration", "field"),
    [
        ({"PixelSpacing": [0.3, 0.3], "ImagerPixelSpacing": [0.3, 0.3]}, "Calibration: projection.", "0.3"),
        ({"PixelSpacing": [0.25, 0.25]}, "Calibration: unknown.", "0.25"),
        ({}, "The header gives no pixel spacing", ""),
    ],
)
def test_spacing_read_from_the_header(
    browser: Any, live_url: str, tmp_path: Path, spacing: dict[str, list[float]], calibration: str, field: str
) -> None:
    film = tmp_path / "film.dcm"
    make_dicom(film, spacing=spacing)
    context, page, _ = open_page(browser, live_url + "/", None, height=1100)
    page.set_input_files("#pa-file", str(film))
    page.wait_for_selector("#pa-header dd")
    assert calibration in (page.text_content("#pa-header") or "")
    assert page.input_value("#pa-spacing") == field
    click_pa_midpoints(page, (0, 16))
    missing = page.text_content("#missing") or ""
    assert ("Enter the pixel spacing of the PA film" in missing) == (field == ""), missing
    assert ("its header gives none" in missing) == (field == "")
    context.close()


def test_a_compressed_film_is_refused_by_name(browser: Any, live_url: str, tmp_path: Path) -> None:
    film = tmp_path / "jpeg.dcm"
    make_dicom(film, transfer_syntax="1.2.840.10008.1.2.4.50")  # JPEG Baseline (PS3.5 §A.4.1)
    context, page, _ = open_page(browser, live_url + "/", None)
    page.set_input_files("#pa-file", str(film))
    page.wait_for_selector("#pa-error:not([hidden])")
    error = page.text_content("#pa-error") or ""
    assert "1.2.840.10008.1.2.4.50" in error and "uncompressed" in error
    assert "Open the PA film" in (page.text_content("#missing") or "")
    context.close()
