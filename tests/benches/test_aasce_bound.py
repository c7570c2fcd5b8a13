"""``spine bench aasce-bound``'s learners on made-up numbers (no AASCE data): the chord features turn
and mirror with the image, least absolute deviations ignore outliers that least squares follows,
and the cross-validation never scores a radiograph with a learner that saw it."""

from __future__ import annotations

import numpy as np
import pytest

from benches import aasce_bound

RNG = np.random.default_rng(5)


def _made_up(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Smooth chord angles (a curve of random size and place), tilts the chord normal plus noise, and
    the major angle as the tilts' range."""
    s = np.linspace(0.0, 1.0, 16)
    size = RNG.uniform(10.0, 60.0, n)
    apex = RNG.uniform(0.3, 0.7, n)
    chords = size[:, None] * np.sin(np.pi * (s[None, :] - apex[:, None] + 0.5)) / 2.0 + RNG.normal(0.0, 2.0, (n, 16))
    normal = np.concatenate([chords[:, :1], 0.5 * (chords[:, :-1] + chords[:, 1:]), chords[:, -1:]], axis=1)
    tilts = normal + RNG.normal(0.0, 1.5, normal.shape)
    return tilts, chords, tilts.max(axis=1) - tilts.min(axis=1)


def test_chord_ranges_turn_and_mirror_with_the_image() -> None:
    _, chords, _ = _made_up(5)
    ranges = aasce_bound.chord_ranges(chords)
    assert ranges.shape == (5, aasce_bound.SMOOTHING_MAX)
    np.testing.assert_allclose(aasce_bound.chord_ranges(chords + 7.0), ranges, atol=1e-9)
    np.testing.assert_allclose(aasce_bound.chord_ranges(-chords), ranges, atol=1e-9)
    np.testing.assert_allclose(ranges[:, 0], chords.max(axis=1) - chords.min(axis=1))
    # smoothing over more chords cannot widen the range
    assert (np.diff(ranges, axis=1) <= 1e-9).all()


def test_least_absolute_deviations_ignore_outliers() -> None:
    x = RNG.uniform(0.0, 50.0, 200)
    y = 2.0 + 0.8 * x + RNG.normal(0.0, 0.1, 200)
    y[:20] += 40.0  # a tenth of the points far off, all on one side
    lad = aasce_bound.lad_fit(x[:, None], y)
    # weights 1/max(|r|, 0.5): an outlier keeps weight 1/40 and pulls 20·40/40 = 20 against the
    # inliers' 180·2 = 360, an offset of at most 20/380 ≈ 0.05 beside the noise
    assert lad == pytest.approx([0.8, 2.0], abs=0.1)
    ls = np.linalg.lstsq(np.column_stack([x, np.ones_like(x)]), y, rcond=None)[0]
    assert abs(ls[1] - 2.0) > 2.0  # least squares is pulled toward them
    np.testing.assert_allclose(aasce_bound.lad_predict(lad, np.array([[10.0]])), [10.0], atol=0.5)


def test_cross_validation_scores_each_radiograph_once_on_unseen_folds() -> None:
    """Every radiograph gets one error per learner; a radiograph changed wildly changes no error but
    its own fold's scores (the learners of the folds that hold it out never saw it)."""
    tilts, chords, major = _made_up(120)
    errors = aasce_bound.cross_validated_errors(tilts, chords, major, seed=1, folds=4)
    assert set(errors) == {"tilt_prior", "direct"}
    for e in errors.values():
        assert e.shape == (120,) and np.isfinite(e).all()
    # the tilt prior on these tilts (chord normal + noise) reads the range to within a few degrees
    assert np.mean(np.abs(errors["tilt_prior"])) < 5.0
    fold = np.random.default_rng(1).integers(0, 4, 120)
    changed = major.copy()
    i = int(np.flatnonzero(fold == 0)[0])
    changed[i] += 500.0
    again = aasce_bound.cross_validated_errors(tilts, chords, changed, seed=1, folds=4)
    held = fold == 0
    for name in errors:
        # a truth changed in fold 0 moves its own error by exactly the change, through no learner
        assert again[name][i] == pytest.approx(errors[name][i] - 500.0)
        rest = held & (np.arange(120) != i)
        np.testing.assert_allclose(again[name][rest], errors[name][rest])


def test_learners_trained_on_one_set_read_another() -> None:
    """``--test``'s readout: the learners trained on one made-up set read a second set, which they never
    saw, as well as the cross-validation reads the first (the tilts' noise, 1.5° per vertebra, moves a
    range of 17 tilts by a few degrees)."""
    tilts, chords, major = _made_up(150)
    _, new_chords, new_major = _made_up(60)
    angles = aasce_bound.trained_learners(tilts, chords, major, seed=2, new_chords=new_chords)
    assert set(angles) == {"tilt_prior", "direct"}
    cv = aasce_bound.cross_validated_errors(tilts, chords, major, seed=1, folds=4)
    for name, predicted in angles.items():
        assert predicted.shape == (60,)
        held_out_mae = np.mean(np.abs(predicted - new_major))
        assert held_out_mae < 5.0
        assert held_out_mae < 2.0 * np.mean(np.abs(cv[name])) + 1.0
