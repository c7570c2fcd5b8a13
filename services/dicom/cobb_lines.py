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
  corners, else of its pedicles); a level without a landmark is placed by linear interpolation in
  level number between the nearest landmarked levels above and below (the nearest one beyond the
  ends);
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

from spine_engine.levels import LEVELS
from spine_engine.models import PA_ORIENTATION
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


def _centre_at(centres: Mapping[int, np.ndarray], index: int) -> np.ndarray:
    if index in centres:
        return centres[index]
    above = [i for i in centres if i < index]
    below = [i for i in centres if i > index]
    if not above or not below:
        return centres[min(centres, key=lambda i: abs(i - index))]
    a, b = max(above), min(below)
    t = (index - a) / (b - a)
    return np.asarray((1 - t) * centres[a] + t * centres[b])


def cobb_lines_px(
    result: Mapping[str, Any], view: Mapping[str, Any], curve: Mapping[str, Any], spacing: tuple[float, float]
) -> np.ndarray | None:
    """(4, 2) (column, row) pixels: the upper end vertebra's line (points 1, 2) and the lower's (3, 4),
    each from the image's left to its right, for ``curve`` (a ``CobbCurve`` as JSON) on the PA
    ``view`` (its JSON, landmarks in ``px`` or ``mm``). ``spacing`` is [row, column] mm per pixel of
    the landmarks' mm and of the directions. None when the view has no landmark."""
    row_mm, col_mm = spacing
    units_px = view.get("units", "mm") == "px"
    centres = _centres(view.get("landmarks") or [])
    if not centres:
        return None
    if not units_px:  # landmarks in mm → pixels
        centres = {i: c / np.array([col_mm, row_mm]) for i, c in centres.items()}
    e_c, e_r = image_axes(tuple(view.get("patient_orientation") or PA_ORIENTATION))  # type: ignore[arg-type]
    by_level = {v["level"]: v for v in result.get("vertebrae") or []}
    points = []
    for level in (curve["upper"], curve["lower"]):
        theta = math.radians(_tilt_deg(by_level[level]))
        v = np.array([math.cos(theta), 0.0, math.sin(theta)])
        along_mm = np.array([e_c @ v, e_r @ v])
        along_mm /= np.linalg.norm(along_mm)
        if along_mm[0] < 0:  # from the image's left to its right
            along_mm = -along_mm
        half = HALF_WIDTH_MM * along_mm / np.array([col_mm, row_mm])
        centre = _centre_at(centres, LEVELS.index(level))
        points += [centre - half, centre + half]
    return np.array(points, dtype=float)
