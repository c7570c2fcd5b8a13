"""A view's mm in the patient plane ('calibrated', PS3.3 §10.7.1.1: what the DICOM layer hands over
for a calibrated Pixel Spacing or an imager spacing divided by the ERMF) give the same spine as the
same film in detector mm: the engine multiplies them back by the acquisition's magnification (ERMF,
else SID/SOD) instead of dividing twice, and without a magnification takes 1, not the PA prior."""

from __future__ import annotations

from typing import Any

import numpy as np

from benches.clinic import synthetic_truths
from benches.clinic_films import CASES, build_payload, simulate_series
from spine_engine.clinical import calibrated_magnification, detector_spacing
from spine_engine.models import JobPayload
from spine_engine.reconstruction import register_model


def _series() -> Any:
    return simulate_series(synthetic_truths(1, seed=11)[0], noise_mm=0.5, seed=3)


def _to_patient_plane(view: dict[str, Any], magnification: float) -> dict[str, Any]:
    """The view's detector-mm landmarks (and central ray) divided by the magnification, flagged calibrated;
    its landmark SD stays in detector mm (``landmark_sd_mm``'s unit), so the fit weighs it the same."""
    out = {**view, "pixel_spacing_calibration": "calibrated"}
    out["landmarks"] = [{**lm, "point": [c / magnification for c in lm["point"]]} for lm in view["landmarks"]]
    acq = view.get("acquisition")
    if acq and acq.get("central_ray"):
        out["acquisition"] = {**acq, "central_ray": [c / magnification for c in acq["central_ray"]]}
    return out


def _fit(payload: dict[str, Any]) -> Any:
    return register_model(JobPayload.model_validate(payload))


def _relative_positions(result: Any) -> np.ndarray:
    p = np.array([v.position for v in result.vertebrae])
    return p - p.mean(axis=0)


def test_calibrated_perspective_film_equals_the_detector_film() -> None:
    detector = build_payload(_series(), CASES["c"]).model_dump(mode="json", exclude_none=True)
    calibrated = dict(detector)
    for role in ("pa", "lateral"):
        acq = detector[role]["acquisition"]
        m = acq["distance_source_to_detector_mm"] / acq["distance_source_to_patient_mm"]
        calibrated[role] = _to_patient_plane(detector[role], m)
    a, b = _fit(detector), _fit(calibrated)
    # the same numbers up to rounding: 1e-6 mm is far below any landmark's precision
    assert np.allclose(_relative_positions(a), _relative_positions(b), atol=1e-6)
    assert b.fit.pa.pixel_spacing_calibration == "calibrated"


def test_calibrated_film_with_its_ermf_equals_the_detector_film() -> None:
    detector = build_payload(_series(), CASES["e"]).model_dump(mode="json", exclude_none=True)
    ermf = 1.12
    acquisition = {"magnification": ermf}
    given = {**detector, "pa": {**detector["pa"], "acquisition": acquisition}}
    calibrated = {**detector, "pa": {**_to_patient_plane(detector["pa"], ermf), "acquisition": acquisition}}
    a, b = _fit(given), _fit(calibrated)
    assert np.allclose(_relative_positions(a), _relative_positions(b), atol=1e-6)


def test_calibrated_without_geometry_takes_magnification_one_not_the_prior() -> None:
    detector = build_payload(_series(), CASES["e"]).model_dump(mode="json", exclude_none=True)
    calibrated = {**detector, "pa": _to_patient_plane(detector["pa"], 1.12)}
    view = JobPayload.model_validate(calibrated).pa
    assert calibrated_magnification(view) == 1.0
    assert np.allclose(detector_spacing(view), 1.0)
    result = _fit(calibrated)
    assert result.fit.pa.scale_source == "acquisition" and "scale" not in result.fit.unreliable
    assert abs(result.fit.pa.scale - 1.0) < 1e-12
    assert _fit(detector).fit.pa.scale_source == "prior"  # detector mm without geometry: the prior, flagged
