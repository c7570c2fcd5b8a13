"""``spine bench pa-bound``: the PA features ignore what the film does not fix, the ridge recovers a
linear law, foreshortening is what the features see, and the command on a few spines."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from benches import pa_bound

DATA = Path(__file__).resolve().parents[1] / "data" / "verse_dev.csv"


def test_features_ignore_the_films_offset_turn_and_magnification() -> None:
    rng = np.random.default_rng(3)
    points = np.cumsum(rng.normal([0.0, 25.0], [3.0, 2.0], size=(17, 2)), axis=0)
    c, s = np.cos(0.3), np.sin(0.3)
    moved = 1.2 * points @ np.array([[c, -s], [s, c]]).T + np.array([40.0, -7.0])
    np.testing.assert_allclose(pa_bound.pa_features(moved), pa_bound.pa_features(points), atol=1e-12)
    assert pa_bound.pa_features(points).sum() == pytest.approx(1.0)


def test_a_segment_inclined_out_of_the_film_images_shorter_by_its_cosine() -> None:
    """Straight vertebrae 25 mm apart; inclining segment 5 by β out of the frontal plane shortens its
    image to 25 cos β, against the other 15 segments."""
    positions = np.zeros((17, 3))
    positions[:, 2] = -25.0 * np.arange(17)
    beta = np.radians(30.0)
    positions[6:, 1] += 25.0 * np.sin(beta)
    positions[6:, 2] += 25.0 * (1.0 - np.cos(beta))
    f = pa_bound.pa_features(positions[:, [0, 2]])
    assert f[5] / f[4] == pytest.approx(np.cos(beta))


def test_ridge_recovers_a_linear_law() -> None:
    """Noise-free targets: CV picks the smallest penalty λ, which shrinks the weights by about
    1/(1 + λ) = 1 % on standardised features, so predictions are within 2 % of the targets' spread."""
    rng = np.random.default_rng(0)
    X = rng.normal(size=(200, 5))
    Y = np.stack([1.0 + X @ [2.0, 0.0, -1.0, 0.5, 0.0], 3.0 - X[:, 1]], axis=1)
    model = pa_bound.cross_validated_ridge(X, Y)
    assert model.penalty == min(pa_bound.RIDGE_GRID)
    spread = np.abs(Y - Y.mean(axis=0)).max()
    assert np.abs(model.predict(X) - Y).max() <= 0.02 * spread


def test_the_truths_own_depth_reads_no_turn_and_a_flat_one_reads_its_curves_as_one() -> None:
    """The depth answer of ``Films.rotation_rms_deg`` is the truth itself for the truth's depth (no
    rotation); answering no depth at all (a flat spine) turns the alignment, mostly about x and z."""
    truths = pa_bound.generated_truths(3, 5)
    films = pa_bound.film(truths, 1.0, [0, 1, 2])
    np.testing.assert_allclose(films.rotation_rms_deg(films.depth), 0.0, atol=1e-9)
    flat = films.rotation_rms_deg(np.zeros_like(films.depth))
    assert flat.max() > 1.0 and flat[1] < max(flat[0], flat[2])


def test_command_on_a_few_spines(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    shutil.copy(DATA, tmp_path / "dev.csv")
    (tmp_path / "test.csv").write_text("\n".join(DATA.read_text().splitlines()[:4]) + "\n")
    code = pa_bound.main(["--train", "30", "--held-out", "0", "--data", str(tmp_path), "--out", str(tmp_path)])
    assert code == 0
    report = json.loads((tmp_path / "pa-bound.json").read_text())
    tests = {(r["population"], r["test"]) for r in report["rows"]}
    assert tests == {("synthetic", "clinic bench's synthetic test"), ("VerSe", "VerSe test"),
                     ("VerSe", "clinic bench's synthetic test")}
    floor = [r for r in report["rows"] if r["estimator"].startswith("floor")]
    assert all(r["kyphosis_t4_t12_mae_deg"] > 0.0 for r in floor)
    assert all(len(r["rotation_rms_deg_xyz"]) == 3 for r in report["rows"])
    assert "ridge on the PA segment lengths" in capsys.readouterr().out
    interval = report["lordosis_interval"]
    assert set(interval["half_width_90_deg"]) == {"VerSe test", "clinic bench's synthetic test"}
    assert interval["verse_dev_half_width_98_deg"] > 0.0


def test_half_width_is_the_quantile_of_the_distance_to_the_centre() -> None:
    """Values 1..10 about 0: 90 % of them lie within 9.1 (between the 9th and 10th, interpolated); about
    5.5 the distances are 0.5..4.5 twice, so 90 % lie within 4.5."""
    values = np.arange(1.0, 11.0)
    assert pa_bound.half_width_deg(values, 0.0, 0.9) == pytest.approx(9.1)
    assert pa_bound.half_width_deg(values, 5.5, 0.9) == pytest.approx(4.5)
    inside = np.abs(values - 5.5) <= pa_bound.half_width_deg(values, 5.5, 0.9)
    assert inside.mean() >= 0.9
