"""Regressions found by a property-based probe of ``register()`` on valid payloads (films simulated from
VerSe dev and synthetic spines by ``benches.clinic_films``, then mutated as a clinic can: levels left
out, corners, pedicles, noise 0–5 mm, every allowed patient orientation, px or mm, geometry given or
not). Each payload is one such film cut down to what shows the defect, inline.

A film whose image axes are named otherwise (a film hung turned a quarter or flipped, which
``docs/engine.md`` accepts: "a PA film turned in its plane, as ["F", "L"] ... stays frontal", corners
need only rows toward H or F) is the same film: its result must be the same."""

import copy
from typing import Any

import pytest

from spine_engine.errors import InvalidInput
from spine_engine.reconstruction import register
from spine_engine.validation import MEAN_SEGMENT_MM

UPRIGHT_D = [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]
"""Directors (rows d1, d2, d3) of an upright vertebra facing the detector: d1 left, d2 anterior, d3 caudal."""


def _swap_axes(view: dict[str, Any]) -> dict[str, Any]:
    """The same film with its column and row directions exchanged (["A", "F"] ↔ ["F", "A"], ["L", "F"] ↔
    ["F", "L"]): every point (column, row) becomes (row, column) and the pixel spacing [row, column] swaps."""
    out = copy.deepcopy(view)
    out["patient_orientation"] = view["patient_orientation"][::-1]
    for lm in out["landmarks"]:
        lm["point"] = lm["point"][::-1]
    if "pixel_spacing" in out:
        out["pixel_spacing"] = out["pixel_spacing"][::-1]
    return out


def test_one_pa_landmark_with_given_projection_and_exact_boundary_is_fitted() -> None:
    """``validation.MIN_LEVELS_PROJECTION_GIVEN``: with the PA's projection and T1 and L5 given exactly, one PA
    landmark is enough (docs/engine.md, "Levels per view"). The fit must not break down: today
    ``reconstruction.projected_arc_scale`` divides the one landmark's polyline length (0) by the rest rod's
    (0), and ``register`` raises FitFailed "float division by zero" on every such payload."""
    payload = {
        "pa": {
            "landmarks": [{"level": "T9", "point": [150.0, 340.0]}],  # T9 at (0, 0, −200) under s = 1.1, T
            "projection": {"scale": 1.1, "translation": [150.0, 120.0]},
        },
        "boundary": {
            "T1": {"position": [0.0, 0.0, 0.0], "directors": UPRIGHT_D},
            "L5": {"position": [0.0, 0.0, -400.0], "directors": UPRIGHT_D},
        },
    }
    result = register(payload)
    assert result["fit"]["converged"]


def _head_up_film(head_up: bool) -> dict[str, Any]:
    """A straight PA film of 17 midpoints spaced by VerSe dev's mean segments × 1.125 (the PA's
    magnification), T2 given by its four corners (a body 18 mm high, 29 mm wide on the film). Rows toward
    the feet, or (``head_up``) the same film flipped top to bottom, rows toward the head: there the
    superior endplate is the bottom pair of corners (``observations.corner_geometry``,
    ``benches.truth.image_corners``)."""
    rows, row = [], 600.0
    for k in range(17):
        rows.append(row)
        if k < 16:
            row -= 1.125 * MEAN_SEGMENT_MM[k]
    levels = ["T1", "T2", "T3", "T4", "T5", "T6", "T7", "T8", "T9", "T10", "T11", "T12", "L1", "L2", "L3", "L4", "L5"]
    landmarks: list[dict[str, Any]] = []
    for k, level in enumerate(levels):
        landmarks.append({"level": level, "point": [100.0, rows[k] if head_up else 1200.0 - rows[k]]})
    top = landmarks[1].pop("point")[1]
    superior = [[85.5, top], [114.5, top]]
    inferior = [[85.5, top + (-18.0 if head_up else 18.0)], [114.5, top + (-18.0 if head_up else 18.0)]]
    landmarks[1]["corners"] = inferior + superior if head_up else superior + inferior  # top pair first
    return {"pa": {"patient_orientation": ["L", "H" if head_up else "F"], "landmarks": landmarks}}


def test_corners_on_a_film_with_rows_toward_the_head_are_read_by_their_superior_endplate() -> None:
    """The same straight film, rows toward the feet and flipped (rows toward the head), is one valid payload
    twice. Today the flipped one is refused (``implausible_distance``: "T2 and T3 are 0.23 times as far apart as
    the other landmarks' spacing predicts"): ``validation._top_midpoint`` takes the image's top pair of corners
    as the superior endplate whatever the rows' direction, while the fit takes the bottom pair on such a film.
    In the probe this refused 1.3 % of all valid payloads (2.8 % at 0–1 mm of noise): 379 of the 387 payloads
    refused ``implausible_distance`` had corners on rows toward H."""
    feet_down = register(_head_up_film(False))
    try:
        head_up = register(_head_up_film(True))
    except InvalidInput as exc:
        pytest.fail(f"a valid flipped film was refused: {exc}")
    # the same film: T2's node (its superior endplate midpoint) at the same place, within 0.1 mm
    for a, b in zip(feet_down["vertebrae"][1]["position"], head_up["vertebrae"][1]["position"], strict=True):
        assert abs(a - b) < 0.1


# A point-source lateral hung turned a quarter (columns toward the feet) and its PA: cut from a synthetic
# spine's films (`benches.clinic_films`, case (d), no noise) to the landmarks that still show the defect.
TURNED_LATERAL: dict[str, Any] = {
    "pa": {"patient_orientation": ["L", "F"], "units": "mm", "landmarks": [
        {"level": "T2", "point": [181.74, 322.08]}, {"level": "T6", "point": [182.67, 401.43]},
        {"level": "L4", "point": [200.7, 690.67]}, {"level": "L5", "point": [212.07, 727.18]}]},
    "lateral": {"patient_orientation": ["F", "A"], "units": "px", "pixel_spacing": [0.1, 0.12],
                "acquisition": {"projection_model": "perspective", "distance_source_to_patient_mm": 1506.7},
                "landmarks": [
                    {"level": "T2", "point": [-98.28, 5596.86]}, {"level": "T3", "point": [55.74, 5481.33]},
                    {"level": "T4", "point": [203.43, 5364.87]}, {"level": "T11", "point": [1710.17, 5116.04]},
                    {"level": "L4", "point": [3051.73, 5339.26]}, {"level": "L5", "point": [3336.6, 5227.49]}]},
    "options": {"tilt_prior": False},
}


def test_a_lateral_film_turned_a_quarter_reads_as_the_same_film_upright() -> None:
    """The lateral named ["F", "A"] (columns toward the feet) and the same film named ["A", "F"] must give one
    spine. Today the turned one folds into a loop: largest Cobb angle 349.9° (upright: 15.3°), vertebrae
    turned end over end. ``clinical.place_without_boundary`` reads the lateral's rows as the vertical
    (``lateral.points[:, 1]``) and its columns as depth (``lateral.points[:, 0]``, only when
    ``lc @ normal`` is ±1), so a turned lateral starts the fit with a scale from depth against depth (0.59
    instead of 0.96 on the probe's case) and no depth from the film. Any Cobb angle past 180° is impossible."""
    upright = copy.deepcopy(TURNED_LATERAL)
    upright["lateral"] = _swap_axes(TURNED_LATERAL["lateral"])
    a = register(upright)["measures"]
    b = register(TURNED_LATERAL)["measures"]
    assert b["largest_cobb"]["angle_deg"] < 180.0
    # the same film: the same angles, within 1° (the fits converge to 1e-10 relative energy)
    assert abs(a["largest_cobb"]["angle_deg"] - b["largest_cobb"]["angle_deg"]) < 1.0
    assert abs(a["thoracic_kyphosis_t4_t12_deg"] - b["thoracic_kyphosis_t4_t12_deg"]) < 1.0


# verse270's PA film (`benches.clinic_films`, case (e), 1 mm noise, seed 0), rounded to 0.1 mm
VERSE270_PA = [
    ["T1", 207.4, 185.6], ["T2", 201.5, 202.3], ["T3", 192.9, 219.2], ["T4", 195.1, 242.6], ["T5", 191.3, 265.7],
    ["T6", 185.8, 287.5], ["T7", 183.4, 311.8], ["T8", 186.5, 334.6], ["T9", 187.2, 358.1], ["T10", 183.5, 385.4],
    ["T11", 181.3, 413.5], ["T12", 182.8, 442.3], ["L1", 182.8, 474.0], ["L2", 177.2, 506.7], ["L3", 176.7, 545.7],
    ["L4", 172.1, 579.9], ["L5", 175.3, 613.7],
]


def test_a_pa_film_turned_a_quarter_keeps_its_tilt_prior() -> None:
    """A PA film hung turned a quarter (["F", "L"]: columns toward the feet) "stays frontal" (docs/engine.md,
    implausible inputs). Today it silently loses the tilt prior (``clinical.is_frontal`` asks for columns
    along x and rows along z, in ``with_observations`` and ``place_without_boundary``): this film reads its
    largest Cobb angle 24.8° upright and 17.2° turned, and ``fit.tilt_prior`` True and False. In the probe
    218 of 1213 turned PA films read the largest Cobb angle 3–30° away from the same film upright (two more
    beyond 30°)."""
    upright = {"pa": {"patient_orientation": ["L", "F"],
                      "landmarks": [{"level": lv, "point": [c, r]} for lv, c, r in VERSE270_PA]}}
    turned = {"pa": _swap_axes(upright["pa"])}
    a, b = register(upright), register(turned)
    assert a["fit"]["tilt_prior"] == b["fit"]["tilt_prior"]
    assert abs(a["measures"]["largest_cobb"]["angle_deg"] - b["measures"]["largest_cobb"]["angle_deg"]) < 1.0


# A synthetic spine's PA film (`spine_engine.synthetic`, seed of `benches.clinic.generated_truths(48, 7)`'s
# synthetic-422827225; `clinic_films` case (e), 5 mm noise, seed 0), rounded to 0.1 mm: its truth's largest
# frontal Cobb angle (centreline frames) is 17.2°. The noise puts T2 4.5 mm above T1, within the 3√2 SDs
# (21 mm) that validation allows a segment to read reversed.
NOISY_PA = [
    ["T1", 177.6, 218.9], ["T2", 168.1, 214.4], ["T3", 171.2, 240.7], ["T4", 167.0, 263.7], ["T5", 159.3, 276.6],
    ["T6", 147.6, 292.7], ["T7", 153.7, 317.4], ["T8", 154.0, 341.3], ["T9", 156.2, 357.8], ["T10", 153.4, 393.5],
    ["T11", 157.8, 409.1], ["T12", 151.1, 438.2], ["L1", 163.5, 462.2], ["L2", 173.6, 504.4], ["L3", 166.7, 533.2],
    ["L4", 176.0, 566.2], ["L5", 185.6, 598.9],
]
NOISY_PA_TRUE_COBB_DEG = 17.2


def test_the_tilt_prior_does_not_turn_a_vertebra_past_90_degrees_on_a_noisy_film() -> None:
    """Stated 5 mm of noise, the film is valid. Today the tilt prior reads T1–T2's chord (−115.6°, the segment
    reversed by the noise) as T1's tilt: T1 is fitted at −94.5°, T2 at −53°, and the largest Cobb angle reads
    109.3° ± 11.3° against the truth's 17.2° (8 SDs; without the tilt prior 8.9°). A frontal tilt past 90° is
    the one ``corners_not_upright`` refuses in corners ("its tilt would read past ±90° and a Cobb angle past
    180°"). Either a refusal naming the levels or a result whose tilts stay within ±90° and whose 3-SD interval
    holds the truth is right; the 3 SDs leave room for one fixed draw (a 95 % interval would be 1.96)."""
    payload = {"pa": {"landmark_sd_mm": 5.0,
                      "landmarks": [{"level": lv, "point": [c, r]} for lv, c, r in NOISY_PA]}}
    try:
        result = register(payload)
    except InvalidInput:
        return
    assert max(abs(v["frontal_tilt_deg"]) for v in result["vertebrae"]) < 90.0
    largest = result["measures"]["largest_cobb"]
    assert abs(largest["angle_deg"] - NOISY_PA_TRUE_COBB_DEG) < 3.0 * largest["angle_sd_deg"]



def test_a_projection_scale_beyond_any_radiographs_is_refused_naming_it() -> None:
    """A given projection's scale is a magnification (detector mm per patient mm): held to the range an ERMF is
    held to (``validation.MAGNIFICATION_RANGE`` widened by ``UNVERIFIED_SCALE``: 0.36–3.5). The probe's payloads
    with a scale up to 1000 ended in FitFailed instead of a refusal that names the field."""
    payload = {"pa": {"landmarks": [{"level": lv, "point": [c, r]} for lv, c, r in VERSE270_PA],
                      "projection": {"scale": 1000.0, "translation": [200.0, 180.0]}}}
    with pytest.raises(InvalidInput) as refused:
        register(payload)
    assert any(e.loc == ("pa", "projection", "scale") and e.type == "implausible_geometry"
               for e in refused.value.errors), refused.value.errors
