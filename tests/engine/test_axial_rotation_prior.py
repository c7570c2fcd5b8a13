"""Axial rotation that no pedicle observed: the population's mean given the frontal curves
(``reconstruction.population_axial_rotation_deg``), reported with the population's SD and named in
``fit.assumed``."""

from __future__ import annotations

import numpy as np
import pytest

from benches.truth import payload_from_truth
from spine_engine.frames import axial_rotation_deg
from spine_engine.levels import LEVEL_INDEX
from spine_engine.models import CobbCurve, Measures, RegistrationResult
from spine_engine.reconstruction import (
    APICAL_ROTATION_PER_COBB,
    population_axial_rotation_deg,
    register,
)
from spine_engine.synthetic import generate_spines

ALL = list(range(17))


def _curve(upper: str, apex: str, lower: str, angle: float, convexity: str) -> CobbCurve:
    return CobbCurve.model_validate({
        "upper": upper, "lower": lower, "apex": apex, "angle_deg": angle, "major": False, "convexity": convexity,
        "apex_axial_rotation_deg": 0.0, "plane_of_max_curvature_deg": 0.0, "max_curvature_deg": angle,
    })


def test_the_apex_turns_toward_the_convexity_by_the_populations_share_of_the_cobb_angle() -> None:
    """A left thoracic curve T5–T11 (apex T8, 40°) and a right lumbar one T11–L4 (apex L2, 30°):
    ψ > 0 toward patient left (``frames.axial_rotation_deg``), k·C at the apexes, linear to 0 at the
    end vertebrae, 0 outside the curves."""
    spine = generate_spines(1, seed=1)[0]
    measures = RegistrationResult.model_validate(register(payload_from_truth(spine.positions, spine.rotations, ALL)))
    curves = [_curve("T5", "T8", "T11", 40.0, "left"), _curve("T11", "L2", "L4", 30.0, "right")]
    psi = population_axial_rotation_deg(Measures.model_validate(
        {**measures.measures.model_dump(), "cobb": [c.model_dump() for c in curves]}
    ))
    thoracic = APICAL_ROTATION_PER_COBB["thoracic"] * 40.0
    lumbar = APICAL_ROTATION_PER_COBB["lumbar"] * 30.0
    assert psi[LEVEL_INDEX["T8"]] == pytest.approx(thoracic)
    assert psi[LEVEL_INDEX["T6"]] == pytest.approx(thoracic / 3.0)
    assert psi[LEVEL_INDEX["T10"]] == pytest.approx(thoracic / 3.0)
    assert psi[LEVEL_INDEX["L2"]] == pytest.approx(-lumbar)
    assert psi[LEVEL_INDEX["L3"]] == pytest.approx(-lumbar / 2.0)
    for level in ("T1", "T4", "T5", "T11", "L4", "L5"):
        assert psi[LEVEL_INDEX[level]] == 0.0


def test_without_pedicles_the_result_reports_the_populations_rotation() -> None:
    """Vertebrae and curve apexes carry ``population_axial_rotation_deg`` of the result's own curves,
    with SDs of at least 0.30·C at the apex, and fit.assumed names it; with pedicles the directors'
    rotation is reported and nothing is assumed of it."""
    spine = generate_spines(1, seed=3)[0]
    result = RegistrationResult.model_validate(register(payload_from_truth(spine.positions, spine.rotations, ALL)))
    assert result.measures.cobb, "the synthetic spine has a curve"
    psi = np.array([v.axial_rotation_deg for v in result.vertebrae])
    np.testing.assert_allclose(psi, population_axial_rotation_deg(result.measures), atol=1e-12)
    for c in result.measures.cobb:
        apex = result.vertebrae[LEVEL_INDEX[c.apex]]
        assert c.apex_axial_rotation_deg == apex.axial_rotation_deg
        assert apex.axial_rotation_sd_deg is not None and apex.axial_rotation_sd_deg >= 0.30 * c.angle_deg - 1e-9
    assert "population_axial_rotation" in [a.name for a in result.fit.assumed]
    observed = RegistrationResult.model_validate(
        register(payload_from_truth(spine.positions, spine.rotations, ALL, pedicle_levels=ALL))
    )
    directors = np.array([np.asarray(v.directors).T for v in observed.vertebrae])
    np.testing.assert_allclose([v.axial_rotation_deg for v in observed.vertebrae], axial_rotation_deg(directors))
    assert "population_axial_rotation" not in [a.name for a in observed.fit.assumed]


def test_without_pedicles_the_answer_is_no_worse_than_no_rotation() -> None:
    """Eight synthetic spines, midpoints only: the mean |ψ − truth| is below that of answering 0 (the
    trivial answer; the rod's own directors were above it, turned toward the concavity). The synthetic
    spines turn toward the convexity, as the cited population does, so this checks the direction and
    the profile, not the population's ratio."""
    errors, trivial = [], []
    for s in generate_spines(8, seed=21):
        truth = axial_rotation_deg(s.rotations)
        result = register(payload_from_truth(s.positions, s.rotations, ALL))
        psi = np.array([v["axial_rotation_deg"] for v in result["vertebrae"]])
        errors.append(np.mean(np.abs(psi - truth)))
        trivial.append(np.mean(np.abs(truth)))
    assert np.mean(errors) < np.mean(trivial)
