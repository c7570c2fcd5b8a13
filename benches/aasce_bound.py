"""``spine bench aasce-bound``: how much of the Cobb angle the superior endplate midpoints carry.

The midpoints fix where the vertebrae are, not how their endplates are tilted; the engine reads
the tilts with the tilt prior (``spine_engine.tilt_prior``), a per-level linear map of the nearby
chords' angles fitted on AASCE 2019 ``training``. This command asks whether a learner the engine
does not have reads the major Cobb angle from the same midpoints better, in k-fold
cross-validation on ``training`` only (the test split is never read):

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

from benches.aasce import default_data_dir, prior_major_angles, read_split, tilt_training_arrays, tunes_the_prior
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


def cross_validated_errors(
    tilts: np.ndarray, chords: np.ndarray, major: np.ndarray, seed: int, folds: int
) -> dict[str, np.ndarray]:
    """Signed errors (n,) of each learner (module docstring) on folds it did not see."""
    fold = np.random.default_rng(seed).integers(0, folds, len(major))
    errors = {"tilt_prior": np.empty(len(major)), "direct": np.empty(len(major))}
    for f in range(folds):
        train, test = fold != f, fold == f
        t, c, m = tilts[train], chords[train], major[train]
        inner = np.random.default_rng(seed + 1).integers(0, INNER_FOLDS, len(m))
        inner_angles = np.empty(len(m))
        for g in range(INNER_FOLDS):
            held = inner == g
            inner_angles[held] = prior_major_angles(t[~held], c[~held], m[~held], c[held])
        coefficients = lad_fit(np.column_stack([inner_angles, chord_ranges(c)]), m)
        angles = prior_major_angles(t, c, m, chords[test])
        errors["tilt_prior"][test] = angles - major[test]
        direct = lad_predict(coefficients, np.column_stack([angles, chord_ranges(chords[test])]))
        errors["direct"][test] = direct - major[test]
    return errors


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
    report = run(data, tuple(int(v) for v in args.seeds.split(",")), args.folds)
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
    write_json(args.out / "aasce-bound.json", report)
    print(f"wrote {args.out}/aasce-bound.json")
    return 0
