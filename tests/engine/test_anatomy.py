"""The generic rest model and the elastic profiles."""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from spine_engine.anatomy import (
    NORMAL_KYPHOSIS_T4_T12_DEG,
    NORMAL_LORDOSIS_L1_L5_DEG,
    Profile,
    list_profiles,
    load_profile,
    population_prior,
    profile_from_dict,
    rest_model,
    rest_segment_lengths,
    save_profile,
    section_properties,
    segment_semi_axes,
    typical_bending_energy_nmm,
)
from spine_engine.errors import InvalidInput, UnknownProfile
from spine_engine.levels import LEVELS
from spine_engine.measures import compute_measures, frontal_tilt_deg

VERSE_DEV = Path(__file__).parents[1] / "data" / "verse_dev.csv"


@pytest.fixture(scope="module")
def profile() -> Profile:
    """The literature profile: normal sagittal rest shape, uncalibrated elastic values."""
    return load_profile("literature")


def test_rest_model_has_the_documented_sagittal_profile_and_no_frontal_curve(profile: Profile) -> None:
    rest = rest_model(profile)
    m = compute_measures(rest.positions, rest.rotations, min_cobb_deg=0.5)
    assert m.thoracic_kyphosis_t4_t12_deg == pytest.approx(NORMAL_KYPHOSIS_T4_T12_DEG, abs=1.0)
    assert m.lumbar_lordosis_l1_l5_deg == pytest.approx(NORMAL_LORDOSIS_L1_L5_DEG, abs=1.0)
    assert (NORMAL_KYPHOSIS_T4_T12_DEG, NORMAL_LORDOSIS_L1_L5_DEG) == (38.0, 46.0)
    assert m.cobb == []
    np.testing.assert_allclose(frontal_tilt_deg(rest.rotations), 0.0, atol=1e-12)


def test_rest_model_geometry(profile: Profile) -> None:
    rest = rest_model(profile)
    assert rest.levels == LEVELS
    assert rest.ds.shape == (16,) and rest.positions.shape == (17, 3) and rest.rotations.shape == (17, 3, 3)
    np.testing.assert_allclose(rest.positions[0], 0.0)
    np.testing.assert_allclose(rest.positions[:, 0], 0.0, atol=1e-12)  # no lateral curve
    np.testing.assert_allclose(np.linalg.norm(np.diff(rest.positions, axis=0), axis=1), rest.ds, rtol=1e-12)
    np.testing.assert_allclose(rest.rotations[:, :, 0], np.tile([1.0, 0.0, 0.0], (17, 1)), atol=1e-12)
    R = rest.rotations
    np.testing.assert_allclose(np.swapaxes(R, 1, 2) @ R, np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    assert np.all(R[:, 2, 2] < -0.8) and np.all(R[:, 1, 1] < -0.8)  # d3 caudal, d2 anterior
    assert rest.positions[-1, 1] == pytest.approx(0.0, abs=1e-6)  # L5 straight below T1
    assert np.argmax(rest.positions[:, 1]) in range(4, 9)  # kyphosis apex mid-thoracic, posterior


def test_stiffness_formulas_and_length_scale(profile: Profile) -> None:
    rest = rest_model(profile)
    a, b = segment_semi_axes()
    j = 7
    A = np.pi * a[j] * b[j]
    Y, G, k = profile.youngs_modulus_mpa, profile.shear_modulus_mpa, profile.shear_coefficient
    expected_alpha = [
        Y * np.pi * a[j] * b[j] ** 3 / 4,
        Y * np.pi * a[j] ** 3 * b[j] / 4,
        G * np.pi * a[j] ** 3 * b[j] ** 3 / (a[j] ** 2 + b[j] ** 2),
    ]
    np.testing.assert_allclose(rest.alpha[j], expected_alpha, rtol=1e-12)
    np.testing.assert_allclose(rest.beta[j], [k * G * A, k * G * A, Y * A], rtol=1e-12)
    assert np.all(a > b)  # endplates are wider than deep: lateral bending (about d2) is stiffer
    assert np.all(rest.alpha[:, 1] > rest.alpha[:, 0])

    big = rest_model(profile, length_scale=1.2)
    np.testing.assert_allclose(big.ds, 1.2 * rest.ds)
    np.testing.assert_allclose(big.positions, 1.2 * rest.positions, atol=1e-9)
    np.testing.assert_allclose(big.rotations, rest.rotations, atol=1e-12)
    np.testing.assert_allclose(big.alpha, 1.2**4 * rest.alpha, rtol=1e-12)
    np.testing.assert_allclose(big.beta, 1.2**2 * rest.beta, rtol=1e-12)
    with pytest.raises(ValueError):
        rest_model(profile, length_scale=0.0)
    with pytest.raises(ValueError):
        rest.ds[0] = 1.0  # read-only


def test_circle_section() -> None:
    sec = section_properties(10.0, 10.0)
    assert sec["A"] == pytest.approx(np.pi * 100)
    assert sec["I1"] == pytest.approx(np.pi * 1e4 / 4) and sec["I2"] == pytest.approx(np.pi * 1e4 / 4)
    assert sec["J"] == pytest.approx(np.pi * 1e4 / 2)


def test_segment_lengths_are_close_to_verse_dev() -> None:
    """Tables vs VerSe dev (a tuning split): each level within 12 %, the total within 8 %."""
    rows = np.genfromtxt(VERSE_DEV, delimiter=",", skip_header=1)[:, 1:].reshape(-1, 17, 3)
    verse = np.linalg.norm(np.diff(rows, axis=1), axis=2).mean(axis=0)
    table = rest_segment_lengths()
    assert np.all(np.abs(table / verse - 1) < 0.12)
    assert abs(table.sum() / verse.sum() - 1) < 0.08


def test_literature_profile(profile: Profile) -> None:
    assert {"default", "literature"} <= set(list_profiles())
    assert profile.name == "literature" and profile.rest_shape is None and profile.stretch_factor == 1.0
    assert profile.provenance["status"].startswith("initial values from the literature")
    nu = profile.youngs_modulus_mpa / (2 * profile.shear_modulus_mpa) - 1
    assert 0.3 < nu < 0.5
    assert 0.8 < profile.shear_coefficient < 1.0
    # the fit weight makes a 0.2 mm residual cost about one segment's bending energy
    ratio = profile.fit_weight_pa * 0.2**2 / typical_bending_energy_nmm(profile)
    assert 0.5 < ratio < 2.0
    raw = json.loads((Path(__file__).parents[2] / "spine_engine" / "profiles" / "literature.json").read_text())
    assert set(raw) <= set(Profile.__dataclass_fields__)


def test_default_profile_is_calibrated_with_provenance() -> None:
    default = load_profile("default")
    assert default.name == "default"
    assert "Monte Carlo" in default.provenance["method"] and "dev" in default.provenance["training_set"]
    assert default.rest_shape is not None and "VerSe dev" in default.rest_shape["source"]
    rest = rest_model(default, length_scale=1.1)
    assert sum(rest_model(default).ds) * 1.1 == pytest.approx(sum(rest.ds))
    assert abs(rest.positions[-1, 1] - rest.positions[0, 1]) < 1e-6  # balanced: L5 below T1
    # the stretch stiffness is the mechanical Y·A; bending, twist and shear come from the population prior
    literature_sections = rest_model(dataclasses.replace(default, population_prior=None), length_scale=1.1)
    np.testing.assert_allclose(rest.beta[:, 2], literature_sections.beta[:, 2])
    prior = population_prior(default)
    assert prior is not None
    expected = 2 * prior.temperature_nmm * rest.ds / np.radians(prior.sagittal_sd_deg) ** 2
    np.testing.assert_allclose(rest.alpha[:, 0], expected)


def test_with_a_population_prior_only_the_stretch_stiffness_reads_y_and_g_none() -> None:
    """With a population prior the rod's stiffnesses are the prior's but the stretch's,
    stretch_factor·Y·A: G changes nothing, and Y and the stretch factor act only as their product
    (so ``spine bench calibrate`` draws only the stretch factor from such a profile)."""
    default = load_profile("default")
    rest = rest_model(default)
    softer_shear = rest_model(dataclasses.replace(default, shear_modulus_mpa=default.shear_modulus_mpa * 10))
    traded = rest_model(dataclasses.replace(default, youngs_modulus_mpa=default.youngs_modulus_mpa * 4,
                                            stretch_factor=default.stretch_factor / 4))  # fmt: skip
    for other in (softer_shear, traded):
        np.testing.assert_allclose(other.alpha, rest.alpha, rtol=1e-12)
        np.testing.assert_allclose(other.beta, rest.beta, rtol=1e-12)


def test_profile_rest_shape_is_checked() -> None:
    base = load_profile("literature")
    with pytest.raises(ValueError, match="rest_shape"):
        dataclasses.replace(base, rest_shape={"sagittal_inclination_deg": [0.0] * 3, "length_fractions": [1.0]})
    with pytest.raises(ValueError, match="stretch_factor"):
        dataclasses.replace(base, stretch_factor=0.0)


@pytest.mark.parametrize("name", ["nope", "../default", "", ".hidden", "default.json"])
def test_unknown_profile_raises(name: str) -> None:
    with pytest.raises(UnknownProfile) as info:
        load_profile(name)
    assert isinstance(info.value, InvalidInput)
    assert info.value.errors[0].loc == ("options", "profile")


def test_save_and_read_back(profile: Profile, tmp_path: Path) -> None:
    path = tmp_path / "calibrated.json"
    changed = Profile(**{**profile.__dict__, "name": "calibrated", "youngs_modulus_mpa": 12.5})
    save_profile(changed, path)
    data = json.loads(path.read_text())
    assert list(data) == list(Profile.__dataclass_fields__)
    assert profile_from_dict(data) == changed
    with pytest.raises(ValueError):
        profile_from_dict({**data, "extra": 1})
    with pytest.raises(ValueError):
        Profile(**{**profile.__dict__, "shear_modulus_mpa": -1.0})
