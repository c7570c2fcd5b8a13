"""``spine bench prior``: the shipped profile's population prior predicts VerSe dev (the prior
predictive check of ``benches.prior``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from benches import prior
from benches.truth import read_verse
from spine_engine.anatomy import load_profile
from spine_engine.frames import frames_from_centreline
from spine_engine.measures import kyphosis_lordosis_deg

DEV = Path(__file__).resolve().parents[1] / "data" / "verse_dev.csv"
SPINES = read_verse(DEV)


def test_prior_predictive_means_match_dev() -> None:
    """1500 spines drawn from the shipped prior with no landmark (the mean's sampling SD about 0.5°):
    kyphosis and lordosis means within 2° of VerSe dev's, the T1–L5 length's mean within 2 % and its
    SD within 20 % (the acceptance bands; the sagittal SDs are wider by design,
    ``prior.SAGITTAL_FIT_LOOSENING``)."""
    profile = load_profile()
    data = profile.population_prior
    assert data is not None
    drawn = prior.sample_prior(profile, 1500, 1, (data["size_mean"], data["size_sd"]))
    dev = np.array([kyphosis_lordosis_deg(frames_from_centreline(p)) for _, p in SPINES])
    assert abs(drawn["kyphosis_t4_t12_deg"].mean() - dev[:, 0].mean()) <= 2.0
    assert abs(drawn["lordosis_l1_l5_deg"].mean() - dev[:, 2].mean()) <= 2.0
    lengths = np.array([np.linalg.norm(np.diff(p, axis=0), axis=1).sum() for _, p in SPINES])
    assert abs(drawn["length_t1_l5_mm"].mean() / lengths.mean() - 1.0) <= 0.02
    assert abs(drawn["length_t1_l5_mm"].std() / lengths.std(ddof=1) - 1.0) <= 0.20
    # the prior is at least as wide as the population in the sagittal plane: never tighter
    assert drawn["kyphosis_t4_t12_deg"].std() >= 0.8 * dev[:, 0].std(ddof=1)
    assert drawn["lordosis_l1_l5_deg"].std() >= 0.8 * dev[:, 2].std(ddof=1)


def test_prior_predictive_cobb_matches_training() -> None:
    """The shipped prior's major Cobb angle (1500 spines drawn with no landmark) has AASCE training's
    root mean square (the population in the profile's provenance; the AASCE data stay out of the
    repo) within 3 of its Monte Carlo standard errors (delta method), as ``prior.calibrate`` sets it
    on the prior as shipped, and its mean within 2° and SD within 20 % (the acceptance bands)."""
    profile = load_profile()
    data = profile.population_prior
    assert data is not None
    population = data["provenance"]["population"]["major_cobb_deg"]
    cobb = prior.sample_prior(profile, 1500, 1, (data["size_mean"], data["size_sd"]))["major_cobb_deg"]
    rms = float(np.sqrt(np.mean(cobb**2)))
    rms_se = float(np.std(cobb**2, ddof=1) / np.sqrt(cobb.size) / (2.0 * rms))
    assert abs(rms - float(np.hypot(population["mean"], population["sd"]))) <= 3.0 * rms_se
    assert abs(cobb.mean() - population["mean"]) <= 2.0
    assert abs(cobb.std(ddof=1) / population["sd"] - 1.0) <= 0.20


def test_coupling_check_of_the_independent_prior_is_the_mean() -> None:
    """``sagittal_coupling``'s shrinkage 1 keeps the covariance's diagonal, whose conditional mean is
    the other spines' mean: its row is the leave-one-out error of that mean, computed here apart;
    shrinkage 0 conditions on the full covariance and answers otherwise."""
    rows = prior.sagittal_coupling([pos for _, pos in SPINES])
    assert [r["shrinkage"] for r in rows] == list(prior.COUPLING_SHRINKAGE)
    theta = np.array([prior.sagittal_angles_deg(pos) for _, pos in SPINES])[:, prior.UNSEEN_BY_LATERAL_FROM_T4]
    loo = [np.delete(theta, k, axis=0).mean(axis=0).sum() - theta[k].sum() for k in range(len(theta))]
    assert rows[-1]["rms_error_deg"] == pytest.approx(float(np.sqrt(np.mean(np.square(loo)))), rel=1e-12)
    assert abs(rows[0]["rms_error_deg"] - rows[-1]["rms_error_deg"]) > 0.1
