"""``spine bench clinic-bound``: the oracle's rotation covariance against a hand-derived case,
its Monte Carlo error against the exact formula, and the command on two spines."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from benches import clinic, clinic_bound, clinic_films
from benches.truth import read_verse
from spine_engine.anatomy import load_profile, population_prior
from spine_engine.clinical import PA_MAGNIFICATION_PRIOR
from spine_engine.projection import image_axes

DATA = Path(__file__).resolve().parents[1] / "data" / "verse_dev.csv"


def _sagittal_only_truth() -> clinic_films.Truth:
    """17 vertebrae straight in the frontal plane (x = 40 mm for all), a kyphosis-lordosis curve
    in depth and 25 mm apart in height."""
    k = np.arange(17, dtype=float)
    positions = np.stack([np.full(17, 40.0), 150.0 + 20.0 * np.sin(np.pi * k / 12.0), 600.0 - 25.0 * k], axis=1)
    return clinic_films.Truth("sagittal", positions, np.repeat(np.eye(3)[None], 17, axis=0))


def test_lean_variance_with_a_free_turn_is_the_pa_rows_regression() -> None:
    """With the lateral film's turn free (σ_ψ = 10⁶°) the lateral cannot tell a lean δ (rotation
    about x) from its own turn, and a spine with no frontal curve shows δ on the PA only in its
    rows: m·(z_i + δ·(y_i − ȳ)) + T, scaled by e^μ. So var(δ) is the (δ, δ) entry of the inverse of
    XᵀX/σ² + diag(0, 0, π_μ), X = [m(y − ȳ), m, m·e_r·(r − o)] the columns of δ, the row
    translation and μ, π_μ the PA magnification prior's precision: a 3-parameter regression derived
    by hand, against the oracle's 13-parameter Jacobian of both films by finite differences."""
    truth = _sagittal_only_truth()
    series = clinic_films.simulate_series(truth, noise_mm=1.0, seed=4)
    cov = clinic_bound.rotation_covariance(series, clinic_films.CASES["a"], clinic_bound.Priors(film_turn_sd_deg=1e6))
    film = series.pa
    m = film.magnification
    _, e_r = image_axes(film.orientation)
    y = truth.positions[:, 1]
    X = np.stack([m * (y - y.mean()), np.full(17, m), m * (truth.positions - film.principal_point) @ e_r], axis=1)
    prior_mu = (PA_MAGNIFICATION_PRIOR[0] / PA_MAGNIFICATION_PRIOR[1]) ** 2
    info = X.T @ X / series.noise_mm**2 + np.diag([0.0, 0.0, prior_mu])
    assert cov[0, 0] == pytest.approx(np.linalg.inv(info)[0, 0], rel=1e-6)


def test_a_tighter_turn_prior_never_loosens_the_rotation() -> None:
    """Σ_ω(σ_ψ = 2°) − Σ_ω(σ_ψ = 1.32°) and Σ_ω(no orientation prior) − Σ_ω(with one) are positive
    semi-definite (adding prior precision lowers a Gaussian posterior's covariance in Loewner order);
    eigenvalues ≥ −10⁻¹², the roundoff of entries of order 10⁻⁴ rad²."""
    series = clinic_films.simulate_series(clinic_films.Truth("dev0", *_first_dev_spine()), noise_mm=1.0, seed=0)
    case = clinic_films.CASES["a"]
    wide = clinic_bound.rotation_covariance(series, case, clinic_bound.Priors(film_turn_sd_deg=2.0))
    tight = clinic_bound.rotation_covariance(series, case, clinic_bound.Priors(film_turn_sd_deg=1.32))
    oriented = clinic_bound.rotation_covariance(series, case, clinic_bound.Priors(1.32, (3.0, 2.0, 9.0)))
    assert np.linalg.eigvalsh(wide - tight).min() > -1e-12
    assert np.linalg.eigvalsh(tight - oriented).min() > -1e-12
    assert wide[0, 0] > tight[0, 0]  # the lean is what the turn's prior decides


def _first_dev_spine() -> tuple[np.ndarray, np.ndarray]:
    positions = read_verse(DATA)[0][1]
    return positions, np.repeat(np.eye(3)[None], 17, axis=0)


def test_expected_error_of_a_lean_is_the_chord_formula() -> None:
    """A rotation δ about x moves a point at distance ρ_i from the axis by the chord 2ρ_i|sin(δ/2)|,
    so with δ ~ N(0, s²) the expected mean error is E[2|sin(δ/2)|]·mean ρ_i, E computed by
    quadrature. 20,000 draws: the relative SD of a mean of |N| is √(π/2 − 1)/√20000 = 0.53 %;
    the tolerance is 4 SD (2.2 %)."""
    positions, _ = _first_dev_spine()
    centred = positions - positions.mean(axis=0)
    s = np.radians(1.0)
    cov = np.diag([s**2, 0.0, 0.0])
    rho = np.hypot(centred[:, 1], centred[:, 2])
    grid = np.linspace(-8 * s, 8 * s, 20001)
    density = np.exp(-0.5 * (grid / s) ** 2) / (s * np.sqrt(2 * np.pi))
    chord = float(np.sum(2 * np.abs(np.sin(grid / 2)) * density) * (grid[1] - grid[0]))
    got = clinic_bound.expected_error(cov, centred, draws=20000, seed=3)
    assert got == pytest.approx(chord * rho.mean(), rel=0.022)


def test_bench_turn_rms() -> None:
    """|ψ| uniform on [0.5°, 2°]: E ψ² = (2³ − 0.5³)/(3·1.5) = 1.75, RMS 1.3229°."""
    assert clinic_bound.bench_turn_rms_deg() == pytest.approx(np.sqrt(1.75), rel=1e-12)


def test_command_on_two_spines(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Two dev spines as the split, (a) and (c), 500 draws: exit 0, a row per case with the three
    bounds, the engine's figures and the issue's target; an unknown case exits 2."""
    shutil.copy(DATA, tmp_path / "dev.csv")
    (tmp_path / "test.csv").write_text("\n".join(DATA.read_text().splitlines()[:3]) + "\n")
    args = ["--data", str(tmp_path), "--cases", "ac", "--draws", "500", "--json", "--out", str(tmp_path)]
    code = clinic_bound.main(args)
    assert code == 0
    report = json.loads(capsys.readouterr().out)
    assert [r["case"] for r in report["rows"]] == ["a", "c"]
    a = report["rows"][0]
    assert a["target_mm"] == 1.2 and a["spines"] == 2
    assert set(a["bound_mm"]) == {"engine_priors", "bench_turn", "bench_turn_and_orientation"}
    assert all(0.0 < v < 10.0 for v in a["bound_mm"].values())
    assert np.isfinite(a["engine_mean_3d_error_mm"]) and np.isfinite(a["floor_estimate_mm"])
    assert (tmp_path / "clinic-bound-test.json").is_file()
    chords = report["rows"][1]["chord_lengths_unknown"]  # case (c)
    assert len(chords["prior_sd_pct"]) == 15
    assert chords["to_oracle_xyz"][0] >= 1.0 and chords["best_priors_to_oracle_xyz"][0] > 0.0
    assert clinic_bound.main(["--data", str(tmp_path), "--cases", "f"]) == 2


def test_the_engine_setting_holds_the_rigid_turn_with_t1s_and_l5s_orientation_priors() -> None:
    """A rigid turn moves T1's and L5's directors alike, so the engine's two orientation priors add
    their precisions about each axis: σ = (σ_T1⁻² + σ_L5⁻²)^(−1/2), from the shipped profile."""
    prior = population_prior(load_profile())
    assert prior is not None
    top, bottom = np.asarray(prior.orientation_sd_deg["T1"]), np.asarray(prior.orientation_sd_deg["L5"])
    expected = 1.0 / np.sqrt(1.0 / top**2 + 1.0 / bottom**2)
    assert clinic_bound.engine_orientation_sd_deg() == pytest.approx(tuple(expected), rel=1e-12)
    settings = clinic_bound.prior_settings((3.0, 2.0, 9.0))
    assert settings["engine_priors"].orientation_sd_deg == pytest.approx(tuple(expected))
    assert settings["engine_priors"].film_turn_sd_deg == clinic_bound.FILM_TURN_PRIOR_SD_DEG


def test_a_bend_or_a_stretch_at_a_joint_moves_only_what_is_above_it() -> None:
    """``bent`` turns the vertebrae above joint J rigidly (their distances kept, the rest fixed) and
    ``top_parameters`` reads the truth's bends plus β at J alone (a chord above J and the one below
    meet at J; chords both above or both below turn together); ``stretched`` lengthens the chord
    from J up by its fraction, every other chord and every bend kept."""
    positions = _first_dev_spine()[0]
    rest_ds = np.ones(16)  # the bends do not depend on the rest lengths
    joints = clinic_bound.UNSEEN_TOP_JOINTS
    chords = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    for k, j in enumerate(joints):
        beta = np.zeros(3)
        beta[k] = 0.1
        moved = clinic_bound.bent(positions, beta, joints)
        np.testing.assert_array_equal(moved[j:], positions[j:])
        above = positions[: j + 1]
        np.testing.assert_allclose(np.linalg.norm(moved[: j + 1, None] - moved[None, : j + 1], axis=2),
                                   np.linalg.norm(above[:, None] - above[None], axis=2), atol=1e-9)
        delta = clinic_bound.top_parameters(moved, rest_ds) - clinic_bound.top_parameters(positions, rest_ds)
        np.testing.assert_allclose(delta[:3], beta, atol=1e-12)
        longer = clinic_bound.stretched(positions, 0.5 * beta, joints)
        ratio = np.linalg.norm(np.diff(longer, axis=0), axis=1) / chords
        expected = np.ones(16)
        expected[j - 1] = 1.05
        np.testing.assert_allclose(ratio, expected, rtol=1e-12)
        np.testing.assert_allclose(clinic_bound.top_parameters(longer, rest_ds)[:3],
                                   clinic_bound.top_parameters(positions, rest_ds)[:3], atol=1e-12)


def test_shape_errors_remove_the_best_rigid_motion() -> None:
    """A rigidly moved spine has no shape error; a deformed one has Kabsch's (scipy's align_vectors)."""
    truth = _first_dev_spine()[0]
    rng = np.random.default_rng(3)
    turn = Rotation.from_rotvec([0.2, -0.1, 0.3])
    rigid = turn.apply(truth) + np.array([5.0, -3.0, 8.0])
    deformed = truth + rng.normal(scale=2.0, size=truth.shape)
    errors = clinic_bound.shape_errors(np.stack([rigid, deformed]), truth)
    assert errors[0] == pytest.approx(0.0, abs=1e-9)
    centred = deformed - deformed.mean(axis=0)
    best, _ = Rotation.align_vectors(truth - truth.mean(axis=0), centred)
    expected = np.linalg.norm(best.apply(centred) - (truth - truth.mean(axis=0)), axis=1).mean()
    assert errors[1] == pytest.approx(expected, rel=1e-9)


def test_best_rotations_are_the_engine_metrics() -> None:
    """``best_rotations`` gives the rotation ``clinic.rigid_difference`` reports (scipy's align_vectors)."""
    truth = _first_dev_spine()[0]
    deformed = Rotation.from_rotvec([0.05, 0.2, -0.1]).apply(truth) + np.random.default_rng(4).normal(size=truth.shape)
    q, _, _ = clinic_bound.best_rotations(deformed[None], truth)
    _, rotvec = clinic.rigid_difference(deformed, truth)
    np.testing.assert_allclose(Rotation.from_matrix(q[0]).as_rotvec(degrees=True), rotvec, atol=1e-9)


def test_the_unseen_tops_aligned_rotation_is_its_sd_without_top_uncertainty_and_more_with_it() -> None:
    """With the top's bends and stretches known (their variance 10⁻¹⁶) the aligned rotation's RMS is
    the rotation's SD (Monte Carlo, 20,000 draws: within 2 %); with T2–T4's bends uncertain (SD 0.1
    rad) the alignment turns about x more, since the bends move T1–T3 in depth (by about 17 % here;
    > 10 % is far outside the 20,000 draws' Monte Carlo error of about 0.5 %)."""
    truth = _first_dev_spine()[0]
    sd = np.radians([0.8, 0.1, 0.9])
    known = np.diag(np.concatenate([sd**2, np.full(6, 1e-16)]))
    rms = clinic_bound.unseen_top_rotation(truth, known, 20_000, 0)
    assert rms == pytest.approx(np.degrees(sd), rel=0.02)
    bent = known.copy()
    bent[3:6, 3:6] = np.eye(3) * 0.1**2
    assert clinic_bound.unseen_top_rotation(truth, bent, 20_000, 0)[0] > 1.1 * rms[0]


def test_the_unseen_tops_bound_grows_with_its_prior_and_the_films_narrow_it() -> None:
    """The bends' and chord lengths' posterior SDs are below their prior's (the PA film's
    foreshortening tells some of T1–T3's depth), and a wider prior leaves a larger shape bound."""
    series = clinic_films.simulate_series(clinic_films.Truth("dev0", *_first_dev_spine()), noise_mm=1.0, seed=0)
    case = clinic_films.CASES["b"]
    priors = clinic_bound.Priors(orientation_sd_deg=clinic_bound.engine_orientation_sd_deg())
    sd = np.concatenate([np.radians([3.0, 3.0, 3.0]), [0.02, 0.02, 0.02]])
    narrow, wide = np.diag(sd**2), np.diag((3.0 * sd) ** 2)
    joints = clinic_bound.UNSEEN_TOP_JOINTS
    post_narrow, post_wide = (clinic_bound.posterior_covariance(series, case, priors, joints, c)[-6:, -6:]
                              for c in (narrow, wide))
    assert np.all(np.sqrt(np.diag(post_wide)) < 3.0 * sd)
    small = clinic_bound.unseen_top_shape(series.truth.positions, post_narrow, None, 2000, 0)
    large = clinic_bound.unseen_top_shape(series.truth.positions, post_wide, None, 2000, 0)
    assert 0.0 < small[0] < large[0]
    assert np.isnan(small[1])


def test_an_oracle_that_does_not_know_the_top_places_the_spine_less_well() -> None:
    """More unknowns, the same data: the rotation block of the posterior with T1–T3's bends and chord
    lengths unknown exceeds the one with them known (Loewner order, eigenvalues ≥ −10⁻¹²), and the
    lean (about x) grows most: the PA film's rows see the lean through the depths of the sagittal
    curve, T1–T3's among them (docs/engine.md)."""
    series = clinic_films.simulate_series(clinic_films.Truth("dev0", *_first_dev_spine()), noise_mm=1.0, seed=0)
    case = clinic_films.CASES["b"]
    priors = clinic_bound.Priors(orientation_sd_deg=clinic_bound.engine_orientation_sd_deg())
    sd = np.concatenate([np.radians([7.0, 8.0, 6.5]), [0.06, 0.05, 0.07]])
    known = clinic_bound.rotation_covariance(series, case, priors)
    unknown = clinic_bound.posterior_covariance(series, case, priors, clinic_bound.UNSEEN_TOP_JOINTS,
                                                np.diag(sd**2))[:3, :3]
    assert np.linalg.eigvalsh(unknown - known).min() > -1e-12
    growth = np.diag(unknown - known)
    assert growth[0] > 0.0 and growth[0] == growth.max()


def test_seeds_are_pooled_as_means_and_root_mean_squares() -> None:
    """``pooled``: millimetres averaged, angle vectors (RMS over the same spines) pooled as the √ of
    the mean of their squares, names kept, nested rows field by field, and each seed's engine
    rotation RMS beside the pooled one."""
    def row(mm: float, rms: list[float]) -> dict:
        return {"case": "b", "spines": 17, "bound_mm": {"engine_priors": mm}, "engine_shape_error_mm": mm,
                "engine_rotation_rms_deg_xyz": rms, "oracle_rotation_sd_deg_xyz": [2.0, 1.0, 1.0],
                "unseen_top_shape": {"joints": ["T4"], "bound_mm": mm}}

    rows = clinic_bound.pooled([[row(1.0, [3.0, 0.0, 1.0])], [row(2.0, [4.0, 0.0, 1.0])]])
    assert len(rows) == 1
    got = rows[0]
    assert got["case"] == "b" and got["spines"] == 17
    assert got["bound_mm"] == {"engine_priors": 1.5} and got["engine_shape_error_mm"] == 1.5
    assert got["engine_rotation_rms_deg_xyz"] == pytest.approx([np.sqrt(12.5), 0.0, 1.0], abs=1e-3)
    assert got["unseen_top_shape"] == {"joints": ["T4"], "bound_mm": 1.5}
    assert got["engine_rotation_rms_deg_xyz_by_seed"] == [[3.0, 0.0, 1.0], [4.0, 0.0, 1.0]]
    # ratio of the pooled values; SE from the seeds' ratios 1.5 and 2.0 about x: SD 0.354, / √2
    assert got["engine_to_oracle_xyz"] == pytest.approx([np.sqrt(12.5) / 2.0, 0.0, 1.0], abs=1e-3)
    assert got["engine_to_oracle_se_xyz"] == pytest.approx([0.25, 0.0, 0.0], abs=1e-3)


def test_one_seed_has_no_ratio_error() -> None:
    """With a single seed the ratio has no standard error (None), not a zero one."""
    row = {"engine_rotation_rms_deg_xyz": [1.0, 1.0, 1.0], "oracle_rotation_sd_deg_xyz": [1.0, 2.0, 4.0]}
    ratio, se = clinic_bound.rotation_ratio([row], row)
    assert ratio == [1.0, 0.5, 0.25] and se == [None, None, None]


def test_stretches_of_many_draws_are_each_draws_own() -> None:
    """``stretched`` with a leading axis of draws gives, draw by draw, what one draw alone gives."""
    positions = _first_dev_spine()[0]
    joints = clinic_bound.CHORD_JOINTS
    fractions = np.random.default_rng(5).normal(scale=0.06, size=(4, len(joints)))
    batch = clinic_bound.stretched(positions, fractions, joints)
    assert batch.shape == (4, 17, 3)
    for got, f in zip(batch, fractions, strict=True):
        np.testing.assert_allclose(got, clinic_bound.stretched(positions, f, joints), rtol=0, atol=1e-12)


def test_chords_alone_are_the_chords_with_their_bends_known() -> None:
    """``posterior_covariance`` with ``bends`` False leaves the bends' columns out, which is the
    posterior with them known: the same as with their prior variance 10⁻²⁰ rad² (the precision 10²⁰
    pins them; the rest agrees to 10⁻⁶ relative)."""
    series = clinic_films.simulate_series(clinic_films.Truth("dev0", *_first_dev_spine()), noise_mm=1.0, seed=0)
    case = clinic_films.CASES["c"]
    priors = clinic_bound.Priors(orientation_sd_deg=clinic_bound.engine_orientation_sd_deg())
    joints = clinic_bound.UNSEEN_TOP_JOINTS
    chords = np.diag([0.06, 0.05, 0.07]) ** 2
    alone = clinic_bound.posterior_covariance(series, case, priors, joints, chords, bends=False)
    pinned = clinic_bound.posterior_covariance(series, case, priors, joints, np.block(
        [[np.eye(3) * 1e-20, np.zeros((3, 3))], [np.zeros((3, 3)), chords]]))  # fmt: skip
    keep = np.r_[0 : len(alone) - 3, len(pinned) - 3 : len(pinned)]
    np.testing.assert_allclose(alone, pinned[np.ix_(keep, keep)], rtol=1e-6, atol=1e-14)


def test_an_oracle_that_does_not_know_the_chords_leans_less_surely_on_perspective_films() -> None:
    """Perspective films with their geometry (case (c)) show a lean on the PA film's rows through the
    sagittal curve's depths, read against the chords' lengths: with the fifteen chords' lengths
    unknown (VerSe dev's spread, ``chord_prior_covariance``) the rotation block exceeds the one with
    them known (Loewner order, eigenvalues ≥ −10⁻¹²), and most about x."""
    dev = [clinic_films.Truth(sid, p, np.repeat(np.eye(3)[None], 17, axis=0)) for sid, p in read_verse(DATA)]
    chords = clinic_bound.chord_prior_covariance(dev)
    assert chords.shape == (15, 15) and np.linalg.eigvalsh(chords).min() > 0.0
    series = clinic_films.simulate_series(dev[0], noise_mm=1.0, seed=0)
    case = clinic_films.CASES["c"]
    priors = clinic_bound.Priors(orientation_sd_deg=clinic_bound.engine_orientation_sd_deg())
    known = clinic_bound.rotation_covariance(series, case, priors)
    unknown = clinic_bound.posterior_covariance(series, case, priors, clinic_bound.CHORD_JOINTS, chords,
                                                bends=False)[:3, :3]  # fmt: skip
    assert np.linalg.eigvalsh(unknown - known).min() > -1e-12
    growth = np.diag(unknown - known)
    assert growth[0] > 0.0 and growth[0] == growth.max()
