"""The contract's payload and result fields (openapi.yaml): new optional payload fields, result fields, and the
deprecated bending names, which must equal the new names by plane."""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
import pytest

from spine_engine import register
from spine_engine.errors import InvalidInput
from spine_engine.models import JobPayload, RegistrationResult, VertebraResult
from spine_engine.validation import validate_payload
from tests.conftest import spine_payload


def test_deprecated_bending_names_equal_the_new_ones() -> None:
    result = register(spine_payload())
    segments = [v for v in result["vertebrae"] if v["u"] is not None]
    assert len(segments) == 16
    for v in segments:
        assert v["sagittal_bending_deg"] == v["pa_bending_deg"]
        assert v["frontal_bending_deg"] == v["lateral_bending_deg"]
    assert any(abs(v["frontal_bending_deg"]) > 0.1 for v in segments)  # a C-curve bends frontally
    assert result["vertebrae"][-1]["sagittal_bending_deg"] is None and result["vertebrae"][-1]["pa_bending_deg"] is None


def test_old_names_alone_fill_the_new_ones() -> None:
    """A stored result written before this version (old names only) reads back with both names."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        v = VertebraResult(
            level="T3", position=(0, 0, 0), directors=((1, 0, 0), (0, 1, 0), (0, 0, 1)), u=None, v=None,
            pa_bending_deg=2.5, lateral_bending_deg=-1.0, twist_deg=None, axial_rotation_deg=0.0,
        )  # fmt: skip
    dumped = v.model_dump()
    assert (dumped["sagittal_bending_deg"], dumped["frontal_bending_deg"]) == (2.5, -1.0)
    assert (dumped["pa_bending_deg"], dumped["lateral_bending_deg"]) == (2.5, -1.0)


def test_deprecated_names_are_marked_in_the_schema() -> None:
    props = RegistrationResult.model_json_schema()["$defs"]["VertebraResult"]["properties"]
    assert props["pa_bending_deg"].get("deprecated") is True
    assert props["lateral_bending_deg"].get("deprecated") is True
    assert "deprecated" not in props["sagittal_bending_deg"]


def _full_payload() -> dict[str, Any]:
    payload = spine_payload()
    payload["pa"].update(
        landmark_sd_mm=0.8,
        pixel_spacing_calibration="detector",
        acquisition={"magnification": 1.15, "distance_source_to_detector_mm": 1800.0,
                     "distance_source_to_patient_mm": 1560.0, "central_ray": [100.0, 260.0]},
    )  # fmt: skip
    payload["boundary"]["T1"].update(position_sd_mm=2.0, directors_sd_deg=3.0)
    return payload


def test_new_payload_fields_are_accepted() -> None:
    model = validate_payload(_full_payload())
    assert model.pa.landmark_sd_mm == 0.8
    assert model.pa.acquisition is not None and model.pa.acquisition.perspective
    assert model.boundary is not None and model.boundary.T1.soft and not model.boundary.L5.soft


@pytest.mark.parametrize(
    ("edit", "loc"),
    [
        (lambda p: p["pa"]["acquisition"].update(distance_source_to_patient_mm=1900.0), "pa.acquisition"),
        (lambda p: p["pa"].update(landmark_sd_mm=0.0), "pa.landmark_sd_mm"),
        (lambda p: p["boundary"]["T1"].pop("directors_sd_deg"), "boundary.T1"),
        (lambda p: p["pa"].update(pixel_spacing_calibration="guessed"), "pa.pixel_spacing_calibration"),
    ],
)
def test_bad_new_fields_are_named(edit: Any, loc: str) -> None:
    payload = _full_payload()
    edit(payload)
    with pytest.raises(InvalidInput) as info:
        validate_payload(payload)
    assert loc in [e.path for e in info.value.errors]


def test_old_payloads_stay_valid() -> None:
    assert JobPayload.model_validate(spine_payload()).pa.acquisition is None


def test_one_pixel_to_mm_conversion_for_head_up_images() -> None:
    """The figure and the fit read a head-up image's corners the same way: the
    superior endplate is the bottom pair when rows run toward the head, in px × pixel spacing."""
    from spine_engine.clinical import landmark_arrays
    from spine_engine.figures import _detector_mm

    payload = spine_payload()
    payload["pa"].update(units="px", pixel_spacing=[0.2, 0.1], patient_orientation=["L", "H"])
    for lm in payload["pa"]["landmarks"]:
        col, row = lm.pop("point")
        lm["corners"] = [[col - 10, 3000 - row - 5], [col + 10, 3000 - row - 5],
                         [col - 10, 3000 - row + 5], [col + 10, 3000 - row + 5]]  # fmt: skip
    model = validate_payload(payload)
    fitted = landmark_arrays(model.pa).points
    np.testing.assert_array_equal(_detector_mm(model.pa), fitted)
    first = model.pa.landmarks[0].corners
    assert first is not None
    # rows toward the head: the image's bottom pair (larger rows) is the cranial, superior endplate;
    # [row, column] spacing (0.2, 0.1) mm
    expected = (0.5 * (first[2][0] + first[3][0]) * 0.1, 0.5 * (first[2][1] + first[3][1]) * 0.2)
    assert tuple(fitted[0]) == pytest.approx(expected)
