"""Figures of a reconstruction: the pure renderer (spine_engine.figures) and
GET /v1/jobs/{id}/figure.png|svg (services/api/routes/figures.py)."""

from __future__ import annotations

import uuid
import xml.etree.ElementTree as ET
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from benches.truth import payload_from_truth
from services.core.problems import PROBLEM_BASE
from services.db import runs as repo
from services.db.engine import session_scope
from spine_engine import register
from spine_engine.figures import _detector_mm, model_points, render_figure
from spine_engine.levels import LEVEL_INDEX, N_LEVELS
from spine_engine.models import JobPayload, RegistrationResult
from spine_engine.synthetic import generate_spine
from tests.conftest import problem_of, spine_payload

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
SVG_ROOT = "{http://www.w3.org/2000/svg}svg"


@pytest.fixture(scope="module")
def fitted() -> tuple[dict[str, Any], dict[str, Any]]:
    payload = spine_payload(curve_mm=30.0)
    return register(payload), payload


def test_png_is_a_png_of_the_figure_size(fitted: tuple[dict[str, Any], dict[str, Any]]) -> None:
    body = render_figure(*fitted, "png")
    assert body.startswith(PNG_SIGNATURE)
    width, height = int.from_bytes(body[16:20], "big"), int.from_bytes(body[20:24], "big")
    assert (width, height) == (1320, 880)  # 12 x 8 in at 110 dpi


def test_svg_is_an_svg_document_and_deterministic(fitted: tuple[dict[str, Any], dict[str, Any]]) -> None:
    body = render_figure(*fitted, "svg")
    root = ET.fromstring(body)
    assert root.tag == SVG_ROOT
    assert body == render_figure(*fitted, "svg")  # no date, fixed ids


def test_lateral_view_and_pixel_units_are_drawn() -> None:
    payload = spine_payload(curve_mm=20.0)
    spacing = 0.25
    for lm in payload["pa"]["landmarks"]:
        lm["point"] = [round(lm["point"][0] / spacing, 2), round(lm["point"][1] / spacing, 2)]
    payload["pa"].update(units="px", pixel_spacing=[spacing, spacing])
    lateral = [{"level": lm["level"], "point": [200.0 + 3 * i, lm["point"][1] * spacing]}
               for i, lm in enumerate(payload["pa"]["landmarks"])]  # fmt: skip
    payload["lateral"] = {"landmarks": lateral}
    result = register(payload)
    assert result["fit"]["lateral"] is not None
    assert render_figure(result, payload, "png").startswith(PNG_SIGNATURE)
    assert ET.fromstring(render_figure(result, payload, "svg")).tag == SVG_ROOT


def test_the_title_of_a_spine_below_the_threshold_gives_its_largest_angle() -> None:
    """No curve of 10°: the title says so and gives ``largest_cobb`` (the SVG holds its text)."""
    payload = spine_payload(curve_mm=1.5)
    result = register(payload)
    assert result["measures"]["cobb"] == []
    largest = result["measures"]["largest_cobb"]
    text = f"largest angle {largest['angle_deg']:.1f}° ± {largest['angle_sd_deg']:.1f}°"
    assert text in render_figure(result, payload, "svg").decode()


def test_the_title_marks_a_model_estimated_cobb_angle_and_names_an_apical_disc(
    fitted: tuple[dict[str, Any], dict[str, Any]],
) -> None:
    """``fit.unreliable`` ``cobb``: the title's major Cobb angle says '(model estimate)', as its
    kyphosis does when that is listed; a one-segment curve's apex is its disc ('L4/L5 disc')."""
    result, payload = fitted
    major = next(c for c in result["measures"]["cobb"] if c["major"])
    plain = render_figure(result, payload, "svg").decode()
    angle = f"major Cobb {major['angle_deg']:.1f}° ± {major['angle_sd_deg']:.1f}°"
    assert f"{angle} (" in plain and f"{angle} (model estimate)" not in plain
    flagged = {**result, "fit": {**result["fit"], "unreliable": [*result["fit"]["unreliable"], "cobb"]}}
    assert f"{angle} (model estimate)" in render_figure(flagged, payload, "svg").decode()
    disc = {**result, "measures": {**result["measures"], "cobb": [
        {**major, "upper": "L4", "lower": "L5", "apex": "L4", "apical_disc": True}]}}  # fmt: skip
    assert "L4–L5, apex L4/L5 disc" in render_figure(disc, payload, "svg").decode()


def test_panels_drawn_from_the_prior_say_so() -> None:
    """One PA film without boundary (``fit.unreliable`` has ``depth`` and ``twist``): the lateral projection is
    the prior's sagittal shape and says so, and the angular strain panel names u1 and u3 as model estimates;
    with T1 and L5 given neither note appears on the sagittal side."""
    payload = spine_payload(curve_mm=30.0)
    del payload["boundary"]
    result = register(payload)
    assert {"depth", "twist"} <= set(result["fit"]["unreliable"])
    svg = render_figure(result, payload, "svg").decode()
    assert "model estimate: no film shows depth" in svg and "(u1 and u3: model estimates)" in svg
    given = spine_payload(curve_mm=30.0)
    with_ends = register(given)
    assert "depth" not in with_ends["fit"]["unreliable"]
    svg = render_figure(with_ends, given, "svg").decode()
    assert "no film shows depth" not in svg and "u1 and" not in svg


def test_unknown_format_is_refused(fitted: tuple[dict[str, Any], dict[str, Any]]) -> None:
    with pytest.raises(ValueError, match="unknown figure format"):
        render_figure(*fitted, "gif")  # type: ignore[arg-type]


def _drawn_and_reported(payload: dict[str, Any], view: str) -> tuple[dict[str, Any], np.ndarray, np.ndarray]:
    """The fit of ``payload``; each ``view`` landmark's distance from the model point the figure draws
    its residual line to (``model_points``, detector mm / the view's reported scale), and the distance
    ``fit.residuals`` reports, patient mm."""
    result = register(payload)
    drawn = model_points(result, payload, view)
    film = getattr(JobPayload.model_validate(payload), view)
    scale = result["fit"][view]["scale"]
    reported = {r["level"]: r["residual_mm"] for r in result["fit"]["residuals"] if r["view"] == view}
    points = zip(film.landmarks, _detector_mm(film), strict=True)
    lengths = [np.linalg.norm(p - drawn[LEVEL_INDEX[lm.level]]) / scale for lm, p in points]
    return result, np.array(lengths), np.array([reported[lm.level] for lm in film.landmarks])


def _point_source_pa(acquisition: dict[str, Any], boundary: bool) -> dict[str, Any]:
    payload = spine_payload(curve_mm=30.0)
    if not boundary:
        payload.pop("boundary")
    payload["pa"]["acquisition"] = acquisition
    return payload


SID_SOD = {"distance_source_to_detector_mm": 1800, "distance_source_to_patient_mm": 1600}


@pytest.mark.parametrize(
    "payload",
    [
        _point_source_pa(SID_SOD, boundary=False),  # central ray estimated, o along the beam
        _point_source_pa({**SID_SOD, "central_ray": [100, 250]}, boundary=True),  # c given, o free in 3D
        _point_source_pa({"projection_model": "perspective"}, boundary=False),  # geometry assumed
    ],
    ids=["sid_sod", "central_ray", "projection_model"],
)
def test_the_point_source_pa_residual_lines_are_the_reported_residuals(payload: dict[str, Any]) -> None:
    """A perspective PA: the figure projects the model from the point source as the fit did (not by a
    weak perspective through the central ray's foot, which drew L5 8.7 mm from its landmark where the
    fit reports 0.21 mm), so each residual line is as long as ``fit.residuals`` says."""
    result, drawn, reported = _drawn_and_reported(payload, "pa")
    assert result["fit"]["pa"]["model"] == "perspective"
    np.testing.assert_allclose(drawn, reported, atol=0.01)


def test_the_lateral_residual_lines_turn_with_the_fitted_film_rotation() -> None:
    """A weak-perspective lateral whose in-plane rotation ψ the fit estimated: the figure turns the
    model by ψ, so each residual line is as long as ``fit.residuals`` says (the reported scale is the
    fitted one, the residuals' the starting one: they differ by well under 0.01 mm here)."""
    spine = generate_spine(3, "thoracic")
    every = list(range(N_LEVELS))
    payload = payload_from_truth(spine.positions, spine.rotations, every, every, noise_mm=1.0,
                                 rng=np.random.default_rng(1), boundary=False)  # fmt: skip
    result, drawn, reported = _drawn_and_reported(payload, "lateral")
    assert result["fit"]["lateral"]["model"] == "weak_perspective"
    assert abs(result["fit"]["lateral"]["rotation_deg"]) > 0.3
    np.testing.assert_allclose(drawn, reported, atol=0.01)


# ------------------------------------------------------------------ the routes


def _run_job(api: TestClient, payload: dict[str, Any], *, fail: bool = False) -> str:
    """Submit a job and run it as the worker would (claim, register, finish), in process."""
    job_id = api.post("/v1/jobs", json=payload).json()["id"]
    settings = api.app.state.settings  # type: ignore[attr-defined]
    with session_scope(settings) as session:
        claim = repo.claim_job(session, uuid.UUID(job_id), "test")
        assert claim is not None
        if fail:
            error = {"type": PROBLEM_BASE + "fit-failed", "title": "failed", "status": 422, "detail": "no"}
            assert repo.finish_job(session, claim, error=error)
        else:
            assert repo.finish_job(session, claim, result=RegistrationResult.model_validate(register(claim.payload)))
    return str(job_id)


@pytest.mark.parametrize(("fmt", "media_type"), [("png", "image/png"), ("svg", "image/svg+xml")])
def test_a_succeeded_job_has_its_figure(api: TestClient, fmt: str, media_type: str) -> None:
    job_id = _run_job(api, spine_payload(curve_mm=25.0))
    response = api.get(f"/v1/jobs/{job_id}/figure.{fmt}")
    assert response.status_code == 200, response.text
    assert response.headers["content-type"].startswith(media_type)
    if fmt == "png":
        assert response.content.startswith(PNG_SIGNATURE)
    else:
        assert ET.fromstring(response.content).tag == SVG_ROOT


@pytest.mark.parametrize("fmt", ["png", "svg"])
def test_queued_failed_and_cancelled_jobs_answer_409(api: TestClient, fmt: str) -> None:
    queued = api.post("/v1/jobs", json=spine_payload()).json()["id"]
    failed = _run_job(api, spine_payload(), fail=True)
    cancelled = api.post("/v1/jobs", json=spine_payload()).json()["id"]
    api.post(f"/v1/jobs/{cancelled}/cancel")
    for job_id, status in ((queued, "queued"), (failed, "failed"), (cancelled, "cancelled")):
        response = api.get(f"/v1/jobs/{job_id}/figure.{fmt}")
        assert response.status_code == 409
        problem = problem_of(response)
        assert problem["type"] == PROBLEM_BASE + "job-has-no-result"
        assert problem["job_status"] == status
        assert problem["instance"] == f"/v1/jobs/{job_id}/figure.{fmt}"
        assert problem["detail"].startswith(f"job {job_id} ")
    assert "once it has succeeded" in problem_of(api.get(f"/v1/jobs/{queued}/figure.{fmt}"))["detail"]


@pytest.mark.parametrize("fmt", ["png", "svg"])
def test_unknown_job_is_404_and_bad_id_422(api: TestClient, fmt: str) -> None:
    response = api.get(f"/v1/jobs/{uuid.uuid4()}/figure.{fmt}")
    assert response.status_code == 404
    assert problem_of(response)["type"] == PROBLEM_BASE + "not-found"
    response = api.get(f"/v1/jobs/not-a-uuid/figure.{fmt}")
    assert response.status_code == 422
    assert problem_of(response)["type"] == PROBLEM_BASE + "validation-error"
