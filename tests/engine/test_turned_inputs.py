"""Inputs that would turn vertebrae past what a film can show: pedicles swapped, corners turned by
90° or more, corners that contradict the points, an exact boundary's own axial rotation, and
point-source geometries with no room for the spine. Each is refused naming its field, or kept
as the payload states it; none reports a Cobb angle past 180° or intervals of micrometres."""

import json
import math
from typing import Any

import numpy as np
import pytest

from benches.truth import payload_from_truth
from spine_engine.errors import InvalidInput
from spine_engine.frames import axial_rotation_deg
from spine_engine.measures import compute_measures, frontal_tilt_deg
from spine_engine.models import FULL_SPINE_SID_MM, SPINE_TO_DETECTOR_MM, Acquisition
from spine_engine.reconstruction import END_ON_PROJECTION, register
from spine_engine.rotations import exp_so3
from spine_engine.synthetic import generate_spine
from spine_engine.validation import validate_payload

ALL = list(range(17))


@pytest.fixture(scope="module")
def spine() -> Any:
    return generate_spine(21, "double")


def _refusals(payload: dict[str, Any]) -> list[tuple[str, str, str]]:
    with pytest.raises(InvalidInput) as caught:
        register(payload)
    return [(e.path, e.type, e.msg) for e in caught.value.errors]


def _turned(quad: list[list[float]], degrees: float) -> list[list[float]]:
    """The quadrilateral turned by ``degrees`` in the image about its top edge's midpoint."""
    q = np.asarray(quad, dtype=float)
    pivot = 0.5 * (q[0] + q[1])
    a = math.radians(degrees)
    turn = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    return ((q - pivot) @ turn.T + pivot).tolist()


def test_swapped_or_coincident_pedicles_are_refused_naming_them(spine: Any) -> None:
    payload = payload_from_truth(spine.positions, spine.rotations, ALL, ALL, pedicle_levels=[4, 8])
    register(json.loads(json.dumps(payload)))  # in order: reconstructed
    swapped = json.loads(json.dumps(payload))
    left, right = swapped["pa"]["landmarks"][4]["pedicles"]
    swapped["pa"]["landmarks"][4]["pedicles"] = [right, left]
    swapped["pa"]["landmarks"][8]["pedicles"][1] = list(swapped["pa"]["landmarks"][8]["pedicles"][0])
    refused = _refusals(swapped)
    assert [(path, kind) for path, kind, _ in refused] == [
        ("pa.landmarks[4].pedicles", "pedicles_not_in_order"),
        ("pa.landmarks[8].pedicles", "pedicles_not_in_order"),
    ]
    assert "T5" in refused[0][2] and "image-right first" in refused[0][2]
    assert "T9" in refused[1][2] and "at one column" in refused[1][2]


@pytest.mark.parametrize("degrees", [95.0, 135.0, 180.0, -100.0])
def test_corners_turned_by_90_degrees_or_more_are_refused(spine: Any, degrees: float) -> None:
    payload = payload_from_truth(spine.positions, spine.rotations, ALL, ALL, corner_levels=[6])
    validate_payload(json.loads(json.dumps(payload)))
    payload["pa"]["landmarks"][6]["corners"] = _turned(payload["pa"]["landmarks"][6]["corners"], degrees)
    with pytest.raises(InvalidInput) as caught:
        validate_payload(payload)
    [(path, kind)] = [(e.path, e.type) for e in caught.value.errors]
    assert (path, kind) == ("pa.landmarks[6].corners", "corners_not_upright")


def test_a_corner_turned_less_than_90_degrees_is_a_tilted_vertebra(spine: Any) -> None:
    payload = payload_from_truth(spine.positions, spine.rotations, ALL, ALL, corner_levels=[6])
    payload["pa"]["landmarks"][6]["corners"] = _turned(payload["pa"]["landmarks"][6]["corners"], 80.0)
    validate_payload(payload)


def test_a_vertebra_turned_past_90_degrees_reads_the_tilt_of_its_line() -> None:
    """A Cobb angle is the angle between two endplates' lines, below 180°: a vertebra whose d1
    points to the patient's right (turned 180° about its axis) has the same tilt as the unturned
    one, not θ ± 180°."""
    tilts = np.radians([0, 5, 10, 20, 30, 25, 15, 5, 0, -5, -15, -25, -30, -20, -10, -5, 0])
    R = np.stack([exp_so3(np.array([0.0, -t, 0.0])) @ np.diag([1.0, -1.0, -1.0]) for t in tilts])
    flipped = R.copy()
    flipped[4] = flipped[4] @ np.diag([-1.0, -1.0, 1.0])  # turned 180° about d3
    assert frontal_tilt_deg(flipped)[4] == pytest.approx(frontal_tilt_deg(R)[4])
    p = np.stack([np.zeros(17), np.zeros(17), -25.0 * np.arange(17)], axis=1)
    largest = compute_measures(p, flipped).largest_cobb
    assert largest is not None and largest.angle_deg == pytest.approx(60.0) and largest.angle_deg < 180.0


def test_corners_against_the_points_curve_are_refused_not_reported_with_micrometre_intervals() -> None:
    """Corners tilted 45° against the curve the points draw: the fit met them by turning vertebrae
    end-on to the film (d1 projected 1e-9 long) and reported every SD about 1e-6; they are refused,
    naming the levels. Corners drawn from the spine's own tilts are reconstructed."""
    s = generate_spine(1, "double")
    payload = payload_from_truth(s.positions, s.rotations, ALL, ALL, corner_levels=ALL, boundary=False,
                                 noise_mm=1.0, rng=np.random.default_rng(0))  # fmt: skip
    result = register(json.loads(json.dumps(payload)))
    d1 = np.array([np.asarray(v["directors"])[0] for v in result["vertebrae"]])
    assert np.hypot(d1[:, 0], d1[:, 2]).min() > END_ON_PROJECTION
    tilts = frontal_tilt_deg(s.rotations)
    for k, lm in enumerate(payload["pa"]["landmarks"]):
        lm["corners"] = _turned(lm["corners"], 45.0 + tilts[k])  # each quad's edges now at 45° in the image
    [(path, kind, msg)] = _refusals(payload)
    assert (path, kind) == ("pa.landmarks", "corners_contradicted")
    assert "end-on" in msg and "T9" in msg


def test_an_exact_boundary_keeps_its_own_axial_rotation(spine: Any) -> None:
    """T1 and L5 given exactly, turned 20° about their axes, no pedicles: the reported axial rotations
    of T1 and L5 are the payload's (the population's profile, 0 outside every curve, stands for the
    vertebrae in between)."""
    R = spine.rotations.copy()
    for k in (0, 16):
        R[k] = R[k] @ exp_so3(np.array([0.0, 0.0, math.radians(20.0)]))
    payload = payload_from_truth(spine.positions, R, ALL)
    given = axial_rotation_deg(R)[[0, 16]]
    result = register(payload)
    reported = [result["vertebrae"][k]["axial_rotation_deg"] for k in (0, 16)]
    assert reported == pytest.approx(given.tolist(), abs=1e-6)
    assert "population_axial_rotation" in [a["name"] for a in result["fit"]["assumed"]]
    assert "axial_rotation" in result["fit"]["unreliable"]  # the vertebrae between: every consumer marks them


@pytest.mark.parametrize(
    ("acquisition", "field"),
    [
        ({"distance_source_to_detector_mm": 150.0}, "pa.acquisition.distance_source_to_detector_mm"),
        ({"distance_source_to_detector_mm": 200.5}, "pa.acquisition.distance_source_to_detector_mm"),
        ({"magnification": 5.0}, "pa.acquisition.magnification"),
        ({"distance_source_to_detector_mm": 1800.0, "distance_source_to_patient_mm": 100.0}, "pa.acquisition"),
        ({"distance_source_to_detector_mm": 1.0, "distance_source_to_patient_mm": 0.5}, "pa.acquisition"),
        ({"distance_source_to_detector_mm": 1000.0, "distance_source_to_patient_mm": 290.0}, "pa.acquisition"),
    ],
)
def test_a_point_source_geometry_with_no_room_for_the_spine_is_refused(
    spine: Any, acquisition: dict[str, float], field: str
) -> None:
    """An SID of 150 mm with the SOD assumed 200 mm before the detector put the spine behind the source
    (the fit broke down: "scale must be positive"); 200.5 mm magnified it 401 times; SID 1 mm and SOD
    0.5 mm read a kyphosis of −359.7°. The source lies at least 300 mm from the spine
    (``validation.SOURCE_TO_SPINE_MIN_MM``)."""
    payload = payload_from_truth(spine.positions, spine.rotations, ALL, boundary=False)
    payload["pa"]["acquisition"] = {"projection_model": "perspective", **acquisition}
    with pytest.raises(InvalidInput) as caught:
        validate_payload(payload)
    assert [(e.path, e.type) for e in caught.value.errors] == [(field, "implausible_geometry")]


def test_a_missing_distance_is_taken_200_mm_from_the_given_one() -> None:
    def distances(**given: float) -> tuple[float, float] | None:
        return Acquisition.model_validate({"projection_model": "perspective", **given}).point_source_distances()

    assert distances() == (FULL_SPINE_SID_MM, FULL_SPINE_SID_MM - SPINE_TO_DETECTOR_MM)
    assert distances(distance_source_to_patient_mm=1900.0) == (1900.0 + SPINE_TO_DETECTOR_MM, 1900.0)
    assert distances(distance_source_to_detector_mm=1000.0) == (1000.0, 1000.0 - SPINE_TO_DETECTOR_MM)
    assert distances(distance_source_to_patient_mm=1500.0, magnification=1.2) == pytest.approx((1800.0, 1500.0))
    assert distances(distance_source_to_detector_mm=1800.0, magnification=1.2) == pytest.approx((1800.0, 1500.0))


def test_the_central_ray_is_judged_in_millimetres_only_once_the_spacing_is_known(spine: Any) -> None:
    """A by-reference view is checked at admission with a stand-in spacing of 1 mm per pixel
    (``services.api.admission``): a central ray 2,500 px from the landmarks, 250 mm on a film of
    0.1 mm pixels, is judged when the header gives the spacing, not refused as 2,500 mm."""
    payload = payload_from_truth(spine.positions, spine.rotations, ALL, boundary=False)
    view = payload["pa"]
    view["units"], view["pixel_spacing"] = "px", [1.0, 1.0]
    top = min(lm["point"][1] for lm in view["landmarks"])
    view["acquisition"] = {"distance_source_to_detector_mm": 1800.0, "distance_source_to_patient_mm": 1600.0,
                           "central_ray": [view["landmarks"][0]["point"][0], top - 2500.0]}  # fmt: skip
    validate_payload(payload, unscaled_views=("pa",))
    with pytest.raises(InvalidInput) as caught:
        validate_payload(payload)
    assert [(e.path, e.type) for e in caught.value.errors] == [("pa.acquisition.central_ray", "implausible_geometry")]
