"""``spine bench pa-bound``: how much of the sagittal profile one PA film carries, for a learner.

With one PA film (case (e) of ``spine bench clinic``) the depth of the spine is not seen, but a
segment inclined by β out of the frontal plane images ds·cos β long: the film's foreshortening
carries some of the kyphosis and lordosis, against the spread of the vertebrae's own heights. This
command measures how much, with an estimator the engine does not have: ridge regression
trained on spines of the population it is then tested on.

* features: the PA film's 16 projected segment lengths over their sum (the film's landmarks as the
  clinic sends them, ``clinic_films.build_payload`` of case (e): invariant to the film's offset,
  turn and magnification), standardised;
* targets: the truth's kyphosis T4–T12 and lordosis L1–L5, measured as ``spine bench clinic``
  measures a truth (``measures.compute_measures`` on the centreline frames); and, by a second
  ridge, its depth profile (y_i − y_T1 over the T1–L5 height, 17 values), from which the answer
  is the truth's frontal curve (x, z) with that depth: its best rotation onto the truth
  (``clinic.rigid_difference``) is read as the clinic bench reads the engine's spin about the
  vertical (z) and lean (x);
* ridge, its penalty chosen by 5-fold cross-validation on the training spines (``RIDGE_GRID``);
* populations: synthetic spines (``spine_engine.synthetic``), trained on ``--train`` spines drawn
  apart from the benches' (``TRAIN_SEED``) and tested on the clinic bench's synthetic test spines
  (the same films: noise seed ``--seed``) and on ``--held-out`` more (``HELD_OUT_SEED``); VerSe,
  trained on ``dev`` (its 24 spines) and tested on ``test`` and on the clinic bench's synthetic
  test spines: the learner trained on what the engine may be tuned on, read on a population unlike
  it, as the engine's case (e) is.

Beside it, the clinic bench's floor (VerSe dev's means, ``clinic.population_means``; for the
rotation, ``clinic.population_sagittal_answer``, VerSe dev's mean sagittal shape as depth) and the
training spines' own mean. The learner knows the population it is tested on, which a patient's
answer cannot; its figure says what the films allow in that population, not what an engine
calibrated on VerSe dev can reach there. With VerSe, ``lordosis_interval`` says how wide an interval
about the PA-only lordosis (VerSe dev's mean, as the engine reports it) must be to cover 90 % of each
test set, and how wide it may be to cover at most 98 % of dev (``lordosis_interval``). The JSON is
``pa-bound.json``.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benches.clinic import (
    generated_truths,
    population_means,
    population_sagittal_answer,
    rigid_difference,
    synthetic_truths,
    verse_truths,
)
from benches.clinic_films import CASES, FloatArray, Truth, build_payload, centreline_measures, simulate_series
from benches.report import format_table, shared_data_dir, write_json

TRAIN_SEED = 20_000
"""``generate_spines`` seed of the synthetic training spines: apart from the clinic bench's test (0)
and dev (10 000) spines."""
HELD_OUT_SEED = 30_000
"""``generate_spines`` seed of the extra held-out synthetic spines."""
RIDGE_GRID = (0.01, 0.1, 1.0, 10.0, 100.0, 1000.0)
"""Ridge penalties tried (on standardised features; n·λ added to XᵀX)."""
MEASURES = ("kyphosis_t4_t12", "lordosis_l1_l5")


@dataclass(frozen=True)
class Films:
    """Features (n, 16) of the PA films, the truths' measures (n, 2), degrees, and positions (n, 17, 3), mm."""

    features: FloatArray
    truth: FloatArray
    positions: FloatArray

    @staticmethod
    def depth_of(positions: FloatArray) -> FloatArray:
        """(..., 17) depth y_i − y_T1 over the T1–L5 height z_T1 − z_L5 of spines (..., 17, 3)."""
        p = np.asarray(positions)
        return np.asarray((p[..., 1] - p[..., :1, 1]) / (p[..., 0, 2] - p[..., -1, 2])[..., None])

    @property
    def depth(self) -> FloatArray:
        """(n, 17) each truth's ``depth_of``."""
        return self.depth_of(self.positions)

    def rotation_rms_deg(self, depth: FloatArray) -> FloatArray:
        """(3,) RMS over the spines of the rotation vector (degrees, about x, y, z) that best aligns
        each answer, the truth's (x, z) with ``depth`` (n, 17, over the height) as y, on the truth."""
        turns = []
        for p, d in zip(self.positions, depth, strict=True):
            answer = p.copy()
            answer[:, 1] = p[0, 1] + d * (p[0, 2] - p[-1, 2])
            turns.append(rigid_difference(answer, p)[1])
        return np.sqrt(np.mean(np.square(turns), axis=0))


def pa_features(points: FloatArray) -> FloatArray:
    """(16,) projected segment lengths over their sum of 17 PA landmarks (17, 2), any unit."""
    lengths = np.linalg.norm(np.diff(points, axis=0), axis=1)
    return np.asarray(lengths / lengths.sum())


def film(truths: Sequence[Truth], noise_mm: float, seeds: Sequence[int]) -> Films:
    """The PA film of case (e) of each truth (``simulate_series`` with its noise seed) as the clinic
    sends it, and the truth's measures."""
    features, truth = [], []
    for t, seed in zip(truths, seeds, strict=True):
        payload = build_payload(simulate_series(t, noise_mm, seed), CASES["e"])
        assert payload.pa is not None
        points = np.array([lm.point for lm in payload.pa.landmarks], dtype=float)
        features.append(pa_features(points))
        m = centreline_measures(t.positions)
        truth.append((m.thoracic_kyphosis_t4_t12_deg, m.lumbar_lordosis_l1_l5_deg))
    return Films(np.array(features), np.array(truth, dtype=float), np.array([t.positions for t in truths]))


@dataclass(frozen=True)
class Ridge:
    """y ≈ ȳ + ((x − x̄)/s_x) w, per target column."""

    x_mean: FloatArray
    x_sd: FloatArray
    y_mean: FloatArray
    weights: FloatArray
    penalty: float

    def predict(self, X: FloatArray) -> FloatArray:
        return np.asarray(self.y_mean + ((X - self.x_mean) / self.x_sd) @ self.weights)


def fit_ridge(X: FloatArray, Y: FloatArray, penalty: float) -> Ridge:
    """Ridge on standardised features: w = (ZᵀZ + nλI)⁻¹ Zᵀ(Y − Ȳ), Z = (X − X̄)/s_X."""
    mean, sd = X.mean(axis=0), X.std(axis=0) + 1e-12
    Z = (X - mean) / sd
    y_mean = Y.mean(axis=0)
    w = np.linalg.solve(Z.T @ Z + len(X) * penalty * np.eye(X.shape[1]), Z.T @ (Y - y_mean))
    return Ridge(mean, sd, y_mean, w, penalty)


def cross_validated_ridge(X: FloatArray, Y: FloatArray, folds: int = 5, seed: int = 0) -> Ridge:
    """``fit_ridge`` on all of X with the penalty of ``RIDGE_GRID`` whose ``folds``-fold CV mean absolute
    error (summed over the targets) is lowest."""
    fold = np.random.default_rng(seed).permutation(len(X)) % folds

    def cv_error(penalty: float) -> float:
        err = 0.0
        for f in range(folds):
            model = fit_ridge(X[fold != f], Y[fold != f], penalty)
            err += float(np.abs(model.predict(X[fold == f]) - Y[fold == f]).sum())
        return err
    return fit_ridge(X, Y, min(RIDGE_GRID, key=cv_error))


def rows_of(population: str, train: Films, tests: dict[str, Films], floor: FloatArray) -> list[dict[str, Any]]:
    """MAE of the floor, of the training mean and of the ridge on each test set, and the rotation RMS
    of their depth answers."""
    model = cross_validated_ridge(train.features, train.truth)
    depth_model = cross_validated_ridge(train.features, train.depth)
    rows = []
    for name, test in tests.items():
        floor_depth = np.array([Films.depth_of(population_sagittal_answer(p)) for p in test.positions])
        floor_rotation = test.rotation_rms_deg(floor_depth)
        for estimator, answer, rotation in (
            ("floor (VerSe dev mean)", np.broadcast_to(floor, test.truth.shape), floor_rotation),
            ("training spines' mean", np.broadcast_to(train.truth.mean(axis=0), test.truth.shape),
             test.rotation_rms_deg(np.broadcast_to(train.depth.mean(axis=0), test.depth.shape))),
            (f"ridge on the PA segment lengths (λ {model.penalty:g}; depth λ {depth_model.penalty:g})",
             model.predict(test.features), test.rotation_rms_deg(depth_model.predict(test.features))),
        ):
            mae = np.abs(answer - test.truth).mean(axis=0)
            rows.append({"population": population, "train": len(train.truth), "test": name,
                         "spines": len(test.truth), "estimator": estimator,
                         **{f"{m}_mae_deg": float(v) for m, v in zip(MEASURES, mae, strict=True)},
                         "rotation_rms_deg_xyz": np.round(rotation, 3).tolist()})
    return rows


def half_width_deg(truth: FloatArray, centre: float, coverage: float) -> float:
    """Half-width h (degrees) of the narrowest interval [c − h, c + h] about ``centre`` that holds the
    fraction ``coverage`` of ``truth`` (n,): the ``coverage`` quantile of |truth − c| (linear
    interpolation between order statistics)."""
    return float(np.quantile(np.abs(np.asarray(truth) - centre), coverage))


def lordosis_interval(floor: float, dev: Films, tests: dict[str, Films]) -> dict[str, Any]:
    """One PA film's lordosis is reported as VerSe dev's mean (``floor``) with an interval about it, the
    film carrying nothing of it that dev shows (docs/accuracy.md). Its half-width h covers at most 98 % of
    dev's spines only while h ≤ dev's 98 % quantile of |L − floor| (and, for dev's Gaussian, 2.326 SD),
    and at least 90 % of a test set only while h ≥ that set's 90 % quantile: where the second exceeds the
    first, no interval about that value meets the 90–98 % band on both."""
    lordosis = dev.truth[:, MEASURES.index("lordosis_l1_l5")]
    return {
        "centre_deg": floor,
        "verse_dev_half_width_98_deg": half_width_deg(lordosis, floor, 0.98),
        "verse_dev_gaussian_half_width_98_deg": float(2.326 * lordosis.std(ddof=1)),
        "half_width_90_deg": {
            name: half_width_deg(t.truth[:, MEASURES.index("lordosis_l1_l5")], floor, 0.90)
            for name, t in tests.items()
        },
    }


def run(
    train_n: int, held_out: int, noise_mm: float, seed: int, verse: Path | None
) -> tuple[list[dict[str, Any]], dict[str, Any] | None]:
    """Every row of the command and, with VerSe, the lordosis interval's bounds (module docstring)."""
    means = population_means()
    floor = np.array([means[m] for m in MEASURES])
    train = film(generated_truths(train_n, TRAIN_SEED), noise_mm, range(train_n))
    bench_test = synthetic_truths(20, seed, "test")
    bench_films = film(bench_test, noise_mm, [seed] * len(bench_test))
    tests = {"clinic bench's synthetic test": bench_films}
    if held_out:
        extra = generated_truths(held_out, HELD_OUT_SEED)
        tests[f"{held_out} more synthetic"] = film(extra, noise_mm, [seed] * held_out)
    rows = rows_of("synthetic", train, tests, floor)
    if verse is None:
        return rows, None
    dev, test = verse_truths("dev", verse), verse_truths("test", verse)
    dev_films = film(dev, noise_mm, [seed] * len(dev))
    verse_tests = {"VerSe test": film(test, noise_mm, [seed] * len(test)), **tests}
    rows += rows_of("VerSe", dev_films, {k: verse_tests[k] for k in ("VerSe test", "clinic bench's synthetic test")},
                    floor)
    return rows, lordosis_interval(float(floor[MEASURES.index("lordosis_l1_l5")]), dev_films, verse_tests)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="spine bench pa-bound", description=__doc__.split("\n\n")[0])
    parser.add_argument("--train", type=int, default=1500, help="synthetic training spines (default 1500)")
    parser.add_argument("--held-out", type=int, default=500, help="extra held-out synthetic spines (0: none)")
    parser.add_argument("--noise-mm", type=float, default=1.0, help="landmark noise SD, detector mm (default 1)")
    parser.add_argument("--seed", type=int, default=0, help="noise seed of the test films (the clinic bench's)")
    parser.add_argument("--data", type=Path, default=None,
                        help="VerSe folder with dev.csv and test.csv (default: the shared data, if present)")
    parser.add_argument("--no-verse", action="store_true", help="synthetic spines only")
    parser.add_argument("--out", type=Path, default=Path("bench-out/pa-bound"), help="folder of the JSON")
    ns = parser.parse_args(argv)
    verse = None if ns.no_verse else (ns.data or shared_data_dir("verse"))
    rows, interval = run(ns.train, ns.held_out, ns.noise_mm, ns.seed, verse)
    print(format_table(
        ["population", "test", "spines", "estimator", "kyphosis MAE", "lordosis MAE", "rotation RMS x/y/z"],
        [[r["population"], r["test"], r["spines"], r["estimator"], r["kyphosis_t4_t12_mae_deg"],
          r["lordosis_l1_l5_mae_deg"], "/".join(f"{v:.2f}" for v in r["rotation_rms_deg_xyz"])] for r in rows],
    ))
    if interval is not None:
        print(f"lordosis L1–L5 reported as {interval['centre_deg']:.1f}°: an interval about it covers at most 98 % of "
              f"VerSe dev up to a half-width of {interval['verse_dev_half_width_98_deg']:.1f}° "
              f"({interval['verse_dev_gaussian_half_width_98_deg']:.1f}° for dev's Gaussian) and at least 90 % from "
              + ", ".join(f"{h:.1f}° ({name})" for name, h in interval["half_width_90_deg"].items()))
    write_json(ns.out / "pa-bound.json", {"command": "spine bench pa-bound " + " ".join(argv or sys.argv[2:]),
                                         "train": ns.train, "held_out": ns.held_out, "noise_mm": ns.noise_mm,
                                         "seed": ns.seed, "rows": rows, "lordosis_interval": interval})
    print(f"wrote {ns.out / 'pa-bound.json'}")
    return 0
