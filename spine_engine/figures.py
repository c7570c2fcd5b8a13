"""Figures of a reconstruction: PA and lateral views with landmarks and residuals, and strains.

``render_figure(result, payload, fmt)`` is a pure function from a ``RegistrationResult`` dict and
the ``JobPayload`` dict it came from to the bytes of a PNG or SVG image. It knows nothing of HTTP.
This module places what the panels show (projections, landmarks, titles); ``figure_drawing`` draws
them with matplotlib (Agg; no pyplot state, so it is safe in threads), imported on the first figure.

The figure has four panels:

- PA view, in the PA image's detector frame (column right, row down, mm): the landmarks, the
  model's vertebrae projected as the fit projected them (``view_projection``: the view's camera,
  weak perspective or point source, with its fitted in-plane rotation), and the residual of each
  landmark (a line to the projected model point, as long as ``fit.residuals`` says);
- lateral view: the lateral image's frame when the payload has one (same content as PA), else
  the model projected laterally (``["A","F"]``) with the PA scale, its mean row the PA panel's;
- per-level angular strain u = (u1, u2, u3) and per-level v = (v1, v2, v3).

Vertebrae are drawn as the projection of a box below their top endplate midpoint, spanned by
d1 (PA) or d2 (lateral) and d3, and coloured by frontal bending (u2·Δs, degrees) on a diverging
map, as in Fig. 2 of Li et al. (CAIP 2009). L5 has no segment below it and is drawn grey.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Literal

import numpy as np

from .clinical import landmark_arrays
from .fit import Camera
from .fit.cameras import project as project_by_camera
from .models import LATERAL_ORIENTATION, JobPayload, LateralView, PAView
from .projection import Projector, image_axes, project

FigureFormat = Literal["png", "svg"]
MEDIA_TYPES: dict[str, str] = {"png": "image/png", "svg": "image/svg+xml"}


def _detector_mm(view: Any) -> np.ndarray:
    """The view's fitted points in detector mm, as the engine converts them (``clinical.landmark_arrays``:
    px × pixel spacing; corners → the superior endplate midpoint, whichever way up the image is)."""
    return landmark_arrays(view).points.reshape(-1, 2)


def _landmarks(view: PAView | LateralView) -> list[tuple[str, np.ndarray]]:
    """(level, detector mm) of each landmark of ``view`` (``_detector_mm``), as the figure draws them."""
    return [(lm.level, p) for lm, p in zip(view.landmarks, _detector_mm(view), strict=True)]


def view_projection(result: Mapping[str, Any], payload: JobPayload, name: str) -> Projector:
    """The projection of view ``name`` ("pa" or "lateral") as the fit projected the model, from the
    result's ``fit.<name>`` (``ViewProjection``) through the engine's own ``fit.cameras.project``: weak
    perspective p = s·Rot(ψ)(e_c·r, e_r·r) + T, or the point source (``model`` "perspective")
    p = c + m·Rot(ψ)(e_c·(r − o), e_r·(r − o)), m = SID / (SOD + b·(r − o)), with c = ``translation``,
    o = ``central_ray_point_mm``, b = ``beam_direction``. The drawing and ``model_points`` both
    project through it."""
    proj = result["fit"].get(name)
    view = payload.pa if name == "pa" else payload.lateral
    if view is None or proj is None:
        raise ValueError(f"the {'payload' if view is None else 'result'} has no {name} view")
    e_c, e_r = image_axes(view.patient_orientation)
    psi = math.radians(float(proj.get("rotation_deg", 0.0)))
    c_c, c_r = (float(t) for t in proj["translation"])
    if proj.get("model", "weak_perspective") == "perspective" and proj.get("central_ray_point_mm") is not None:
        values = np.array([c_c, c_r, *(float(v) for v in proj["central_ray_point_mm"]), psi])
        camera = Camera(
            "perspective", values, np.zeros(6, dtype=bool), sid_mm=float(proj["source_to_detector_mm"]),
            sod_mm=float(proj["source_to_patient_mm"]), beam=np.asarray(proj["beam_direction"], dtype=float),
        )  # fmt: skip
    else:  # weak perspective (a result stored before the point source was reported is drawn so too)
        values = np.array([float(proj["scale"]), c_c, c_r, psi])
        camera = Camera("weak", values, np.zeros(4, dtype=bool))

    def projector(points: np.ndarray) -> np.ndarray:
        points = np.asarray(points, dtype=float)
        flat = project_by_camera(camera, values, points.reshape(-1, 3), e_c, e_r).points
        return flat.reshape(*points.shape[:-1], 2)

    return projector


def model_points(result: Mapping[str, Any], payload: Mapping[str, Any], name: str) -> np.ndarray:
    """(17, 2) the model's vertebrae (top endplate midpoints) on view ``name``'s detector, mm, where the
    figure draws them (``view_projection``): each landmark's residual line ends there."""
    positions = np.array([v["position"] for v in result["vertebrae"]], dtype=float)
    return view_projection(result, JobPayload.model_validate(payload), name)(positions)


def _depth_note(fit: Mapping[str, Any]) -> str:
    """The lateral projection's second title line when no film places the spine in depth (``fit.unreliable``
    ``depth``): the depths drawn are the population prior's sagittal shape, not a measurement."""
    if "depth" not in set(fit.get("unreliable") or []):
        return ""
    return "\nmodel estimate: no film shows depth"


def render_figure(
    result: Mapping[str, Any], payload: Mapping[str, Any], fmt: FigureFormat = "png", *, dpi: int = 110
) -> bytes:
    """The figure of a reconstruction as PNG or SVG bytes.

    ``result`` is a ``RegistrationResult`` as JSON (what a succeeded job holds), ``payload`` the
    ``JobPayload`` it was computed from. Raises ValueError for an unknown format.
    """
    if fmt not in MEDIA_TYPES:
        raise ValueError(f"unknown figure format {fmt!r}; expected one of {sorted(MEDIA_TYPES)}")
    from .figure_drawing import DrawnView, draw_figure  # lazy: matplotlib, a fifth of a process's start, to draw only

    model = JobPayload.model_validate(payload)
    fit = result["fit"]
    pa_projector = view_projection(result, model, "pa")
    pa = DrawnView("PA view: landmarks, model and residuals", pa_projector, _landmarks(model.pa))
    if model.lateral is not None and model.lateral.landmarks and fit.get("lateral") is not None:
        lateral = DrawnView("Lateral view: landmarks, model and residuals", view_projection(result, model, "lateral"),
                            _landmarks(model.lateral))  # fmt: skip
    else:
        positions = np.array([v["position"] for v in result["vertebrae"]], dtype=float)
        e_c, e_r = image_axes(LATERAL_ORIENTATION)
        scale = float(fit["pa"]["scale"])  # a point-source PA's: SID/SOD at the spine's mid-plane
        row = float(np.mean(pa_projector(positions)[:, 1]) - scale * np.mean(positions @ e_r))  # the PA's mean row
        lateral = DrawnView("Lateral projection of the model (anterior right)" + _depth_note(fit),
                            lambda r: project(r, e_c, e_r, scale, np.array([0.0, row])), [])  # fmt: skip
    return draw_figure(result, pa, lateral, fmt, dpi=dpi)
