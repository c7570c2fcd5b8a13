"""Elastic properties by Monte Carlo, as in Li et al. (2009): sample, score on a training set, keep the best.

Two steps, both on the training split (VerSe ``dev``) only — never on ``test``:
1. Rest shape: the mean sagittal shape of the training spines (the inclination of each
   vertebra's tangent relative to T1's, and each segment's share of the T1–L5 length) replaces
   the literature's normal profile as the rod's rest shape.
2. Monte Carlo: Young's modulus Y, shear modulus G (MPa) and the stretch factor are drawn
   log-uniformly around the starting profile; each draw reconstructs every training spine from
   17 PA landmarks and from 17 PA + 17 lateral landmarks and is scored by the sum of the two mean
   3D errors. The landmark weights stay fixed: only the ratio of stiffness to weight matters.
The best draw is written as a named profile with its provenance.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import time
from pathlib import Path
from typing import Any

import numpy as np

from benches.truth import read_verse
from benches.verse import default_data_dir, evaluate, mean_interior_error
from spine_engine.anatomy import PROFILES_DIR, Profile, load_profile, save_profile
from spine_engine.frames import frames_from_centreline


def score(spines: list[tuple[str, np.ndarray]], profile: Profile) -> tuple[float, float]:
    """Mean 3D error (mm, T2..L4) with PA-17 and with PA-17 + lateral-17."""
    return (
        mean_interior_error(evaluate(spines, "PA-17", profile)),
        mean_interior_error(evaluate(spines, "PA-17+L-17", profile)),
    )


def sample(base: Profile, rng: np.random.Generator, decades: float) -> Profile:
    """A profile with Y, G and the stretch factor drawn log-uniformly within ±``decades``."""
    factor_y, factor_g, factor_s = 10.0 ** rng.uniform(-decades, decades, size=3)
    return dataclasses.replace(
        base,
        youngs_modulus_mpa=float(base.youngs_modulus_mpa * factor_y),
        shear_modulus_mpa=float(base.shear_modulus_mpa * factor_g),
        stretch_factor=float(base.stretch_factor * factor_s),
    )


def mean_sagittal_shape(spines: list[tuple[str, np.ndarray]]) -> dict[str, Any]:
    """Mean rest shape of real spines: per-vertebra sagittal inclination relative to T1 (degrees,
    the tangent's angle toward +y going caudally, as ``measures.sagittal_inclination_deg``) and
    each segment's fraction of the summed segment lengths."""
    inclinations, fractions = [], []
    for _, positions in spines:
        tangent = frames_from_centreline(positions)[:, :, 2]
        beta = np.degrees(np.arctan2(tangent[:, 1], -tangent[:, 2]))
        inclinations.append(beta - beta[0])
        lengths = np.linalg.norm(np.diff(positions, axis=0), axis=1)
        fractions.append(lengths / lengths.sum())
    return {
        "sagittal_inclination_deg": np.round(np.mean(inclinations, axis=0), 4).tolist(),
        "length_fractions": np.round(np.mean(fractions, axis=0), 6).tolist(),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="spine bench calibrate", description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=None, help="VerSe folder (only dev.csv is read)")
    parser.add_argument("--samples", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--decades", type=float, default=1.5, help="half-width of the log10 sampling range")
    parser.add_argument("--start", default="literature", help="profile to start from")
    parser.add_argument("--write", default=None, help="write the best draw as this profile name")
    args = parser.parse_args(argv)
    path = (args.data or default_data_dir()) / "dev.csv"
    if not path.is_file():
        print(f"error: VerSe dev split not found at {path} (pass --data or set SPINE_SHARED_DATA)")
        return 2
    spines = read_verse(path)
    shape = mean_sagittal_shape(spines)
    shape["source"] = f"mean of the VerSe dev split ({len(spines)} spines from CT), {path.name}"
    base = dataclasses.replace(load_profile(args.start), rest_shape=shape)
    rng = np.random.default_rng(args.seed)
    start = time.perf_counter()
    best, best_scores = base, score(spines, base)
    print(f"start  Y={base.youngs_modulus_mpa:10.4g} G={base.shear_modulus_mpa:10.4g} "
          f"stretch={base.stretch_factor:8.3g}  "
          f"PA {best_scores[0]:.3f} mm  PA+L {best_scores[1]:.3f} mm")
    for i in range(args.samples):
        candidate = sample(base, rng, args.decades)
        scores = score(spines, candidate)
        if sum(scores) < sum(best_scores):
            best, best_scores = candidate, scores
            print(f"#{i:<5} Y={best.youngs_modulus_mpa:10.4g} G={best.shear_modulus_mpa:10.4g} "
                  f"stretch={best.stretch_factor:8.3g}  "
                  f"PA {scores[0]:.3f} mm  PA+L {scores[1]:.3f} mm  (best so far)")
    elapsed = time.perf_counter() - start
    print(f"best   Y={best.youngs_modulus_mpa:.4g} MPa G={best.shear_modulus_mpa:.4g} MPa "
          f"stretch factor {best.stretch_factor:.4g}: "
          f"PA {best_scores[0]:.3f} mm, PA+L {best_scores[1]:.3f} mm on {len(spines)} dev spines ({elapsed:.0f} s)")
    if args.write:
        provenance = {
            "method": "rest shape = mean sagittal shape of the training spines; then Monte Carlo over Y, G "
                      "and the stretch factor (log-uniform), benches.calibrate",
            "command": f"spine bench calibrate --samples {args.samples} --seed {args.seed} "
                       f"--decades {args.decades} --start {args.start} --write {args.write}",
            "training_set": f"VerSe dev split ({len(spines)} spines), {path.name}",
            "started_from": {"profile": args.start, "youngs_modulus_mpa": base.youngs_modulus_mpa,
                             "shear_modulus_mpa": base.shear_modulus_mpa, "stretch_factor": base.stretch_factor,
                             "provenance": base.provenance},
            "score_dev_mean_3d_error_mm": {"PA-17": round(best_scores[0], 4), "PA-17+L-17": round(best_scores[1], 4)},
            "date": dt.date.today().isoformat(),
        }
        chosen = dataclasses.replace(best, name=args.write, provenance=provenance)
        save_profile(chosen, PROFILES_DIR / f"{args.write}.json")
        print(f"wrote profile {args.write!r} to {PROFILES_DIR / (args.write + '.json')}")
    return 0
