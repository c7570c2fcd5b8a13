"""The kyphosis one PA film's foreshortening reads (``spine_engine.sagittal_reading``): its search
against scipy's, its fixed point, its refusals, and that it reads more kyphosis from a more kyphotic
real spine. Spines: VerSe dev (``tests/data/verse_dev.csv``, CC BY-SA 4.0, credited there), filmed
by the clinic bench's simulated series."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import least_squares

from benches import clinic, clinic_films
from spine_engine.frames import frames_from_centreline
from spine_engine.measures import compute_measures
from spine_engine.sagittal_reading import (
    MIN_CHORDS,
    ReadingModel,
    chord_inclinations_deg,
    kyphoses_deg,
    load_reading_model,
    read_inclinations_deg,
)

VERSE_DEV = clinic.truths_of_csv(Path(__file__).resolve().parents[1] / "data" / "verse_dev.csv")
LEVELS = np.arange(17)


def _model() -> ReadingModel:
    model = load_reading_model()
    assert model is not None  # shipped in spine_engine/priors
    return model


def _pa_image(positions: np.ndarray, noise_mm: float, seed: int = 0) -> np.ndarray:
    truth = clinic_films.Truth("spine", positions, frames_from_centreline(positions))
    series = clinic_films.simulate_series(truth, noise_mm, seed)
    return np.asarray(series.pa.image(positions, False) + (series.pa_noise if noise_mm > 0 else 0.0))


def _scipy_reading(model: ReadingModel, image: np.ndarray, sd_mm: float) -> np.ndarray:
    """The same MAP by scipy's trust-region least squares, tolerances at their finest."""
    ell = np.linalg.norm(np.diff(image, axis=0), axis=1)
    noise = np.sqrt(model.length_sd**2 + 2.0 * sd_mm**2 / ell**2)
    mu, prior_sd = np.radians(model.mean_inclination_deg), np.radians(np.r_[model.lean_sd_deg, model.mode_sd_deg])

    def residuals(p: np.ndarray) -> np.ndarray:
        beta = mu + p[1] + p[2:] @ model.modes
        return np.r_[(np.log(ell) - p[0] - np.log(model.chord_share) - np.log(np.cos(beta))) / noise, p[1:] / prior_sd]

    start = np.r_[np.log(ell.sum()), np.zeros(1 + len(model.modes))]
    p = least_squares(residuals, start, xtol=1e-15, ftol=1e-15, gtol=1e-15).x
    return np.asarray(np.degrees(mu + p[1] + p[2:] @ model.modes))


def test_the_search_finds_scipys_optimum() -> None:
    """Newton's search (hand-written for speed) ends where scipy's least squares does, within 1e-4° of
    every chord's inclination, on the 24 dev spines' PA films at 1 mm of noise; the tolerance is 60
    times the search's step tolerance (1e-6 rad)."""
    model = _model()
    for truth in VERSE_DEV:
        image = _pa_image(truth.positions, 1.0)
        ours = read_inclinations_deg(model, LEVELS, image, 1.0)
        assert ours is not None
        np.testing.assert_allclose(ours, _scipy_reading(model, image, 1.0), atol=1e-4, err_msg=truth.spine_id)


def test_lengths_of_the_mean_shape_read_the_mean_inclinations() -> None:
    """Chords of the population's mean shares, each shortened by the cosine of its mean inclination,
    leave every residual and prior row at 0: the reading is μ itself, at any size."""
    model = _model()
    ell = 431.0 * model.chord_share * np.cos(np.radians(model.mean_inclination_deg))
    points = np.column_stack((np.zeros(17), np.r_[0.0, np.cumsum(ell)]))
    read = read_inclinations_deg(model, LEVELS, points, 1.0)
    assert read is not None
    np.testing.assert_allclose(read, model.mean_inclination_deg, atol=1e-9)


def test_too_few_adjacent_levels_read_nothing() -> None:
    """Fewer than ``MIN_CHORDS`` chords between adjacent landmarked levels (every other level here: none)
    give no reading, and the rod's reading stands alone."""
    model = _model()
    image = _pa_image(VERSE_DEV[0].positions, 1.0)
    assert read_inclinations_deg(model, LEVELS[::2], image[::2], 1.0) is None
    kept = LEVELS[: MIN_CHORDS + 1]
    assert read_inclinations_deg(model, kept, image[kept], 1.0) is not None
    assert read_inclinations_deg(model, kept[:-1], image[kept[:-1]], 1.0) is None


def _bent(positions: np.ndarray, factor: float) -> np.ndarray:
    """The spine with every chord's inclination out of the frontal plane multiplied by ``factor``, its
    length and its direction within the frontal plane kept: a deeper or shallower sagittal curve of the
    same vertebrae."""
    d = np.diff(positions, axis=0)
    length = np.linalg.norm(d, axis=1)
    frontal = np.column_stack((d[:, 0], np.zeros(len(d)), d[:, 2]))
    frontal /= np.linalg.norm(frontal, axis=1, keepdims=True)
    beta = factor * np.arctan2(d[:, 1], np.hypot(d[:, 0], d[:, 2]))
    chords = length[:, None] * (np.cos(beta)[:, None] * frontal + np.sin(beta)[:, None] * np.array([0.0, 1.0, 0.0]))
    return np.asarray(positions[0] + np.vstack((np.zeros(3), np.cumsum(chords, axis=0))))


def test_a_deeper_sagittal_curve_reads_more_kyphosis() -> None:
    """A real spine bent sagittally by ×0.5 and ×1.5 (``_bent``: each chord's length kept, so a PA film
    sees it shorter as it leans more) makes films whose readings order the two kyphoses as the truths
    do, for every dev spine, without noise; the truths' kyphoses on their centreline frames."""
    model = _model()
    for truth in VERSE_DEV:
        read, true = [], []
        for factor in (0.5, 1.5):
            q = _bent(truth.positions, factor)
            beta = read_inclinations_deg(model, LEVELS, _pa_image(q, 0.0), 1.0)
            assert beta is not None
            read.append(kyphoses_deg(beta)[0])
            true.append(compute_measures(q, frames_from_centreline(q)).thoracic_kyphosis_t4_t12_deg)
        assert (read[1] - read[0]) * (true[1] - true[0]) > 0, (truth.spine_id, read, true)


def test_a_kyphotic_spines_chords_read_its_kyphosis() -> None:
    """``kyphoses_deg`` of a spine's own chord inclinations is within 2° of its kyphosis on its
    centreline frames (tangents of neighbouring chords against the frames' finite differences) for
    every dev spine, and positive (kyphotic) as theirs is."""
    for truth in VERSE_DEV:
        t4_t12, t5_t12 = kyphoses_deg(chord_inclinations_deg(truth.positions))
        measured = compute_measures(truth.positions, frames_from_centreline(truth.positions))
        assert t4_t12 == pytest.approx(measured.thoracic_kyphosis_t4_t12_deg, abs=2.0), truth.spine_id
        assert t5_t12 == pytest.approx(measured.thoracic_kyphosis_t5_t12_deg, abs=2.0), truth.spine_id
        assert t4_t12 > 0


def test_a_point_source_films_landmarks_are_read_at_one_magnification() -> None:
    """``reconstruction.weak_perspective_points``: the fitted spine projected by the PA film's fitted
    point-source camera (clinic case (c), SID and SOD given, one PA film), scaled back by its depths,
    is its weak-perspective projection at SID/SOD: p = c + (SID/SOD)·Rot(ψ)·E(r − o), to 1e-9 mm.
    A weak-perspective film's points are returned as they are."""
    import dataclasses

    from spine_engine.anatomy import load_profile
    from spine_engine.fit.cameras import project
    from spine_engine.reconstruction import fit_patient_rod, prepare_inputs, weak_perspective_points
    from spine_engine.validation import validate_payload

    profile = load_profile()
    truth = VERSE_DEV[2]
    series = clinic_films.simulate_series(truth, 1.0, 0)
    for key, perspective in (("c", True), ("e", False)):
        case = dataclasses.replace(clinic_films.CASES[key], lateral_from=None)
        payload = clinic_films.build_payload(series, case).model_dump(mode="json", exclude_none=True)
        inputs = prepare_inputs(validate_payload(payload), profile)
        out = fit_patient_rod(inputs, profile)[0].output
        [pa] = inputs.views
        if not perspective:
            assert weak_perspective_points(pa, out) is pa.points
            continue
        assert pa.camera is not None and pa.camera.kind == "perspective"
        values = out.cameras["pa"]
        r = out.positions[pa.indices]
        projected = dataclasses.replace(pa, points=project(pa.camera, values, r, pa.e_c, pa.e_r).points)
        psi = values[-1]
        turn = np.array([[np.cos(psi), -np.sin(psi)], [np.sin(psi), np.cos(psi)]])
        rel = np.column_stack(((r - values[2:5]) @ pa.e_c, (r - values[2:5]) @ pa.e_r))
        weak = values[0:2] + pa.camera.sid_mm / pa.camera.sod_mm * rel @ turn.T
        np.testing.assert_allclose(weak_perspective_points(projected, out), weak, atol=1e-9)
