"""The page's other inputs and its 3D view, against a real `spine serve`: a CSV refused line by line
then used (with a lateral row), the landmarks saved back as CSV, the sample payload sent with the
API key, and the reconstruction's 3D view in WebGL or in three's SVG fallback (?renderer=svg),
turned by keyboard and by mouse. (These paths were tests/browser/test_web_e2e.py's, whose page
they replace.)"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from page_fixtures import LEVELS, open_page

pytestmark = pytest.mark.browser


def _centre(box: dict[str, float] | None) -> tuple[float, float]:
    assert box is not None
    return box["x"] + box["width"] / 2, box["y"] + box["height"] / 2


@pytest.mark.parametrize("renderer", ["svg", "default"])
def test_csv_then_sample_payload_and_the_3d_view(browser: Any, live_url: str, api_key: str, renderer: str) -> None:
    query = "?renderer=svg" if renderer == "svg" else ""
    context, page, watch = open_page(browser, f"{live_url}/{query}", None)

    # CSV: a bad one is refused line by line, a good one (header, comment, a lateral row) is used
    page.click("#tab-csv")
    page.fill("#csv-text", "level,column,row\nT1,1,2\nT13,3,4\nT2,x,5\n")
    page.click("#use-csv")
    error = page.text_content("#input-error") or ""
    assert 'line 3: level "T13"' in error and "line 4: column and row" in error
    rows = ["level,column,row,view", "# endplate midpoints, detector mm"]
    rows += [f"{lv},{100 + i},{50 + 25 * i}" for i, lv in enumerate(LEVELS)] + ["T1,200,50,lateral"]
    page.fill("#csv-text", "\n".join(rows))
    page.click("#use-csv")
    assert page.is_hidden("#input-error")
    assert "17 PA landmarks, 1 lateral landmark from the CSV." in (page.text_content("#landmark-summary") or "")
    with page.expect_download() as info:
        page.click("#download-landmarks")
    saved = Path(info.value.path()).read_text().splitlines()
    assert saved[0] == "level,column,row,view" and saved[1] == "T1,100,50,pa" and saved[-1] == "T1,200,50,lateral"
    # px without a spacing is refused in words
    page.select_option("#csv-units", "px")
    page.click("#use-csv")
    assert "pixel spacing" in (page.text_content("#input-error") or "")

    # the sample payload, sent with the API key
    page.fill("#api-key", api_key)
    assert page.evaluate("sessionStorage.getItem('spine.apiKey')") == api_key
    page.click("#tab-json")
    page.click("#load-sample")
    assert "17 PA landmarks from the payload." in (page.text_content("#landmark-summary") or "")
    assert '"boundary"' not in (page.text_content("#payload-preview") or "")  # the sample assumes no poses
    with page.expect_response(lambda r: r.request.method == "POST" and r.url.endswith("/v1/jobs")) as posted:
        page.click("#submit")
    assert posted.value.status == 202
    assert posted.value.request.headers.get("authorization") == f"Bearer {api_key}"
    page.wait_for_selector("#job-status[data-status=succeeded]", timeout=90_000)
    page.wait_for_selector("#view3d[data-shown]")
    assert page.locator("#view-pa svg image").count() == 0  # no film: detector mm
    assert page.locator("#strains tbody tr").count() == 17

    view3d = page.locator("#view3d")
    shown = view3d.get_attribute("data-renderer")
    assert shown == "svg" if renderer == "svg" else shown in ("webgl", "svg")
    if shown == "svg":
        assert page.locator("#view3d svg path").count() > 17 * 6  # box faces and edges
    else:
        assert page.locator("#view3d canvas").count() == 1
    before = page.text_content("#view3d-orientation")
    view3d.focus()
    page.keyboard.press("ArrowLeft")
    page.keyboard.press("ArrowLeft")
    turned = page.text_content("#view3d-orientation")
    assert turned != before
    x, y = _centre(view3d.bounding_box())
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + 80, y + 10, steps=4)
    page.mouse.up()
    assert page.text_content("#view3d-orientation") != turned
    page.click("#view-reset")
    assert page.text_content("#view3d-orientation") == before
    page.click("#view-side")
    assert page.text_content("#view3d-orientation") != before
    with page.expect_download() as info:
        page.click("#download-png")
    assert Path(info.value.path()).read_bytes().startswith(b"\x89PNG\r\n\x1a\n")
    assert not watch.errors and not watch.foreign
    context.close()
