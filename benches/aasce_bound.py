"""``spine bench aasce-bound``: how much of the Cobb angle the superior endplate midpoints carry.

The midpoints fix where the vertebrae are, not how their endplates are tilted; the engine reads
the tilts with the tilt prior (``spine_engine.tilt_prior``), a per-level linear map of the nearby
chords' angles fitted on AASCE 2019 ``training``. This command asks whether a learner the engine
does not have reads the major Cobb angle from the same midpoints better, in k-fold
cross-validation on ``training`` (with ``--test`` it also reads the test split with the learners
trained on all of training: a report, from which nothing is chosen):

* **tilt prior**: the shipped procedure (``aasce.prior_major_angles``: ``fit_tilt_prior``'s
  coefficients, its blend toward the chord normal chosen inside the training folds); the angle is
  the largest difference of its predicted tilts, as in the prior's own cross-validation;
* **direct**: the major angle regressed, by least absolute deviations, on the tilt prior's angle
  (itself cross-validated inside the training folds, ``INNER_FOLDS``) and on the range of the chord
  angles smoothed over 1 to ``SMOOTHING_MAX`` chords (the Cobb angle of the midpoints' line at six
  scales). The features turn with the image and mirror with it, as the angle does.

The learners see the whole training split's population, more than a patient's fit can; what they
cannot read from the midpoints is beyond the engine too, so their figure is an estimate of what
the midpoints hold, not a proof. The JSON is ``aasce-bound.json``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import sys
from pathlib import Path
from typing import Any

import numpy as np

from benches.aasce import (
    default_data_dir,
    plausible,
    prior_major_angles,
    read_split,
    tilt_training_arrays,
    tunes_the_prior,
)
from benches.report import format_table, write_json

SMOOTHING_MAX = 6
"""The chord angles are smoothed by moving means of 1 to this many chords."""
INNER_FOLDS = 5
"""Folds of the tilt prior's cross-validation inside a training fold (the direct learner's input)."""
LAD_ITERATIONS = 50
LAD_FLOOR_DEG = 0.5
"""Iteratively reweighted least squares for least absolute deviations: weights 1/max(|r|, this)."""


def chord_ranges(chords: np.ndarray) -> np.ndarray:
    """(n, ``SMOOTHING_MAX``): max − min of the chord angles after a moving mean over w = 1, 2, …
    chords, degrees."""
    cumulative = np.concatenate([np.zeros((len(chords), 1)), np.cumsum(chords, axis=1)], axis=1)
    columns = []
    for w in range(1, SMOOTHING_MAX + 1):
        smoothed = (cumulative[:, w:] - cumulative[:, :-w]) / w
        columns.append(smoothed.max(axis=1) - smoothed.min(axis=1))
    return np.stack(columns, axis=1)


def lad_fit(features: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Coefficients (k + 1,), intercept last, minimising Σ |Xc + c₀ − y| (iteratively reweighted
    least squares, ``LAD_ITERATIONS`` rounds, weights 1/max(|r|, ``LAD_FLOOR_DEG``))."""
    design = np.column_stack([features, np.ones(len(features))])
    weights = np.ones(len(target))
    coefficients = np.zeros(design.shape[1])
    for _ in range(LAD_ITERATIONS):
        root = np.sqrt(weights)
        coefficients = np.linalg.lstsq(design * root[:, None], target * root, rcond=None)[0]
        weights = 1.0 / np.maximum(np.abs(design @ coefficients - target), LAD_FLOOR_DEG)
    return np.asarray(coefficients)


def lad_predict(coefficients: np.ndarray, features: np.ndarray) -> np.ndarray:
    return np.asarray(features @ coefficients[:-1] + coefficients[-1])


def trained_learners(
    tilts: np.ndarray, chords: np.ndarray, major: np.ndarray, seed: int, new_chords: np.ndarray
) -> dict[str, np.ndarray]:
    """Each learner (module docstring) trained on (tilts, chords, major) alone, its major angles (m,) of
    ``new_chords`` (m, 16), degrees; ``seed`` draws the inner folds of the direct learner's input."""
    inner = np.random.default_rng(seed).integers(0, INNER_FOLDS, len(major))
    inner_angles = np.empty(len(major))
    for g in range(INNER_FOLDS):
        held = inner == g
        inner_angles[held] = prior_major_angles(tilts[~held], chords[~held], major[~held], chords[held])
    coefficients = lad_fit(np.column_stack([inner_angles, chord_ranges(chords)]), major)
    angles = prior_major_angles(tilts, chords, major, new_chords)
    direct = lad_predict(coefficients, np.column_stack([angles, chord_ranges(new_chords)]))
    return {"tilt_prior": angles, "direct": direct}


def cross_validated_errors(
    tilts: np.ndarray, chords: np.ndarray, major: np.ndarray, seed: int, folds: int
) -> dict[str, np.ndarray]:
    """Signed errors (n,) of each learner (module docstring) on folds it did not see."""
    fold = np.random.default_rng(seed).integers(0, folds, len(major))
    errors = {"tilt_prior": np.empty(len(major)), "direct": np.empty(len(major))}
    for f in range(folds):
        train, test = fold != f, fold == f
        angles = trained_learners(tilts[train], chords[train], major[train], seed + 1, chords[test])
        for name, predicted in angles.items():
            errors[name][test] = predicted - major[test]
    return errors


def held_out_errors(data: Path, seeds: tuple[int, ...]) -> dict[str, Any]:
    """Report only: each learner trained on all of ``training``'s radiographs that tune the prior, its
    major-angle MAE (± its standard error) and bias on ``test``'s plausible radiographs (those whose
    midpoints go down the image in order, as ``spine bench aasce`` reads them), mean over ``seeds``.
    Nothing is chosen from it: it says whether the test split reads as the cross-validation does."""
    tilts, chords, major = tilt_training_arrays([r for r in read_split(data / "training") if tunes_the_prior(r)])
    held = [r for r in read_split(data / "test") if plausible(r)]
    _, test_chords, test_major = tilt_training_arrays(held)
    by_seed = [trained_learners(tilts, chords, major, seed + 1, test_chords) for seed in seeds]
    learners = {}
    for name in by_seed[0]:
        errors = np.mean([angles[name] for angles in by_seed], axis=0) - test_major
        learners[name] = {
            "major_mae_deg": float(np.mean(np.abs(errors))),
            "major_mae_se_deg": float(np.std(np.abs(errors)) / np.sqrt(len(errors))),
            "major_bias_deg": float(np.mean(errors)),
        }
    return {"radiographs": len(held), "learners": learners}


def run(data: Path, seeds: tuple[int, ...], folds: int) -> dict[str, Any]:
    """Every learner's cross-validated major-angle MAE and bias on ``training``'s plausible
    radiographs (major < 90°), per seed and averaged."""
    rads = [r for r in read_split(data / "training") if tunes_the_prior(r)]
    tilts, chords, major = tilt_training_arrays(rads)
    by_seed = [cross_validated_errors(tilts, chords, major, seed, folds) for seed in seeds]
    learners = {}
    for name in by_seed[0]:
        mae = [float(np.mean(np.abs(e[name]))) for e in by_seed]
        learners[name] = {
            "major_mae_deg": float(np.mean(mae)),
            "major_mae_deg_by_seed": [round(v, 3) for v in mae],
            "major_bias_deg": float(np.mean([np.mean(e[name]) for e in by_seed])),
        }
    return {"radiographs": len(rads), "seeds": list(seeds), "folds": folds, "learners": learners}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="spine bench aasce-bound", description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--data", type=Path, default=None, help="AASCE 2019 folder with training/")
    parser.add_argument("--seeds", default="1,2,3", help="fold draws, comma-separated (default 1,2,3)")
    parser.add_argument("--folds", type=int, default=5)
    parser.add_argument("--test", action="store_true", help=(
        "also read the test split with the learners trained on all of training (report only)"))
    parser.add_argument("--out", type=Path, default=Path("bench-out/aasce"), help="folder of the JSON")
    args = parser.parse_args(argv)
    data = args.data or default_data_dir()
    if not (data / "training" / "landmarks_px_from_mat.csv").is_file():
        print(f"error: AASCE 2019 training data not found at {data} (pass --data or set SPINE_SHARED_DATA)",
              file=sys.stderr)
        return 2
    if args.folds < 2:
        print("error: --folds must be at least 2", file=sys.stderr)
        return 2
    if args.test and not (data / "test" / "landmarks_px_from_mat.csv").is_file():
        print(f"error: AASCE 2019 test data not found at {data}", file=sys.stderr)
        return 2
    seeds = tuple(int(v) for v in args.seeds.split(","))
    report = run(data, seeds, args.folds)
    if args.test:
        report["test"] = held_out_errors(data, seeds)
    report = {
        "command": "spine bench aasce-bound " + " ".join(argv if argv is not None else sys.argv[1:]),
        "date": dt.date.today().isoformat(),
        "data": str(data / "training"),
        **report,
    }
    rows = [[name, v["major_mae_deg"], " ".join(f"{m:.3f}" for m in v["major_mae_deg_by_seed"]), v["major_bias_deg"]]
            for name, v in report["learners"].items()]  # fmt: skip
    print(f"AASCE 2019 training, {report['radiographs']} plausible radiographs, {args.folds}-fold CV, seeds "
          f"{report['seeds']}: the major angle read from the superior endplate midpoints")
    print(format_table(["learner", "major MAE (°)", "by seed", "bias (°)"], rows))
    if args.test:
        test = report["test"]
        print(f"AASCE 2019 test, {test['radiographs']} plausible radiographs, learners trained on all of training "
              "(report only)")
        print(format_table(["learner", "major MAE (°)", "SE (°)", "bias (°)"], [
            [name, v["major_mae_deg"], v["major_mae_se_deg"], v["major_bias_deg"]]
            for name, v in test["learners"].items()]))  # fmt: skip
    write_json(args.out / "aasce-bound.json", report)
    print(f"wrote {args.out}/aasce-bound.json")
    return 0
