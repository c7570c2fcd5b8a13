"""The two lines of a Cobb angle on the PA film, in image pixels, as the SR writes them for viewers.

A Cobb angle is the angle between a line across the upper end vertebra and one across the lower
end vertebra. The engine measures it from each vertebra's frontal tilt θ (``VertebraResult.
frontal_tilt_deg``: from the four corners when the film gives them, else the model's d1;
docs/measures.md), angle = |θ_upper − θ_lower|. Each line is drawn here at its vertebra's tilt:

- direction: the patient-frame vector v = (cos θ, 0, sin θ) (LPS, the frontal plane), on the film
  (e_c·v, e_r·v) in detector mm with e_c, e_r the image axes of the view's patient orientation
  (``spine_engine.projection.image_axes``), then divided by the pixel spacing. The angle between the
  two lines in detector millimetres is therefore exactly the Cobb angle (a viewer that converts the
  pixels with the image's spacing measures the SR's value);
- centre: where the vertebra is on the film, its landmark (endplate midpoint, else the mean of its
  corners, else of its pedicles); a level without a landmark (landmarks on T1..T6 only, the largest
  angle T1–L5) is placed where the fit projects the reconstructed vertebra (its top endplate
  midpoint, ``position``) on the film: ``spine_engine.figures.model_points``, the view's fitted
  projection of the result's ``fit.pa`` (weak perspective s·Rot(ψ)(e_c·r, e_r·r) + T, or the point
  source through its reported central ray, central-ray point, beam, SID and SOD), brought from
  detector mm to the view's units by ``clinical.detector_spacing``. When
  that projection cannot be made (a payload the engine's model no longer validates) no line is drawn
  for such a curve: a line at a neighbouring landmark would put the vertebra elsewhere;
- length: the line runs ``HALF_WIDTH_MM`` either side of the centre, the half-width of a vertebral
  body (about 40 mm wide in the thoracolumbar spine, Panjabi et al., Spine 1992;17:299–306): for
  display only, the angle does not depend on it.

The film's in-plane rotation estimated by the fit (``fit.pa.rotation_deg``) is not applied, as the
tilts from corners are measured in the film's own axes: the drawn lines keep the measured angle.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from pydantic import ValidationError

from services.db.job_forms import engine_payload
from spine_engine.clinical import detector_spacing
from spine_engine.figures import model_points
from spine_engine.levels import LEVELS
from spine_engine.models import PA_ORIENTATION, JobPayload
from spine_engine.projection import image_axes

HALF_WIDTH_MM = 20.0
"""Half the length of each drawn line, detector mm (half a vertebral body's width; module docstring)."""


def _tilt_deg(vertebra: Mapping[str, Any]) -> float:
    """θ = atan2(d1_z, d1_x) (docs/measures.md), the result's ``frontal_tilt_deg`` when it has one."""
    if vertebra.get("frontal_tilt_deg") is not None:
        return float(vertebra["frontal_tilt_deg"])
    d1 = vertebra["directors"][0]
    return math.degrees(math.atan2(d1[2], d1[0]))


def _landmark_centre(landmark: Mapping[str, Any]) -> np.ndarray | None:
    for key in ("point", "corners", "pedicles"):
        if landmark.get(key) is not None:
            points = np.asarray(landmark[key], dtype=float).reshape(-1, 2)
            return np.asarray(points.mean(axis=0))
    return None


def _centres(landmarks: Sequence[Mapping[str, Any]]) -> dict[int, np.ndarray]:
    centres: dict[int, np.ndarray] = {}
    for lm in landmarks:
        centre = _landmark_centre(lm)
        if centre is not None and lm.get("level") in LEVELS:
            centres[LEVELS.index(lm["level"])] = centre
    return centres


def _model_centres(result: Mapping[str, Any], payload: Mapping[str, Any]) -> dict[int, np.ndarray] | None:
    """Every level's reconstructed vertebra where the fit projects it on the PA film, in the PA view's
    own units (px or mm, as its landmarks); None when the projection cannot be made."""
    try:
        engine = engine_payload(payload)
        detector_mm = model_points(result, engine, "pa")
        spacing = detector_spacing(JobPayload.model_validate(engine).pa)
    except (ValidationError, ValueError, KeyError, TypeError, IndexError, ArithmeticError):
        return None
    points = np.asarray(detector_mm, dtype=float) / spacing
    if points.shape != (len(LEVELS), 2) or not np.all(np.isfinite(points)):
        return None
    return {i: points[i] for i in range(len(LEVELS))}


def cobb_lines_px(
    result: Mapping[str, Any], payload: Mapping[str, Any], curve: Mapping[str, Any], spacing: tuple[float, float]
) -> np.ndarray | None:
    """(4, 2) (column, row) pixels: the upper end vertebra's line (points 1, 2) and the lower's (3, 4),
    each from the image's left to its right, for ``curve`` (a ``CobbCurve`` as JSON) on the PA view of
    ``payload`` (the job's payload as JSON, landmarks in ``px`` or ``mm``). ``spacing`` is [row,
    column] mm per pixel of the landmarks' mm and of the directions. None when the view has no
    landmark, or an end vertebra has none and the fit's projection cannot place it (module docstring)."""
    view: Mapping[str, Any] = payload.get("pa") or {}
    row_mm, col_mm = spacing
    units_px = view.get("units", "mm") == "px"
    centres = _centres(view.get("landmarks") or [])
    if not centres:
        return None
    ends = [LEVELS.index(curve["upper"]), LEVELS.index(curve["lower"])]
    if any(i not in centres for i in ends):
        projected = _model_centres(result, payload)
        if projected is None:
            return None
        centres = {**projected, **centres}
    if not units_px:  # landmarks in mm → pixels
        centres = {i: c / np.array([col_mm, row_mm]) for i, c in centres.items()}
    e_c, e_r = image_axes(tuple(view.get("patient_orientation") or PA_ORIENTATION))  # type: ignore[arg-type]
    by_level = {v["level"]: v for v in result.get("vertebrae") or []}
    points = []
    for level, index in zip((curve["upper"], curve["lower"]), ends, strict=True):
        theta = math.radians(_tilt_deg(by_level[level]))
        v = np.array([math.cos(theta), 0.0, math.sin(theta)])
        along_mm = np.array([e_c @ v, e_r @ v])
        along_mm /= np.linalg.norm(along_mm)
        if along_mm[0] < 0:  # from the image's left to its right
            along_mm = -along_mm
        half = HALF_WIDTH_MM * along_mm / np.array([col_mm, row_mm])
        centre = centres[index]
        points += [centre - half, centre + half]
    return np.array(points, dtype=float)
