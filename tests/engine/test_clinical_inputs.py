"""Clinical inputs end to end: corners, pedicles, mixed payloads, no boundary, and their measures.

Corners and pedicles are built from synthetic spines (a box around each vertebra, pedicle centres
at the engine's offsets), never from the AASCE data.
"""

import json
from typing import Any

import numpy as np
import pytest

from benches.truth import payload_from_truth
from spine_engine.anatomy import load_profile, population_prior
from spine_engine.errors import InvalidInput
from spine_engine.fit import RegistrationProblem
from spine_engine.frames import axial_rotation_deg
from spine_engine.measures import aasce_major_angle, major_first_curves
from spine_engine.models import RegistrationResult
from spine_engine.reconstruction import (
    UNRELIABLE_SD_FRACTION,
    patient_rest_model,
    prepare_inputs,
    register,
    rod_parameters,
)
from spine_engine.rotations import exp_so3
from spine_engine.synthetic import generate_spine, generate_spines
from spine_engine.tilt_prior import load_tilt_prior, predict_tilts_deg
from spine_engine.validation import validate_payload

ALL = list(range(17))
RNG = np.random.default_rng(3)


@pytest.fixture(scope="module")
def spine() -> Any:
    return generate_spine(21, "double")


def _aasce_major_from_corners(payload: dict[str, Any]) -> float:
    """The AASCE 2019 script's major angle, written out independently of the engine: for each
    vertebra the vector from the midpoint of its left edge (TL, BL) to that of its right edge
    (TR, BR), the largest arccos of the clipped cosine between any two."""
    corners = np.array([lm["corners"] for lm in payload["pa"]["landmarks"]], dtype=float)
    v = 0.5 * (corners[:, 1] + corners[:, 3]) - 0.5 * (corners[:, 0] + corners[:, 2])
    n = np.linalg.norm(v, axis=1)
    cosine = np.clip((v @ v.T) / np.outer(n, n), 0.0, 1.0)
    return float(np.degrees(np.arccos(cosine).max()))


def _major(result: dict[str, Any]) -> dict[str, Any]:
    return next(c for c in result["measures"]["cobb"] if c["major"])


N_SEGMENTS = 16


def test_corner_and_pedicle_rows_of_a_payload_have_exact_jacobians(spine: Any) -> None:
    payload = payload_from_truth(
        spine.positions, spine.rotations, ALL, corner_levels=ALL[::2], pedicle_levels=ALL[1::3], noise_mm=0.4, rng=RNG
    )
    profile = load_profile()
    inputs = prepare_inputs(validate_payload(payload), profile)
    view = inputs.views[0]
    assert view.n_tilts == 9 and view.n_offsets == 9 + 2 * 6  # inferior midpoints + pedicle pairs
    prob = RegistrationProblem(rod_parameters(patient_rest_model(profile, inputs)), inputs.views,
                               None, None, pose_priors=inputs.pose_priors)  # fmt: skip
    r = spine.positions + RNG.normal(0, 1.5, spine.positions.shape)
    R = spine.rotations @ exp_so3(RNG.normal(0, 0.05, (17, 3)))
    J = prob.jacobian(r, R)
    assert prob.n_border == 3  # no boundary: the PA's scale and translation are estimated (ψ = 0 by convention)
    start = 6 * (N_SEGMENTS) + prob.n_fit
    stop = start + view.n_offsets + view.n_tilts
    state = prob.initial_state(r, R)
    h = 1e-6
    J_fd = np.empty((stop - start, J.shape[1]))
    for k in range(J.shape[1]):
        d = np.zeros(J.shape[1])
        d[k] = h
        plus = prob.evaluate(prob.step(state, d))[0]
        minus = prob.evaluate(prob.step(state, -d))[0]
        J_fd[:, k] = (plus[start:stop] - minus[start:stop]) / (2 * h)
    assert np.linalg.norm(J[start:stop] - J_fd) < 1e-7 * np.linalg.norm(J[start:stop])


def test_corners_give_the_aasce_major_angle_and_the_endplate_variant(spine: Any) -> None:
    payload = payload_from_truth(spine.positions, spine.rotations, ALL, corner_levels=ALL)
    result = register(payload)
    RegistrationResult.model_validate(result)
    expected = _aasce_major_from_corners(payload)
    assert 10.0 < expected < 90.0
    major = _major(result)
    assert major["angle_deg"] == pytest.approx(expected, abs=1e-9)
    assert result["measures"]["aasce2019"]["angle_deg"] == pytest.approx(expected, abs=1e-9)
    assert (result["measures"]["aasce2019"]["upper"], result["measures"]["aasce2019"]["lower"]) == (
        major["upper"],
        major["lower"],
    )
    assert major["tilt_source"] == "corners"
    assert all(v["frontal_tilt_source"] == "corners" for v in result["vertebrae"])
    # the boxes are rectangles: each endplate is parallel to the corner line, so both variants agree
    for curve in result["measures"]["cobb"]:
        assert curve["endplate_angle_deg"] == pytest.approx(curve["angle_deg"], abs=1e-6)
    # the rod follows the corner tilts
    assert max(abs(t["residual_deg"]) for t in result["fit"]["tilt_residuals"]) < 0.5


def test_endplate_variant_uses_the_drawn_endplates(spine: Any) -> None:
    payload = payload_from_truth(spine.positions, spine.rotations, ALL, corner_levels=ALL)
    major = _major(register(payload))
    landmarks = {lm["level"]: lm for lm in payload["pa"]["landmarks"]}
    # turn the endplates of the upper end vertebra, not its edge midpoints (rows grow toward the feet)
    for corner, shift in zip(landmarks[major["upper"]]["corners"], (2.0, -2.0, -2.0, 2.0), strict=True):
        corner[1] += shift
    changed = _major(register(payload))
    assert (changed["upper"], changed["lower"]) == (major["upper"], major["lower"])
    assert changed["angle_deg"] == pytest.approx(major["angle_deg"], abs=1e-9)
    upper = np.array(landmarks[changed["upper"]]["corners"])
    lower = np.array(landmarks[changed["lower"]]["corners"])
    superior, inferior = upper[1] - upper[0], lower[3] - lower[2]  # top-left → top-right, bottom-left → bottom-right
    tilt = np.degrees(np.arctan2(-np.array([superior[1], inferior[1]]), [superior[0], inferior[0]]))
    assert changed["endplate_angle_deg"] == pytest.approx(abs(tilt[0] - tilt[1]), abs=1e-9)
    assert abs(changed["endplate_angle_deg"] - changed["angle_deg"]) > 1.0


def test_mixed_point_and_corner_payload(spine: Any) -> None:
    corner_levels = [0, 4, 5, 9, 12, 16]
    payload = payload_from_truth(spine.positions, spine.rotations, ALL, corner_levels=corner_levels)
    kinds = [("corners" in lm, "point" in lm) for lm in payload["pa"]["landmarks"]]
    assert sum(c for c, _ in kinds) == 6 and all(c != p for c, p in kinds)
    result = register(payload)
    assert result["fit"]["converged"]
    sources = [v["frontal_tilt_source"] for v in result["vertebrae"]]
    assert [i for i, s in enumerate(sources) if s == "corners"] == corner_levels
    assert {t["level"] for t in result["fit"]["tilt_residuals"]} == {f"{lv}" for lv in
            [result["vertebrae"][i]["level"] for i in corner_levels]}  # fmt: skip
    assert len(result["fit"]["residuals"]) == 17
    assert result["measures"]["aasce2019"] is None  # not every level has corners
    # a point-only vertebra reports the model's tilt
    both = register(payload_from_truth(spine.positions, spine.rotations, ALL))
    assert both["vertebrae"][2]["frontal_tilt_source"] == "model"


def test_corners_in_pixels_with_spacing_equal_millimetres(spine: Any) -> None:
    mm = payload_from_truth(spine.positions, spine.rotations, ALL, corner_levels=ALL, pedicle_levels=ALL)
    px = json.loads(json.dumps(mm))
    px["pa"]["units"] = "px"
    px["pa"]["pixel_spacing"] = [0.2, 0.25]  # row, column
    for lm in px["pa"]["landmarks"]:
        for key in ("corners", "pedicles"):
            lm[key] = [[c / 0.25, r / 0.2] for c, r in lm[key]]
    a, b = register(mm), register(px)
    np.testing.assert_allclose([v["position"] for v in a["vertebrae"]], [v["position"] for v in b["vertebrae"]],
                               atol=1e-6)  # fmt: skip
    assert _major(a)["angle_deg"] == pytest.approx(_major(b)["angle_deg"], abs=1e-9)


def _landmark_errors(payload: dict[str, Any]) -> list[tuple[str, str]]:
    with pytest.raises(InvalidInput) as info:
        validate_payload(payload)
    return [(e.path, e.type) for e in info.value.errors]


def test_landmark_with_both_or_neither_point_and_corners_names_the_field(spine: Any) -> None:
    payload = payload_from_truth(spine.positions, spine.rotations, ALL, corner_levels=[3])
    both = json.loads(json.dumps(payload))
    both["pa"]["landmarks"][3]["point"] = [1.0, 2.0]
    assert _landmark_errors(both) == [("pa.landmarks[3].corners", "landmark_point_and_corners")]
    neither = json.loads(json.dumps(payload))
    del neither["pa"]["landmarks"][3]["corners"]
    assert _landmark_errors(neither) == [("pa.landmarks[3].point", "landmark_point_missing")]
    short = json.loads(json.dumps(payload))
    short["pa"]["landmarks"][3]["corners"] = short["pa"]["landmarks"][3]["corners"][:3]
    assert _landmark_errors(short)[0][0].startswith("pa.landmarks[3].corners")


def test_pedicles_and_corners_need_suitable_views(spine: Any) -> None:
    payload = payload_from_truth(spine.positions, spine.rotations, ALL, ALL, corner_levels=[2], pedicle_levels=[2])
    lateral = json.loads(json.dumps(payload))
    lateral["lateral"]["landmarks"][5]["pedicles"] = [[1.0, 2.0], [3.0, 4.0]]
    assert _landmark_errors(lateral) == [("lateral.landmarks[5].pedicles", "pedicles_not_supported")]
    turned = json.loads(json.dumps(payload))
    turned["pa"]["patient_orientation"] = ["F", "L"]  # a PA image shown on its side
    assert ("pa.landmarks[2].corners", "corners_need_upright_view") in _landmark_errors(turned)
    assert ("pa.landmarks[2].pedicles", "pedicles_not_supported") in _landmark_errors(turned)


def test_without_boundary_the_fit_converges_and_flags_what_the_model_supplies(spine: Any) -> None:
    base = payload_from_truth(spine.positions, spine.rotations, ALL, boundary=False)
    result = register(base)
    RegistrationResult.model_validate(result)
    fit = result["fit"]
    assert fit["converged"] and fit["boundary"] == "estimated" and fit["pa"]["estimated"]
    assert {"scale", "depth", "kyphosis", "lordosis", "axial_rotation", "twist"} <= set(fit["unreliable"])
    assert fit["tilt_prior"] and {t["source"] for t in fit["tilt_residuals"]} == {"prior"}
    assert fit["mean_registration_error_mm"] < 0.5
    assert _major(result)["angle_deg"] == pytest.approx(spine.cobb_target_deg[0], abs=12.0)
    # each input removes what it makes observable
    known = register(payload_from_truth(spine.positions, spine.rotations, ALL, boundary=False, projection=True))
    assert "scale" not in known["fit"]["unreliable"] and not known["fit"]["pa"]["estimated"]
    lateral = register(payload_from_truth(spine.positions, spine.rotations, ALL, ALL, boundary=False))
    assert lateral["fit"]["converged"] and "depth" not in lateral["fit"]["unreliable"]
    pedicles = register(payload_from_truth(spine.positions, spine.rotations, ALL, boundary=False, pedicle_levels=ALL))
    assert pedicles["fit"]["converged"] and "axial_rotation" not in pedicles["fit"]["unreliable"]
    # with the boundary given a sagittal measure is flagged only when its SD is a large part of the
    # population's (reconstruction.UNRELIABLE_SD_FRACTION), and the prior is off unless asked for
    given = register(payload_from_truth(spine.positions, spine.rotations, ALL))
    assert given["fit"]["boundary"] == "given" and not given["fit"]["tilt_prior"]
    population = population_prior(load_profile()).measure_sd_deg  # type: ignore[union-attr]
    for name, sd_key, pop_key in (
        ("kyphosis", "thoracic_kyphosis_t4_t12_sd_deg", "kyphosis_t4_t12_deg"),
        ("lordosis", "lumbar_lordosis_l1_l5_sd_deg", "lordosis_l1_l5_deg"),
    ):
        wide = given["measures"][sd_key] > UNRELIABLE_SD_FRACTION * population[pop_key]
        assert (name in given["fit"]["unreliable"]) == wide
    # and, without pedicles, the axial rotations between T1 and L5 (the population's: fit.assumed)
    assert set(given["fit"]["unreliable"]) - {"kyphosis", "lordosis"} == {"axial_rotation"}
    asked = payload_from_truth(spine.positions, spine.rotations, ALL)
    asked["options"] = {"tilt_prior": True}
    assert register(asked)["fit"]["tilt_prior"]


def test_without_boundary_and_with_a_known_projection_the_in_plane_shape_is_the_truth(spine: Any) -> None:
    payload = payload_from_truth(spine.positions, spine.rotations, ALL, ALL, boundary=False, projection=True,
                                 landmark_sd_mm=0.01)  # fmt: skip
    result = register(payload)
    r = np.array([v["position"] for v in result["vertebrae"]])
    # x and z come from the PA view, y from the lateral view up to one offset (T1 placed at generic depth)
    np.testing.assert_allclose(r[:, [0, 2]], spine.positions[:, [0, 2]], atol=0.05)
    depth = r[:, 1] - spine.positions[:, 1]
    assert np.ptp(depth) < 0.5


def test_pedicles_reduce_axial_rotation_error_on_synthetic_spines() -> None:
    without, with_pedicles = [], []
    for s in generate_spines(4, seed=8):
        truth = axial_rotation_deg(s.rotations)[1:-1]
        for bucket, kw in ((without, {}), (with_pedicles, {"pedicle_levels": ALL})):
            result = register(payload_from_truth(s.positions, s.rotations, ALL, **kw))
            psi = np.array([v["axial_rotation_deg"] for v in result["vertebrae"]])[1:-1]
            bucket.append(np.mean(np.abs(psi - truth)))
        assert np.max(np.abs(truth)) > 3.0  # the synthetic spines are rotated
    assert np.mean(with_pedicles) < np.mean(without)  # without pedicles: the population's rotation
    assert np.mean(with_pedicles) < 1.0


def test_major_first_curves_and_the_aasce_major_angle() -> None:
    wiggle = [0, 20, 11, 30, 25, 5, 8]  # one long curve 0 → 30 with a 9° reversal inside, then 25° back
    assert major_first_curves(wiggle, 0.0) == [(0, 3, 30.0), (3, 5, 25.0), (5, 6, 3.0)]
    assert major_first_curves(wiggle, 10.0) == [(0, 3, 30.0), (3, 5, 25.0)]
    # a reversal of 10° (a curve by the SRS threshold) is a curve of its own: 0 → 20 → 10 → 30 is three
    # curves, not one of 30° (docs/measures.md, ``measures.CURVE_REVERSAL_DEG``); the AASCE script's
    # angle stays the most tilted pair's
    tilts = [0, 20, 10, 30, 25, 5, 8]
    assert major_first_curves(tilts, 0.0) == [(0, 1, 20.0), (1, 2, 10.0), (2, 3, 20.0), (3, 5, 25.0), (5, 6, 3.0)]
    assert major_first_curves(tilts, 10.0) == [(0, 1, 20.0), (1, 2, 10.0), (2, 3, 20.0), (3, 5, 25.0)]
    assert aasce_major_angle(tilts) == pytest.approx((30.0, 0, 3))
    assert major_first_curves([4.0] * 17) == []
    assert aasce_major_angle([-50.0, 60.0])[0] == pytest.approx(90.0)  # the script's clip


def test_lenke_inputs_are_model_estimates(spine: Any) -> None:
    lenke = register(payload_from_truth(spine.positions, spine.rotations, ALL))["measures"]["lenke"]
    assert lenke["model_estimate"] is True
    assert lenke["sagittal_thoracic_modifier"] in {"-", "N", "+"}
    majors = [c for c in lenke["curves"] if c["major"]]
    assert len(majors) <= 1 and all(c["structural_by_magnitude"] for c in majors)
    for c in lenke["curves"]:
        assert c["structural_by_magnitude"] == (c["major"] or c["angle_deg"] >= 25.0)
    assert "side_bending_cobb" in lenke["not_supported"]


def test_tilt_prior_turns_with_the_image_and_mirrors() -> None:
    prior = load_tilt_prior()
    np.testing.assert_allclose(prior.coefficients.sum(axis=1), 1.0, atol=1e-5)
    chords = RNG.normal(0, 8, 16)
    tilts = predict_tilts_deg(prior, chords)
    np.testing.assert_allclose(predict_tilts_deg(prior, chords + 7.0), tilts + 7.0, atol=1e-4)
    np.testing.assert_allclose(predict_tilts_deg(prior, -chords), -tilts, atol=1e-9)
    missing = chords.copy()
    missing[8] = np.nan
    assert np.isnan(predict_tilts_deg(prior, missing)[8]) and np.isfinite(predict_tilts_deg(prior, missing)[0])
    assert "training" in json.dumps(prior.provenance)
