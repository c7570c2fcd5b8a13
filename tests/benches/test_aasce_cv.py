"""The tilt prior's windows and blend, and the helpers of ``spine bench aasce --cv``, on made-up
numbers (no AASCE data)."""

import numpy as np

from benches.aasce import end_weights
from benches.perf import synthetic_spine
from benches.truth import payload_from_truth
from spine_engine.anatomy import load_profile
from spine_engine.reconstruction import prepare_inputs
from spine_engine.tilt_prior import (
    WINDOW,
    TiltPrior,
    chord_windows,
    fit_coefficients,
    load_tilt_prior,
    predict_tilts_deg,
    toward_chord_normal,
)
from spine_engine.validation import validate_payload

RNG = np.random.default_rng(11)


def _made_up(n: int = 60) -> tuple[np.ndarray, np.ndarray]:
    chords = RNG.normal(0.0, 15.0, (n, 16))
    tilts = np.concatenate([chords[:, :1], 0.5 * (chords[:, :-1] + chords[:, 1:]), chords[:, -1:]], axis=1)
    return tilts + RNG.normal(0.0, 2.0, tilts.shape), chords


def test_unit_weights_give_the_shipped_fit() -> None:
    tilts, chords = _made_up()
    weighted = fit_coefficients(tilts, chords, WINDOW, 1e-3, weights=np.ones_like(tilts))
    np.testing.assert_allclose(weighted, fit_coefficients(tilts, chords), atol=1e-10)


def test_weighted_fit_keeps_the_sum_of_coefficients() -> None:
    tilts, chords = _made_up()
    coefficients = fit_coefficients(tilts, chords, tuple(range(-16, 16)), 1e-3, weights=end_weights(tilts, 3.0))
    np.testing.assert_allclose(coefficients.sum(axis=1), 1.0, atol=1e-9)


def test_end_weights_mark_the_most_and_least_tilted_vertebrae() -> None:
    tilts = np.array([[0.0, 5.0, -3.0, 1.0], [2.0, 2.5, 9.0, -8.0]])
    np.testing.assert_array_equal(end_weights(tilts, 3.0), [[1, 4, 4, 1], [1, 1, 4, 4]])


def test_a_prior_passed_to_prepare_inputs_replaces_the_shipped_one() -> None:
    """The bench's cross-validated priors reach the fit through ``tilt_prior`` (no patching)."""
    positions, rotations = synthetic_spine(cobb_deg=40.0)
    model = validate_payload(payload_from_truth(positions, rotations, list(range(17)), boundary=False))
    profile = load_profile()
    other = TiltPrior("cv", WINDOW, np.full((17, len(WINDOW)), 0.25), 7.0)

    def tilt_directions(prior: TiltPrior | None) -> np.ndarray:
        inputs = prepare_inputs(model, profile, prior)
        assert inputs.tilt_prior
        directions = inputs.views[0].tilt_directions
        assert directions is not None
        return directions

    shipped = tilt_directions(None)
    np.testing.assert_array_equal(shipped, tilt_directions(load_tilt_prior()))
    assert np.abs(tilt_directions(other) - shipped).max() > 1e-3


def test_shifted_windows_use_distinct_chords_inside_the_spine() -> None:
    idx = chord_windows(tuple(range(-3, 3)), "shifted")
    assert idx.shape == (17, 6) and idx.min() == 0 and idx.max() == 15
    assert all(len(set(row)) == 6 for row in idx)
    np.testing.assert_array_equal(idx[8], np.arange(5, 11))  # inside the spine: as the clipped window
    np.testing.assert_array_equal(idx[8], chord_windows(tuple(range(-3, 3)))[8])


def test_full_blend_is_the_chord_normal_tilt() -> None:
    window = tuple(range(-3, 3))
    _, chords = _made_up(5)
    coefficients = toward_chord_normal(np.full((17, 6), 1.0 / 6.0), window, "shifted", 1.0)
    prior = TiltPrior("normal", window, coefficients, 1.0, {}, "shifted")
    normal = np.concatenate([chords[:, :1], 0.5 * (chords[:, :-1] + chords[:, 1:]), chords[:, -1:]], axis=1)
    np.testing.assert_allclose(predict_tilts_deg(prior, chords), normal, atol=1e-12)
    half = toward_chord_normal(np.full((17, 6), 1.0 / 6.0), window, "shifted", 0.3)
    np.testing.assert_allclose(half.sum(axis=1), 1.0, atol=1e-12)
