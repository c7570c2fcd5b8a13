"""Placement that cannot go wrong silently, in Debian's Chromium against a real `spine serve`.

A full-size DX phantom (1400 × 3000 px at 0.15 mm, the size of a clinic's full-spine film) gets its
17 × 4 corners by mouse at the fitted zoom (26 %) and at 63 %, with each vertebra's top corners
clicked 5 CSS px below the corners of the one above: every click places the next corner in its
role (a click on or near a point never selects it). A crossed quadrilateral is drawn and named
before sending and the send is refused, and the service refuses the same payload (422 naming the
corners); Ctrl+Z / Ctrl+Shift+Z undo and redo the clicks.
"""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path
from typing import Any

import httpx
import pytest
from page_fixtures import FILM_SIZE, LEVELS, make_dicom, make_png, open_page

pytestmark = pytest.mark.browser

PHANTOM_SIZE = (1400, 3000)  # columns, rows: the DX phantom
PHANTOM_SPACING = 0.15  # mm, Imager Pixel Spacing
CORNER_ROLES = ["top-left", "top-right", "bottom-left", "bottom-right"]


def phantom_corners(gap_px: float) -> list[list[tuple[float, float]]]:
    """Corners (TL, TR, BL, BR) of 17 wedged bodies down an S-curve, each top endplate `gap_px`
    below the endplate above it (a disc seen edge-on). Body heights grow from 15 mm (T1) to 27 mm
    (L5) and widths from 33 to 50 mm, in the range of adult vertebral bodies (Panjabi et al., Spine
    1991/1992); endplate tilts reach ±14° (a 55° thoracic curve spreads over about 4 levels)."""

    def tilt(i: int) -> float:  # tilt (rad) of the top endplate of level i; the bottom takes level i+1's
        return math.radians(14.0) * math.sin(2 * math.pi * i / 17)

    def along(t: float) -> tuple[float, float]:
        return math.cos(t), -math.sin(t)

    def down(t: float) -> tuple[float, float]:
        return math.sin(t), math.cos(t)

    out = []
    mid = (PHANTOM_SIZE[0] / 2, 160.0)
    for i in range(len(LEVELS)):
        h = (15.0 + 12.0 * i / 16) / PHANTOM_SPACING
        half = (33.0 + 17.0 * i / 16) / PHANTOM_SPACING / 2
        t0, t1 = tilt(i), tilt(i + 1)
        bottom_mid = (mid[0] + h * down((t0 + t1) / 2)[0], mid[1] + h * down((t0 + t1) / 2)[1])
        a0, a1 = along(t0), along(t1)
        tl, tr = (mid[0] - half * a0[0], mid[1] - half * a0[1]), (mid[0] + half * a0[0], mid[1] + half * a0[1])
        bl = (bottom_mid[0] - half * a1[0], bottom_mid[1] - half * a1[1])
        br = (bottom_mid[0] + half * a1[0], bottom_mid[1] + half * a1[1])
        out.append([tl, tr, bl, br])
        d = down(t1)
        mid = (bottom_mid[0] + gap_px * d[0], bottom_mid[1] + gap_px * d[1])
    return out


def view(page: Any) -> tuple[float, float, float]:
    """The PA canvas's CSS px per image px and the image point at its top-left corner."""
    s, ox, oy = (float(x) for x in (page.get_attribute("#pa-canvas", "data-view") or "").split())
    return s, ox, oy


def screen(page: Any, p: tuple[float, float]) -> tuple[float, float]:
    box = page.locator("#pa-canvas").bounding_box()
    s, ox, oy = view(page)
    return box["x"] + (p[0] - ox) * s, box["y"] + (p[1] - oy) * s


def bring_into_view(page: Any, rows: tuple[float, float]) -> None:
    """Pan (a drag at the canvas's left edge, on soft tissue) so that image rows `rows` are inside the canvas."""
    box = page.locator("#pa-canvas").bounding_box()
    s, _, oy = view(page)
    top, bottom = (r - oy for r in rows)
    if top * s > 40 and bottom * s < box["height"] - 40:
        return
    shift = ((top + bottom) / 2 - box["height"] / 2 / s) * s  # CSS px to move the film up
    x, y = box["x"] + 8, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x, y - shift, steps=4)
    page.mouse.up()


def open_phantom(browser: Any, url: str, key: str, tmp_path: Path, gap_px: float) -> tuple[Any, Any, Any, list]:
    corners = phantom_corners(gap_px)
    film = tmp_path / "phantom.dcm"
    make_dicom(film, view="pa", bodies=corners, size=PHANTOM_SIZE,
               spacing={"ImagerPixelSpacing": [PHANTOM_SPACING, PHANTOM_SPACING]})  # fmt: skip
    context, page, watch = open_page(browser, url + "/", key, height=1000)
    page.set_input_files("#pa-file", str(film))
    page.wait_for_selector("#pa-header dd")
    page.check("#pa-mode-corners")
    page.evaluate("document.getElementById('pa-canvas').scrollIntoView({block: 'start'})")
    return context, page, watch, corners


@pytest.mark.parametrize("zoom_in", [0, 4], ids=["zoom-26", "zoom-63"])
def test_68_corner_clicks_5_px_apart_take_their_roles(
    browser: Any, live_url: str, api_key: str, tmp_path: Path, zoom_in: int
) -> None:
    # the fitted film: canvas min(78vh, 60rem) = 780 CSS px for 3000 rows -> 26 %; four "+" (×1.25) -> 63 %
    fitted_scale = 780 / PHANTOM_SIZE[1]
    scale = fitted_scale * 1.25**zoom_in
    gap_px = 5.0 / scale  # image px between a body's bottom corners and the next body's top corners: 5 CSS px
    context, page, watch, corners = open_phantom(browser, live_url, api_key, tmp_path, gap_px)
    for _ in range(zoom_in):
        page.click("#pa-zoom-in")
    assert page.text_content("#pa-zoom") == f"{round(scale * 100)} %"
    assert view(page)[0] == pytest.approx(scale, rel=1e-3)
    for level, quad in zip(LEVELS, corners, strict=True):
        bring_into_view(page, (min(p[1] for p in quad), max(p[1] for p in quad)))
        for role, p in zip(CORNER_ROLES, quad, strict=True):
            x, y = screen(page, p)
            page.mouse.move(x, y)
            assert page.get_attribute("#pa-canvas", "data-next") == f"{level} {role}"  # the role, at the cursor
            page.mouse.click(x, y)
    # the top corners of T2..L5 were clicked about 5 CSS px from the bottom corners of the level above
    # (the gap is 5 px along the endplate's normal; the wedge adds a little along the endplate)
    s = view(page)[0]
    near = [
        math.dist(a, b) * s for up, low in itertools.pairwise(corners) for a, b in ((up[2], low[0]), (up[3], low[1]))
    ]
    assert max(near) < 5.5 and min(near) >= 5.0 - 1e-6, near
    assert "17 vertebrae on the PA film (T1–L5): 17 with four corners" in (page.text_content("#pa-status") or "")
    assert page.get_attribute("#pa-canvas", "data-next") == "L5 complete"
    assert "L5 is complete" in (page.text_content("#pa-prompt") or "")
    placed = json.loads(page.text_content("#payload-preview") or "{}")["pa"]["landmarks"]
    assert [lm["level"] for lm in placed] == list(LEVELS)
    tolerance = 1.0 / scale  # one CSS px: a mouse event lands on the nearest CSS px
    for lm, quad in zip(placed, corners, strict=True):
        for got, want in zip(lm["corners"], quad, strict=True):
            assert got == pytest.approx(want, abs=tolerance), (lm["level"], got, want)
    assert page.get_attribute("#pa-canvas", "data-problems") == ""
    assert "Ready to send" in (page.text_content("#missing") or "")
    assert not watch.errors
    context.close()


def test_crossed_quadrilateral_named_before_sending_and_undo_redo(
    browser: Any, live_url: str, api_key: str, tmp_path: Path
) -> None:
    context, page, watch, corners = open_phantom(browser, live_url, api_key, tmp_path, 20.0)
    for quad in corners[:2]:
        for p in quad:
            page.mouse.click(*screen(page, p))
    # T3 with its top corners clicked right before left: a crossed quadrilateral
    tl, tr, bl, br = corners[2]
    for p in (tr, tl, bl, br):
        page.mouse.click(*screen(page, p))
    crossed = (
        "PA film, T3: the corners of T3 cross each other: give them as they appear in the image, in the order "
        "top-left, top-right, bottom-left, bottom-right, forming a convex quadrilateral; "
        "the top-left and top-right corners look swapped"
    )
    assert crossed in (page.text_content("#missing") or "")
    assert page.get_attribute("#pa-canvas", "data-problems") == "T3"
    page.click("#submit")
    assert crossed in (page.text_content("#problem") or "")
    assert not watch.posted_jobs()
    # the service refuses the same payload, naming the corners (spine_engine.validation's corner check)
    payload = json.loads(page.text_content("#payload-preview") or "{}")
    answer = httpx.post(f"{live_url}/v1/jobs", json=payload, headers={"Authorization": f"Bearer {api_key}"}, timeout=30)
    assert answer.status_code == 422, answer.text
    refused = {e["path"]: e for e in answer.json()["errors"]}
    assert refused["pa.landmarks[2].corners"]["type"] == "corners_not_convex", refused
    assert "T3" in refused["pa.landmarks[2].corners"]["msg"]

    # undo the four clicks of T3 (Ctrl+Z on the film), redo two, undo them again (the button)
    page.focus("#pa-canvas")
    for _ in range(4):
        page.keyboard.press("Control+z")
    assert "2 vertebrae on the PA film (T1–T2)" in (page.text_content("#pa-status") or "")
    assert page.get_attribute("#pa-canvas", "data-next") == "T3 top-left"
    page.keyboard.press("Control+Shift+z")
    page.keyboard.press("Control+Shift+z")
    assert "T3: 2 of 4 corners placed" in (page.text_content("#missing") or "")
    assert page.get_attribute("#pa-canvas", "data-next") == "T3 bottom-left"
    page.click("#pa-undo")
    page.click("#pa-undo")
    assert page.get_attribute("#pa-canvas", "data-next") == "T3 top-left"
    for p in corners[2]:
        page.mouse.click(*screen(page, p))
    assert page.get_attribute("#pa-canvas", "data-problems") == ""
    assert page.is_disabled("#pa-redo")  # a new click drops what was undone
    # a drag (press and move past the threshold) moves a corner, and undo puts it back
    start = screen(page, corners[1][3])
    page.mouse.move(*start)
    page.mouse.down()
    page.mouse.move(start[0] + 12, start[1], steps=4)
    page.mouse.up()
    moved = json.loads(page.text_content("#payload-preview") or "{}")["pa"]["landmarks"][1]["corners"][3]
    assert moved[0] == pytest.approx(corners[1][3][0] + 12 / view(page)[0], abs=1 / view(page)[0])
    page.click("#pa-undo")
    back = json.loads(page.text_content("#payload-preview") or "{}")["pa"]["landmarks"][1]["corners"][3]
    assert back == pytest.approx(list(corners[1][3]), abs=1 / view(page)[0])
    assert "3 vertebrae on the PA film (T1–T3): 3 with four corners" in (page.text_content("#pa-status") or "")
    # by keyboard: comma selects the previous point, Alt+arrow moves it, Ctrl+Z puts it back
    page.focus("#pa-canvas")
    page.keyboard.press(".")  # nothing selected after the undo: the first point
    assert page.get_attribute("#pa-canvas", "data-selected") == "T1 top-left"
    page.keyboard.press(",")
    assert page.get_attribute("#pa-canvas", "data-selected") == "T3 bottom-right"
    page.keyboard.press("Alt+ArrowRight")
    nudged = json.loads(page.text_content("#payload-preview") or "{}")["pa"]["landmarks"][2]["corners"][3]
    assert nudged[0] > corners[2][3][0] + 0.5
    page.keyboard.press("Control+z")
    back = json.loads(page.text_content("#payload-preview") or "{}")["pa"]["landmarks"][2]["corners"][3]
    assert back == pytest.approx(list(corners[2][3]), abs=1 / view(page)[0])
    assert not watch.errors
    context.close()


def open_film(browser: Any, url: str, key: str, tmp_path: Path) -> tuple[Any, Any, Any]:
    """The page with the synthetic PA film (FILM_SIZE, page_fixtures) open and fitted in the PA panel."""
    film = tmp_path / "a.dcm"
    make_dicom(film, view="pa")
    context, page, watch = open_page(browser, url + "/", key, height=1000)
    page.set_input_files("#pa-file", str(film))
    page.wait_for_selector("#pa-header dd")
    page.evaluate("document.getElementById('pa-canvas').scrollIntoView({block: 'start'})")
    return context, page, watch


def test_a_click_beside_the_film_places_nothing(browser: Any, live_url: str, api_key: str, tmp_path: Path) -> None:
    """Zoomed out (two "−"), the film has dark canvas around it: a click there, left, right or below the
    film, is not a landmark at the film's nearest edge (the click's column or row clamped): nothing is
    placed and the cursor and the prompt say why; a click on the film then places T1 where it lands."""
    context, page, watch = open_film(browser, live_url, api_key, tmp_path)
    page.focus("#pa-canvas")
    page.keyboard.press("-")
    page.keyboard.press("-")
    width, height = FILM_SIZE
    for beside in ((-40.0, 100.0), (width + 40.0, 100.0), (width / 2, height + 40.0)):
        page.mouse.click(*screen(page, beside))
        assert page.get_attribute("#pa-canvas", "data-next") == "Nothing placed: the click is outside the film"
        assert "Nothing placed: the click is outside the film" in (page.text_content("#pa-prompt") or "")
        assert page.text_content("#pa-status") == "No landmark on this film yet."
    page.mouse.click(*screen(page, (width / 2, 100.0)))
    placed = json.loads(page.text_content("#payload-preview") or "{}")["pa"]["landmarks"]
    s = view(page)[0]
    assert [lm["level"] for lm in placed] == ["T1"]
    assert placed[0]["point"] == pytest.approx([width / 2, 100.0], abs=1 / s)  # one CSS px
    assert page.get_attribute("#pa-canvas", "data-next") == "T2 midpoint"
    assert not watch.errors, watch.errors
    context.close()


SLOW_DECODE = """() => {
    const decode = HTMLImageElement.prototype.decode;
    HTMLImageElement.prototype.decode = function () {
        return new Promise((resolve) => setTimeout(resolve, 1500)).then(() => decode.call(this));
    };
}"""
"""A PNG or JPEG that takes 1.5 s to decode, as a large film on a slow workstation does (Chromium decodes
the synthetic film in a few ms)."""


def test_a_film_still_loading_takes_no_click_and_a_newer_film_wins(
    browser: Any, live_url: str, api_key: str, tmp_path: Path
) -> None:
    """While a PNG replacing the open film is still decoding, a click places nothing (the landmark would
    belong to the film about to go) and the prompt says the film is loading. A slow PNG chosen and then,
    before it is decoded, a DICOM film: the DICOM film, the newer choice, stays, and the landmark placed on
    it is not dropped when the older choice finishes decoding."""
    context, page, watch = open_film(browser, live_url, api_key, tmp_path)
    page.mouse.click(*screen(page, (FILM_SIZE[0] / 2, 100.0)))
    assert "1 vertebra on the PA film" in (page.text_content("#pa-status") or "")
    page.evaluate(SLOW_DECODE)
    png = tmp_path / "b.png"
    make_png(png)
    page.set_input_files("#pa-file", str(png))
    page.wait_for_selector("#pa-prompt:text-is('Loading b.png…')")
    page.mouse.click(*screen(page, (FILM_SIZE[0] / 2, 200.0)))
    assert page.get_attribute("#pa-canvas", "data-next") == "Nothing placed: b.png is still loading"
    page.wait_for_selector("#pa-canvas[aria-label*='b.png']")
    status = page.text_content("#pa-status") or ""
    assert "The landmarks of 1 vertebra placed on the previous film were removed" in status, status
    # a slow PNG, then at once a DICOM film: the DICOM film stays, with the landmark placed on it
    slow, newer = tmp_path / "c.png", tmp_path / "d.dcm"
    make_png(slow)
    make_dicom(newer, view="pa", study={"PatientID": "PAT-NEWER"})
    page.set_input_files("#pa-file", str(slow))
    page.set_input_files("#pa-file", str(newer))
    page.wait_for_selector("#pa-canvas[aria-label*='d.dcm']")
    page.mouse.click(*screen(page, (FILM_SIZE[0] / 2, 100.0)))
    assert "1 vertebra on the PA film" in (page.text_content("#pa-status") or "")
    page.wait_for_timeout(2500)  # c.png's decode (1.5 s) is over
    assert "d.dcm" in (page.get_attribute("#pa-canvas", "aria-label") or "")
    assert "ID PAT-NEWER" in (page.text_content("#pa-header") or "")
    status = page.text_content("#pa-status") or ""
    assert status.startswith("1 vertebra on the PA film (T1–T1)"), status
    assert page.text_content("#pa-prompt") == "Next: the top endplate midpoint of T2."
    assert not watch.errors, watch.errors
    context.close()


def test_placing_a_level_again_in_another_mode_says_what_it_replaces(
    browser: Any, live_url: str, api_key: str, tmp_path: Path
) -> None:
    """The payload takes a level's midpoint or its four corners, not both: T1's four corners, then T1
    chosen again in midpoint mode: the prompt and the cursor say that the click replaces the corners
    (it does: the corners go); T2's midpoint, then T2 in four-corner mode: the first corner replaces it."""
    context, page, watch = open_film(browser, live_url, api_key, tmp_path)
    col = FILM_SIZE[0] / 2
    page.check("#pa-mode-corners")
    for p in ((col - 20, 60.0), (col + 20, 60.0), (col - 20, 80.0), (col + 20, 80.0)):
        page.mouse.click(*screen(page, p))
    page.select_option("#pa-level", "T1")
    page.check("#pa-mode-point")
    assert page.text_content("#pa-prompt") == "Next: the top endplate midpoint of T1, replacing T1's four corners."
    page.mouse.move(*screen(page, (col, 62.0)))
    assert page.get_attribute("#pa-canvas", "data-next") == "T1 midpoint, replaces its four corners"
    page.mouse.click(*screen(page, (col, 62.0)))
    t1 = json.loads(page.text_content("#payload-preview") or "{}")["pa"]["landmarks"][0]
    assert "corners" not in t1 and t1["point"] == pytest.approx([col, 62.0], abs=1 / view(page)[0])
    # T2 (the next level) by its midpoint, then again by four corners
    page.mouse.click(*screen(page, (col, 110.0)))
    page.select_option("#pa-level", "T2")
    page.check("#pa-mode-corners")
    assert page.text_content("#pa-prompt") == "Next: the top-left corner of T2, replacing T2's midpoint."
    page.mouse.move(*screen(page, (col - 20, 108.0)))
    assert page.get_attribute("#pa-canvas", "data-next") == "T2 top-left, replaces its midpoint"
    page.mouse.click(*screen(page, (col - 20, 108.0)))
    assert page.text_content("#pa-prompt") == "Next: the top-right corner of T2."
    assert not watch.errors, watch.errors
    context.close()
