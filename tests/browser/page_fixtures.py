"""Shared pieces of the page's browser tests: a real `spine serve` (API + worker child, embedded
SQLite) on 127.0.0.1, Debian's Chromium driven by Playwright, synthetic DX films made with pydicom
(PS3.3 §A.26 Digital X-Ray Image, uncompressed explicit VR little endian), and axe-core (shipped
by the pinned axe-playwright-python wheel) for the accessibility checks.

Imported by the test modules (`from page_fixtures import ...`); the service and the browser are
session fixtures of tests/browser/conftest.py, shared by every page module.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import socket
import subprocess
import sys
import time
import uuid
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import httpx
import numpy as np
import pytest

from spine_engine.levels import LEVELS
from tests import stopping

CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
    "--disable-component-update", "--no-first-run", "--disable-sync", "--disable-quic",
]  # fmt: skip
FILM_SIZE = (560, 900)  # columns, rows (px)
PA_SPACING = 0.4  # Imager Pixel Spacing of the PA film, mm
LATERAL_SPACING = 0.45  # calibrated Pixel Spacing of the lateral film, mm
BODY_HALF_WIDTH = 24.0  # px
BODY_HEIGHT = 22.0  # px


def spacing_shown(mm: float) -> str:
    """A header's spacing as the page's field shows it: six significant digits (``panel.ts`` ``spacingText``,
    JavaScript's ``String(Number(mm.toPrecision(6)))``)."""
    return repr(float(f"{mm:.6g}"))


def chromium_path() -> str | None:
    for candidate in (os.environ.get("SPINE_CHROMIUM"), "/usr/bin/chromium", shutil.which("chromium")):
        if candidate and os.access(candidate, os.X_OK):
            return candidate
    return None


# ---------------------------------------------------------------- synthetic films


def centreline(i: int, curve_px: float = 70.0) -> tuple[float, float, float]:
    """Top endplate midpoint (column, row) of level i on the PA film and the tilt (rad) of its
    endplate: an S-curve, thoracic to the right of the image, lumbar to the left."""
    t = i / (len(LEVELS) - 1)
    col = FILM_SIZE[0] / 2 + curve_px * math.sin(2 * math.pi * t) * 0.8
    row = 60.0 + 740.0 * t
    slope = curve_px * 0.8 * 2 * math.pi * math.cos(2 * math.pi * t) / 740.0  # d col / d row
    return col, row, math.atan(slope)


def pa_corners() -> list[list[tuple[float, float]]]:
    """Four corners per level (top-left, top-right, bottom-left, bottom-right) of bodies tilted with the curve."""
    out = []
    for i in range(len(LEVELS)):
        col, row, tilt = centreline(i)
        across = (math.cos(tilt), -math.sin(tilt))  # along the endplate (image right)
        down = (math.sin(tilt), math.cos(tilt))
        tl = (col - BODY_HALF_WIDTH * across[0], row - BODY_HALF_WIDTH * across[1])
        tr = (col + BODY_HALF_WIDTH * across[0], row + BODY_HALF_WIDTH * across[1])
        bl = (tl[0] + BODY_HEIGHT * down[0], tl[1] + BODY_HEIGHT * down[1])
        br = (tr[0] + BODY_HEIGHT * down[0], tr[1] + BODY_HEIGHT * down[1])
        out.append([tl, tr, bl, br])
    return out


def lateral_points(first: str = "T4") -> list[tuple[str, float, float]]:
    """Endplate midpoints of the lateral film from `first` to L5: kyphosis then lordosis."""
    out = []
    for i, level in enumerate(LEVELS):
        if i < LEVELS.index(first):
            continue
        t = i / (len(LEVELS) - 1)
        out.append((level, FILM_SIZE[0] / 2 - 40.0 * math.sin(2 * math.pi * t), 60.0 + 700.0 * t))
    return out


def film_pixels(
    bodies: list[list[tuple[float, float]]], monochrome1: bool, size: tuple[int, int] = FILM_SIZE
) -> np.ndarray:
    """12-bit film of `size` (columns, rows): soft tissue, and bright (dense) vertebral bodies;
    MONOCHROME1 stores them low."""
    from PIL import Image, ImageDraw, ImageFilter

    image = Image.new("L", size, 20)
    draw = ImageDraw.Draw(image)
    draw.rectangle((size[0] * 0.2, 0, size[0] * 0.8, size[1]), fill=60)
    for tl, tr, bl, br in bodies:
        draw.polygon([tl, tr, br, bl], fill=210)
    grey = np.asarray(image.filter(ImageFilter.GaussianBlur(1.2)), dtype=np.float64)
    density = (grey / 255.0 * 3000 + 500).astype(np.uint16)  # 12 bits stored
    return (4095 - density).astype(np.uint16) if monochrome1 else density


def make_dicom(
    path: Path,
    *,
    view: str = "pa",
    monochrome1: bool = False,
    first_lateral: str = "T4",
    spacing: dict[str, list[float]] | None = None,
    transfer_syntax: str | None = None,
    bodies: list[list[tuple[float, float]]] | None = None,
    size: tuple[int, int] = FILM_SIZE,
    study: dict[str, str] | None = None,
) -> dict[str, Any]:
    """A DX film with the attributes the page reads; returns them for the assertions. `spacing`
    replaces the view's spacing attributes (keys PixelSpacing, ImagerPixelSpacing); an empty dict
    leaves the film without any. `transfer_syntax` only labels the file (its pixels stay raw).
    `bodies` (four corners each) and `size` (columns, rows) replace the synthetic spine and film
    size; `study` replaces header attributes by keyword (e.g. StudyInstanceUID, StudyDate)."""
    import pydicom
    from pydicom.dataset import FileMetaDataset
    from pydicom.encaps import encapsulate
    from pydicom.uid import UID, ExplicitVRLittleEndian, generate_uid

    if bodies is not None:
        pass
    elif view == "pa":
        bodies = pa_corners()
    else:
        bodies = []
        for _, col, row in lateral_points(first_lateral):
            bodies.append([(col - 26, row), (col + 26, row), (col - 26, row + 22), (col + 26, row + 22)])
    pixels = film_pixels(bodies, monochrome1, size)
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = UID("1.2.840.10008.5.1.4.1.1.1.1")  # Digital X-Ray Image Storage - For Presentation
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = pydicom.Dataset()
    ds.file_meta = meta
    ds.SOPClassUID = meta.MediaStorageSOPClassUID
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.StudyInstanceUID = "1.2.826.0.1.3680043.8.498.1001"
    ds.SeriesInstanceUID = "1.2.826.0.1.3680043.8.498.1002"
    ds.Modality = "DX"
    ds.PatientName = "DOE^JANE"
    ds.PatientID = "PAT-0042"
    ds.AccessionNumber = "ACC-7"
    ds.StudyDate = "20261130"
    ds.ViewPosition = "PA" if view == "pa" else "LL"
    ds.PatientOrientation = ["L", "F"] if view == "pa" else ["A", "F"]
    ds.Rows, ds.Columns = pixels.shape
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME1" if monochrome1 else "MONOCHROME2"
    ds.BitsAllocated = 16
    ds.BitsStored = 12
    ds.HighBit = 11
    ds.PixelRepresentation = 0
    ds.WindowCenter = 2000
    ds.WindowWidth = 3500
    for keyword, text in (study or {}).items():
        setattr(ds, keyword, text)
    if spacing is not None:
        for keyword, value in spacing.items():
            setattr(ds, keyword, value)
    elif view == "pa":
        ds.ImagerPixelSpacing = [PA_SPACING, PA_SPACING]
        ds.EstimatedRadiographicMagnificationFactor = 1.2
        ds.DistanceSourceToDetector = 1800
        ds.DistanceSourceToPatient = 1500
    else:
        ds.PixelSpacing = [LATERAL_SPACING, LATERAL_SPACING]
        ds.ImagerPixelSpacing = [0.5, 0.5]
        ds.PixelSpacingCalibrationType = "GEOMETRY"
    ds.PixelData = pixels.tobytes()
    ds.save_as(path, enforce_file_format=True)
    if transfer_syntax:
        relabelled = pydicom.dcmread(path)
        relabelled.file_meta.TransferSyntaxUID = UID(transfer_syntax)
        relabelled.PixelData = encapsulate([pixels.tobytes()])  # one fragment: labelled, not really encoded
        relabelled.save_as(path, enforce_file_format=True)
    return {"bodies": bodies, "pixels": pixels}


def make_png(path: Path) -> None:
    from PIL import Image

    density = film_pixels(pa_corners(), monochrome1=False)
    Image.fromarray((density / 16).astype(np.uint8)).save(path)


# ---------------------------------------------------------------- service and browser


def pdf_text(pdf: Path) -> str:
    """The text of a printed report (poppler-utils' ``pdftotext``, which ``make browser`` installs); a
    skip saying why where it is missing, which fails in CI (tests/conftest.py)."""
    if shutil.which("pdftotext") is None:
        pytest.skip("pdftotext (Debian's poppler-utils) is missing: `make browser` installs it")
    return subprocess.run(["pdftotext", str(pdf), "-"], capture_output=True, text=True, check=True).stdout


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class Serve:
    """One `spine serve` subprocess: its URL and the API key it printed at first start."""

    proc: subprocess.Popen[bytes]
    url: str
    api_key: str
    log: Path


def start_serve(data_dir: Path, **extra_env: str) -> Serve:
    """`spine serve` (uvicorn API and its Celery worker child, embedded SQLite in `data_dir`) on a free
    port of 127.0.0.1 with `extra_env`; waits for /readyz and reads the API key it prints."""
    port = free_port()
    env = {
        **os.environ,
        "SPINE_DATA_DIR": str(data_dir),
        "SPINE_QUEUE_NAME": f"spine-page-{uuid.uuid4().hex[:8]}",
        "SPINE_WORKER_CONCURRENCY": "1",
        "SPINE_LOG_LEVEL": "WARNING",
    }
    for key in ("DATABASE_URL", "CELERY_BROKER_URL", "SPINE_SERVE_WORKER"):
        env.pop(key, None)
    env.update(extra_env)
    log_path = data_dir / "serve.log"
    with log_path.open("wb") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "serve", "--host", "127.0.0.1", "--port", str(port)],
            env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
        )  # fmt: skip
    stopping.started(proc)
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
        printed = re.search(r"^(spine_[0-9a-f]{12}_[A-Za-z0-9_-]{43})$", log_path.read_text(errors="replace"), re.M)
        assert printed, f"spine serve printed no API key:\n{log_path.read_text(errors='replace')[-4000:]}"
    except BaseException:
        stop_serve(proc)
        raise
    return Serve(proc, url, printed.group(1), log_path)


def stop_serve(proc: subprocess.Popen[bytes]) -> None:
    """SIGTERM to `spine serve` (it stops its worker child; none if the session's end sent it already,
    tests/stopping.py), SIGKILL to its process group after 30 s."""
    stopping.stop(proc, grace_s=30)


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

    def posted_jobs(self) -> list[Any]:
        return [r for r in self.requests if r.method == "POST" and r.url.endswith("/v1/jobs")]


def pa_points_payload() -> dict[str, Any]:
    """A PA film's 17 midpoints along ``centreline``, in px of 0.4 mm: a payload the service fits."""
    marks = [
        {"level": lv, "point": [round(centreline(i)[0], 1), round(centreline(i)[1], 1)]} for i, lv in enumerate(LEVELS)
    ]
    return {"pa": {"units": "px", "pixel_spacing": [0.4, 0.4], "landmarks": marks}}


def run_job(url: str, key: str, payload: dict[str, Any]) -> dict[str, Any]:
    """Submit ``payload`` to the service at ``url`` and wait (up to 90 s) for its job to succeed."""
    headers = {"Authorization": f"Bearer {key}"}
    job = httpx.post(f"{url}/v1/jobs", json=payload, headers=headers, timeout=10).json()
    deadline = time.monotonic() + 90
    while job["status"] not in ("succeeded", "failed", "cancelled"):
        assert time.monotonic() < deadline, job
        time.sleep(0.3)
        job = httpx.get(f"{url}/v1/jobs/{job['id']}", headers=headers, timeout=10).json()
    assert job["status"] == "succeeded", job
    return job


def reconstruct_on_page(page: Any) -> dict[str, Any]:
    """Click Reconstruct, check the service took the job (202) and wait (up to 120 s) for the page to show it
    succeeded, with no problem shown; returns the payload the page sent."""
    with page.expect_response(lambda r: r.request.method == "POST" and r.url.endswith("/v1/jobs")) as posted:
        page.click("#submit")
    assert posted.value.status == 202, posted.value.text()
    job_id = posted.value.json()["id"]
    # the status of this job, not the previous one's "succeeded" still shown right after the POST's answer
    page.wait_for_function(
        "(id) => { const s = document.getElementById('job-status'); "
        "return (s.textContent || '').includes(id) && ['succeeded', 'failed'].includes(s.dataset.status); }",
        arg=job_id, timeout=120_000,
    )
    if page.get_attribute("#job-status", "data-status") != "succeeded":  # the job's own error says why
        job = page.evaluate(
            "(id) => fetch('/v1/jobs/' + id, {headers: {Authorization: 'Bearer ' + "
            "document.getElementById('api-key').value}}).then((r) => r.json())",
            job_id,
        )
        raise AssertionError(f"job {job_id} did not succeed: {job.get('status')} {job.get('error')}; the page "
                             f"says {page.text_content('#problem')!r}")  # fmt: skip
    assert page.locator("#problem").is_hidden()
    sent: dict[str, Any] = json.loads(posted.value.request.post_data or "{}")
    return sent


def open_page(
    browser: Any, url: str, api_key: str | None, *, width: int = 1440, height: int = 1000
) -> tuple[Any, Any, PageWatch]:
    context = browser.new_context(viewport={"width": width, "height": height}, accept_downloads=True)
    page = context.new_page()
    parts = urlsplit(url)
    watch = PageWatch(page, f"{parts.scheme}://{parts.netloc}")
    page.goto(url)
    page.wait_for_selector("body[data-ready=true]")
    if api_key:
        page.fill("#api-key", api_key)
    return context, page, watch


def payload_preview(page: Any) -> Any:
    """The payload the page would send, as its preview shows it: parsed JSON, or the preview's text
    when it is not JSON (a message instead of a payload)."""
    text = page.text_content("#payload-preview") or ""
    try:
        return json.loads(text)
    except ValueError:
        return text


def open_film(page: Any, view: str, path: Path) -> None:
    """Open the film ``path`` in ``view``'s panel ("pa" or "lateral") and wait until its canvas names it."""
    page.click(f"#tab-film-{view}")
    page.set_input_files(f"#{view}-file", str(path))
    page.wait_for_function(
        f"() => /{path.name}/.test(document.getElementById('{view}-canvas').getAttribute('aria-label'))"
    )


def click_pa_midpoints(page: Any, levels: Any) -> None:
    """Click, on the PA film's canvas, the endplate midpoints of the synthetic film's bodies ``levels``
    (indices 0 = T1 … 16 = L5, ``centreline``), in that order."""
    for i in levels:
        col, row, _ = centreline(i)
        page.mouse.click(*canvas_point(page, "pa", col, row))


JOB_READ = re.compile(r"/v1/jobs/[0-9a-f-]{36}$")
"""GET /v1/jobs/{id}: the page's read of a job (its poll), not of the job's figures or downloads."""


def unavailable_once(page: Any, url: str | re.Pattern[str], detail: str = "the API is restarting") -> list[float]:
    """Route the page's requests to ``url`` (a Playwright glob or pattern) so that the first is answered 503 with
    Retry-After: 30 and a problem+json saying ``detail``, the others reach the service; returns the list
    to which each request's time (``time.monotonic()``) is appended."""
    reads: list[float] = []
    unavailable = [1]

    def answer(route: Any) -> None:
        reads.append(time.monotonic())
        if unavailable[0]:
            unavailable[0] -= 1
            route.fulfill(status=503, headers={"Retry-After": "30"}, content_type="application/problem+json",
                          body=json.dumps({"type": "about:blank", "title": "Service Unavailable", "status": 503,
                                           "detail": detail}))  # fmt: skip
        else:
            route.continue_()

    page.route(url, answer)
    return reads


def place_pa_and_lateral(page: Any, tmp_path: Any) -> None:
    """Open the synthetic PA and lateral DICOM films (``make_dicom``, written under ``tmp_path``) on ``page``
    and click T1–L5's midpoints on the PA and T4–L5's on the lateral: a lateral from T4, as clinics send."""
    make_dicom(tmp_path / "pa.dcm", view="pa")
    make_dicom(tmp_path / "lat.dcm", view="lateral")
    open_film(page, "pa", tmp_path / "pa.dcm")
    click_pa_midpoints(page, range(len(LEVELS)))
    open_film(page, "lateral", tmp_path / "lat.dcm")
    page.select_option("#lateral-level", "T4")
    for _, col, row in lateral_points("T4"):
        page.mouse.click(*canvas_point(page, "lateral", col, row))


def click_pa_pedicles(page: Any, body: Any) -> None:
    """Click, on the PA film's canvas, two pedicle centres inside the synthetic body with corners ``body``
    (``pa_corners()[i]``: top-left, top-right, bottom-left, bottom-right): a quarter and three quarters
    across its top edge, 0.3 of its height down."""
    tl, tr, bl, _ = body
    for f in (0.25, 0.75):
        page.mouse.click(*canvas_point(page, "pa", tl[0] + f * (tr[0] - tl[0]) + 0.3 * (bl[0] - tl[0]),
                                       tl[1] + f * (tr[1] - tl[1]) + 0.3 * (bl[1] - tl[1])))  # fmt: skip


def canvas_point(page: Any, view: str, col: float, row: float) -> tuple[float, float]:
    """Page coordinates (CSS px) of an image point on a fitted film canvas (scrolled to the window's top)."""
    page.evaluate("(view) => document.getElementById(view + '-canvas').scrollIntoView({block: 'start'})", view)
    box = page.locator(f"#{view}-canvas").bounding_box()
    assert box is not None
    fitted = page.evaluate(
        """([view, w, h]) => {
            const c = document.getElementById(view + '-canvas').getBoundingClientRect();
            const s = Math.min(c.width / w, c.height / h);
            return [s, (c.width - w * s) / 2, (c.height - h * s) / 2];
        }""",
        [view, FILM_SIZE[0], FILM_SIZE[1]],
    )
    s, ox, oy = fitted
    return box["x"] + ox + col * s, box["y"] + oy + row * s


def canvas_grey(page: Any, view: str, col: float, row: float) -> int:
    """Grey level drawn on the film canvas at image point (col, row)."""
    x, y = canvas_point(page, view, col, row)
    return int(page.evaluate(
        """([view, x, y]) => {
            const c = document.getElementById(view + '-canvas');
            const r = c.getBoundingClientRect();
            const k = c.width / r.width;
            const [px, py] = [Math.round((x - r.left) * k), Math.round((y - r.top) * k)];
            return c.getContext('2d').getImageData(px, py, 1, 1).data[0];
        }""",
        [view, x, y],
    ))  # fmt: skip


def run_axe(page: Any) -> list[dict[str, Any]]:
    """axe-core (WCAG 2 A and AA rules) on the page as it is; returns the violations."""
    script = resources.files("axe_playwright_python").joinpath("axe.min.js").read_text()
    page.evaluate(script)
    result = page.evaluate(
        "async () => await axe.run(document, {runOnly: {type: 'tag', "
        "values: ['wcag2a', 'wcag2aa', 'wcag21a', 'wcag21aa']}})"
    )
    return [
        {"id": v["id"], "help": v["help"], "nodes": [n["target"] for n in v["nodes"]][:5]} for v in result["violations"]
    ]
