"""``acquisition.image_size``: with SID and SOD and no central ray the ray defaults to the image's
centre, and ``fit.assumed`` says so."""

from __future__ import annotations

import copy
from typing import Any

import numpy as np
import pytest

from benches import clinic, clinic_films
from spine_engine import register
from spine_engine.errors import InvalidInput
from spine_engine.validation import validate_payload

NO_PEDICLES = ("population_axial_rotation", None)
"""``fit.assumed`` of a payload without pedicles: the axial rotations are the population's."""


def _case_c(units: str) -> dict[str, Any]:
    """The clinic bench's case (c) (perspective PA + lateral, SID, SOD and central ray given) of one
    synthetic spine, in mm or in px at 0.2 mm per px."""
    series = clinic_films.simulate_series(clinic.synthetic_truths(1, seed=5)[0], noise_mm=1.0, seed=0)
    payload = clinic_films.build_payload(series, clinic_films.CASES["c"]).model_dump(mode="json", exclude_none=True)
    if units == "px":
        for name in ("pa", "lateral"):
            view = payload[name]
            view.update(units="px", pixel_spacing=[0.2, 0.2])
            for lm in view["landmarks"]:
                lm["point"] = [x / 0.2 for x in lm["point"]]
            view["acquisition"]["central_ray"] = [x / 0.2 for x in view["acquisition"]["central_ray"]]
    return payload


def _positions(result: dict[str, Any]) -> np.ndarray:
    return np.array([v["position"] for v in result["vertebrae"]])


@pytest.mark.parametrize("units", ["mm", "px"])
def test_the_central_ray_defaults_to_the_image_centre(units: str) -> None:
    """An image whose centre is where the given central ray met it: the same reconstruction without
    the central ray, and fit.assumed names the default on both views."""
    given = _case_c(units)
    centred = copy.deepcopy(given)
    for name in ("pa", "lateral"):
        acquisition = centred[name]["acquisition"]
        column, row = acquisition.pop("central_ray")
        acquisition["image_size"] = [2.0 * column, 2.0 * row]
    a, b = register(given), register(centred)
    np.testing.assert_allclose(_positions(b), _positions(a), rtol=0, atol=1e-9)
    assert b["measures"]["thoracic_kyphosis_t4_t12_deg"] == pytest.approx(a["measures"]["thoracic_kyphosis_t4_t12_deg"])
    assert [x["name"] for x in a["fit"]["assumed"]] == ["population_axial_rotation"]  # no pedicles
    assert [(x["name"], x["view"]) for x in b["fit"]["assumed"]] == [
        ("central_ray_at_image_centre", "pa"), ("central_ray_at_image_centre", "lateral"), NO_PEDICLES,
    ]
    assert units in b["fit"]["assumed"][0]["reason"]


def test_a_given_central_ray_wins_and_weak_perspective_ignores_the_size() -> None:
    """image_size changes nothing when the central ray is given, nor without SID and SOD."""
    given = _case_c("mm")
    sized = copy.deepcopy(given)
    sized["pa"]["acquisition"]["image_size"] = [350.0, 900.0]
    a, b = register(given), register(sized)
    np.testing.assert_array_equal(_positions(b), _positions(a))
    assert b["fit"]["assumed"] == a["fit"]["assumed"]
    for payload in (given, sized):
        for name in ("pa", "lateral"):
            payload[name]["acquisition"] = {"image_size": [350.0, 900.0]} if payload is sized else {}
    a, b = register(given), register(sized)
    np.testing.assert_array_equal(_positions(b), _positions(a))
    assert b["fit"]["assumed"] == a["fit"]["assumed"]
    assert [(x["name"], x["view"]) for x in b["fit"]["assumed"]] == [
        ("magnification_prior", "pa"), ("projection_unstated", "pa"), ("projection_unstated", "lateral"), NO_PEDICLES,
    ]


def test_priors_that_decide_are_named() -> None:
    """SID and SOD alone (no central ray, no image size): the ray's prior is named per view; one PA
    film alone: the standing orientation and the population's sagittal shape are named; without
    pedicles, the population's axial rotation."""
    bare = _case_c("mm")
    for name in ("pa", "lateral"):
        bare[name]["acquisition"].pop("central_ray")
    names = [(x["name"], x["view"]) for x in register(bare)["fit"]["assumed"]]
    assert names == [("central_ray_near_landmarks", "pa"), ("central_ray_near_landmarks", "lateral"), NO_PEDICLES]
    del bare["lateral"]
    names = [x["name"] for x in register(bare)["fit"]["assumed"]]
    assert names == [
        "central_ray_near_landmarks", "standing_orientation", "population_sagittal_shape", "population_axial_rotation",
    ]


@pytest.mark.parametrize("bad", [0.0, -10.0])
def test_image_size_must_be_positive(bad: float) -> None:
    payload = _case_c("mm")
    payload["pa"]["acquisition"]["image_size"] = [bad, 900.0]
    with pytest.raises(InvalidInput) as info:
        validate_payload(payload)
    assert [e.path for e in info.value.errors] == ["pa.acquisition.image_size[0]"]
