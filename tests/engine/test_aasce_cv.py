"""The cross-validation helpers of ``spine bench aasce --cv`` on made-up numbers (no AASCE data)."""

import numpy as np

from spine_engine import reconstruction
from spine_engine.experiments.aasce import end_weights, fit_weighted, prior_in_use
from spine_engine.tilt_prior import WINDOW, TiltPrior, fit_coefficients, load_tilt_prior

RNG = np.random.default_rng(11)


def _made_up(n: int = 60) -> tuple[np.ndarray, np.ndarray]:
    chords = RNG.normal(0.0, 15.0, (n, 16))
    tilts = np.concatenate([chords[:, :1], 0.5 * (chords[:, :-1] + chords[:, 1:]), chords[:, -1:]], axis=1)
    return tilts + RNG.normal(0.0, 2.0, tilts.shape), chords


def test_unit_weights_give_the_shipped_fit() -> None:
    tilts, chords = _made_up()
    weighted = fit_weighted(tilts, chords, WINDOW, 1e-3, np.ones_like(tilts))
    np.testing.assert_allclose(weighted, fit_coefficients(tilts, chords), atol=1e-10)


def test_weighted_fit_keeps_the_sum_of_coefficients() -> None:
    tilts, chords = _made_up()
    coefficients = fit_weighted(tilts, chords, tuple(range(-16, 16)), 1e-3, end_weights(tilts, 3.0))
    np.testing.assert_allclose(coefficients.sum(axis=1), 1.0, atol=1e-9)


def test_end_weights_mark_the_most_and_least_tilted_vertebrae() -> None:
    tilts = np.array([[0.0, 5.0, -3.0, 1.0], [2.0, 2.5, 9.0, -8.0]])
    np.testing.assert_array_equal(end_weights(tilts, 3.0), [[1, 4, 4, 1], [1, 1, 4, 4]])


def test_prior_in_use_replaces_the_shipped_prior_only_inside() -> None:
    shipped = load_tilt_prior()
    other = TiltPrior("cv", WINDOW, np.full((17, len(WINDOW)), 0.25), 7.0)
    with prior_in_use(other):
        assert reconstruction.load_tilt_prior() is other
    assert reconstruction.load_tilt_prior() is shipped
