"""The shipped calibrations are what their commands compute from today's engine (``make calibrate``,
docs/engine.md "Calibration"): a change to the engine that moves one of them fails here until the
chain is re-run, so the files never describe an engine that no longer exists (the tilt prior's
weight fraction and ``cobb_sd_deg`` once did, for two days).

Each check re-runs a command's computation without writing and compares it to the shipped file.
The population and tilt priors need AASCE training (kept outside the repository: skipped where
``../shared`` is absent, a failure in CI); the uncertainty calibration needs only VerSe dev, copied
in ``tests/data``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from benches import aasce, clinic, noise_weight, pa_reading, prior
from benches.calibrate import mean_sagittal_shape
from benches.clinic_films import CASES
from benches.truth import read_verse
from benches.uncertainty_calibration import calibrate, collect
from spine_engine.anatomy import load_profile
from spine_engine.fit.uncertainty import calibration
from spine_engine.sagittal_reading import load_reading_model
from spine_engine.tilt_prior import load_tilt_prior

VERSE_DEV = Path(__file__).resolve().parents[1] / "data" / "verse_dev.csv"
AASCE = clinic.shared_data_dir("aasce2019")
needs_aasce = pytest.mark.skipif(
    not (AASCE / "training").is_dir(), reason=f"AASCE 2019 training not found at {AASCE} (tuning data)"
)


def test_rest_shape_is_current() -> None:
    """``spine bench calibrate``'s first step, VerSe dev's mean sagittal shape, is the shipped rest
    shape (stored rounded to 4 and 6 decimals, as the step rounds it)."""
    shipped = load_profile().rest_shape
    assert shipped is not None
    today = mean_sagittal_shape(read_verse(VERSE_DEV))
    assert today["sagittal_inclination_deg"] == shipped["sagittal_inclination_deg"]
    assert today["length_fractions"] == shipped["length_fractions"]


def test_landmark_weight_is_current() -> None:
    """``spine bench noise-weight --write default`` (its default grid of multipliers, on VerSe dev with
    the shipped provenance's noise, seed and cases) keeps the shipped weights: ×1 scores best. The
    profile's weights came from a grid around earlier ones (``started_from``); a change to the
    engine that moves the optimum past the grid's neighbours (×3, ×0.3) fails here."""
    profile = load_profile()
    shipped = profile.provenance["noise_calibration"]
    rows = noise_weight.grid_scores(profile, clinic.truths_of_csv(VERSE_DEV), list(noise_weight.DEFAULT_GRID),
                                    shipped["cases"], shipped["noise_mm"], shipped["seed"])  # fmt: skip
    best = min(rows, key=lambda r: r["score_mm"])
    assert best["multiplier"] == 1.0, [(r["multiplier"], round(r["score_mm"], 4)) for r in rows]


def test_pa_reading_is_current() -> None:
    """``spine bench pa-reading --write`` on VerSe dev and the clinic bench's 20 synthetic dev spines gives
    the shipped reading model (stored to 6 decimals, angles to 4) and weight, and its weight table."""
    shipped = load_reading_model()
    assert shipped is not None
    today, rows = pa_reading.calibrate(clinic.truths_of_csv(VERSE_DEV), clinic.synthetic_truths(20, 0, "dev"))
    assert today.weight == shipped.weight
    np.testing.assert_allclose(today.chord_share, shipped.chord_share, atol=5e-7)
    np.testing.assert_allclose(today.mean_inclination_deg, shipped.mean_inclination_deg, atol=5e-5)
    np.testing.assert_allclose(today.modes, shipped.modes, atol=5e-7)
    np.testing.assert_allclose(today.mode_sd_deg, shipped.mode_sd_deg, atol=5e-5)
    assert today.lean_sd_deg == pytest.approx(shipped.lean_sd_deg, abs=5e-5)
    assert today.length_sd == pytest.approx(shipped.length_sd, abs=5e-7)
    table = shipped.provenance["weight_table"]
    assert [r["weight"] for r in rows] == [r["weight"] for r in table]
    for ours, theirs in zip(rows, table, strict=True):
        assert ours["mean_ratio"] == pytest.approx(theirs["mean_ratio"], abs=1e-9), ours["weight"]


def test_uncertainty_calibration_is_current() -> None:
    """``spine bench clinic --split dev --calibrate-uncertainty`` on VerSe dev with the shipped
    provenance's noise and seed gives the shipped λ and c to 1e-6 (both bisections run to 2⁻³⁰ of
    their ranges; the fits are deterministic) and the same PA-only readings."""
    shipped = calibration()
    noise_mm, seed = shipped.provenance["noise_mm"], shipped.provenance["seed"]
    today, _ = calibrate(collect(clinic.truths_of_csv(VERSE_DEV), list(CASES.values()), noise_mm, seed, "default"))
    assert today.prior_weight == pytest.approx(shipped.prior_weight, rel=1e-6)
    assert today.uncertainty_scale == pytest.approx(shipped.uncertainty_scale, rel=1e-6)
    assert today.prior_only.keys() == shipped.prior_only.keys()
    for name, reading in today.prior_only.items():
        assert reading.film_predicts == shipped.prior_only[name].film_predicts, name
        assert reading.offset_deg == pytest.approx(shipped.prior_only[name].offset_deg, abs=1e-6), name


@needs_aasce
def test_population_prior_is_current() -> None:
    """``spine bench prior --write default`` (600 draws per calibration step, seed 0, as the command
    runs it) gives the shipped profile's population prior to 1e-9 of each SD."""
    profile = load_profile()
    shipped = profile.population_prior
    assert shipped is not None
    today = prior.calibrate(profile, prior.population(VERSE_DEV, AASCE / "training"), 600, 0).population_prior
    assert today is not None
    for key in ("sagittal_sd_deg", "frontal_sd_deg", "stretch_sd", "shear_sd", "twist_sd_deg", "size_mean", "size_sd"):
        np.testing.assert_allclose(today[key], shipped[key], rtol=1e-9, err_msg=key)
    assert today["measure_sd_deg"].keys() == shipped["measure_sd_deg"].keys()
    for name, sd in today["measure_sd_deg"].items():  # the floors of prior-decided measures' SDs
        assert sd == pytest.approx(shipped["measure_sd_deg"][name], rel=1e-9), name


@needs_aasce
def test_tilt_prior_is_current() -> None:
    """``spine bench aasce --calibrate`` gives the shipped coefficients (least squares, stored to 6
    decimals) and weight fraction, and ``--calibrate-cobb-sd`` (run after the uncertainty calibration, whose λ the
    reported SD holds) the shipped ``cobb_sd_deg`` (its bisection's 0.01°)."""
    shipped = load_tilt_prior()
    today = aasce.fit_tilt_prior(AASCE, aasce.WEIGHT_FRACTIONS, None)
    np.testing.assert_allclose(today.coefficients, shipped.coefficients, rtol=0, atol=5e-7 + 1e-12)
    assert today.weight_fraction == shipped.weight_fraction
    sigmas, _, _ = aasce.cobb_sd_on_training(AASCE, None)
    assert sigmas == pytest.approx(shipped.cobb_sd_deg, abs=0.01 + 1e-9)
