"""Cobb angles on levels no film shows (``reconstruction.frontal_observed_levels``, ``_unseen_cobb``).

Truths are real spines: VerSe dev vertebral-body centroids shipped in ``tests/data/verse_dev.csv``
(CC BY-SA 4.0, credited in ``tests/data/README.md``), filmed as ``spine bench clinic`` films them
(``benches.clinic_films``, 1 mm of landmark noise), then the PA film's landmarks cut to a few levels.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from benches import clinic_films
from benches.truth import read_verse
from spine_engine import register
from spine_engine.anatomy import load_profile, population_prior
from spine_engine.frames import frames_from_centreline
from spine_engine.levels import LEVEL_INDEX, LEVELS
from spine_engine.reconstruction import UNRELIABLE_SD_FRACTION, frontal_tilt_seen_levels
from spine_engine.synthetic import generate_spine

SPINES = read_verse(Path(__file__).resolve().parents[1] / "data" / "verse_dev.csv")
COBB_SD = float(load_profile().population_prior["provenance"]["population"]["major_cobb_deg"]["sd"])  # type: ignore[index]
"""The population's SD of the major Cobb angle (AASCE 2019 training, 18.4°, as the shipped profile's
population prior records it): the floor."""


def _films(k: int, case: str, pa_levels: list[str] | None = None) -> dict[str, Any]:
    """Dev spine k filmed as in the clinic bench's case ``case``, the PA landmarks cut to ``pa_levels``."""
    spine_id, positions = SPINES[k]
    truth = clinic_films.Truth(spine_id, positions, frames_from_centreline(positions))
    series = clinic_films.simulate_series(truth, noise_mm=1.0, seed=0)
    payload = clinic_films.build_payload(series, clinic_films.CASES[case]).model_dump(mode="json", exclude_none=True)
    if pa_levels is not None:
        payload["pa"]["landmarks"] = [lm for lm in payload["pa"]["landmarks"] if lm["level"] in pa_levels]
    return payload


T1_T4 = ["T1", "T2", "T3", "T4"]


@pytest.mark.parametrize("case", ["e", "a"])
def test_a_pa_film_of_t1_t4_leaves_the_largest_cobb_angle_to_the_prior(case: str) -> None:
    """PA landmarks on T1–T4 only (case "e": no lateral; "a": a full lateral film, which shows no frontal
    coordinate), every dev spine: the largest Cobb angle ranges over T5–L5, whose tilts only the prior
    decides, so "cobb" is in ``fit.unreliable`` and its SD is at least the population's; a curve with an
    end below T2 likewise (T4's own tilt is the rod's extrapolation, and T3's end only T4's tilt would
    show, ``frontal_tilt_seen_levels``), and a curve T1–T2 keeps the SD the film gives it. The old
    engine reported such curves unflagged, e.g. T1–L5 12° ± 17° from the PA film alone and T1–T10
    22° ± 9° with the lateral film."""
    beyond = within = 0
    for k in range(len(SPINES)):
        result = register(_films(k, case, T1_T4))
        measures, unreliable = result["measures"], result["fit"]["unreliable"]
        assert "cobb" in unreliable
        assert measures["largest_cobb"]["angle_sd_deg"] >= COBB_SD
        for curve in measures["cobb"]:
            if LEVEL_INDEX[curve["lower"]] > LEVEL_INDEX["T2"]:
                beyond += 1
                assert curve["angle_sd_deg"] >= COBB_SD
            else:
                within += 1
                assert curve["angle_sd_deg"] < COBB_SD
    assert beyond > 0  # the spines do bring curves reaching past the film (else this test tests nothing)


def test_the_whole_pa_film_leaves_no_cobb_angle_to_the_prior() -> None:
    """The same spines with all 17 PA levels (cases e and a): no Cobb angle is flagged or floored."""
    for k in range(0, len(SPINES), 3):
        for case in ("e", "a"):
            result = register(_films(k, case))
            assert "cobb" not in result["fit"]["unreliable"]
            assert result["measures"]["largest_cobb"]["angle_sd_deg"] < UNRELIABLE_SD_FRACTION * COBB_SD


@pytest.mark.parametrize("pa_levels", [["T1", "L5"], ["T1", "T9", "L5"]], ids=["T1 and L5", "T1, T9 and L5"])
def test_a_sparse_pa_film_leaves_its_cobb_angles_to_the_prior(pa_levels: list[str]) -> None:
    """PA landmarks on a few levels far apart: the tilts between are the rod's interpolation under its
    prior, so "cobb" is flagged and the largest angle's SD is at least the population's. Measured on
    every dev spine with T1, T9 and L5 (no lateral) before this rule: none flagged, SDs 7.1–8.6°, the
    largest angle 5–27° below the whole film's, its 95 % interval covering 79 % of them."""
    for k in range(0, len(SPINES), 4):
        result = register(_films(k, "e", pa_levels))
        assert "cobb" in result["fit"]["unreliable"]
        assert result["measures"]["largest_cobb"]["angle_sd_deg"] >= COBB_SD


def test_one_missing_level_between_two_landmarks_is_still_seen() -> None:
    """A PA film missing one level (T7) between landmarked neighbours: its tilt is their chord's, so no
    Cobb angle is flagged or floored for it."""
    for k in range(0, len(SPINES), 4):
        result = register(_films(k, "e", [level for level in LEVELS if level != "T7"]))
        assert "cobb" not in result["fit"]["unreliable"]
        assert result["measures"]["largest_cobb"]["angle_sd_deg"] < UNRELIABLE_SD_FRACTION * COBB_SD


def test_frontal_observed_levels() -> None:
    """The PA landmarks' levels, T1 and L5 when the boundary gives their directors exactly, and a level
    between two of these; the population prior carries the major Cobb angle's SD among the measures'."""
    from spine_engine.reconstruction import frontal_observed_levels

    assert population_prior(load_profile()).measure_sd_deg["major_cobb_deg"] == COBB_SD  # type: ignore[union-attr]

    def names(mask: np.ndarray) -> list[str]:
        return [LEVELS[i] for i in np.flatnonzero(mask)]

    assert names(frontal_observed_levels(np.array([2, 0, 1, 3]), "estimated")) == T1_T4
    assert names(frontal_observed_levels(np.array([4, 11]), "soft")) == ["T5", "T12"]
    assert names(frontal_observed_levels(np.array([0, 1, 2, 3]), "given")) == [*T1_T4, "L5"]
    assert names(frontal_observed_levels(np.array([0, 1, 3, 4]), "estimated")) == ["T1", "T2", "T3", "T4", "T5"]
    assert names(frontal_observed_levels(np.array([1, 15]), "given")) == ["T1", "T2", "L4", "L5"]
    assert names(frontal_observed_levels(np.array([0, 2, 4]), "estimated")) == ["T1", "T2", "T3", "T4", "T5"]


def test_a_film_cut_inside_the_spine_shows_no_tilt_at_its_last_landmark() -> None:
    """The first or last point landmark of a film cut inside the spine has one landmarked neighbour: its
    tilt is the rod's extrapolation, not shown; corners, or T1 and L5 given exactly, show their own."""

    def names(mask: np.ndarray) -> list[str]:
        return [LEVELS[i] for i in np.flatnonzero(mask)]

    observed = np.zeros(len(LEVELS), dtype=bool)
    observed[:8] = True  # a film of T1–T8
    assert names(frontal_tilt_seen_levels(observed, np.array([], dtype=int), "estimated")) == list(LEVELS[:7])
    assert names(frontal_tilt_seen_levels(observed, np.array([7]), "estimated")) == list(LEVELS[:8])
    observed[:] = True
    assert names(frontal_tilt_seen_levels(observed, np.array([], dtype=int), "estimated")) == list(LEVELS)
    observed[[8, 9]] = False  # two levels in a row without landmark: T8 and T11 are the edges of the gap
    assert names(frontal_tilt_seen_levels(observed, np.array([], dtype=int), "soft")) == [
        level for level in LEVELS if level not in ("T8", "T9", "T10", "T11")
    ]
    ends_only = np.zeros(len(LEVELS), dtype=bool)
    ends_only[[0, len(LEVELS) - 1]] = True
    assert names(frontal_tilt_seen_levels(ends_only, np.array([], dtype=int), "given")) == ["T1", "L5"]


def test_a_curve_ending_at_the_films_edge_is_the_priors() -> None:
    """A synthetic double curve (seed 7: T4–T11 73°, ``spine_engine.synthetic``) filmed PA only with
    landmarks on T1–T8: the thoracic curve goes on past T8, and T8's tilt is the rod's extrapolation
    toward straight, so the curve the fit finds ends on or next to T8 at well under the truth's angle.
    Its end vertebra is not one the film shows: "cobb" is flagged and its SD is at least the
    population's. The old engine reported it as T3–T7 34° ± 5°, the truth 7.4 of its SDs away."""
    spine = generate_spine(7)
    truth = clinic_films.Truth("synthetic-7", spine.positions, spine.rotations)
    series = clinic_films.simulate_series(truth, noise_mm=1.0, seed=0)
    payload = clinic_films.build_payload(series, clinic_films.CASES["e"]).model_dump(mode="json", exclude_none=True)
    on_film = [lm for lm in payload["pa"]["landmarks"] if LEVEL_INDEX[lm["level"]] <= LEVEL_INDEX["T8"]]
    payload["pa"]["landmarks"] = on_film
    result = register(payload)
    assert "cobb" in result["fit"]["unreliable"]
    reaching = [c for c in result["measures"]["cobb"] if LEVEL_INDEX[c["lower"]] >= LEVEL_INDEX["T7"]]
    assert reaching  # the curve toward the film's edge is reported (else this test tests nothing)
    for curve in reaching:
        assert curve["angle_sd_deg"] >= COBB_SD


def test_curves_inside_a_cut_film_keep_their_sd_and_those_at_its_edge_are_floored() -> None:
    """Dev spines filmed PA only from T1 to T8–T12 and from T6–T10 to L5: a curve whose end vertebrae
    and the levels beyond them show their tilts keeps the Laplace SD the film gives it; one ending on
    the last landmark or next to it has at least the population's."""
    inside = edge = 0
    for k in range(0, len(SPINES), 2):
        for levels in (LEVELS[: 8 + k % 5], LEVELS[5 + k % 5 :]):
            first, last = LEVEL_INDEX[levels[0]], LEVEL_INDEX[levels[-1]]
            for curve in register(_films(k, "e", list(levels)))["measures"]["cobb"]:
                upper, lower = LEVEL_INDEX[curve["upper"]], LEVEL_INDEX[curve["lower"]]
                if (first > 0 and upper - 1 <= first) or (last < len(LEVELS) - 1 and lower + 1 >= last):
                    edge += 1
                    assert curve["angle_sd_deg"] >= COBB_SD
                else:
                    inside += 1
                    assert curve["angle_sd_deg"] < COBB_SD
    assert inside > 0 and edge > 0
