"""A film's orientation checked on the page before sending, in Debian's Chromium against a real `spine serve`:
every orientation a clinician can choose under a film (two lists of L, R, A, P, H, F: 36 pairs on each film)
is named at that film's orientation controls and listed before sending exactly when the service refuses it,
by the service's rules (spine_engine/models.py `_View._orientation`: two values on one axis of the patient;
spine_engine/validation.py `_plane_errors`, orientation_not_of_view: a PA film toward A or P, a lateral one
toward L or R; `_landmark_form_errors`: corners need rows toward H or F, pedicles a PA film with columns
toward L or R), compared with the service's own 422 on the page's payload; and a PA film turned in its plane
(["F", "L"], rows toward the patient's left) stays a frontal film the page sends and the service fits.

Patient Orientation (0020,0020), DICOM PS3.3 C.7.6.1.1.1: its first value is the patient direction toward
which a row's pixels run (the image's right), its second the direction down a column (the image's bottom),
each of L/R, A/P, H/F; a frontal (PA or AP) film's two directions lie in the patient's L/R and H/F axes, a
lateral film's in A/P and H/F.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import httpx
import pytest
from page_fixtures import (
    LEVELS,
    canvas_point,
    centreline,
    click_pa_midpoints,
    click_pa_pedicles,
    lateral_points,
    make_dicom,
    open_film,
    open_page,
    pa_corners,
    payload_preview,
    place_pa_and_lateral,
    reconstruct_on_page,
    run_axe,
)

pytestmark = pytest.mark.browser

DIRECTIONS = "LRAPHF"
# The page's head of a line naming a film's orientation before sending (web/src/panel.ts `problems`).
HEAD = "{film} film, orientation (under the film, DICOM Patient Orientation): "
# The service's errors that judge a view's orientation, with the paths they are given at.
ORIENTATION_TYPES = {"value_error", "orientation_not_of_view", "corners_need_upright_view", "pedicles_not_supported"}


def _service_errors(url: str, key: str, payload: dict[str, Any]) -> list[dict[str, Any]]:
    """The service's own refusals of the payload, the unknown profile's left out. An unknown profile is
    added so that the payload is always refused (422) and no job is made: the service lists every error
    of the payload with it (validation.py `validate_payload`), but for a payload the contract's models
    refuse (two directions on one axis), which is refused by that error alone."""
    probe = {**payload, "options": {"profile": "no-such-profile"}}
    answer = httpx.post(f"{url}/v1/jobs", json=probe, headers={"Authorization": f"Bearer {key}"}, timeout=30)
    assert answer.status_code == 422, answer.text
    return [e for e in answer.json()["errors"] if e["path"] != "options.profile"]


def _plain(message: str) -> str:
    """The service's message as the page gives it: an orientation ['A', 'F'] as A, F and 'A' as A."""
    return re.sub(r"'([LRAPHF])'", r"\1", re.sub(r"\['([LRAPHF])', '([LRAPHF])'\]", r"\1, \2", message))


def _missing(page: Any) -> list[str]:
    return [t.strip() for t in page.locator("#missing li").all_text_contents()]


def _choose(page: Any, view: str, column: str, row: str) -> None:
    page.select_option(f"#{view}-orientation-column", column)
    page.select_option(f"#{view}-orientation-row", row)


def _compare(page: Any, url: str, key: str, view: str, column: str, row: str) -> tuple[list[str], list[str]]:
    """The page's verdict on the view's orientation (the lines before sending, the controls' mark and words)
    against the service's 422 on the page's own payload: the types of the service's orientation errors, and
    where the page differs, each as "<view> [column, row] <type>: what differs" (empty when it agrees)."""
    film = "PA" if view == "pa" else "Lateral"
    payload = payload_preview(page)
    assert payload[view]["patient_orientation"] == [column, row]
    errors = _service_errors(url, key, payload)
    about = [e for e in errors if e["type"] in ORIENTATION_TYPES]
    at = re.compile(rf"{view}\.(patient_orientation|landmarks\[\d+\]\.(corners|pedicles))")
    assert all(at.fullmatch(e["path"]) for e in about), about
    said = [m for m in _missing(page) if m.startswith(HEAD.format(film=film))]
    case = f"{view} [{column}, {row}]"
    wrong: list[str] = []
    for e in about:
        line = next((m for m in said if m.endswith(f"The service refuses it: {_plain(e['msg'])}.")), None)
        if line is None:
            wrong.append(f"{case} {e['type']}: not named before sending")
            continue
        index = re.search(r"landmarks\[(\d+)\]", e["path"])
        if index and payload[view]["landmarks"][int(index.group(1))]["level"] not in line:
            wrong.append(f"{case} {e['type']}: the level of {e['path']} not named: {line}")
        words = line.split("The service refuses it:")[0]
        wrong += [
            f"{case} {e['type']}: {c!r} in {words}" for c in ("patient_orientation", e["type"], "['", "{") if c in words
        ]
    # one line per rule the service applies (it names each landmark; the page names their levels in one line)
    if len(said) != len({e["type"] for e in about}):
        wrong.append(f"{case}: the page lists {said}, the service {[e['type'] for e in about]}")
    # at the controls: marked invalid and said in words exactly when the service refuses
    visible = page.locator(f"#{view}-orientation-check").is_visible()
    invalid = page.get_attribute(f"#{view}-orientation-column", "aria-invalid") == "true"
    described = f"{view}-orientation-check" in (
        page.get_attribute(f"#{view}-orientation-row", "aria-describedby") or ""
    )
    if not visible == invalid == described == bool(about):
        wrong.append(f"{case}: at the controls shown {visible}, aria-invalid {invalid}, described {described}")
    # nothing else stands between the page and the service: ready exactly when the service refuses nothing
    if page.get_attribute("#missing", "data-ready") != ("false" if errors else "true"):
        wrong.append(
            f"{case}: ready to send is not the service's verdict {[e['type'] for e in errors]}: {_missing(page)}"
        )
    return [e["type"] for e in about], wrong


def test_every_orientation_is_named_before_sending_as_the_service_refuses_it(
    browser: Any, live_url: str, api_key: str, tmp_path: Path
) -> None:
    """A PA film with 17 landmarks (T3 as four corners, T8 with pedicles) and a lateral film with T4–L5 (T10 as
    four corners): each of the 36 orientations chosen at the PA film's controls (the lateral at ["A", "F"]),
    then each at the lateral film's (the PA at ["L", "F"]). The page names, before sending and at that film's
    controls, exactly what the service's 422 on the page's payload names (two directions on one axis, the
    other film's plane, corners on a film not upright, pedicles without columns toward L or R), by rule, the
    levels, and the service's words; and it is ready to send exactly when the service refuses nothing."""
    make_dicom(tmp_path / "pa.dcm", view="pa")
    make_dicom(tmp_path / "lateral.dcm", view="lateral")
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    open_film(page, "pa", tmp_path / "pa.dcm")
    click_pa_midpoints(page, range(len(LEVELS)))
    page.check("#pa-mode-corners")
    page.select_option("#pa-level", "T3")
    corners = pa_corners()
    for col, row in corners[2]:
        page.mouse.click(*canvas_point(page, "pa", col, row))
    page.check("#pa-mode-pedicles")
    page.select_option("#pa-level", "T8")
    click_pa_pedicles(page, corners[7])
    assert "17 vertebrae on the PA film (T1–L5): 16 midpoints, 1 with four corners, 1 with pedicles" in (
        page.text_content("#pa-status") or "")  # fmt: skip
    open_film(page, "lateral", tmp_path / "lateral.dcm")
    page.select_option("#lateral-level", "T4")
    for _, col, row in lateral_points("T4"):
        page.mouse.click(*canvas_point(page, "lateral", col, row))
    page.check("#lateral-mode-corners")
    page.select_option("#lateral-level", "T10")
    _, col, row = lateral_points("T4")[6]
    for c, r in ((col - 26, row), (col + 26, row), (col - 26, row + 22), (col + 26, row + 22)):
        page.mouse.click(*canvas_point(page, "lateral", c, r))
    assert "14 vertebrae on the lateral film (T4–L5): 13 midpoints, 1 with four corners" in (
        page.text_content("#lateral-status") or "")  # fmt: skip
    assert page.get_attribute("#missing", "data-ready") == "true", _missing(page)

    refused: dict[str, list[tuple[str, str]]] = {"pa": [], "lateral": []}
    rules: dict[str, set[str]] = {"pa": set(), "lateral": set()}
    differ: list[str] = []  # every case where the page is not the service, gathered: a failure names them all
    for view in ("pa", "lateral"):
        page.click(f"#tab-film-{view}")
        for toward_right in DIRECTIONS:
            for toward_bottom in DIRECTIONS:
                _choose(page, view, toward_right, toward_bottom)
                types, wrong = _compare(page, live_url, api_key, view, toward_right, toward_bottom)
                differ += wrong
                rules[view] |= set(types)
                if types:
                    refused[view].append((toward_right, toward_bottom))
        _choose(page, view, *(("L", "F") if view == "pa" else ("A", "F")))
    assert not differ, f"{len(differ)} differences from the service:\n" + "\n".join(differ)
    assert rules == {"pa": ORIENTATION_TYPES, "lateral": ORIENTATION_TYPES - {"pedicles_not_supported"}}, rules
    # the rules' verdicts, counted: of 36 pairs, 12 on one axis; the PA's other 24 with A or P in 16, its T3
    # corners refusing rows toward L or R in 4 more (["H", "L"], ["F", "R"] …), its T8 pedicles columns toward
    # H or F in 4 more (["F", "L"] …, its rows L or R, already counted with the corners): 32 refused, the 4
    # accepted being ["L", "F"], ["R", "F"], ["L", "H"], ["R", "H"] (["L", "H"], rows toward the head, the
    # fixture's landmarks then out of order); the lateral likewise with A/P for L/R and no pedicles.
    assert len(refused["pa"]) == 32, refused["pa"]
    assert len(refused["lateral"]) == 32, refused["lateral"]
    assert {("L", "F"), ("R", "F"), ("L", "H"), ("R", "H")}.isdisjoint(refused["pa"])
    assert {("A", "F"), ("P", "F"), ("A", "H"), ("P", "H")}.isdisjoint(refused["lateral"])
    assert not watch.posted_jobs() and not watch.errors, watch.errors
    context.close()


def _turned_point(page: Any, col: float, row: float, size: tuple[int, int]) -> tuple[float, float]:
    """Page coordinates (CSS px) of an image point on the PA canvas fitted to a film of ``size`` (columns, rows)."""
    page.evaluate("() => document.getElementById('pa-canvas').scrollIntoView({block: 'start'})")
    box = page.locator("#pa-canvas").bounding_box()
    assert box is not None
    s = min(box["width"] / size[0], box["height"] / size[1])
    return box["x"] + (box["width"] - size[0] * s) / 2 + col * s, box["y"] + (box["height"] - size[1] * s) / 2 + row * s


def test_a_pa_film_turned_in_its_plane_stays_frontal_and_is_sent(
    browser: Any, live_url: str, api_key: str, tmp_path: Path
) -> None:
    """The fixtures' PA film turned a quarter: the feet toward the image's right and the patient's left
    toward its bottom (["F", "L"], the fixtures' film transposed, 900 × 560 px): chosen at the controls, it
    is a frontal film (no mark, nothing listed), its 17 midpoints running across the film, in order along its
    head-to-feet axis (its columns: spine_engine/validation.py `_order_errors`, `_across_errors`), and the job
    is sent (202) and fitted."""
    size = (900, 560)
    bodies = [[(r, c) for c, r in body] for body in pa_corners()]  # transposed: column ↔ row
    make_dicom(tmp_path / "turned.dcm", view="pa", bodies=bodies, size=size)
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    open_film(page, "pa", tmp_path / "turned.dcm")
    _choose(page, "pa", "F", "L")
    for i in range(len(LEVELS)):
        col, row, _ = centreline(i)
        page.mouse.click(*_turned_point(page, row, col, size))
    assert "17 vertebrae on the PA film (T1–L5): 17 midpoints" in (page.text_content("#pa-status") or "")
    assert page.locator("#pa-orientation-check").is_hidden()
    assert page.get_attribute("#pa-orientation-column", "aria-invalid") != "true"
    assert page.get_attribute("#missing", "data-ready") == "true", _missing(page)
    sent = payload_preview(page)["pa"]
    assert sent["patient_orientation"] == ["F", "L"]
    assert reconstruct_on_page(page)["pa"]["patient_orientation"] == ["F", "L"]
    assert not watch.errors, watch.errors
    context.close()


def test_an_orientation_on_one_axis_is_said_at_the_control_and_not_sent(
    browser: Any, live_url: str, api_key: str, tmp_path: Path
) -> None:
    """Columns toward A and rows toward P chosen under a lateral film with landmarks: said at the lateral film's
    orientation controls in plain words (both marked invalid, the words in their description, axe-core clean),
    listed before sending, and Reconstruct sends nothing; rows toward F again clears the mark and the job goes."""
    context, page, watch = open_page(browser, f"{live_url}/", api_key)
    place_pa_and_lateral(page, tmp_path)
    _choose(page, "lateral", "A", "P")
    check = page.locator("#lateral-orientation-check")
    assert check.is_visible()
    said = check.text_content() or ""
    assert "front–back axis (A and P)" in said and "front–back (A or P) and head–feet (H or F)" in said, said
    assert "column and row directions A, P are not orthogonal" in said, said  # the service's words, unquoted
    for code_form in ("patient_orientation", "value_error", "['", "'A'"):
        assert code_form not in said, (code_form, said)
    for select in ("#lateral-orientation-column", "#lateral-orientation-row"):
        assert page.get_attribute(select, "aria-invalid") == "true"
        assert "lateral-orientation-check" in (page.get_attribute(select, "aria-describedby") or "")
    assert page.get_attribute("#pa-orientation-column", "aria-invalid") != "true"
    assert [m for m in _missing(page) if m.startswith(HEAD.format(film="Lateral"))], _missing(page)
    assert not run_axe(page)
    page.click("#submit")
    assert "Lateral film, orientation" in (page.text_content("#problem") or "")
    assert not watch.posted_jobs()  # nothing sent

    page.select_option("#lateral-orientation-row", "F")
    assert check.is_hidden()
    assert page.get_attribute("#lateral-orientation-column", "aria-invalid") != "true"
    assert page.get_attribute("#missing", "data-ready") == "true", _missing(page)
    with page.expect_response(lambda r: r.request.method == "POST" and r.url.endswith("/v1/jobs")) as posted:
        page.click("#submit")
    assert posted.value.status == 202, posted.value.text()
    assert not watch.errors, watch.errors
    context.close()
