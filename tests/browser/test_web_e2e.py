"""The web front end end to end: headless Chromium (Debian's, driven by Playwright) against a real
`spine serve` (API + Celery worker child, embedded SQLite mode) on 127.0.0.1.

A person's path through the page: load a PA radiograph, click the 17 landmarks (one undone and
placed again, the last one placed with the keyboard), submit, watch the job, see the 3D view,
the projections over the image and the measures, download the result; then a sample payload with
an API key set. A screenshot of the page is saved under the test's tmp dir and its path printed.

Skipped, saying why, when the Python `playwright` package or a Chromium executable is missing
(`make browser` installs Debian's chromium; SPINE_CHROMIUM names another executable).
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

pytestmark = pytest.mark.browser

LEVELS = ["T1", "T2", "T3", "T4", "T5", "T6", "T7", "T8", "T9", "T10", "T11", "T12",
          "L1", "L2", "L3", "L4", "L5"]  # fmt: skip
CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
    "--disable-component-update", "--no-first-run", "--disable-sync", "--disable-quic",
]  # fmt: skip
IMAGE_SIZE = (600, 720)  # width, height in px
PIXEL_SPACING = 0.6  # mm per px


def chromium_path() -> str | None:
    for candidate in (os.environ.get("SPINE_CHROMIUM"), "/usr/bin/chromium", shutil.which("chromium"),
                      shutil.which("chromium-browser")):  # fmt: skip
        if candidate and os.access(candidate, os.X_OK):
            return candidate
    return None


def landmark_pixels() -> list[tuple[float, float]]:
    """Top endplate midpoints (column, row) in px of the synthetic radiograph: a C-curve."""
    points = []
    for i in range(len(LEVELS)):
        t = i / (len(LEVELS) - 1)
        points.append((300.0 + 60.0 * math.sin(math.pi * t), 40.0 + 640.0 * t))
    return points


def make_radiograph(path: Path) -> None:
    """A dark PNG with a bright vertebral body below each landmark."""
    from PIL import Image, ImageDraw, ImageFilter

    image = Image.new("L", IMAGE_SIZE, 30)
    draw = ImageDraw.Draw(image)
    draw.rectangle((150, 0, 450, IMAGE_SIZE[1]), fill=55)  # soft tissue
    for col, row in landmark_pixels():
        draw.rectangle((col - 28, row + 2, col + 28, row + 28), fill=200)
    image.filter(ImageFilter.GaussianBlur(1.5)).convert("RGB").save(path)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def live_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """`spine serve` on a free port of 127.0.0.1: uvicorn API and its Celery worker child."""
    data_dir = tmp_path_factory.mktemp("web-service")
    port = free_port()
    env = {
        **os.environ,
        "SPINE_DATA_DIR": str(data_dir),
        "SPINE_QUEUE_NAME": f"spine-web-{uuid.uuid4().hex[:8]}",
        "SPINE_WORKER_CONCURRENCY": "1",
        "SPINE_LOG_LEVEL": "WARNING",
    }
    for key in ("DATABASE_URL", "CELERY_BROKER_URL", "SPINE_SERVE_WORKER"):
        env.pop(key, None)
    log_path = data_dir / "serve.log"
    with log_path.open("wb") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "serve", "--host", "127.0.0.1", "--port", str(port)],
            env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
        )  # fmt: skip
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get(f"{url}/readyz", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"spine serve did not become ready:\n{log_path.read_text(errors='replace')[-4000:]}")
            time.sleep(0.2)
        # the first start of the embedded default prints an admin API key, once: the page needs it
        printed = re.search(r"^(spine_[0-9a-f]{12}_[A-Za-z0-9_-]{43})$", log_path.read_text(errors="replace"), re.M)
        assert printed, f"spine serve printed no API key:\n{log_path.read_text(errors='replace')[-4000:]}"
        API_KEYS[url] = printed.group(1)
        yield url
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)  # serve stops its worker child, then itself
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()


API_KEYS: dict[str, str] = {}


@pytest.fixture(scope="module")
def api_key(live_url: str) -> str:
    """The admin key `spine serve` printed at its first start."""
    return API_KEYS[live_url]


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    try:
        from playwright.sync_api import sync_playwright
    except ImportError as exc:  # pragma: no cover - the dev extra installs it
        pytest.skip(f"the Python playwright package is not installed ({exc}); run `make install`")
    executable = chromium_path()
    if executable is None:
        pytest.skip("no Chromium executable (looked for $SPINE_CHROMIUM, /usr/bin/chromium, chromium on PATH): "
                    "`make browser` installs Debian's chromium as root")  # fmt: skip
    with sync_playwright() as pw:
        chromium = pw.chromium.launch(executable_path=executable, headless=True, args=CHROMIUM_FLAGS)
        try:
            yield chromium
        finally:
            chromium.close()


class PageWatch:
    """Console errors, page errors and requests of one page."""

    def __init__(self, page: Any, base: str):
        self.errors: list[str] = []
        self.foreign: list[str] = []
        self.requests: list[Any] = []
        page.on("console", lambda m: self.errors.append(f"console {m.type}: {m.text}") if m.type == "error" else None)
        page.on("pageerror", lambda e: self.errors.append(f"page error: {e}"))

        def on_request(request: Any) -> None:
            self.requests.append(request)
            if not request.url.startswith((base + "/", "blob:", "data:")):
                self.foreign.append(request.url)

        page.on("request", on_request)


def test_click_landmarks_on_a_radiograph_and_see_the_reconstruction(
    browser: Any,
    live_url: str,
    api_key: str,
    tmp_path_factory: pytest.TempPathFactory,
    capsys: pytest.CaptureFixture[str],
) -> None:
    out = tmp_path_factory.mktemp("web-e2e")
    radiograph = out / "radiograph.png"
    make_radiograph(radiograph)
    context = browser.new_context(viewport={"width": 1600, "height": 1200}, accept_downloads=True)
    page = context.new_page()
    watch = PageWatch(page, live_url)
    page.goto(live_url + "/")
    page.wait_for_selector("body[data-ready=true]")
    assert page.title() == "Spine reconstruction"
    page.fill("#api-key", api_key)

    # -- landmarks: click T1..L4 (T3 undone and clicked again), then L5 with the keyboard
    page.set_input_files("#image-file", str(radiograph))
    page.fill("#pixel-spacing", str(PIXEL_SPACING))
    canvas = page.locator("#image-canvas")
    page.wait_for_function("document.getElementById('image-canvas').width > 0")
    box = canvas.bounding_box()
    assert box is not None and box["height"] < 1100, box
    scale = box["width"] / IMAGE_SIZE[0]
    points = landmark_pixels()
    for i, (col, row) in enumerate(points[:-1]):
        canvas.click(position={"x": col * scale, "y": row * scale})
        if LEVELS[i] == "T3":
            page.click("#undo-landmark")
            canvas.click(position={"x": col * scale, "y": row * scale})
    assert "L5" in page.text_content("#click-prompt")  # type: ignore[operator]
    canvas.focus()
    step = max(1, round(IMAGE_SIZE[1] / 400))
    down = round((points[-1][1] - points[-2][1]) / step)
    right = round((points[-1][0] - points[-2][0]) / step)
    for _ in range(down // 10):
        page.keyboard.press("Shift+ArrowDown")
    for _ in range(down % 10):
        page.keyboard.press("ArrowDown")
    for _ in range(abs(right)):
        page.keyboard.press("ArrowRight" if right > 0 else "ArrowLeft")
    page.keyboard.press("Enter")
    assert page.text_content("#click-prompt").startswith("All levels done: 17 landmarks")  # type: ignore[union-attr]
    assert "17 PA landmarks clicked on the radiograph" in page.text_content("#landmark-summary")  # type: ignore[operator]
    l5_z = float(page.input_value("#L5-position-z"))
    assert l5_z == pytest.approx(-640 * PIXEL_SPACING, abs=2 * step * PIXEL_SPACING)  # placed from the landmarks

    # -- submit and watch
    page.click("#submit")
    page.wait_for_selector("#job-status[data-status=succeeded]", timeout=30_000)
    posted = [r for r in watch.requests if r.method == "POST" and r.url.endswith("/v1/jobs")]
    assert len(posted) == 1
    body = posted[0].post_data_json
    assert body["pa"]["units"] == "px" and body["pa"]["pixel_spacing"] == [PIXEL_SPACING, PIXEL_SPACING]
    assert [lm["level"] for lm in body["pa"]["landmarks"]] == LEVELS
    assert body["pa"]["landmarks"][5]["point"] == pytest.approx(list(points[5]), abs=1 / scale + 0.1)  # whole CSS px
    assert posted[0].headers.get("authorization") == f"Bearer {api_key}"
    polls = [r for r in watch.requests if r.method == "GET" and "/v1/jobs/" in r.url]
    assert polls, "the page did not poll the job"

    # -- the result: 3D view, projections over the image, tables
    view3d = page.locator("#view3d")
    renderer = view3d.get_attribute("data-renderer")
    assert renderer in ("webgl", "svg")
    assert page.locator("#view3d canvas, #view3d svg").count() == 1
    before = page.text_content("#view3d-orientation")
    view3d.focus()
    page.keyboard.press("ArrowLeft")
    page.keyboard.press("ArrowLeft")
    assert page.text_content("#view3d-orientation") != before
    page.mouse.move(*_centre(view3d.bounding_box()))
    page.mouse.down()
    page.mouse.move(_centre(view3d.bounding_box())[0] + 80, _centre(view3d.bounding_box())[1] + 10, steps=4)
    page.mouse.up()
    page.click("#view-reset")
    assert page.locator("#view-pa svg image").count() == 1  # the radiograph under the PA projection
    assert page.locator("#view-pa svg polygon").count() == 17
    assert page.locator("#view-pa svg circle").count() == 17
    assert page.locator("#view-lateral svg polygon").count() == 17
    measures = page.text_content("#measures")
    assert measures is not None
    for text in ("Thoracic kyphosis T4–T12", "Lumbar lordosis L1–L5", "Mean PA registration error", "converged"):
        assert text in measures
    assert "Major curve" in measures  # a 60 px (36 mm) C-curve has a frontal curve
    assert page.locator("#strains tbody tr").count() == 17

    # -- downloads
    with page.expect_download() as info:
        page.click("#download-csv")
    csv_text = Path(info.value.path()).read_text()
    assert csv_text.splitlines()[0].startswith("level,x_mm,y_mm,z_mm")
    assert len(csv_text.strip().splitlines()) == 18
    with page.expect_download() as info:
        page.click("#download-png")
    assert Path(info.value.path()).read_bytes().startswith(b"\x89PNG\r\n\x1a\n")

    screenshot = out / "web-result.png"
    page.screenshot(path=str(screenshot), full_page=True)
    with capsys.disabled():
        print(f"\nweb front end screenshot ({renderer} 3D view): {screenshot}")
    assert not watch.errors, watch.errors
    assert not watch.foreign, f"the page reached beyond the service: {watch.foreign}"
    context.close()


def test_sample_payload_with_an_api_key(
    browser: Any,
    live_url: str,
    api_key: str,
    tmp_path_factory: pytest.TempPathFactory,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Also the 3D view's fallback without WebGL (three's SVG renderer, forced by ?renderer=svg)."""
    context = browser.new_context(viewport={"width": 1400, "height": 1000}, accept_downloads=True)
    page = context.new_page()
    watch = PageWatch(page, live_url)
    page.goto(live_url + "/?renderer=svg")
    page.wait_for_selector("body[data-ready=true]")

    # CSV: a bad one is refused line by line, a good one (header, comment, a lateral row) is used
    page.click("#tab-csv")
    page.fill("#csv-text", "level,column,row\nT1,1,2\nT13,3,4\nT2,x,5\n")
    page.click("#use-csv")
    error = page.text_content("#input-error")
    assert error is not None and 'line 3: level "T13"' in error and "line 4: column and row" in error
    rows = ["level,column,row,view", "# endplate midpoints, detector mm"]
    rows += [f"{lv},{100 + i},{50 + 25 * i}" for i, lv in enumerate(LEVELS)] + ["T1,200,50,lateral"]
    page.fill("#csv-text", "\n".join(rows))
    page.click("#use-csv")
    assert page.is_hidden("#input-error")
    assert "17 PA landmarks, 1 lateral from the CSV (mm)" in page.text_content("#landmark-summary")  # type: ignore[operator]
    with page.expect_download() as info:
        page.click("#download-landmarks")
    saved = Path(info.value.path()).read_text().splitlines()
    assert saved[0] == "level,column,row,view" and saved[1] == "T1,100,50,pa" and saved[-1] == "T1,200,50,lateral"
    page.fill("#api-key", api_key)
    assert page.evaluate("sessionStorage.getItem('spine.apiKey')") == api_key
    page.click("#tab-json")
    assert page.is_visible("#panel-json") and not page.is_visible("#panel-image")
    page.click("#load-sample")
    assert "17 PA landmarks from the payload (mm)" in page.text_content("#landmark-summary")  # type: ignore[operator]
    page.click("#submit")
    page.wait_for_selector("#job-status[data-status=succeeded]", timeout=30_000)
    posted = next(r for r in watch.requests if r.method == "POST" and r.url.endswith("/v1/jobs"))
    assert posted.headers.get("authorization") == f"Bearer {api_key}"
    assert page.locator("#view-pa svg image").count() == 0  # no radiograph: detector mm
    assert page.locator("#strains tbody tr").count() == 17
    assert page.get_attribute("#view3d", "data-renderer") == "svg"
    assert page.locator("#view3d svg path").count() > 17 * 6  # box faces and edges
    page.click("#view-side")
    screenshot = tmp_path_factory.mktemp("web-e2e-svg") / "web-result-svg.png"
    page.locator("#result").screenshot(path=str(screenshot))
    with capsys.disabled():
        print(f"\nweb front end result, SVG 3D view from the side: {screenshot}")

    # a payload the API refuses: its problem is shown with the offending field
    page.fill("#L5-d1-x", "")
    page.click("#submit")
    page.wait_for_selector("#problem:not([hidden])")
    assert "boundary.L5.directors" in page.text_content("#problem")  # type: ignore[operator]

    # T1 and L5 not known: the payload goes without boundary and the result says what is estimated
    page.check("#no-boundary")
    assert page.is_disabled("#L5-d1-x") and page.is_disabled("#auto-l5")
    assert '"boundary"' not in page.text_content("#payload-preview")  # type: ignore[operator]
    with page.expect_response(lambda r: r.request.method == "POST" and r.url.endswith("/v1/jobs")) as posted_job:
        page.click("#submit")
    assert posted_job.value.status == 202 and "boundary" not in json.loads(posted_job.value.request.post_data or "{}")
    # the status still shows the previous job's "succeeded": wait for this job's result instead
    estimated = page.locator("#result").get_by_text("estimated from the generic model and the landmarks", exact=False)
    estimated.first.wait_for(timeout=30_000)
    assert "from the model only: scale, depth" in estimated.first.text_content()  # type: ignore[operator]
    page.uncheck("#no-boundary")
    assert not page.is_disabled("#L5-d1-x") and '"boundary"' in page.text_content("#payload-preview")  # type: ignore[operator]
    assert not watch.errors or all("422" in e for e in watch.errors), watch.errors
    assert not watch.foreign
    context.close()


def _centre(box: dict[str, float] | None) -> tuple[float, float]:
    assert box is not None
    return box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
